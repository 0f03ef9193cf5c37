"""How early any contact decision could find a recording's presses: the information bound on
onset delay, from the interrogator's noise and the pad's sensitivity.

A detector that raises at most ``per_min`` false contact events a minute at rest has an
average run length at rest of ``gamma = 60 * rate / per_min`` samples, and cannot, on
average, find a change before the log-likelihood ratio of what it has seen since the change
reaches ``log(gamma)`` (Lorden 1971 for a fixed change, Lai 1998 for one that grows, as a
press does; asymptotically in ``gamma``). For a press of force ``f(t)`` on a pad whose shifts
move by ``f(t - d) * s`` (``s``, pm/N per grating, the press's own location; ``d`` the lag of
the shifts behind the load cell) under white noise of covariance ``C`` (pm^2), each sample
adds ``f(t - d)^2 * s' C^-1 s / 2`` to that ratio. The bound is the delay after the contact
label's onset at which the sum from the press's last unloaded sample reaches ``log(gamma)``
(0 where it does so before the label): the quickest median onset of a detector that knew the
press's location and force profile in advance. Any decision that must learn them from the
signal, the contact net's included, comes later. The samples above 1 N that such a detector
has not yet found are the fewest any decision misses, on average.

``C`` is half the covariance of the rests' first differences (white noise doubles in a
difference; the zero's wander and the temperature's drift vanish from it; the rests those of
the tare, :func:`fbgforce.recordings.tare.contact_free_mask`), ``s`` each press's least-squares
shift per newton over its samples above 1 N, from the rest before it. ``d`` is the recording's
own, read where it matters, on the presses' rises up to :data:`LAG_FIT_MAX_N`: the whole
samples, within :data:`LAG_MAX_MS` either way, that bring the matched filter's reading of the
shifts (``s' C^-1 (x - zero) / s' C^-1 s``, newtons) closest to the load cell. A pad whose
rubber damps the rise gives its shifts milliseconds after the load (a Kelvin-Voigt damper of
4 ms: ``d`` 4 ms, and a bound of 7 ms where the load cell times a fixed sensitivity promised
3), and a load cell whose clock runs behind the interrogator's a negative ``d``; a pad that
answers its load at once keeps ``d`` 0 and the bound it had.

Used by ``fbgforce coverage`` (what a calibration's noise allows), ``fbgforce evaluate`` (beside
the onset it measures) and ``python -m fbgforce.bench.bench_onset_bound`` (any labelled
recordings).
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from fbgforce.recordings.dataset import Dataset
from fbgforce.recordings.stagelog import runs
from fbgforce.recordings.tare import contact_free_mask, sample_rate_hz
from fbgforce.samples import sensor_fault_rows

#: Unloaded samples before a press that give its zero for the sensitivity fit.
ZERO_SAMPLES = 50
#: Force below which the load cell's own noise is all there is (its squares would add
#: evidence the press never gave), N.
FORCE_FLOOR_N = 0.05
#: Force above which a press's samples give its sensitivity, and above which its samples
#: count as ones a decision should find (the ``contact_accuracy_above_1N`` of the metrics), N.
SENSITIVITY_MIN_N = 1.0
#: Rest sample pairs needed to measure the noise on.
MIN_REST_PAIRS = 100
#: The shifts' lag behind the load cell is read on each press's rise up to this force (the
#: onset the bound is about; a friction loop's lag grows further up), N, and sought within
#: this many milliseconds either way.
LAG_FIT_MAX_N = 2.0
LAG_MAX_MS = 10.0
#: How much better than none a lag must fit before the bound takes it: its squared
#: differences lower by this much in units of the reading's noise variance (a chi-square of
#: 9 on one degree of freedom: the 5 % level once twenty lags have been tried).
LAG_MIN_GAIN = 9.0


def rest_noise_covariance(wl_pm: np.ndarray, contact: np.ndarray,
                          t_s: np.ndarray | None = None, fault: np.ndarray | None = None
                          ) -> np.ndarray | None:
    """Half the covariance of consecutive rest samples' differences, pm^2 (None with fewer
    than ``MIN_REST_PAIRS`` pairs); the rest samples are the tare's
    (:func:`fbgforce.recordings.tare.contact_free_mask`), less the ``fault`` rows (a lost
    peak, :func:`fbgforce.samples.sensor_fault_rows`)."""
    rest = contact_free_mask(contact, t_s)
    if fault is not None:
        rest = rest & ~np.asarray(fault, bool)
    pair = rest[1:] & rest[:-1]
    if pair.sum() < MIN_REST_PAIRS:
        return None
    wl = np.asarray(wl_pm, dtype=np.float64)
    d = wl[1:][pair] - wl[:-1][pair]
    return np.cov(d, rowvar=False) / 2.0


def press_bounds(wl_pm: np.ndarray, force_N: np.ndarray, contact: np.ndarray,
                 noise_cov: np.ndarray, rate_hz: float, per_min: float = 1.0,
                 keep: np.ndarray | None = None, fault: np.ndarray | None = None
                 ) -> list[dict[str, float]]:
    """The bound for every press of one recording with a rest before it.

    Parameters
    ----------
    wl_pm
        (n, m) the gratings' shifts, pm (any common offset).
    force_N, contact
        (n,) the load cell and the contact label.
    noise_cov
        (m, m) the noise covariance per sample, pm^2 (:func:`rest_noise_covariance`).
    rate_hz
        Sample rate.
    per_min
        False events per minute at rest the detector may raise.
    keep
        (n,) bool: only the presses whose first labelled sample it holds (all when None), as
        ``fbgforce evaluate --split`` scores them.
    fault
        (n,) bool: samples with a lost peak (:func:`fbgforce.samples.sensor_fault_rows`),
        which give no evidence, no zero and no sensitivity.

    Returns
    -------
    list of dict
        Per press: ``onset_bound_ms`` (inf where the press never gives enough evidence),
        ``force_noise_N`` (the per-sample noise of a force read by the matched filter at the
        press's location, ``1 / sqrt(s' C^-1 s)``), ``shift_lag_ms`` (the recording's,
        :func:`shift_lag`), ``above_1N`` (its labelled contact
        samples above 1 N) and ``missed_above_1N`` (those of them before the bound).
    """
    contact = np.asarray(contact, bool)
    f = np.where(np.asarray(force_N, float) > FORCE_FLOOR_N, np.asarray(force_N, float), 0.0)
    good = np.ones(contact.size, bool) if fault is None else ~np.asarray(fault, bool)
    threshold = math.log(60.0 * rate_hz / per_min)
    inv = np.linalg.pinv(noise_cov)
    starts, stops = runs(contact)
    presses = []
    rests_from = [0, *stops[:-1].tolist()]
    for t_on, t_off, rest_from in zip(starts.tolist(), stops.tolist(), rests_from):
        # From the last unloaded sample of the rest: the tail of the release before counts
        # for nothing.
        unloaded = np.flatnonzero(f[rest_from:t_on] == 0.0)
        above = np.arange(t_on, t_off)[f[t_on:t_off] > SENSITIVITY_MIN_N]
        loaded = above[good[above]]
        if not unloaded.size or unloaded[-1] + 1 < ZERO_SAMPLES or loaded.size < 5:
            continue
        start = rest_from + int(unloaded[-1])
        window = np.arange(start + 1 - ZERO_SAMPLES, start + 1)
        window = window[good[window]]
        if not window.size:
            continue
        zero = wl_pm[window].mean(axis=0)
        s = (f[loaded] @ (wl_pm[loaded] - zero)) / float(f[loaded] @ f[loaded])
        presses.append((t_on, t_off, start, above, zero, s, float(s @ inv @ s)))
    lag = shift_lag(wl_pm, f, good, inv,
                    [(start, t_off, zero, s, q) for _, t_off, start, _, zero, s, q in presses],
                    rate_hz)
    out = []
    for t_on, t_off, start, above, zero, s, q in presses:
        if keep is not None and not keep[t_on]:
            continue
        lagged = f[np.clip(np.arange(start, t_off) - lag, 0, f.size - 1)]
        evidence = 0.5 * q * np.cumsum(np.where(good[start:t_off], lagged, 0.0) ** 2)
        reached = np.flatnonzero(evidence >= threshold)
        delay = (start + int(reached[0]) - int(t_on)) if reached.size else math.inf
        found_from = t_on + max(delay, 0) if reached.size else t_off
        out.append({"onset_bound_ms": max(delay, 0) * 1000.0 / rate_hz,
                    "force_noise_N": 1.0 / math.sqrt(q) if q > 0 else math.inf,
                    "shift_lag_ms": lag * 1000.0 / rate_hz,
                    "above_1N": int(above.size),
                    "missed_above_1N": int((above < found_from).sum())})
    return out


def shift_lag(wl_pm: np.ndarray, f: np.ndarray, good: np.ndarray, inv: np.ndarray,
              presses: Sequence[tuple[int, int, np.ndarray, np.ndarray, float]], rate_hz: float
              ) -> int:
    """The shifts' lag behind the load cell on the presses' rises, samples (module docstring).

    ``presses`` holds ``(start, stop, zero, s, q)`` each: the press's last unloaded sample,
    the end of its label, its zero, its sensitivity and ``s' C^-1 s``. Each rise runs from ``start`` to the first
    sample at :data:`LAG_FIT_MAX_N`; the lag is the whole number of samples, within
    :data:`LAG_MAX_MS`, that minimises the squared difference, over every rise's good samples,
    between the matched filter's reading of the shifts and the load cell's force that many
    samples before, each press weighted by its ``s' C^-1 s`` (the reading's inverse noise
    variance). 0 without a rise to read it on, or where no lag fits better than none by
    :data:`LAG_MIN_GAIN` (a slow rise under heavy noise cannot tell a few samples apart).
    """
    most = int(round(LAG_MAX_MS * rate_hz / 1000.0))
    lags = np.arange(-most, most + 1)
    cost = np.zeros(lags.size)
    for start, stop, zero, s, q in presses:
        strong = np.flatnonzero(f[start:stop] >= LAG_FIT_MAX_N)
        end = start + (int(strong[0]) if strong.size else stop - start)
        rise = np.arange(start, end)
        rise = rise[good[rise] & (rise - most >= 0) & (rise + most < f.size)]
        if q <= 0 or not rise.size:
            continue
        reading = (wl_pm[rise] - zero) @ inv @ s / q
        cost += q * np.array([float(np.sum((reading - f[rise - d]) ** 2)) for d in lags])
    best = int(np.argmin(cost))
    return int(lags[best]) if cost[most] - cost[best] > LAG_MIN_GAIN else 0


def bound(datasets: Sequence[Dataset], per_min: float = 1.0,
          keeps: Sequence[np.ndarray | None] | None = None) -> dict[str, Any] | None:
    """:func:`press_bounds` over recordings (the noise from each one's own rests, or pooled
    over the others where one has too few; ``keeps``: each recording's ``keep``); None when
    none has ``MIN_REST_PAIRS`` rest pairs.

    Returns
    -------
    dict or None
        ``per_min``, ``presses`` (how many had a rest before them and 5 samples above 1 N),
        ``noise_pm`` (the median grating's noise per sample), ``force_noise_N`` (median over
        the presses), ``shift_lag_ms`` (the shifts' lag behind the load cell that the bound
        took, :func:`shift_lag`, median over the presses), ``onset_bound_ms`` (``median``
        and ``p90``, each None where that share of the presses never gives the evidence) and
        ``detected_above_1N`` (the share of the presses' samples above 1 N found by the
        bound's detector); the last four None with no press.
    """
    shifts = [1000.0 * np.asarray(ds.wl_nm, float) for ds in datasets]
    faults = [sensor_fault_rows(ds.wl_nm) for ds in datasets]
    covs = [rest_noise_covariance(w, ds.contact, ds.t_s, bad)
            for w, ds, bad in zip(shifts, datasets, faults)]
    known = [c for c in covs if c is not None]
    if not known:
        return None
    pooled = np.mean(known, axis=0)
    presses: list[dict[str, float]] = []
    for i, (w, ds, cov) in enumerate(zip(shifts, datasets, covs)):
        presses += press_bounds(w, ds.force_N, ds.contact, pooled if cov is None else cov,
                                sample_rate_hz(ds.t_s), per_min,
                                None if keeps is None else keeps[i], faults[i])
    delays = np.array([p["onset_bound_ms"] for p in presses])
    noise = np.array([p["force_noise_N"] for p in presses])
    lags = np.array([p["shift_lag_ms"] for p in presses])
    above = sum(p["above_1N"] for p in presses)
    missed = sum(p["missed_above_1N"] for p in presses)
    return {"per_min": per_min, "presses": len(presses),
            "noise_pm": float(np.sqrt(np.median(np.diag(pooled)))),
            "force_noise_N": _finite(np.median(noise)) if noise.size else None,
            "shift_lag_ms": float(np.median(lags)) if lags.size else None,
            "onset_bound_ms": ({"median": _finite(np.median(delays)),
                                "p90": _finite(np.percentile(delays, 90))}
                               if delays.size else None),
            "detected_above_1N": 1.0 - missed / above if above else None}


def median_onset_ms(allows: Mapping[str, Any] | None) -> float | None:
    """The median onset a :func:`bound` result allows, ms; None without a result, without a
    press, or where most presses never give the evidence."""
    return ((allows or {}).get("onset_bound_ms") or {}).get("median")


def delay_text(ms: float | None) -> str:
    """An onset of the bound as the commands print it: ``12.3 ms``, or ``never`` (None)."""
    return "never" if ms is None else f"{ms:.1f} ms"


def lag_text(allows: Mapping[str, Any] | None) -> str:
    """The lag of the shifts behind the load cell a :func:`bound` result took, as the
    commands print it after the noise: ``, the shifts 4 ms behind the load cell`` (``ahead of``
    where they lead it); empty where the bound took none."""
    lag = (allows or {}).get("shift_lag_ms") or 0.0
    return (f", the shifts {abs(lag):g} ms {'behind' if lag > 0 else 'ahead of'} the load cell"
            if lag else "")


def _finite(value: float) -> float | None:
    """A float, or None for the presses that never give the evidence (inf, or the NaN two of
    them interpolate to): what JSON can hold."""
    return float(value) if math.isfinite(value) else None
