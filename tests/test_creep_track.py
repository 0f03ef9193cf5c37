"""The at-rest tracker's creep term (``track_creep``, ``track_creep_shift``): the tracker sums
``f - m * L`` at rest, ``L`` each strain grating's first-order average of its filtered shift
(docs/runtime.md, "In use"; docs/fixed-point.md).

The C fixed point equals the integer reference bit for bit on every host kernel through
presses, rests, faults, tares, resets and new baselines; the float engines (FloatPipeline, the
C float build) follow the same rule; on a recording whose rests carry the pad's creep the term
keeps the tracked baseline at the true zero, which the tracker without it leaves; a model
without the fields is the model it was. (The Cortex-M4 builds run it in tests/test_target.py.)
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from conftest import make_random_model, make_random_walk
from fbgforce import contract
from fbgforce.model import freshness
from fbgforce.model import artifact, floatref, modeldir
from fbgforce.export import blob, intref, mutate
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import QModel
from fbgforce.geometry import NOMINAL
from fbgforce.pybind import PACKED_KERNELS, FloatRuntime, RangeError, Runtime
from test_simd import host_kernels
from test_temp_reference import VERSION6_DIGEST, assert_version6_export, version6_model

FIELDS = contract.OUTPUT_FIELDS
FAULT = contract.STATUS_FLAG["SENSOR_FAULT"]
#: A tracker that learns within a short recording (short settle, fast, a few pm of bound).
QUICK = artifact.InUse(contact_on_margin=0.05, contact_off_margin=-0.05, contact_rise_samples=3,
                 track_shift=5, track_settle=40, track_step_max_pm=20.0, track_limit_pm=60.0)


def _quantised(track_creep: float, track_creep_shift: int, seed: int = 3, n: int = 4000,
               **preprocess: Any):
    """A small random model with the quick tracker and the creep term (and the preprocessing
    fields ``preprocess``), its blob model and (n, 5) wavelengths (nm): a walk with about a
    third of it in contact and lost peaks."""
    model = make_random_model(seed, sizes=((16, 8), (16, 8), (16, 8)), n_taps=7, sigma=2.0,
                              memory=artifact.Memory(ema_shifts=(4,), play_widths=(0.1,), loc_shift=3))
    model.preprocess = dataclasses.replace(model.preprocess, **preprocess)
    model.in_use = dataclasses.replace(QUICK, track_creep=track_creep,
                                       track_creep_shift=track_creep_shift)
    wl = make_random_walk(model, n, seed, step_nm=0.0015)
    x = floatref.features(model, wl, model.baseline_nm)
    logits = model.contact.forward(x[:, :model.preprocess.n_features])
    model.contact.biases[-1][1] -= float(np.quantile(logits[:, 1] - logits[:, 0], 0.66))
    q, _ = qz.quantize(model, qz.calibrate(model, [(wl, model.baseline_nm)]))
    rng = np.random.default_rng(seed)
    for start in rng.integers(100, n - 50, 6):
        wl[start:start + int(rng.integers(1, 30)), int(rng.integers(5))] = 0.0
    return model, q, wl


def _equal(c: dict[str, np.ndarray], ref: dict[str, np.ndarray], what: str) -> None:
    for k in FIELDS:
        bad = np.flatnonzero(np.asarray(c[k], dtype=np.int64) != ref[k])
        assert bad.size == 0, f"{what}: {k} differs at {bad[:5]}"


def _run_ref(q: QModel, wl_fm: np.ndarray, base: np.ndarray,
             rt: Runtime | None = None, state: str = "creep") -> tuple[dict, np.ndarray]:
    """The integer reference from a fresh state on ``base``: outputs and the end baseline;
    with ``rt`` (run on the same samples), checks that its states ``state`` (``fbg_state``'s
    member, the reference's ``end`` key) are the reference's."""
    end: dict = {}
    out = intref.run(q, wl_fm, base, end=end)
    if rt is not None:
        assert list(getattr(rt._state, state)) == end[state].tolist()
    return out, end["baseline_fm"]


@pytest.mark.parametrize("creep, creep_shift", [(0.5, 3), (0.05, 10), (0.2, 15)])
def test_every_kernel_equals_the_integer_reference(creep, creep_shift):
    """Portable C and every host kernel, packed or not, equal export/intref.py bit for bit
    with the creep term on (its largest magnitude included), faults and all, and reach the
    same tracked baseline; and the term moves that baseline (the test would not notice a
    runtime that ignored it)."""
    model, q, wl = _quantised(creep, creep_shift)
    assert q.track_creep_q15 == round(creep * 2**15) and q.track_creep_shift == creep_shift
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    _, reached = assert_every_kernel(q, wl_fm, base, "creep")
    _, untermed = _run_ref(dataclasses.replace(q, track_creep_q15=0, track_creep_shift=0), wl_fm, base)
    assert not np.array_equal(untermed, reached)


def assert_every_kernel(q: QModel, wl_fm: np.ndarray, base: np.ndarray, state: str
                        ) -> tuple[dict, np.ndarray]:
    """Portable C and every host kernel, packed or not, from a new baseline ``base``: the
    outputs, the tracked baseline and ``fbg_state``'s ``state`` equal the integer
    reference's (whose recording must hold faults and a share of contact); returns the
    reference's outputs and end baseline."""
    ref, reached = _run_ref(q, wl_fm, base)
    assert np.count_nonzero(ref["status"] & FAULT) > 6 and 0.1 < ref["contact"].mean() < 0.95
    for kernel in ["portable"] + host_kernels():
        for packed in ([False, True] if kernel in PACKED_KERNELS else [False]):
            rt = Runtime(blob.to_bytes(q), kernel=kernel, packed=packed)
            rt.set_baseline(base.astype(np.int32))
            _equal(rt.run_raw(wl_fm), ref, f"{kernel} packed={packed}")
            assert np.array_equal(np.asarray(rt.baseline_fm, dtype=np.int64), reached)
            _run_ref(q, wl_fm, base, rt, state)
    return ref, reached


@pytest.mark.parametrize("kernel", ["portable"] + host_kernels())
def test_tare_reset_and_baseline_reprime_and_faults_hold(kernel):
    """A faulty sample leaves the creep states as they were; after a reset, a tare and a new
    baseline the next good sample primes them again (the C state from there equals a fresh
    integer reference, end baseline included)."""
    model, q, wl = _quantised(0.5, 8, seed=5)
    assert_reprimes(model, q, wl, kernel, "creep", "mem_primed")


def assert_reprimes(model: artifact.HierarchicalModel, q: QModel, wl: np.ndarray, kernel: str,
                    state: str, primed: str) -> None:
    """On ``kernel``, ``fbg_state``'s ``state`` (primed when ``primed`` is set) holds through
    a faulty sample and is primed again after a reset, a tare and a new baseline: from each,
    outputs, states and end baseline equal a fresh integer reference's (:func:`_run_ref`)."""
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    rt = Runtime(blob.to_bytes(q), kernel=kernel)
    st = rt._state

    def segment(start: int, stop: int, on: np.ndarray, what: str) -> None:
        """The C state on samples start..stop equals a fresh reference on the baseline
        ``on``: outputs, the tracked baseline and the creep states."""
        got = rt.run_raw(wl_fm[start:stop])
        ref, end = _run_ref(q, wl_fm[start:stop], on, rt, state)
        _equal(got, ref, what)
        assert np.array_equal(np.asarray(rt.baseline_fm, dtype=np.int64), end), what

    rt.set_baseline(base.astype(np.int32))
    segment(0, 1500, base, "set_baseline")
    before = list(getattr(st, state))
    assert getattr(st, primed) == 1 and any(before)
    lost = wl_fm[1500:1501].copy()
    lost[0, 2] = 0
    assert rt.run_raw(lost)["status"][0] & FAULT
    assert list(getattr(st, state)) == before
    # Reset: the baseline the tracker reached stays, the states are primed again.
    reached = np.asarray(rt.baseline_fm, dtype=np.int64)
    rt.reset()
    assert getattr(st, primed) == 0
    segment(1501, 2500, reached, "reset")
    rt.tare(wl[2500:2600])
    assert getattr(st, primed) == 0
    segment(2600, 3300, np.asarray(rt.baseline_fm, dtype=np.int64), "tare")
    rt.set_baseline(base.astype(np.int32))
    assert getattr(st, primed) == 0
    segment(3300, 4000, base, "set_baseline again")


def pushed_in_pieces(model: artifact.HierarchicalModel, wl: np.ndarray
                     ) -> tuple[floatref.FloatPipeline, list[dict], floatref.FloatPipeline, dict]:
    """``wl`` (2000 samples) through one FloatPipeline in pieces of 1 to 1000 samples and
    through another at once: each pipeline and its outputs."""
    pipe = floatref.FloatPipeline(model, model.baseline_nm)
    cuts = (0, 1, 70, 333, 1000, 2000)
    pieces = [pipe.push(wl[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
    whole_pipe = floatref.FloatPipeline(model, model.baseline_nm)
    return pipe, pieces, whole_pipe, whole_pipe.push(wl)


def test_float_engines_follow_the_same_rule():
    """FloatPipeline fed in pieces equals it fed at once (the creep states carry over), its
    states are the rule written out (primed by the first good sample, held by a faulty one),
    and the C float build, also after a reset, a tare and a new baseline, follows
    FloatPipeline started there: the same decisions and the same tracked baseline."""
    model, _, wl = _quantised(0.5, 4, seed=6)
    wl[0, 1] = np.nan          # the first sample faulty: the second primes
    pipe, pieces, whole_pipe, whole = pushed_in_pieces(model, wl[:2000])
    assert np.array_equal(np.concatenate([p["contact"] for p in pieces]), whole["contact"])
    np.testing.assert_allclose(pipe.baseline_nm, whole_pipe.baseline_nm, rtol=0, atol=1e-12)
    assert not np.allclose(pipe.baseline_nm, model.baseline_nm, rtol=0, atol=1e-7)
    # The rule written out on a fresh pipeline's first samples (a zero filter history): a
    # faulty sample leaves no state, the first good one primes L = f, the next steps it, a
    # faulty one holds it.
    k, taps = 4, model.preprocess.runtime_taps()
    good = wl[1:3]
    comp = floatref.compensate(model, good, model.baseline_nm, [None], np.zeros(2, dtype=bool))
    f1, f2 = taps[0] * comp[0], taps[0] * comp[1] + taps[1] * comp[0]
    fresh = floatref.FloatPipeline(model, model.baseline_nm)
    fresh.push(wl[0:1])
    assert fresh._track_creep is None
    fresh.push(wl[1:2])
    np.testing.assert_allclose(fresh._track_creep, f1, rtol=1e-12)
    fresh.push(wl[2:3])
    np.testing.assert_allclose(fresh._track_creep, f1 + (f2 - f1) / 2.0**k, rtol=1e-12)
    held = fresh._track_creep.copy()
    fresh.push(wl[0:1])
    assert np.array_equal(fresh._track_creep, held)

    rt = FloatRuntime(model)
    rt.set_baseline(model.baseline_nm)
    c = rt.run(wl[:2000])
    ok = (c["status"] & FAULT) == 0
    assert np.array_equal(ok, whole["status"] == 0)
    assert np.mean(c["contact"][ok] == whole["contact"][ok]) > 0.995
    np.testing.assert_allclose(list(rt._state.creep_pm), whole_pipe._track_creep, rtol=1e-4, atol=1e-3)
    moved = (whole_pipe.baseline_nm - model.baseline_nm)[:4] * 1000.0
    np.testing.assert_allclose(_float_correction_pm(rt), moved, rtol=0, atol=2e-3)

    def follows(start: int, stop: int, base: np.ndarray) -> None:
        """The C float build from here is FloatPipeline started on ``base`` (the tare, and
        the correction the build holds through a reset)."""
        held = np.array(list(rt._state.held_pm))
        flt_pipe = floatref.FloatPipeline(model, base + np.r_[held, 0.0] / 1000.0)
        flt = flt_pipe.push(wl[start:stop])
        got = rt.run(wl[start:stop])
        assert np.mean(got["contact"] == flt["contact"]) > 0.995
        np.testing.assert_allclose(_float_correction_pm(rt) - held,
                                   (flt_pipe.baseline_nm - base)[:4] * 1000.0 - held, rtol=0, atol=2e-3)

    rt.reset()
    follows(2000, 2800, rt.baseline_nm)
    tared = rt.tare(wl[2800:2850])
    follows(2850, 3400, tared)
    rt.set_baseline(model.baseline_nm)
    follows(3400, 4000, model.baseline_nm)


def _float_correction_pm(rt: FloatRuntime) -> np.ndarray:
    """The C float build's tracked correction of the strain baselines (pm): it subtracts it
    from the compensated shifts instead of moving baseline_fm."""
    return np.array(list(rt._state.held_pm)) + np.array(list(rt._state.drift_pm))


#: The pad's creep in the effect test: a few % with a time constant of 2^10 samples (1 s).
CREEP, CREEP_SHIFT = 0.05, 10


def _creeping_presses(model: artifact.HierarchicalModel, force_N: float = 20.0, cycles: int = 12
                      ) -> np.ndarray:
    """(n, 5) wavelengths (nm) of a square load on the nominal pad at its tare, without drift:
    2 s rests and 1 s presses of ``force_N``, whose gratings read ``(1 - m) * F + m *
    lag(F)`` (the pad's creep, lag first order with time constant 2^CREEP_SHIFT samples):
    every rest opens with a decaying residual ``m * lag(F)`` of the press before it."""
    f = np.r_[np.zeros(2000), np.tile(np.r_[np.zeros(2000), np.full(1000, force_N)], cycles),
              np.zeros(3000)]
    lag = np.zeros_like(f)
    for i in range(1, f.size):
        lag[i] = lag[i - 1] + (f[i] - lag[i - 1]) / 2.0**CREEP_SHIFT
    design = NOMINAL.replace(base_wl_nm=model.baseline_nm)
    wl = design.forward((1.0 - CREEP) * f + CREEP * lag, np.full(f.size, 10.0), np.full(f.size, 13.0))
    return wl + np.random.default_rng(0).normal(0.0, 3e-4, wl.shape)


def test_the_creep_term_keeps_the_tracked_baseline_at_the_true_zero(small_exported_dir):
    """Presses on a pad that creeps back after each release, at constant temperature (the
    true baseline is the tare): the tracker without the term learns the residual as drift
    and moves every strain baseline by more than 0.5 pm; with it (the C fixed point, the
    float model and the C float build alike) every one stays within 0.2 pm."""
    # The term is for nets trained on shifts that still carry the creep: the front's creep
    # inverse (on in the trainer's models) is turned off here. These nets were trained with
    # it, so they read the first part of each recovery as a light load: contact lasts
    # longer than the 1 s presses (half the samples, a third of them pressed).
    loaded = modeldir.load(small_exported_dir)
    model = dataclasses.replace(loaded, preprocess=dataclasses.replace(
        loaded.preprocess, creep=0.0, creep_shift=0))
    q = dataclasses.replace(blob.load_model_blob(small_exported_dir), creep_q15=0, creep_shift=0)
    assert model.in_use.track_shift
    wl = _creeping_presses(model)
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    moved = {}
    for on in (False, True):
        qq = dataclasses.replace(q, track_creep_q15=round(CREEP * 2**15) if on else 0,
                                 track_creep_shift=CREEP_SHIFT if on else 0)
        rt = Runtime(blob.to_bytes(qq))
        rt.set_baseline(base.astype(np.int32))
        out = rt.run_raw(wl_fm)
        assert 0.25 < out["contact"].mean() < 0.6
        moved[on] = (np.asarray(rt.baseline_fm, dtype=np.int64) - base)[:4] / 1000.0
    assert np.all(np.abs(moved[False]) > 0.5), moved
    assert np.all(np.abs(moved[True]) < 0.2), moved
    flt_model = dataclasses.replace(model, in_use=dataclasses.replace(
        model.in_use, track_creep=CREEP, track_creep_shift=CREEP_SHIFT))
    pipe = floatref.FloatPipeline(flt_model, model.baseline_nm)
    pipe.push(wl)
    assert np.all(np.abs(pipe.baseline_nm - model.baseline_nm)[:4] * 1000.0 < 0.2)
    rt = FloatRuntime(flt_model)
    rt.set_baseline(model.baseline_nm)
    rt.run(wl)
    assert np.all(np.abs(_float_correction_pm(rt)) < 0.2)


def test_a_model_without_the_fields_is_the_model_it_was(tmp_path):
    """An old model.json (no track_creep, no track_creep_shift, no ref_shift) loads with the
    term off and exports the blob the version 6 exporter wrote, apart from the header's
    version and CRC (the fields sit in what was the parameter block's padding), with the
    freshness digest its export recorded (both taken with that exporter; see
    tests/test_temp_reference.py); the term on changes the digest and only its own bytes."""
    old, wl = version6_model(tmp_path)
    assert old.in_use.track_creep == 0.0 and old.in_use.track_creep_shift == 0
    q = assert_version6_export(old, wl)
    assert q.track_creep_q15 == q.track_creep_shift == 0
    on = dataclasses.replace(old, in_use=dataclasses.replace(old.in_use, track_creep=0.05,
                                                             track_creep_shift=10))
    assert freshness.model_digest(on) != VERSION6_DIGEST
    q_on, _ = qz.quantize(on, qz.calibrate(on, [(wl, on.baseline_nm)]))
    new = blob.to_bytes(q_on)
    slots = [o for o, _, f in mutate.param_slots() if f.name.startswith("track_creep")]
    differ = [i for i, (a, b) in enumerate(zip(new, blob.to_bytes(q))) if a != b]
    assert set(differ) - {12, 13, 14, 15} <= set(range(min(slots), max(slots) + 1))
    assert q_on.track_creep_q15 == 1638 and q_on.track_creep_shift == 10


def test_the_fields_are_range_checked_by_every_reader():
    """A magnitude above 0.5 (2^14 in Q15), a shift above 15, or a magnitude without a shift:
    the blob readers (C and Python) give FBG_ERR_RANGE, the float model refuses them, and
    the C float build refuses a model that got past that check."""
    model, q, _ = _quantised(0.05, 10, n=400)
    good = blob.to_bytes(q)
    slot = {f.name: o for o, _, f in mutate.param_slots() if f.name.startswith("track_creep")}
    for name, value in (("track_creep_q15", contract.LIMIT["MAX_TRACK_CREEP_Q15"] + 1),
                        ("track_creep_shift", contract.LIMIT["MAX_EMA_SHIFT"] + 1),
                        ("track_creep_shift", 0)):
        data = bytearray(good)
        size = 2 if name == "track_creep_q15" else 1
        data[slot[name]:slot[name] + size] = value.to_bytes(size, "little")
        data = mutate.fix_crc(data)
        assert mutate.c_verdict(data) == mutate.python_verdict(data) == "FBG_ERR_RANGE", name
    # The shift alone, with the magnitude 0, is off: accepted.
    data = bytearray(good)
    data[slot["track_creep_q15"]:slot["track_creep_q15"] + 2] = b"\0\0"
    assert mutate.c_verdict(mutate.fix_crc(data)) == "FBG_OK"
    for bad in ({"track_creep": 0.6, "track_creep_shift": 10}, {"track_creep": -0.1},
                {"track_creep": 0.05, "track_creep_shift": 0},
                {"track_creep": 0.05, "track_creep_shift": 16},
                {"track_creep": 0.0, "track_creep_shift": 3}):
        with pytest.raises(ValueError, match="track_creep"):
            artifact.InUse(**bad)
    for creep, shift in ((0.6, 10), (0.05, 0), (0.05, 16)):
        model.in_use.track_creep, model.in_use.track_creep_shift = creep, shift  # past the check
        with pytest.raises(RangeError):
            FloatRuntime(model)


def test_recommended_converts_the_fitted_creep():
    """The trainer's fit (magnitude, time constant in samples) becomes the two fields in one
    place: the magnitude clipped to 0..0.5, the time constant the nearest power of two with
    k in 1..15; no creep leaves the term off, and the positional arguments are as before."""
    def fields(**kw):
        iu = artifact.InUse.recommended(1000.0, None, **kw)
        return iu.track_creep, iu.track_creep_shift

    assert fields() == (0.0, 0)
    assert fields(creep_magnitude=0.05, creep_time_constant_samples=1000.0) == (0.05, 10)
    assert fields(creep_magnitude=0.03, creep_time_constant_samples=700.0) == (0.03, 9)
    assert fields(creep_magnitude=0.8, creep_time_constant_samples=1e7) == (0.5, 15)
    assert fields(creep_magnitude=0.05, creep_time_constant_samples=1.2) == (0.05, 1)
    assert fields(creep_magnitude=0.0, creep_time_constant_samples=1000.0) == (0.0, 0)
    assert fields(creep_magnitude=0.05, creep_time_constant_samples=0.0) == (0.0, 0)
    assert artifact.InUse.recommended(1000.0, np.array([0.1, 0.2])).track_creep == 0.0


def _hardcases():
    """runtime_c/fuzz/hardcases.py (a script, not a package module), as tests/hardcase_support.py
    loads it."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "runtime_c" / "fuzz" / "hardcases.py"
    spec = importlib.util.spec_from_file_location("fbg_hardcases", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_the_creep_term_at_its_bounds_is_exact():
    """The stress model (every value saturated) with the creep term at its largest
    magnitude and its slowest average, z0 at +32767 and z swinging from +32767 to -32767: a
    sample's term reaches -65533, next to the bound 65534 docs/fixed-point.md proves, the
    block sums times the largest tracker gain come near 2^53, and every host kernel still
    equals the integer reference bit for bit."""
    hc = _hardcases()
    q = dataclasses.replace(
        hc.stress_qmodel(width=16, n_layers=3, n_taps=8), mean_fm=[-70_000] * 4,
        track_shift=1, track_settle=0, track_gain=[contract.SAT32] * 4,
        track_step_max_fm=contract.SAT32, track_limit_fm=contract.LIMIT["TRACK_LIMIT_MAX_FM"],
        track_creep_q15=contract.LIMIT["MAX_TRACK_CREEP_Q15"],
        track_creep_shift=contract.LIMIT["MAX_EMA_SHIFT"])
    z0, _ = q.z_rest()
    assert z0.tolist() == [contract.SAT16] * 4
    sat = np.array([[contract.SAT16] * 4] * 40 + [[-contract.SAT16] * 4] * 400, dtype=np.int64)
    terms = intref._RestTracker(q).rest_terms(sat, z0)
    assert terms.min() == -65533 and np.abs(terms).max() <= 65534
    wl = np.vstack([hc.stress_inputs(q, 1, 40), hc.stress_inputs(q, -1, 64 * 8)])
    base = np.asarray(q.baseline_fm, dtype=np.int64)
    ref, reached = _run_ref(q, wl, base)
    assert not np.array_equal(reached, base)      # the tracker ran on those sums
    for kernel in ["portable"] + host_kernels():
        rt = Runtime(blob.to_bytes(q), kernel=kernel)
        rt.set_baseline(base.astype(np.int32))
        _equal(rt.run_raw(wl), ref, kernel)
        assert np.array_equal(np.asarray(rt.baseline_fm, dtype=np.int64), reached), kernel
