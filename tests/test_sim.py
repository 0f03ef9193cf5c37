"""The scene-driven simulator: scenes, exact inversion of `ideal`, determinism, the calibration
scene's shape, bad scenes, and the `fbgforce simulate` command."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fbgforce import geometry
from fbgforce.recordings import dataset
from fbgforce.cli import main
from fbgforce.errors import InputError
from fbgforce.sim import EndEffector, builtin_scenes, build_schedule, load_scene, simulate

SPEC_SCENES = {"calibration", "calibration_paper", "ideal", "thermal_soak", "impact",
               "low_force", "boundary", "overload", "two_devices", "smoke", "calibration_holds",
               "long_holds"}


def small(name: str, n_presses: int = 12):
    return load_scene(name).replace(schedule={"n_presses": n_presses})


def test_builtin_scenes_all_load_and_schedule():
    names = set(builtin_scenes())
    assert SPEC_SCENES <= names
    for name in names:
        scene = load_scene(name)
        sched = build_schedule(scene)
        assert len(sched) > 0 and np.all(np.diff(sched.t_s) > 0)
        assert not sched.contact[: int(0.2 * scene.sample_rate_hz)].any(), name  # tare window


def test_calibration_holds_dwells_at_every_peak():
    """The dwell protocol: each press holds its peak load for hold_s, on the calibration device."""
    scene = small("calibration_holds", 3)
    assert scene.schedule["hold_s"] == 0.5
    assert scene.effects == load_scene("calibration").effects
    sched = build_schedule(scene)
    for p in np.unique(sched.press_id[sched.contact]):
        f = sched.truth_force_N[sched.press_id == p]
        at_peak = np.isclose(f, f.max(), rtol=1e-9)
        assert at_peak.sum() >= int(0.5 * scene.sample_rate_hz) - 1, p


def test_ideal_inverts_exactly_through_the_nominal_model():
    ds = simulate(small("ideal", 20))
    force, x, y = geometry.inverse_nominal(ds.wl_nm)
    c = ds.contact
    # Float precision given absolute wavelengths (ulp(1550 nm) ~ 2e-13 nm ~ 7e-12 N per beam).
    assert np.max(np.abs(force - ds.force_N)) < 1e-9
    assert np.max(np.abs(x[c] - ds.x_mm[c])) < 1e-6
    assert np.max(np.abs(y[c] - ds.y_mm[c])) < 1e-6
    assert np.all(ds.wl_nm[:, 4] == geometry.BASE_WL_NM[4])
    # The ideal has nothing but the analytic forward model in it (where the location is in
    # the data: contact, or no force at all).
    known = c | (ds.force_N == 0)
    np.testing.assert_array_equal(ds.wl_nm[known], geometry.forward_nominal(
        ds.force_N, np.nan_to_num(ds.x_mm, nan=10.5), np.nan_to_num(ds.y_mm, nan=13.5))[known])


@pytest.mark.slow
def test_calibration_full_size_and_shape():
    ds = simulate("calibration_paper")
    assert len(ds) == 234_300 and ds.n_presses == 300
    assert set(ds.extra) == {"temperature_K"}
    c = ds.contact
    assert 0.5 < c.mean() < 0.9
    assert 60 < ds.force_N.max() <= 70 and ds.force_N.min() == 0
    assert np.all((ds.x_mm[c] >= 0.5) & (ds.x_mm[c] <= 20.5))
    assert np.all((ds.y_mm[c] >= 0.5) & (ds.y_mm[c] <= 26.5))
    # Base wavelengths within the device tolerance of the design; tared shifts within range.
    assert np.all(np.abs(ds.wl_nm[0] - geometry.BASE_WL_NM) < 1.0)
    shift = ds.wl_nm - ds.wl_nm[:200].mean(axis=0)
    assert np.all(np.abs(shift[:, :4]) < 4.0) and np.all(np.abs(shift[:, 4]) < 0.05)
    # Interrogator noise at rest (first tare window, quantised to 1 pm): within 3-10 pm.
    rest_sd_pm = ds.wl_nm[:200].std(axis=0) * 1000
    assert np.all((rest_sd_pm > 3) & (rest_sd_pm < 10)), rest_sd_pm
    # Quantised to the interrogator's 1 pm.
    np.testing.assert_allclose(ds.wl_nm * 1000, np.round(ds.wl_nm * 1000), atol=1e-6)
    # Wavelengths fall under load (compressed gratings), as the device's design says: near the
    # centre the summed shift per newton is the beams' mean sensitivity (tuned scene values
    # such as the bond's strain transfer included).
    centred = c & (np.abs(ds.x_mm - 10.5) < 2) & (np.abs(ds.y_mm - 13.5) < 2) & (ds.force_N > 20)
    per_newton_pm = (shift[centred, :4].sum(axis=1) * 1000 / ds.force_N[centred]).mean()
    expected = EndEffector("calibration").design.shift_per_newton_nm().mean() * 1000
    assert expected < 0 and per_newton_pm == pytest.approx(expected, rel=0.2)


def press_phases(sched, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Per press of a schedule: seconds at its peak force, seconds from onset to peak."""
    held, rising = [], []
    for p in np.unique(sched.press_id):
        f = sched.force_N[sched.press_id == p]
        at_peak = np.flatnonzero(np.isclose(f, f.max(), rtol=1e-9))
        held.append(at_peak.size / rate)
        rising.append((at_peak[0] - np.flatnonzero(f > 0)[0] + 1) / rate)
    return np.array(held), np.array(rising)


def test_calibration_holds_some_presses_and_spreads_speeds():
    """The default calibration holds one press in ten at its peak for 1.5-6 s and loads at
    speeds spread over 4x; `calibration_paper` (the same points and peaks) is the paper's
    protocol: one speed, no hold; `long_holds` holds every press 1.5-6 s."""
    cal = build_schedule(load_scene("calibration"))
    held, rising = press_phases(cal, 1000.0)
    holding = held > 1.0
    assert 0.05 < holding.mean() < 0.15
    assert held[holding].min() >= 1.5 and held[holding].max() <= 6.0 + 1e-3
    assert np.all(held[~holding] <= 0.002)
    assert rising.min() < 0.16 and rising.max() > 0.5 and np.all((rising > 0.14) & (rising < 0.59))
    paper = build_schedule(load_scene("calibration_paper"))
    held, rising = press_phases(paper, 1000.0)
    assert np.all(held <= 0.002) and np.all(rising == 0.29)
    np.testing.assert_array_equal(np.unique(cal.x_mm[cal.contact]),
                                  np.unique(paper.x_mm[paper.contact]))
    held, _ = press_phases(build_schedule(load_scene("long_holds")), 1000.0)
    assert held.min() >= 1.5 and held.max() <= 6.0 + 1e-3


def test_nominal_sensitivity_matches_the_paper():
    """1.5 N ≈ 10 µε ≈ 10 pm (paper §VII-B): a centred 1.5 N load on the nominal design."""
    wl = geometry.forward_nominal(np.array([1.5]), np.array([10.5]), np.array([13.5]))
    shift_pm = (wl[0, :4] - geometry.BASE_WL_NM[:4]) * 1000
    strain_ue = 1.5 / 4 * geometry.STRAIN_PER_N * 1e6
    assert 8 < strain_ue < 12 and np.all((shift_pm > -14) & (shift_pm < -8))


def test_seeded_determinism_and_seed_device_overrides():
    scene = small("smoke", 4)
    a, b = simulate(scene), simulate(scene)
    np.testing.assert_array_equal(a.wl_nm, b.wl_nm)
    other_seed = simulate(scene, seed=scene.seed + 1)
    assert not np.array_equal(a.force_N, other_seed.force_N)  # another press program
    other_device = simulate(scene, device=3)
    np.testing.assert_array_equal(a.force_N, other_device.force_N)  # same program ...
    assert not np.allclose(a.wl_nm, other_device.wl_nm, atol=0.01)  # ... another device
    assert other_device.source.endswith("device=3")


def test_two_devices_share_the_protocol_not_the_device():
    a = build_schedule(load_scene("calibration"))
    b = build_schedule(load_scene("two_devices"))
    np.testing.assert_array_equal(a.force_N, b.force_N)
    assert load_scene("two_devices").device != load_scene("calibration").device


def loop_gaps(ds) -> np.ndarray:
    """Per press: (loading - unloading) summed shift at half the peak force, relative to the
    loading shift there."""
    gaps = []
    for pid in np.unique(ds.press_id):
        p = ds.press_id == pid
        f, s = ds.force_N[p], ds.wl_nm[p, :4].sum(axis=1) * 1000
        k = int(np.argmax(f))
        half = f[k] / 2
        up = np.interp(half, f[: k + 1], s[: k + 1])
        down = np.interp(half, f[k:][::-1], s[k:][::-1])
        gaps.append((up - down) / abs(up - s[0]))
    return np.array(gaps)


@pytest.mark.parametrize("effect", ["viscoelastic", "friction_hysteresis"])
def test_pad_loop_is_visible(effect):
    gaps = loop_gaps(simulate(small("smoke", 6).replace(effects={effect: {}})))
    # The pad lags: at the same load-cell force the beams carry less while loading than while
    # unloading, so unloading reads a lower wavelength (more compression): a loop.
    assert min(gaps) > 0 and np.median(gaps) > 0.02


def test_calibration_pad_loop_strength():
    """The calibration device's pad: at half the peak force, unloading reads 6-12 % more
    than loading (friction gap 0.06 per unit force on developed branches, about 0.055 at the
    half-peak point, plus the viscoelastic lag)."""
    scene = small("calibration_paper", 8)
    assert scene.effects["friction_hysteresis"]["gap"] == 0.06
    pad_only = {k: scene.effects[k] for k in ("friction_hysteresis", "viscoelastic")}
    gaps = loop_gaps(simulate(scene.replace(effects=pad_only)))
    assert 0.06 < np.median(gaps) < 0.12, gaps
    friction = loop_gaps(simulate(scene.replace(effects={"friction_hysteresis":
                                                         pad_only["friction_hysteresis"]})))
    assert 0.04 < np.median(friction) < 0.07, friction


def test_impact_rings_and_decays_within_40_ms():
    scene = load_scene("impact").replace(schedule={"n_impacts": 3},
                                         effects={"dynamics": {}})
    ds = simulate(scene)
    j = ds.extra["impulse_Ns"]
    k = int(np.flatnonzero(j)[0])
    s = np.abs(ds.wl_nm[:, 0] - ds.wl_nm[0, 0]) * 1000
    peak = s[k:k + 5].max()
    assert peak > 50  # a tap of >= 2 mN s swings the gratings by tens of pm or more
    assert s[k + 40:k + 60].max() < 0.03 * peak  # below 3 % after 40 ms
    # The mode (720 Hz) aliases at 1 kHz: the response changes sign sample to sample.
    assert np.any(np.diff(np.sign(ds.wl_nm[k:k + 10, 0] - ds.wl_nm[0, 0])) != 0)
    assert ds.contact[k] and ds.force_N[k] == pytest.approx(j[k] * 1000)


def test_thermal_soak_has_no_contact_and_a_40K_ramp():
    ds = simulate(load_scene("thermal_soak"))
    assert not ds.contact.any()
    dT = ds.extra["temperature_K"]
    assert dT[-1000:].mean() == pytest.approx(40, abs=1)
    shift_T = (ds.wl_nm[-1000:, 4].mean() - ds.wl_nm[:1000, 4].mean()) * 1000
    assert 40 * 10 < shift_T < 40 * 25  # 10-25 pm/K


@pytest.mark.parametrize("toml,column,fragment", [
    ('[schedule]\nkind = "presses"\n[effects.nois]\n', "effects.nois", "allowed effects: tolerance"),
    ('[schedule]\nkind = "presses"\n[effects.noise]\nsigma = 3\n', "effects.noise.sigma",
     "allowed keys: sigma_pm, relative"),
    ('[schedule]\nkind = "presses"\n[effects.noise]\nsigma_pm = "3"\n', "effects.noise.sigma_pm",
     "expected a number in [0, 1000]"),
    ('[schedule]\nkind = "presses"\n[effects.viscoelastic]\ntime_constant_s = 0\n',
     "effects.viscoelastic.time_constant_s", "out of range; expected a number in (0, 100]"),
    ('[schedule]\nkind = "presses"\n[effects.hysteresis]\n[effects.viscoelastic]\n',
     "effects.viscoelastic", "given twice"),
    ('[schedule]\nkind = "presses"\n[effects.friction_hysteresis]\ngap = 0.9\n',
     "effects.friction_hysteresis.gap", "out of range"),
    ('[schedule]\nkind = "presses"\nn_presses = 2.5\n', "schedule.n_presses", "an integer"),
    ('[schedule]\nkind = "presses"\nregion = "edge"\n', "schedule.region", "one of 'pad'"),
    ('[schedule]\nkind = "walk"\n', "schedule.kind", "allowed: presses, rest, impacts"),
    ('seed = -1\n[schedule]\nkind = "rest"\n', "seed", "out of range"),
    ('colour = "red"\n[schedule]\nkind = "rest"\n', "colour", "allowed top-level keys"),
    ('[schedule]\nkind = "presses"\nforce_min_N = 9\nforce_max_N = 5\n', "schedule.force_min_N",
     "must not exceed"),
    ('[schedule]\nkind = "presses"\nhold_s = 2\nhold_max_s = 1\n', "schedule.hold_max_s",
     "at least hold_s"),
    ('[schedule]\nkind = "presses"\nspeed_spread = 0.5\n', "schedule.speed_spread",
     "out of range"),
    ('[schedule]\nkind = "presses"\n[effects.dynamics]\ninternal_rate_hz = 10500\n',
     "effects.dynamics.internal_rate_hz", "integer multiple"),
    ('description = "no schedule"\n', "schedule", "missing [schedule]"),
    ('[schedule]\nkind = "presses"\n[effects]\nnoise = 3\n', "effects.noise", "must be a table"),
])
def test_bad_scene_errors_name_file_key_and_allowed_values(tmp_path, toml, column, fragment):
    p = tmp_path / "bad.toml"
    p.write_text(toml)
    with pytest.raises(InputError) as info:
        load_scene(p)
    assert info.value.path == str(p) and info.value.column == column
    assert fragment in str(info.value)


def test_toml_syntax_and_unknown_scene_errors(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[schedule\nkind = 1\n")
    with pytest.raises(InputError, match="TOML syntax error"):
        load_scene(p)
    with pytest.raises(InputError, match="built-in scenes: .*calibration"):
        load_scene("no_such_scene")


def test_cli_simulate_round_trip(tmp_path, capsys):
    scene = tmp_path / "mini.toml"
    scene.write_text("""
description = "mini"
seed = 5
[schedule]
kind = "presses"
n_presses = 3
[effects.noise]
[effects.dropout]
rate = 0.01
""")
    out = tmp_path / "mini.csv"
    assert main(["simulate", "--scene", str(scene), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["samples"] == 3 * 781 and summary["presses"] == 3
    assert summary["file"] == str(out) and summary["effects"] == ["noise", "dropout"]
    back = dataset.load(out)
    ref = simulate(scene)
    np.testing.assert_allclose(back.wl_nm, ref.wl_nm, atol=5.1e-7, rtol=0)
    np.testing.assert_array_equal(back.extra["dropout"], ref.extra["dropout"])
    assert main(["simulate", "--scene", str(scene), "--out", str(tmp_path / "x.npz"),
                 "--seed", "9"]) == 0
    assert not np.array_equal(dataset.load(tmp_path / "x.npz").force_N[:800], ref.force_N[:800])
    assert main(["simulate", "--scene", str(scene), "--out", str(tmp_path / "x.txt")]) == 2
    assert main(["simulate", "--scene", "no_such_scene", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "x.txt" in err and "no_such_scene" in err


def test_scene_inheritance_merges_and_removes(tmp_path):
    (tmp_path / "parent.toml").write_text("""
description = "parent"
seed = 2
[schedule]
kind = "presses"
n_presses = 5
force_max_N = 30.0
[effects.noise]
sigma_pm = 6.0
[effects.hysteresis]
""")
    (tmp_path / "child.toml").write_text("""
base = "parent.toml"
device = 4
[schedule]
n_presses = 2
[effects.noise]
relative = 0.0
[effects]
hysteresis = false
quantization = {step_pm = 2.0}
""")
    child = load_scene(tmp_path / "child.toml")
    assert (child.seed, child.device, child.description) == (2, 4, "parent")
    assert child.schedule["n_presses"] == 2 and child.schedule["force_max_N"] == 30.0
    assert child.effects["noise"] == {"sigma_pm": 6.0, "relative": 0.0}
    assert list(child.effects) == ["noise", "quantization"]
    (tmp_path / "rest.toml").write_text('base = "parent.toml"\n[schedule]\nkind = "rest"\n')
    assert load_scene(tmp_path / "rest.toml").schedule == {
        "kind": "rest", "duration_s": 60.0, "contact_threshold_N": 0.05, "lead_in_s": 0.0,
        "tail_s": 0.0}


def test_scene_inheritance_errors(tmp_path):
    (tmp_path / "a.toml").write_text('base = "b.toml"\n')
    (tmp_path / "b.toml").write_text('base = "a.toml"\n')
    with pytest.raises(InputError, match="circular base"):
        load_scene(tmp_path / "a.toml")
    (tmp_path / "bad_parent.toml").write_text('[schedule]\nkind = "presses"\nn_presses = 0\n')
    (tmp_path / "c.toml").write_text('base = "bad_parent.toml"\n')
    with pytest.raises(InputError) as info:
        load_scene(tmp_path / "c.toml")
    assert info.value.path.endswith("bad_parent.toml") and info.value.column == "schedule.n_presses"
    (tmp_path / "d.toml").write_text('base = "nonesuch"\n')
    with pytest.raises(InputError, match="unknown base scene 'nonesuch'"):
        load_scene(tmp_path / "d.toml")


def test_derived_scenes_run_on_the_calibration_device():
    cal = EndEffector("calibration").design
    for name in ("smoke", "low_force", "boundary", "overload", "thermal_soak", "impact"):
        d = EndEffector(name).design
        np.testing.assert_array_equal(d.gain, cal.gain)
        np.testing.assert_array_equal(d.supports_mm, cal.supports_mm)
    assert not np.array_equal(EndEffector("two_devices").design.gain, cal.gain)


def test_a_toleranced_device_inverts_exactly_with_its_own_design():
    """Stiffness spread changes how a load splits, never the force/moment balance: the device's
    own supports and gains recover force and location exactly; the nominal ones do not."""
    ee = EndEffector({"tolerance": {"stiffness_sd": 0.3, "support_sd_y_mm": 1.0}}, device=3)
    rng = np.random.default_rng(0)
    f, x, y = rng.uniform(1, 70, 50), rng.uniform(0, 21, 50), rng.uniform(0, 27, 50)
    wl = ee.process(np.arange(50) / 1000, f, x, y)
    force, xe, ye = ee.design.inverse(wl)
    np.testing.assert_allclose(force, f, atol=1e-9)
    np.testing.assert_allclose(xe, x, atol=1e-8)
    np.testing.assert_allclose(ye, y, atol=1e-8)
    _, _, y_nominal = geometry.inverse_nominal(wl, ee.design.base_wl_nm)
    assert np.abs(y_nominal - y).max() > 0.1
