"""Evidence before correction for the pad's hysteresis: whether a calibration shows a friction
(a gap between a press's rise and its fall at equal load that stays when the load moves slowly)
rather than a damper (a gap that grows with the load's speed), :func:`friction_evidence`; and
whether the force net therefore also trains on holds placed on the release or wandering holds
(:func:`friction_hold_choice`).

Why it matters: both kinds of hold keep the strain a branch had when the load stops or turns.
A friction keeps it, so such holds teach the nets a held grip's falling branch and its turns;
a damper lets it relax, so the same holds teach a grip read low by the release's lag
(docs/robustness.md, "Grips that wander").
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from fbgforce.errors import InputError
from fbgforce.model import artifact
from fbgforce.trainer.creep_fit import load_excess
from fbgforce.trainer.data import Prepared


#: What ``fbgforce train --release-holds`` and ``--wander-holds`` may say: make those holds
#: where the calibration establishes a friction, always, or never.
HOLD_MODES = ("auto", "on", "off")

#: The part of each press's rise and fall compared (:class:`PressLoops`): loads between these
#: shares of its peak, past the contact's first grams and short of the turn.
LOOP_BAND = (0.3, 0.9)
#: Samples of each branch in that band a press needs to count, and presses a calibration needs
#: before the test says anything.
LOOP_MIN_SAMPLES = 3
LOOP_MIN_PRESSES = 20
#: A friction is established when its term is this many standard errors above zero, it is at
#: least :data:`FRICTION_MIN_SHARE` of the gap at the median press, and it predicts the gaps of
#: held-out presses better than the speed alone on more presses than chance allows
#: (:data:`FRICTION_FOLDS` folds, a one-sided sign test at :data:`FRICTION_LEVEL`).
FRICTION_MIN_Z = 3.0
FRICTION_MIN_SHARE = 0.5
FRICTION_FOLDS = 5
FRICTION_LEVEL = 0.05
#: Presses whose speeds follow their peaks closer than this (correlation) cannot tell the two
#: apart: every press then lasts as long, and a gap in proportion to the load is one in
#: proportion to its speed (the paper's protocol at one speed; the foreign pads' calibrations,
#: 6-290 N/s, correlate 0.92-0.95).
LOOP_MAX_CORRELATION = 0.98


@dataclass
class PressLoops:
    """Each press's hysteresis loop, as far as the test reads it.

    Attributes
    ----------
    peak_N
        (p,) the press's peak load.
    speed_N_s
        (p,) the load's mean speed over the band (:data:`LOOP_BAND`) on both branches.
    gap_N
        (p,) a least-squares load signal (the force on the compensated shifts of every loaded
        sample, with an offset) less the load, its mean over the band's falling samples less
        its mean over the rising ones: what the pad holds back, in newtons.
    """

    peak_N: np.ndarray
    speed_N_s: np.ndarray
    gap_N: np.ndarray

    @classmethod
    def of(cls, data: Prepared, pre: artifact.Preprocess, rows: np.ndarray) -> "PressLoops":
        """The loops of the presses among ``rows`` (those with enough samples on both
        branches in the band)."""
        loaded = data.row_mask(rows) & data.contact
        force = np.nan_to_num(data.force_N)
        excess = load_excess(data, pre, rows)
        peaks, speeds, gaps = [], [], []
        for r, sl in data.recording_slices():
            f, e = force[sl], excess[sl]
            # Five samples smooth the load cell's noise out of its speed; the loops' speeds
            # span tens of newtons a second, the noise's a few.
            speed = np.abs(np.gradient(np.convolve(f, np.ones(5) / 5, "same"))) * r.rate_hz
            pid = np.asarray(r.ds.press_id)
            on = loaded[sl]
            for p in np.unique(pid[on]):
                idx = np.flatnonzero(on & (pid == p))
                top = idx[np.argmax(f[idx])]
                band = idx[(f[idx] > LOOP_BAND[0] * f[top]) & (f[idx] < LOOP_BAND[1] * f[top])]
                rise, fall = band[band < top], band[band > top]
                if rise.size < LOOP_MIN_SAMPLES or fall.size < LOOP_MIN_SAMPLES:
                    continue
                peaks.append(f[top])
                speeds.append(0.5 * (speed[rise].mean() + speed[fall].mean()))
                gaps.append(e[fall].mean() - e[rise].mean())
        return cls(np.asarray(peaks), np.asarray(speeds), np.asarray(gaps))


def speed_follows_peak(peak_N: np.ndarray, speed_N_s: np.ndarray) -> float | None:
    """The correlation of the presses' speeds with their peaks where it exceeds
    :data:`LOOP_MAX_CORRELATION`, too close for :func:`friction_evidence` to tell a friction
    from a damper (1 where either does not vary), else None."""
    corr = (float(np.corrcoef(peak_N, speed_N_s)[0, 1])
            if np.std(peak_N) > 0 and np.std(speed_N_s) > 0 else 1.0)
    return corr if corr > LOOP_MAX_CORRELATION else None


def _fit(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of ``y`` on the columns of ``x`` (no offset): coefficients and their
    standard errors."""
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    dof = max(1, len(y) - x.shape[1])
    resid = y - x @ coef
    cov = (resid @ resid / dof) * np.linalg.pinv(x.T @ x)
    return coef, np.sqrt(np.maximum(np.diag(cov), 0.0))


def _sign_test(better: int, n: int) -> float:
    """One-sided p of at least ``better`` of ``n`` under a fair coin."""
    return sum(math.comb(n, k) for k in range(better, n + 1)) / 2.0 ** n if n else 1.0


def friction_evidence(loops: PressLoops, seed: int = 0) -> dict[str, Any]:
    """Whether the presses' gaps establish a friction: ``gap = a peak + b speed`` fitted over
    the presses, a rate-independent part proportional to the load (a friction's loop widens
    with the normal load) beside a damper's rate part.

    Returns ``established`` (bool), ``presses``, ``friction`` (``a``: its ``coefficient``, the
    gap's share of the load, ``se`` and ``z``), ``damper`` (``b``: ``coefficient_s``, ``se_s``,
    ``z``), ``share`` (``a`` over the whole gap at the median press), ``held_out`` (``better``
    of ``presses`` held out predicted nearer with the friction's term than without, and the
    sign test's ``p``), and ``why`` in words.
    """
    n = loops.gap_N.size
    base = {"established": False, "presses": int(n)}
    if n < LOOP_MIN_PRESSES:
        return {**base, "why": f"{n} presses with both branches between "
                                f"{100 * LOOP_BAND[0]:g} and {100 * LOOP_BAND[1]:g} % of their "
                                f"peak (at least {LOOP_MIN_PRESSES} needed)"}
    follows = speed_follows_peak(loops.peak_N, loops.speed_N_s)
    if follows is not None:
        return {**base, "correlation": follows,
                "why": f"the presses' speeds follow their peaks (correlation {follows:.3f}), so a "
                       f"friction and a damper leave the same gaps: presses at several speeds "
                       f"to the same load would tell them apart"}
    x = np.column_stack([loops.peak_N, loops.speed_N_s])
    corr = float(np.corrcoef(x.T)[0, 1])
    coef, se = _fit(x, loops.gap_N)
    z = coef / np.maximum(se, 1e-300)
    at_median = np.array([np.median(loops.peak_N), np.median(loops.speed_N_s)]) * coef
    share = float(np.clip(at_median[0] / at_median.sum(), 0.0, 1.0)) if at_median.sum() > 0 else 0.0
    fold = np.random.default_rng(seed).permutation(n) % FRICTION_FOLDS
    better = 0
    for k in range(FRICTION_FOLDS):
        fit, held = fold != k, fold == k
        both, _ = _fit(x[fit], loops.gap_N[fit])
        rate, _ = _fit(x[fit][:, 1:], loops.gap_N[fit])
        err_both = (loops.gap_N[held] - x[held] @ both) ** 2
        err_rate = (loops.gap_N[held] - x[held][:, 1:] @ rate) ** 2
        better += int(np.sum(err_both < err_rate))
    p = _sign_test(better, n)
    established = bool(z[0] >= FRICTION_MIN_Z and share >= FRICTION_MIN_SHARE
                       and p < FRICTION_LEVEL)
    figures = (f"rise-fall gap {100 * coef[0]:.2f} % of the load (z {z[0]:.1f}) and "
               f"{1000 * coef[1]:.2f} ms of its speed (z {z[1]:.1f}) on {n} presses, "
               f"{100 * share:.0f} % rate-independent at the median press; held-out presses "
               f"nearer with the friction {better}/{n} (p {p:.2g})")
    return {**base, "established": established, "correlation": corr,
            "friction": {"coefficient": float(coef[0]), "se": float(se[0]), "z": float(z[0])},
            "damper": {"coefficient_s": float(coef[1]), "se_s": float(se[1]), "z": float(z[1])},
            "share": share, "held_out": {"better": better, "presses": int(n), "p": p},
            "why": ("friction established: " if established else "no friction established: ")
            + figures}


def friction_hold_choice(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, mode: str,
                         seed: int = 0, option: str = "--release-holds",
                         evidence: dict[str, Any] | None = None) -> dict[str, Any]:
    """Whether the force net trains on the holds ``option`` names in ``mode``
    (:data:`HOLD_MODES`), by :func:`friction_evidence` on the presses among ``rows``
    (``evidence``: that result, already read): ``applied``, ``mode`` and ``why`` beside the
    evidence's keys."""
    if mode not in HOLD_MODES:
        raise InputError(f"must be one of {', '.join(HOLD_MODES)}, not {mode!r}",
                         column=option)
    if mode == "off":
        return {"established": None, "applied": False, "mode": mode, "why": f"{option} off"}
    if evidence is None:
        evidence = friction_evidence(PressLoops.of(data, pre, rows), seed)
    applied = mode == "on" or evidence["established"]
    why = evidence["why"] if mode == "auto" else f"{option} on ({evidence['why']})"
    return {**evidence, "applied": bool(applied), "mode": mode, "why": why}
