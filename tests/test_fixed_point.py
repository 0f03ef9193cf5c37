"""Fixed-point pipeline: C runtime == numpy integer reference bit for bit; fixed vs float within
the bounds of docs/fixed-point.md; accumulator bounds; fault, tare and status rules."""
from __future__ import annotations

import math

import numpy as np

from fbgforce import contract
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fbgforce.model import artifact, floatref, modeldir
from fbgforce.export import blob, intref
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import NET_NAMES, QModel
from fbgforce.pybind import ArgError, NotTaredError, Runtime, TareError, ffi, lib

FIELDS = contract.OUTPUT_FIELDS


def _balance_contact(model, wl):
    """Shift the contact logit so that about half of ``wl`` is "contact" (both paths run)."""
    logits = model.contact.forward(floatref.features(model, wl, model.baseline_nm)[:, :model.preprocess.n_features])
    model.contact.biases[-1][1] -= float(np.median(logits[:, 1] - logits[:, 0]))
    return model


def _export(model, wl, bits=16, **kw):
    cal = qz.calibrate(model, [(wl, model.baseline_nm)])
    q, rep = qz.quantize(model, cal, bits=bits, **kw)
    return q, blob.to_bytes(q), rep


def _assert_bitexact(q, data, wl_fm, base_fm):
    rt = Runtime(data)
    if base_fm is not None:
        rt.set_baseline(np.asarray(base_fm, dtype=np.int32))
    c = rt.run_raw(np.asarray(wl_fm, dtype=np.int32))
    ref = intref.run(q, wl_fm, base_fm)
    for k in FIELDS:
        bad = np.flatnonzero(np.asarray(c[k], dtype=np.int64) != ref[k])
        assert bad.size == 0, f"{k} differs at samples {bad[:10]}: C {c[k][bad[:3]]} ref {ref[k][bad[:3]]}"
    return ref


@pytest.fixture(scope="module")
def exported(random_model_factory, random_walk_factory):
    model = random_model_factory(1)
    wl = random_walk_factory(model, 4000, seed=1)
    _balance_contact(model, wl)
    q, data, rep = _export(model, wl)
    return model, wl, q, data, rep


def test_sigmoid_table_formula_and_c_agree():
    k = np.arange(129)
    formula = np.minimum(32767, np.floor(32768 / (1 + np.exp(-(k - 64) / 8.0)) + 0.5)).astype(np.int64)
    assert np.array_equal(intref.SIGMOID_Q15_TABLE, formula)
    xs = np.concatenate([np.arange(-2200, 2200), [-2**31 + 1, -10**6, 10**6, 2**31 - 1]])
    c = np.array([lib.fbg_sigmoid_q15(int(x)) for x in xs])
    assert np.array_equal(c, intref.sigmoid_q15(xs))
    # Q15 of the real sigmoid within interpolation (6.2 LSB) plus two roundings (docs).
    inside = np.abs(xs) < 2048
    exact = 32768 / (1 + np.exp(-xs[inside] / 256.0))
    assert np.abs(c[inside] - exact).max() <= 7.5


def test_rounding_and_saturation_rules():
    x = np.array([-5, -4, -3, -2, -1, 0, 1, 2, 3, 4, 5], dtype=np.int64)
    # round half up: -2.5 -> -2, -1.5 -> -1, -0.5 -> 0, 0.5 -> 1, 2.5 -> 3
    assert intref.rshift_round(x, 1).tolist() == [-2, -2, -1, -1, 0, 0, 1, 1, 2, 2, 3]
    y, clamped = intref.sat(np.array([-40000, -32768, -32767, 0, 32767, 32768]), 32767)
    assert y.tolist() == [-32767, -32767, -32767, 0, 32767, 32767]
    assert clamped.tolist() == [True, True, False, False, False, True]


@pytest.mark.parametrize("bits", [16, 8])
def test_bitexact_random_models(random_model_factory, random_walk_factory, bits):
    for seed in (2, 3):
        model = random_model_factory(seed, sizes=((30, 20), (40, 20, 10), (50, 30, 40)))
        wl = random_walk_factory(model, 2500, seed=seed)
        _balance_contact(model, wl)
        q, data, _ = _export(model, wl, bits=bits)
        assert q.w_bits == bits
        wl_fm = intref.nm_to_fm(wl)
        # Inject lost peaks, a jump and a reference-grating loss.
        wl_fm[100, 2] = 0
        wl_fm[700:705, 4] = -1
        wl_fm[1500, 1] += 5_000_000
        ref = _assert_bitexact(q, data, wl_fm, intref.nm_to_fm(model.baseline_nm))
        assert ref["contact"].any() and not ref["contact"].all()
        fault = (ref["status"] & intref.STATUS_SENSOR_FAULT) != 0
        assert fault[[100, 700, 704, 1500]].all()
        # Not tared: the model's nominal baseline, flag set on every sample.
        ref2 = _assert_bitexact(q, data, wl_fm, None)
        assert np.all(ref2["status"] & intref.STATUS_NOT_TARED)


_EXTREMES = [0, -1, 1, -2**31 + 1, 2**31 - 1, 999_999_999, 1_000_000_000, 2_000_000_000,
             2_000_000_001, 1_530_000_000, 1_545_000_000]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_bitexact_hypothesis(exported, data):
    model, _, q, blob_bytes, _ = exported
    n = data.draw(st.integers(1, 60), label="n")
    base = intref.nm_to_fm(model.baseline_nm).astype(np.int64)
    mode = data.draw(st.sampled_from(["near", "wide", "extreme"]), label="mode")
    if mode == "near":
        # Within a few nm of the baseline: the normal operating range, including overload.
        offs = data.draw(st.lists(st.integers(-3_000_000, 3_000_000), min_size=5 * n, max_size=5 * n))
        wl = base + np.array(offs, dtype=np.int64).reshape(n, 5)
    elif mode == "wide":
        vals = data.draw(st.lists(st.integers(900_000_000, 2_100_000_000), min_size=5 * n, max_size=5 * n))
        wl = np.array(vals, dtype=np.int64).reshape(n, 5)
    else:
        vals = data.draw(st.lists(st.one_of(st.sampled_from(_EXTREMES),
                                            st.integers(-2**31 + 1, 2**31 - 1)),
                                  min_size=5 * n, max_size=5 * n))
        wl = np.array(vals, dtype=np.int64).reshape(n, 5)
    b_off = data.draw(st.lists(st.integers(-20_000_000, 20_000_000), min_size=5, max_size=5))
    tared = data.draw(st.booleans(), label="tared")
    baseline = np.clip(base + np.array(b_off), contract.LIMIT["WL_MIN_FM"], contract.LIMIT["WL_MAX_FM"]) if tared else None
    _assert_bitexact(q, blob_bytes, wl, baseline)


def test_bitexact_on_scenes(small_exported_dir, small_dataset_path):
    """The trained small model on the smoke scene, the dropout scene and a short overload
    scene (forces beyond calibration: saturation and overload flags)."""
    import dataclasses

    from fbgforce import sim
    from fbgforce.recordings import dataset
    from fbgforce.export.exporter import recording_baseline

    mdir = small_exported_dir
    q = blob.load_model_blob(mdir)
    data = (mdir / "model.fbgm").read_bytes()
    over = sim.load_scene("overload")
    over = dataclasses.replace(over, schedule={**over.schedule, "n_presses": 8})
    recordings = [dataset.load(small_dataset_path), sim.simulate("dropout", seed=3), sim.simulate(over, seed=4)]
    refs = []
    for ds in recordings:
        base = recording_baseline(ds)
        refs.append(_assert_bitexact(q, data, intref.nm_to_fm(ds.wl_nm), intref.nm_to_fm(base)))
    # OVERLOAD: never inside the calibrated range (smoke), always for presses 20 % beyond it
    # (the input-side load proxy catches what the extrapolating nets under-read).
    over = [(r["status"] & intref.STATUS_OVERLOAD) != 0 for r in refs]
    assert not over[0].any()
    hard = recordings[2].force_N > 1.2 * q.overload_mN / 1000.0
    assert hard.sum() > 100 and over[2][hard].all()


def test_fixed_vs_float_within_bounds(small_exported_dir, small_dataset_path):
    """docs/fixed-point.md: force within 0.05 N, location within 0.05 mm, contact decisions
    differ only where the float margin is within 0.1 of the threshold (memory features carry
    the input rounding times their gain, up to 16x); and every difference within the error
    budget the exporter proved for the model."""
    from fbgforce.recordings import dataset
    from fbgforce.export.exporter import recording_baseline

    mdir = small_exported_dir
    model = modeldir.load(mdir)
    q = blob.load_model_blob(mdir)
    ds = dataset.load(small_dataset_path)
    base = recording_baseline(ds)
    raw = intref.run(q, intref.nm_to_fm(ds.wl_nm), intref.nm_to_fm(base))
    fixed = intref.to_engine_dict(raw)
    flt = floatref.predict(model, ds.wl_nm, base)
    margin = flt["margin"]        # on the float tracker's baseline
    both = fixed["contact"] & flt["contact"]
    assert both.sum() > 1000
    assert np.abs(fixed["force_N"][both] - flt["force_N"][both]).max() < 0.05
    assert np.abs(fixed["x_mm"][both] - flt["x_mm"][both]).max() < 0.05
    assert np.abs(fixed["y_mm"][both] - flt["y_mm"][both]).max() < 0.05
    dis = fixed["contact"] != flt["contact"]
    assert dis.mean() < 0.001
    if dis.any():
        # Each stretch of disagreement starts near one of the decision's thresholds, at most
        # contact_rise_n samples before (the rise count carries a crossing forward); the
        # hysteresis then keeps the two decisions apart until both cross again.
        iu = model.in_use
        near = np.min([np.abs(margin - th) for th in
                       (0.0, iu.contact_on_margin, iu.contact_off_margin)], axis=0) < 0.1
        recent = np.convolve(near, np.ones(iu.contact_rise_samples, dtype=int))[:near.size] > 0
        starts = np.flatnonzero(dis & ~np.concatenate([[False], dis[:-1]]))
        assert recent[starts].all()
    # ... and within the error budget the exporter derived (first-order, per sample).
    import json

    bounds = json.loads((mdir / "export_report.json").read_text())["error_bounds"]
    assert np.abs(fixed["force_N"][both] - flt["force_N"][both]).max() <= bounds["force_N"]
    assert np.abs(fixed["x_mm"][both] - flt["x_mm"][both]).max() <= bounds["x_mm"]
    assert np.abs(fixed["y_mm"][both] - flt["y_mm"][both]).max() <= bounds["y_mm"]
    # The margins themselves (the decisions' disagreements come from them, see above).
    ran = (raw["status"] & intref.STATUS_SENSOR_FAULT) == 0
    assert np.abs(raw["contact_margin_q8"][ran] / 256.0 - margin[ran]).max() <= bounds["contact_margin"]


@pytest.mark.slow
def test_a_row_switched_off_by_weight_decay_exports_and_stays_within_bounds(
        small_model_dir, small_exported_dir, small_dataset_path, tmp_path):
    """Weight decay leaves a dead unit's weights at 1e-300 and below; the quantiser must treat
    them as zeros (not divide its bias by an underflowed scale) and the chain stay exact."""
    import json
    import shutil
    import subprocess
    from pathlib import Path

    from fbgforce.recordings import dataset
    from fbgforce.export.exporter import export_model, recording_baseline

    mdir = tmp_path / "model"
    shutil.copytree(small_model_dir, mdir)
    model = modeldir.load(mdir)
    w0 = model.force.weights[0]
    w0[3] = np.array([7e-319, -1e-318, 1e-250] + [0.0] * (w0.shape[1] - 3))
    model.force.weights[1][5] *= 1e-300
    modeldir.save(model, mdir)
    export_model(mdir, onnx=False)
    q = blob.load_model_blob(mdir)
    ds = dataset.load(small_dataset_path)
    base = recording_baseline(ds)
    fixed = intref.to_engine_dict(intref.run(q, intref.nm_to_fm(ds.wl_nm), intref.nm_to_fm(base)))
    flt = floatref.predict(model, ds.wl_nm, base)
    both = fixed["contact"] & flt["contact"]
    report = json.loads((mdir / "export_report.json").read_text())
    assert both.sum() > 1000
    assert np.abs(fixed["force_N"][both] - flt["force_N"][both]).max() <= report["error_bounds"]["force_N"]
    # The dead rows take the scale of the live ones: no layer needs a smaller shift than the
    # unmodified model's (int32 layers keep shift 32, the Cortex-M4's fast requantisation).
    before = json.loads((small_exported_dir / "export_report.json").read_text())["nets"]["force"]
    assert [ly["shift"] for ly in report["nets"]["force"]] == [ly["shift"] for ly in before]
    # The generated float model writes them as 0.0f, which -Werror accepts (a 1e-318 literal
    # is "truncated to zero" and fails the build).
    cc = shutil.which("cc")
    if cc is None:
        pytest.skip("needs a C compiler")
    inc = Path(__file__).resolve().parents[1] / "runtime_c" / "include"
    src = next((mdir / "c").glob("*_f32.c"))
    assert "e-318" not in src.read_text() and "e-250" not in src.read_text()
    r = subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-I", str(inc),
                        "-I", str(mdir / "c"), "-c", str(src), "-o", str(tmp_path / "f32.o")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_a_faint_row_is_zeroed_rather_than_taking_its_layer_to_int64():
    """Weight decay can leave a unit's weights far below its bias but not switched off: int32
    would cost that row more than ACC32_MAX_DROP bits. If its weights cannot move its output by
    a quarter LSB it becomes a row of zeros and the layer stays int32 at shift 32; a small row
    that can move its output keeps the layer int64."""
    rng = np.random.default_rng(3)
    in_scale, out_ratio = 2.0**-11, np.full(5, 3276.0)
    w = rng.normal(0.0, 1.0, (5, 8))
    b = rng.normal(0.0, 0.1, 5)
    w[2], b[2] = 1e-7 * rng.normal(0.0, 1.0, 8), 1.0
    wq, bq, mult, shift, info = qz._quantize_layer(w, b, in_scale, out_ratio, 16,
                                                   qz.ACC32_MAX_DROP, relu_inputs=True)
    reach = np.abs(w[2]).sum() * contract.SAT16 * in_scale * out_ratio[2]
    assert reach <= qz.FAINT_ROW_LSB
    assert info["acc32"] and shift == 32
    assert not wq[2].any() and bq[2] != 0
    # The other rows are quantised as without the faint one.
    ref = qz._quantize_layer(np.delete(w, 2, 0), np.delete(b, 2), in_scale, np.delete(out_ratio, 2),
                             16, qz.ACC32_MAX_DROP, relu_inputs=True)
    assert np.array_equal(np.delete(wq, 2, 0), ref[0]) and np.array_equal(np.delete(bq, 2), ref[1])
    # A row a thousand times stronger moves its output by tens of LSB: not faint, so int64.
    w[2] *= 1e3
    _, _, _, shift64, info64 = qz._quantize_layer(w, b, in_scale, out_ratio, 16,
                                                  qz.ACC32_MAX_DROP, relu_inputs=True)
    assert not info64["acc32"] and shift64 > 32


def test_odd_hidden_widths_are_padded_to_even_with_the_same_outputs(random_model_factory,
                                                                   random_walk_factory):
    """The Cortex-M4 kernels pair rows and inputs: the exporter pads odd hidden widths with a
    unit of zeros, and the integer outputs are the same numbers as without it."""
    model = random_model_factory(5, sizes=((35, 25, 9), (33, 19, 8), (35, 24, 21)))
    wl = random_walk_factory(model, 600, seed=5)
    _balance_contact(model, wl)
    q, data, _ = _export(model, wl)
    for net in q.nets:
        assert all(layer.w.shape[0] % 2 == 0 for layer in net[:-1])
    q_odd, data_odd, _ = _export(model, wl, even_widths=False)
    assert [layer.w.shape[0] for layer in q_odd.nets[0][:-1]] == [35, 25, 9]
    wl_fm = intref.nm_to_fm(wl)
    base = intref.nm_to_fm(model.baseline_nm)
    even_out, odd_out = intref.run(q, wl_fm, base), intref.run(q_odd, wl_fm, base)
    for k in FIELDS:
        assert np.array_equal(even_out[k], odd_out[k]), k
    _assert_bitexact(q, data, wl_fm, base)


def test_accumulator_bounds_hold_and_are_enforced(exported):
    model, wl, q, data, rep = exported
    trace: dict[str, int] = {}
    intref.run(q, intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm), trace=trace)
    for name, net in zip(NET_NAMES, q.nets):
        for i, layer in enumerate(net):
            bound = layer.acc_bound()
            assert rep["nets"][name][i]["acc_bound"] == int(bound.max())
            assert trace[f"{name}.{i}"] <= bound.max()
            worst = max(int(b) * abs(int(m)) for b, m in zip(bound, layer.mult)) + (1 << (layer.shift - 1))
            assert worst < 2**63
    assert trace["fir"] <= rep["fir"]["acc_bound"] < 2**63
    # A blob whose bias breaks the bound is refused by the C loader (valid CRC, shapes).
    bad = blob.from_bytes(data)
    bad.nets[0][0].bias[0] = 2**59
    bad.nets[0][0].mult[0] = 2**30
    raw = _unchecked_bytes(bad)
    m = ffi.new("fbg_model *")
    buf = ffi.new("uint64_t[]", (len(raw) + 7) // 8)
    ffi.memmove(buf, raw, len(raw))
    assert lib.fbg_model_from_blob(m, ffi.cast("uint8_t *", buf), len(raw)) == lib.FBG_ERR_BOUND


def _unchecked_bytes(q):
    orig = QModel.check
    try:
        QModel.check = lambda self: None
        return blob.to_bytes(q)
    finally:
        QModel.check = orig


def test_fault_rule_and_safe_output(exported):
    model, wl, q, data, _ = exported
    assert q.stuck_max >= 25
    rt = Runtime(data)
    base = intref.nm_to_fm(model.baseline_nm)
    rt.set_baseline(base)
    n = 60 + q.stuck_max
    rng = np.random.default_rng(0)
    x = base + rng.integers(-2000, 2000, (n, 5))   # +-2 pm of noise: values never repeat long
    x[20:, 0] += 3_000_000           # a genuine 3 nm step: faults exactly one sample
    x[30, 4] = 0                     # reference grating lost for one sample
    x[40:, 3] = x[40, 3]             # channel 4 frozen from sample 40 on
    out = rt.run_raw(x.astype(np.int32))
    fault = (out["status"] & intref.STATUS_SENSOR_FAULT) != 0
    stuck_from = 40 + q.stuck_max    # the stuck_max-th repetition
    assert np.flatnonzero(fault).tolist() == [20, 30] + list(range(stuck_from, n))
    for k in ("force_mN", "x_um", "y_um", "contact", "contact_conf_q15", "contact_margin_q8"):
        assert np.all(out[k][fault] == 0)
    warm = (out["status"] & intref.STATUS_WARMUP) != 0
    assert warm[: q.taps.size - 1].all() and not warm[q.taps.size - 1:].any()
    ref = intref.run(q, x, base)
    assert np.array_equal(ref["status"], np.asarray(out["status"], dtype=np.int64))
    # The frozen channel moves again: the fault clears at once.
    x2 = x[-1] + rng.integers(-2000, 2000, (5, 5))
    out2 = rt.run_raw(x2.astype(np.int32))
    assert not np.any(out2["status"] & intref.STATUS_SENSOR_FAULT)


def test_tare_api(exported):
    model, wl, q, data, _ = exported
    rt = Runtime(data, require_tare=True)
    with pytest.raises(NotTaredError):
        rt.step(wl[0])
    samples = intref.nm_to_fm(wl[:7]).astype(np.int64)
    samples[3, 2] = 0                # skipped by the tare
    base = rt.tare(samples.astype(np.int32))
    good = np.delete(samples, 3, axis=0)
    expect = (good.sum(axis=0) + good.shape[0] // 2) // good.shape[0]
    assert np.array_equal(rt.baseline_fm, expect)
    assert np.allclose(base, expect * 1e-6)
    assert rt.tared
    rt.step(wl[0])
    with pytest.raises(TareError):
        rt.tare(np.zeros((3, 5), dtype=np.int32))
    with pytest.raises(ArgError):
        rt.set_baseline(np.array([0, 1, 2, 3, 4], dtype=np.int32))
    # Tared output equals the reference run with that baseline.
    rt2 = Runtime(data)
    rt2.tare(samples.astype(np.int32))
    c = rt2.run_raw(intref.nm_to_fm(wl[:500]))
    ref = intref.run(q, intref.nm_to_fm(wl[:500]), expect)
    assert all(np.array_equal(np.asarray(c[k], dtype=np.int64), ref[k]) for k in FIELDS)


def test_quantizer_rejects_unexportable_models(random_model_factory):
    from fbgforce.errors import InputError

    model = random_model_factory(5)
    cen = artifact.Preprocess(model.preprocess.temp_coeff, "centred", 2.0, np.ones(5) / 5,
                        model.preprocess.input_mean, model.preprocess.input_std)
    with pytest.raises(InputError, match="centred"):
        qz.quantize_taps(cen)
    long = artifact.Preprocess(model.preprocess.temp_coeff, "causal", 30.0, np.ones(100) / 100,
                         model.preprocess.input_mean, model.preprocess.input_std)
    with pytest.raises(InputError, match="taps"):
        qz.quantize_taps(long)
    t, q = qz.quantize_taps(artifact.Preprocess(model.preprocess.temp_coeff, "none", 0.0, [1.0],
                                          model.preprocess.input_mean, model.preprocess.input_std))
    assert t.tolist() == [16384] and q == 14
    # DC gain exact for a normal Gaussian.
    t, q = qz.quantize_taps(model.preprocess)
    assert q == 15 and t.sum() == 32768


def test_choose_shift_precision():
    s, m = qz.choose_shift([0.1234567, -3.5e-4, 1.0])
    assert np.all(np.abs(m) <= 2**30)
    rel = np.abs(m / 2.0**s - np.array([0.1234567, -3.5e-4, 1.0])) / np.array([0.1234567, 3.5e-4, 1.0])
    assert rel.max() < 2**-17
    assert math.isclose(m[2] / 2.0**s, 1.0)
    # Ratios above 2 overflow int64 at the largest shifts (a noise-free recording gives load
    # signal weights of about 3): the shift is chosen without the overflow.
    s, m = qz.choose_shift([2.49, -3.02])
    assert s == qz.MULT_BITS - 2 and m.dtype == np.int64
    assert np.abs(m / 2.0**s - np.array([2.49, -3.02])).max() < 2.0**-s


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10_000), bits=st.sampled_from([16, 8]),
       n_taps=st.sampled_from([1, 2, 7, 64]),
       widths=st.lists(st.lists(st.integers(1, 128), min_size=0, max_size=3), min_size=3, max_size=3),
       even=st.booleans())
def test_bitexact_random_structures(random_model_factory, random_walk_factory, seed, bits, n_taps, widths,
                                    even):
    """Any shape the runtime accepts: 0-3 hidden layers of width 1..128, 1..64 taps, int8/int16,
    odd widths as the model has them or padded to even by the exporter."""
    model = random_model_factory(seed, sizes=tuple(tuple(w) for w in widths), n_taps=n_taps,
                                 sigma=max(n_taps / 4.0, 0.5))
    wl = random_walk_factory(model, 600, seed=seed)
    _balance_contact(model, wl)
    q, data, _ = _export(model, wl, bits=bits, even_widths=even)
    wl_fm = intref.nm_to_fm(wl)
    wl_fm[50] = [0, 2**31 - 1, -2**31 + 1, 1, 2_000_000_001]
    _assert_bitexact(q, data, wl_fm, intref.nm_to_fm(model.baseline_nm))
