"""The stage/load-cell log (:class:`StageLog`) and its clock aligned to the interrogator's
(:func:`align`, step 2 of :func:`fbgforce.recordings.labimport.import_logs`):
``t_stage = t_fbg + offset + drift (t_fbg - t_fbg[0])``. A coarse normalised
cross-correlation of the load against the gratings' sum; each press timed on its loading and
unloading flanks (the gratings combined for that press by their gain over their noise, a gain
per flank so the pad's friction loop does not bias it) and a weighted straight line through the
presses, which gives the drift; the level from the pad's lag (a causal response of unknown
shape: non-negative shares of first-order lags of the load over a range of time constants)
fitted over the whole log together with it (docs/lab-import.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from fbgforce.errors import InputError
from fbgforce.recordings import dataset as fds

#: Default bound on the clock offset searched, s.
MAX_OFFSET_S = 10.0
#: The coarse alignment works on bins of this width, high-passed over :data:`HIGHPASS_S`.
COARSE_STEP_S = 0.01


HIGHPASS_S = 5.0
#: The two logs must share at least this long (or half the shorter log) at the offset found.
MIN_OVERLAP_S = 10.0
#: Refusals: coarse correlation below this; a second peak at least this fraction of the first.
MIN_CORRELATION = 0.5


AMBIGUOUS_RATIO = 0.9
#: Per-press refinement: search ± this around the running estimate, in steps of FINE_STEP_S,
#: on the flanks (below LOAD_FRACTION / UNLOAD_FRACTION of the press's peak) plus
#: FLANK_REST_S of rest.
FINE_WINDOW_S = 0.02


FINE_STEP_S = 0.0005


LOAD_FRACTION = 0.5


UNLOAD_FRACTION = 0.3


FLANK_REST_S = 0.06
#: The pad's lag: the gratings follow the load through a causal response of unknown shape,
#: modelled as the load itself plus first-order lags of it with these time constants (s), each
#: with a share fitted over the whole log together with the clock's level (searched over
#: ± LAG_SEARCH_S in steps of LAG_STEP_S around the plain flanks' line).
LAG_TIME_CONSTANTS_S = (0.03, 0.1, 0.3, 1.0)


LAG_SEARCH_S = 0.01


LAG_STEP_S = 0.0005
#: The creep the presses before left gets a scale of each press's own only where, at the
#: press's own scale, its sum of squares is at least this many times the press's noise
#: variance (:func:`_lag_fit`): a free scale on a tail the noise hides fits the noise.
TAIL_VISIBLE = 1.0
#: Presses lighter than this are not used to align (too little signal above the noise).
ALIGN_MIN_PEAK_N = 0.5


MIN_ALIGN_PRESSES = 3
#: The per-press offsets must sit on one straight line within this (weighted RMS), ms, with
#: at least half of them within 4 sd of it.
MAX_RESIDUAL_MS = 10.0
#: A per-press estimate's uncertainty is never taken below this, s (model error).
PRESS_SIGMA_FLOOR_S = 0.0003
#: Press numbering: contact runs closer than this merge into one press (load-cell chatter
#: around the threshold), and runs shorter than PRESS_MIN_S start no press.
PRESS_MERGE_GAP_S = 0.05
PRESS_MIN_S = 0.01
#: Contact is labelled above the dataset's threshold or this many standard deviations of the
#: load cell's noise, whichever is higher (:func:`contact_threshold`): at 5 a sample at rest
#: reads as contact once in 3.5 million.
LOAD_CELL_NOISE_SIGMAS = 5.0


@dataclass
class StageLog:
    """The stage/load-cell log on its own clock: time (s), force (N), position (mm, pad
    frame), and where each row came from (``line``: 1-based line of ``path``).

    ``time_flag``, ``force_flag`` and ``position_flag`` name the options that set the units,
    for the plausibility refusals (:func:`check_stage_units`)."""

    t: np.ndarray
    force_N: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    line: np.ndarray
    path: str = "<stage>"
    time_flag: str = "--stage-time-unit"
    force_flag: str = "--force-unit"
    position_flag: str = "--position-unit"

    def subset(self, keep: np.ndarray) -> "StageLog":
        """The rows where ``keep`` is True (a new log: its noise is measured again)."""
        return StageLog(t=np.ascontiguousarray(self.t[keep]), force_N=self.force_N[keep],
                        x_mm=self.x_mm[keep], y_mm=self.y_mm[keep], line=self.line[keep],
                        path=self.path, time_flag=self.time_flag, force_flag=self.force_flag,
                        position_flag=self.position_flag)

    @cached_property
    def noise_N(self) -> float:
        """The load cell's noise (standard deviation, N), from the second differences of the
        force: they cancel the slow loads of presses and rests alike, so their median absolute
        value is the noise's, whatever share of the log is pressed."""
        d2 = np.diff(np.asarray(self.force_N, dtype=np.float64), 2)
        return float(1.4826 * np.median(np.abs(d2)) / np.sqrt(6.0)) if d2.size else 0.0

    @property
    def contact_threshold_N(self) -> float:
        """:func:`contact_threshold` of this log's load cell."""
        return contact_threshold(self.noise_N)


def time_text(t: float) -> str:
    """A time as read (every digit float64 holds: an epoch clock's milliseconds included)."""
    return repr(float(t))


def label_contact(force_N: np.ndarray, threshold_N: float = fds.CONTACT_THRESHOLD_N
                  ) -> np.ndarray:
    """Contact where the load cell reads above ``threshold_N`` (default the dataset's rule;
    the import passes :func:`contact_threshold` of its load cell)."""
    return np.asarray(force_N) > threshold_N


def press_runs(t: np.ndarray, contact: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The presses' contact runs (start, stop exclusive): runs closer than
    :data:`PRESS_MERGE_GAP_S` merged, runs shorter than :data:`PRESS_MIN_S` left out."""
    starts, stops = runs(contact)
    if starts.size > 1:
        join = t[starts[1:]] - t[stops[:-1] - 1] < PRESS_MERGE_GAP_S
        keep_start = np.concatenate([[True], ~join])
        keep_stop = np.concatenate([~join, [True]])
        starts, stops = starts[keep_start], stops[keep_stop]
    long = t[stops - 1] - t[starts] >= PRESS_MIN_S
    return starts[long], stops[long]


@dataclass
class Alignment:
    """The stage clock against the interrogator's:
    ``t_stage = t_fbg + offset_s + drift * (t_fbg - t_ref_s)``.

    ``correlation`` is the coarse peak's normalised correlation, ``second_peak`` the best
    one outside its lobe; ``residual_ms`` the weighted RMS of the per-press offsets about the
    line; ``line_sd_ms`` the line's standard error at the log's ends, the larger (what the
    presses' scatter leaves uncertain in the drift and level; the lag's fit adds to it);
    ``lag_ms`` how far the pad's lag moved the clock's level from the flanks' line;
    ``lag_shares`` the fitted share of the load reaching the gratings through each lag of
    :data:`LAG_TIME_CONSTANTS_S`; ``press_offsets`` the per-press estimates on the flanks
    (fbg time, offset, sd, used on the line)."""

    offset_s: float
    drift: float
    t_ref_s: float
    correlation: float
    second_peak: float
    residual_ms: float
    line_sd_ms: float
    lag_ms: float
    presses_used: int
    presses_rejected: int
    lag_shares: tuple[float, ...] = ()
    press_offsets: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))

    def to_stage(self, t_fbg: np.ndarray) -> np.ndarray:
        """Interrogator times -> stage clock."""
        return t_fbg + self.offset_s + self.drift * (t_fbg - self.t_ref_s)

    def summary(self) -> dict[str, Any]:
        """The JSON form (docs/cli.md#import)."""
        return {"offset_s": self.offset_s, "drift_ppm": self.drift * 1e6,
                "correlation": self.correlation, "second_peak": self.second_peak,
                "residual_ms": self.residual_ms, "line_sd_ms": self.line_sd_ms,
                "lag_ms": self.lag_ms,
                "lag_shares": {f"{tau:g}": share for tau, share in
                               zip(LAG_TIME_CONSTANTS_S, self.lag_shares)},
                "presses_used": self.presses_used,
                "presses_rejected": self.presses_rejected}


def _binned(t: np.ndarray, v: np.ndarray, t0: float, n: int) -> np.ndarray:
    """Means of ``v`` in :data:`COARSE_STEP_S` bins from ``t0`` (empty bins interpolated),
    high-passed by subtracting a centred :data:`HIGHPASS_S` moving mean."""
    idx = np.clip(((t - t0) / COARSE_STEP_S).astype(np.int64), 0, n - 1)
    count = np.bincount(idx, minlength=n)
    mean = np.bincount(idx, v, minlength=n) / np.maximum(count, 1)
    full = count > 0
    if not full.all():
        k = np.arange(n)
        mean = np.interp(k, k[full], mean[full])
    w = max(1, int(round(HIGHPASS_S / COARSE_STEP_S)))
    c = np.concatenate([[0.0], np.cumsum(mean)])
    lo = np.clip(np.arange(n) - w // 2, 0, n)
    hi = np.clip(np.arange(n) + w // 2 + 1, 0, n)
    return mean - (c[hi] - c[lo]) / (hi - lo)


def _coarse(t_f: np.ndarray, proxy: np.ndarray, stage: StageLog, max_offset_s: float,
            where: str) -> tuple[float, float, float, float]:
    """Coarse offset (stage minus interrogator clock), its correlation, the second peak and
    the most negative correlation (a signal that falls under load)."""
    tf0, ts0 = float(t_f[0]), float(stage.t[0])
    nf = int((t_f[-1] - tf0) / COARSE_STEP_S) + 1
    ns = int((stage.t[-1] - ts0) / COARSE_STEP_S) + 1
    f = _binned(t_f, proxy, tf0, nf)
    s = _binned(stage.t, stage.force_N, ts0, ns)
    # Lag k pairs fbg bin i with stage bin i + k: offset = ts0 - tf0 + k * step.
    size = 1 << int(np.ceil(np.log2(nf + ns)))
    xy = np.fft.irfft(np.fft.rfft(s, size) * np.conj(np.fft.rfft(f, size)), size)
    ks = np.arange(-(nf - 1), ns)
    sxy = xy[ks % size]
    lo = np.maximum(0, -ks)
    hi = np.minimum(nf, ns - ks)
    m = (hi - lo).astype(np.float64)
    cf, cf2 = np.concatenate([[0.0], np.cumsum(f)]), np.concatenate([[0.0], np.cumsum(f * f)])
    cs, cs2 = np.concatenate([[0.0], np.cumsum(s)]), np.concatenate([[0.0], np.cumsum(s * s)])
    sf, sff = cf[hi] - cf[lo], cf2[hi] - cf2[lo]
    ss, sss = cs[hi + ks] - cs[lo + ks], cs2[hi + ks] - cs2[lo + ks]
    offsets = ts0 - tf0 + ks * COARSE_STEP_S
    shorter = min(nf, ns) * COARSE_STEP_S
    need = min(MIN_OVERLAP_S, 0.5 * shorter) / COARSE_STEP_S
    allowed = (np.abs(offsets) <= max_offset_s) & (m >= need)
    if not allowed.any():
        raise InputError(
            f"no overlap: the interrogator log covers {time_text(t_f[0])}-{time_text(t_f[-1])} s and the "
            f"stage log {time_text(stage.t[0])}-{time_text(stage.t[-1])} s on their clocks; with offsets up to "
            f"±{max_offset_s:g} s they share less than {need * COARSE_STEP_S:.3g} s "
            "(give a larger --max-offset-s if the clocks count from different origins)",
            path=where)
    with np.errstate(invalid="ignore", divide="ignore"):
        den = np.sqrt(np.maximum(sff - sf * sf / m, 0) * np.maximum(sss - ss * ss / m, 0))
        r = np.where(allowed & (den > 0), (sxy - sf * ss / m) / den, -np.inf)
    best = int(np.argmax(r))
    r1 = float(r[best])
    # The main lobe: out to where the correlation first falls below half the peak.
    a = best
    while a > 0 and r[a - 1] > 0.5 * r1:
        a -= 1
    b = best
    while b < r.size - 1 and r[b + 1] > 0.5 * r1:
        b += 1
    rest = np.concatenate([r[:a], r[b + 1:]])
    r2 = float(rest.max()) if rest.size and np.isfinite(rest.max()) else 0.0
    shift = 0.0
    if 0 < best < r.size - 1 and np.isfinite(r[best - 1]) and np.isfinite(r[best + 1]):
        den2 = r[best - 1] - 2 * r1 + r[best + 1]
        if den2 < 0:
            shift = 0.5 * (r[best - 1] - r[best + 1]) / den2
    lowest = float(np.min(np.where(np.isfinite(r), r, np.inf)))
    return float(offsets[best] + shift * COARSE_STEP_S), r1, max(r2, 0.0), lowest


@dataclass
class _Press:
    on_s: float     # stage clock
    off_s: float
    peak_s: float
    peak_N: float


def runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and stop (exclusive) indices of the runs of True."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def _stage_presses(stage: StageLog) -> list[_Press]:
    starts, stops = press_runs(stage.t, label_contact(stage.force_N, stage.contact_threshold_N))
    out = []
    for a, b in zip(starts, stops):
        k = a + int(np.argmax(stage.force_N[a:b]))
        out.append(_Press(float(stage.t[a]), float(stage.t[b - 1]), float(stage.t[k]),
                          float(stage.force_N[k])))
    return out


def first_order_lag(t: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """``x`` sampled at times ``t`` through a first-order lag of time constant ``tau_s``
    (``y' = (x - y) / tau``, starting at ``x[0]``; one backward step per interval, so
    irregular intervals are followed exactly for an input held over each interval).

    Vectorised in blocks short enough (:math:`300 \\tau`) that the exponential weights stay
    within floating point range."""
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    out = np.empty_like(x)
    decay = np.exp(-np.diff(t, prepend=t[0]) / tau_s)
    y = float(x[0])
    start = 0
    while start < t.size:
        stop = int(np.searchsorted(t, t[start] + 300.0 * tau_s, side="right"))
        stop = max(stop, start + 1)
        # y_n = E_n (y_prev + sum_k (1 - a_k) x_k / E_k), E_n = prod_{k <= n} a_k.
        e = np.exp(-(t[start:stop] - t[start]) / tau_s) * decay[start]
        out[start:stop] = e * (y + np.cumsum((1.0 - decay[start:stop]) * x[start:stop] / e))
        y = float(out[stop - 1])
        start = stop
    return out


def _press_signal(t: np.ndarray, strain: np.ndarray, force: np.ndarray) -> np.ndarray | None:
    """The four gratings combined for one press, in newtons: each grating's gain on the load
    (with a level and slope in time) over its noise variance weights it (the matched
    combination: a press near one support loads one grating most, and an equal sum would add
    the noise of the others). None when the gratings do not follow the load."""
    x = np.column_stack([np.ones(t.size), t - t[0], force])
    coef, *_ = np.linalg.lstsq(x, strain.astype(np.float64), rcond=None)
    resid = strain - x @ coef
    var = np.maximum((resid**2).sum(axis=0) / max(t.size - 3, 1), 1e-12)
    gain = coef[2]
    w = gain / var
    norm = float(w @ gain)
    if not np.isfinite(norm) or norm <= 0:
        return None
    return strain.astype(np.float64) @ (w / norm)


@dataclass
class _Window:
    """One press's interrogator samples used to time it: times, the combined gratings
    (:func:`_press_signal`), and the flanks' samples (loading, unloading) on the line."""

    t: np.ndarray
    signal: np.ndarray
    load: np.ndarray
    unload: np.ndarray


def _flanks(t_stage: np.ndarray, force: np.ndarray, press: _Press
            ) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the loading flank below :data:`LOAD_FRACTION` of the press's peak and the
    unloading flank below :data:`UNLOAD_FRACTION` (the rests beside them included), at the
    stage-clock times ``t_stage`` where the load is ``force``."""
    rising = t_stage <= press.peak_s
    return (rising & (force < LOAD_FRACTION * press.peak_N),
            ~rising & (force < UNLOAD_FRACTION * press.peak_N))


def _press_terms(t: np.ndarray, tail: np.ndarray | None = None) -> np.ndarray:
    """An orthonormal basis (columns) of what a press's gratings read besides its own load:
    a level and a slope in time (temperature) and, when given, ``tail``: the creep the
    presses before left in the pad (left at another place, so at a scale of its own)."""
    el = t - t[0]
    cols = np.column_stack([np.ones(t.size), el / max(float(el[-1]), 1e-9),
                            *(() if tail is None else (tail,))])
    u, sv, _ = np.linalg.svd(cols, full_matrices=False)
    return u[:, sv > 1e-9 * sv[0]]


def _fine(t: np.ndarray, signal: np.ndarray, stage: StageLog, press: _Press, tau0: float
          ) -> tuple[float, float] | None:
    """One press's offset (stage minus interrogator clock) near ``tau0`` and its sd, from its
    loading flank below :data:`LOAD_FRACTION` of its peak and its unloading flank below
    :data:`UNLOAD_FRACTION` with the rests beside them: a gain per flank (so the pad's
    friction loop does not bias it) and one level and slope in time; None when the best
    offset lies on the edge of the search or the press holds too little signal."""
    if t.size < 10:
        return None
    steps = np.arange(-FINE_WINDOW_S, FINE_WINDOW_S + FINE_STEP_S / 2, FINE_STEP_S)
    taus = tau0 + steps
    force = np.interp(t[None, :] + taus[:, None], stage.t, stage.force_N)
    load, unload = _flanks(t + tau0, force[steps.size // 2], press)
    if load.sum() < 5 or unload.sum() < 5:
        return None
    sel = load | unload
    # One level and slope in time over the press (temperature, the creep of the press
    # before), set by the rests on both sides, and one gain per flank (the pad's loop). They
    # are projected out of both sides, leaving a 2x2 problem per offset. (The lag's own
    # terms would take the lag out here too, at the cost of most of each press's precision:
    # the drift keeps it, the level is left to _lag_fit.)
    basis = _press_terms(t[sel])
    y = signal[sel] - basis @ (basis.T @ signal[sel])
    cols = []
    for m in (load[sel], unload[sel]):
        x = np.where(m[None, :], force[:, sel], 0.0)
        x -= (x @ basis) @ basis.T
        cols.append(x)
    g11, g22 = (cols[0] ** 2).sum(axis=1), (cols[1] ** 2).sum(axis=1)
    g12 = (cols[0] * cols[1]).sum(axis=1)
    h1, h2 = cols[0] @ y, cols[1] @ y
    det = g11 * g22 - g12 * g12
    if (det <= 1e-12 * np.maximum(g11 * g22, 1e-300)).any():
        return None
    rss = float(y @ y) - (g22 * h1 * h1 - 2 * g12 * h1 * h2 + g11 * h2 * h2) / det
    n_used = int(sel.sum())
    k = int(np.argmin(rss))
    if k == 0 or k == taus.size - 1:
        return None
    curv = (rss[k - 1] - 2 * rss[k] + rss[k + 1]) / FINE_STEP_S**2
    if curv <= 0:
        return None
    shift = 0.5 * (rss[k - 1] - rss[k + 1]) / (rss[k - 1] - 2 * rss[k] + rss[k + 1])
    sigma2 = max(rss[k], 0.0) / max(n_used - basis.shape[1] - 2, 1)
    return float(taus[k] + shift * FINE_STEP_S), float(np.sqrt(2 * sigma2 / curv))


def _line_fit(c: np.ndarray, tau: np.ndarray, sd: np.ndarray, t_ref: float
              ) -> tuple[float, float, np.ndarray]:
    """Weighted straight line ``tau = a + d (c - t_ref)`` with outliers (beyond 4 sd) left
    out; returns a, d and the mask of the points used."""
    sig = np.hypot(sd, PRESS_SIGMA_FLOOR_S)
    use = np.ones(c.size, dtype=bool)
    a, d = float(np.average(tau, weights=sig**-2)), 0.0
    for _ in range(6):
        w = sig[use] ** -2
        x = c[use] - t_ref
        if use.sum() >= 3 and np.ptp(x) > 0:
            d, a = np.polyfit(x, tau[use], 1, w=np.sqrt(w))
        else:
            a, d = float(np.average(tau[use], weights=w)), 0.0
        resid = tau - (a + d * (c - t_ref))
        new = np.abs(resid) <= 4 * sig
        if new.sum() < 1 or np.array_equal(new, use):
            break
        use = new
    return float(a), float(d), use


def _nonnegative_lstsq(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The non-negative ``x`` minimising ``x @ gram @ x - 2 rhs @ x`` (least squares from its
    normal equations): every subset of free variables tried, the best feasible one kept
    (exact, and cheap for the few lag time constants)."""
    n = rhs.size
    best, best_gain = np.zeros(n), 0.0
    for mask in range(1, 1 << n):
        free = np.array([(mask >> j) & 1 for j in range(n)], dtype=bool)
        try:
            x = np.linalg.solve(gram[np.ix_(free, free)], rhs[free])
        except np.linalg.LinAlgError:
            continue
        gain = float(rhs[free] @ x)
        if (x >= 0).all() and gain > best_gain:
            best = np.zeros(n)
            best[free] = x
            best_gain = gain
    return best


def _flank_basis(ts: np.ndarray, basis: np.ndarray, load: np.ndarray, unload: np.ndarray,
                 local: np.ndarray, shift: float) -> np.ndarray:
    """An orthonormal basis (columns) of a press's flank gains at the shifted stage times
    ``ts + shift``, its own terms ``basis`` taken out (``local``: its stage times and loads)."""
    f = np.interp(ts + shift, local[0], local[1])
    gains = np.column_stack([f * load, f * unload])
    gains -= basis @ (basis.T @ gains)
    return np.linalg.qr(gains)[0]


def _lag_decays(ts: np.ndarray) -> np.ndarray:
    """The free decay of each lag of :data:`LAG_TIME_CONSTANTS_S` over a press's samples
    ``ts`` (columns), one at its first sample."""
    return np.exp(-(ts - ts[0])[:, None] / np.asarray(LAG_TIME_CONSTANTS_S))


def _lag_starts(ts: np.ndarray, local: np.ndarray, shift: float) -> np.ndarray:
    """The lagged loads (``local[2:]``) at a press's first sample ``ts[0] + shift``: with
    :func:`_lag_decays`, what the presses before left in them over the press (a first-order
    lag is linear: the lagged load is that decay plus its response to the press's own load
    from rest)."""
    return np.array([np.interp(ts[0] + shift, local[0], lag) for lag in local[2:]])


def _lag_fit(windows: list[_Window], stage: StageLog, lags: list[np.ndarray], a: float,
             d: float, t_ref: float, tail_shares: np.ndarray | None = None
             ) -> tuple[float, np.ndarray]:
    """The clock's level and the pad's lag, fitted together over every timed press.

    The gratings are modelled, press by press, as a gain per flank times the load plus
    shares of the lagged loads ``lags`` (one share each for the whole log: it is one pad),
    with the press's own level and slope in time (:func:`_press_terms`). The clock's level
    is shifted over ± :data:`LAG_SEARCH_S` from the line ``a + d (t - t_ref)``; the shift of
    least weighted squares (each press weighted by its residual variance without lag) is
    returned with the shares. The shares are not negative: the gratings lag the load (their
    response to a step of load rises to its final value without overshoot), they never lead
    it. A lag moves a flank as a delay would, but not the start of a press, nor the rest
    after it (where the creep shows alone): those set the level.

    The lagged loads run over the whole stage log, so they hold the creep the presses before
    left, at the press's own scale. Those presses loaded other places, which each press's
    combination of gratings weighs otherwise: given ``tail_shares`` (the shares of a fit
    without them), a press on which that creep (the lags' decays from its first sample,
    :func:`_lag_decays`, weighted by ``tail_shares``) stands above its noise
    (:data:`TAIL_VISIBLE`) takes it as a term of its own scale, its lagged loads keeping the
    response to its own load. One term of a known shape and only where it shows: a free
    decay per time constant on every press takes most of what sets the level from a pad that
    does not creep (a millisecond of level on a noisy log)."""
    shifts = np.arange(-LAG_SEARCH_S, LAG_SEARCH_S + LAG_STEP_S / 2, LAG_STEP_S)
    n_lag = len(lags)
    prepared = []
    for w in windows:
        ts = w.t + a + d * (w.t - t_ref)
        sel = w.load | w.unload
        # The stage samples this press can reach, copied once: the search interpolates in
        # them many times over.
        j0, j1 = np.searchsorted(stage.t, [ts[0] - 2 * LAG_SEARCH_S, ts[-1] + 2 * LAG_SEARCH_S])
        j0, j1 = max(j0 - 1, 0), min(j1 + 1, stage.t.size)
        local = np.array([stage.t[j0:j1], stage.force_N[j0:j1], *(g[j0:j1] for g in lags)])
        basis = _press_terms(w.t[sel])
        y = w.signal[sel] - basis @ (basis.T @ w.signal[sel])
        # Weighted by its residual variance on the line without lag.
        q = _flank_basis(ts[sel], basis, w.load[sel], w.unload[sel], local, 0.0)
        yr = y - q @ (q.T @ y)
        weight = 1.0 / max(float(yr @ yr) / max(int(sel.sum()) - basis.shape[1] - 2, 1), 1e-12)
        decays = None
        if tail_shares is not None:
            decays = _lag_decays(ts[sel])
            tail = decays @ (_lag_starts(ts[sel], local, 0.0) * tail_shares)
            seen = tail - basis @ (basis.T @ tail)
            if weight * float(seen @ seen) >= TAIL_VISIBLE:
                basis = _press_terms(w.t[sel], tail)
                y = w.signal[sel] - basis @ (basis.T @ w.signal[sel])
            else:
                decays = None
        prepared.append((ts[sel], basis, y, w.load[sel], w.unload[sel], local, weight, decays))
    rss = np.empty(shifts.size)
    shares = np.zeros((shifts.size, n_lag))
    for i, shift in enumerate(shifts):
        za = np.zeros((n_lag, n_lag))
        zb = np.zeros(n_lag)
        yy = 0.0
        for ts, basis, y, load, unload, local, weight, decays in prepared:
            q = _flank_basis(ts, basis, load, unload, local, shift)
            f = np.interp(ts + shift, local[0], local[1])
            yr = y - q @ (q.T @ y)
            z = np.column_stack([np.interp(ts + shift, local[0], lag) - f for lag in local[2:]])
            if decays is not None:
                z -= decays * _lag_starts(ts, local, shift)
            z -= basis @ (basis.T @ z)
            zr = z - q @ (q.T @ z)
            za += weight * zr.T @ zr
            zb += weight * zr.T @ yr
            yy += weight * float(yr @ yr)
        shares[i] = _nonnegative_lstsq(za, zb)
        rss[i] = yy - float(zb @ shares[i])
    k = int(np.argmin(rss))
    shift = float(shifts[k])
    if 0 < k < shifts.size - 1:
        den = rss[k - 1] - 2 * rss[k] + rss[k + 1]
        if den > 0:
            shift += 0.5 * (rss[k - 1] - rss[k + 1]) / den * LAG_STEP_S
    return shift, shares[k]


def _time_presses(t_f: np.ndarray, strain: np.ndarray, stage: StageLog,
                  presses: list[_Press], bounds: list[tuple[float, float]], offset0: float,
                  t_ref: float) -> tuple[list[tuple[float, float, float]], list[_Window]]:
    """Time each press (:func:`_fine`), outwards from the middle of the log, each searched
    around the line fitted to those already done (refitted every 5 presses, starting from
    ``offset0`` without drift), so drift is followed over any length. Returns (fbg time,
    offset, sd) per timed press and its window."""
    mids = np.array([0.5 * (p.on_s + p.off_s) for p in presses]) - offset0
    order = np.argsort(np.abs(mids - 0.5 * (t_f[0] + t_f[-1])), kind="stable")
    found: list[tuple[float, float, float]] = []
    windows: list[_Window] = []
    a, d = offset0, 0.0
    for n_done, k in enumerate(order):
        if n_done >= 5 and n_done % 5 == 0 and found:
            arr = np.array(found)
            a, d, _ = _line_fit(arr[:, 0], arr[:, 1], arr[:, 2], t_ref)
        tau0 = a + d * (mids[k] - t_ref)
        lo, hi = bounds[k]
        i0, i1 = np.searchsorted(t_f, [lo - tau0, hi - tau0])
        t = t_f[i0:i1]
        if t.size < 10:
            continue
        signal = _press_signal(t, strain[i0:i1], np.interp(t + tau0, stage.t, stage.force_N))
        if signal is None:
            continue
        res = _fine(t, signal, stage, presses[k], tau0)
        if res is not None:
            found.append((float(mids[k]), res[0], res[1]))
            load, unload = _flanks(t + res[0], np.interp(t + res[0], stage.t, stage.force_N),
                                   presses[k])
            windows.append(_Window(t, signal, load, unload))
    return found, windows


def align(t_f: np.ndarray, strain: np.ndarray, stage: StageLog, *,
          max_offset_s: float = MAX_OFFSET_S, where: str = "<logs>") -> Alignment:
    """Estimate the stage clock against the interrogator's from the data (module docstring);
    ``strain`` is :func:`grating_strain` of the interrogator's samples ``t_f``.

    Refuses (:class:`InputError`) logs that share no time, a stage log without presses, a
    correlation below :data:`MIN_CORRELATION`, a second correlation peak within
    :data:`AMBIGUOUS_RATIO` of the first (a periodic protocol of equal presses), too few
    presses to refine, and per-press offsets off a straight line by more than
    :data:`MAX_RESIDUAL_MS`.
    """
    presses = [p for p in _stage_presses(stage) if p.peak_N >= ALIGN_MIN_PEAK_N]
    if not presses:
        raise InputError(f"no presses: the load cell never exceeds {ALIGN_MIN_PEAK_N:g} N "
                         f"(is {stage.force_flag} right: N or mN?)",
                         path=stage.path, column="force")
    # Gratings on the beams' other face are stretched by the load, not compressed: then the
    # sum falls under load, and its negative is what correlates. (Each press combines the
    # gratings by their own gains, whatever their signs: _press_signal.)
    total = strain.sum(axis=1, dtype=np.float64)
    offset0, r1, r2, lowest = _coarse(t_f, total, stage, max_offset_s, where)
    if -lowest > r1:
        offset0, r1, r2, _ = _coarse(t_f, -total, stage, max_offset_s, where)
    if r1 < MIN_CORRELATION:
        raise InputError(f"alignment failed: the load and the gratings' strain correlate at "
                         f"best {r1:.2f} (at least {MIN_CORRELATION:g} needed): are these logs "
                         "of the same session, the columns and units right?", path=where)
    if r2 >= AMBIGUOUS_RATIO * r1:
        raise InputError(f"alignment ambiguous: two clock offsets fit almost equally well "
                         f"(correlation {r1:.3f} and {r2:.3f}); a protocol of identical presses "
                         "at a fixed period cannot be aligned: vary the forces or the rests "
                         "(fbgforce protocol)", path=where)
    t_ref = float(t_f[0])
    bounds = [(p.on_s - FLANK_REST_S, p.off_s + FLANK_REST_S) for p in presses]
    # Never reach into the neighbouring press: clip to the middle of each rest.
    for k in range(len(presses) - 1):
        gap_mid = 0.5 * (presses[k].off_s + presses[k + 1].on_s)
        bounds[k] = (bounds[k][0], min(bounds[k][1], gap_mid))
        bounds[k + 1] = (max(bounds[k + 1][0], gap_mid), bounds[k + 1][1])
    found, windows = _time_presses(t_f, strain, stage, presses, bounds, offset0, t_ref)
    if len(found) < MIN_ALIGN_PRESSES:
        raise InputError(f"alignment failed: only {len(found)} of {len(presses)} presses could "
                         f"be timed against the gratings (at least {MIN_ALIGN_PRESSES} needed)",
                         path=where)
    arr = np.array(found)
    a_flanks, d, use = _line_fit(arr[:, 0], arr[:, 1], arr[:, 2], t_ref)
    resid = arr[use, 1] - (a_flanks + d * (arr[use, 0] - t_ref))
    w = np.hypot(arr[use, 2], PRESS_SIGMA_FLOOR_S) ** -2
    rms_ms = float(np.sqrt(np.average(resid**2, weights=w)) * 1e3)
    if use.sum() < max(MIN_ALIGN_PRESSES, 0.5 * len(found)) or rms_ms > MAX_RESIDUAL_MS:
        raise InputError(f"alignment ambiguous: the presses' offsets do not follow one clock "
                         f"(residual {rms_ms:.2g} ms, at most {MAX_RESIDUAL_MS:g}; "
                         f"{int(use.sum())} of {len(found)} presses agree)", path=where)
    # The line's covariance from the presses' sds, scaled up when they scatter more than
    # their sds say.
    design = np.column_stack([np.ones(int(use.sum())), arr[use, 0] - t_ref])
    chi2 = float(np.sum(w * resid**2)) / max(int(use.sum()) - 2, 1)
    cov = np.linalg.pinv(design.T @ (design * w[:, None])) * max(chi2, 1.0)
    ends = np.array([[1.0, 0.0], [1.0, float(t_f[-1]) - t_ref]])
    line_sd_ms = float(np.sqrt(np.max(np.einsum("ij,jk,ik->i", ends, cov, ends))) * 1e3)
    # The flanks time the load as the gratings see it through the pad: late by the pad's
    # lag, by about as much all through the log, so the line's drift holds and its level
    # does not. The level comes from the lag's shares fitted with it over every press.
    lags = [first_order_lag(stage.t, stage.force_N, tau) for tau in LAG_TIME_CONSTANTS_S]
    # Fitted twice when the pad lags: the creep the presses before left is then known in
    # shape (the first fit's shares), and takes a scale of each press's own where it shows.
    on_line = [w for w, u in zip(windows, use) if u]
    shift, shares = _lag_fit(on_line, stage, lags, a_flanks, d, t_ref)
    if shares.any():
        shift, shares = _lag_fit(on_line, stage, lags, a_flanks, d, t_ref, tail_shares=shares)
    a = a_flanks + shift
    table = np.column_stack([arr, use])
    return Alignment(offset_s=a, drift=d, t_ref_s=t_ref, correlation=r1, second_peak=r2,
                     residual_ms=rms_ms, line_sd_ms=line_sd_ms, lag_ms=shift * 1e3,
                     lag_shares=tuple(float(s) for s in shares),
                     presses_used=int(use.sum()),
                     presses_rejected=len(presses) - int(use.sum()), press_offsets=table)


def contact_threshold(noise_N: float) -> float:
    """The load above which a sample is labelled contact, N: the dataset's rule,
    :data:`fbgforce.recordings.dataset.CONTACT_THRESHOLD_N` (as the simulator labels), raised to
    :data:`LOAD_CELL_NOISE_SIGMAS` times a noisier load cell's noise ``noise_N``, so that its
    noise at rest is not labelled as touches."""
    return max(fds.CONTACT_THRESHOLD_N, LOAD_CELL_NOISE_SIGMAS * float(noise_N))
