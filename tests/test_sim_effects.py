"""Effect isolation, random-stream independence and streaming of the EndEffector."""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce.errors import InputError
from fbgforce.sim import EFFECT_ORDER, EFFECTS, EndEffector, effect_rng

RATE = 1000.0

#: Parameters under which each effect must be an exact no-op (None: it has none).
NEUTRAL = {
    "tolerance": dict(gain_sd=0.0, strain_transfer=1.0, strain_transfer_sd=0.0,
                      support_sd_x_mm=0.0, support_sd_y_mm=0.0, stiffness_sd=0.0, base_wl_sd_nm=0.0),
    "edge_contact": dict(strength_x=0.0, strength_y=0.0),
    "hysteresis": dict(magnitude=0.0),
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
    "hysteresis": dict(magnitude=0.3, time_constant_s=0.05),
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
