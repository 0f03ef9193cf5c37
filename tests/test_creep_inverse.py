"""The pad's creep inverse (``Preprocess.creep``, ``creep_shift``): each good sample's
compensated shift ``c`` is replaced before the FIR by ``e = c + q (c - L)``, ``L`` the
first-order lag of ``e`` (docs/runtime.md, "Creep inverse"; docs/fixed-point.md).

The C fixed point equals the integer reference bit for bit on every host kernel through
presses, rests, faults, tares, resets and new baselines, at the rule's bounds too; the float
engines (the float model, FloatPipeline, the C float build) follow the same rule; a pad whose
gratings creep comes out of the inverse as the elastic strain it hides; a model without the
fields is the model it was. (The Cortex-M4 builds run it in tests/test_target.py.)
"""
from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import make_random_model
from fbgforce import contract
from fbgforce.model import freshness
from fbgforce.model import artifact, floatref, modeldir
from fbgforce.errors import InputError
from fbgforce.export import blob, intref, mutate
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import QModel
from fbgforce.pybind import FloatRuntime, RangeError, Runtime
import test_creep_track as creep_track
from test_creep_track import _equal, _hardcases
from test_simd import host_kernels
from test_temp_reference import VERSION6_DIGEST, assert_version6_export, version6_model

FAULT = contract.STATUS_FLAG["SENSOR_FAULT"]


def _with_creep(model: artifact.HierarchicalModel, creep: float, creep_shift: int) -> artifact.HierarchicalModel:
    return dataclasses.replace(model, preprocess=dataclasses.replace(
        model.preprocess, creep=creep, creep_shift=creep_shift))


def _quantised(creep: float, creep_shift: int, seed: int = 3, n: int = 4000):
    """The creep-term tests' small model (quick tracker, about a third in contact, lost
    peaks) with the creep inverse instead of the tracker's creep term."""
    return creep_track._quantised(0.0, 0, seed, n, creep=creep, creep_shift=creep_shift)


def _run_ref(q: QModel, wl_fm: np.ndarray, base: np.ndarray,
             rt: Runtime | None = None) -> tuple[dict, np.ndarray]:
    """The integer reference from a fresh state on ``base``, the creep inverse's states of
    ``rt`` checked against it."""
    return creep_track._run_ref(q, wl_fm, base, rt, "creep_acc")


@pytest.mark.parametrize("creep, creep_shift", [(0.5, 15), (0.05, 10), (0.3, 1)])
def test_every_kernel_equals_the_integer_reference(creep, creep_shift):
    """Portable C and every host kernel, packed or not, equal export/intref.py bit for bit
    with the inverse on (its largest gain and its shortest lag included), faults and all,
    with the same creep states and tracked baseline; and the inverse changes the outputs
    (the test would not notice a runtime that ignored it)."""
    model, q, wl = _quantised(creep, creep_shift)
    assert q.creep_q15 == round(model.preprocess.creep_gain * 2**15) > 0
    assert q.creep_shift == creep_shift
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    ref, _ = creep_track.assert_every_kernel(q, wl_fm, base, "creep_acc")
    off, _ = _run_ref(dataclasses.replace(q, creep_q15=0, creep_shift=0), wl_fm, base)
    assert not np.array_equal(off["force_mN"], ref["force_mN"])


@pytest.mark.parametrize("kernel", ["portable"] + host_kernels())
def test_tare_reset_and_baseline_reprime_and_faults_hold(kernel):
    """A faulty sample leaves the creep inverse's states as they were; after a reset, a tare
    and a new baseline the next good sample primes them again (the C state from there equals
    a fresh integer reference: outputs, states and end baseline)."""
    model, q, wl = _quantised(0.5, 8, seed=5)
    creep_track.assert_reprimes(model, q, wl, kernel,
                                "creep_acc", "creep_primed")


def test_the_inverse_at_its_bounds_is_exact():
    """The stress model (every value saturated) with the largest gain and the slowest lag,
    its compensated shifts swinging between the int32 bounds: the inverse clamps (SATURATED)
    and every host kernel still equals the integer reference bit for bit, states included."""
    hc = _hardcases()
    q = dataclasses.replace(hc.stress_qmodel(width=16, n_layers=3, n_taps=8),
                            creep_q15=contract.LIMIT["MAX_CREEP_Q15"],
                            creep_shift=contract.LIMIT["MAX_EMA_SHIFT"])
    wl = np.vstack([hc.stress_inputs(q, 1, 40), hc.stress_inputs(q, -1, 300),
                    hc.stress_inputs(q, 1, 300)])
    base = np.asarray(q.baseline_fm, dtype=np.int64)
    end: dict = {}
    ref = intref.run(q, wl, base, end=end)
    comp = np.full((2, 4), contract.SAT32, dtype=np.int64)
    comp[1] = -contract.SAT32
    e, clamped = intref.creep_inverse(q, comp, np.ones(2, dtype=bool), [None])
    assert clamped[1] and e[1].tolist() == [-contract.SAT32] * 4
    for kernel in ["portable"] + host_kernels():
        rt = Runtime(blob.to_bytes(q), kernel=kernel)
        rt.set_baseline(base.astype(np.int32))
        _equal(rt.run_raw(wl), ref, kernel)
        assert list(rt._state.creep_acc) == end["creep_acc"].tolist(), kernel


def test_float_engines_follow_the_same_rule():
    """FloatPipeline fed in pieces equals it fed at once (the lags carry over) and equals the
    float model's features; its lags are the rule written out (primed by the first good
    sample, held by a faulty one); the C float build, also after a reset, a tare and a new
    baseline, follows FloatPipeline started there."""
    model, _, wl = _quantised(0.5, 4, seed=6)
    wl[0, 1] = np.nan          # the first sample faulty: the second primes
    pipe, pieces, whole_pipe, whole = creep_track.pushed_in_pieces(model, wl[:2000])
    for key in ("contact", "force_N"):
        np.testing.assert_allclose(np.concatenate([p[key] for p in pieces]), whole[key],
                                   rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(pipe._creep_lag[0], whole_pipe._creep_lag[0], rtol=1e-10)
    # The rule written out on the first samples: a faulty one leaves no state, the first good
    # one primes L = c (e = c), the next gives e = c + q (c - L) and steps L, a faulty one holds.
    pre, k = model.preprocess, model.preprocess.creep_shift
    q = pre.creep_gain
    c = floatref.compensate(model, wl[1:3], model.baseline_nm, [None], np.zeros(2, dtype=bool))
    fresh = floatref.FloatPipeline(model, model.baseline_nm)
    fresh.push(wl[0:1])
    assert fresh._creep_lag[0] is None
    fresh.push(wl[1:2])
    np.testing.assert_allclose(fresh._creep_lag[0], c[0], rtol=1e-12)
    fresh.push(wl[2:3])
    e = c[1] + q * (c[1] - c[0])
    np.testing.assert_allclose(fresh._creep_lag[0], c[0] + (e - c[0]) / 2.0**k, rtol=1e-12)
    held = fresh._creep_lag[0].copy()
    fresh.push(wl[0:1])
    assert np.array_equal(fresh._creep_lag[0], held)
    # The float model's whole-recording features take the same inverse (faults and all).
    off = _with_creep(model, 0.0, 0)
    feats = floatref.features(model, wl[:2000], model.baseline_nm)
    assert not np.allclose(feats, floatref.features(off, wl[:2000], model.baseline_nm))
    np.testing.assert_allclose(floatref.predict(model, wl[:2000], model.baseline_nm)["force_N"],
                               floatref.FloatPipeline(model, model.baseline_nm).push(wl[:2000])["force_N"],
                               rtol=1e-9, atol=1e-9)

    rt = FloatRuntime(model)
    rt.set_baseline(model.baseline_nm)
    got = rt.run(wl[:2000])
    ok = (got["status"] & FAULT) == 0
    assert np.mean(got["contact"][ok] == whole["contact"][ok]) > 0.995
    np.testing.assert_allclose(list(rt._state.creep_lag_pm), whole_pipe._creep_lag[0],
                               rtol=1e-4, atol=2e-3)

    def follows(start: int, stop: int, base: np.ndarray) -> None:
        held = np.array(list(rt._state.held_pm))
        flt_pipe = floatref.FloatPipeline(model, base + np.r_[held, 0.0] / 1000.0)
        flt = flt_pipe.push(wl[start:stop])
        c_out = rt.run(wl[start:stop])
        assert rt._state.creep_primed == 1
        assert np.mean(c_out["contact"] == flt["contact"]) > 0.995
        np.testing.assert_allclose(list(rt._state.creep_lag_pm), flt_pipe._creep_lag[0],
                                   rtol=1e-4, atol=2e-3)

    rt.reset()
    assert rt._state.creep_primed == 0
    follows(2000, 2800, rt.baseline_nm)
    tared = rt.tare(wl[2800:2850])
    assert rt._state.creep_primed == 0
    follows(2850, 3400, tared)
    rt.set_baseline(model.baseline_nm)
    assert rt._state.creep_primed == 0
    follows(3400, 4000, model.baseline_nm)


#: The pad's creep in the effect test: 5 % with a time constant of 2^10 samples (1 s).
CREEP, CREEP_SHIFT = 0.05, 10


def _creeping_pad(model: artifact.HierarchicalModel) -> tuple[np.ndarray, np.ndarray]:
    """(n, 5) wavelengths (nm) of a square load at the tare, without drift or noise, as the
    elastic strain gives them (``e``) and as a creeping pad's gratings read them: every
    strain grating's shift ``(1 - m) e + m lag(e)``, lag first order with step 2^-CREEP_SHIFT
    (twelve 1 s presses of 300 pm and 2 s rests). The temperature grating does not creep."""
    load = np.r_[np.zeros(500), np.tile(np.r_[np.full(1000, 300.0), np.zeros(2000)], 12)]
    strain = load[:, None] * np.array([1.0, 0.7, 1.3, 0.9])
    lag = np.zeros_like(strain)
    for i in range(1, load.size):
        lag[i] = lag[i - 1] + (strain[i] - lag[i - 1]) / 2.0**CREEP_SHIFT
    read = (1.0 - CREEP) * strain + CREEP * lag
    base = model.baseline_nm
    elastic = np.hstack([base[:4] + strain / 1000.0, np.full((load.size, 1), base[4])])
    creeping = np.hstack([base[:4] + read / 1000.0, np.full((load.size, 1), base[4])])
    return elastic, creeping


def test_the_inverse_takes_the_pads_creep_out():
    """A pad whose gratings creep: its compensated shifts lag each press's edges by up to 5 %
    of the press (19.5 pm on the 390 pm grating) and carry a residual through each rest; the
    inverse's output is the elastic strain's compensated shifts throughout, within rounding in
    float (2e-10 pm measured) and within 20 fm in the fixed point (2 fm measured; the bound of
    docs/fixed-point.md allows about 13 here, mostly the Q15 gain's residue)."""
    model = _with_creep(make_random_model(0, sizes=((8,), (8,), (8,)), n_taps=5, sigma=1.5),
                        CREEP, CREEP_SHIFT)
    elastic, creeping = _creeping_pad(model)
    truth = floatref.compensate(model, elastic, model.baseline_nm)
    comp = floatref.compensate(model, creeping, model.baseline_nm)
    assert np.abs(comp - truth).max() > 10.0
    inverted = floatref.creep_inverse(model.preprocess, comp)
    assert np.abs(inverted - truth).max() < 1e-6
    # The fixed point on the same shifts in fm: the gain's Q15 and the roundings, a few fm.
    fixed = SimpleNamespace(**qz.quantize_creep(model.preprocess))   # all the rule reads
    comp_fm = np.rint(comp * 1000.0).astype(np.int64)
    e_fm, clamped = intref.creep_inverse(fixed, comp_fm, np.ones(len(comp_fm), dtype=bool), [None])
    assert not clamped.any()
    assert np.abs(e_fm - truth * 1000.0).max() < 20.0
    assert np.abs(comp_fm - truth * 1000.0).max() > 10_000.0


def test_a_model_without_the_fields_is_the_model_it_was(tmp_path):
    """An old model.json (no creep, no creep_shift, none of the fields since blob version 6)
    loads with the inverse off and exports the version 6 blob apart from the header and the
    creep inverse's zero bytes, with the freshness digest its export recorded; on, the
    digest changes and only the fields' own bytes (and the header) differ."""
    old, wl = version6_model(tmp_path)
    assert old.preprocess.creep == 0.0 and old.preprocess.creep_shift == 0
    q = assert_version6_export(old, wl)
    assert q.creep_q15 == q.creep_shift == 0
    on = _with_creep(old, 0.05, 10)
    assert freshness.model_digest(on) != VERSION6_DIGEST
    q_on, _ = qz.quantize(on, qz.calibrate(on, [(wl, on.baseline_nm)]))
    assert (q_on.creep_q15, q_on.creep_shift) == (round(on.preprocess.creep_gain * 2**15), 10)
    q_off = dataclasses.replace(q_on, creep_q15=0, creep_shift=0)
    new, plain = blob.to_bytes(q_on), blob.to_bytes(q_off)
    slots = [o for o, _, f in mutate.param_slots() if f.name.startswith("creep_")]
    differ = [i for i, (a, b) in enumerate(zip(new, plain)) if a != b]
    assert differ and set(differ) - {12, 13, 14, 15} <= set(range(min(slots), max(slots) + 2))
    # A model.json with a magnitude out of range: one error naming the directory and the field.
    doc = json.loads((tmp_path / modeldir.MODEL_JSON).read_text())
    doc["preprocess"].update(creep=0.7, creep_shift=10)
    (tmp_path / modeldir.MODEL_JSON).write_text(json.dumps(doc))
    with pytest.raises(InputError, match="creep must be 0 .. 0.5, not 0.7") as err:
        modeldir.load(tmp_path)
    assert err.value.path == str(tmp_path)


def test_the_fields_are_range_checked_by_every_reader():
    """A shift above 15, or a gain without a shift: the blob readers (C and Python) give
    FBG_ERR_RANGE; the float model refuses a magnitude outside 0..0.5 and a shift that does
    not go with it; the C float build refuses a model that got past that check."""
    model, q, _ = _quantised(0.05, 10, n=400)
    good = blob.to_bytes(q)
    slot = {f.name: o for o, _, f in mutate.param_slots() if f.name.startswith("creep_")}
    for name, value in (("creep_shift", contract.LIMIT["MAX_EMA_SHIFT"] + 1), ("creep_shift", 0)):
        data = bytearray(good)
        data[slot[name]] = value
        data = mutate.fix_crc(data)
        assert mutate.c_verdict(data) == mutate.python_verdict(data) == "FBG_ERR_RANGE", name
    data = bytearray(good)
    data[slot["creep_q15"]:slot["creep_q15"] + 2] = b"\0\0"
    assert mutate.c_verdict(mutate.fix_crc(data)) == "FBG_OK"    # the shift alone is off
    for bad in ({"creep": 0.6, "creep_shift": 10}, {"creep": -0.1, "creep_shift": 3},
                {"creep": 0.05, "creep_shift": 0}, {"creep": 0.05, "creep_shift": 16},
                {"creep": 0.0, "creep_shift": 3}):
        with pytest.raises(ValueError, match="creep"):
            dataclasses.replace(model.preprocess, **bad)
    for creep, shift in ((0.6, 10), (0.05, 16)):
        model.preprocess.creep, model.preprocess.creep_shift = creep, shift   # past the check
        with pytest.raises(RangeError):
            FloatRuntime(model)


def test_the_trainers_recordings_take_the_inverse_and_its_levels_do_not():
    """The trainer's features of a continuous recording (``recording_features``) take the
    inverse, as the runtimes do; its rows compensated one by one (``compensated``, which
    makes the synthetic holds and rests from levels) do not."""
    from fbgforce.trainer import preprocess as pp

    model = _with_creep(make_random_model(0, sizes=((8,), (8,), (8,)), n_taps=5, sigma=1.5),
                        CREEP, CREEP_SHIFT)
    pre, base = model.preprocess, model.baseline_nm
    _, creeping = _creeping_pad(model)
    comp = floatref.compensate(model, creeping, base)
    assert np.array_equal(pp.compensated(pre, creeping, base), comp)
    np.testing.assert_allclose(pp.recording_features(pre, creeping, base),
                               floatref.apply_filter(dataclasses.replace(pre, creep=0.0, creep_shift=0),
                                               floatref.creep_inverse(pre, comp)), rtol=0, atol=1e-9)
    assert np.abs(pp.recording_features(pre, creeping, base)
                  - floatref.apply_filter(dataclasses.replace(pre, creep=0.0, creep_shift=0), comp)).max() > 10.0
