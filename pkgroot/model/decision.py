"""The contact decision over time and its calibration: the rule every engine runs after the
contact net (the C runtimes' ``contact_decision``), a Schmitt trigger with a count or a
one-sided CUSUM on the net's margin, and how the trainer sets either from the calibration's
rests (docs/runtime.md, "In use")."""
from __future__ import annotations

import math
import statistics
from typing import Any, Sequence

import numpy as np

from fbgforce import contract

#: The decision's rise threshold: :data:`REST_MARGIN_FACTOR` times this quantile of the contact
#: net's margin at rest in the calibration data, its synthetic long rests included
#: (docs/runtime.md, "In use").
REST_MARGIN_QUANTILE = 0.9999
#: A calibration's rests end within half a second of a release, where the margin is still
#: rising out of the release; in use rests last seconds, and 0.2-1.5 s after a release, as the
#: load signal's averages settle, it comes higher than any calibration rest shows (on the
#: hours-of-use run, docs/robustness.md: 3.8 false events per minute at the quantile itself,
#: 1.2 at 1.5 times it, 0.5 at twice it).
REST_MARGIN_FACTOR = 2.0
#: How long the rise condition must hold, s: 3 samples at 1 kHz. On fault-free logs one
#: sample past a threshold set on settled rests is nearly as quiet and 3 ms faster, but the
#: count also rides out the few samples a burst of lost peaks disturbs (docs/tradeoff.md).
RISE_S = 0.003
#: The CUSUM threshold's floor, in samples at the drift: ``h`` is at least this many times
#: ``max(k, 0.5)`` (with ``hi = k + h / 2`` no single sample rises even at the floor). One
#: sample, not the Schmitt trigger's three: on a calibration whose rests hold a release's tail
#: the drift comes out near 3 and three samples of it, not the rests, set the threshold; at
#: one sample the family's worst member found contact 0-3 ms sooner, with as few false events
#: (docs/robustness.md, "A calibration through a few kelvin").
CUSUM_FLOOR_SAMPLES = 1.0
#: Largest magnitude of every CUSUM value of :class:`~fbgforce.model.artifact.InUse` (margin
#: units): the contract's
#: ``MAX_CUSUM_Q8`` in Q8.
CUSUM_MAX = contract.LIMIT["MAX_CUSUM_Q8"] / 256.0
#: The CUSUM rise's false events per minute at rest that :func:`cusum_parameters` aims at on
#: the calibration's rests extended (:func:`extended_rests`): an average run length at rest of
#: 2 minutes, half the goal of 1 per minute. Aimed at 0.3, the family's 5 pm members found
#: contact up to 2 ms later on a 100-press calibration, for a worst rate of 0.35 against 0.53
#: a minute on a 60-press one (docs/tradeoff.md, "A short calibration's rests").
CUSUM_FALSE_PER_MIN = 0.5
#: The drifts :func:`cusum_parameters` tries above the rests' quantile, margin units: steps of
#: this up to :data:`CUSUM_DRIFT_MAX`. Past the quantile a higher drift lets rest noise add
#: less, so a lower threshold holds the same false events; which finds presses sooner depends
#: on how the margin rises, which the calibration's presses show.
CUSUM_DRIFT_STEP = 0.25
#: The highest drift :func:`cusum_parameters` tries (margin units; the contact net's margin at
#: rest spreads about 2, under contact it reaches 10 and more).
CUSUM_DRIFT_MAX = 4.0
#: Synthetic long rests whose median margin lies above this quantile of the calibration's rests
#: are not rest to the contact net (a net that never learned them, a calibration whose rests
#: wander off the zero they are made at) and cannot set the threshold: on such a calibration
#: they asked for an ``h`` of 800,000, no press rose, and the tracker took the loads for drift.
LONG_REST_BODY_QUANTILE = 0.99
#: Fewest excursion peaks for the tail fit above their 90th percentile (fewer: all of them).
CUSUM_TAIL_MIN = 20
#: A calibration holds a few tenths of a minute of rest in pieces under a second long; a
#: false-event rate of half a minute is set on minutes of rest that :func:`extended_rests`
#: simulates from them: this many (30 events at the aim, to fit and to count).
REST_EXTEND_MINUTES = 60.0
#: The rest margins' upper tail is modelled as exponential above this quantile of them
#: (:func:`extended_rests`): on a 60-press calibration (0.19 min of rest) the fit read the
#: rate of margins above 1 and 3 within a factor 1.7 of six minutes of rest in use, where
#: the samples themselves reached 1.8 and in use 5.3.
REST_TAIL_QUANTILE = 0.99
#: Order of the autoregression of the rest margins' normal scores (:func:`extended_rests`).
REST_AR_ORDER = 3
#: Seed of :func:`extended_rests`' draws: one calibration always sets one decision.
REST_EXTEND_SEED = 0
#: Consecutive samples of the margin at or below 0 before contact is released inside the
#: decision's hold (the contract's, as the C runtimes read it).
RELEASE_DWELL = contract.LIMIT["RELEASE_DWELL"]


def decide_over_time(raw: np.ndarray, margin: np.ndarray, on: float, off: float, rise_n: int,
                     state: list[Any], cusum: tuple[float, float, float, float] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The contact decision over time on consecutive samples, in any units of the margin.

    The decision holds while ``raw`` (the net's own decision) or ``margin > off``. Within a
    hold, contact is shown until ``raw`` or ``margin > 0`` has failed on ``RELEASE_DWELL``
    consecutive samples (the contract's; a count kept in the state); from there to the hold's
    end (the release band, where ``off < 0``) it is not, the force and location still follow
    the falling load, and contact shows again only by a new rise. It rises by one of two
    rules, which run out of the hold and in the release band, never on the sample the hold ends
    or contact is released. With ``cusum`` None or its threshold ``h`` 0: after ``rise_n``
    consecutive samples with ``raw`` and ``margin >= on`` (a Schmitt trigger with a count).
    Else ``cusum = (h, k, lo, hi)``, a one-sided CUSUM: ``S = max(0, S + clip(margin, lo, hi)
    - k)``, contact rises when ``S >= h`` and ``S`` restarts at 0 (it stays 0 while contact is
    shown). ``state`` is ``[decision, rise_run, S, released, release_run]`` of the previous
    sample, carried and updated. Integer arguments give the integer rule exactly (Python
    integers); the C runtimes run this rule (``fbg_contact_decision`` in fbg_stage_decision.c,
    ``fbgf_contact_decision`` in fbgf_float.c).

    Returns
    -------
    tuple
        ``(contact, held)``, bool (n,) each: the contact shown, and the decision held (contact
        and its release band), on which the force, the location, the settled-hold gain and the
        tracker's rests run.
    """
    raw = np.asarray(raw, dtype=bool)
    contact = np.zeros(raw.size, dtype=bool)
    held = np.zeros(raw.size, dtype=bool)
    decision, rise, s, released, release_run = state
    h, k, lo, hi = cusum if cusum is not None else (0, 0, 0, 0)
    for i, (r, mg) in enumerate(zip(raw.tolist(), np.asarray(margin).tolist())):
        if decision and not (r or mg > off):
            decision = released = release_run = 0
        elif decision and not released:
            release_run = 0 if (r or mg > 0) else release_run + 1
            if release_run >= RELEASE_DWELL:
                released, release_run = 1, 0
        else:
            if h:
                s = max(s + (min(max(mg, lo), hi) - k), 0)
                rises = s >= h
                if rises:
                    s = 0
            else:
                rise = min(rise + 1, 255) if (r and mg >= on) else 0
                rises = rise >= rise_n
                if rises:
                    rise = 0
            if rises:
                decision, released = 1, 0
        held[i] = decision
        contact[i] = decision and not released
    state[:] = [decision, rise, s, released, release_run]
    return contact, held


def cusum_path(margins: np.ndarray, k: float, lo: float = -CUSUM_MAX, hi: float = CUSUM_MAX
               ) -> np.ndarray:
    """S of the CUSUM rise over consecutive margins, never rising (no threshold): ``S_t =
    max(0, S_{t-1} + clip(m_t, lo, hi) - k)``, from ``S = 0``, in closed form (Lindley: the
    walk of the increments less its running minimum, 0 included)."""
    # In place: the trainer runs this over an hour of samples for each drift it tries.
    s = np.clip(np.asarray(margins, dtype=np.float64).ravel(), lo, hi)
    s -= k
    np.cumsum(s, out=s)
    low = np.minimum.accumulate(s)
    np.minimum(low, 0.0, out=low)
    s -= low
    return s


def cusum_peaks(margins: np.ndarray, k: float, lo: float = -CUSUM_MAX, hi: float = CUSUM_MAX
                ) -> np.ndarray:
    """The highest S of each excursion of :func:`cusum_path` above 0: a CUSUM with threshold
    ``h`` raises one false event per excursion whose peak reaches ``h``."""
    return _peaks_of_path(cusum_path(margins, k, lo, hi))


def _peaks_of_path(s: np.ndarray) -> np.ndarray:
    """The highest value of each run of a CUSUM path above 0."""
    up = s > 0
    if not up.any():
        return np.empty(0)
    starts = np.flatnonzero(up[1:] & ~up[:-1]) + 1
    if up[0]:
        starts = np.concatenate([[0], starts])
    # S is 0 between excursions, so each start's stretch up to the next peaks where its
    # excursion does.
    return np.maximum.reduceat(s, starts)


def cusum_false_rate(peaks: np.ndarray, minutes: float, h: float) -> float:
    """False events per minute at rest of a CUSUM with threshold ``h``, estimated from the
    excursion peaks (:func:`cusum_peaks`) of ``minutes`` of rest: the peaks' upper tail as an
    exponential, ``rate(h) = r_u exp(-(h - u) / beta)`` (a random walk with a negative drift
    has excursion maxima with such a tail), ``u`` the peaks' 90th percentile (0 with fewer than
    :data:`CUSUM_TAIL_MIN` peaks), ``r_u`` the rate of the peaks above it, ``beta`` their mean
    excess. Past the highest observed peak only the fit counts; below it, the larger of the
    fit and the observed rate."""
    p = np.asarray(peaks, dtype=np.float64)
    if not p.size or minutes <= 0:
        return 0.0
    u = float(np.quantile(p, 0.9)) if p.size >= CUSUM_TAIL_MIN else 0.0
    tail = p[p > u]
    if not tail.size:
        return 0.0
    rate_u, beta = tail.size / minutes, max(float(np.mean(tail - u)), 1e-12)
    fit = rate_u * float(np.exp(-(h - u) / beta)) if h > u else rate_u
    return max(fit, float(np.sum(p >= h)) / minutes)


def _normal_scores(values: np.ndarray) -> np.ndarray:
    """The normal quantiles of the values' ranks (ties by order)."""
    n = values.size
    inv = statistics.NormalDist().inv_cdf
    grid = np.array([inv((r + 0.5) / n) for r in range(n)])
    ranks = np.empty(n, dtype=np.int64)
    ranks[np.argsort(values, kind="stable")] = np.arange(n)
    return grid[ranks]


def _autoregression(z: np.ndarray, order: int) -> tuple[np.ndarray, float]:
    """Yule-Walker coefficients of an AR(``order``) of ``z`` and its innovations' variance
    relative to ``z``'s (a stationary process: the biased autocorrelation is positive
    definite)."""
    zc = z - z.mean()
    energy = float(zc @ zc)
    acf = np.array([float(zc[:zc.size - lag] @ zc[lag:]) / energy for lag in range(order + 1)])
    toeplitz = acf[np.abs(np.subtract.outer(np.arange(order), np.arange(order)))]
    phi = np.linalg.solve(toeplitz, acf[1:])
    return phi, max(float(1.0 - phi @ acf[1:]), 1e-12)


def _ar_noise(phi: np.ndarray, innovation_var: float, n: int, rng: np.random.Generator
              ) -> np.ndarray:
    """``n`` samples of the stationary AR process ``phi``, standardised: white noise through
    the process's impulse response (cut where it has decayed to 1e-9), by FFT."""
    taps = [1.0]
    while len(taps) < 200_000:
        nxt = sum(c * taps[-1 - j] for j, c in enumerate(phi) if len(taps) - 1 - j >= 0)
        taps.append(nxt)
        if len(taps) > 2 * phi.size and max(abs(t) for t in taps[-phi.size - 1:]) < 1e-9:
            break
    h = np.asarray(taps)
    white = rng.normal(0.0, math.sqrt(innovation_var), n + h.size)
    size = 1 << int(np.ceil(np.log2(white.size + h.size)))
    out = np.fft.irfft(np.fft.rfft(white, size) * np.fft.rfft(h, size), size)[h.size:h.size + n]
    return out / out.std()


def _interp_on_grid(x: np.ndarray, grid: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``np.interp(x, grid, values)`` bit for bit on finite ``x``, for an evenly spaced
    ``grid`` (a ``linspace``): the interval from the spacing, corrected by one comparison each
    way, instead of a search through ``grid`` (0.12 s against 0.2 s on an hour of samples)."""
    last = grid.size - 1
    step = (grid[last] - grid[0]) / last
    j = np.clip(np.floor((x - grid[0]) / step), 0, last - 1).astype(np.int64)
    j -= (j > 0) & (grid[j] > x)
    j += (j < last - 1) & (grid[j + 1] <= x)
    slope = (values[1:] - values[:-1]) / (grid[1:] - grid[:-1])
    out = slope[j] * (x - grid[j]) + values[j]
    out = np.where(x == grid[j], values[j], out)
    out = np.where(x < grid[0], values[0], out)
    return np.where(x >= grid[last], values[last], out)


def _interp_on_ranks(x: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``np.interp(x, np.arange(values.size), values)`` bit for bit, by the integer part of
    ``x`` instead of a search through ``values`` (a third of the time on an hour of
    samples)."""
    last = values.size - 1
    if last < 1:
        return np.full(x.shape, values[0] if values.size else np.nan)
    j = np.clip(np.floor(x), 0, last - 1).astype(np.int64)
    slope = values[1:] - values[:-1]
    out = slope[j] * (x - j) + values[j]
    out = np.where(x == j, values[j], out)
    out = np.where(x < 0, values[0], out)
    return np.where(x >= last, values[last], out)


def extended_rests(rest_margins: np.ndarray, sample_rate_hz: float = 1000.0,
                   minutes: float = REST_EXTEND_MINUTES) -> np.ndarray:
    """``minutes`` of rest margins like the calibration's, for a false-event rate its own
    rests are too short to show; the rests themselves when they are that long already, or
    when fewer than :data:`CUSUM_TAIL_MIN` of them lie above their
    :data:`REST_TAIL_QUANTILE` quantile to model the tail on.

    The margins' ranks become normal scores, an AR(:data:`REST_AR_ORDER`) fitted to those is
    run for ``minutes`` (seed :data:`REST_EXTEND_SEED`), and its scores are mapped back
    through the margins' distribution: their own quantiles below
    :data:`REST_TAIL_QUANTILE`, above it an exponential tail with their mean excess there. So
    the simulated rests keep the margins' spread and how long an excursion lasts, and reach
    the margins a calibration's fraction of a minute never shows: a CUSUM set on the rests
    alone, their few excursions below its threshold, raised 1.8 false events a minute in use
    (docs/tradeoff.md, "A short calibration's rests").
    """
    rest = np.asarray(rest_margins, dtype=np.float64).ravel()
    rest = rest[np.isfinite(rest)]
    n_out = int(round(minutes * 60.0 * sample_rate_hz))
    if rest.size >= n_out or rest.size * (1.0 - REST_TAIL_QUANTILE) < CUSUM_TAIL_MIN:
        return rest
    u = float(np.quantile(rest, REST_TAIL_QUANTILE))
    excess = rest[rest > u] - u
    if excess.size < CUSUM_TAIL_MIN:   # ties at the quantile: no tail to fit
        return rest
    phi, innovation_var = _autoregression(_normal_scores(rest), REST_AR_ORDER)
    z = _ar_noise(phi, innovation_var, n_out, np.random.default_rng(REST_EXTEND_SEED))
    # Upper tail probabilities of the simulated scores, from a table of erfc (exact far out).
    grid = np.linspace(-8.0, 8.0, 3201)
    log_upper = np.log([0.5 * math.erfc(g / math.sqrt(2.0)) for g in grid])
    upper = np.exp(_interp_on_grid(z, grid, log_upper))
    ordered = np.sort(rest)
    body = _interp_on_ranks((1.0 - upper) * rest.size - 0.5, ordered)
    beta = float(np.mean(excess))
    tail = u + beta * (np.log(1.0 - REST_TAIL_QUANTILE) - np.log(upper))
    return np.where(upper < 1.0 - REST_TAIL_QUANTILE, tail, body)


class _Excursions:
    """Rest margins and the CUSUM excursions of their lowest drift ``k0``, for the peaks of
    every drift at or above it (:meth:`peaks`, :func:`cusum_peaks`' on the same margins).

    A higher drift's ``S`` is 0 wherever ``k0``'s is, so its excursions lie within ``k0``'s,
    and each of those starts from ``S = 0``: the drift grid the trainer searches scans those
    stretches, a few thousand samples, instead of the hour :func:`extended_rests` makes. Each
    stretch is its own row (padded with the clip's floor, where ``S`` is 0), so its walk sums
    only its own samples; the peaks are the whole series' to within its rounding. The drift
    chosen has its peaks walked over the whole series (:meth:`exact_peaks`): a threshold set
    just above a peak sits as near it as the rounding, and a model trained through the
    tracker follows which side of it the calibration's own excursions fall."""

    def __init__(self, margins: np.ndarray, k0: float) -> None:
        self.margins = np.asarray(margins, dtype=np.float64).ravel()
        self.k0 = float(k0)
        s = cusum_path(self.margins, self.k0)
        self.lowest = _peaks_of_path(s)
        self._exact: dict[float, np.ndarray] = {}
        up = np.r_[False, s > 0, False]
        starts = np.flatnonzero(up[1:] & ~up[:-1])
        lengths = np.flatnonzero(~up[1:] & up[:-1]) - starts
        self.rows: np.ndarray | None = None
        # No excursion at k0 leaves none at any higher drift: no rows, nothing to walk.
        width = int(lengths.max()) + 1 if lengths.size else 1
        if starts.size * width <= self.margins.size:
            rows = np.full((starts.size, width), -CUSUM_MAX)
            row = np.repeat(np.arange(starts.size), lengths)
            col = np.arange(row.size) - np.repeat(np.cumsum(lengths) - lengths, lengths)
            rows[row, col] = np.clip(self.margins[starts[row] + col], -CUSUM_MAX, CUSUM_MAX)
            self.rows = rows

    def exact_peaks(self, k: float) -> np.ndarray:
        """:func:`cusum_peaks` of the margins at drift ``k``, bit for bit."""
        if k == self.k0:
            return self.lowest
        if k not in self._exact:
            self._exact[k] = cusum_peaks(self.margins, k)
        return self._exact[k]

    def peaks(self, k: float) -> np.ndarray:
        """:func:`cusum_peaks` of the margins at drift ``k`` to within the rounding of its walk
        over the whole series (the whole series below ``k0``, or where the stretches would take
        more room than it)."""
        if k == self.k0:
            return self.lowest
        if k < self.k0 or self.rows is None:
            return cusum_peaks(self.margins, k)
        walk = np.cumsum(self.rows - k, axis=1)
        low = np.minimum.accumulate(walk, axis=1)
        np.minimum(low, 0.0, out=low)
        walk -= low
        walk[:, -1] = 0.0          # the pad: no excursion runs on into the next row
        return _peaks_of_path(walk.ravel())


def _cusum_threshold(peaks: np.ndarray, minutes: float, own: np.ndarray, k: float,
                     target: float) -> float:
    """The least ``h`` at which the CUSUM of drift ``k`` raises at most ``target`` false events
    a minute on ``minutes`` of rests :func:`extended_rests` made of ``own``, whose excursions
    peak at ``peaks``: where the exponential fit of the peaks above their 90th percentile, and
    their count where there are more than it says, fall to ``target``; above every peak of
    ``own`` and at least :data:`CUSUM_FLOOR_SAMPLES` samples at ``max(k, 0.5)``."""
    h = CUSUM_FLOOR_SAMPLES * max(k, 0.5)
    own_peaks = cusum_peaks(own, k)
    if own_peaks.size:
        h = max(h, float(np.nextafter(own_peaks.max(), np.inf)))
    if peaks.size and minutes > 0:
        u = float(np.quantile(peaks, 0.9)) if peaks.size >= CUSUM_TAIL_MIN else 0.0
        tail = peaks[peaks > u]
        if tail.size and tail.size / minutes > target:
            beta = max(float(np.mean(tail - u)), 1e-12)
            h = max(h, u + beta * float(np.log(tail.size / minutes / target)))
        # Where the peaks' tail is heavier than the fit, their count itself is the bound.
        h = max(h, _above_all_but(peaks, int(target * minutes)))
    return min(h, CUSUM_MAX)


def _above_all_but(peaks: np.ndarray, allowed: int) -> float:
    """The least ``h`` that at most ``allowed`` of the excursion ``peaks`` reach (0 when there
    are no more than that many)."""
    if peaks.size <= allowed:
        return 0.0
    return float(np.nextafter(np.sort(peaks)[-(allowed + 1)], np.inf))


def idle_threshold(draws: Sequence[np.ndarray], k: float, target: float,
                   sample_rate_hz: float) -> float:
    """The least ``h`` at which the CUSUM of drift ``k`` raises at most
    ``floor(target * minutes)`` false events on each of the idle pads ``draws`` (the contact
    net's margins on each, in time order; 0 without).

    An idle pad's rest does not extend as the calibration's do: its memory's play operators
    follow the noise's record low, so a contact net that reads them (``fbgforce train
    --contact-plays on``) reads a margin that creeps up with the log of the rest's length
    (docs/robustness.md, "An idle pad"), and a threshold read on rests of seconds extended to
    an hour sits below what a pad left alone for minutes reaches. So each draw is scored as
    it is, whole, and the worst one counts. Unclipped, as the rests' peaks are: the clip only
    lowers them."""
    h = max([_above_all_but(cusum_peaks(margins, k),
                            int(target * np.size(margins) / sample_rate_hz / 60.0))
             for margins in draws], default=0.0)
    return min(h, CUSUM_MAX)


def mean_onset_samples(presses: Sequence[tuple[np.ndarray, int]], h: float, k: float,
                       lo: float, hi: float) -> float:
    """Mean delay, in samples, from each press's first labelled contact sample to the CUSUM's
    rise (``S`` from 0 at the window's start; a window that never rises counts its length
    after the label). ``presses``: ``(margins, label)``, the contact net's margins over a
    window around one press and the index of its first labelled contact sample in it."""
    delays = []
    for margins, label in presses:
        crossed = np.flatnonzero(cusum_path(margins, k, lo, hi) >= h)
        delays.append((crossed[0] if crossed.size else margins.size) - label)
    return float(np.mean(delays)) if delays else 0.0


def cusum_parameters(rest_margins: np.ndarray, sample_rate_hz: float = 1000.0,
                     contact_margins: np.ndarray | None = None,
                     false_per_min: float | None = None, k: float | None = None,
                     long_rests: np.ndarray | None = None,
                     presses: Sequence[tuple[np.ndarray, int]] | None = None,
                     idle: Sequence[np.ndarray] = ()) -> dict[str, float]:
    """The CUSUM rise the trainer sets from the calibration's rests (docs/runtime.md, "In
    use").

    ``h`` for a drift ``k``: the least threshold at which the false events at rest stay at
    ``false_per_min`` (:data:`CUSUM_FALSE_PER_MIN`, an average run length at rest of 2
    minutes) on the calibration's rests extended to :data:`REST_EXTEND_MINUTES`
    (:func:`extended_rests`) and, given ``long_rests`` (the net's margins on every sample of
    synthetic long rests, in time order), on those extended alike: the larger of the two
    (:func:`_cusum_threshold`); long rests whose median lies above the rests'
    :data:`LONG_REST_BODY_QUANTILE` quantile are left out; given ``idle`` (its margins on
    idle pads, one array each, :func:`idle_threshold`), at least what keeps each of those
    within the aim, unless even at the highest drift tried that lies past the CUSUM's peak
    on half of ``presses``: then the net reads a long rest as contact, which no threshold
    mends (a calibration whose rests never lasted), and they are left out. ``k``, unless given: the rests'
    :data:`REST_MARGIN_QUANTILE` quantile ``q`` (the level rest noise almost never passes; at least 0); given ``presses``
    (:func:`mean_onset_samples`), the drift of ``q`` and the grid of :data:`CUSUM_DRIFT_STEP`
    up to :data:`CUSUM_DRIFT_MAX` above it whose ``h`` finds those presses soonest on average
    (ties: the lower ``h``); given ``contact_margins`` whose 10th percentile lies above ``q``
    (and no ``presses``), the midpoint of the two. ``hi = k + h / 2``: no single sample
    raises contact, and the clip only lowers the peaks the estimate counted; ``lo`` the
    contract's lowest (no clip).

    Returns ``h``, ``k``, ``lo``, ``hi`` (margin units), the fitted ``false_per_min`` at ``h``
    on the calibration's rests extended, the ``rest_minutes`` of the calibration, the
    ``extended_minutes`` it was read on, the ``long_minutes`` of ``long_rests`` (0 without,
    or left out), the ``idle_minutes`` of ``idle`` and the ``onset_samples`` of ``presses``
    at the choice (None without).
    """
    rest = np.asarray(rest_margins, dtype=np.float64).ravel()
    rest = rest[np.isfinite(rest)]
    target = CUSUM_FALSE_PER_MIN if false_per_min is None else float(false_per_min)
    long = np.empty(0) if long_rests is None else np.asarray(long_rests, np.float64).ravel()
    long = long[np.isfinite(long)]
    if long.size and rest.size and np.median(long) > np.quantile(rest, LONG_REST_BODY_QUANTILE):
        long = long[:0]
    idle = [np.asarray(m, np.float64).ravel() for m in idle]

    q = max(0.0, float(np.quantile(rest, REST_MARGIN_QUANTILE))) if rest.size else 0.0
    searched = k is None and bool(presses)
    if k is not None:
        grid = [float(k)]
    elif searched:
        grid = [q] + [CUSUM_DRIFT_STEP * i for i in range(1, int(CUSUM_DRIFT_MAX
                                                                / CUSUM_DRIFT_STEP) + 1)
                      if CUSUM_DRIFT_STEP * i > q]
    else:
        grid = [q]
        if contact_margins is not None and np.size(contact_margins):
            c10 = float(np.quantile(np.asarray(contact_margins, dtype=np.float64), 0.1))
            if c10 > q:
                grid = [0.5 * (q + c10)]
    grid = [float(np.clip(drift, -CUSUM_MAX, CUSUM_MAX)) for drift in grid]
    idle_h: dict[float, float] = {}     # by drift: the search and the final walk share them

    def idle_at(drift: float) -> float:
        if drift not in idle_h:
            idle_h[drift] = idle_threshold(idle, drift, target, sample_rate_hz)
        return idle_h[drift]

    if idle and presses and (idle_at(max(grid))
                             > np.median([cusum_path(m, max(grid)).max() for m, _ in presses])):
        idle = []
        idle_h.clear()
    series = [(_Excursions(extended_rests(own, sample_rate_hz), grid[0]), own)
              for own in (rest, long) if own is rest or own.size]

    minutes = series[0][0].margins.size / sample_rate_hz / 60.0

    def threshold(drift: float, exact: bool = False) -> float:
        """``h`` at ``drift``, the largest of the series' and the idle pads'; ``exact``: from
        the excursions walked over the whole hour, bit for bit what the grid's stretches give
        to within their rounding (the trainer's models are reproducible from one release to
        the next)."""
        return max([_cusum_threshold((ext.exact_peaks if exact else ext.peaks)(drift),
                                     ext.margins.size / sample_rate_hz / 60.0, own, drift,
                                     target) for ext, own in series]
                   + [idle_at(drift)])

    def onset(drift: float, h: float) -> float:
        """Mean onset of ``presses``, in samples, at ``drift`` and ``h``."""
        return mean_onset_samples(presses, h, drift, -CUSUM_MAX, min(drift + 0.5 * h, CUSUM_MAX))

    k = grid[0]
    if searched:
        # The drift that finds the presses soonest, by the stretches (ties: the lower h); then
        # its threshold, and so the presses' onset, on the whole hour.
        scored = []
        for drift in grid:
            h = threshold(drift)
            scored.append((onset(drift, h), h, drift))
        k = min(scored)[2]
    h = threshold(k, exact=True)
    return {"h": h, "k": k, "lo": -CUSUM_MAX, "hi": min(k + 0.5 * h, CUSUM_MAX),
            "false_per_min": cusum_false_rate(series[0][0].exact_peaks(k), minutes, h),
            "rest_minutes": rest.size / sample_rate_hz / 60.0, "extended_minutes": minutes,
            "long_minutes": long.size / sample_rate_hz / 60.0,
            "idle_minutes": sum(np.size(m) for m in idle) / sample_rate_hz / 60.0,
            "onset_samples": onset(k, h) if searched else None}
