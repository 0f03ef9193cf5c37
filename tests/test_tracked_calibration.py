"""The calibration as the at-rest tracker hands it to the nets (``fbgforce.trainer.tracked``,
``TrainParams.track_calibration``, docs/trainer.md "The tracker's zero").

A recording shifted by the tracker's corrections and run without the tracker gives what the
recording itself gives with it, sample for sample; the tracker model drives the tracker with
the contact decision alone; and a training on a calibration whose zero wanders learns loads
from the zero the runtime will hold, where the training on the log as tared reads its own
presses low.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import make_random_model, make_random_walk, make_synthetic_recording
from fbgforce import contract
from fbgforce.model import artifact, floatref
from fbgforce.recordings import tare as fbgtare
from fbgforce.trainer import tracked
from fbgforce.trainer.fit_nets import Scaling
from fbgforce.trainer import preprocess as pp
from fbgforce.trainer.train import train

#: A tracker that moves within a short recording (short settle, fast, a few pm of bound).
QUICK = artifact.InUse(contact_on_margin=0.05, contact_off_margin=-0.05, contact_rise_samples=3,
                       track_shift=5, track_settle=40, track_step_max_pm=2.0,
                       track_limit_pm=20.0)


def _tracking_model(seed: int = 3) -> artifact.HierarchicalModel:
    model = make_random_model(seed, sizes=((8,), (8,), (8,)))
    model.in_use = QUICK
    return model


def test_the_tracked_recording_without_the_tracker_is_the_recording_with_it():
    model = _tracking_model()
    wl = make_random_walk(model, n=4000, seed=5)
    base = model.baseline_nm
    held = floatref.tracked_baselines(model, wl, base)
    assert held.shape == wl.shape
    assert np.array_equal(held[:, 4], np.full(len(wl), base[4]))   # the reference never moves
    drift = held[:, :4] - base[:4]
    block = contract.LIMIT["TRACK_BLOCK"]
    moved = np.flatnonzero(np.any(np.diff(drift, axis=0) != 0, axis=1)) + 1
    assert moved.size and np.all(moved % block == 0)   # only at the tracker's block boundaries
    with_tracker = floatref.predict(model, wl, base)
    ds = dataclasses.replace(make_synthetic_recording(n_press=1), t_s=np.arange(len(wl)) / 1e3,
                             wl_nm=wl, contact=np.zeros(len(wl), bool),
                             x_mm=np.full(len(wl), np.nan), y_mm=np.full(len(wl), np.nan),
                             force_N=np.zeros(len(wl)), press_id=np.zeros(len(wl), np.int64))
    shifted = tracked.tracked_dataset(ds, drift)
    assert np.array_equal(shifted.wl_nm[:, 4], wl[:, 4])
    untracked = dataclasses.replace(model, in_use=dataclasses.replace(QUICK, track_shift=0))
    without = floatref.predict(untracked, shifted.wl_nm, base)
    assert np.array_equal(with_tracker["contact"], without["contact"])
    np.testing.assert_allclose(without["margin"], with_tracker["margin"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(without["force_N"], with_tracker["force_N"], rtol=0, atol=1e-6)


def test_the_tracker_model_reads_the_decision_alone():
    model = _tracking_model()
    pre = model.preprocess
    scaling = Scaling(pp.Standardisation(pre.input_mean, pre.input_std), 20.0, 15.0,
                      np.array([10.5, 13.5]), np.array([6.0, 7.5]))
    holding = dataclasses.replace(QUICK, hold_gain=0.01, hold_shift=6, hold_settle=50)
    lone = tracked.tracker_model(pre, model.contact, holding, scaling, None, model.baseline_nm)
    assert lone.in_use == dataclasses.replace(holding, hold_gain=0.0)   # the gain off
    wl = make_random_walk(model, n=3000, seed=7)
    np.testing.assert_array_equal(floatref.tracked_baselines(lone, wl, model.baseline_nm),
                                  floatref.tracked_baselines(model, wl, model.baseline_nm))
    out = floatref.predict(lone, wl, model.baseline_nm)
    assert not np.any(out["force_N"][out["contact"]] != 20.0)   # its force net reads 0


def _wandering_calibration(wander_pm: float) -> object:
    """A synthetic calibration whose strain gratings' zero rises by ``wander_pm`` between 5 %
    and 15 % of the recording (after the tare) and stays there: a grating's own drift, which
    the reference grating does not see, slow enough for the tracker to catch up within a
    quarter of the recording."""
    ds = make_synthetic_recording(n_press=64, seed=11, noise_pm=2.0)
    n = len(ds)
    rise = np.clip((np.arange(n) - n // 20) / (n // 10), 0.0, 1.0) * wander_pm / 1000.0
    wl = ds.wl_nm.copy()
    wl[:, :4] += rise[:, None]
    return dataclasses.replace(ds, wl_nm=wl)


@pytest.mark.slow
def test_a_wandering_calibration_is_learned_from_the_zero_the_tracker_holds():
    ds = _wandering_calibration(6.0)
    common = dict(epochs=25, seed=0, progress=False, restarts=1, hold_augment=0.0, idle_pads=0,
                  rest_augment=0.0, sizes={"contact": (16, 8), "force": (16, 8),
                                           "location": (8,)})
    as_tared = train([ds], track_calibration=False, **common)
    tracking = train([ds], **common)
    assert as_tared.metadata["tracked_calibration"] is None
    summary = tracking.metadata["tracked_calibration"]
    mean = np.array(summary["recordings"][0]["mean_pm"])
    assert np.all(mean > 3.0) and np.all(mean < 6.0), mean   # it followed the wander
    names = {c["name"]: c for c in tracking.metadata["corrections"]}
    assert names["tracked_calibration"]["applied"]
    assert not {c["name"]: c for c in as_tared.metadata["corrections"]}[
        "tracked_calibration"]["applied"]
    # Each model run as the runtime runs it, tracker on, on the presses of its own calibration
    # after the wander: the one trained as tared reads them off by the tracker's correction
    # (about 8 pm a newton on this pad: high, the loads shift the gratings down; the wander's
    # 6 pm are about 0.7 N).
    base, _ = fbgtare.tare(ds.wl_nm, ds.contact, ds.t_s)
    late = (np.arange(len(ds)) > len(ds) // 2) & ds.contact & (ds.force_N > 5.0)
    bias = {name: float(np.mean(floatref.predict(m, ds.wl_nm, base)["force_N"][late]
                                - ds.force_N[late]))
            for name, m in (("as_tared", as_tared), ("tracking", tracking))}
    assert bias["as_tared"] > 0.3, bias
    assert abs(bias["tracking"]) < 0.5 * bias["as_tared"], bias
