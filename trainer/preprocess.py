"""Fitting the preprocessing parameters of :class:`fbgforce.model.artifact.Preprocess`.

The float pipeline itself (``compensate -> apply_filter -> standardise``) is
:mod:`fbgforce.model`; this module only *fits* its parameters from calibration recordings (taring a recording is
:mod:`fbgforce.recordings.tare`):

- :func:`fit_temp_coeff`: per-channel temperature coefficients by least squares of the strain
  gratings' shifts on the reference grating's shift, over contact-free samples, shrunk toward
  1.0 when the data does not contain enough temperature variation to identify them;
- :func:`choose_ref_shift`: whether to average the reference grating's shift before it
  compensates the strain gratings, by the compensated channels' noise at rest with and without;
- :func:`gaussian_taps`: the Gaussian smoothing filter, causal (half-Gaussian over the last
  ``window`` samples, what ships) or centred (the paper's offline smoothing);
- :func:`recording_features`: compensated, filtered shifts of one continuous recording, so that
  every recording is filtered on its own BEFORE any split by press.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import Any, Sequence

import numpy as np

from fbgforce import contract
from fbgforce.model import artifact, floatref
from fbgforce.errors import InputError

#: Prior standard deviation of a temperature coefficient around 1.0 (gratings on one steel part
#: differ by a few percent; their base wavelengths by up to ~2 %): the ridge toward 1.
TEMP_PRIOR_SD = 0.25
#: Least spread of the temperature grating's shift over the rests (pm, 1st to 99th
#: percentile of their block means) from which a strain grating's own temperature coefficient
#: is fitted. Gratings wander on their own by a few pm over tens of seconds (interrogator,
#: bonds, a pad settling), which over a short log is a trend like the temperature's: beside
#: a kelvin or so of calibration it fitted coefficients up to 63 % off, on either half of the
#: rests alike (docs/measurements/trainer.md, "Temperature coefficients"), and
#: those leave the at-rest tracker up to 250 pm over a 40 K ramp. Over 30 pm a 3 pm wander is
#: a 10 % error at most; below it the reference is subtracted as it is (coefficient 1).
TEMP_MIN_SPAN_PM = 30.0
#: Default Gaussian sigma in samples AT 1 kHz, and the window in sigmas.
DEFAULT_SIGMA = 5.0
WINDOW_SIGMAS = 3.0
#: Default Gaussian sigma in milliseconds. The filter trades noise for delay on signals whose
#: dynamics (press onsets, grasps) are set in TIME, so a log at another rate gets the same time
#: constant (10 samples at 2 kHz, 2.5 at 500 Hz), not the same number of samples.
DEFAULT_SIGMA_MS = DEFAULT_SIGMA


#: Time constant of the temperature reference's average, s: temperature moves slowly (20 K/min
#: is about 3 pm/s), so 32 ms of averaging lags by a small fraction of a pm.
REF_TIME_CONSTANT_S = 0.032
#: The average is kept only when it lowers the compensated channels' noise at rest by this
#: fraction at least: an interrogator whose noise is common to all gratings (a swept laser's
#: jitter) is better served by the raw reference, whose noise cancels the strain gratings'.
REF_MIN_GAIN = 0.05


def default_sigma(rate_hz: float) -> float:
    """Default sigma in samples at ``rate_hz``: :data:`DEFAULT_SIGMA_MS` milliseconds."""
    return DEFAULT_SIGMA_MS * float(rate_hz) / 1000.0


def _block_means(x: np.ndarray, mask: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of ``block`` consecutive masked samples inside contiguous masked runs, and the
    number of the run each comes from."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return np.empty((0,) + x.shape[1:]), np.empty(0, dtype=np.int64)
    # Run boundaries where consecutive masked indices are not adjacent.
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    out, runs = [], []
    for k, run in enumerate(np.split(idx, breaks)):
        m = run.size // max(block, 1)
        if m:
            out.append(x[run[:m * block]].reshape(m, block, *x.shape[1:]).mean(axis=1))
            runs.append(np.full(m, k))
    if not out:
        return np.empty((0,) + x.shape[1:]), np.empty(0, dtype=np.int64)
    return np.concatenate(out), np.concatenate(runs)


def fit_temp_coeff(shifts_pm: Sequence[np.ndarray], masks: Sequence[np.ndarray], *,
                   rate_hz: float = 1000.0, prior_sd: float = TEMP_PRIOR_SD,
                   min_span_pm: float = TEMP_MIN_SPAN_PM) -> tuple[np.ndarray, dict[str, Any]]:
    """Per-channel temperature coefficients ``k_i`` in ``shift_i ~ k_i * shift_T``.

    Least squares over contact-free samples of all recordings (shifts relative to each
    recording's own tare), on 50 ms block means (slow temperature survives, interrogator noise
    averages out), with two safeguards that make it work on any file:

    - errors in variables: the reference shift is noisy too, which would bias plain least
      squares toward 0 when the temperature barely moves; its noise variance (from first
      differences) is subtracted from the regressor's energy;
    - shrinkage toward 1 like a Gaussian prior ``k ~ N(1, prior_sd^2)``: the least-squares
      estimate gets the weight ``info / (info + 1/prior_sd^2)`` with ``info`` the reference
      signal energy beyond what noise alone would give (over the residual variance), so with
      little temperature variation the estimate moves smoothly to 1.0 (plain reference
      subtraction) instead of to noise;
    - evidence before correction: coefficients other than 1 only from rests whose temperature
      spans ``min_span_pm`` (:data:`TEMP_MIN_SPAN_PM`) or more; below it every channel stays
      at 1.0. The gratings' own slow wander beside the kelvin or so a
      calibration spans passes the noise test, on each half of the rests alike, and fits
      coefficients up to 63 % off; in use the at-rest tracker then carries that error times the
      temperature change.

    Parameters
    ----------
    shifts_pm
        Per recording, (n, 5) tared shifts in pm (gratings 1..4, T).
    masks
        Per recording, (n,) contact-free samples to fit on.

    Returns
    -------
    temp_coeff, info
        ``info``: ``temp_coeff_identified`` (0..1 per channel, the data's weight against the
        prior, 0 where the span is too short: ~0 means "fell back to 1.0"),
        ``temp_ref_range_pm`` (spread of the reference shift seen, 1st to 99th percentile of
        the block means), ``temp_fit_samples``.
    """
    block = max(1, int(round(0.05 * rate_hz)))
    xs, ys, noise_t, runs = [], [], [], []
    for s, m in zip(shifts_pm, masks):
        s = np.asarray(s, dtype=np.float64)
        m = np.asarray(m, dtype=bool)
        if m.sum() < 2:
            continue
        bm, run = _block_means(s, m, block)
        if bm.shape[0] < 2:
            continue
        runs.append(run + (runs[-1][-1] + 1 if runs else 0))
        # Centred per recording: a tare is itself a noisy estimate, and its constant error
        # must not pass for temperature; only variation within a recording identifies k.
        bm = bm - bm.mean(axis=0)
        xs.append(bm[:, artifact.N_STRAIN])
        ys.append(bm[:, :artifact.N_STRAIN])
        free_t = s[m, artifact.N_STRAIN]
        # White-noise variance of one sample from first differences, then of a block mean.
        noise_t.append((np.var(np.diff(free_t)) / 2.0 / block, bm.shape[0] - 1))
    n_fit = int(sum(x.size for x in xs))
    if n_fit < 3:
        return np.ones(artifact.N_STRAIN), {"temp_coeff_identified": [0.0] * artifact.N_STRAIN,
                                      "temp_ref_range_pm": 0.0, "temp_fit_samples": n_fit}
    x = np.concatenate(xs)
    y = np.concatenate(ys)
    noise_energy = sum(v * k for v, k in noise_t)
    noise_energy_sd = math.sqrt(2.0 * sum(v * v * k for v, k in noise_t))
    # Energy of the reference shift that noise does not explain (errors in variables) ...
    sxx = max(float(x @ x) - noise_energy, 0.0)
    sxy = x @ y
    k_ols = sxy / sxx if sxx > 0 else np.ones(artifact.N_STRAIN)
    resid = y - np.outer(x, k_ols)
    # Residual variance per channel, floored so a noiseless synthetic file stays well posed.
    sigma2 = np.maximum(np.var(resid, axis=0), 1e-6)
    # ... of which only what lies 3 standard deviations beyond pure noise's energy counts as
    # information, so a file without temperature change gets weight ~0 (k = 1), not noise.
    # A residual that wanders slowly (a grating's own drift, a bond creeping) is not
    # independent from block to block: its blocks carry the information of fewer, by the
    # factor (1 - rho) / (1 + rho) of a first-order autoregression with lag-1 correlation
    # rho. Without it, 3 pm of wander beside 1 K of temperature passed for a 25 % coefficient.
    info_data = max(sxx - 3.0 * noise_energy_sd, 0.0) / sigma2 * _independent_fraction(resid, np.concatenate(runs))
    info_prior = 1.0 / prior_sd ** 2
    span = float(np.percentile(x, 99) - np.percentile(x, 1))
    weight = info_data / (info_data + info_prior)
    if span < min_span_pm:
        weight = np.zeros_like(weight)
    coeff = 1.0 + weight * (k_ols - 1.0)
    return coeff, {"temp_coeff_identified": weight.tolist(), "temp_ref_range_pm": span,
                   "temp_fit_samples": n_fit}


def _independent_fraction(resid: np.ndarray, run: np.ndarray) -> np.ndarray:
    """Per channel, ``(1 - rho) / (1 + rho)`` for the lag-1 autocorrelation ``rho`` (>= 0) of
    the block residuals ``resid``, from pairs of neighbouring blocks of one contiguous rest
    (``run`` numbers them): blocks either side of a press are not neighbours in time."""
    same = run[1:] == run[:-1]
    if not same.any():
        return np.ones(resid.shape[1])
    r = resid - resid.mean(axis=0)
    num = np.sum(r[1:][same] * r[:-1][same], axis=0)
    den = 0.5 * np.sum(r[1:][same] ** 2 + r[:-1][same] ** 2, axis=0)
    rho = np.clip(num / np.maximum(den, 1e-30), 0.0, 1.0)
    return (1.0 - rho) / (1.0 + rho)


def gaussian_taps(kind: str, sigma: float = DEFAULT_SIGMA, window: int | None = None
                  ) -> np.ndarray:
    """Gaussian FIR taps summing to 1.

    Parameters
    ----------
    kind
        ``"causal"``: half-Gaussian over the last ``window`` samples, ``taps[k]`` weighting
        sample ``n - k`` (no future sample, what a 1 kHz controller can run). ``"centred"``:
        symmetric over ``2 * window + 1`` samples (the paper's offline smoothing).
        ``"none"``: ``[1.0]``.
    sigma
        Standard deviation in samples.
    window
        Causal: number of taps; centred: half-width. Default ``ceil(3 sigma)`` (+1 causal).
    """
    if kind == "none" or sigma <= 0:
        return np.ones(1)
    if kind not in ("causal", "centred"):
        raise InputError(f"filter must be one of {artifact.FILTER_KINDS}, not {kind!r}",
                         column="--filter")
    if window is None:
        window = int(math.ceil(WINDOW_SIGMAS * sigma)) + (1 if kind == "causal" else 0)
    if window < 1:
        raise InputError("filter window must be at least 1 sample", column="--window")
    k = np.arange(window) if kind == "causal" else np.arange(-window, window + 1)
    taps = np.exp(-0.5 * (k / sigma) ** 2)
    return taps / taps.sum()


def rest_noise_pm2(pre: artifact.Preprocess, recordings: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]
                   ) -> float | None:
    """The compensated channels' sample-to-sample noise at rest under ``pre``: the variance of
    the first differences of :func:`compensated` between consecutive rest samples, summed
    over the four channels (pm^2), pooled over ``recordings`` = [(wl_nm (n, 5), baseline_nm
    (5,), rest (n,) bool), ...]. None without two consecutive finite rest samples."""
    diffs = []
    for wl, base, rest in recordings:
        comp = compensated(pre, wl, base, recording=True)
        d = np.diff(comp, axis=0)
        keep = np.asarray(rest[1:] & rest[:-1], dtype=bool) & np.all(np.isfinite(d), axis=1)
        diffs.append(d[keep])
    d = np.concatenate(diffs) if diffs else np.empty((0, artifact.N_STRAIN))
    return float(np.var(d, axis=0).sum()) if d.shape[0] > 1 else None


def choose_ref_shift(pre: artifact.Preprocess, recordings: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                     rate_hz: float, given: int | None = None) -> tuple[int, dict[str, Any]]:
    """The temperature reference's average for ``pre`` (:attr:`fbgforce.model.artifact.Preprocess.ref_shift`).

    The candidates are 0 (the raw reference) and ``round(log2(REF_TIME_CONSTANT_S *
    rate_hz))`` (clipped to 0 .. ``MAX_REF_SHIFT``); the average is kept when it lowers
    :func:`rest_noise_pm2` by :data:`REF_MIN_GAIN` or more. ``recordings`` as
    :func:`rest_noise_pm2` takes them. ``given`` (``fbgforce train --ref-shift``) is taken
    as it is, in place of the candidate, and recorded as ``"given": true``.

    Returns
    -------
    tuple
        The chosen shift and what the model's metadata records of the choice:
        ``ref_shift``, ``candidate``, ``rest_noise_pm2`` ({"raw", "averaged"}: the summed
        variances of first differences at rest, None where there is no rest) and ``given``.
    """
    candidate = int(np.clip(round(math.log2(max(REF_TIME_CONSTANT_S * float(rate_hz), 1.0))),
                            0, contract.LIMIT["MAX_REF_SHIFT"])) if given is None else int(given)
    raw = rest_noise_pm2(replace(pre, ref_shift=0), recordings)
    averaged = (rest_noise_pm2(replace(pre, ref_shift=candidate), recordings)
                if candidate else raw)
    keep = (candidate > 0 and raw is not None and averaged is not None
            and averaged <= (1.0 - REF_MIN_GAIN) * raw)
    chosen = candidate if keep or given is not None else 0
    return chosen, {"ref_shift": chosen, "candidate": candidate,
                    "rest_noise_pm2": {"raw": raw, "averaged": averaged},
                    "given": given is not None}


def make_preprocess(kind: str, sigma: float, temp_coeff: np.ndarray,
                    window: int | None = None) -> artifact.Preprocess:
    """A :class:`~fbgforce.model.artifact.Preprocess` with unit standardisation (fit it afterwards)."""
    kind = "none" if sigma <= 0 else kind
    return artifact.Preprocess(temp_coeff=temp_coeff, filter_kind=kind, filter_sigma=float(sigma),
                         taps=gaussian_taps(kind, sigma, window), input_mean=np.zeros(artifact.N_STRAIN),
                         input_std=np.ones(artifact.N_STRAIN))


def group_delay_ms(pre: artifact.Preprocess, rate_hz: float = 1000.0) -> float:
    """Delay the filter adds to a slowly varying signal, in milliseconds."""
    return pre.group_delay_samples * 1000.0 / rate_hz


def compensated(pre: artifact.Preprocess, wl_nm: np.ndarray, baseline_nm: np.ndarray, *,
                recording: bool = False) -> np.ndarray:
    """Tared, temperature-compensated shifts (n, 4) in pm via :func:`fbgforce.model.floatref.compensate`.

    By default every row on its own, with the reference grating's own shift: what a steady
    level compensates to (the reference's average converges to it), which splits wavelengths
    into their strain part and the rest (the synthetic holds and rests are made of such
    levels, one row each). ``recording=True``: the rows are ONE continuous recording, the
    reference averaged along it as the model does (``pre.ref_shift``).
    """
    if not recording:
        pre = replace(pre, ref_shift=0)
    # compensate() only reads model.preprocess; a namespace avoids building a dummy model.
    return floatref.compensate(SimpleNamespace(preprocess=pre), wl_nm, baseline_nm)  # type: ignore[arg-type]


def recording_features(pre: artifact.Preprocess, wl_nm: np.ndarray, baseline_nm: np.ndarray
                       ) -> np.ndarray:
    """Compensated and filtered shifts (n, 4), pm, of ONE continuous recording (unstandardised)."""
    return floatref.apply_filter(pre, compensated(pre, wl_nm, baseline_nm, recording=True))


@dataclass
class Standardisation:
    """Input standardisation fitted on training features."""

    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray) -> "Standardisation":
        std = np.std(x, axis=0)
        # A dead channel must not divide by zero; 1e-3 pm is far below any interrogator's noise.
        return cls(np.mean(x, axis=0), np.maximum(std, 1e-3))
