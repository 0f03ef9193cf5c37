"""Effect isolation, random-stream independence and streaming of the EndEffector."""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce.errors import InputError
from fbgforce.sim import EFFECT_ORDER, EFFECTS, EndEffector, effect_rng
from fbgforce.sim.effects import Context, FrictionHysteresis

RATE = 1000.0

#: Parameters under which each effect must be an exact no-op (None: it has none).
NEUTRAL = {
    "tolerance": dict(gain_sd=0.0, strain_transfer=1.0, strain_transfer_sd=0.0,
                      support_sd_x_mm=0.0, support_sd_y_mm=0.0, stiffness_sd=0.0, base_wl_sd_nm=0.0),
    "edge_contact": dict(strength_x=0.0, strength_y=0.0),
    "friction_hysteresis": dict(gap=0.0),
    "viscoelastic": dict(magnitude=0.0),
    "dynamics": None,
    "temperature": dict(drift_K_per_sqrt_s=0.0, mismatch_sd=0.0),
    "noise": dict(sigma_pm=0.0, relative=0.0),
    "quantization": None,
    "dropout": dict(rate=0.0),
}
#: Non-default parameters, to show an effect's parameters never reach another effect.
OTHER = {
    "tolerance": dict(gain_sd=0.2, support_sd_y_mm=2.0),
    "edge_contact": dict(width_mm=5.0, strength_y=0.3),
    "friction_hysteresis": dict(gap=0.2, gap_sd=0.5, n_operators=3),
    "viscoelastic": dict(magnitude=0.3, time_constant_s=0.05),
    "dynamics": dict(frequency_hz=900.0, internal_rate_hz=50000.0),
    "temperature": dict(ramp_K=5.0, ramp_duration_s=0.5, drift_K_per_sqrt_s=1.0),
    "noise": dict(sigma_pm=9.0, relative=0.05),
    "quantization": dict(step_pm=10.0),
    "dropout": dict(rate=0.05, burst_mean_samples=5.0),
}
ALL = {name: {} for name in EFFECT_ORDER}
ALL["dropout"] = {"rate": 0.01}
ALL["temperature"] = {"ramp_K": 2.0, "ramp_duration_s": 1.0}


def recording(seed: int = 0):
    """Two presses (one near the edge) and two taps, 1.5 s at 1 kHz."""
    rng = np.random.default_rng(seed)
    n = 1500
    t = np.arange(n) / RATE
    f = np.zeros(n)
    x = np.full(n, np.nan)
    y = np.full(n, np.nan)
    for start, peak, px, py in ((100, 40.0, 10.0, 12.0), (700, 25.0, 1.0, 25.5)):
        s = np.sin(np.linspace(0, np.pi, 400))
        f[start:start + 400] = peak * s
        x[start:start + 400], y[start:start + 400] = px, py
    j = np.zeros(n)
    for k, jj in ((1200, 0.01), (1350, 0.004)):
        j[k] = jj
        x[k], y[k] = rng.uniform(2, 19), rng.uniform(2, 25)
    return t, f, x, y, j


def run(effects, seed=1, device=2, chunks=None):
    t, f, x, y, j = recording()
    ee = EndEffector(effects, seed=seed, device=device, rate_hz=RATE)
    if chunks is None:
        return ee.process_with_extras(t, f, x, y, f > 0.05, j)
    wls, extras = [], {}
    bounds = np.cumsum([0] + list(chunks))
    assert bounds[-1] == t.size
    for a, b in zip(bounds[:-1], bounds[1:]):
        wl, ex = ee.process_with_extras(t[a:b], f[a:b], x[a:b], y[a:b], None, j[a:b])
        wls.append(wl)
        for k, v in ex.items():
            extras.setdefault(k, []).append(v)
    return np.concatenate(wls), {k: np.concatenate(v) for k, v in extras.items()}


@pytest.mark.parametrize("name", EFFECT_ORDER)
def test_adding_an_effect_changes_the_output(name):
    without = {k: v for k, v in ALL.items() if k != name}
    wl0, ex0 = run(without)
    wl1, ex1 = run(ALL)
    if name == "dropout":  # flags only; the wavelengths are left for the serial emulator
        np.testing.assert_array_equal(wl0, wl1)
        assert "dropout" not in ex0 and ex1["dropout"].any()
    else:
        assert not np.array_equal(wl0, wl1)


@pytest.mark.parametrize("name", [n for n in EFFECT_ORDER if NEUTRAL[n] is not None])
def test_a_neutral_effect_leaves_every_other_effect_bit_identical(name):
    """Listing an effect with no-op parameters changes nothing at all: it draws only from its
    own stream, so the other effects' random numbers are untouched."""
    without = {k: v for k, v in ALL.items() if k != name}
    with_neutral = dict(without)
    with_neutral[name] = NEUTRAL[name]
    wl0, ex0 = run(without)
    wl1, ex1 = run(with_neutral)
    np.testing.assert_array_equal(wl0, wl1)
    for k in ex0:
        np.testing.assert_array_equal(ex0[k], ex1[k])


@pytest.mark.parametrize("name", EFFECT_ORDER)
def test_an_effects_parameters_never_reach_another_effects_stream(name):
    """Each random effect's draws depend on (seed, device, its own name) only."""
    changed = dict(ALL)
    changed[name] = OTHER[name]
    ees = []
    for effects in (ALL, changed, {k: v for k, v in ALL.items() if k != name}):
        ee = EndEffector(effects, seed=1, device=2, rate_hz=RATE)
        t, f, x, y, j = recording()
        ee.process(t, f, x, y, None, j)
        ees.append(ee)
    for other in ("temperature", "noise", "dropout"):
        if other == name:
            continue
        states = []
        for ee in ees:
            eff = ee.effects[other]
            gen = eff.walk_rng if other == "temperature" else eff.stream
            states.append(gen.bit_generator.state["state"])
        assert states[0] == states[1] == states[2]
    if name != "tolerance":  # the device itself is the same whatever the other effects
        np.testing.assert_array_equal(ees[0].design.gain, ees[1].design.gain)
        np.testing.assert_array_equal(ees[0].design.supports_mm, ees[2].design.supports_mm)


def test_streams_depend_on_seed_device_and_name_only():
    a = effect_rng("noise", 1, 2).standard_normal(4)
    np.testing.assert_array_equal(a, effect_rng("noise", 1, 2).standard_normal(4))
    assert not np.array_equal(a, effect_rng("noise", 1, 3).standard_normal(4))
    assert not np.array_equal(a, effect_rng("noise", 2, 2).standard_normal(4))
    assert not np.array_equal(a, effect_rng("temperature", 1, 2).standard_normal(4))
    dev = effect_rng("tolerance", 1, 2, device_property=True).standard_normal(4)
    np.testing.assert_array_equal(dev, effect_rng("tolerance", 99, 2, device_property=True)
                                  .standard_normal(4))


def test_device_is_the_same_under_any_scene_seed_and_differs_between_devices():
    d1 = EndEffector({"tolerance": {}}, seed=1, device=4).design
    d2 = EndEffector({"tolerance": {}}, seed=7, device=4).design
    d3 = EndEffector({"tolerance": {}}, seed=1, device=5).design
    np.testing.assert_array_equal(d1.gain, d2.gain)
    np.testing.assert_array_equal(d1.supports_mm, d2.supports_mm)
    assert not np.array_equal(d1.gain, d3.gain)
    # Support position errors are worse in y than in x (defaults 0.2 vs 0.6 mm sd).
    supports = np.array([EndEffector({"tolerance": {}}, device=d).design.supports_mm
                         for d in range(40)])
    spread = supports.std(axis=0).mean(axis=0)
    assert spread[1] > 1.8 * spread[0]


@pytest.mark.parametrize("chunks", [(1500,), (1, 7, 100, 1392), (750, 750), (300,) * 5])
def test_chunked_processing_equals_one_call(chunks):
    wl_whole, ex_whole = run(ALL)
    wl_chunked, ex_chunked = run(ALL, chunks=chunks)
    np.testing.assert_array_equal(wl_whole, wl_chunked)
    assert ex_whole.keys() == ex_chunked.keys() == {"temperature_K", "dropout"}
    for k in ex_whole:
        np.testing.assert_array_equal(ex_whole[k], ex_chunked[k])


def test_sample_by_sample_streaming_equals_one_call():
    wl_whole, _ = run(ALL)
    wl_steps, _ = run(ALL, chunks=(1,) * 1500)
    np.testing.assert_array_equal(wl_whole, wl_steps)


def test_edge_contact_makes_boundary_loads_alike():
    ideal = EndEffector(None)
    edge = EndEffector({"edge_contact": {"strength_y": 1.0, "width_mm": 3.0}})
    ys = np.array([24.0, 25.0, 26.0, 27.0])
    f = np.full(4, 10.0)
    x = np.full(4, 10.5)
    wl_ideal = ideal.process(np.arange(4) / RATE, f, x, ys)[:, 2]
    wl_edge = edge.process(np.arange(4) / RATE, f, x, ys)[:, 2]
    # Across the 3 mm band the signal changes half as much; across its outer 1 mm, a sixth.
    assert np.ptp(wl_edge) == pytest.approx(0.5 * np.ptp(wl_ideal), rel=1e-6)
    assert abs(wl_edge[3] - wl_edge[2]) < 0.2 * abs(wl_ideal[3] - wl_ideal[2])
    inner = np.array([12.0, 13.5])  # interior loads are untouched
    np.testing.assert_array_equal(ideal.process(np.arange(2) / RATE, f[:2], x[:2], inner),
                                  edge.process(np.arange(2) / RATE, f[:2], x[:2], inner))


def test_noise_grows_with_the_signal():
    ee = EndEffector({"noise": {"sigma_pm": 4.0, "relative": 0.01}}, seed=3)
    n = 20000
    t = np.arange(n) / RATE
    rest = ee.process(t, np.zeros(n), np.full(n, np.nan), np.full(n, np.nan))
    loaded = ee.process(t, np.full(n, 60.0), np.full(n, 10.5), np.full(n, 13.5))
    sd_rest = rest[:, 0].std() * 1000
    sd_loaded = loaded[:, 0].std() * 1000
    assert sd_rest == pytest.approx(4.0, rel=0.05)
    shift_pm = abs(loaded[:, 0].mean() - rest[:, 0].mean()) * 1000
    assert sd_loaded == pytest.approx(4.0 + 0.01 * shift_pm, rel=0.05)


def test_dropout_flags_bursts_of_both_kinds():
    _, ex = run({"dropout": {"rate": 0.02, "burst_mean_samples": 4.0, "garbled_fraction": 0.5}})
    flags = ex["dropout"]
    assert set(np.unique(flags)) == {0, 1, 2}
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], flags != 0, [0]]))))[::2]
    assert 2.0 < runs.mean() < 8.0


def test_bad_effects_mapping_and_inputs():
    with pytest.raises(InputError, match="allowed effects"):
        EndEffector({"vibration": {}})
    with pytest.raises(InputError, match="effects.noise.sigma_pm"):
        EndEffector({"noise": {"sigma_pm": -1.0}})
    ee = EndEffector(None)
    with pytest.raises(ValueError, match="x_mm/y_mm must be finite"):
        ee.process([0.0], [1.0], [np.nan], [3.0])
    with pytest.raises(ValueError, match="samples"):
        ee.process([0.0, 0.001], [1.0], [3.0], [3.0])
    assert set(EFFECTS) == set(EFFECT_ORDER)


# ------------------------------------------------------------------ rate-independent pad loop

def friction_pad(gap: float = 0.1, n_operators: int = 8):
    """The friction loop alone, without spread between beams."""
    ctx = Context(seed=0, device=0, rate_hz=RATE)
    return FrictionHysteresis({"gap": gap, "gap_sd": 0.0, "n_operators": n_operators}, ctx)


def triangle(peak: float, n_up: int) -> np.ndarray:
    """0 -> peak -> 0 in ``n_up`` equal steps each way, on every beam."""
    up = np.linspace(0.0, peak, n_up + 1)
    return np.repeat(np.concatenate([up, up[-2::-1]])[:, None], 4, axis=1)


def test_friction_loop_gap_at_equal_force_matches_the_parameter():
    gap, peak, n_up = 0.1, 40.0, 400
    out = friction_pad(gap).process(triangle(peak, n_up))[:, 0]
    f = triangle(peak, n_up)[:, 0]
    load, unload = out[:n_up + 1], out[n_up:][::-1]  # both indexed by the same force
    # Developed branches: every operator has slipped (F below peak (1 - r_max) / (1 + r_max)).
    r_max = gap * (2 * 8 - 1) / (2 * 8)
    developed = (f[:n_up + 1] > 0) & (f[:n_up + 1] < peak * (1 - r_max) / (1 + r_max))
    np.testing.assert_allclose(load[developed], (1 - gap / 2) * f[:n_up + 1][developed], rtol=1e-12)
    np.testing.assert_allclose((unload - load)[developed], gap * f[:n_up + 1][developed],
                               rtol=1e-12)
    # Sticking at the reversal: the output stays flat at first, then the operators release.
    k = n_up
    assert out[k + 1] == out[k] and out[k + 40] < out[k]
    # The loop closes at zero load: nothing is left on the beams once the press is over.
    assert out[-1] == 0.0 and out[0] == 0.0


def test_friction_loop_is_rate_independent_and_the_viscoelastic_one_is_not():
    """The same press at two speeds (the slow one samples the fast one's forces and 9 more
    between each): the friction loop gives the same output at the same force, the viscoelastic
    lag does not."""
    peak = 30.0
    fast, slow = triangle(peak, 40), triangle(peak, 400)
    out_fast = friction_pad(0.08).process(fast)
    out_slow = friction_pad(0.08).process(slow)
    np.testing.assert_allclose(out_slow[::10], out_fast, rtol=1e-12, atol=1e-12)

    def viscoelastic(forces):
        ve = EFFECTS["viscoelastic"]({"magnitude": 0.1, "time_constant_s": 0.05},
                                     Context(seed=0, device=0, rate_hz=RATE))
        return ve.process(forces)
    assert np.max(np.abs(viscoelastic(slow)[::10] - viscoelastic(fast))) > 0.05 * peak * 0.1


def test_friction_loop_through_the_end_effector_at_two_press_speeds():
    """At the sensor: the wavelength gap at equal force is the same for a 0.1 s and a 1 s
    press."""
    gaps = []
    for n_up in (100, 1000):
        f = triangle(20.0, n_up)[:, 0]
        n = f.size
        ee = EndEffector({"friction_hysteresis": {"gap": 0.1, "gap_sd": 0.0}})
        wl = ee.process(np.arange(n) / RATE, f, np.full(n, 10.5), np.full(n, 13.5))
        s = (wl[:, :4] - wl[0, :4]).sum(axis=1)
        gaps.append(s[n_up // 4] - s[n - 1 - n_up // 4])  # loading vs unloading at 5 N
    assert gaps[0] == pytest.approx(gaps[1], rel=1e-9)
    ideal = EndEffector(None).process(np.zeros(2), [0.0, 5.0], [10.5, 10.5], [13.5, 13.5])
    per_5N = (ideal[1, :4] - ideal[0, :4]).sum()
    assert gaps[0] == pytest.approx(-0.1 * per_5N, rel=1e-9)  # a 10 % gap of 5 N


def test_friction_loop_state_carries_across_chunks():
    forces = np.abs(np.sin(np.linspace(0, 9, 1000)))[:, None] * np.array([[10.0, 20.0, 5.0, 1.0]])
    forces[::97] *= -0.3  # a beam may be pulled (negative force) near an edge
    whole = friction_pad(0.2, 5).process(forces)
    pad = friction_pad(0.2, 5)
    parts = [pad.process(forces[a:b]) for a, b in ((0, 1), (1, 333), (333, 334), (334, 1000))]
    np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_friction_loop_spread_between_beams_is_a_device_property():
    ctx = Context(seed=5, device=3, rate_hz=RATE)
    a = FrictionHysteresis({"gap": 0.06, "gap_sd": 0.2, "n_operators": 8}, ctx).beam_gap
    b = FrictionHysteresis({"gap": 0.06, "gap_sd": 0.2, "n_operators": 8},
                           Context(seed=9, device=3, rate_hz=RATE)).beam_gap
    np.testing.assert_array_equal(a, b)  # same device under another scene seed
    assert np.ptp(a) > 0 and np.all(a >= 0)
    c = FrictionHysteresis({"gap": 0.06, "gap_sd": 0.2, "n_operators": 8},
                           Context(seed=5, device=4, rate_hz=RATE)).beam_gap
    assert not np.array_equal(a, c)


def test_former_effect_name_hysteresis_reads_as_viscoelastic():
    old = EndEffector({"hysteresis": {"magnitude": 0.2}})
    assert list(old.effects) == ["viscoelastic"]
    assert old.effects["viscoelastic"].p["magnitude"] == 0.2
    with pytest.raises(InputError, match="repeated"):
        EndEffector({"hysteresis": {}, "viscoelastic": {}})
