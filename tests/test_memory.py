"""The memory states (exponential averages, play operators, location averages) in every
engine: float reference, integer reference, C fixed point (bit for bit), C float; what they do
on reset, tare and sensor faults."""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce import contract
from fbgforce.model import artifact, floatref, modeldir
from fbgforce.export import blob, intref
from fbgforce.export import quantize as qz
from fbgforce.pybind import FloatRuntime, Runtime

MEMORIES = {
    "ema": artifact.Memory(ema_shifts=(2, 9), ema_gains=(3, 0), weights=(0.4, 0.3, -0.1, 0.2)),
    "play": artifact.Memory(play_widths=(0.02, 0.4), play_gains=(5, 1), weights=(0.25, 0.25, 0.25, 0.25)),
    "full": artifact.Memory(ema_shifts=(1, 4, 8, 15), ema_gains=(8, 2, 1, 0),
                      play_widths=(0.0, 0.05, 0.3, 2.0), play_gains=(0, 4, 2, 0),
                      weights=(1.0, -0.5, 0.7, 0.1), loc_shift=5),
    "loc": artifact.Memory(loc_shift=2),
    "loc15": artifact.Memory(ema_shifts=(3,), ema_gains=(2,), loc_shift=15),
}
Z_REST = np.array([-0.3, 0.5, -1.2, 0.1])


def naive_memory(memory: artifact.Memory, z: np.ndarray, z_rest: np.ndarray) -> np.ndarray:
    """The float recursion written sample by sample, as the C float build runs it."""
    u = z @ np.asarray(memory.weights)
    feats = [z]
    for shift, gain in zip(memory.ema_shifts, memory.ema_gains):
        e, out = u[0], np.empty_like(u)
        for i, ui in enumerate(u):
            e = e + (ui - e) * 2.0**-shift
            out[i] = (ui - e) * 2.0**gain
        feats.append(out[:, None])
    for width, gain in zip(memory.play_widths, memory.play_gains):
        p, out = u[0] + width, np.empty_like(u)
        for i, ui in enumerate(u):
            p = min(max(p, ui - width), ui + width)
            out[i] = (ui - p) * 2.0**gain
        feats.append(out[:, None])
    if memory.loc_shift:
        r = z - z_rest
        a, out = r[0].copy(), np.empty_like(r)
        for i, ri in enumerate(r):
            a = a + (ri - a) * 2.0**-memory.loc_shift
            out[i] = a
        feats.append(out)
    return np.concatenate(feats, axis=1)


def test_the_play_scan_is_the_loop_bit_for_bit():
    """The play operator's scan gives exactly what the clamp taken sample by sample gives: on
    walks and on white noise, for bands of width 0 to wider than the signal, from a state
    inside, above and below the first band, and on one sample or none."""
    rng = np.random.default_rng(11)
    for trial in range(200):
        n = int(rng.integers(0, 4000))
        u = (np.cumsum(rng.normal(0, 0.05, n)) if trial % 2 else rng.normal(0, 1.0, n))
        width = float(rng.choice([0.0, 0.05, 0.25, 5.0]))
        state = float(rng.normal(0, 3.0))
        p, expected = state, np.empty(n)
        for i in range(n):
            p = min(max(p, u[i] - width), u[i] + width)
            expected[i] = p
        assert np.array_equal(floatref.play_path(state, u - width, u + width), expected)


@pytest.mark.parametrize("name", sorted(MEMORIES))
def test_float_reference_equals_the_naive_recursion(name):
    rng = np.random.default_rng(3)
    z = np.cumsum(rng.normal(0, 0.05, (2000, 4)), axis=0)
    got = floatref.memory_features(MEMORIES[name], z, Z_REST)
    assert got.shape == (2000, 4 + MEMORIES[name].n_states + MEMORIES[name].n_loc)
    assert np.allclose(got, naive_memory(MEMORIES[name], z, Z_REST), atol=1e-9)
    stream = floatref.MemoryStream(MEMORIES[name], Z_REST)          # fed in pieces: the same
    pieces = np.concatenate([stream.push(z[a:b]) for a, b in ((0, 1), (1, 700), (700, 2000))])
    assert np.allclose(pieces, got, atol=1e-9)


def _model(random_model_factory, random_walk_factory, memory, seed=2):
    model = random_model_factory(seed, sizes=((24, 12), (24, 12), (24, 16)), n_taps=9,
                                 sigma=2.5, memory=memory)
    wl = random_walk_factory(model, 3000, seed)
    x = floatref.features(model, wl, model.baseline_nm)
    logits = model.contact.forward(x[:, :model.preprocess.n_features])
    model.contact.biases[-1][1] -= float(np.median(logits[:, 1] - logits[:, 0]))
    q, rep = qz.quantize(model, qz.calibrate(model, [(wl, model.baseline_nm)]))
    q.report = rep
    return model, wl, q


def _with_faults(wl: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    wl = wl.copy()
    for start in rng.integers(100, wl.shape[0] - 50, 6):
        length = int(rng.integers(1, 40))
        wl[start:start + length, int(rng.integers(5))] = 0.0     # a lost peak
    return wl


@pytest.mark.parametrize("name", sorted(MEMORIES))
def test_c_fixed_point_equals_the_integer_reference(random_model_factory, random_walk_factory, name):
    model, wl, q = _model(random_model_factory, random_walk_factory, MEMORIES[name])
    assert q.n_ema == len(MEMORIES[name].ema_shifts) and q.n_play == len(MEMORIES[name].play_widths)
    wl = _with_faults(wl, np.random.default_rng(5))
    wl_fm, base_fm = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    rt = Runtime(blob.to_bytes(q))
    rt.set_baseline(base_fm.astype(np.int32))
    c = rt.run_raw(wl_fm)
    ref = intref.run(q, wl_fm, base_fm)
    assert (ref["status"] & contract.STATUS_FLAG["SENSOR_FAULT"]).any()
    for k in contract.OUTPUT_FIELDS:
        bad = np.flatnonzero(c[k].astype(np.int64) != ref[k])
        assert bad.size == 0, f"{k} differs at {bad[:5]}"


@pytest.mark.parametrize("name", sorted(MEMORIES))
def test_fixed_and_c_float_follow_the_float_model(random_model_factory, random_walk_factory, name):
    model, wl, q = _model(random_model_factory, random_walk_factory, MEMORIES[name])
    flt = floatref.predict(model, wl, model.baseline_nm)
    fixed = intref.to_engine_dict(intref.run(q, intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)))
    rt = FloatRuntime(model)
    rt.set_baseline(model.baseline_nm)
    cf = rt.run(wl)
    both = flt["contact"] & fixed["contact"] & cf["contact"]
    assert both.sum() > 200
    scale = max(1.0, float(np.abs(flt["force_N"][both]).max()))
    # Fixed point: within the error budget the exporter proved for this model (the "full"
    # memory's gain of 2^8 on a 2-sample average is a stress case, not a sensible model).
    assert np.abs(fixed["force_N"][both] - flt["force_N"][both]).max() <= q.report["error_bounds"]["force_N"]
    assert np.abs(cf["force_N"][both] - flt["force_N"][both]).max() < 1e-3 * scale
    assert np.mean(fixed["contact"] == flt["contact"]) > 0.98


def test_fault_freezes_and_reset_clears_the_states(random_model_factory, random_walk_factory):
    model, wl, q = _model(random_model_factory, random_walk_factory, MEMORIES["full"])
    rt = Runtime(blob.to_bytes(q))
    rt.set_baseline(model.baseline_nm)
    st = rt._state

    def states() -> dict[str, np.ndarray]:
        return {name: np.array(list(getattr(st, name))) for name in contract.MEMORY_STATES}

    rt.run(wl[:500])
    assert st.mem_primed == 1
    before = states()
    bad = wl[500:530].copy()
    bad[:, 2] = np.nan                                   # channel 3 lost for 30 samples
    out = rt.run(bad)
    assert np.all(out["status"] & contract.STATUS_FLAG["SENSOR_FAULT"])
    after = states()
    assert all(np.array_equal(before[k], after[k]) for k in before)   # frozen, not poisoned
    rt.run(wl[530:600])
    assert not np.array_equal(states()["ema"], before["ema"])       # running again
    assert not np.array_equal(states()["loc"], before["loc"])
    rt.reset()
    assert st.mem_primed == 0 and not any(a.any() for a in states().values())
    rt.run(wl[600:700])
    rt.tare(wl[:50])
    assert st.mem_primed == 0 and not any(a.any() for a in states().values())


def test_first_sample_after_reset_primes_the_states_as_at_rest(random_model_factory,
                                                               random_walk_factory):
    """Averages start at z (feature 0), play operators at z + width (feature -width * gain:
    what every rest after a release shows), in the float and the integer reference."""
    model, wl, q = _model(random_model_factory, random_walk_factory, MEMORIES["full"])
    z = np.array([[100, -200, 300, -400]], dtype=np.int64)
    x, _ = intref.memory_features(q, z)
    assert list(x[0, :4]) == [100, -200, 300, -400]
    assert np.all(x[0, 4:4 + q.n_ema] == 0)
    expect = -(q.play_width[:q.n_play] << q.play_gain[:q.n_play])
    assert np.array_equal(x[0, 4 + q.n_ema:q.n_features], np.clip(expect, -32767, 32767))
    z0, _ = q.z_rest()
    assert np.array_equal(x[0, 4 + q.n_ema + q.n_play:], np.clip(z[0] - z0, -32767, 32767))
    mem = MEMORIES["full"]
    f = floatref.memory_features(mem, np.zeros((1, 4)), Z_REST)
    assert np.allclose(f[0, 4 + 4:4 + 8], -np.array(mem.play_widths) * 2.0 ** np.array(mem.play_gains))
    assert np.allclose(f[0, 4 + 8:], -Z_REST)                  # the average starts at r = z - z0


def test_location_averages_read_zero_at_rest_and_keep_a_press_direction(random_model_factory,
                                                                         random_walk_factory):
    """r = z - z0 is 0 for a zero filtered shift in every engine, so a press onset after rest
    only scales the average; the location net reads z, contact, force, then the averages."""
    model, wl, q = _model(random_model_factory, random_walk_factory, MEMORIES["full"])
    pre = model.preprocess
    assert np.allclose((np.zeros(4) - pre.input_mean) / pre.input_std, pre.z_rest)
    z0, saturated = q.z_rest()
    assert not saturated
    # The fixed z0 is the standardisation of a zero shift, within half an LSB of the float.
    assert np.abs(z0 / 2.0**q.z_frac - pre.z_rest).max() <= 0.5 * 2.0**-q.z_frac + 1e-3
    rest = np.repeat(z0[None, :], 50, axis=0)
    direction = np.array([3000, -1000, 2000, 500])
    press = np.concatenate([rest, rest + direction])
    x, _ = intref.memory_features(q, press)
    a = x[:, q.n_features:]
    assert not intref._location_averages(q, press)[1].any()     # nothing saturated there
    assert np.all(a[:50] == 0)
    later = a[60].astype(float)                                # 10 samples into the press
    cos = later @ direction / np.linalg.norm(later) / np.linalg.norm(direction)
    assert cos > 0.9999 and np.linalg.norm(later) < np.linalg.norm(direction)
    assert contract.net_inputs("location", q.n_memory, q.n_loc) == 10 <= contract.LIMIT["MAX_INPUTS"]


def test_memory_text_and_presets():
    from fbgforce.errors import InputError
    from fbgforce.trainer.memory import MEMORY_PRESETS, parse_memory

    m = parse_memory("ema:3,6+play:0.1")
    assert m.ema_shifts == (3, 6) and m.play_widths == (0.1,) and m.loc_shift == 0
    m = parse_memory("play:0.1+loc:5")
    assert m.play_widths == (0.1,) and m.loc_shift == 5 and m.n_loc == 4
    assert parse_memory("loc:4").n_states == 0
    assert parse_memory("none").n_states == 0
    assert all(p.n_states <= contract.LIMIT["MAX_INPUTS"] - contract.N_STRAIN for p in MEMORY_PRESETS.values())
    for bad in ("ema:0", "play:-1", "lstm:3", "ema:1,2,3,4,5", "loc:0", "loc:16", "loc:3,4",
                "loc:3+loc:4"):
        with pytest.raises(InputError):
            parse_memory(bad)


@pytest.mark.parametrize("field, index, value, code", [
    ("n_ema", None, contract.MEMORY_KIND["ema"].limit + 1, "FBG_ERR_SHAPE"),
    ("n_play", None, contract.MEMORY_KIND["play"].limit + 1, "FBG_ERR_SHAPE"),
    ("ema_shift", 1, 0, "FBG_ERR_RANGE"),
    ("ema_shift", 0, contract.MAX_EMA_SHIFT + 1, "FBG_ERR_RANGE"),
    ("ema_gain", 1, contract.MAX_MEM_GAIN + 1, "FBG_ERR_RANGE"),
    ("play_gain", 3, contract.MAX_MEM_GAIN + 1, "FBG_ERR_RANGE"),
    ("play_width", 2, -0.5, "FBG_ERR_RANGE"),
    ("play_width", 0, float("nan"), "FBG_ERR_RANGE"),
    ("play_width", 3, float("inf"), "FBG_ERR_RANGE"),
])
def test_float_build_checks_memory_parameters(random_model_factory, field, index, value, code):
    """fbgf_model_check refuses a memory parameter of a state in use outside the ranges of
    fbg_model's, as the fixed-point checker does (the generated fbgf_memory_check)."""
    from fbgforce._runtime import lib

    rt = FloatRuntime(random_model_factory(1, sizes=((8,), (8,), (8,)), memory=MEMORIES["full"]))
    assert lib.fbgf_model_check(rt._model) == lib.FBG_OK
    if index is None:
        setattr(rt._model, field, value)
    else:
        getattr(rt._model, field)[index] = value
    assert lib.fbgf_model_check(rt._model) == getattr(lib, code)


def test_memory_refuses_parameters_outside_the_contract():
    for bad in (dict(ema_shifts=(0,)), dict(ema_shifts=(16,)), dict(ema_shifts=(3,), ema_gains=(9,)),
                dict(ema_shifts=(3,), ema_gains=(1, 2)), dict(play_widths=(-0.1,)),
                dict(play_widths=(float("nan"),)), dict(play_widths=(0.1,) * 5)):
        with pytest.raises(ValueError):
            artifact.Memory(**bad)
    assert artifact.Memory(play_widths=(0.1, 0.2)).play_gains == (0, 0)


@pytest.mark.parametrize("name", ["full", "loc"])
def test_tare_and_reset_restart_every_state_bit_for_bit(random_model_factory, random_walk_factory,
                                                        name):
    """After a reset or a tare the C engine continues exactly as the integer reference started
    afresh on the samples that follow: every state (load averages, plays, location averages)
    is cleared and primed again."""
    model, wl, q = _model(random_model_factory, random_walk_factory, MEMORIES[name])
    wl_fm = intref.nm_to_fm(wl)
    rt = Runtime(blob.to_bytes(q))
    rt.set_baseline(intref.nm_to_fm(model.baseline_nm).astype(np.int32))
    rt.run_raw(wl_fm[:800])
    rt.reset()
    c = rt.run_raw(wl_fm[800:1600])
    ref = intref.run(q, wl_fm[800:1600], intref.nm_to_fm(model.baseline_nm))
    for k in contract.OUTPUT_FIELDS:
        assert np.array_equal(c[k].astype(np.int64), ref[k]), k
    rt.tare(wl[1600:1700])
    base = np.asarray(rt.baseline_fm, dtype=np.int64)
    c = rt.run_raw(wl_fm[1700:])
    ref = intref.run(q, wl_fm[1700:], base)
    assert not np.array_equal(base, intref.nm_to_fm(model.baseline_nm))
    for k in contract.OUTPUT_FIELDS:
        assert np.array_equal(c[k].astype(np.int64), ref[k]), k


def test_a_blob_of_the_previous_version_is_refused(random_model_factory, random_walk_factory):
    """Blob version 5 added loc_shift to the parameter block; a version 4 blob is refused by
    both readers (re-export the model)."""
    from fbgforce.export import mutate

    _, _, q = _model(random_model_factory, random_walk_factory, MEMORIES["loc"])
    old = bytearray(blob.to_bytes(q))
    old[4:6] = (contract.LIMIT["BLOB_VERSION"] - 1).to_bytes(2, "little")
    old = mutate.fix_crc(old)
    assert mutate.c_verdict(old) == mutate.python_verdict(old) == "FBG_ERR_VERSION"


def test_location_averages_at_their_saturation_bounds(random_model_factory, random_walk_factory):
    """z0 saturated (a mean far from zero) and z driven to the opposite end: r = z - z0
    saturates, the averages stay within their proven range, and C equals the integer
    reference bit for bit, SATURATED included."""
    import dataclasses

    _, _, q = _model(random_model_factory, random_walk_factory, MEMORIES["full"])
    ratio = q.z_mult / 2.0**q.z_shift                       # z per fm of filtered shift
    mean = np.round(2.0 * 32767 / np.abs(ratio)) * np.sign(ratio) * np.array([1, -1, 1, -1])
    q = dataclasses.replace(q, mean_fm=mean.astype(np.int64))
    z0, saturated = q.z_rest()
    assert saturated and np.all(np.abs(z0) == 32767)
    base = intref.nm_to_fm(np.array([1530.0, 1535.0, 1540.0, 1545.0, 1550.0]))
    q = dataclasses.replace(q, baseline_fm=base, jump_max_fm=2**31 - 1, stuck_max=0)
    # Each channel swings to +-4 times the saturating shift (signs against z0) and back.
    n = 1200
    swing = np.sin(np.linspace(0.0, 4.0 * np.pi, n))[:, None] * 4.0 * np.abs(mean)[None, :] * -np.sign(z0)
    wl = np.column_stack([base[:4] + np.round(swing).astype(np.int64), np.full(n, base[4])])
    ref = intref.run(q, wl, base)
    rt = Runtime(blob.to_bytes(q))
    rt.set_baseline(base.astype(np.int32))
    c = rt.run_raw(wl)
    for k in contract.OUTPUT_FIELDS:
        assert np.array_equal(c[k].astype(np.int64), ref[k]), k
    sat = contract.STATUS_FLAG["SATURATED"]
    assert np.all(ref["status"][q.taps.size:] & sat)
    x, _ = intref.memory_features(q, np.tile(-np.sign(z0) * 32767, (3, 1)))
    assert np.all(np.abs(x[:, q.n_features:]) == 32767)
    assert all(abs(int(v)) <= 32767 << 15 for v in rt._state.loc)


def test_holds_are_found_and_a_memory_without_them_is_warned_about(small_model_dir):
    """train() records how long the training presses hold their load; with averages in the
    memory, no hold and the synthetic holds turned off it warns (the averages would read a
    held grip low); by default the synthetic holds stand in for them."""
    from fbgforce import sim
    from fbgforce.trainer.data import hold_seconds
    from fbgforce.trainer.params import DEFAULT_SIZES
    from fbgforce.trainer.train import prepare, train

    small = sim.load_scene("calibration_holds").replace(schedule={"n_presses": 3})
    held = prepare([sim.simulate(small)])
    # 3 presses holding 0.5 s each, found in 10 ms blocks.
    assert hold_seconds(held) == pytest.approx(1.5, abs=0.1)
    assert hold_seconds(held, np.arange(0)) == 0.0
    presses = prepare([sim.simulate(small.replace(schedule={"hold_s": 0.0}))])
    assert hold_seconds(presses) == 0.0
    md = modeldir.load(small_model_dir).metadata  # the smoke scene, trained without synthetic holds
    assert md["train_hold_s"] == 0.0 and md["memory"]["ema_shifts"]
    assert md["synthetic_holds"]["samples"]["train"] == 0
    assert sum("held grip" in w for w in md["warnings"]) == 1
    tiny = {net: (4,) for net in DEFAULT_SIZES}
    plain = sim.simulate(small.replace(schedule={"hold_s": 0.0, "n_presses": 10}))
    md = train([plain], epochs=1, sizes=tiny, restarts=1, idle_pads=0, progress=False).metadata
    # (A 10-press log also warns that its test split is small: not about holds.)
    assert md["synthetic_holds"]["samples"]["train"] > 0
    assert not any("held grip" in w for w in md["warnings"])


def test_the_contact_net_reads_no_play_operator_unless_asked(tmp_path):
    """By default the contact net's first layer has exact zeros on the play operators'
    columns, in the float model and in the blob, so what the plays hold after a long rest
    cannot move its margin in any engine; the force net reads them. ``contact_plays`` gives
    it them again, and model.json records which."""
    from fbgforce import sim
    from fbgforce.export.exporter import export_model
    from fbgforce.trainer.params import DEFAULT_SIZES
    from fbgforce.trainer.train import train

    rec = sim.simulate(sim.load_scene("smoke").replace(schedule={"n_presses": 10}))
    tiny = {net: (4,) for net in DEFAULT_SIZES}
    models = {asked: train([rec], epochs=1, sizes=tiny, restarts=1, idle_pads=0, progress=False,
                           contact_plays=asked) for asked in (False, True)}
    for asked, model in models.items():
        memory = model.preprocess.memory
        plays = list(memory.columns("play"))
        assert plays == [contract.N_STRAIN + len(memory.ema_shifts) + i
                         for i in range(len(memory.play_widths))] and plays
        assert model.metadata["contact_reads_plays"] is asked
        assert model.contact.weights[0][:, plays].all() if asked \
            else not model.contact.weights[0][:, plays].any()
        assert model.contact.weights[0][:, :plays[0]].any() and model.force.weights[0][:, plays].any()

    model = models[False]
    out = tmp_path / "model"
    modeldir.save(model, out)
    export_model(out)
    q = blob.from_bytes((out / "model.fbgm").read_bytes())
    first = q.nets[artifact.NET_NAMES.index("contact")][0].w
    assert not first[:, plays].any() and first.any()
    # Whatever the plays hold, the same logits.
    rng = np.random.default_rng(3)
    z = rng.normal(size=(64, model.preprocess.n_features))
    moved = z.copy()
    moved[:, plays] += rng.normal(scale=3.0, size=(64, len(plays)))
    assert np.array_equal(model.contact.forward(z), model.contact.forward(moved))
