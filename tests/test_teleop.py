"""Tests of the bilateral teleoperation scene (fbgforce.teleop): scene file, models, loop, CLI.

Kept short: the mechanical conditions (true force, no feedback) run many seeded operators in
a second or two; the sensor condition (simulator + C runtime per sample) runs a few short runs.
"""
from __future__ import annotations

import copy
import json
import tomllib
from importlib import resources

import numpy as np
import pytest

from fbgforce.cli import main as cli_main
from fbgforce.errors import InputError
from fbgforce.teleop.feedback import DelayLine, NoFeedback, SensorFeedback, TrueForce
from fbgforce.teleop.loop import measure_delay_ms, run_seeds, simulate
from fbgforce.teleop.models import Egg, Gripper, HapticMaster, arm_load_acceleration
from fbgforce.teleop.scene import load_teleop_scene, parse_scene


@pytest.fixture(scope="module")
def doc():
    text = resources.files("fbgforce.scenes").joinpath("egg_grasp.toml").read_text()
    return tomllib.loads(text)


@pytest.fixture(scope="module")
def scene():
    return load_teleop_scene("egg_grasp")


def short_scene(doc, duration_s=4.0, lift_s=2.5):
    """The egg scene shortened: grasp, then one lift move."""
    d = copy.deepcopy(doc)
    d["schedule"]["duration_s"] = duration_s
    d["teleop"]["arm"]["moves"] = [{"start_s": lift_s, "duration_s": 1.0, "dx_m": 0.2,
                                    "dz_m": 0.15}]
    return parse_scene(d, "<short>", "short")


# ------------------------------------------------------------------------------ scene file

def test_builtin_scene_is_also_a_simulator_scene(scene):
    from fbgforce.sim import EndEffector, load_scene

    sim_scene = load_scene("egg_grasp")  # the simulator ignores [teleop]
    assert sim_scene.schedule["kind"] == "rest"
    assert scene.rate_hz == 1000.0 and scene.duration_s == 10.0
    assert scene.lift_s == 4.0
    assert set(scene.sim_scene.effects) == set(sim_scene.effects)
    ee = EndEffector(scene.sim_scene, seed=3)
    assert ee.process(np.zeros(2), np.zeros(2), np.full(2, np.nan), np.full(2, np.nan)).shape == (2, 5)


@pytest.mark.parametrize("edit, column", [
    (lambda d: d["teleop"]["master"].update(peak_force_N=-1.0), "teleop.master.peak_force_N"),
    (lambda d: d["teleop"]["master"].update(peak_force_N=[1.0, 2.0]), "teleop.master.peak_force_N"),
    (lambda d: d["teleop"]["operator"].update(hand_mass_kg=[0.3, 0.1]), "teleop.operator.hand_mass_kg"),
    (lambda d: d["teleop"]["operator"].update(hand_mass_kg="heavy"), "teleop.operator.hand_mass_kg"),
    (lambda d: d["teleop"]["egg"].update(colour=1.0), "teleop.egg.colour"),
    (lambda d: d["teleop"]["egg"].pop("break_force_N"), "teleop.egg.break_force_N"),
    (lambda d: d["teleop"].pop("gripper"), "teleop.gripper"),
    (lambda d: d["teleop"].update(robot={}), "teleop.robot"),
    (lambda d: d["teleop"]["arm"]["moves"][1].update(start_s=4.5), "teleop.arm.moves"),
    (lambda d: d.update(schedule={"kind": "presses"}), "schedule.kind"),
    (lambda d: d["effects"].update(sparkle={}), "effects.sparkle"),
])
def test_bad_scenes_name_the_key(doc, edit, column):
    d = copy.deepcopy(doc)
    edit(d)
    with pytest.raises(InputError) as exc:
        parse_scene(d, "bad.toml", "bad")
    assert exc.value.path == "bad.toml"
    assert exc.value.column == column


def test_missing_scene_and_bad_toml(tmp_path):
    with pytest.raises(InputError, match="no built-in scene"):
        load_teleop_scene("no_such_scene")
    bad = tmp_path / "bad.toml"
    bad.write_text("[teleop\n")
    with pytest.raises(InputError, match="TOML"):
        load_teleop_scene(bad)


def test_draw_depends_only_on_the_runs_seed(scene):
    a = scene.draw("operator", [np.random.default_rng(7), np.random.default_rng(8)])
    b = scene.draw("operator", [np.random.default_rng(8)])
    for key, (lo, hi) in ((k, v) for k, v in scene.tables["operator"].items()
                          if isinstance(v, tuple)):
        assert a[key][1] == b[key][0]
        assert lo <= a[key][0] <= hi
    assert np.all(a["max_correction_speed_mm_s"] == 10.0)


# ------------------------------------------------------------------------------ models

def test_minimum_jerk_moves_carry_the_load(scene):
    dt = 1e-4
    t = np.arange(0.0, scene.duration_s, dt)
    load = arm_load_acceleration(scene, t)
    g = scene.fixed("arm", "gravity_m_s2")
    assert load[0] == pytest.approx(g) and load[-1] == pytest.approx(g)
    # The lift (0.15 m up in 1 s): integrating its vertical acceleration twice gives 0.15 m.
    lift = (t >= 4.0) & (t <= 5.0)
    az = np.sqrt(load[lift] ** 2) - g  # purely vertical move: |g + a| = g + a_z
    v = np.cumsum(az) * dt
    assert v[-1] == pytest.approx(0.0, abs=1e-3)
    assert np.sum(v) * dt == pytest.approx(0.15, rel=1e-3)
    # The brisk move (0.3 m in 0.7 s) peaks at 5.77 D / T^2 sideways.
    brisk = (t >= 7.5) & (t <= 8.2)
    assert np.sqrt(load[brisk].max() ** 2 - g * g) == pytest.approx(5.7735 * 0.3 / 0.49, rel=1e-3)


def test_master_stiffness_follows_force_and_saturates(scene):
    m = HapticMaster(scene)
    k = m.stiffness(np.array([0.0, m.f_full / 2, m.f_full, 10 * m.f_full]))
    assert k[0] == m.k0 and k[2] == m.kmax and k[3] == m.kmax
    assert k[1] == pytest.approx((m.k0 + m.kmax) / 2)
    f = m.force(np.array([0.0, 1e3]), np.array([10.0, 100.0]), np.zeros(2))
    assert f[0] == pytest.approx(m.k0 * 0.010)
    assert f[1] == m.f_peak  # 400 N/m * 0.1 m = 40 N asked, the Touch gives 3.3 N


def test_gripper_lag_and_speed_limit(scene):
    g = Gripper(scene, 1)
    start = g.opening_mm.copy()
    step = g.step(np.array([50.0]))  # command a 50 mm close at once
    assert start - step == pytest.approx(g.max_step_mm)  # speed limited
    for _ in range(3000):
        g.step(np.array([50.0]))
    assert g.opening_mm[0] == pytest.approx(g.command(np.array([50.0]))[0], abs=1e-6)
    k = g.chain_stiffness(np.array([150.0]))
    assert k[0] == pytest.approx(1 / (1 / 20 + 2 / 20 + 1 / 150))


def test_egg_breaks_holds_and_drops(scene):
    rng = [np.random.default_rng(i) for i in range(3)]
    params = scene.draw("egg", rng)
    egg = Egg(params, scene)
    g = scene.fixed("arm", "gravity_m_s2")
    need = egg.required_grip_N(g)
    force = np.array([params["break_force_N"][0] + 1.0, need[1] * 1.2, need[2] * 0.5])
    for _ in range(1000):
        egg.step(np.where(egg.present, force, 0.0), g, carried=True)
    assert egg.broken.tolist() == [True, False, False]
    assert egg.dropped.tolist() == [False, False, True]
    assert egg.slip_mm[1] == 0.0


def test_delay_line_and_measured_delay():
    line = DelayLine(3, 1)
    out = [line.push(np.array([float(i)]))[0] for i in range(6)]
    assert out == [0.0, 0.0, 0.0, 0.0, 1.0, 2.0]
    t = np.arange(2000) * 1e-3
    true = 5 + 5 * np.sin(2 * np.pi * 1.3 * t)
    late = np.concatenate([np.zeros(12), true[:-12]])
    assert measure_delay_ms(true, late, 1e-3) == 12.0
    assert np.isnan(measure_delay_ms(np.zeros(100), np.zeros(100), 1e-3))


# ------------------------------------------------------------------------------ the loop

def test_runs_are_seeded_and_independent_of_batch(doc):
    scene = short_scene(doc)
    a = simulate(scene, TrueForce(), [5, 6, 7])
    b = simulate(scene, TrueForce(), [6])
    np.testing.assert_array_equal(a.traces["force_true_N"][:, 1], b.traces["force_true_N"][:, 0])
    assert a.run_summary(1) == b.run_summary(0)


@pytest.mark.slow
def test_force_feedback_is_what_saves_the_egg(scene):
    """Many operators: with (ideal) force feedback nearly all carry the egg unbroken; without,
    clearly fewer, and they squeeze much harder. Delay makes the stiffening master oscillate."""
    seeds = run_seeds(100, 40)
    fed = simulate(scene, TrueForce(), seeds)
    blind = simulate(scene, NoFeedback(), seeds)
    late = simulate(scene, TrueForce(delay_ms=50), seeds)
    assert fed.rates()["success_rate"] >= 0.9
    assert blind.rates()["success_rate"] <= fed.rates()["success_rate"] - 0.1
    assert np.median(blind.outcomes["max_force_N"]) > 1.5 * np.median(fed.outcomes["max_force_N"])
    assert (np.mean(fed.outcomes["time_in_safe_band_fraction"])
            > np.mean(blind.outcomes["time_in_safe_band_fraction"]) + 0.2)
    assert late.rates()["success_rate"] < fed.rates()["success_rate"]
    assert np.all(np.isnan(blind.outcomes["estimator_delay_ms"]))
    assert np.nanmedian(late.outcomes["estimator_delay_ms"]) == 50.0


@pytest.mark.slow
def test_estimator_in_the_loop(doc, small_exported_dir):
    """The simulator + C runtime close the loop: the reported force follows the true one."""
    scene = short_scene(doc)
    fb = SensorFeedback(small_exported_dir)
    res = simulate(scene, fb, [0, 1])
    f = res.traces["force_true_N"]
    r = res.traces["force_reported_N"]
    for k in range(2):
        assert f[:, k].max() > 2.0
        assert np.corrcoef(f[:, k], r[:, k])[0, 1] > 0.8
        assert 0.0 <= res.outcomes["estimator_delay_ms"][k] <= 40.0
    assert res.run_summary(0)["estimator_delay_ms"] is not None


def test_estimator_needs_an_exported_model(small_model_dir):
    with pytest.raises(InputError, match="export"):
        SensorFeedback(small_model_dir, engine="fixed")
    with pytest.raises(InputError, match="engine"):
        SensorFeedback(small_model_dir, engine="turbo")


# ------------------------------------------------------------------------------ CLI

@pytest.mark.slow
def test_cli_json_and_files(tmp_path, capsys):
    out = tmp_path / "run"
    rc = cli_main(["teleop", "--scene", "egg_grasp", "--feedback", "true", "--runs", "3",
                   "--seed", "2", "--out", str(out), "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    for key in ("egg_broken", "egg_dropped", "max_force_N", "time_in_safe_band_fraction",
                "estimator_delay_ms", "force_rmse_N", "force_bias_N"):
        assert key in res
    assert res["force_rmse_N"] == 0.0 and res["force_bias_N"] == 0.0  # undelayed true force
    assert res["n_runs"] == 3 and res["seed"] == 2
    assert json.loads((out / "summary.json").read_text())["max_force_N"] == res["max_force_N"]
    lines = (out / "runs.csv").read_text().splitlines()
    assert len(lines) == 4 and lines[0].startswith("seed,")
    pytest.importorskip("matplotlib")
    assert (out / "fig7.png").stat().st_size > 10_000


@pytest.mark.parametrize("argv, message", [
    (["--runs", "0"], "--runs"),
    (["--feedback", "estimator"], "--model"),
    (["--scene", "nope"], "nope"),
    (["--feedback", "true", "--delay-ms", "-5"], "--delay-ms"),
])
def test_cli_bad_input_exits_2(tmp_path, capsys, argv, message):
    rc = cli_main(["teleop", "--out", str(tmp_path / "x"), *argv])
    assert rc == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_sensor_prefetch_changes_nothing(doc, small_exported_dir):
    """Computing announced contact-free stretches in blocks gives the same loop, bit for bit."""
    scene = short_scene(doc, duration_s=2.5, lift_s=2.0)
    a = simulate(scene, SensorFeedback(small_exported_dir, prefetch=True), [3])
    b = simulate(scene, SensorFeedback(small_exported_dir, prefetch=False), [3])
    assert a.traces["force_true_N"].max() > 0.0
    for key in ("force_reported_N", "force_true_N", "master_mm"):
        np.testing.assert_array_equal(a.traces[key], b.traces[key])


def test_corrupt_blob_is_an_input_error(tmp_path, small_exported_dir):
    import shutil

    bad = tmp_path / "model"
    shutil.copytree(small_exported_dir, bad)
    blob = bytearray((bad / "model.fbgm").read_bytes())
    blob[-1] ^= 0xFF  # breaks the CRC
    (bad / "model.fbgm").write_bytes(bytes(blob))
    with pytest.raises(InputError, match="export"):
        simulate(load_teleop_scene("egg_grasp"), SensorFeedback(bad), [0])


# ------------------------------------------------------------------------------ truth in the loop

def offline_test_rmse_up_to(model, force_N: float) -> float:
    """The model's offline test force RMSE over the force bins that start below ``force_N``
    (sample-weighted), from its metadata."""
    bins = [b for b in model.metadata["metrics"]["test"]["by_force"]
            if b["range_N"][0] < force_N and b["n_samples"]]
    n = sum(b["n_samples"] for b in bins)
    return float(np.sqrt(sum(b["rmse_force_N"] ** 2 * b["n_samples"] for b in bins) / n))


@pytest.mark.slow
def test_in_loop_force_error_is_bounded_by_the_offline_test_error(doc, small_exported_dir):
    """The loop's fingertip is the calibrated device, so the reported force is as good in the
    loop as on held-out calibration presses of the same force range. Factor 1.6 for what the
    loop adds: the C fixed-point engine (rounding, a few mN), grips held for seconds while the
    calibration presses never hold (the pad's creep runs further, and the memory's averages
    read a hold as no calibration press ever showed them: measured 1.11-1.48 N in the loop
    against 0.98 N offline, docs/teleop.md), and another temperature history. The bias, which
    the holds make positive (0.88-1.05 N measured), stays within 1.1 times the offline RMSE."""
    fb = SensorFeedback(small_exported_dir)
    res = simulate(short_scene(doc), fb, [0, 1, 2])
    assert fb.device_check["status"] == "verified"
    o = res.outcomes
    offline = offline_test_rmse_up_to(fb.model, float(o["max_force_N"].max()))
    assert np.all(o["max_force_N"] > 2.0)
    assert np.all(o["force_rmse_N"] <= 1.6 * offline), (o["force_rmse_N"], offline)
    assert np.all(np.abs(o["force_bias_N"]) <= 1.1 * offline), (o["force_bias_N"], offline)
    summary = res.run_summary(0)
    assert summary["force_rmse_N"] == pytest.approx(o["force_rmse_N"][0], abs=1e-4)
    assert summary["force_bias_N"] == pytest.approx(o["force_bias_N"][0], abs=1e-4)


@pytest.mark.slow
def test_a_fingertip_that_is_not_the_calibrated_device_is_refused(doc, small_exported_dir):
    """A fingertip with another bond strain transfer (0.90 against the calibration's 0.48)
    reads about twice the true force: refused, or measured with allow_other_device."""
    d = copy.deepcopy(doc)
    d["effects"] = {"tolerance": {"strain_transfer": 0.90}}
    other = parse_scene(d, "<other>", "other")
    with pytest.raises(InputError, match="strain_transfer"):
        simulate(other, SensorFeedback(small_exported_dir), [0])
    fb = SensorFeedback(small_exported_dir, allow_other_device=True)
    res = simulate(other, fb, [0])
    assert fb.device_check["status"] == "mismatch"
    assert res.outcomes["force_bias_N"][0] > 0.5 * res.outcomes["force_rmse_N"][0] > 1.0


def test_device_check_without_a_known_origin(small_exported_dir, tmp_path):
    from fbgforce.model import modeldir as fm
    from fbgforce.teleop.sensor import check_device

    model = fm.load(small_exported_dir)
    scene = load_teleop_scene("egg_grasp").sim_scene
    assert check_device(model, scene)["status"] == "verified"
    model.metadata = {**model.metadata, "data": [{"path": str(tmp_path / "moved.csv")}]}
    assert check_device(model, scene)["status"] == "unverified"
    model.metadata["data"] = [{"source": "sim:smoke seed=0 device=7"}]
    result = check_device(model, scene)
    assert result["status"] == "mismatch" and "device 7" in result["detail"]


@pytest.mark.parametrize("memory, words", [
    ({"ema_shifts": (4, 7), "play_widths": (0.05, 0.25)}, "memory averages 4,7 + plays 0.05,0.25"),
    ({"play_widths": (0.1,), "loc_shift": 5}, "memory plays 0.1)"),
    ({"loc_shift": 5}, "no memory"),
])
def test_estimator_label_names_the_memory_kinds(random_model_factory, memory, words):
    """The ablation table's label lists every kind of memory state the model has."""
    from types import SimpleNamespace

    from fbgforce.model import artifact as fm
    from fbgforce.teleop.ablation import estimator_label

    model = random_model_factory(0, sizes=((8,), (8,), (8,)), memory=fm.Memory(**memory))
    label = estimator_label(SimpleNamespace(model=model, engine="fixed", extra_delay_ms=0))
    assert label.endswith(words + ("" if words.endswith(")") else ")"))
