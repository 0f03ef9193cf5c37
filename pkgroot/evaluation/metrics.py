"""The one definition of fbgforce's accuracy metrics (docs/cli.md, "Metric definitions").

Every engine, command and benchmark scores predictions with :func:`compute` (or
:func:`from_dataset`), so a number printed by ``evaluate``, ``report`` or ``tradeoff`` always
means the same thing:

- ``contact_accuracy``: fraction of ALL samples whose predicted contact equals the true contact.
- ``rmse_force_N``: RMSE over samples with TRUE contact of what the pipeline outputs (0 N where
  it says "no contact") against the load-cell force. A missed contact therefore costs its whole
  force, as it would in a controller.
- ``rmse_x_mm`` / ``rmse_y_mm``: RMSE over samples where true AND predicted contact are both
  "contact" (a location only exists there).
- ``n_samples``: number of samples scored.

Extras (same conventions): ``contact_accuracy_above_5N`` (true contact with force > 5 N,
fraction detected, the paper's "100 % over 5 N"), ``false_contact_rate`` (fraction of true
no-contact samples flagged as contact), ``by_force`` (the three RMSEs and contact accuracy per
true-force range), ``boundary`` / ``interior`` (location and force RMSE for contacts within
``boundary_mm`` of the pad edge, and the rest), ``contact_accuracy_above_1N`` and
``contact_by_force`` (fraction of true-contact samples detected per finer force bin: where
light-touch detection fails). An RMSE over an empty set is ``None`` (JSON ``null``), never
NaN, so the JSON stays standard.

Location on common contacts (:func:`common_location`): ``rmse_x_mm``/``rmse_y_mm`` of several
estimators over the samples where the truth and EVERY one of them say "contact". Each
estimator's own ``rmse_x_mm`` is scored where it detects contact, so a detector that misses the
light touches (where location is hardest) is scored on easier samples; on the common samples
the comparison is like for like.

Contact timing (:func:`press_delays`, :func:`timing_summary`; ``contact_timing`` when the
caller passes ``delays``): per press, the onset delay is the first predicted-contact sample
minus the first true-contact sample, the release delay the first predicted no-contact sample
after the press minus the first true no-contact sample after it, both in ms (negative: early).

In use (:func:`use_masks`, then ``at_rest`` and ``holds`` when the caller passes ``use``):

- rest: samples at least :data:`REST_GAP_S` (50 ms) from any labelled contact; an event: the
  predicted contact rising from no-contact to contact; ``at_rest`` counts the events whose
  rising sample is at rest (per minute of rest), the fraction of rest samples flagged as
  contact and the 99th percentile and maximum of the force output's magnitude at rest;
- hold: a run of true-contact samples lasting at least :data:`HOLD_MIN_S` (1 s) around each of
  which the true force, averaged over :data:`HOLD_SMOOTH_S` against load-cell noise, varies by
  at most ``max(HOLD_BAND_N, HOLD_BAND_FRACTION * force)`` over a centred
  :data:`HOLD_WINDOW_S` window (a slope below about 1 N/s at light loads, so ramps are not
  holds); ``holds`` gives the force output's bias and RMSE over the held samples, and the
  same over the held samples more than :data:`AFTER_TURN_S` after the last turn of the load
  (``away_from_turns``);
- turn: where the smoothed true force reverses, found once it has moved :data:`HOLD_BAND_N`
  back from its extreme (a dead band against load-cell noise), dated at the extreme. A pad with
  friction changes branch within a fraction of a newton of load after a turn, while its
  strain tells a slow turn from noise only later; how a model reads the grip away from the
  turns separates that from a level error;
- direction: between two turns the load rises or falls (``falling``: on its way down from a
  turn at a high, or before a first turn at a low); ``holds.by_direction`` gives the bias and
  RMSE over the held samples of each. A pad with friction reads its falling samples high and
  its rising ones low by about the same; a level error reads both alike.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

#: Upper edges (N) of the force ranges reported under ``by_force``; the last range is open.
FORCE_BINS_N: tuple[float, ...] = (5.0, 20.0, 40.0)
#: Contacts closer than this to the pad edge count as "boundary" (mm).
BOUNDARY_MM = 2.0
#: Force above which the paper reports a 100 % contact success rate.
HIGH_FORCE_N = 5.0
#: Upper edges (N) of the finer force bins of ``contact_by_force`` (light touch); last is open.
CONTACT_BINS_N: tuple[float, ...] = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0)
#: Force above which the contact goal is "every sample detected" (``contact_accuracy_above_1N``).
LIGHT_FORCE_N = 1.0
#: Rest: samples at least this far (s) from any labelled contact (``at_rest``).
REST_GAP_S = 0.05
#: A hold lasts at least this long (s) (``holds``).
HOLD_MIN_S = 1.0
#: Moving average (s) of the true force before the hold test: load-cell noise is no change.
HOLD_SMOOTH_S = 0.02
#: Centred window (s) over which a held sample's smoothed true force stays within the band.
HOLD_WINDOW_S = 0.2
#: Band of a hold: the smoothed true force varies by at most the larger of these (N, fraction).
HOLD_BAND_N = 0.2
HOLD_BAND_FRACTION = 0.05
#: Held samples this long (s) after a turn of the load count as near it (``holds``,
#: ``away_from_turns``).
AFTER_TURN_S = 0.75
#: Keys of :func:`use_masks` (each (n,)).
USE_KEYS = ("rest", "event", "held", "hold_start", "after_turn", "falling", "period_s")
#: Fewest presses a held-out split should hold for its metrics to mean much: fewer is a
#: warning (``warnings`` in the JSON of train and evaluate), not an error.
MIN_SPLIT_PRESSES = 5


def _pad_size_mm() -> tuple[float, float]:
    """Sensing-area size (x, y) in mm of the nominal design."""
    from fbgforce.geometry import PAD_SIZE_MM

    return (float(PAD_SIZE_MM[0]), float(PAD_SIZE_MM[1]))


def _rmse(err: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(np.square(err)))) if err.size else None


def _core(pc: np.ndarray, pf: np.ndarray, px: np.ndarray, py: np.ndarray,
          tc: np.ndarray, tf: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> dict[str, Any]:
    both = tc & pc
    return {
        "contact_accuracy": float(np.mean(pc == tc)) if tc.size else None,
        "rmse_force_N": _rmse(pf[tc] - tf[tc]),
        "rmse_x_mm": _rmse(px[both] - tx[both]),
        "rmse_y_mm": _rmse(py[both] - ty[both]),
        "n_samples": int(tc.size),
    }


def compute(pred: Mapping[str, np.ndarray], contact: np.ndarray, force_N: np.ndarray,
            x_mm: np.ndarray, y_mm: np.ndarray, *, extras: bool = True,
            force_bins_N: Sequence[float] = FORCE_BINS_N, boundary_mm: float = BOUNDARY_MM,
            pad_mm: tuple[float, float] | None = None,
            delays: tuple[np.ndarray, np.ndarray] | None = None,
            use: Mapping[str, np.ndarray] | None = None) -> dict[str, Any]:
    """Score predictions against ground truth.

    Parameters
    ----------
    pred
        Engine output with keys ``contact`` (bool), ``force_N``, ``x_mm``, ``y_mm`` (n,).
        ``force_N`` is taken as 0 wherever ``contact`` is False, whatever the engine put there.
    contact, force_N, x_mm, y_mm
        Ground truth (n,); x/y may be NaN where there is no contact.
    extras
        Add ``contact_accuracy_above_5N``, ``false_contact_rate``, ``by_force``, ``boundary``,
        ``interior``, ``contact_accuracy_above_1N``, ``contact_by_force`` to the five shared
        keys.
    force_bins_N, boundary_mm, pad_mm
        Range edges for ``by_force``; edge distance and pad size (x, y) for ``boundary``.
    delays
        Per-press onset and release delays (ms) from :func:`press_delays` (concatenated over
        recordings); with ``extras`` they are summarised under ``contact_timing``.
    use
        :func:`use_masks` of each recording, concatenated in the order of the samples; with
        ``extras`` they give ``at_rest`` and ``holds``.

    Returns
    -------
    dict
        ``contact_accuracy``, ``rmse_force_N``, ``rmse_x_mm``, ``rmse_y_mm``, ``n_samples``
        (+ extras). RMSEs over empty sets are ``None``.
    """
    tc = np.asarray(contact).astype(bool).reshape(-1)
    n = tc.size
    tf = np.asarray(force_N, dtype=np.float64).reshape(-1)
    tx = np.asarray(x_mm, dtype=np.float64).reshape(-1)
    ty = np.asarray(y_mm, dtype=np.float64).reshape(-1)
    pc = np.asarray(pred["contact"]).astype(bool).reshape(-1)
    pf = np.where(pc, np.asarray(pred["force_N"], dtype=np.float64).reshape(-1), 0.0)
    px = np.asarray(pred["x_mm"], dtype=np.float64).reshape(-1)
    py = np.asarray(pred["y_mm"], dtype=np.float64).reshape(-1)
    for name, arr in (("truth force_N", tf), ("truth x_mm", tx), ("truth y_mm", ty),
                      ("pred contact", pc), ("pred force_N", pf), ("pred x_mm", px),
                      ("pred y_mm", py)):
        if arr.size != n:
            raise ValueError(f"{name} has {arr.size} samples, contact has {n}")
    out = _core(pc, pf, px, py, tc, tf, tx, ty)
    if not extras:
        return out
    out.update(_contact_extras(pc, tc, tf))
    truth, pred_ = (tc, tf, tx, ty), (pc, pf, px, py)
    out["by_force"] = _by_force(pred_, truth, force_bins_N)
    out.update(_by_edge(pred_, truth, boundary_mm, pad_mm))
    if delays is not None:
        out["contact_timing"] = timing_summary(*delays)
    if use is not None:
        masks = {k: np.asarray(use[k]).reshape(-1) for k in USE_KEYS}
        for k, arr in masks.items():
            if arr.size != n:
                raise ValueError(f"use {k} has {arr.size} samples, contact has {n}")
        out["at_rest"] = rest_summary(pc, pf, masks)
        out["holds"] = hold_summary(pf, tf, masks)
    return out


def _contact_extras(pc: np.ndarray, tc: np.ndarray, tf: np.ndarray) -> dict[str, Any]:
    """The contact decision's accuracy above 5 N and 1 N, by force and its false contacts."""
    out: dict[str, Any] = {}
    high = tc & (tf > HIGH_FORCE_N)
    out["contact_accuracy_above_5N"] = float(np.mean(pc[high])) if high.any() else None
    above_1 = tc & (tf > LIGHT_FORCE_N)
    out["contact_accuracy_above_1N"] = float(np.mean(pc[above_1])) if above_1.any() else None
    contact_by_force = []
    cedges = [-np.inf, *map(float, CONTACT_BINS_N), np.inf]
    for lo, hi in zip(cedges[:-1], cedges[1:]):
        # The first bin is open below: a labelled contact may read <= 0 N on a noisy load cell.
        sel = tc & (tf > lo) & (tf <= hi)
        contact_by_force.append({"range_N": [max(lo, 0.0), None if np.isinf(hi) else hi],
                                 "n_samples": int(sel.sum()),
                                 "contact_accuracy": float(np.mean(pc[sel])) if sel.any() else None})
    out["contact_by_force"] = contact_by_force
    out["false_contact_rate"] = float(np.mean(pc[~tc])) if (~tc).any() else None
    return out


def _by_force(pred: tuple[np.ndarray, ...], truth: tuple[np.ndarray, ...],
              force_bins_N: Sequence[float]) -> list[dict[str, Any]]:
    """The shared metrics of the true contacts in each force range."""
    (pc, pf, px, py), (tc, tf, tx, ty) = pred, truth
    edges = [0.0, *map(float, force_bins_N), np.inf]
    by_force = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = tc & (tf > lo) & (tf <= hi)
        row = _core(pc[sel], pf[sel], px[sel], py[sel], tc[sel], tf[sel], tx[sel], ty[sel])
        row["range_N"] = [lo, None if np.isinf(hi) else hi]
        by_force.append(row)
    return by_force


def _by_edge(pred: tuple[np.ndarray, ...], truth: tuple[np.ndarray, ...], boundary_mm: float,
             pad_mm: tuple[float, float] | None) -> dict[str, dict[str, Any]]:
    """The shared metrics of the true contacts within ``boundary_mm`` of the pad's edge
    (``boundary``) and further in (``interior``)."""
    (pc, pf, px, py), (tc, tf, tx, ty) = pred, truth
    w, h = pad_mm if pad_mm is not None else _pad_size_mm()
    with np.errstate(invalid="ignore"):
        edge_dist = np.minimum.reduce([tx, w - tx, ty, h - ty])
        near = tc & (edge_dist < boundary_mm)
    out = {}
    for key, sel in (("boundary", near), ("interior", tc & ~near)):
        row = _core(pc[sel], pf[sel], px[sel], py[sel], tc[sel], tf[sel], tx[sel], ty[sel])
        row["within_mm"] = boundary_mm
        out[key] = row
    return out


def use_masks(pred_contact: np.ndarray, contact: np.ndarray, force_N: np.ndarray,
              t_s: np.ndarray) -> dict[str, np.ndarray]:
    """Per-sample masks of ONE continuous recording for ``at_rest`` and ``holds``.

    Parameters
    ----------
    pred_contact, contact
        (n,) predicted and labelled contact, in time order.
    force_N
        (n,) true (load-cell) force.
    t_s
        (n,) sample times; the sample period is their median difference.

    Returns
    -------
    dict
        ``rest``: at least :data:`REST_GAP_S` from any labelled contact; ``event``: the
        prediction rises from no-contact to contact here (never at the first sample);
        ``held``: in a hold (module docstring); ``hold_start``: the first sample of each hold;
        ``after_turn``: within :data:`AFTER_TURN_S` after a turn of the load, ``falling``:
        the load on its way down between turns (module docstring); ``period_s``: the
        recording's sample period, on every sample (rest time adds up over recordings of
        different rates).
    """
    pc = np.asarray(pred_contact, bool).reshape(-1)
    tc = np.asarray(contact, bool).reshape(-1)
    tf = np.asarray(force_N, dtype=np.float64).reshape(-1)
    n = tc.size
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    period = float(np.median(np.diff(t))) if n > 1 else 1e-3

    def samples(seconds: float) -> int:
        return max(1, int(round(seconds / period)))

    gap = samples(REST_GAP_S)
    # A sample is at rest when no labelled contact lies fewer than `gap` samples away.
    # Counted from cumulative sums, not np.convolve(mode="same"), which returns the kernel's
    # length when a recording is shorter than it.
    count = np.concatenate([[0], np.cumsum(tc, dtype=np.int64)])
    idx = np.arange(n)
    near = count[np.minimum(idx + gap, n)] - count[np.maximum(idx - gap + 1, 0)] > 0
    event = np.zeros(n, bool)
    event[1:] = pc[1:] & ~pc[:-1]
    held = np.zeros(n, bool)
    half = samples(HOLD_WINDOW_S) // 2
    after_turn = np.zeros(n, bool)
    falling = np.zeros(n, bool)
    if n > 2 * half:
        k = samples(HOLD_SMOOTH_S)
        smooth = np.convolve(tf, np.ones(k) / k, mode="same")
        # Read only beside holds, which a recording shorter than the window cannot hold.
        turns = load_turns(smooth, HOLD_BAND_N)
        for turn in turns:
            after_turn[turn:turn + samples(AFTER_TURN_S)] = True
        falling = load_falling(smooth, turns)
        padded = np.pad(smooth, half, mode="edge")
        windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)
        spread = windows.max(axis=1) - windows.min(axis=1)
        steady = tc & (spread <= np.maximum(HOLD_BAND_N, HOLD_BAND_FRACTION * np.abs(smooth)))
        edges = np.flatnonzero(np.diff(np.concatenate([[0], steady.astype(np.int8), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a >= samples(HOLD_MIN_S):
                held[a:b] = True
    hold_start = held & ~np.concatenate([[False], held[:-1]])
    return {"rest": ~near, "event": event, "held": held, "hold_start": hold_start,
            "after_turn": after_turn, "falling": falling, "period_s": np.full(n, period)}


def load_turns(force_N: np.ndarray, band_N: float) -> list[int]:
    """The samples where ``force_N`` turns: each extreme from which it then moves back by more
    than ``band_N`` (smaller reversals are noise), in time order."""
    turns: list[int] = []
    f = np.asarray(force_N, dtype=np.float64).tolist()
    if not f:
        return turns
    hi = lo = 0          # the extremes since the last turn
    going = 0            # +1 rising, -1 falling, 0 not yet known
    for i, v in enumerate(f):
        if v >= f[hi]:      # a flat extreme turns where the load leaves it
            hi = i
        if v <= f[lo]:
            lo = i
        if going >= 0 and v < f[hi] - band_N:
            if going > 0:
                turns.append(hi)
            going, lo = -1, i
        elif going <= 0 and v > f[lo] + band_N:
            if going < 0:
                turns.append(lo)
            going, hi = 1, i
    return turns


def load_falling(force_N: np.ndarray, turns: Sequence[int]) -> np.ndarray:
    """(n,) True where ``force_N`` is on its way down: from each turn at a high (the load then
    lower at the next turn, or at the end) to the next turn; before the first turn, where that
    turn is a low. Without turns, nothing falls."""
    f = np.asarray(force_N, dtype=np.float64).reshape(-1)
    out = np.zeros(f.size, bool)
    if not turns:
        return out
    edges = [0, *turns, f.size - 1]
    for a, b in zip(edges[:-1], edges[1:]):
        # Every segment runs from one extreme to the next, so its ends tell its direction.
        out[a:b] = f[b] < f[a]
    return out


def rest_summary(pc: np.ndarray, pf: np.ndarray, masks: Mapping[str, np.ndarray]
                 ) -> dict[str, Any]:
    """``at_rest``: samples and seconds at rest, the fraction flagged as contact, false contact
    events (per minute of rest), and the 99th percentile and maximum of ``|pf|`` there."""
    rest = masks["rest"].astype(bool)
    seconds = float(np.sum(masks["period_s"][rest]))
    events = int(np.sum(masks["event"].astype(bool) & rest))
    force = np.abs(pf[rest])
    return {"gap_ms": 1000.0 * REST_GAP_S, "samples": int(rest.sum()), "seconds": seconds,
            "contact_fraction": float(np.mean(pc[rest])) if rest.any() else None,
            "false_events": events,
            "false_events_per_min": 60.0 * events / seconds if seconds > 0 else None,
            "force_p99_N": float(np.percentile(force, 99)) if force.size else None,
            "force_max_N": float(np.max(force)) if force.size else None}


def hold_summary(pf: np.ndarray, tf: np.ndarray, masks: Mapping[str, np.ndarray]
                 ) -> dict[str, Any]:
    """``holds``: how many holds, their samples and seconds, and the bias (mean of output minus
    true force) and RMSE of the force output over the held samples; the same over those away
    from the load's turns (``away_from_turns``) and over those whose load rises or falls
    (``by_direction``), each with its share of the held samples."""
    held = masks["held"].astype(bool)
    err = pf[held] - tf[held]
    away = ~masks["after_turn"].astype(bool)[held]
    falling = masks["falling"].astype(bool)[held]

    def part(keep: np.ndarray) -> dict[str, Any]:
        return {"fraction": float(np.mean(keep)) if err.size else None,
                "force_bias_N": float(np.mean(err[keep])) if keep.any() else None,
                "rmse_force_N": _rmse(err[keep])}

    return {"min_s": HOLD_MIN_S, "band_N": HOLD_BAND_N, "band_fraction": HOLD_BAND_FRACTION,
            "holds": int(np.sum(masks["hold_start"].astype(bool))), "samples": int(held.sum()),
            "seconds": float(np.sum(masks["period_s"][held])),
            "force_bias_N": float(np.mean(err)) if err.size else None,
            "rmse_force_N": _rmse(err),
            "away_from_turns": {"after_turn_s": AFTER_TURN_S, **part(away)},
            "by_direction": {"rising": part(~falling), "falling": part(falling)}}


def common_location(preds: Mapping[str, Mapping[str, np.ndarray]], contact: np.ndarray,
                    x_mm: np.ndarray, y_mm: np.ndarray) -> dict[str, Any]:
    """Location RMSE of each estimator on the samples every estimator and the truth call contact.

    Parameters
    ----------
    preds
        Estimator name -> engine output (``contact``, ``x_mm``, ``y_mm``; (n,) each).
    contact, x_mm, y_mm
        Ground truth (n,).

    Returns
    -------
    dict
        ``n_samples`` (the common contacts) and, per estimator name, ``rmse_x_mm`` and
        ``rmse_y_mm`` over them (``None`` when there are none).
    """
    both = np.asarray(contact).astype(bool).reshape(-1)
    for p in preds.values():
        both = both & np.asarray(p["contact"]).astype(bool).reshape(-1)
    tx = np.asarray(x_mm, dtype=np.float64).reshape(-1)[both]
    ty = np.asarray(y_mm, dtype=np.float64).reshape(-1)[both]
    out: dict[str, Any] = {"n_samples": int(both.sum())}
    for name, p in preds.items():
        out[name] = {"rmse_x_mm": _rmse(np.asarray(p["x_mm"], dtype=np.float64).reshape(-1)[both] - tx),
                     "rmse_y_mm": _rmse(np.asarray(p["y_mm"], dtype=np.float64).reshape(-1)[both] - ty)}
    return out


def press_delays(pred_contact: np.ndarray, contact: np.ndarray, t_s: np.ndarray,
                 press_id: np.ndarray, keep: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Onset and release delays (ms) of every press of ONE continuous recording.

    A press is a run of equal ``press_id`` holding at least one true-contact sample; its true
    onset is its first true-contact sample and its true release the sample after its last one
    (load-cell flicker around the threshold inside a press does not split it).

    - Onset: if the prediction is off at the true onset, the first predicted-contact sample
      up to the true release minus the onset (> 0, late); if it is already on, the start of
      that predicted run (not before the press's first sample) minus the onset (<= 0, early).
    - Release: if the prediction is still on at the last true-contact sample, the first
      predicted no-contact sample after it (searched until the next press's true onset or the
      end of the recording) minus the true release (>= 0, late); otherwise the sample after
      the last predicted-contact sample within the press's contact minus the true release
      (< 0, early).

    A press with no predicted contact between its true onset and release is missed: both
    delays are NaN.

    Parameters
    ----------
    pred_contact, contact
        (n,) predicted and true contact of the recording, in time order.
    t_s
        (n,) sample times; the sample period is their median difference.
    press_id
        (n,) press of every sample.
    keep
        (n,) only presses whose true onset sample is kept are returned (a split's rows).

    Returns
    -------
    onset_ms, release_ms
        One entry per press (NaN where missed).
    """
    pc = np.asarray(pred_contact, bool).reshape(-1)
    tc = np.asarray(contact, bool).reshape(-1)
    pid = np.asarray(press_id).reshape(-1)
    n = tc.size
    if n < 2:
        return np.empty(0), np.empty(0)
    # The period to the nanosecond: time stamps tens of seconds into a log carry float error
    # in the last digits (1.000000000057 ms at 1 kHz), which turned a 12-sample onset into
    # more than 12 ms.
    dt_ms = float(np.round(np.median(np.diff(np.asarray(t_s, dtype=np.float64))) * 1e9)) / 1e6
    seg_starts = np.concatenate([[0], np.flatnonzero(pid[1:] != pid[:-1]) + 1])
    seg_ends = np.concatenate([seg_starts[1:], [n]])
    presses = []
    for a, b in zip(seg_starts, seg_ends):
        on = np.flatnonzero(tc[a:b])
        if on.size:
            presses.append((a, a + on[0], a + on[-1] + 1))
    onsets, releases = [], []
    for k, (seg_a, t_on, t_off) in enumerate(presses):
        if keep is not None and not keep[t_on]:
            continue
        inside = np.flatnonzero(pc[t_on:t_off])
        if inside.size == 0:
            onsets.append(np.nan)
            releases.append(np.nan)
            continue
        if pc[t_on]:
            off_before = np.flatnonzero(~pc[seg_a:t_on])
            start = seg_a + (off_before[-1] + 1 if off_before.size else 0)
        else:
            start = t_on + inside[0]
        onsets.append((start - t_on) * dt_ms)
        if pc[t_off - 1]:
            limit = presses[k + 1][1] if k + 1 < len(presses) else n
            off_after = np.flatnonzero(~pc[t_off:limit])
            stop = t_off + (off_after[0] if off_after.size else limit - t_off)
        else:
            stop = t_on + inside[-1] + 1
        releases.append((stop - t_off) * dt_ms)
    return np.asarray(onsets, dtype=np.float64), np.asarray(releases, dtype=np.float64)


def timing_summary(onset_ms: np.ndarray, release_ms: np.ndarray) -> dict[str, Any]:
    """``contact_timing``: presses, missed presses, and mean / median / 90th percentile / max
    of the onset and release delays (ms) over the presses that were detected."""
    onset = np.asarray(onset_ms, dtype=np.float64)
    release = np.asarray(release_ms, dtype=np.float64)
    found = np.isfinite(onset)

    def stats(d: np.ndarray) -> dict[str, float | None]:
        if not d.size:
            return {"mean": None, "median": None, "p90": None, "max": None}
        return {"mean": float(np.mean(d)), "median": float(np.median(d)),
                "p90": float(np.percentile(d, 90)), "max": float(np.max(d))}

    return {"presses": int(onset.size), "missed_presses": int((~found).sum()),
            "onset_delay_ms": stats(onset[found]), "release_delay_ms": stats(release[found])}


def from_dataset(pred: Mapping[str, np.ndarray], ds: Any, **kwargs: Any) -> dict[str, Any]:
    """:func:`compute` with the ground truth of a ``fbgforce.recordings.dataset.Dataset``."""
    return compute(pred, ds.contact, ds.force_N, ds.x_mm, ds.y_mm, **kwargs)


def headline(metrics: Mapping[str, Any]) -> str:
    """One line for progress bars and logs, e.g. ``acc 98.7% F 1.02 N x 0.41 y 0.88 mm``."""
    def fmt(v: Any, spec: str) -> str:
        return "-" if v is None else format(v, spec)
    acc = metrics.get("contact_accuracy")
    return (f"acc {fmt(None if acc is None else 100 * acc, '.1f')}% "
            f"F {fmt(metrics.get('rmse_force_N'), '.2f')} N "
            f"x {fmt(metrics.get('rmse_x_mm'), '.2f')} y {fmt(metrics.get('rmse_y_mm'), '.2f')} mm")


def few_presses_warning(split: str, n_presses: int) -> str | None:
    """The warning for a ``split`` ("test", "val") scored on ``n_presses`` presses, or None
    when they are at least :data:`MIN_SPLIT_PRESSES`."""
    if n_presses >= MIN_SPLIT_PRESSES:
        return None
    return (f"the {split} split holds {n_presses} press{'es' if n_presses != 1 else ''} "
            f"(fewer than {MIN_SPLIT_PRESSES}): its metrics rest on too little data; record "
            "more presses (the split is 8:1:1 by press) or score other recordings")
