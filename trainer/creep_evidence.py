"""Evidence before correction: whether a calibration establishes the creep fitted on it
(:func:`creep_evidence`, :func:`creep_press_check`), whether the model corrects for it
(:func:`creep_choice`) and how (:func:`takes_creep_out`)."""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Callable

import numpy as np

from fbgforce.model import artifact, floatref
from fbgforce.errors import InputError
from fbgforce.trainer import preprocess as pp
from fbgforce.trainer.creep import Creep
from fbgforce.trainer.creep_fit import (CREEP_EVIDENCE_MIN_TAU_S, RATE_EFFECT_TIME_CONSTANT_S,
                                        CreepTails, creep_of)
from fbgforce.trainer.data import Prepared


#: What ``creep`` (``fbgforce train --creep``) may say: correct for the fitted creep where the
#: calibration establishes it, wherever the fit finds one, or never.
CREEP_MODES = ("auto", "on", "off")


def creep_choice(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, mode: str,
                 seed: int = 0) -> tuple[Creep, dict[str, Any]]:
    """The creep :func:`~fbgforce.trainer.creep_fit.fit_creep` finds on the releases among
    ``rows``, and :func:`creep_evidence` on it with whether the model corrects for it in
    ``mode`` (:data:`CREEP_MODES`): ``applied`` (bool), ``mode`` and ``rate_effect`` (the
    tails' :meth:`~fbgforce.trainer.creep_fit.CreepTails.rate_effect_test`, None without
    tails) beside the evidence's keys; ``why`` says why it is applied or not, and whether the
    creep was fitted beside the release's rate effect."""
    if mode not in CREEP_MODES:
        raise InputError(f"must be one of {', '.join(CREEP_MODES)}, not {mode!r}",
                         column="--creep")
    tails = CreepTails.of(data, pre, rows)
    found = creep_of(tails)
    rate = tails.rate_effect if tails is not None else None
    if mode == "off":
        return found, {"applied": False, "mode": mode, "established": None, "tests": {},
                       "rate_effect": rate, "why": "--creep off"}
    evidence = creep_evidence(tails, found, seed,
                              lambda: creep_press_check(data, pre, rows, found))
    applied = found.magnitude > 0 and (mode == "on" or evidence["established"])
    why = evidence["why"] if mode == "auto" or not found.magnitude else (
        f"--creep on (established: {evidence['established']}; {evidence['why']})")
    if rate is not None and rate["fitted"] and found.time_constant_s >= CREEP_EVIDENCE_MIN_TAU_S:
        why += (f"; fitted beside the release's rate effect ({100 * rate['coefficient']:.1f} % "
                f"at {1000 * RATE_EFFECT_TIME_CONSTANT_S:.0f} ms, z {rate['z']:.1f})")
    return found, {**evidence, "applied": applied, "mode": mode, "rate_effect": rate,
                   "why": why}


#: The creep a calibration must establish before the trainer corrects for it
#: (:func:`creep_evidence`): a relaxation time clear of the fit's shortest
#: (:data:`~fbgforce.trainer.creep_fit.CREEP_EVIDENCE_MIN_TAU_S`: a rate effect at the release,
#: a damper's, reads as a creep there), and more of the tails' residual removed beside the
#: offsets and that rate effect, in sample and on releases the fit never saw, than the fit
#: removes from any of :data:`CREEP_EVIDENCE_DRAWS` sign-flipped draws of the noise.
CREEP_EVIDENCE_DRAWS = 19


#: Folds of the training presses for :func:`creep_press_check`, and the one-sided level of
#: its sign test.
CREEP_PRESS_FOLDS = 5
CREEP_PRESS_LEVEL = 0.05


def creep_press_check(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, creep: Creep
                      ) -> dict[str, Any]:
    """Whether taking ``creep`` out of the shifts reads held-out presses better.

    A least-squares load signal (the force on the compensated shifts of the contact samples,
    with an offset) is fitted on all but one of :data:`CREEP_PRESS_FOLDS` folds of the
    presses among ``rows`` and scored on the fold left out, once on the shifts as recorded and
    once after the creep inverse (:func:`fbgforce.model.floatref.creep_inverse` with ``creep`` at a
    time constant the model can hold). A creep that outlasts the rests leaves a load-history
    offset on every press that the inverse takes away, and which the release tails, whose
    10 s offsets absorb it, cannot show. Each press's mean squared error counts as better or
    worse; a one-sided sign test at :data:`CREEP_PRESS_LEVEL` says whether the inverse reads
    more held-out presses better than chance would.

    Returns
    -------
    dict
        ``presses``, ``better`` (presses read better with the inverse), ``p_value``,
        ``rmse_N`` and ``rmse_inverse_N`` (over the held-out contact samples), ``passes``.
    """
    m, k = artifact.creep_parameters(creep.magnitude, creep.time_constant_s * data.rate_hz)
    keep = data.row_mask(rows) & data.contact & np.isfinite(data.force_N)
    if m <= 0 or not keep.any():
        return {"presses": 0, "better": 0, "p_value": 1.0, "rmse_N": None,
                "rmse_inverse_N": None, "passes": False}
    inv_pre = replace(pre, creep=m, creep_shift=k)
    plain, inverted, pids = [], [], []
    for r, sl in data.recording_slices():
        comp = pp.compensated(pre, r.ds.wl_nm, r.baseline_nm, recording=True)
        plain.append(comp)
        inverted.append(floatref.creep_inverse(inv_pre, comp))
        pids.append(np.asarray(r.ds.press_id))
    force = data.force_N[keep]
    press = np.unique(np.concatenate(pids)[keep], return_inverse=True)[1]
    fold = press % CREEP_PRESS_FOLDS
    errors = []
    for shifts in (plain, inverted):
        x = np.column_stack([np.concatenate(shifts)[keep], np.ones(keep.sum())])
        err = np.empty(force.size)
        for f in range(CREEP_PRESS_FOLDS):
            out = fold == f
            if out.all() or not out.any():
                err[out] = np.nan
                continue
            w, *_ = np.linalg.lstsq(x[~out], force[~out], rcond=None)
            err[out] = x[out] @ w - force[out]
        errors.append(err)
    n = int(press.max()) + 1
    per_press = [np.bincount(press, weights=np.nan_to_num(e) ** 2, minlength=n) for e in errors]
    better, worse = int(np.sum(per_press[1] < per_press[0])), int(np.sum(per_press[1] > per_press[0]))
    # One-sided sign test: the chance of this many better presses or more if better and worse
    # were equally likely.
    trials = better + worse
    p = float(sum(math.comb(trials, j) for j in range(better, trials + 1)) / 2.0 ** trials) \
        if trials else 1.0
    scored = np.isfinite(errors[0])
    if not scored.any():      # the presses fall in one fold: nothing is held out
        return {"presses": n, "better": 0, "p_value": 1.0, "rmse_N": None,
                "rmse_inverse_N": None, "passes": False}
    rmse = [float(np.sqrt(np.mean(e[scored] ** 2))) for e in errors]
    return {"presses": n, "better": better, "p_value": p, "rmse_N": rmse[0],
            "rmse_inverse_N": rmse[1], "passes": bool(p < CREEP_PRESS_LEVEL and rmse[1] < rmse[0])}


def _held_out_gains(tails: CreepTails) -> list[float]:
    """For each half of the releases (every other one), the share of its residual beside its
    offsets that the creep fitted on the other half removes (0 where a half is empty)."""
    half = tails.release % 2 == 0
    gains = []
    for fit_on, check in ((half, ~half), (~half, half)):
        if not fit_on.any() or not check.any():
            gains.append(0.0)
            continue
        held = tails.subset(check)
        creep = tails.subset(fit_on).fit()[1]
        gains.append(1.0 - held.rss_with(creep) / max(held.rss_offsets(), 1e-300))
    return gains


def _noise_removed(tails: CreepTails, seed: int) -> list[float]:
    """The residual the fit removes from each of :data:`CREEP_EVIDENCE_DRAWS` draws in which
    every release's ``lag(F) - F`` has its sign flipped at random: a draw keeps the noise, the
    wander and the offsets, and breaks any creep."""
    rss0 = tails.rss_offsets()
    rng = np.random.default_rng(seed)
    null = []
    for _ in range(CREEP_EVIDENCE_DRAWS):
        sign = rng.choice([-1.0, 1.0], int(tails.release.max()) + 1)[tails.release]
        null.append(rss0 - tails.fit(tails.lags * sign[:, None])[0])
    return null


def creep_evidence(tails: CreepTails | None, fitted: Creep, seed: int = 0,
                   presses: Callable[[], dict[str, Any]] | None = None) -> dict[str, Any]:
    """Whether the releases whose ``tails`` (:class:`~fbgforce.trainer.creep_fit.CreepTails`)
    :func:`~fbgforce.trainer.creep_fit.fit_creep` read establish the creep ``fitted`` on them,
    or, for the held-out check, the presses (``presses()``: :func:`creep_press_check` of the
    same creep, run only when the held-out releases do not show it).

    Three tests:

    - the relaxation time: above :data:`CREEP_EVIDENCE_MIN_TAU_S`. At the shortest times of
      the fit's grid a creep is indistinguishable from a rate-dependent hysteresis (a
      damper's, which lets go the moment the load stands still): the release's last
      milliseconds read as a creep that a hold would never show;
    - against the noise: the share of the residual the fit removes must exceed what it
      removes from each of :data:`CREEP_EVIDENCE_DRAWS` draws in which every release's
      ``lag(F) - F`` has its sign flipped at random (a draw keeps the noise, the wander and
      the offsets, and breaks any creep), a test at the 5 % level;
    - held out: the releases are split in two halves (every other release); the creep fitted
      on each half must lower the other half's residual (beside its offsets) by a larger
      share than the noise's largest; or, where the releases cannot show it (a creep slower
      than the rests is an offset 150 ms into one), taking it out must read the calibration's
      held-out presses better (``presses``, :func:`creep_press_check`, run only then and
      only when the other tests pass).

    Returns
    -------
    dict
        ``established`` (bool), ``why`` (one line), ``tests`` (each test's figures).
    """
    if fitted.magnitude <= 0:
        return {"established": False, "why": "the fit found no creep", "tests": {}}
    if tails is None:
        return {"established": False, "why": "too few samples after releases to test a creep",
                "tests": {}}
    tests: dict[str, Any] = {"time_constant_s": fitted.time_constant_s}
    fails = []
    if fitted.time_constant_s < CREEP_EVIDENCE_MIN_TAU_S:
        fails.append(f"its time constant ({1000 * fitted.time_constant_s:.0f} ms) is at the "
                     "fit's shortest, where a rate-dependent hysteresis reads the same")
    gains = _held_out_gains(tails)
    rss0 = tails.rss_offsets()
    removed = rss0 - tails.fit()[0]
    null = _noise_removed(tails, seed)
    noise = float(max(null) / max(rss0, 1e-300))
    tests.update(removed_share=float(removed / max(rss0, 1e-300)), noise_removed_share_max=noise,
                 held_out_gain=[float(g) for g in gains])
    if removed <= max(null):
        fails.append(f"it removes {100 * tests['removed_share']:.2f} % of the residual, no "
                     f"more than sign-flipped noise does ({100 * noise:.2f} %)")
    held_out = min(gains) > noise
    checked = presses() if presses is not None and not held_out and not fails else None
    if checked is not None:
        tests["presses"] = checked
    if not held_out and not (checked is not None and checked["passes"]):
        fails.append(f"fitted on half the releases it explains {100 * min(gains):.2f} % of the "
                     f"other half's residual, no more than noise does ({100 * noise:.2f} %)"
                     + (f", and taking it out reads {checked['better']} of {checked['presses']}"
                        f" held-out presses better (p = {checked['p_value']:.2g})"
                        if checked is not None else ""))
    if fails:
        return {"established": False, "why": "; ".join(fails), "tests": tests}
    if held_out:
        why = (f"held out it explains {100 * min(gains):.1f}-{100 * max(gains):.1f} % of the "
               f"residual after releases, noise at most {100 * noise:.2f} %")
    else:
        why = (f"taking it out reads {checked['better']} of {checked['presses']} held-out "
               f"presses better (p = {checked['p_value']:.2g}; load signal RMSE "
               f"{checked['rmse_N']:.3f} -> {checked['rmse_inverse_N']:.3f} N)")
    return {"established": True, "why": why, "tests": tests}


#: The smallest creep magnitude the trainer takes out before the filter by itself
#: (:func:`takes_creep_out`): the fit finds up to 0.5 % on a pad without creep (the synthetic
#: device of tests/conftest.py: 0.5 % with a 4 s time constant), the pads that creep 5 %.
CREEP_INVERSE_MIN = 0.02


def takes_creep_out(creep: Creep, memory_s: float) -> bool:
    """Whether a model whose memory's longest average has the time constant ``memory_s``
    (seconds, 0 without averages) should take the pad's ``creep`` out before the filter.

    A creep faster than the memory's averages is one the nets see whole in their inputs: they
    learn it from the calibration's presses, and the inverse only adds its fit's error. A
    slower one outlasts every average: the nets read the part a press leaves behind as load,
    after a long hold as a light press (the flicker after each release of docs/trainer.md
    "The pad's creep in use"), and only the inverse takes it out. A model without averages
    keeps the at-rest tracker's creep term, and so does a creep below
    :data:`CREEP_INVERSE_MIN`.
    """
    return (creep.magnitude >= CREEP_INVERSE_MIN and memory_s > 0
            and creep.time_constant_s > memory_s)
