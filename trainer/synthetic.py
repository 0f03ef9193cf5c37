"""Synthetic recordings the nets also train on: the calibration's presses held at their peak
(:func:`synthetic_holds`), long rests inserted before them (:func:`synthetic_rests`) and
pressed harder (:func:`scaled_presses`); and the long rests (:func:`decision_rests`) and idle
pads (:func:`idle_rests`) the contact decision is set on; each recomputed through the model's
preprocessing as the runtime would run it."""
from __future__ import annotations

from dataclasses import replace
from typing import Iterator, Sequence

import numpy as np

from fbgforce.evaluation import metrics as fmetrics
from fbgforce.model import artifact, floatref
from fbgforce.recordings import tare as fbgtare
from fbgforce.trainer import preprocess as pp
from fbgforce.trainer.creep import Creep
from fbgforce.trainer.data import Prepared, Recording


#: The location net also trains on copies of the training presses scaled by a factor drawn
#: per press from [1, LOCATION_AUGMENT] (see :func:`scaled_presses`); 1 turns this off.
LOCATION_AUGMENT = 3.0


#: Synthetic holds (:func:`synthetic_holds`): the contact and force nets also train on this
#: share of the training presses with their peak stretched into a hold of a length drawn in
#: :data:`HOLD_AUGMENT_S` (seconds), of which one sample every :data:`HOLD_AUGMENT_STEP_S`
#: trains (consecutive held samples differ only by noise and the averages' slow decay); 0 turns
#: this off (docs/trainer.md, "Held grips").
HOLD_AUGMENT = 0.2
HOLD_AUGMENT_S = (1.5, 6.0)
HOLD_AUGMENT_STEP_S = 0.004
#: Holds on the release (``synthetic_holds(on_release=True)``) start where the load has fallen
#: to a share of its peak drawn here: well into the falling branch, short of the last
#: newtons where the contact ends. Not just past the peak: a hold there has the inputs of the
#: release's first milliseconds and another label, and on the family's pads the test presses'
#: force read up to a quarter worse with holds drawn up to the peak.
RELEASE_HOLD_AT = (0.4, 0.9)
#: Wandering holds (``synthetic_holds(wander=True)``): the load stands at the peak for a time
#: drawn in :data:`WANDER_LEAD_S`, then dips by a share of the peak drawn in
#: :data:`WANDER_DEPTH` and comes back, over a period drawn in :data:`WANDER_PERIOD_S`, as a
#: hand's grip wanders. The lead: a wander that turns at the peak sample has the inputs of the
#: release's first milliseconds and another label. One held sample every
#: :data:`WANDER_STEP_S` trains: at the flat holds' density they outnumbered the recorded
#: presses' samples, and the family's test presses read worse.
WANDER_LEAD_S = (0.3, 1.0)
WANDER_DEPTH = (0.1, 0.3)
WANDER_PERIOD_S = (2.0, 8.0)
WANDER_STEP_S = 0.016
#: Each branch of a press is a running mean over this many samples before a wander reads its
#: strain there: one sample's noise would otherwise run through a whole hold.
BRANCH_SMOOTH = 7


#: Synthetic long rests (:func:`synthetic_rests`): the contact and force nets also train on
#: rests of a length drawn in :data:`REST_AUGMENT_S` (seconds) inserted before this share of
#: the training presses, one sample every :data:`REST_AUGMENT_STEP_S` from
#: :data:`REST_AUGMENT_SETTLE_S` into the rest on; 0 turns this off (docs/trainer.md, "Long
#: rests"). Up to a minute: the play operators' states keep creeping with the noise's extremes
#: for minutes of rest; one sample in 50 ms trains as many samples per rest as one in 10 ms
#: over 12 s did.
REST_AUGMENT = 0.2
REST_AUGMENT_S = (3.0, 60.0)
REST_AUGMENT_STEP_S = 0.05
REST_AUGMENT_SETTLE_S = 0.5

#: Synthetic long rests the contact decision's threshold is read on (:func:`decision_rests`):
#: every sample of rests of a length drawn in :data:`DECISION_REST_S` inserted before this
#: share of the calibration's training and validation presses, drawn apart from those the
#: nets train on. A calibration's rests end within half a second of a release; in use the
#: margin's tail 1-20 s into a rest lies past theirs (on a 60-press calibration its 99.99 %
#: quantile 3.2 against 0.3), and these rests read it within a fifth (docs/tradeoff.md,
#: "Long rests for the threshold"). 3-12 s: past the memory's settling, and many presses'
#: states in a few minutes of rest.
DECISION_REST_SHARE = 0.3
DECISION_REST_S = (3.0, 12.0)
#: At most this many minutes of them, whatever the calibration's length (the share falls on
#: longer ones): on 100 presses the share gives 3.4, whose net inputs take 22 MB.
DECISION_REST_MINUTES = 4.0
#: Each of them follows this many seconds of the recording before it: the states the
#: preprocessing primes at its first sample (the creep inverse's lag, up to 2^12 samples;
#: the plays, which a press resets) have then come to what the whole recording leaves.
DECISION_REST_HISTORY_S = 30.0

#: Idle pads the contact decision's threshold is also read on (:func:`idle_rests`): this many
#: draws, each this many minutes of the calibration's own rest noise at its tare, from a fresh
#: start, their first :data:`IDLE_WARMUP_S` seconds (the filter's warm-up and the averages'
#: start) not scored. The threshold is aimed at half an event a minute: one event a draw.
#: What a draw leaves in the memory varies a great deal, so it takes many: on the family's
#: worst member 9 % of idle minutes still raised more than one event at the threshold 20
#: draws set, 2 % at the one 40 set. One-minute draws allowed none cost the quiet members'
#: onset too (docs/design-history.md, "The CUSUM's threshold: on idle pads too").
IDLE_DRAWS = 40
IDLE_MINUTES = 2.0
IDLE_WARMUP_S = 1.0

#: Synthetic samples: their net inputs and the rows (of the prepared data) whose labels they take.
Held = tuple[np.ndarray, np.ndarray]


def synthetic_holds(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, share: float,
                    creep: Creep, rng: np.random.Generator, on_release: bool = False,
                    wander: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Net inputs of presses among ``rows`` held at their peak (``on_release``: on their
    release; ``wander``: their load wandering below the peak), and the rows (of ``data``)
    whose labels they take.

    A calibration stage that turns round at every peak never shows the memory a load standing
    still: its averages then decay towards the load, a state the nets meet first in a held grip.
    A ``share`` of the presses (drawn per press) gets a hold of ``U(*HOLD_AUGMENT_S)`` seconds
    inserted after its peak sample: the five wavelengths at the mean of the six raw samples up
    to the peak, scaled to the peak force, plus interrogator noise drawn (one row of all five
    channels at a time) from the recording's own first differences at rest over √2, the labels
    those of the peak. Through the hold the pad keeps creeping as ``creep`` says
    (:func:`~fbgforce.trainer.creep_fit.fit_creep`): the strain part of the held shifts
    (temperature and tare untouched) rises by ``m (F - lag(F))`` of the force it carried at the
    peak, with the creep's time constant, and the samples after the hold carry what is left of
    that rise as the lag runs down; without it the nets would learn the peak's still-lagging
    shifts as the held load and read a real hold high by that creep (1.8 % on the calibration
    scene). The inputs are recomputed with ``pre`` over the whole lengthened recording, so the
    filter and the memory states run through the hold as the runtime's would; the held samples
    (one every :data:`HOLD_AUGMENT_STEP_S`) and the rest of the press after the hold are
    returned.

    ``on_release``: each hold starts instead at the first sample of the release at or below a
    share of the peak drawn in :data:`RELEASE_HOLD_AT`, and keeps the strain the release had
    there: what a friction keeps when the load stops on its way down, and a damper does not
    (:func:`~fbgforce.trainer.hysteresis.friction_hold_choice` decides whether the calibration
    shows the one and not the other).

    ``wander``: after a lead at the peak the load dips and comes back (:data:`WANDER_DEPTH`,
    :data:`WANDER_PERIOD_S`) through the press's own samples, each held sample labelled by one
    of them, and the strain follows as a friction has it (:func:`_wandering`): a grip that
    wanders runs the pad through loops a calibration press, which turns once, never shows.
    One held sample every :data:`WANDER_STEP_S` is returned.
    """
    inputs, kept = [], []
    for r, sl, sel, contact, noise, pid in _augmented_recordings(data, rows):
        wl = np.asarray(r.ds.wl_nm, dtype=np.float64)
        presses = np.unique(pid[contact[sel]])
        peaks, pressed_rows, after = [], [], np.zeros(len(wl), dtype=bool)
        for p in presses[rng.random(presses.size) < share]:
            loaded = sel[(pid == p) & contact[sel]]
            pressed = np.nan_to_num(np.asarray(r.ds.force_N, float)[loaded])
            top = int(np.argmax(pressed))
            if on_release:
                below = np.flatnonzero(pressed[top:] <= rng.uniform(*RELEASE_HOLD_AT) * pressed[top])
                if not below.size:
                    continue
                top += int(below[0])
            peak = int(loaded[top])
            peaks.append(peak)
            pressed_rows.append(loaded)
            after[sel[(pid == p) & (sel > peak)]] = True
        if not peaks:
            continue
        order = np.argsort(peaks)   # in time order: a hold's creep runs on into the later ones
        peaks = [peaks[i] for i in order]
        lengths = np.round(rng.uniform(*HOLD_AUGMENT_S, len(peaks)) * r.rate_hz).astype(np.int64)
        # The mean of the 6 samples up to the peak, its strain part scaled by the peak force
        # over their mean force (the load still rises there). Not the samples after it: past
        # a turn the pad's friction holds the strain while the load falls.
        force = np.nan_to_num(np.asarray(r.ds.force_N, float))
        around = [slice(max(0, k - 5), k + 1) for k in peaks]
        level = np.array([wl[a].mean(axis=0) for a in around])
        base = np.asarray(r.baseline_nm, float)
        scale = force[peaks] / np.maximum([force[a].mean() for a in around], 1e-12)
        level[:, :artifact.N_STRAIN] = (base[:artifact.N_STRAIN]
                                  + (level[:, :artifact.N_STRAIN] - base[:artifact.N_STRAIN]) * scale[:, None])
        rise = creep.still_to_come(force, np.asarray(peaks), r.rate_hz)
        strain = pp.compensated(pre, level, r.baseline_nm) / 1000.0     # nm
        ramp = [rise[i] * creep.settling(n, r.rate_hz) for i, n in enumerate(lengths)]
        held = (np.repeat(level, lengths, axis=0)
                + noise[rng.integers(0, len(noise), int(lengths.sum()))])
        held[:, :artifact.N_STRAIN] += np.concatenate(ramp)[:, None] * np.repeat(strain, lengths, axis=0)
        labels = np.repeat(peaks, lengths)
        if wander:
            first = np.concatenate([[0], np.cumsum(lengths)[:-1]])
            for i, k, n, at in zip(order, peaks, lengths, first):
                moved, labels[at:at + n] = _wandering(wl, force, pressed_rows[i], k, n,
                                                      r.rate_hz, rng)
                held[at:at + n, :artifact.N_STRAIN] += moved
        wl, held = _creep_left_after_holds(wl, held, peaks, lengths, ramp, strain, creep,
                                           r.rate_hz)
        in_hold = np.concatenate([np.arange(n) for n in lengths])
        step = max(1, int(round((WANDER_STEP_S if wander else HOLD_AUGMENT_STEP_S) * r.rate_hz)))
        x, src = _lengthened_inputs(pre, r, wl, peaks, lengths, held, in_hold % step == 0, after,
                                    labels)
        inputs.append(x)
        kept.append(src + sl.start)
    return _stacked(inputs, kept, pre, rows)


def _branch(wl: np.ndarray, force: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The loads and strain shifts (nm) of the samples ``idx`` (at least
    :data:`BRANCH_SMOOTH`) of one branch of a press, each a running mean over
    :data:`BRANCH_SMOOTH` of them, in the order of the load."""
    kernel = np.ones(BRANCH_SMOOTH) / BRANCH_SMOOTH
    load = np.convolve(force[idx], kernel, "valid")
    shifts = np.column_stack([np.convolve(wl[idx, c], kernel, "valid")
                              for c in range(artifact.N_STRAIN)])
    order = np.argsort(load, kind="stable")
    return load[order], shifts[order]


def _shifts_at(branch: tuple[np.ndarray, np.ndarray], load: np.ndarray) -> np.ndarray:
    """(len(load), N_STRAIN) the strain shifts of ``branch`` (:func:`_branch`) at ``load``."""
    at, shifts = branch
    return np.column_stack([np.interp(load, at, shifts[:, c]) for c in range(shifts.shape[1])])


def _wandering(wl: np.ndarray, force: np.ndarray, pressed: np.ndarray, peak: int, n: int,
               rate_hz: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """What a hold of ``n`` samples at ``peak`` (a sample of the press whose loaded samples
    are ``pressed``) gains in strain shifts (n, N_STRAIN) when its load wanders, and the
    samples of the press whose labels its samples take.

    The load stands for :data:`WANDER_LEAD_S`, then dips by :data:`WANDER_DEPTH` of the peak
    and back over :data:`WANDER_PERIOD_S` (whole periods, so that it ends at the peak), each
    step to the press's sample (rise or fall) nearest it, whose labels the held sample takes.
    The strain is the press's own: its load signal (the least-squares force of the press's
    strain shifts) stays where it is while it lies between the rise and the fall at the
    present load, and is carried along the branch the load pushes it onto: it sticks at each
    turn, then slides on the other branch, as a friction has it. A damper's fall relaxes when
    the load stops, which is why these holds are made only where the calibration establishes
    a friction (:func:`~fbgforce.trainer.hysteresis.friction_hold_choice`). A press with too
    few samples on a branch to read it gets a flat hold."""
    top = int(np.searchsorted(pressed, peak))
    rise, fall = pressed[:top + 1], pressed[top:]
    if min(rise.size, fall.size) < BRANCH_SMOOTH + 2:
        return np.zeros((n, artifact.N_STRAIN)), np.full(n, peak)
    up_branch, down_branch = _branch(wl, force, rise), _branch(wl, force, fall)
    both = np.concatenate([rise, fall])
    fit = np.column_stack([wl[both, :artifact.N_STRAIN], np.ones(both.size)])
    signal = np.linalg.lstsq(fit, force[both], rcond=None)[0][:artifact.N_STRAIN]

    lead = min(n - 1, int(rng.uniform(*WANDER_LEAD_S) * rate_hz))
    depth, period = rng.uniform(*WANDER_DEPTH), rng.uniform(*WANDER_PERIOD_S) * rate_hz
    # Whole periods: the hold ends back at the peak, where the press's recorded release goes
    # on (a hold that ended below it would hand the release a jump back up).
    period = (n - 1 - lead) / max(1, round((n - 1 - lead) / period))
    phase = 2 * np.pi * np.maximum(np.arange(n) - lead, 0) / max(period, 1.0)
    wanted = force[peak] * (1.0 - 0.5 * depth * (1.0 - np.cos(phase)))
    wanted = np.maximum(wanted, max(up_branch[0][0], down_branch[0][0]))
    by_load = both[np.argsort(force[both], kind="stable")]
    j = np.clip(np.searchsorted(force[by_load], wanted), 1, both.size - 1)
    j -= (wanted - force[by_load[j - 1]]) < (force[by_load[j]] - wanted)
    labels = by_load[j]
    labels[:lead] = peak
    load = force[labels]

    up, down = _shifts_at(up_branch, load), _shifts_at(down_branch, load)
    start = _shifts_at(up_branch, force[peak:peak + 1])[0]
    lo_is_up = up @ signal <= down @ signal
    lo = np.where(lo_is_up[:, None], up, down)
    hi = np.where(lo_is_up[:, None], down, up)
    level, now = start, float(start @ signal)
    moved = np.empty((n, artifact.N_STRAIN))
    for i in range(n):
        if now < lo[i] @ signal:
            level = lo[i]
            now = float(level @ signal)
        elif now > hi[i] @ signal:
            level = hi[i]
            now = float(level @ signal)
        moved[i] = level
    return moved - start, labels


def _creep_left_after_holds(wl: np.ndarray, held: np.ndarray, peaks: Sequence[int],
                            lengths: np.ndarray, ramp: Sequence[np.ndarray], strain: np.ndarray,
                            creep: Creep, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The recorded wavelengths ``wl`` and the held rows ``held`` (the holds of ``peaks``, in
    order, ``lengths[i]`` rows after ``peaks[i]``) with what the creep each hold reached
    (``ramp[i][-1]`` of its strain shifts ``strain[i]``) leaves as its lag runs down after the
    hold: over 10 time constants, on every later sample of the lengthened recording, the
    later holds' rows included. A hold that starts while an earlier one's creep still runs
    down holds that residue too, and keeps it running down; levelled without it, its rows
    would step down from the samples before it by the residue (the nets would learn a held
    load read low by it, up to a few percent with a creep of seconds)."""
    inserted = np.insert(np.zeros(len(wl), dtype=bool), np.repeat(np.asarray(peaks) + 1, lengths),
                         True)
    out = np.empty((inserted.size, wl.shape[1]))
    out[~inserted], out[inserted] = wl, held
    tail = 1.0 - creep.settling(int(10 * creep.time_constant_s * rate_hz) + 1, rate_hz)
    ends = np.asarray(peaks) + 1 + np.cumsum(lengths)      # first sample after each hold
    for end, reached, shifts in zip(ends, ramp, strain):
        left = reached[-1] * tail[1:1 + out.shape[0] - end]
        out[end:end + left.size, :artifact.N_STRAIN] += left[:, None] * shifts
    return out[~inserted], out[inserted]


def synthetic_rests(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, share: float,
                    step: int, rng: np.random.Generator,
                    lengths_s: tuple[float, float] = REST_AUGMENT_S
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Net inputs of long rests inserted among the presses of ``rows``, and the rows (of
    ``data``) whose labels they take.

    A calibration stage that presses again within a second never shows the nets a fingertip
    that has rested for long: the pad's creep recovered, the at-rest tracker's correction
    taken (docs/runtime.md, "In use"), the memory's averages settled at zero and its play
    operators where the last release left them. Nets that never saw that state read its
    noise as light presses (false contact events at rest). A ``share`` of the presses (drawn
    per press) gets a rest of ``U(*lengths_s)`` seconds inserted midway between its first
    contact sample and the previous press's last (when they lie more than ``2 * REST_GAP_S``
    apart): the five wavelengths of the six samples there, their strain part moved to zero
    compensated shift (temperature untouched), plus interrogator noise as in
    :func:`synthetic_holds`. Zero, not the level there: a short rest still carries the pad's
    creep recovery, and a long one held at it would teach the nets that a light press is no
    contact. The inputs are recomputed with ``pre`` over the lengthened recording; returned is
    one rest sample in ``step`` from :data:`REST_AUGMENT_SETTLE_S` on, past the step down to
    zero, labelled as the sample where the rest was inserted (contact-free). The press after
    the rest is not: it would start with a step up from zero to the residual.
    """
    inputs, kept = [], []
    for r, sl, wl, noise, starts, level, lengths in _placed_rests(data, pre, rows, share, rng,
                                                                  lengths_s):
        rest = (np.repeat(level, lengths, axis=0)
                + noise[rng.integers(0, len(noise), int(lengths.sum()))])
        in_rest = np.concatenate([np.arange(n) for n in lengths])
        settle = int(round(REST_AUGMENT_SETTLE_S * r.rate_hz))
        x, src = _lengthened_inputs(pre, r, wl, starts, lengths, rest,
                                    (in_rest >= settle) & ((in_rest - settle) % step == 0),
                                    np.zeros(len(wl), dtype=bool))
        inputs.append(x)
        kept.append(src + sl.start)
    return _stacked(inputs, kept, pre, rows)


def _placed_rests(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, share: float,
                  rng: np.random.Generator, lengths_s: tuple[float, float]
                  ) -> Iterator[tuple[Recording, slice, np.ndarray, np.ndarray, list[int],
                                      np.ndarray, np.ndarray]]:
    """Where the rests of :func:`synthetic_rests` go, per recording with some of ``rows``:
    ``(r, sl, wl, noise, points, levels, lengths)``, the recording, its slice of the prepared
    rows, its wavelengths and rest noise; the samples after which a rest goes, before a
    ``share`` of its presses (drawn per press), midway between the press's first contact
    sample and the previous press's last where they lie more than ``2 * REST_GAP_S`` apart;
    each rest's five wavelengths (the mean of the six samples there, the strain part moved to
    zero compensated shift, temperature untouched) and its length, ``U(*lengths_s)``
    seconds."""
    for r, sl, sel, contact, noise, pid in _augmented_recordings(data, rows):
        gap = int(round(fmetrics.REST_GAP_S * r.rate_hz))
        touched = np.flatnonzero(contact)
        points = []
        for p in np.unique(pid[contact[sel]]):
            if rng.random() >= share:
                continue
            first = int(sel[(pid == p) & contact[sel]].min())
            before = touched[touched < first]
            prev = int(before[-1]) if before.size else -gap
            if first - prev > 2 * gap + 6:
                points.append((prev + first) // 2)
        if not points:
            continue
        wl = np.asarray(r.ds.wl_nm, dtype=np.float64)
        levels = np.array([wl[max(0, k - 5):k + 1].mean(axis=0) for k in points])
        levels[:, :artifact.N_STRAIN] -= pp.compensated(pre, levels, r.baseline_nm) / 1000.0
        lengths = np.round(rng.uniform(*lengths_s, len(points)) * r.rate_hz).astype(np.int64)
        yield r, sl, wl, noise, points, levels, lengths


def unloaded_recovery(pre: artifact.Preprocess, comp: np.ndarray, n: int) -> np.ndarray:
    """What to add (pm, (n, 4)) to the compensated shifts of ``n`` samples at zero that follow
    a recording's compensated shifts ``comp`` (m, 4) for ``pre``'s creep inverse to read no
    load on them: the pad's own recovery. The standard linear solid of
    :mod:`fbgforce.model.floatref` with no elastic strain reads ``kappa L``, ``L`` the
    inverse's lag after ``comp`` decaying by ``2^-creep_shift`` a sample, and its inverse reads
    exactly zero on that. Zeros without a creep inverse."""
    if not pre.creep or n == 0 or len(comp) == 0:
        return np.zeros((n, artifact.N_STRAIN))
    comp = np.asarray(comp, dtype=np.float64)
    lag = floatref.creep_lags(pre, comp, comp[0].copy())[-1]
    kappa = pre.creep_gain / (1.0 + pre.creep_gain)
    return kappa * lag * (1.0 - 2.0 ** -pre.creep_shift) ** np.arange(n)[:, None]


def decision_rests(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray,
                   rng: np.random.Generator) -> np.ndarray:
    """Net inputs of every sample of synthetic long rests after :data:`DECISION_REST_SHARE`
    of the presses of ``rows`` (fewer on a calibration so long that they would last past
    :data:`DECISION_REST_MINUTES`), each ``U(*DECISION_REST_S)`` seconds long, from
    :data:`REST_AUGMENT_SETTLE_S` on, in time order: what the contact decision's threshold is
    read on beside the calibration's own rests.

    Each rest is placed where :func:`synthetic_rests` places one, but made on its own: the
    recording's last :data:`DECISION_REST_HISTORY_S` seconds up to that point, then the pad
    left unloaded, with the calibration's rest noise. Unloaded is zero compensated shift,
    or with ``pre``'s creep inverse the pad's own recovery from where it stood
    (:func:`unloaded_recovery`), which the inverse reads as no load at all. So each rest
    begins in the state a real rest after that press begins in: not after the rests inserted
    before it (the recording would resume from each with a step up to its residual), and
    not with a step to zero, which reads through the inverse as a load below zero fading
    over the creep's time constant."""
    presses = sum(np.unique(pid[contact[sel]]).size
                  for _, _, sel, contact, _, pid in _augmented_recordings(data, rows))
    share = decision_rest_share(presses)
    inputs = []
    for r, _, wl, noise, points, levels, lengths in _placed_rests(data, pre, rows, share, rng,
                                                                  DECISION_REST_S):
        history = int(round(DECISION_REST_HISTORY_S * r.rate_hz))
        settle = int(round(REST_AUGMENT_SETTLE_S * r.rate_hz))
        for point, level, n in zip(points, levels, lengths):
            m = min(history, point + 1)
            both = np.concatenate([wl[point + 1 - m:point + 1],
                                   level + noise[rng.integers(0, len(noise), int(n))]])
            # Compensated causally, so its first m rows are the history's own.
            comp = pp.compensated(pre, both, r.baseline_nm, recording=True)
            comp[m:] += unloaded_recovery(pre, comp[:m], int(n))
            x = floatref.standardise(pre, floatref.apply_filter(pre, comp))
            inputs.append(x[m + settle:])
    return np.concatenate(inputs) if inputs else np.empty((0, pre.n_inputs))


def idle_rests(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray,
               rng: np.random.Generator, draws: int = IDLE_DRAWS,
               minutes: float = IDLE_MINUTES) -> list[np.ndarray]:
    """The contact net's inputs (``pre.n_features`` columns) on ``draws`` idle pads: a fresh
    start at the tare of the first recording of ``rows`` with rest noise, then ``minutes`` of
    nothing but that noise (rows of :func:`_rest_noise`, all five channels together, drawn
    with replacement from every such recording of ``rows``), computed with ``pre`` as the
    runtime would run them; each draw's samples from :data:`IDLE_WARMUP_S` on, in time order;
    none without rest noise.

    A calibration's rests are broken by its presses; a pad left alone for minutes is not, and
    what the noise's record lows leave in the memory then stays (docs/robustness.md, "An idle
    pad")."""
    found = [(r, noise) for r, _, _, _, noise, _ in _augmented_recordings(data, rows)]
    if not found:
        return []
    noise = np.concatenate([n for _, n in found])
    base = np.asarray(found[0][0].baseline_nm, dtype=np.float64)
    skip = int(round(IDLE_WARMUP_S * data.rate_hz))
    n = skip + int(round(minutes * 60.0 * data.rate_hz))
    # The contact net reads none of the location averages: a third of the time, left out.
    contact_only = replace(pre, memory=replace(pre.memory, loc_shift=0))
    out = []
    for _ in range(draws):
        wl = base + noise[rng.integers(0, len(noise), n)]
        x = floatref.standardise(contact_only, pp.recording_features(contact_only, wl, base))
        out.append(x[skip:, :pre.n_features])
    return out


def decision_rest_share(presses: int) -> float:
    """The share of ``presses`` :func:`decision_rests` inserts a rest before:
    :data:`DECISION_REST_SHARE`, or less where their rests' mean length would add up past
    :data:`DECISION_REST_MINUTES`."""
    return min(DECISION_REST_SHARE, DECISION_REST_MINUTES * 60.0
               / (max(presses, 1) * float(np.mean(DECISION_REST_S))))


def scaled_presses(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, max_scale: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Net inputs of the training presses pressed ``k`` times harder, ``k ~ U(1, max_scale)``
    per press, and the rows (of ``data``) they stand for.

    Where a press lands does not depend on how hard: the strain part of every grating's
    compensated shift is scaled by ``k`` (temperature and tare untouched) and the inputs are
    recomputed with the model's own preprocessing ``pre`` (filter, standardisation, memory) on
    the whole recording, so the memory states see a consistent time series. The location net
    then sees each spot at forces the calibration did not reach there; without it, it
    interpolates between the few presses that reached high force (docs/trainer.md).
    """
    inputs, kept = [], []
    for r, sl in data.recording_slices():
        start = sl.start
        sel = rows[(rows >= start) & (rows < sl.stop)] - start
        if sel.size:
            _, inverse = np.unique(np.asarray(r.ds.press_id), return_inverse=True)
            k = rng.uniform(1.0, max_scale, inverse.max() + 1)[inverse]
            comp = pp.compensated(pre, r.ds.wl_nm, r.baseline_nm)
            wl = np.array(r.ds.wl_nm, dtype=np.float64, copy=True)
            wl[:, :artifact.N_STRAIN] += (k[:, None] - 1.0) * comp / 1000.0
            feats = pp.recording_features(pre, wl, r.baseline_nm)
            inputs.append(floatref.standardise(pre, feats)[sel])
            kept.append(sel + start)
    return _stacked(inputs, kept, pre, rows)


def _stacked(inputs: list[np.ndarray], kept: list[np.ndarray], pre: artifact.Preprocess,
             rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The synthetic samples of every recording, ``(inputs, rows)`` one after the other; none
    made, empty arrays of ``pre``'s input width and ``rows``' type."""
    if not inputs:
        return np.empty((0, pre.n_inputs)), rows[:0]
    return np.concatenate(inputs), np.concatenate(kept)


def _lengthened_inputs(pre: artifact.Preprocess, r: Recording, wl: np.ndarray, points: Sequence[int],
                       lengths: np.ndarray, inserted: np.ndarray, keep_inserted: np.ndarray,
                       keep_recorded: np.ndarray, labels: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Net inputs of recording ``r`` (wavelengths ``wl``) lengthened by ``inserted`` (the
    rows of all insertions, ``lengths[i]`` of them after sample ``points[i]``), recomputed
    with ``pre`` over the whole lengthened recording as the runtime would run it; returned
    are the inserted rows ``keep_inserted`` marks and the recorded samples ``keep_recorded``
    marks, and the samples of ``r`` whose labels they take (an inserted row its point's, or
    its entry of ``labels``)."""
    at = np.repeat(np.asarray(points) + 1, lengths)
    keep = np.insert(keep_recorded, at, keep_inserted)
    source = np.insert(np.arange(len(wl)), at,
                       np.repeat(points, lengths) if labels is None else labels)
    feats = pp.recording_features(pre, np.insert(wl, at, inserted, axis=0), r.baseline_nm)
    return floatref.standardise(pre, feats)[keep], source[keep]


def _augmented_recordings(data: Prepared, rows: np.ndarray
                          ) -> Iterator[tuple[Recording, slice, np.ndarray, np.ndarray,
                                              np.ndarray, np.ndarray]]:
    """The recordings synthetic holds and rests are made in: per recording with some of
    ``rows`` and rest noise to draw from, ``(r, sl, sel, contact, noise, pid)``: the recording,
    its slice of the prepared rows, its rows among ``rows`` (recording-local), its contact
    labels, its :func:`_rest_noise` and the press ids of ``sel``."""
    for r, sl in data.recording_slices():
        sel = rows[(rows >= sl.start) & (rows < sl.stop)] - sl.start
        noise = _rest_noise(r)
        if not sel.size or noise is None:
            continue
        yield (r, sl, sel, np.asarray(r.ds.contact, bool), noise,
               np.asarray(r.ds.press_id)[sel])


def _rest_noise(r: Recording) -> np.ndarray | None:
    """Interrogator noise of recording ``r``: its first differences between contact-free
    samples over √2 (one row of all five channels each), or None without two in a row."""
    rest = fbgtare.contact_free_mask(np.asarray(r.ds.contact, bool), r.ds.t_s)
    still = rest[1:] & rest[:-1]
    if not still.any():
        return None
    return np.diff(np.asarray(r.ds.wl_nm, dtype=np.float64), axis=0)[still] / np.sqrt(2.0)
