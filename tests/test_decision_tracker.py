"""The runtime in use: the contact decision over time and the at-rest baseline tracker.

Bit-exactness of both against the integer reference on every host kernel (with faults,
resets, tares and the tracker at its bound), the decision's rule on hand-made margins, and
what the tracker does with drift and with held loads on the simulator's gripper.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fbgforce import contract
from fbgforce.model import artifact, decision, floatref, modeldir
from fbgforce.export import blob
from fbgforce.export import intref
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import QModel
from fbgforce.pybind import FloatRuntime, Runtime
from fbgforce.units import estimate_shown

from test_simd import host_kernels

LIMIT = contract.STATUS_FLAG["BASELINE_LIMIT"]
AGGRESSIVE = artifact.InUse(contact_on_margin=0.5, contact_off_margin=-1.0, contact_rise_samples=3,
                      track_shift=5, track_settle=40, track_step_max_pm=0.3, track_limit_pm=2.0)


def _drifting_model(random_model_factory, random_walk_factory, in_use: artifact.InUse, seed: int = 3):
    """A random model with the given in-use parameters, and (n, 5) wavelengths whose strain
    gratings drift away from the temperature compensation, with lost peaks."""
    model = random_model_factory(seed, sizes=((24, 12), (24, 12), (24, 16)), n_taps=9,
                                 sigma=2.5, memory=artifact.Memory(weights=(0.25, 0.25, 0.25, 0.25), ema_shifts=(4,), ema_gains=(2,), play_widths=(0.3,), play_gains=(2,), loc_shift=3))
    model.in_use = in_use
    wl = random_walk_factory(model, 6000, seed, step_nm=0.0015)
    wl[:, :4] += np.linspace(0.0, 0.02, wl.shape[0])[:, None] * np.array([1.0, -0.5, 0.8, 0.2])
    x = floatref.features(model, wl, model.baseline_nm)
    logits = model.contact.forward(x[:, :model.preprocess.n_features])
    # About a third of the samples in contact: the decision has both rests and contacts.
    model.contact.biases[-1][1] -= float(np.quantile(logits[:, 1] - logits[:, 0], 0.66))
    # The first half of the walk is "the calibration": later inputs leave its range.
    model.input_range = artifact.input_range_of(x[:3000, :model.preprocess.n_features], margin=0.0)
    q, _ = qz.quantize(model, qz.calibrate(model, [(wl, model.baseline_nm)]))
    rng = np.random.default_rng(seed)
    for start in rng.integers(100, wl.shape[0] - 50, 5):
        wl[start:start + int(rng.integers(1, 30)), int(rng.integers(5))] = 0.0
    return model, q, wl


def _equal(c: np.ndarray, ref: dict[str, np.ndarray]) -> None:
    for k in contract.OUTPUT_FIELDS:
        bad = np.flatnonzero(c[k].astype(np.int64) != ref[k])
        assert bad.size == 0, f"{k} differs at {bad[:5]}"


@pytest.mark.parametrize("kernel", ["portable", *host_kernels()])
def test_decision_and_tracker_are_bit_exact(random_model_factory, random_walk_factory, kernel):
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, AGGRESSIVE)
    assert q.track_shift == 5 and q.contact_rise_n == 3 and q.track_gain.any()
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    ref = intref.run(q, wl_fm, base)
    # The stream exercises every branch: rests long enough to track, the bound, faults, the
    # release band.
    assert (ref["status"] & LIMIT).any() and not (ref["status"] & LIMIT).all()
    assert (ref["status"] & contract.STATUS_FLAG["SENSOR_FAULT"]).any()
    releasing = (ref["status"] & contract.STATUS_FLAG["RELEASING"]) != 0
    assert 0.1 < (ref["contact"].astype(bool) | releasing).mean() < 0.9 and releasing.any()
    outside = (ref["status"] & contract.STATUS_FLAG["OUT_OF_RANGE"]) != 0
    assert outside[:3000].mean() < 0.02 and outside[3000:].mean() > 0.3
    rt = Runtime(blob.to_bytes(q), kernel=kernel)
    rt.set_baseline(base.astype(np.int32))
    _equal(rt.run_raw(wl_fm), ref)
    # The tracker moved the strain baselines, never the reference grating's.
    moved = np.asarray(rt.baseline_fm, dtype=np.int64) - base
    assert np.abs(moved[:4]).max() == q.track_limit_fm and moved[4] == 0


def test_reset_and_tare_restart_the_decision_and_tracker(random_model_factory, random_walk_factory):
    """After a reset the runtime continues as the reference started afresh on the baseline
    the tracker reached; after a tare, on the tare."""
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, AGGRESSIVE, seed=4)
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    rt = Runtime(blob.to_bytes(q))
    rt.set_baseline(base.astype(np.int32))
    rt.run_raw(wl_fm[:2500])
    reached = np.asarray(rt.baseline_fm, dtype=np.int64)
    assert not np.array_equal(reached, base)
    rt.reset()
    _equal(rt.run_raw(wl_fm[2500:4000]), intref.run(q, wl_fm[2500:4000], reached))
    rt.tare(wl[4000:4100])
    tare = np.asarray(rt.baseline_fm, dtype=np.int64)
    _equal(rt.run_raw(wl_fm[4100:]), intref.run(q, wl_fm[4100:], tare))


def test_off_is_the_per_sample_rule(random_model_factory, random_walk_factory):
    """With the defaults the decision is the net's own (acc > 0) and no baseline moves."""
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, artifact.InUse())
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    rt = Runtime(blob.to_bytes(q))
    rt.set_baseline(base.astype(np.int32))
    out = rt.run_raw(wl_fm)
    ok = (out["status"] & contract.STATUS_FLAG["SENSOR_FAULT"]) == 0
    contact, margin = out["contact"][ok] == 1, out["contact_margin_q8"][ok]
    # acc > 0: every positive margin is contact, and no negative one is.
    assert np.all(contact[margin > 0]) and not np.any(contact[margin < 0])
    assert 0.1 < contact.mean() < 0.9
    assert np.array_equal(np.asarray(rt.baseline_fm, dtype=np.int64), base)


def test_the_decision_rule_on_hand_made_margins():
    q = QModel.__new__(QModel)
    q.contact_on_q8, q.contact_off_q8, q.contact_rise_n = 100, -50, 2
    q.contact_cusum_h_q8 = q.contact_cusum_k_q8 = q.contact_cusum_lo_q8 = q.contact_cusum_hi_q8 = 0
    d = decision.RELEASE_DWELL
    margin = np.array([150, 150] + [0] * (d - 1) + [120] + [-40] * d
                      + [-60, 120, 99, 120, 101, 1, -51, -60])
    raw = margin > 0
    # Two samples at or above 100 to rise. Contact shows until the margin has not been
    # positive for d samples (d - 1 at 0 do not release it, the 120 restarts the count); the
    # decision holds while above -50 (the release band); a sample below 100 before the
    # second restarts the rise count.
    want = np.array([0, 1] + [1] * (d - 1) + [1] + [1] * (d - 1) + [0] + [0, 0, 0, 0, 1, 1, 0, 0],
                    dtype=bool)
    held = np.array([0, 1] + [1] * (d - 1) + [1] + [1] * d + [0, 0, 0, 0, 1, 1, 0, 0], dtype=bool)
    state = [0, 0, 0, 0, 0]
    got = intref._contact_decision(q, raw, margin, state)
    assert np.array_equal(got[0], want) and np.array_equal(got[1], held)
    assert state == [0, 0, 0, 0, 0]
    # The state carries from one call to the next exactly as one call.
    state = [0, 0, 0, 0, 0]
    cuts = (0, 1, 2 + d // 2, 2 + d + 3, margin.size)
    parts = [intref._contact_decision(q, raw[a:b], margin[a:b], state) for a, b in zip(cuts, cuts[1:])]
    assert np.array_equal(np.concatenate([p[0] for p in parts]), want)
    assert np.array_equal(np.concatenate([p[1] for p in parts]), held)
    # In the band the Schmitt trigger's rise shows contact again (two samples at 100 or more).
    margin = np.array([150, 150] + [0] * d + [120, 130, -40, -60])
    got = intref._contact_decision(q, margin > 0, margin, [0, 0, 0, 0, 0])
    assert got[0].astype(int).tolist() == [0, 1] + [1] * (d - 1) + [0] + [0, 1, 1, 0]
    assert got[1].astype(int).tolist() == [0, 1] + [1] * d + [1, 1, 1, 0]


def test_in_use_round_trips_through_the_model_directory(tmp_path, random_model_factory):
    model = random_model_factory(1)
    model.in_use = AGGRESSIVE
    modeldir.save(model, tmp_path)
    assert modeldir.load(tmp_path).in_use == AGGRESSIVE
    for bad in ({"contact_on_margin": -1.0}, {"contact_rise_samples": 0}, {"track_shift": 21},
                {"track_limit_pm": 1e6}):
        with pytest.raises(ValueError):
            artifact.InUse(**bad)


def test_the_float_model_runs_the_same_decision_and_tracker(random_model_factory,
                                                           random_walk_factory):
    """The float reference follows the fixed-point runtime through the drift: the same
    decisions but at the margin, and a tracker without it would disagree far more."""
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, AGGRESSIVE)
    wl = np.where(wl == 0.0, np.roll(wl, 40, axis=0), wl)     # no faults: the float model has no rule
    fixed = intref.to_engine_dict(intref.run(q, intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)))
    flt = floatref.predict(model, wl, model.baseline_nm)
    untracked = floatref.predict(dataclasses.replace(model, in_use=artifact.InUse()), wl, model.baseline_nm)
    assert 0.1 < estimate_shown(flt["contact"], flt["status"]).mean() < 0.9
    agree = np.mean(flt["contact"] == fixed["contact"])
    assert agree > 0.98
    assert np.mean(untracked["contact"] == fixed["contact"]) < agree - 0.05
    # The C float build runs the same rules in single precision.
    rt = FloatRuntime(model)
    rt.set_baseline(model.baseline_nm)
    cf = rt.run(wl)
    assert np.mean(cf["contact"] == flt["contact"]) > 0.995
    oor = contract.STATUS_FLAG["OUT_OF_RANGE"]
    assert np.mean(((cf["status"] & oor) != 0) == flt["out_of_range"]) > 0.99
    assert np.mean(((fixed["status"] & oor) != 0) == flt["out_of_range"]) > 0.98
    both = estimate_shown(cf["contact"], cf["status"]) & estimate_shown(flt["contact"], flt["status"])
    assert np.abs(cf["force_N"][both] - flt["force_N"][both]).max() < 1e-2


HOLD_SCENE = """base = "smoke"
description = "one press held for {minutes} minutes at {force} N"
seed = 21
[schedule]
n_presses = 1
rest_s = 3.0
hold_s = {hold_s}
force_min_N = {force}
force_max_N = {force}
tail_s = 1.0
[effects.temperature]
offset_K = 0.0
ramp_K = {ramp}
ramp_start_s = 3.0
ramp_duration_s = {hold_s}
drift_K_per_sqrt_s = 0.0
"""


@pytest.mark.slow
@pytest.mark.parametrize("ramp_K", [0.0, 20.0], ids=["constant", "ramp"])
@pytest.mark.parametrize("force", [0.5, 5.0, 50.0])
def test_a_ten_minute_hold_is_never_absorbed(small_exported_dir, tmp_path, force, ramp_K):
    """The tracker learns only while the decision says rest, and the decision holds a held
    load: through 10 minutes of a grip (at constant temperature, and through a 20 K ramp) the
    decision stays on and the baseline does not move from the press's first sample to its
    release, so the tracker has no part in any estimate of the hold (what the compensation
    leaves of a ramp during a hold is docs/measurements/runtime.md's "In use" figure)."""
    from fbgforce import sim

    path = tmp_path / "hold.toml"
    path.write_text(HOLD_SCENE.format(minutes=10, force=force, hold_s=600.0, ramp=ramp_K))
    ds = sim.simulate(path)
    rt = Runtime(small_exported_dir)
    rt.tare(ds.wl_nm[:2000])
    lead = np.flatnonzero(ds.contact)[0]
    rt.run(ds.wl_nm[:lead])
    before = np.asarray(rt.baseline_fm).copy()
    out = rt.run(ds.wl_nm[lead:])
    held = np.flatnonzero(np.abs(ds.force_N[lead:] - force) < 1e-6 * max(1.0, force))
    assert held.size > 590_000
    assert out["contact"][held].all(), "the decision let go of the held load"
    # Untouched from the press's first sample to its release.
    last = lead + held[-1]
    rt2 = Runtime(small_exported_dir)
    rt2.tare(ds.wl_nm[:2000])
    rt2.run(ds.wl_nm[:last + 1])
    assert np.array_equal(np.asarray(rt2.baseline_fm), before)


@pytest.mark.slow
def test_a_long_run_stays_exact_and_bounded(small_exported_dir):
    """bench_long_run's checks on a short run: one state through a warm-up, grips, a
    cool-down and a rest with lost peaks; bit-exact after a reset mid-run, the tracker inside
    its bound, faults flagged."""
    from fbgforce.bench.bench_long_run import run

    res = run(small_exported_dir, seconds=240.0, segment_s=60.0, seed=1, exact_s=20.0,
              progress=False)
    assert [r["kind"] for r in res["segments"]] == ["warm", "grips", "cool", "rest"]
    assert res["exact"]["samples"] == 20_000 and res["exact"]["mismatched_values"] == 0
    assert res["state"]["baseline_limit_samples"] == 0
    assert res["state"]["largest_tracked_pm"] <= res["state"]["track_limit_pm"]
    assert all(r["faults"] > 0 for r in res["segments"])


def test_the_float_pipeline_fed_in_pieces_equals_the_whole(random_model_factory,
                                                           random_walk_factory):
    """The live stream feeds the float pipeline batch by batch: pieces of any length, across
    the tracker's block boundaries, give what the whole recording gives."""
    model, _, wl = _drifting_model(random_model_factory, random_walk_factory, AGGRESSIVE)
    wl = np.where(wl == 0.0, np.roll(wl, 40, axis=0), wl)
    whole = floatref.predict(model, wl, model.baseline_nm)
    pipe = floatref.FloatPipeline(model, model.baseline_nm)
    cuts = np.unique(np.random.default_rng(0).integers(0, wl.shape[0], 40))
    parts = [pipe.push(wl[a:b]) for a, b in zip(np.r_[0, cuts], np.r_[cuts, wl.shape[0]])]
    assert np.array_equal(np.concatenate([p["contact"] for p in parts]), whole["contact"])
    for k in ("force_N", "margin"):    # a batch's size may change a matrix product's last bit
        np.testing.assert_allclose(np.concatenate([p[k] for p in parts]), whole[k], rtol=0, atol=1e-9)
    assert not np.array_equal(pipe.baseline_nm, model.baseline_nm)


def test_a_burst_of_lost_peaks_leaves_the_rest_at_rest(small_exported_dir):
    """30 samples of a lost reference grating right after a 6 pm noise spike, at rest:
    the filter is fed the last good sample's filtered shifts through the burst, so the
    decision stays at rest and 100 samples on the contact margin is back within one unit of
    the same run without the burst, on every kernel. Holding that raw sample in the filter
    instead read the burst's end as a 6 pm press, which the play operators kept: contact
    latched on for the rest of the run."""
    model = modeldir.load(small_exported_dir)
    q = blob.load_model_blob(small_exported_dir)
    rng = np.random.default_rng(0)
    base = intref.nm_to_fm(model.baseline_nm[None, :])[0]
    wl = base + np.round(rng.normal(0.0, 1000.0, (3000, contract.N_CHANNELS))).astype(np.int64)
    wl[1500, :contract.N_STRAIN] += 6000
    burst = wl.copy()
    burst[1501:1531, contract.N_STRAIN] = 0
    after = slice(1531, None)
    for kernel in ["portable", *host_kernels()]:
        clean, lost = (Runtime(small_exported_dir, kernel=kernel) for _ in range(2))
        for rt in (clean, lost):
            rt.set_baseline(base)
        a, b = clean.run_raw(wl), lost.run_raw(burst)
        assert (b["status"][1501:1531] & contract.STATUS_FLAG["SENSOR_FAULT"]).all()
        assert not b["contact"][after].any(), kernel
        late = slice(1631, None)
        assert np.abs(a["contact_margin_q8"][late].astype(np.int64)
                      - b["contact_margin_q8"][late]).max() < 256, kernel
        ref = intref.run(q, burst, base)
        for key in contract.OUTPUT_FIELDS:
            np.testing.assert_array_equal(b[key], ref[key])
