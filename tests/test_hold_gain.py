"""The settled-hold gain (``InUse.hold_*``, ``fbg_model.hold_*``): once a contact sample's
force has stayed within its band of its own average for ``hold_settle`` samples, the force
takes the trainer's gain, ramped in over ``2^hold_ramp_shift`` samples (docs/runtime.md, "In
use"; docs/fixed-point.md, "Settled-hold gain").

The C fixed point equals the integer reference bit for bit on every host kernel; the rule
is what the docs write (untouched before the settle, the whole gain after the ramp, cleared
by a sample without contact, a reset, a tare or a new baseline, held through a fault); the
float engines follow it; the fields are range-checked by every reader; the trainer measures
the gain on its synthetic holds. (The Cortex-M4 builds run it in tests/test_target.py.)
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import make_random_model, make_random_walk
from fbgforce import contract
from fbgforce.model import artifact, floatref
from fbgforce.export import blob, intref, mutate
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import QModel
from fbgforce.pybind import PACKED_KERNELS, FloatRuntime, RangeError, Runtime
from test_creep_track import _equal, _hardcases
from test_simd import host_kernels

FAULT = contract.STATUS_FLAG["SENSOR_FAULT"]
#: A stage that acts within a short recording: 40 samples to settle, a 32-sample ramp, a
#: gain near its bound so that every step of it shows in mN.
QUICK = dict(hold_gain=0.1, hold_settle=40, hold_band_N=0.002, hold_band_frac=0.001,
             hold_shift=4, hold_ramp_shift=5)
#: Where the recording stands still (start, length): longer than settle + ramp, and one
#: shorter than the settle.
STILL = ((600, 400), (1500, 30), (2300, 500), (3300, 300))


def _quantised(seed: int = 3, n: int = 4000, **hold):
    """A small random model with the stage on, its blob model and (n, 5) wavelengths (nm): a
    walk with about a third of it in contact, stretches where it stands still (:data:`STILL`)
    and a few lost peaks (one inside a still stretch)."""
    model = make_random_model(seed, sizes=((16, 8), (16, 8), (16, 8)), n_taps=7, sigma=2.0,
                              memory=artifact.Memory(ema_shifts=(4,), play_widths=(0.1,), loc_shift=3))
    model.in_use = artifact.InUse(contact_rise_samples=1, **{**QUICK, **hold})
    wl = make_random_walk(model, n, seed, step_nm=0.0015)
    x = floatref.features(model, wl, model.baseline_nm)
    logits = model.contact.forward(x[:, :model.preprocess.n_features])
    margin = logits[:, 1] - logits[:, 0]
    for start, length in STILL:
        # Stand still where the nets read contact, whatever the walk did there.
        at = start + int(np.argmax(margin[start:start + 200]))
        wl[start:start + length] = wl[at]
    x = floatref.features(model, wl, model.baseline_nm)
    logits = model.contact.forward(x[:, :model.preprocess.n_features])
    margin = logits[:, 1] - logits[:, 0]
    still = min(float(margin[start + 20:start + length].min()) for start, length in STILL)
    model.contact.biases[-1][1] -= min(float(np.quantile(margin, 0.6)), still - 0.05)
    q, _ = qz.quantize(model, qz.calibrate(model, [(wl, model.baseline_nm)]))
    wl[2600, 2] = 0.0          # a lost peak inside the third still stretch
    for start in (200, 1200, 3100):
        wl[start, int(start % 5)] = 0.0
    return model, q, wl


def _off(q: QModel) -> QModel:
    return dataclasses.replace(q, **qz.quantize_hold(artifact.InUse()))


def test_every_kernel_equals_the_integer_reference():
    """Portable C and every host kernel, packed or not, equal export/intref.py bit for bit
    with the stage on, faults and all; and the stage changes the force (a runtime that
    ignored it would fail)."""
    model, q, wl = _quantised()
    assert q.hold_gain_q15 == round(0.1 * 2**15) and q.hold_settle == 40
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    ref = intref.run(q, wl_fm, base)
    assert np.count_nonzero(ref["status"] & FAULT) >= 4 and 0.1 < ref["contact"].mean() < 0.95
    off = intref.run(_off(q), wl_fm, base)
    assert np.count_nonzero(ref["force_mN"] != off["force_mN"]) > 300
    for kernel in ["portable"] + host_kernels():
        for packed in ([False, True] if kernel in PACKED_KERNELS else [False]):
            rt = Runtime(blob.to_bytes(q), kernel=kernel, packed=packed)
            rt.set_baseline(base.astype(np.int32))
            _equal(rt.run_raw(wl_fm), ref, f"{kernel} packed={packed}")


def test_the_rule_as_written():
    """Against the same model with the stage off: contact, location and margin never change;
    a still stretch shorter than the settle keeps its force; a long one ends with the whole
    gain, ``rshift_round(f * gain_q15, 15)`` more (the stretch's last 120 samples: its first
    ones still carry the memory's settling, which the band refuses); a fault inside it holds
    the stage, so the sample after the fault has the whole gain at once; samples without
    contact carry no force."""
    model, q, wl = _quantised()
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    on, off = intref.run(q, wl_fm, base), intref.run(_off(q), wl_fm, base)
    for k in ("contact", "x_um", "y_um", "contact_margin_q8"):
        assert np.array_equal(on[k], off[k]), k
    f = off["force_mN"]
    extra = on["force_mN"] - f
    whole = (f * q.hold_gain_q15 + (1 << 14)) >> 15
    short_start, short_len = STILL[1]
    assert not extra[short_start - 50:short_start + short_len + 5].any()
    for start, length in (STILL[0], STILL[2], STILL[3]):
        seg = slice(start + length - 120, start + length)
        assert on["contact"][seg].all()
        good = (on["status"][seg] & FAULT) == 0
        assert np.array_equal(extra[seg][good], whole[seg][good]), start
        assert np.count_nonzero(whole[seg]) > 0.9 * good.sum()
    assert on["status"][2600] & FAULT and extra[2601] == whole[2601] != 0
    assert not on["force_mN"][on["contact"] == 0].any()


@pytest.mark.parametrize("kernel", ["portable"] + host_kernels())
def test_reset_tare_and_baseline_clear_it_and_a_fault_holds_it(kernel):
    """``fbg_state``'s hold members: set while a still stretch is held, unchanged by a faulty
    sample, cleared by a sample without contact, by a reset, a tare and a new baseline; from
    each the C state equals a fresh integer reference."""
    model, q, wl = _quantised(seed=5)
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    rt = Runtime(blob.to_bytes(q), kernel=kernel)
    st = rt._state
    rt.set_baseline(base.astype(np.int32))
    got = rt.run_raw(wl_fm[:900])
    _equal(got, intref.run(q, wl_fm[:900], base), "set_baseline")
    assert st.hold_primed == 1 and st.hold_run == q.hold_settle + (1 << q.hold_ramp_shift)
    held = (st.hold_avg, st.hold_primed, st.hold_run)
    lost = wl_fm[900:901].copy()
    lost[0, 1] = 0
    assert rt.run_raw(lost)["status"][0] & FAULT
    assert (st.hold_avg, st.hold_primed, st.hold_run) == held
    rt.reset()
    assert st.hold_primed == 0 and st.hold_run == 0
    rt.run_raw(wl_fm[901:1000])
    rt.tare(wl[2250:2300])
    assert st.hold_primed == 0 and st.hold_run == 0
    tared = np.asarray(rt.baseline_fm, dtype=np.int64)
    _equal(rt.run_raw(wl_fm[2300:2800]), intref.run(q, wl_fm[2300:2800], tared), "tare")
    rt.set_baseline(base.astype(np.int32))
    assert st.hold_primed == 0 and st.hold_run == 0
    _equal(rt.run_raw(wl_fm[2800:4000]), intref.run(q, wl_fm[2800:4000], base), "baseline")
    out = intref.run(q, wl_fm[2800:4000], base)
    if not out["contact"][-1]:
        assert st.hold_primed == 0 and st.hold_run == 0


def test_float_engines_follow_the_same_rule():
    """FloatPipeline fed in pieces equals it fed at once (the stage carries over), takes the
    gain where the fixed point does, and the C float build follows it."""
    model, q, wl = _quantised(seed=6)
    flt = floatref.FloatPipeline(model, model.baseline_nm).push(wl)
    pipe = floatref.FloatPipeline(model, model.baseline_nm)
    cuts = (0, 1, 70, 650, 1000, 2400, 4000)
    pieces = [pipe.push(wl[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
    # (Equal but for the last bit: numpy's matrix products round by the batch's shape.)
    np.testing.assert_allclose(np.concatenate([p["force_N"] for p in pieces]), flt["force_N"],
                               rtol=1e-12, atol=0)
    plain = dataclasses.replace(model, in_use=dataclasses.replace(model.in_use, hold_gain=0.0))
    flt_off = floatref.FloatPipeline(plain, model.baseline_nm).push(wl)
    start, length = STILL[2]
    late = slice(start + length - 100, start + length)
    np.testing.assert_allclose(flt["force_N"][late], 1.1 * flt_off["force_N"][late], rtol=1e-12)
    short_start, short_len = STILL[1]
    around = slice(short_start - 50, short_start + short_len + 5)
    np.testing.assert_array_equal(flt["force_N"][around], flt_off["force_N"][around])
    rt = FloatRuntime(model)
    rt.set_baseline(model.baseline_nm)
    c = rt.run(wl)
    both = (c["contact"] == 1) & flt["contact"]
    assert both.mean() > 0.2
    np.testing.assert_allclose(np.asarray(c["force_N"])[both], flt["force_N"][both], rtol=0, atol=2e-3)
    assert rt._state.hold_primed in (0, 1)


def test_the_fields_are_range_checked_by_every_reader():
    """A gain beyond 2^12 in Q15 (12.5 %), a ramp shift above 12, or a gain without an
    average's shift: the blob readers (C and Python) give FBG_ERR_RANGE, the float model
    refuses them, and the C float build refuses a model that got past that check."""
    model, q, _ = _quantised()
    good = blob.to_bytes(q)
    slot = {f.name: (o, contract.CTYPES[ctype][2]) for o, ctype, f in mutate.param_slots()
            if f.name.startswith("hold_")}
    top = contract.LIMIT["MAX_HOLD_GAIN_Q15"]
    for name, value in (("hold_gain_q15", top + 1), ("hold_gain_q15", -top - 1),
                        ("hold_ramp_shift", contract.LIMIT["MAX_HOLD_RAMP_SHIFT"] + 1),
                        ("hold_shift", 0), ("hold_band_q15", (1 << 15) + 1)):
        o, size = slot[name]
        data = bytearray(good)
        data[o:o + size] = value.to_bytes(size, "little", signed=value < 0)
        assert mutate.c_verdict(mutate.fix_crc(data)) == "FBG_ERR_RANGE", name
        assert mutate.python_verdict(mutate.fix_crc(data)) == "FBG_ERR_RANGE", name
    o, size = slot["hold_gain_q15"]
    data = bytearray(good)
    data[o:o + size] = b"\0\0"      # the gain 0 is off, whatever the other fields say
    assert mutate.c_verdict(mutate.fix_crc(data)) == "FBG_OK"
    for bad in ({"hold_gain": 0.2, "hold_shift": 7}, {"hold_gain": 0.01, "hold_shift": 0},
                {"hold_gain": 0.01, "hold_shift": 7, "hold_ramp_shift": 13},
                {"hold_band_frac": 1.5}, {"hold_band_N": -1.0}):
        with pytest.raises(ValueError, match="hold_"):
            artifact.InUse(**bad)
    model.in_use.hold_gain = 0.2      # past the check
    with pytest.raises(RangeError):
        FloatRuntime(model)


def test_recommended_sets_the_stage_from_the_gain():
    """The trainer's gain turns the stage on with the documented settle, band, average and
    ramp at the model's rate (clipped to the bound), the band widened to a multiple of the
    nets' scatter on held loads where that is larger; no gain leaves every field 0, and a model
    saved without the fields loads with the stage off."""
    on = artifact.InUse.recommended(1000.0, hold_gain=0.008)
    assert (on.hold_gain, on.hold_settle, on.hold_band_N, on.hold_band_frac, on.hold_shift,
            on.hold_ramp_shift) == (0.008, 200, artifact.HOLD_BAND_N, artifact.HOLD_BAND_FRACTION, 7, 8)
    assert artifact.InUse.recommended(500.0, hold_gain=0.008).hold_settle == 100
    # A pad whose nets scatter more on a held load gets a band that scatter rarely leaves.
    noisy = artifact.InUse.recommended(1000.0, hold_gain=0.008, hold_noise_N=0.3)
    assert artifact.HOLD_BAND_NOISE * 0.3 > artifact.HOLD_BAND_N
    assert noisy.hold_band_N == pytest.approx(artifact.HOLD_BAND_NOISE * 0.3)
    assert artifact.InUse.recommended(1000.0, hold_gain=0.008,
                                      hold_noise_N=0.05).hold_band_N == artifact.HOLD_BAND_N
    assert artifact.InUse.recommended(1000.0, hold_noise_N=0.3).hold_band_N == 0.0
    assert artifact.InUse.recommended(1000.0, hold_gain=1.0).hold_gain == artifact.HOLD_GAIN_MAX
    off = artifact.InUse.recommended(1000.0)
    assert not any(getattr(off, k) for k in QUICK)
    saved = {k: v for k, v in on.to_json().items() if not k.startswith("hold_")}
    assert artifact.InUse(**saved).hold_gain == 0.0
    assert qz.quantize_hold(off) == {k: 0 for k in qz.quantize_hold(off)}
    assert qz.quantize_hold(on)["hold_gain_q15"] == round(0.008 * 2**15)


@pytest.mark.parametrize("gain_q15", [contract.LIMIT["MAX_HOLD_GAIN_Q15"],
                                      -contract.LIMIT["MAX_HOLD_GAIN_Q15"]])
def test_the_stage_at_its_bounds_is_exact(gain_q15):
    """The stress model (its force saturated at +-(2^31 - 1) mN) with the largest gain either
    way, the slowest average, the whole band and the longest ramp: the product reaches
    2^31 * 2^12 * 2^12 = 2^55, under the 2^63 docs/fixed-point.md proves, the force saturates
    and is flagged, and every host kernel equals the integer reference bit for bit."""
    hc = _hardcases()
    ramp_shift = contract.LIMIT["MAX_HOLD_RAMP_SHIFT"]
    q = dataclasses.replace(
        hc.stress_qmodel(width=16, n_layers=3, n_taps=8), hold_gain_q15=gain_q15,
        hold_settle=0, hold_band_mN=contract.SAT32, hold_band_q15=1 << 15,
        hold_shift=contract.LIMIT["MAX_EMA_SHIFT"], hold_ramp_shift=ramp_shift)
    q.check()
    n = (1 << ramp_shift) + 64
    wl = np.vstack([hc.stress_inputs(q, 1, n), hc.stress_inputs(q, -1, n)])
    base = np.asarray(q.baseline_fm, dtype=np.int64)
    ref = intref.run(q, wl, base)
    off = intref.run(_off(q), wl, base)
    force = off["force_mN"][ref["contact"] == 1]
    assert np.abs(force).max() >= contract.SAT32 - 1000     # the nets' force at its bound
    on = ref["contact"] == 1
    if gain_q15 > 0:     # pushed past the bound: held there, flagged, never wrapped
        at_bound = on & (np.abs(off["force_mN"]) == contract.SAT32)
        assert at_bound.sum() > 1000
        assert np.array_equal(ref["force_mN"][at_bound], off["force_mN"][at_bound])
        assert (ref["status"][at_bound] & contract.STATUS_FLAG["SATURATED"]).all()
    else:                # the whole gain, 1/8 off the bound, reached after the ramp
        assert (np.abs(ref["force_mN"][on]) <= contract.SAT32).all()
        assert abs(int(ref["force_mN"][n - 1])) == contract.SAT32 - ((contract.SAT32 + 4) >> 3)
    for kernel in ["portable"] + host_kernels():
        rt = Runtime(blob.to_bytes(q), kernel=kernel)
        rt.set_baseline(base.astype(np.int32))
        _equal(rt.run_raw(wl), ref, kernel)
