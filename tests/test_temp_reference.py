"""The temperature reference's average (``ref_shift``): the reference grating's shift averaged
before it compensates the strain gratings (docs/fixed-point.md, "Temperature reference").

The C fixed point equals the integer reference bit for bit on every host kernel, through
faults, tares, resets and new baselines; the float engines (FloatPipeline, the C float build)
follow the same priming and holding; a model without the field is the model it was, blob
and all; the trainer keeps the average for independent grating noise and not for noise
common to all gratings. (The Cortex-M4 builds run it in tests/test_target.py.)
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from fbgforce.errors import InputError

from conftest import make_random_model, make_random_walk
from fbgforce import contract
from fbgforce.model import freshness
from fbgforce.model import artifact, floatref, modeldir
from fbgforce.export import blob, intref
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import QModel
from fbgforce.pybind import PACKED_KERNELS, FloatRuntime, Runtime
from fbgforce.trainer import preprocess as pp
from test_simd import _balance_contact, host_kernels

FIELDS = contract.OUTPUT_FIELDS
#: Independent interrogator noise per grating, nm (0.5 pm).
NOISE_NM = 5e-4


def _noisy_walk(model: artifact.HierarchicalModel, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_random_walk(model, n, seed) + rng.normal(0.0, NOISE_NM, (n, 5))


def _with_faults(wl: np.ndarray, seed: int) -> np.ndarray:
    """Lost peaks on the reference grating and on the others, single and in bursts."""
    rng = np.random.default_rng(seed)
    wl = wl.copy()
    for start in rng.integers(50, wl.shape[0] - 50, 8):
        wl[start:start + int(rng.integers(1, 30)), int(rng.integers(3, 5))] = 0.0
    return wl


def _quantised(ref_shift: int, seed: int = 4, n: int = 2000):
    """A small random model with the reference's average at ``ref_shift``, its blob model and
    noisy wavelengths (nm) around its baseline."""
    model = make_random_model(seed, sizes=((16, 8), (16, 8), (16, 8)), n_taps=7, sigma=2.0,
                              memory=artifact.Memory(ema_shifts=(4,), play_widths=(0.1,), loc_shift=3))
    model.preprocess = dataclasses.replace(model.preprocess, ref_shift=ref_shift)
    wl = _noisy_walk(model, n, seed)
    _balance_contact(model, wl)
    q, rep = qz.quantize(model, qz.calibrate(model, [(wl, model.baseline_nm)]))
    q.report = rep
    return model, q, wl


def _assert_equal(c: np.ndarray, ref: dict[str, np.ndarray], what: str) -> None:
    for k in FIELDS:
        assert np.array_equal(np.asarray(c[k], dtype=np.int64), ref[k]), (what, k)


@pytest.mark.parametrize("ref_shift", [1, 5, 8])
def test_every_kernel_equals_the_integer_reference(ref_shift):
    """Portable C and every host kernel (the AVX2 front included), packed or not, equal
    export/intref.py bit for bit with the reference averaged, faults included; and the
    average changes the outputs (the test would not notice a runtime that ignored it)."""
    model, q, wl = _quantised(ref_shift)
    wl_fm, base = intref.nm_to_fm(_with_faults(wl, 1)), intref.nm_to_fm(model.baseline_nm)
    ref = intref.run(q, wl_fm, base)
    assert np.count_nonzero(ref["status"] & contract.STATUS_FLAG["SENSOR_FAULT"]) > 8
    for kernel in ["portable"] + host_kernels():
        for packed in ([False, True] if kernel in PACKED_KERNELS else [False]):
            rt = Runtime(blob.to_bytes(q), kernel=kernel, packed=packed)
            rt.set_baseline(base.astype(np.int32))
            _assert_equal(rt.run_raw(wl_fm), ref, f"{kernel} packed={packed}")
    raw = intref.run(dataclasses.replace(q, ref_shift=0), wl_fm, base)
    assert not np.array_equal(raw["contact_margin_q8"], ref["contact_margin_q8"])


def _gain_shift(n: int, k: int) -> int:
    """min(k, floor(log2 n)), written out."""
    s = 0
    while s < k and 2 ** (s + 1) <= n:
        s += 1
    return s


def _expected_acc(shift_t: np.ndarray, good: np.ndarray, k: int) -> int:
    """The rule of docs/fixed-point.md written out: the n-th good sample moves r by
    (shift_T - r) / 2^min(k, floor(log2 n)) (the first sets it), a faulty one leaves it."""
    acc, n = 0, 0
    for x, ok in zip(shift_t.tolist(), good.tolist()):
        if ok:
            n += 1
            r = (acc + (1 << (k - 1))) >> k
            acc = x << k if n == 1 else acc + (x - r) * 2 ** (k - _gain_shift(n, k))
    return acc


def test_the_first_samples_average_to_their_mean_not_to_the_first():
    """Over its first 2^k good samples the average is their running mean to within a factor
    of two in each weight (every engine: the integer reference here, the C kernels equal it
    above): one noisy first sample is no step on every compensated grating for 2^k samples.
    Primed with the first sample and then 2^-k, that sample still weighed (1 - 2^-k)^(2^k - 1),
    about 0.37, at the 2^k-th."""
    k = 5
    model, q, _ = _quantised(k)
    n = 1 << k
    for first in (10**6, -(10**6)):       # a 1 nm step in the first sample alone
        shift_t = np.zeros(3 * n, dtype=np.int64)
        shift_t[0] = first
        r = intref.reference_average(q, shift_t, np.zeros(3 * n, dtype=bool))
        weight = r / first
        count = np.arange(1, 3 * n + 1)
        assert weight[0] == 1.0
        assert np.all(weight[:n] <= 2.0 / count[:n] + 1e-6) and weight[n - 1] < 0.04
        # From there the plain average: the weight decays by (1 - 2^-k) a sample.
        assert weight[-1] == pytest.approx(weight[n - 1] * (1 - 2.0**-k) ** (2 * n), rel=1e-3)
    # The float model's average follows the same rule (1 nm = 1000 pm).
    r_pm, (avg, count) = floatref.reference_average(shift_t / 1000.0, k, np.zeros(3 * n, bool))
    assert count == min(3 * n, floatref.REFERENCE_COUNT_MAX) and avg == r_pm[-1]
    assert np.allclose(r_pm, r / 1000.0, atol=1e-3)


@pytest.mark.parametrize("kernel", ["portable"] + host_kernels())
def test_tare_reset_and_baseline_reprime_and_faults_hold(kernel):
    """After a reset, a tare and a new baseline the next good sample primes the average again
    (the C state from there equals a fresh integer reference); a faulty sample leaves
    ref_acc as it was."""
    k = 5
    model, q, wl = _quantised(k)
    wl_fm = intref.nm_to_fm(_with_faults(wl, 2))
    base = intref.nm_to_fm(model.baseline_nm)
    rt = Runtime(blob.to_bytes(q), kernel=kernel)
    rt.set_baseline(base.astype(np.int32))
    st = rt._state
    rt.run_raw(wl_fm[:600])
    fault = intref.run(q, wl_fm[:600], base)["status"] & contract.STATUS_FLAG["SENSOR_FAULT"] != 0
    assert fault.any() and st.ref_count == min(int(np.sum(~fault)), 255)
    assert st.ref_acc == _expected_acc(wl_fm[:600, 4] - base[4], ~fault, k)
    # A lost reference peak: the average is held.
    before = st.ref_acc
    lost = wl_fm[600:601].copy()
    lost[0, 4] = 0
    assert rt.run_raw(lost)["status"][0] & contract.STATUS_FLAG["SENSOR_FAULT"]
    assert st.ref_acc == before
    # Reset: re-primed by the next good sample, as a fresh state on the same baseline.
    rt.reset()
    assert st.ref_count == 0
    _assert_equal(rt.run_raw(wl_fm[601:1000]), intref.run(q, wl_fm[601:1000], base), "reset")
    # Tare: a new baseline, re-primed.
    rt.tare(wl_fm[1000:1100])
    new_base = rt.baseline_fm
    assert not np.array_equal(new_base, base) and st.ref_count == 0
    _assert_equal(rt.run_raw(wl_fm[1100:1500]), intref.run(q, wl_fm[1100:1500], new_base), "tare")
    # A baseline set directly: re-primed.
    rt.set_baseline(base.astype(np.int32))
    assert st.ref_count == 0
    _assert_equal(rt.run_raw(wl_fm[1500:]), intref.run(q, wl_fm[1500:], base), "set_baseline")


def test_float_engines_prime_hold_and_carry_the_average():
    """FloatPipeline fed in pieces equals it fed at once (the average and its count carry
    over), its first good sample primes it, the next ones follow the falling gain and a faulty
    one holds it (the reference grating's shift of the rule written out); the C float build, fresh after fbgf_reset, fbgf_tare_end or
    fbgf_set_baseline, follows FloatPipeline started there."""
    k = 5
    model, _, wl = _quantised(k)
    wl = _with_faults(wl, 3)
    # The first sample and the first after each reset, tare and new baseline faulty: the
    # next one primes.
    wl[[0, 1200, 1550, 1800, 1810], 4] = np.nan
    pipe = floatref.FloatPipeline(model, model.baseline_nm)
    pieces = [pipe.push(wl[a:b]) for a, b in ((0, 1), (1, 333), (333, 1200))]
    whole = floatref.FloatPipeline(model, model.baseline_nm).push(wl[:1200])
    for key in ("margin", "force_raw_N", "status"):
        got = np.concatenate([p[key] for p in pieces])
        assert np.allclose(got, whole[key], atol=1e-12, equal_nan=True), key
    shift_t = (wl[:1200, 4] - model.baseline_nm[4]) * 1000.0
    good = np.flatnonzero(~floatref.samples.sensor_fault_rows(wl[:1200]))
    r = shift_t[good[0]]
    for n, i in enumerate(good[1:], start=2):
        r += (shift_t[i] - r) / 2.0**_gain_shift(n, k)
    assert pipe._reference[0][0] == pytest.approx(r, abs=1e-9)
    assert pipe._reference[0][1] == min(good.size, floatref.REFERENCE_COUNT_MAX)

    rt = FloatRuntime(model)
    rt.set_baseline(model.baseline_nm)
    rt.run(wl[:1200])

    def follows(c: np.ndarray, start: int, stop: int, base: np.ndarray) -> None:
        flt = floatref.FloatPipeline(model, base).push(wl[start:stop])
        fault = (c["status"] & contract.STATUS_FLAG["SENSOR_FAULT"]) != 0
        assert np.array_equal(fault, flt["status"] != 0) and fault.any()
        assert np.abs(c["margin"][~fault] - flt["margin"][~fault]).max() < 1e-3

    rt.reset()
    follows(rt.run(wl[1200:1500]), 1200, 1500, model.baseline_nm)
    tared = rt.tare(wl[1500:1550])
    follows(rt.run(wl[1550:1800]), 1550, 1800, tared)
    rt.set_baseline(model.baseline_nm)
    follows(rt.run(wl[1800:]), 1800, 2000, model.baseline_nm)


def test_a_model_without_the_field_is_the_model_it_was(tmp_path):
    """An old model.json (no ref_shift) loads with the raw reference, compensates as
    shift_i - temp_coeff_i * shift_T exactly, and exports the blob that blob version 6 wrote:
    the same bytes apart from the header's version and CRC (the field sits in what was the
    parameter block's padding; the digests below were taken with the version 6 exporter), and
    keeps the freshness digest its export recorded, which ref_shift > 0 changes."""
    old, wl = version6_model(tmp_path)
    assert old.preprocess.ref_shift == 0
    shift = (wl - old.baseline_nm) * 1000.0
    expected = shift[:, :4] - shift[:, 4:] * old.preprocess.temp_coeff
    assert np.array_equal(floatref.compensate(old, wl, old.baseline_nm), expected)
    q = assert_version6_export(old, wl)
    assert q.ref_shift == 0
    old.preprocess = dataclasses.replace(old.preprocess, ref_shift=5)
    assert freshness.model_digest(old) != VERSION6_DIGEST


#: The version 6 exporter's blob of the old model above (the header's version and CRC zeroed)
#: and the freshness digest its export recorded.
VERSION6_BLOB_SHA = "641c75ee3a8604f40754188dfe8ca226779f0b2f5bdbf0d04fc29d9a7265d057"
VERSION6_DIGEST = "8bf64e49ac2845e39ea93a1c561840b27883d59a00b7897efa3d88f52a19a40c"


def version6_model(directory: Path) -> tuple[artifact.HierarchicalModel, np.ndarray]:
    """The old model above as the version 6 trainer saved it in ``directory`` (its model.json
    without the fields added since: ``ref_shift``, ``creep``, ``creep_shift``, ``track_creep``,
    ``track_creep_shift``), loaded, and the 600 wavelengths (nm) its export is taken on."""
    model = make_random_model(7, sizes=((12,), (12,), (12,)), n_taps=5, sigma=1.5,
                              memory=artifact.Memory(ema_shifts=(3,), play_widths=(0.2,)))
    modeldir.save(model, directory)
    doc = json.loads((directory / modeldir.MODEL_JSON).read_text())
    for key in ("ref_shift", "creep", "creep_shift"):
        del doc["preprocess"][key]
    del doc["in_use"]["track_creep"], doc["in_use"]["track_creep_shift"]
    (directory / modeldir.MODEL_JSON).write_text(json.dumps(doc))
    old = modeldir.load(directory)
    return old, make_random_walk(old, 600, 7)


def assert_version6_export(old: artifact.HierarchicalModel, wl: np.ndarray) -> QModel:
    """``old`` (the old model above, loaded from a model.json without the fields added since
    blob version 6) quantises on ``wl`` to the version 6 blob apart from the header's version
    and CRC and the creep inverse's fields (blob version 9), which grew the parameter block
    and hold zeros; it keeps the digest its export recorded; returns its blob model."""
    from fbgforce.export import mutate

    q, _ = qz.quantize(old, qz.calibrate(old, [(wl, old.baseline_nm)]))
    data = bytearray(blob.to_bytes(q))
    assert int.from_bytes(data[4:6], "little") == contract.LIMIT["BLOB_VERSION"]
    data[4:6] = b"\0\0"
    data[12:16] = b"\0\0\0\0"
    grown = slice(min(o for o, _, f in mutate.param_slots() if f.name.startswith("creep_")),
                  contract.HEADER.size + contract.PARAMS_SIZE)
    assert not any(data[grown])
    del data[grown]
    data[8:12] = len(data).to_bytes(4, "little")
    assert hashlib.sha256(bytes(data)).hexdigest() == VERSION6_BLOB_SHA
    assert freshness.model_digest(old) == VERSION6_DIGEST
    return q


def test_ref_shift_is_range_checked_by_every_reader():
    """ref_shift beyond MAX_REF_SHIFT: the blob readers (C and Python) give FBG_ERR_RANGE,
    the C float build refuses the model, the float model refuses it."""
    from fbgforce.export import mutate

    model, q, _ = _quantised(3, n=400)
    bad = blob.to_bytes(dataclasses.replace(q, ref_shift=0))
    offset = next(o for o, _, f in mutate.param_slots() if f.name == "ref_shift")
    data = bytearray(bad)
    data[offset] = contract.LIMIT["MAX_REF_SHIFT"] + 1
    data = mutate.fix_crc(data)
    assert mutate.c_verdict(data) == mutate.python_verdict(data) == "FBG_ERR_RANGE"
    with pytest.raises(ValueError, match="ref_shift"):
        dataclasses.replace(model.preprocess, ref_shift=contract.LIMIT["MAX_REF_SHIFT"] + 1)
    model.preprocess.ref_shift = contract.LIMIT["MAX_REF_SHIFT"] + 1   # past the check
    from fbgforce.pybind import RangeError

    with pytest.raises(RangeError):
        FloatRuntime(model)


def _rest_recording(common: bool, n: int = 6000, seed: int = 0):
    """Wavelengths at rest (n, 5) around 1530..1550 nm with a slow temperature ramp and 1 pm
    of interrogator noise, independent per grating or common to all of them."""
    rng = np.random.default_rng(seed)
    base = np.array([1530.0, 1535.0, 1540.0, 1545.0, 1550.0])
    ramp = np.linspace(0.0, 0.01, n)[:, None]                       # 10 pm over 6 s
    noise = rng.normal(0.0, 1e-3, (n, 1 if common else 5))
    return base + ramp + noise, base


@pytest.mark.parametrize("common, averaged", [(False, True), (True, False)])
def test_the_trainer_averages_only_independent_noise(common, averaged):
    """Independent noise on each grating: the average halves the compensated channels'
    noise at rest and is kept (2^5 samples at 1 kHz); noise common to all gratings: the raw
    reference cancels it, the average would not, and the raw reference is kept."""
    wl, base = _rest_recording(common)
    pre = pp.make_preprocess("causal", 5.0, np.ones(4))
    shift, info = pp.choose_ref_shift(pre, [(wl, base, np.ones(wl.shape[0], dtype=bool))], 1000.0)
    noise = info["rest_noise_pm2"]
    assert info["candidate"] == 5 and shift == info["ref_shift"] == (5 if averaged else 0)
    if averaged:
        assert noise["averaged"] < 0.6 * noise["raw"]
    else:
        assert noise["averaged"] > 10.0 * noise["raw"]


@pytest.mark.parametrize("given", [0, 3])
def test_a_given_ref_shift_is_taken_as_it_is(given):
    """``--ref-shift N`` overrides the choice (here against the data, which would average
    over 2^5) and says so in the metadata; an out-of-range one is refused by name."""
    from fbgforce.trainer.params import TrainParams

    wl, base = _rest_recording(False)
    pre = pp.make_preprocess("causal", 5.0, np.ones(4))
    shift, info = pp.choose_ref_shift(pre, [(wl, base, np.ones(wl.shape[0], dtype=bool))], 1000.0,
                                      given=given)
    assert shift == info["ref_shift"] == given and info["given"] is True
    with pytest.raises(InputError, match="--ref-shift"):
        TrainParams(ref_shift=contract.LIMIT["MAX_REF_SHIFT"] + 1)


def test_levels_compensate_each_row_on_its_own():
    """pp.compensated splits rows that are levels, not a recording (the synthetic holds' and
    rests'), with each row's own reference shift, whatever ref_shift; recording=True averages
    the reference along the rows as the model does."""
    wl, base = _rest_recording(False, n=50)
    pre = dataclasses.replace(pp.make_preprocess("causal", 5.0, np.full(4, 0.9)), ref_shift=5)
    shift = (wl - base) * 1000.0
    assert np.array_equal(pp.compensated(pre, wl, base), shift[:, :4] - shift[:, 4:] * 0.9)
    along = pp.compensated(pre, wl, base, recording=True)
    model = dataclasses.replace(make_random_model(0), preprocess=pre)
    assert np.array_equal(along, floatref.compensate(model, wl, base))
    assert not np.allclose(along[1:], shift[1:, :4] - shift[1:, 4:] * 0.9)
