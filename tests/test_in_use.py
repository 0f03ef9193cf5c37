"""Robust in use: the metrics of rests and holds, the in-use foreign logs and their benchmark.

The metrics are checked on hand-made arrays whose answers are counted by hand (rest samples,
events, force at rest, holds); the in-use variants of tests/foreign.py on short logs (one
fingertip, ramps at their rate with a lagging reference, holds the metrics find); the
benchmark end to end on a few presses with the small test model and the C runtime.
"""
from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import foreign as fg  # noqa: E402

from fbgforce.evaluation import metrics  # noqa: E402

NAN = np.full(300, np.nan)


def _rest_case():
    """300 samples at 1 kHz, labelled contact on 100-109; predicted contact on 0-4 (the
    recording starts on: no event), 20-24, 95-112 and 200-201."""
    t = np.arange(300) * 1e-3
    tc = np.zeros(300, bool)
    tc[100:110] = True
    pc = np.zeros(300, bool)
    for a, b in ((0, 5), (20, 25), (95, 113), (200, 202)):
        pc[a:b] = True
    force_out = np.full(300, 0.5)
    force_out[200] = -2.0
    return t, tc, pc, force_out


def test_rest_samples_events_and_force_at_rest():
    t, tc, pc, force_out = _rest_case()
    use = metrics.use_masks(pc, tc, np.where(tc, 3.0, 0.0), t)
    # At least 50 ms (50 samples) from labelled contact: samples 0-50 and 159-299.
    assert np.array_equal(np.flatnonzero(use["rest"]),
                          np.r_[np.arange(0, 51), np.arange(159, 300)])
    assert np.array_equal(np.flatnonzero(use["event"]), [20, 95, 200])
    m = metrics.compute({"contact": pc, "force_N": force_out, "x_mm": NAN, "y_mm": NAN}, tc,
                        np.where(tc, 3.0, 0.0), NAN, NAN, use=use)
    rest = m["at_rest"]
    # The rise at 95 is 5 ms before the labelled onset: not at rest, so not a false event.
    assert rest["samples"] == 192 and rest["false_events"] == 2
    assert rest["seconds"] == pytest.approx(0.192)
    assert rest["false_events_per_min"] == pytest.approx(2 / 0.192 * 60)
    assert rest["contact_fraction"] == pytest.approx(12 / 192)
    # |force output| at rest: 180 zeros, eleven 0.5 N and one 2 N (sample 200, -2 N).
    assert rest["force_max_N"] == pytest.approx(2.0)
    assert rest["force_p99_N"] == pytest.approx(0.5)


def test_rest_seconds_add_up_over_recordings_of_other_rates():
    t, tc, pc, force_out = _rest_case()
    fast = metrics.use_masks(pc, tc, np.zeros(300), t)
    slow = metrics.use_masks(pc, tc, np.zeros(300), 2 * t)   # 500 Hz: the gap is 25 samples
    assert np.array_equal(np.flatnonzero(slow["rest"]),
                          np.r_[np.arange(0, 76), np.arange(134, 300)])
    use = {k: np.concatenate([fast[k], slow[k]]) for k in metrics.USE_KEYS}
    pred = {"contact": np.r_[pc, pc], "force_N": np.r_[force_out, force_out],
            "x_mm": np.r_[NAN, NAN], "y_mm": np.r_[NAN, NAN]}
    m = metrics.compute(pred, np.r_[tc, tc], np.zeros(600), np.r_[NAN, NAN], np.r_[NAN, NAN],
                        use=use)
    assert m["at_rest"]["seconds"] == pytest.approx(0.192 + 2e-3 * 242)
    assert m["at_rest"]["false_events"] == 4


def test_masks_of_a_recording_shorter_than_the_rest_gap():
    # 30 samples at 1 kHz, contact on 10-11: every sample lies within 50 ms of it, so none is
    # at rest, and every mask has the recording's length.
    tc = np.zeros(30, bool)
    tc[10:12] = True
    use = metrics.use_masks(tc, tc, tc * 1.0, np.arange(30) * 1e-3)
    assert all(use[k].shape == (30,) for k in metrics.USE_KEYS)
    assert not use["rest"].any() and not use["held"].any() and not use["after_turn"].any()

def _press(rise: int, level: float, hold: int, fall: int, rest: int) -> np.ndarray:
    return np.concatenate([np.zeros(rest), np.linspace(0.0, level, rise, endpoint=False),
                           np.full(hold, level), np.linspace(level, 0.0, fall)])


def test_holds_are_long_steady_contacts():
    # A 1.5 s hold at 5 N, a 0.6 s one at 2 N (too short), a ramp at 2 N/s for 2 s (not held).
    force = np.concatenate([_press(300, 5.0, 1500, 300, 200), _press(100, 2.0, 600, 100, 500),
                            np.zeros(300), np.linspace(0.5, 4.5, 2000), np.zeros(300)])
    n = force.size
    t = np.arange(n) * 1e-3
    tc = force > 0.3
    use = metrics.use_masks(tc, tc, force, t)
    assert use["hold_start"].sum() == 1
    held = np.flatnonzero(use["held"])
    plateau = np.arange(500, 2000)            # the 5 N samples
    assert set(held) <= set(plateau) and 1200 < held.size <= 1500
    pred = {"contact": tc, "force_N": force + 0.1, "x_mm": np.full(n, np.nan),
            "y_mm": np.full(n, np.nan)}
    m = metrics.compute(pred, tc, force, np.full(n, np.nan), np.full(n, np.nan), use=use)
    assert m["holds"]["holds"] == 1 and m["holds"]["samples"] == held.size
    assert m["holds"]["force_bias_N"] == pytest.approx(0.1)
    assert m["holds"]["rmse_force_N"] == pytest.approx(0.1)
    # Load-cell noise is not a change of load: still the same hold.
    noisy = force + np.random.default_rng(0).normal(0.0, 0.03, n)
    again = metrics.use_masks(tc, tc, noisy, t)
    assert again["hold_start"].sum() == 1 and set(np.flatnonzero(again["held"])) <= set(plateau)
    # No hold at all: the summary says so with nulls, not NaN.
    free = np.zeros(n, bool)
    none = metrics.hold_summary(force, force, metrics.use_masks(free, free, np.zeros(n), t))
    assert none["holds"] == 0 and none["force_bias_N"] is None and none["rmse_force_N"] is None


def test_turns_of_the_load_and_the_holds_away_from_them():
    # A grip at 20 N wandering +-3 N over 4 s for 8 s, between rests; load-cell noise of 30 mN.
    t = np.arange(12000) * 1e-3
    grip = (t >= 2.0) & (t < 10.0)
    force = np.where(grip, 20.0 + 3.0 * np.sin(2 * np.pi * (t - 2.0) / 4.0), 0.0)
    noisy = force + np.random.default_rng(1).normal(0.0, 0.03, t.size)
    smooth = np.convolve(noisy, np.ones(20) / 20, mode="same")
    # The sine's extremes (3, 5, 7, 9 s) and the grip's last sample before the release; the
    # noise (well inside the 0.2 N band) turns nothing.
    turns = t[metrics.load_turns(smooth, metrics.HOLD_BAND_N)]
    assert np.allclose(turns[:4], [3.0, 5.0, 7.0, 9.0], atol=0.05) and turns.size == 5
    assert 9.9 <= turns[4] < 10.0
    use = metrics.use_masks(grip, grip, noisy, t)
    # A model that reads the branch wrong for half a second after each turn, right elsewhere.
    err = np.where(use["after_turn"] & (np.mod(t - 1.0, 2.0) < 0.5), 1.0, 0.02)
    pred = {"contact": grip, "force_N": noisy + err, "x_mm": np.full(t.size, np.nan),
            "y_mm": np.full(t.size, np.nan)}
    holds = metrics.compute(pred, grip, noisy, np.full(t.size, np.nan), np.full(t.size, np.nan),
                            use=use)["holds"]
    away = holds["away_from_turns"]
    assert away["after_turn_s"] == metrics.AFTER_TURN_S
    assert 0.5 < away["fraction"] < 0.8 and holds["force_bias_N"] > 0.2
    assert away["force_bias_N"] == pytest.approx(0.02)
    assert away["rmse_force_N"] == pytest.approx(0.02)
    # The load falls from each high (3, 7 s) to the next low (5, 9 s) and from the last one to
    # the release; a friction's signature reads the falls high and the rises low.
    falling = use["falling"]
    assert falling[(t > 3.05) & (t < 4.95)].all() and falling[(t > 7.05) & (t < 8.95)].all()
    assert not falling[(t > 2.0) & (t < 2.95)].any() and not falling[(t > 5.05) & (t < 6.95)].any()
    assert falling[(t > 10.0) & (t < 10.5)].all() and not falling[t < 1.0].any()
    pred["force_N"] = noisy + np.where(falling, 0.5, -0.5)
    direction = metrics.compute(pred, grip, noisy, np.full(t.size, np.nan),
                                np.full(t.size, np.nan), use=use)["holds"]["by_direction"]
    assert direction["falling"]["force_bias_N"] == pytest.approx(0.5)
    assert direction["rising"]["force_bias_N"] == pytest.approx(-0.5)
    assert direction["falling"]["fraction"] == pytest.approx(0.5, abs=0.05)
    # A flat hold has no turn until its release: every held sample is away from turns.
    flat = _press(300, 5.0, 1500, 300, 200)
    tf = np.arange(flat.size) * 1e-3
    flat_use = metrics.use_masks(flat > 0.3, flat > 0.3, flat, tf)
    assert not (flat_use["after_turn"] & flat_use["held"]).any()


def test_contact_bins_reach_20N():
    tc = np.ones(4, bool)
    tf = np.array([0.7, 15.0, 25.0, 60.0])
    pc = np.array([1, 1, 0, 1], bool)
    nan = np.full(4, np.nan)
    m = metrics.compute({"contact": pc, "force_N": tf, "x_mm": nan, "y_mm": nan}, tc, tf, nan,
                        nan)
    bins = {tuple(b["range_N"]): (b["n_samples"], b["contact_accuracy"])
            for b in m["contact_by_force"]}
    assert bins[(10.0, 20.0)] == (1, 1.0) and bins[(20.0, None)] == (2, 0.5)


def _in_use_log(name: str, presses: int):
    spec = fg.IN_USE_VARIANTS[name]
    dev = fg.device(spec, fg.device_seed(name))
    return dev, fg.log(dev, 2, presses)


def test_in_use_variants_are_one_fingertip_and_ramps_hold_the_same_presses():
    devs = [fg.device(s, fg.device_seed(n)) for n, s in fg.IN_USE_VARIANTS.items()]
    # One pad answers a load alike whatever the protocol's range of presses (light presses
    # of at most 3 N included): the same shifts for the same load at the same place.
    load = np.array([0.5, 2.0, 20.0, 45.0])
    xs, ys = np.full(4, 12.0), np.full(4, 25.0)
    for d in devs[1:]:
        np.testing.assert_array_equal(d.supports_mm, devs[0].supports_mm)
        np.testing.assert_array_equal(d.temp_coeff, devs[0].temp_coeff)
        np.testing.assert_array_equal(fg.strain_pm(d, load, xs, ys),
                                      fg.strain_pm(devs[0], load, xs, ys))
    # Thermal coefficients a few per cent from the reference grating's.
    assert np.all(np.abs(devs[0].temp_coeff - 1.0) <= fg.IN_USE_FINGERTIP.temp_coeff_spread)
    _, const = _in_use_log("const_temp", 4)
    _, ramp = _in_use_log("ramp40K_fast", 4)
    np.testing.assert_array_equal(const.force_N, ramp.force_N)
    assert np.all(const.extra["room_C"] == 22.0)


def test_ramp_rate_and_lagging_reference_grating():
    # Without the wander (up to 3 pm, a quarter of the lag's 13 pm) the lag is read cleanly.
    spec = replace(fg.IN_USE_VARIANTS["ramp40K_fast"], wander_pm=0.0)
    dev = fg.device(spec, fg.device_seed("ramp40K_fast"))
    ds = fg.log(dev, 2, 6)
    temp = ds.extra["room_C"] - 22.0
    first_press = int(np.argmax(ds.force_N > 0.3))
    # Constant until the first press (the start-up tare), then 20 K/min.
    assert np.all(temp[:first_press - 400] == 0.0)
    rise = np.polyfit(ds.t_s[-5000:], temp[-5000:], 1)[0] * 60.0
    assert rise == pytest.approx(spec.ramp_K_per_min, rel=1e-6)
    # The temperature grating trails the ramp by rate x lag once the lag has settled.
    seen_K = (ds.wl_nm[-2000:, 4] - dev.base_nm[4]) * 1000.0 / dev.temp_pm_per_K
    trail = np.mean(temp[-2000:] - seen_K)
    expected = spec.ramp_K_per_min / 60.0 * spec.temp_lag_s
    assert trail == pytest.approx(expected, rel=0.05)


def test_a_grip_held_through_a_ramp_holds_while_the_ramp_goes_on_and_stops():
    spec = replace(fg.IN_USE_VARIANTS["ramp_hold"], last_hold_s=40.0, drift_K=10.0)
    ds = fg.log(fg.device(spec, fg.device_seed("ramp_hold")), 2, 3)
    temp = ds.extra["room_C"] - 22.0
    last = np.flatnonzero(ds.press_id == ds.press_id[-1])
    last = last[np.asarray(ds.force_N)[last] > 0.5 * np.median(np.asarray(ds.force_N)[last])]
    # The last press is the long one, and the ramp both goes on and ends under it.
    assert last.size / spec.rate_hz > spec.last_hold_s
    t_held = temp[last]
    assert t_held[0] < spec.drift_K - 1.0 and t_held[-1] == spec.drift_K


def test_wander_is_slow_and_a_few_pm():
    spec = fg.IN_USE_VARIANTS["long_rests"]
    t = np.arange(0, 600, 1e-3)
    w = fg.wander_pm(spec, np.random.default_rng(3), t)
    assert w.shape == (t.size, 5)
    assert np.max(np.abs(w)) <= spec.wander_pm and np.ptp(w, axis=0).min() > 0.5
    assert np.max(np.abs(np.diff(w, axis=0))) < 1e-3     # pm per ms: slow


def test_calibration_log_is_about_1K_with_short_holds():
    _, ds = _in_use_log("calib_1K", 30)
    temp = ds.extra["room_C"] - 22.0
    assert 0.7 < np.ptp(temp) < 1.4
    assert fg.IN_USE_VARIANTS["calib_1K"].hold_s[1] <= 0.15
    assert metrics.use_masks(ds.contact, ds.contact, ds.force_N, ds.t_s)["held"].sum() == 0


def test_held_grips_are_found_as_holds():
    spec = fg.IN_USE_VARIANTS["held_grips"]
    _, ds = _in_use_log("held_grips", 5)
    use = metrics.use_masks(ds.contact, ds.contact, ds.force_N, ds.t_s)
    # Every press holds 1.5-6 s: one hold each, lasting most of its plateau.
    assert use["hold_start"].sum() == 5
    assert use["held"].sum() > 5 * (spec.hold_s[0] - 0.3) * spec.rate_hz
    # The grips wander +-15 % about levels of 3-40 N, below the calibration's 50 N.
    force = np.asarray(ds.force_N)
    starts = np.flatnonzero(use["hold_start"])
    ends = np.flatnonzero(use["held"] & ~np.r_[use["held"][1:], False])
    spans = []
    for a, b in zip(starts, ends):
        grip = np.convolve(force[a:b + 1], np.ones(20) / 20, mode="valid")
        assert np.std(grip) < spec.hold_modulation * np.mean(grip)
        spans.append(np.ptp(grip) / np.mean(grip))
    assert np.median(spans) > 0.1
    assert force.max() < (1 + spec.hold_modulation) * spec.force_max_N + 0.2
    assert spec.force_max_N * (1 + spec.hold_modulation) < fg.IN_USE_VARIANTS["calib_3K"].force_max_N


@pytest.mark.slow
def test_script_writes_in_use_logs_with_roles(tmp_path):
    assert fg.main(["--out", str(tmp_path), "--presses", "2", "const_temp", "ramp20K",
                    "long_rests"]) == 0
    entries = json.loads((tmp_path / fg.MANIFEST).read_text())["variants"]
    assert entries["const_temp"]["role"] == "constant"
    assert entries["ramp20K"]["ramp_K"] == 20.0 and entries["ramp20K"]["ramp_K_per_min"] == 10.0
    assert {e["device_seed"] for e in entries.values()} == {200}
    assert all((tmp_path / e["other"]).is_file() for e in entries.values())
    assert fg.main(["--out", str(tmp_path), "nosuchvariant"]) == 2


@pytest.fixture(scope="module")
def in_use_logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("in_use")
    fg.write_logs(root, ["const_temp", "ramp40K_fast", "held_grips"], presses=3)
    return root


def test_bench_scores_every_goal(in_use_logs, small_exported_dir, capsys):
    from fbgforce.bench import bench_in_use
    from fbgforce.bench.bench_idle import idle_events
    from fbgforce.evaluation.onset_bound import rest_noise_covariance
    from fbgforce.recordings import dataset
    from fbgforce.trainer.evaluate import evaluate

    assert bench_in_use.main(["--model", str(small_exported_dir), "--logs", str(in_use_logs),
                              "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    rows = {r["key"]: r for r in res["goals"]}
    assert set(rows) == set(bench_in_use.GOALS)
    assert rows["ramp_hold_bias"]["pass"] is None     # no ramp_hold log in this directory
    assert rows["light_accuracy"]["pass"] is None     # nor light presses
    # The calibration's own test presses: contact errors of the same engine on its test split.
    cal = evaluate(small_exported_dir, [d["path"] for d in res_model_data(small_exported_dir)],
                   engine="fixed", split="test")
    assert rows["test_contact_errors"]["value"] == pytest.approx(1.0 - cal["contact_accuracy"])
    assert rows["test_contact_errors"]["scored_on"] == [
        f"calibration test, {cal['contact_timing']['presses']} presses"]
    assert res["passed"] + res["failed"] + res["not_measured"] == len(rows)
    for r in rows.values():
        assert r["pass"] is None or r["pass"] == (abs(r["value"]) <= r["target"]
                                                  if r["compare"] == "abs<="
                                                  else r["value"] <= r["target"]
                                                  if r["compare"] == "<="
                                                  else r["value"] >= r["target"])
    # The ramp's RMSE ratio is against the same presses at constant temperature, each log run
    # through the fixed-point runtime tared at start-up (what `fbgforce evaluate` does).
    ramp = evaluate(small_exported_dir, [in_use_logs / "ramp40K_fast_B.csv"], engine="fixed")
    const = evaluate(small_exported_dir, [in_use_logs / "const_temp_B.csv"], engine="fixed")
    assert rows["rmse_ratio"]["value"] == pytest.approx(ramp["rmse_force_N"]
                                                         / const["rmse_force_N"])
    assert rows["rest_contact"]["value"] == pytest.approx(ramp["at_rest"]["contact_fraction"])
    assert rows["false_events"]["scored_on"] == ["const_temp"]
    # The idle pad at the constant-temperature logs' interrogator noise, tests/foreign.py's
    # in-use fingertip's 5 pm: the worst draw of bench_idle, the same engine.
    ds = dataset.load(in_use_logs / "const_temp_B.csv")
    noise = float(np.median(np.sqrt(np.diag(rest_noise_covariance(
        1000.0 * np.asarray(ds.wl_nm), ds.contact, ds.t_s)))))
    assert noise == pytest.approx(5.0, abs=0.2)
    assert rows["idle_false_events"]["scored_on"] == [f"idle at {noise:.1f} pm"]
    assert rows["idle_false_events"]["value"] == idle_events(
        str(small_exported_dir), noise_pm=noise)["worst_per_min"]
    assert res["scored"]["held_grips"]["holds"]["holds"] == 3
    assert bench_in_use.main(["--model", str(small_exported_dir), "--logs",
                              str(in_use_logs)]) == 0
    text = capsys.readouterr().out
    assert "| force at rest, 99th percentile | ramp40K_fast |" in text
    # Beside the onset goal: what the constant-temperature logs' noise allows any decision.
    allows = res["scored"]["constant+rest"]["noise_allows"]
    assert allows["presses"] > 0
    assert (f"- the noise allows on the constant-temperature presses: onset "
            f"{allows['onset_bound_ms']['median']:.1f} ms, "
            f"{100 * allows['detected_above_1N']:.2f} % of the samples above 1 N") in text
    # Beside the held-grip goals: the same holds away from the load's turns.
    away = res["scored"]["held_grips"]["holds"]["away_from_turns"]
    assert 0.0 < away["fraction"] <= 1.0
    assert (f"- held grips away from the load's turns (the held samples more than 0.75 s after "
            f"one): force bias {away['force_bias_N']:+.3f} N, RMSE "
            f"{away['rmse_force_N'] / res['calibration_test_rmse_force_N']:.2f}×") in text
    rises = res["scored"]["held_grips"]["holds"]["by_direction"]
    assert (f"- held grips by the load's direction: force bias "
            f"{rises['rising']['force_bias_N']:+.3f} N / "
            f"{rises['falling']['force_bias_N']:+.3f} N") in text


def test_bench_goals_without_their_logs_are_not_measured(in_use_logs, small_exported_dir,
                                                         tmp_path):
    from fbgforce.bench import bench_in_use

    entries = json.loads((in_use_logs / fg.MANIFEST).read_text())["variants"]
    only = {"const_temp": {**entries["const_temp"],
                           "other": str(in_use_logs / entries["const_temp"]["other"]),
                           "train": str(in_use_logs / entries["const_temp"]["train"])}}
    (tmp_path / fg.MANIFEST).write_text(json.dumps({"variants": only}))
    res = bench_in_use.score(small_exported_dir, tmp_path)
    verdict = {r["key"]: (r["value"], r["pass"]) for r in res["goals"]}
    assert verdict["rest_contact"] == (None, None) and verdict["hold_bias"] == (None, None)
    assert verdict["false_events"][0] is not None
    # Ramps (3), holds (2), the grip through a ramp and light presses are not measured; the
    # calibration's test presses are, from the model's own training logs.
    assert res["not_measured"] == 7 and verdict["test_contact_errors"][0] is not None


def res_model_data(model_dir):
    return json.loads((model_dir / "model.json").read_text())["metadata"]["data"]


@pytest.mark.slow
def test_family_members_differ_in_their_physics_only(tmp_path):
    # Every member is the in-use fingertip's device with one piece of its physics changed.
    assert set(fg.FAMILY) >= {"in_use", "no_creep", "creep_50ms", "creep_5s", "viscous"}
    base = fg.device(fg.IN_USE_FINGERTIP, 200)
    for member, physics in fg.FAMILY.items():
        dev = fg.device(replace(fg.IN_USE_FINGERTIP, **physics), 200)
        np.testing.assert_array_equal(dev.supports_mm, base.supports_mm)
        np.testing.assert_array_equal(dev.gain_pm_per_N, base.gain_pm_per_N)
        assert set(physics) <= {"creep", "creep_s", "friction", "viscous_s", "noise_pm",
                                "temp_lag_s", "temp_coeff_spread"}, member
    assert fg.main(["--out", str(tmp_path), "--family", "--presses", "2", "no_creep"]) == 0
    listed = json.loads((tmp_path / fg.FAMILY_MANIFEST).read_text())["members"]
    assert list(listed) == ["no_creep"] and listed["no_creep"]["physics"] == {"creep": 0.0}
    variants = json.loads((tmp_path / "no_creep" / fg.MANIFEST).read_text())["variants"]
    assert {e["role"] for e in variants.values()} == {"calibration", "constant", "ramp", "rest",
                                                      "hold", "light"}
    # Two calibrations: about a kelvin, and a few, where temperature coefficients get fitted.
    assert [n for n, e in variants.items() if e["role"] == "calibration"] == ["calib_1K",
                                                                              "calib_3K"]
    assert fg.IN_USE_VARIANTS["calib_3K"].drift_K == 3.0
    assert fg.main(["--out", str(tmp_path), "--family", "nosuchmember"]) == 2


def test_family_cli_writes_as_many_presses_as_the_tables_were_measured_on(tmp_path, monkeypatch):
    # Without --presses the family gets the count docs/robustness.md was measured on, the
    # variants theirs; a count below 2 is refused for both.
    asked = []
    monkeypatch.setattr(fg, "write_family", lambda out, members, presses: asked.append(presses))
    monkeypatch.setattr(fg, "write_logs", lambda out, names, presses: asked.append(presses))
    assert fg.main(["--out", str(tmp_path), "--family"]) == 0
    assert fg.main(["--out", str(tmp_path), "--family", "--presses", "7"]) == 0
    assert fg.main(["--out", str(tmp_path), "const_temp"]) == 0
    assert asked == [fg.FAMILY_PRESSES, 7, fg.VARIANT_PRESSES]
    assert fg.FAMILY_PRESSES == 100
    assert fg.main(["--out", str(tmp_path), "--family", "--presses", "1"]) == 2


def test_a_family_member_trains_on_the_calibration_asked_for(tmp_path, monkeypatch, capsys):
    from fbgforce.bench import bench_in_use

    for name in ("calib_1K_A.csv", "calib_1K_B.csv", "calib_3K_A.csv", "calib_3K_B.csv"):
        (tmp_path / name).write_text("")
    (tmp_path / fg.MANIFEST).write_text(json.dumps({"variants": {
        v: {"train": f"{v}_A.csv", "other": f"{v}_B.csv", "role": "calibration"}
        for v in ("calib_1K", "calib_3K")}}))
    ran = []
    monkeypatch.setattr(bench_in_use, "_cli", ran.append)
    for calibration in (None, "calib_3K"):
        asked = [] if calibration is None else [calibration]
        bench_in_use.member_model(tmp_path, tmp_path / "model", 3, ["--epochs=1"], *asked)
    assert [r[:3] for r in ran[::2]] == [["train", "--data", str(tmp_path / "calib_1K_A.csv")],
                                         ["train", "--data", str(tmp_path / "calib_3K_A.csv")]]
    assert ran[0][-3:] == ["--seed", "3", "--epochs=1"]
    with pytest.raises(SystemExit) as exc:
        bench_in_use.member_model(tmp_path, tmp_path / "model", 0, [], "calib_9K")
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "no calibration 'calib_9K'" in err and "calib_1K, calib_3K" in err


def test_viscous_pad_reads_rate_not_creep():
    # The damper reads a press's loading low and its unloading high, by more the faster the
    # load moves, and nothing once it stands: a hold reads the load, with no creep after it.
    spec = replace(fg.IN_USE_FINGERTIP, creep=0.0, friction=0.0, viscous_s=0.004)
    plain = replace(spec, viscous_s=0.0)
    dev, dev0 = fg.device(spec, 200), fg.device(plain, 200)
    f = np.concatenate([np.linspace(0, 20, 200), np.full(500, 20.0), np.linspace(20, 0, 100),
                        np.zeros(300)])
    x, y = np.full(f.size, 15.0), np.full(f.size, 20.0)
    s, s0 = fg.strain_pm(dev, f, x, y).sum(axis=1), fg.strain_pm(dev0, f, x, y).sum(axis=1)
    assert np.all(s[20:190] < s0[20:190]) and np.all(s[720:790] > s0[720:790])
    # Unloading is twice as fast as loading: twice the gap.
    gap_up, gap_down = np.median(s0[50:150] - s[50:150]), np.median(s[720:780] - s0[720:780])
    assert gap_down / gap_up == pytest.approx(2.0 * s0[720:780].mean() / s0[50:150].mean(),
                                              rel=0.35)
    np.testing.assert_allclose(s[250:650], s0[250:650], atol=1e-9)
    np.testing.assert_allclose(s[850:], s0[850:], atol=1e-9)


def test_friction_pad_is_passive():
    # A friction takes work from the pad, never gives it: where the load turns back, the beams'
    # load stays (the pad sticks) and never moves against the load, then slips onto the other
    # branch, below the load on the rise and above it on the fall.
    rise = np.linspace(0.0, 20.0, 400)
    t = np.arange(2000) / 1000.0
    wander = 20.0 - 3.0 * (1.0 - np.cos(2.0 * np.pi * t))
    f = np.concatenate([rise, wander, np.linspace(20.0, 0.0, 400)])
    beam = fg.pad_friction(np.repeat(f[:, None], 4, axis=1), gap=0.05, sharpness=4.0)[:, 0]
    df, db = np.diff(f), np.diff(beam)
    assert not np.any(df * db < -1e-12)
    # Coulomb: on a slipping branch the beams carry about (1 ± mu) of the load, never more.
    assert np.all(np.abs(db) <= 1.03 * np.abs(df))
    top = rise.size - 1
    assert beam[top:top + 500].max() <= beam[top] + 1e-9
    mid_rise, mid_fall = 200, rise.size + wander.size + 200
    assert f[mid_rise] - beam[mid_rise] == pytest.approx(0.025 * f[mid_rise], rel=0.05)
    assert beam[mid_fall] - f[mid_fall] == pytest.approx(0.025 * f[mid_fall], rel=0.05)
    assert beam[-1] == 0.0


@pytest.mark.slow
def test_family_bench_names_the_worst_member(in_use_logs, small_exported_dir, tmp_path, capsys):
    import shutil

    from fbgforce.bench import bench_in_use

    # Two members on the same logs, their models already in --work (scored as they are): the
    # worst of each goal is the larger (smaller for >=) of the two.
    root = tmp_path / "fam"
    members = {}
    for member in ("a", "b"):
        shutil.copytree(in_use_logs, root / member)
        shutil.copytree(small_exported_dir, tmp_path / "work" / member / "model")
        members[member] = {"manifest": f"{member}/{fg.MANIFEST}", "physics": {}}
    (root / fg.FAMILY_MANIFEST).write_text(json.dumps({"members": members}))
    assert bench_in_use.main(["--family", str(root), "--work", str(tmp_path / "work"),
                              "--without", "hold_gain", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    rows = {r["key"]: r for r in res["goals"]}
    bias = rows["hold_bias"]
    assert set(bias["values"]) == {"a", "b"} and bias["worst"] == bias["values"]["a"]
    assert bias["pass"] == (abs(bias["worst"]) <= 0.1)
    # Without the settled-hold gain the holds read what the nets read.
    held = res["members"]["a"]["without"]["hold_gain"]["scored"]["held_grips"]["holds"]
    assert held["holds"] == 3 and set(bias["without"]["hold_gain"]["values"]) == {"a", "b"}
    copy = json.loads((tmp_path / "work" / "a" / "without_hold_gain" / "model.json").read_text())
    assert copy["in_use"]["hold_gain"] == 0.0
    assert bench_in_use.main(["--family", str(root), "--work", str(tmp_path / "work")]) == 0
    text = capsys.readouterr().out
    assert "| force bias over the holds | within ±0.1 N |" in text
    onset = res["members"]["a"]["scored"]["constant+rest"]["noise_allows"]["onset_bound_ms"]
    assert f"| onset the noise allows, median | | {onset['median']:.1f} ms | " in text
    away = res["members"]["a"]["scored"]["held_grips"]["holds"]["away_from_turns"]
    assert (f"| force bias over the holds, more than 0.75 s after a turn of the load | | "
            f"{away['force_bias_N']:+.3f} N | ") in text
    rises = res["members"]["a"]["scored"]["held_grips"]["holds"]["by_direction"]
    assert (f"| force bias over the holds, load rising / falling | | "
            f"{rises['rising']['force_bias_N']:+.3f} N / "
            f"{rises['falling']['force_bias_N']:+.3f} N | ") in text
    # Members scored in separate runs combine into the same table.
    for member in ("a", "b"):
        assert bench_in_use.main(["--family", str(root), "--work", str(tmp_path / "work"),
                                  "--member", member, "--without", "hold_gain", "--json"]) == 0
        (tmp_path / f"{member}.json").write_text(capsys.readouterr().out)
    assert bench_in_use.main(["--combine", str(tmp_path / "a.json"), str(tmp_path / "b.json"),
                              "--json"]) == 0
    both = json.loads(capsys.readouterr().out)
    assert {r["key"]: r["worst"] for r in both["goals"]} == {r["key"]: r["worst"]
                                                             for r in res["goals"]}
    with pytest.raises(SystemExit) as exc:
        bench_in_use.main(["--family", str(root)])
    assert exc.value.code == 2


def test_evaluate_json_reports_rests_and_holds(in_use_logs, small_exported_dir, capsys):
    from fbgforce.cli import main

    assert main(["evaluate", "--model", str(small_exported_dir), "--data",
                 str(in_use_logs / "held_grips_B.csv"), "--engine", "fixed", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"samples", "seconds", "contact_fraction", "false_events", "false_events_per_min",
            "force_p99_N", "force_max_N", "gap_ms"} <= set(out["at_rest"])
    assert out["holds"]["holds"] == 3 and out["holds"]["rmse_force_N"] is not None
    assert main(["evaluate", "--model", str(small_exported_dir), "--data",
                 str(in_use_logs / "held_grips_B.csv"), "--engine", "fixed"]) == 0
    text = capsys.readouterr().out
    holds = out["holds"]
    assert (f"holds: 3 ({holds['seconds']:.0f} s), force bias {holds['force_bias_N']:+.3f} N, "
            f"RMSE {holds['rmse_force_N']:.3f} N") in text


def test_bench_bad_logs_exit_2(tmp_path, small_exported_dir, capsys):
    from fbgforce.bench import bench_in_use

    with pytest.raises(SystemExit) as exc:
        bench_in_use.main(["--model", str(small_exported_dir), "--logs", str(tmp_path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bench_in_use: ") and "\n" not in err
