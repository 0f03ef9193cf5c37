"""Hard inputs to the fixed-point runtime stay numerically stable (the table in
docs/robustness.md): overload, low force, boundary contacts, a thermal soak, impacts,
dropouts, synthetic sensor faults, extreme and random int32 wavelengths, 10^7 steps, NaN and
infinities into the float paths, and the runtime under valgrind and libFuzzer.

Every case runs three ways (cffi, the sanitizer-built driver, the integer reference) and must
give the same bits within the output contract (tests/hardcase_support.py).
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from fbgforce.export import intref
from fbgforce.export.blob import from_bytes, to_bytes
from hardcase_support import (ALL_FLAGS, FAULT, FIELDS, INT32_MAX, INT32_MIN, OVERLOAD,
                              RUNTIME_C, SATURATED, SPECIAL, TARE_ROWS, WARMUP, CModel, Model,
                              assert_same_results, exec_cffi, expected_tare, ffi, hc, lib,
                              WL_MAX_FM, WL_MIN_FM, record, run_case, scene_fm, with_crc)
# pytest fixtures, used by name
from hardcase_support import driver, models, press_fm, write_report  # noqa: F401

#: Slow (pytest -m slow): sanitizer and valgrind builds of the driver, fuzzers, long runs.
pytestmark = pytest.mark.slow


# --------------------------------------------------------------------------------------------
# Scenes: overload, low force, boundary, thermal soak, impact, dropouts
# --------------------------------------------------------------------------------------------

def _overload_runs(m: Model, driver, gains=(1, 2, 5, 20, 100, 1000)):
    """The overload scene (10 presses, 70-150 N) and the same presses with the strain signal
    scaled by ``gain`` (clipped to the wavelength window: shifts up to hundreds of nm)."""
    wl, ds = scene_fm("overload", n_presses=10)
    base = expected_tare(wl[:TARE_ROWS])
    runs = {}
    for gain in gains:
        w = wl.copy()
        w[:, :4] = np.clip(base[:4] + (wl[:, :4] - base[:4]) * gain, WL_MIN_FM, WL_MAX_FM)
        if gain == 1:
            runs[gain] = run_case(m, w, driver, tare=wl[:TARE_ROWS])
        else:
            runs[gain] = run_case(m, w, driver, baseline=base)
    return runs, ds


@pytest.fixture(scope="module")
def overload_runs(models, driver):
    return {key: _overload_runs(models[key], driver, (1, 2, 5, 20, 100, 1000) if key == "small16"
                                else (1, 5, 1000)) for key in ("small16", "small8")}


@pytest.mark.parametrize("key", ["small16", "small8"])
def test_overload_to_150N_and_beyond_never_wraps(models, overload_runs, key):
    """Up to 150 N and far beyond (x1000 strain): bit-exact (run_case), in contract (OVERLOAD
    whenever the estimate exceeds overload_mN), clamps flagged SATURATED, and no wrap: at
    every sample whose true force exceeds 100 N the runtime reports contact and a positive
    force (a wrap would turn it negative or tiny)."""
    m = models[key]
    runs, ds = overload_runs[key]
    truth = ds.force_N
    hard = truth > 100.0
    assert hard.sum() > 50
    thr = m.q.overload_mN / 1000.0
    rows = []
    for gain, o in runs.items():
        ok = hard & ((o["status"] & FAULT) == 0)
        assert (o["contact"][ok] == 1).all(), gain
        assert (o["force_mN"][ok] > 0).all(), gain
        flags = o["status"][ok]
        if not ok.any():  # x1000: clipped at the window edge for > stuck_max samples: faults
            rows.append({"gain": gain, "faulted": 1.0})
            continue
        rows.append({"gain": gain, "faulted": round(1.0 - float(ok.sum()) / float(hard.sum()), 3),
                     "min_force_N": round(float(o["force_mN"][ok].min()) / 1000, 1),
                     "max_force_N": round(float(o["force_mN"].max()) / 1000, 1),
                     "saturated": round(float(((flags & SATURATED) != 0).mean()), 3),
                     "overload": round(float(((flags & OVERLOAD) != 0).mean()), 3),
                     "neither": round(float(((flags & (SATURATED | OVERLOAD)) == 0).mean()), 3)})
    o = runs[1]
    over = (o["status"] & OVERLOAD) != 0
    record(f"overload/{key}", samples=len(truth), true_max_N=round(float(truth.max()), 1),
           overload_N=thr, samples_true_over_100N=int(hard.sum()),
           overload_rate_by_true_force={f">{g}x": round(float(over[truth > g * thr].mean()), 3)
                                        for g in (1.2, 1.5, 1.8)},
           by_gain_at_true_over_100N=rows)


@pytest.mark.parametrize("key", ["small16", "small8"])
def test_overload_flag_covers_every_true_overload(models, overload_runs, key):
    """OVERLOAD must not depend on the nets' estimate alone: beyond the trained range they
    extrapolate low (a 100-150 N press read 40-70 N with no flag before the runtime got its
    input-side load rule; this test was the strict-xfail that reported it). Every non-faulty
    sample whose true force exceeds 1.2x the calibrated maximum carries OVERLOAD, at every
    strain gain up to the window's end, and none below half of it."""
    m = models[key]
    runs, ds = overload_runs[key]
    thr = m.q.overload_mN / 1000.0
    rates = {}
    for gain, o in runs.items():
        flag = (o["status"] & OVERLOAD) != 0
        okf = (o["status"] & FAULT) == 0
        rates[gain] = {f">{g}x": round(float(flag[sel].mean()), 3) if sel.any() else "all faulted"
                       for g in (1.0, 1.1, 1.2, 1.5)
                       for sel in [(ds.force_N > g * thr) & okf]}
        over = (ds.force_N > 1.2 * thr) & okf
        assert flag[over].all(), (gain, rates[gain])
        if gain == 1:
            assert not flag[ds.force_N < 0.5 * thr].any(), "OVERLOAD far below the range"
    record(f"overload_flag/{key}", overload_rate_by_true_force_per_gain=rates,
           false_overload_below_0p8x=int(((runs[1]["status"] & OVERLOAD) != 0)[ds.force_N < 0.8 * thr].sum()))


def test_low_force_and_boundary_contacts(models, driver):
    m = models["small16"]
    for scene in ("low_force", "boundary"):
        wl, ds = scene_fm(scene, n_presses=12)
        out = run_case(m, wl, driver, tare=wl[:TARE_ROWS])
        c = out["contact"] == 1
        truth = ds.contact
        both = c & truth
        x, y = out["x_um"][both] / 1000.0, out["y_um"][both] / 1000.0
        fmax = float(np.abs(out["force_mN"]).max()) / 1000.0
        record(scene, samples=len(wl), contact_accuracy=round(float((c == truth).mean()), 4),
               true_force_max_N=round(float(ds.force_N.max()), 2), out_force_max_N=round(fmax, 2),
               x_range_mm=[round(float(x.min()), 2), round(float(x.max()), 2)] if both.any() else None,
               y_range_mm=[round(float(y.min()), 2), round(float(y.max()), 2)] if both.any() else None)
        # Bounded outputs even where the model is weak (paper VII-B): the force never exceeds
        # the largest true force by more than the paper's force resolution scale, and the
        # location stays within one pad size of the pad (the nets extrapolate linearly).
        assert fmax < 1.5 * float(ds.force_N.max()) + 2.0
        if both.any():
            assert x.min() > -21 and x.max() < 42 and y.min() > -27 and y.max() < 54


def test_thermal_soak_40K_no_false_contact(models, driver, tmp_path):
    """40 K ramp, no contact. With the temperature coefficients the small model was trained
    with (its smoke data has 0.5 K of drift: coefficients not identified, 1.0) compensation
    leaves ~3 % of the 0.75 nm thermal shift and the nets see a press: recorded, not asserted.
    With coefficients calibrated on the first 20 K of the ramp (12 s to +40 K) (trainer.preprocess.fit_temp_coeff,
    as a thermal calibration would), the ramp adds no false contacts beyond the model's rate
    at rest and the force stays near zero over the full 40 K."""
    from fbgforce.model import modeldir as fm
    from fbgforce import sim
    from fbgforce.export.exporter import export_model
    from fbgforce.trainer.preprocess import fit_temp_coeff

    sc = sim.load_scene("thermal_soak").replace(schedule={"duration_s": 20.0})
    sc = sc.replace(effects={**sc.effects, "temperature": {**sc.effects["temperature"],
                                                            "ramp_start_s": 4.0, "ramp_duration_s": 12.0}})
    ds = sim.simulate(sc)
    wl = intref.nm_to_fm(ds.wl_nm).astype(np.int64)
    dT = float(np.ptp(ds.extra["temperature_K"]))
    assert dT > 39.0
    rest, ramp = slice(TARE_ROWS, 4000), slice(4000, None)

    out = run_case(models["small16"], wl, driver, tare=wl[:TARE_ROWS])
    record("thermal_soak/uncalibrated", samples=len(wl), dT_K=round(dT, 1),
           false_contacts=int(out["contact"].sum()),
           max_force_N=float(out["force_mN"].max()) / 1000.0)

    # Thermal calibration on the first 10 s (0 -> 20 K), then export and run the full 40 K.
    d = tmp_path / "model"
    shutil.copytree(models["small16"].path, d)
    model = fm.load(d)
    base_nm = np.median(ds.wl_nm[:TARE_ROWS], axis=0)
    k, info = fit_temp_coeff([(ds.wl_nm[:10000] - base_nm) * 1000.0], [np.ones(10000, dtype=bool)])
    model.preprocess.temp_coeff = k
    fm.save(model, d)
    from fbgforce.export.blob import FILE_NAME

    calib = [str(p) for p in models["small16"].report["calibration_files"]]
    export_model(d, bits=16, calib=calib, onnx=False)
    blob = (d / FILE_NAME).read_bytes()
    cal = Model(blob, from_bytes(blob), None, d)
    out = run_case(cal, wl, driver, tare=wl[:TARE_ROWS])
    c = out["contact"] == 1
    rate_rest, rate_ramp = float(c[rest].mean()), float(c[ramp].mean())
    fmax = float(out["force_mN"].max()) / 1000.0
    record("thermal_soak/calibrated", temp_coeff=[round(float(v), 4) for v in k],
           false_contact_rate_rest=round(rate_rest, 4), false_contact_rate_ramp=round(rate_ramp, 4),
           max_force_N=fmax, max_conf=float(out["contact_conf_q15"].max()) / 32768.0)
    assert rate_ramp <= 2.0 * rate_rest + 0.01
    # Below the paper's force resolution scale (1.4-1.7 N) plus noise for a memoryless model;
    # the memory's play operators read the residual drift as a slow press (measured 2.8 N with
    # the default memory, docs/robustness.md "Open problems").
    assert fmax < (2.0 if models["small16"].q.n_play == 0 else 3.0)


def test_impact_ringing_settles_without_overflow(models, driver):
    m = models["small16"]
    # Taps 0.6 s apart: after each, the 0.04 s ring-down, the FIR and three time constants
    # of the memory's slowest average (the tap moves the load signal it averages) have run
    # down before the window below, which ends before the next tap.
    wl, ds = scene_fm("impact", n_impacts=8, interval_s=0.6)
    out = run_case(m, wl, driver, tare=wl[:TARE_ROWS])
    sat = (out["status"] & SATURATED) != 0
    slowest = max([int(s) for s in m.q.ema_shift[:m.q.n_ema]], default=0)
    settle = 40 + len(m.q.taps) + 3 * (1 << slowest)
    assert settle + 50 < 600, "the window must end before the next tap"
    impulse = ds.extra["impulse_Ns"]
    taps = np.flatnonzero(impulse > 0)
    late = np.zeros(len(wl), dtype=bool)
    for t in taps:
        late[t + settle:t + settle + 50] = True
    late &= ~ds.contact
    rest_rate = float(out["contact"][TARE_ROWS:taps[0]].mean()) if taps.size else 0.0
    record("impact", samples=len(wl), impacts=len(taps), saturated=int(sat.sum()),
           contact_samples=int(out["contact"].sum()),
           max_force_N=float(out["force_mN"].max()) / 1000.0, settle_ms=settle,
           contact_rate_at_rest=rest_rate, contact_rate_after_settling=float(out["contact"][late].mean()))
    assert not sat.any(), "the FIR / nets clamped during impact ringing"
    # Settled: no more (false) contacts after settling than at rest before the taps.
    assert out["contact"][late].mean() <= 2.0 * rest_rate + 0.01


def test_dropout_scene_lost_and_garbled_samples(models, driver):
    """The dropout effect marks lost (1) and garbled (2) samples; lost peaks reach the runtime
    as NaN nm (-> 0 fm via the one nm->fm rule), garbled ones as random bit flips."""
    m = models["small16"]
    from fbgforce import sim

    ds = sim.simulate(sim.load_scene("dropout").replace(
        schedule={"n_presses": 10}, effects={**sim.load_scene("dropout").effects,
                                            "dropout": {"rate": 0.01, "burst_mean_samples": 3.0,
                                                        "garbled_fraction": 0.4}}))
    flag = ds.extra["dropout"]
    wl_nm = ds.wl_nm.copy()
    wl_nm[flag == 1] = np.nan
    wl = intref.nm_to_fm(wl_nm).astype(np.int64)
    rng = np.random.default_rng(1)
    g = np.flatnonzero(flag == 2)
    bits = rng.integers(0, 31, size=(g.size, 5))
    wl[g] = (wl[g].astype(np.uint32) ^ (np.uint32(1) << bits.astype(np.uint32))).astype(np.int32)
    # The tare window is kept clean (the tare skips out-of-window samples anyway).
    wl[:TARE_ROWS] = intref.nm_to_fm(ds.wl_nm[:TARE_ROWS])
    out = run_case(m, wl, driver, tare=wl[:TARE_ROWS], mode="step")
    fault = (out["status"] & FAULT) != 0
    lost = flag == 1
    lost[:TARE_ROWS] = False
    assert fault[lost].all()
    record("dropout", samples=len(wl), lost=int(lost.sum()), garbled=int(g.size),
           faults=int(fault.sum()), garbled_flagged=int(fault[g].sum()))


# --------------------------------------------------------------------------------------------
# Synthetic sensor faults
# --------------------------------------------------------------------------------------------

def _recovers(m: Model, clean: np.ndarray, faulty: np.ndarray, out: dict, base, end: int,
              contact: np.ndarray | None = None) -> None:
    """Without memory states, n_taps samples after the last faulty sample the output equals
    the clean run's: only the FIR window remembers. With memory the fault froze the states
    (docs/fixed-point.md), so they catch up with the load instead: from the first release
    after the fault (plus the FIR window) contact decisions equal the clean run's on 99 % of
    the samples (a light touch near the threshold may flip) and the force is within 1 N of it,
    and a second later within 0.05 N (measured on the smoke model: 0.51 N and 10 mN)."""
    ref = intref.run(m.q, clean, base)
    k = end + m.q.taps.size
    if m.q.n_ema + m.q.n_play == 0:
        for f in FIELDS:
            np.testing.assert_array_equal(out[f][k:], np.asarray(ref[f][k:], dtype=np.int64), err_msg=f)
        return
    if contact is not None and (~contact[end:]).any():
        k = max(k, end + int(np.flatnonzero(~contact[end:])[0]) + m.q.taps.size)
    assert np.mean(out["contact"][k:] == ref["contact"][k:]) >= 0.99
    df = np.abs(np.asarray(out["force_mN"], dtype=np.int64) - ref["force_mN"])
    assert df[k:].max() <= 1000 and df[k + 1000:].max(initial=0) <= 50, (df[k:].max(), df[k + 1000:].max(initial=0))


@pytest.mark.parametrize("kind", ["lost0", "sentinel_neg1", "int32_min", "int32_max", "below_window",
                                  "above_window", "spike_3nm", "step_3nm", "reference_lost",
                                  "reference_nan", "stuck"])
def test_sensor_faults(models, driver, press_fm, kind):
    m = models["small16"]
    wl, ds = press_fm
    base = expected_tare(wl[:TARE_ROWS])
    # Put the fault in the middle of the first press's load.
    press = np.flatnonzero(ds.contact)
    a = int(press[len(press) // 10])
    b = a + 120
    w = wl.copy()
    ch = 1
    if kind == "lost0":
        w[a:b, ch] = 0
    elif kind == "sentinel_neg1":
        w[a:b, ch] = -1
    elif kind == "int32_min":
        w[a:b, ch] = INT32_MIN
    elif kind == "int32_max":
        w[a:b, ch] = INT32_MAX
    elif kind == "below_window":
        w[a:b, ch] = WL_MIN_FM - 1
    elif kind == "above_window":
        w[a:b, ch] = WL_MAX_FM + 1
    elif kind == "spike_3nm":
        w[a, ch] += 3_000_000
        b = a + 2
    elif kind == "step_3nm":
        w[a:, ch] += 3_000_000
        b = a + 1
    elif kind == "reference_lost":
        w[a:b, 4] = 0
    elif kind == "reference_nan":
        wn = ds.wl_nm.copy()
        wn[a:b, 4] = np.nan
        w = intref.nm_to_fm(wn).astype(np.int64)
    elif kind == "stuck":
        w[a:b, ch] = w[a, ch]
    out = run_case(m, w, driver, baseline=base, mode="step" if kind in ("lost0", "spike_3nm") else "run")
    fault = (out["status"] & FAULT) != 0
    n_fault = int(fault.sum())
    record(f"fault/{kind}", samples_affected=int(b - a), fault_flags=n_fault,
           contact_during=int(out["contact"][a:b].sum()))
    if kind == "stuck":
        # A frozen peak stays in the window and never jumps: the stuck-peak rule faults it
        # from its stuck_max-th repeat on; exact again n_taps samples after it comes unstuck.
        k = m.q.stuck_max
        assert k > 0 and fault[a + k:b].all() and n_fault == b - a - k
        _recovers(m, wl, w, out, base, b, ds.contact)
        return
    if kind == "step_3nm":
        # One faulty sample at the step, then a (wrong but bounded) estimate: the rule treats
        # a step as genuine after one sample.
        assert fault[a] and n_fault == 1
        return
    if kind == "spike_3nm":
        assert fault[a] and fault[a + 1] and n_fault == 2  # the jump there and the jump back
    else:
        assert fault[a:b].all() and n_fault == b - a
    _recovers(m, wl, w, out, base, b, ds.contact)


def test_stuck_peak_is_flagged(models, press_fm, driver):
    """A peak frozen for 0.3 s during a press (a hung interrogator channel) is flagged (the
    runtime's stuck-peak rule; this was a strict-xfail finding of this suite before it
    existed), while the clean recording, with its 3-10 pm noise on a 1 pm grid, never trips
    it. Each channel in turn, the reference grating included."""
    m = models["small16"]
    wl, ds = press_fm
    base = expected_tare(wl[:TARE_ROWS])
    clean = run_case(m, wl, driver, baseline=base)
    assert not np.any(clean["status"] & FAULT)
    a = int(np.flatnonzero(ds.contact)[0])
    k = m.q.stuck_max
    for ch in range(5):
        w = wl.copy()
        w[a:a + 300, ch] = w[a, ch]
        out = run_case(m, w, driver, baseline=base)
        assert ((out["status"][a + k:a + 300] & FAULT) != 0).all(), ch
    record("fault/stuck_rule", stuck_max=k, clean_samples=len(wl), clean_faults=0)


# --------------------------------------------------------------------------------------------
# Extreme integers
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("key", ["small16", "small8", "stress", "stress_bias"])
def test_extreme_int32_wavelengths(models, driver, key):
    m = models[key]
    rng = np.random.default_rng(7)
    n = 3000 if key.startswith("small") else 400
    # Random rows of special values, runs of the same row (so in-window extremes get past the
    # jump rule and fill the FIR), and uniformly random int32.
    rows = SPECIAL[rng.integers(0, SPECIAL.size, (n, 5))]
    held = np.repeat(SPECIAL[rng.integers(0, SPECIAL.size, (n // 20, 5))], 20, axis=0)
    uni = rng.integers(INT32_MIN, INT32_MAX, (n // 4, 5), endpoint=True)
    edge = np.repeat(np.array([[WL_MAX_FM] * 4 + [WL_MIN_FM], [WL_MIN_FM] * 4 + [WL_MAX_FM],
                               [WL_MAX_FM, WL_MIN_FM, WL_MAX_FM, WL_MIN_FM, WL_MAX_FM]]), 80, axis=0)
    wl = np.concatenate([rows, held, uni, edge])
    for base in (None, np.full(5, WL_MIN_FM), np.full(5, WL_MAX_FM), m.q.baseline_fm):
        out = run_case(m, wl, driver, baseline=base, mode="run")
    sat = int(((out["status"] & SATURATED) != 0).sum())
    record(f"extreme/{key}", samples=len(wl) * 4, saturated_last_run=sat,
           faults_last_run=int(((out["status"] & FAULT) != 0).sum()))
    assert sat > 0  # the in-window extremes must clamp (and say so)


@pytest.mark.parametrize("key", ["small16", "small8"])
def test_hypothesis_random_int32_streams(models, driver, key):
    """Property: any int32 stream (biased to the window and its edges) is bit-exact, in
    contract, and flagged by the fault rule. Few examples per run: each goes through the
    sanitizer driver too."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    m = models[key]
    ch = st.one_of(st.integers(INT32_MIN, INT32_MAX), st.sampled_from(SPECIAL.tolist()),
                   st.integers(WL_MIN_FM - 10, WL_MAX_FM + 10),
                   st.integers(-5_000_000, 5_000_000).map(lambda d: 1_546_000_000 + d))
    row = st.lists(ch, min_size=5, max_size=5)

    @settings(max_examples=25, deadline=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(st.lists(st.tuples(row, st.integers(1, 40)), min_size=1, max_size=12),
           st.booleans())
    def prop(segments, tared):
        wl = np.concatenate([np.tile(np.array(r, dtype=np.int64), (k, 1)) for r, k in segments])
        run_case(m, wl, driver, baseline=m.q.baseline_fm if tared else None,
                 mode="step" if len(wl) < 40 else "run")

    prop()


# --------------------------------------------------------------------------------------------
# Long run
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory, press_fm) -> Model:
    """A narrow model (hidden width 8) trained briefly on the press recording: the long run
    tests the streaming state, which does not depend on the nets' width, at ~1 us per step."""
    from fbgforce.recordings import dataset
    from fbgforce.model import artifact, modeldir
    from fbgforce.export.exporter import export_model
    from fbgforce.trainer.train import train

    wl, ds = press_fm
    d = tmp_path_factory.mktemp("tiny")
    dataset.save(ds, d / "data.npz")
    model = train([d / "data.npz"], epochs=3, seed=0, filter="causal", progress=False,
                  sizes={"contact": [8], "force": [8], "location": [8]})
    # The per-sample decision on a fixed tare: then the state after 10^7 steps must equal a
    # fresh one's bit for bit. The at-rest tracker legitimately carries what it learned
    # (tests/test_decision_tracker.py runs it for hours of simulated use).
    model.in_use = artifact.InUse()
    modeldir.save(model, d / "model")
    export_model(d / "model", calib=[d / "data.npz"], onnx=False)
    blob = (d / "model" / "model.fbgm").read_bytes()
    return Model(blob, from_bytes(blob), None, d / "model")


LONG_STEPS = int(os.environ.get("FBGFORCE_LONG_STEPS", 10_000_000))


def test_long_run_1e7_steps_bounded_no_drift(tiny_model, press_fm):
    """10^7 steps through fbg_run (the C batch API): the press recording repeated with fresh
    noise. The state stays bounded (WARMUP only in the first n_taps - 1 samples, the sample
    counter saturates instead of wrapping, the FIR ring index stays in range) and the final
    window equals a fresh runtime's (and the integer reference's) bit for bit: no drift."""
    m = tiny_model
    wl, _ = press_fm
    base = expected_tare(wl[:TARE_ROWS])
    c = CModel(m.blob)
    assert c.init() == 0
    bb = np.ascontiguousarray(base.astype(np.int32))
    assert lib.fbg_set_baseline(c.state, ffi.cast("int32_t *", ffi.from_buffer(bb))) == 0
    rng = np.random.default_rng(11)
    reps = max(1, 250_000 // len(wl))
    done, warm, faults, sat, contacts = 0, 0, 0, 0, 0
    last_in = last_out = None
    while done < LONG_STEPS:
        n = min(reps * len(wl), LONG_STEPS - done)
        chunk = np.tile(wl, (reps, 1))[:n] + rng.integers(-2000, 2001, (n, 5))
        status, out = c.run(chunk)
        assert status == 0
        st = out["status"]
        warm += int(((st & WARMUP) != 0).sum())
        faults += int(((st & FAULT) != 0).sum())
        sat += int(((st & SATURATED) != 0).sum())
        contacts += int(out["contact"].sum())
        done += n
        last_in, last_out = chunk, out
    ntaps = m.q.taps.size
    assert warm == ntaps - 1
    assert faults == 0
    assert c.state.since_reset == 0xFFFF
    assert 0 <= c.state.pos < ntaps
    hist = np.array([[c.state.hist[i][k] for k in range(4)] for i in range(ntaps)])
    assert np.abs(hist).max() < 10**8  # the compensated shifts of the presses, no growth
    # The memory states stay in their proven ranges (docs/fixed-point.md).
    assert all(abs(int(v)) <= 32767 << 15 for v in c.state.ema)
    assert all(abs(int(v)) < 2**16 for v in c.state.play)
    assert all(abs(int(v)) <= 32767 << 15 for v in c.state.loc)
    # Final window vs a fresh runtime fed the same samples, from the start of a repetition of
    # the recording (a rest: where a tare primes the memory states, see docs/fixed-point.md).
    w = 5000
    fresh = CModel(m.blob)
    assert fresh.init() == 0
    assert lib.fbg_set_baseline(fresh.state, ffi.cast("int32_t *", ffi.from_buffer(bb))) == 0
    start = ((len(last_in) - w - ntaps) // len(wl)) * len(wl)
    assert start >= 0
    tail_in = last_in[start:]
    status, fout = fresh.run(tail_in)
    assert status == 0
    ref = intref.run(m.q, tail_in, base)
    for k in FIELDS:
        np.testing.assert_array_equal(last_out[k][-w:], fout[k][-w:], err_msg=k)
        np.testing.assert_array_equal(np.asarray(last_out[k][-w:], dtype=np.int64), ref[k][-w:], err_msg=k)
    record("long_run", steps=done, warmup_flags=warm, faults=faults, saturated=sat,
           contact_samples=contacts, final_window=w, since_reset=int(c.state.since_reset))


def test_long_run_through_driver(tiny_model, press_fm, driver):
    """The same stream, 2 x 10^5 steps (past the 65535-sample counter saturation), through
    the sanitizer driver in one fbg_run call and through the integer reference."""
    wl, _ = press_fm
    base = expected_tare(wl[:TARE_ROWS])
    rng = np.random.default_rng(12)
    n = 200_000
    stream = np.tile(wl, (n // len(wl) + 1, 1))[:n] + rng.integers(-2000, 2001, (n, 5))
    out = run_case(tiny_model, stream, driver, baseline=base)
    assert int(((out["status"] & WARMUP) != 0).sum()) == tiny_model.q.taps.size - 1


# --------------------------------------------------------------------------------------------
# NaN and infinities into the float paths
# --------------------------------------------------------------------------------------------

def _nan_rows(base_nm: np.ndarray) -> np.ndarray:
    rows = np.tile(base_nm, (40, 1))
    specials = [np.nan, np.inf, -np.inf, 1e300, -1e300, 0.0, -0.0, 5e-324, 2.5e3, 999.9999999]
    for i, v in enumerate(specials):
        rows[10 + 2 * i, i % 5] = v
    rows[35] = np.nan
    return rows


def test_nan_inf_into_float_paths(models, driver):
    """Wavelengths in nm (float) go through the one nm->fm rule: NaN/inf -> 0 fm -> a lost
    peak -> SENSOR_FAULT and the safe output; the fixed and the C float runtime never return
    NaN/inf (x/y are NaN only where neither contact nor RELEASING is set, the documented
    convention)."""
    from fbgforce.pybind import FloatRuntime, Runtime

    m = models["small16"]
    rows = _nan_rows(m.q.baseline_fm * 1e-6)
    fm_rows = intref.nm_to_fm(rows).astype(np.int64)
    run_case(m, fm_rows, driver, baseline=m.q.baseline_fm)
    rt = Runtime(m.blob)
    rt.set_baseline(m.q.baseline_fm)
    out = rt.run(rows)
    fault = (out["status"] & FAULT) != 0
    bad = ~np.isfinite(rows).all(axis=1) | (np.abs(rows) > 2000).any(axis=1) | (rows < 1000).any(axis=1)
    assert fault[bad].all()
    for k in ("force_N", "p_contact"):
        assert np.isfinite(out[k]).all(), k
    assert np.isfinite(out["x_mm"][out["contact"]]).all()

    fr = FloatRuntime(m.path)
    fr.set_baseline(m.q.baseline_fm)
    for data in (rows, fm_rows.astype(np.int32),
                 SPECIAL[np.random.default_rng(5).integers(0, SPECIAL.size, (500, 5))].astype(np.int32),
                 hc.stress_inputs(m.q, 1, 50).astype(np.int32), hc.stress_inputs(m.q, -1, 50).astype(np.int32)):
        o = fr.run(data)
        for k in ("force_N", "p_contact", "margin"):
            assert np.isfinite(o[k]).all(), k
        assert np.isfinite(o["x_mm"][o["contact"]]).all() and np.isfinite(o["y_mm"][o["contact"]]).all()
        assert not np.any(np.asarray(o["status"], dtype=np.int64) & ~ALL_FLAGS)
    record("nan_inf", rows=len(rows), faults_fixed=int(fault.sum()))


@pytest.mark.parametrize("where", ["weight", "bias", "temp_coeff", "input_std", "force_scale", "taps"])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_float_model_with_nonfinite_parameter(models, where, value):
    """A float model holding NaN/inf (a corrupt or diverged model) must be refused by
    fbgf_model_check (FBG_ERR_RANGE) rather than produce NaN outputs or reach the
    float->int conversion in fbgf_exp with a NaN (undefined behaviour)."""
    from fbgforce.model import modeldir as fm
    from fbgforce.pybind import FloatRuntime, RangeError

    model = fm.load(models["small16"].path)
    if where == "weight":
        model.contact.weights[0][0, 0] = value
    elif where == "bias":
        model.force.biases[-1][0] = value
    elif where == "temp_coeff":
        model.preprocess.temp_coeff[1] = value
    elif where == "input_std":
        model.preprocess.input_std[2] = value
    elif where == "force_scale":
        model.force_scale = value
    else:
        model.preprocess.taps[0] = value
    with pytest.raises(RangeError):
        FloatRuntime(model)


# --------------------------------------------------------------------------------------------
# valgrind and libFuzzer (bounded runs; `make -C runtime_c valgrind-check fuzz-run` run more)
# --------------------------------------------------------------------------------------------

def _compact_stream(m: Model, press: np.ndarray) -> list[tuple]:
    """A few thousand samples touching every path: tare with faulty rows, presses, faults,
    extremes, reset, step and run."""
    rng = np.random.default_rng(9)
    extreme = SPECIAL[rng.integers(0, SPECIAL.size, (300, 5))]
    held = np.repeat(SPECIAL[rng.integers(0, SPECIAL.size, (15, 5))], 20, axis=0)
    tare = press[:TARE_ROWS].copy()
    tare[::7, 2] = 0
    return [("init", 0), ("run", press[:400]), ("tare", tare), ("run", press[:1500]),
            ("step", extreme[:100]), ("run", extreme), ("run", held), ("reset",),
            ("step", press[1500:1700]), ("base", np.full(5, WL_MIN_FM)),
            ("run", hc.stress_inputs(m.q, 1, 80)), ("base", [0, 0, 0, 0, 0]), ("init", 1),
            ("step", press[:5]), ("tare", np.zeros((3, 5))), ("base", m.q.baseline_fm),
            ("run", press[:200])]


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_valgrind_memcheck_clean(models, press_fm, tmp_path):
    """The plain -g driver under valgrind memcheck (any error or leak exits non-zero) on a
    compact stream through the int16 and int8 models and the stress model, plus corrupt
    blobs; outputs equal the cffi module's. `make -C runtime_c valgrind-check` runs the whole
    suite this way."""
    p = subprocess.run(["make", "-s", "-C", str(RUNTIME_C), "plain-driver", f"HARD_BUILD={tmp_path}"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr
    drv = tmp_path / "plain" / "hardcase_driver"
    wrapper = ("valgrind -q --tool=memcheck --error-exitcode=97 --leak-check=full "
               "--errors-for-leak-kinds=all --track-origins=yes")
    old = os.environ.get("FBGFORCE_HARDCASE_WRAPPER")
    os.environ["FBGFORCE_HARDCASE_WRAPPER"] = wrapper
    try:
        wl, _ = press_fm
        narrow = to_bytes(hc.stress_qmodel(width=16, n_layers=3, bias=(1 << 60) - 1, n_taps=8))
        for key in ("small16", "small8", "stress_narrow"):
            m = models[key] if key in models else Model(narrow, from_bytes(narrow), None, None)
            ops = _compact_stream(m, wl)
            assert_same_results(exec_cffi(m.blob, ops), hc.run_driver(drv, m.blob, ops))
        blob = models["small16"].blob
        from fbgforce.export.blob import PARAMS_END

        # Truncated, bad magic, and a layer table entry of 0xffff x 0xffff with a valid CRC.
        bad = [blob[:10], blob[:500], blob[:-8], bytes([blob[0] ^ 1]) + blob[1:],
               with_crc(bytearray(blob[:PARAMS_END] + b"\xff" * 8 + blob[PARAMS_END + 8:]))]
        got = hc.driver_blob_status(drv, bad + [blob])
        assert got[-1] == 0 and all(s < 0 for s in got[:-1])
    finally:
        if old is None:
            os.environ.pop("FBGFORCE_HARDCASE_WRAPPER")
        else:
            os.environ["FBGFORCE_HARDCASE_WRAPPER"] = old


def _libfuzzer_available() -> bool:
    if shutil.which("clang") is None:
        return False
    probe = subprocess.run(["clang", "-print-file-name=libclang_rt.fuzzer-x86_64.a"],
                           capture_output=True, text=True)
    path = probe.stdout.strip()
    return bool(path) and Path(path).is_file()


@pytest.mark.skipif(not _libfuzzer_available(), reason="clang with libFuzzer not available")
def test_fuzzers_bounded_run(tmp_path):
    """Both libFuzzer targets (ASan+UBSan) run from the committed corpus for a bounded time
    (FBGFORCE_FUZZ_SECONDS, default 4 s each; `make -C runtime_c fuzz-run` uses 20 s) and
    find nothing."""
    secs = os.environ.get("FBGFORCE_FUZZ_SECONDS", "4")
    # The two fuzzers' sanitised builds are most of the time: side by side on two cores.
    jobs = f"-j{min(2, os.cpu_count() or 1)}"
    p = subprocess.run(["make", "-s", jobs, "-C", str(RUNTIME_C), "fuzz-run", f"HARD_BUILD={tmp_path}",
                        f"FUZZ_SECONDS={secs}"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    runs = [int(line.split()[1]) for line in p.stdout.splitlines() if line.startswith("Done ")]
    assert len(runs) == 2 and min(runs) > 100, p.stdout[-2000:]
    record("fuzz", seconds_each=secs, runs=runs)
