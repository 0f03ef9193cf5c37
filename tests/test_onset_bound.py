"""The information bound on onset delay (fbgforce.evaluation.onset_bound, and the bench that
prints it) against presses whose sensitivity, noise and force profile are known."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from fbgforce.bench.bench_onset_bound import main
from fbgforce.evaluation.onset_bound import FORCE_FLOOR_N, press_bounds, rest_noise_covariance
from fbgforce.recordings.dataset import Dataset, save

RATE = 1000.0
SENSITIVITY = np.array([8.0, 8.0, 4.5, 9.0, 0.0])     # pm/N per grating, the last the reference


def _presses(noise_pm: float, slope_N: float = 0.02, presses: int = 40, seed: int = 0
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shifts (pm), force and contact label of presses ramped at ``slope_N`` per sample to
    5 N, held, released, with 300-sample rests between, under white noise of ``noise_pm``."""
    rng = np.random.default_rng(seed)
    ramp = np.arange(1, int(5.0 / slope_N) + 1) * slope_N
    one = np.r_[np.zeros(300), ramp, np.full(100, 5.0), ramp[::-1]]
    force = np.tile(one, presses)
    wl = force[:, None] * SENSITIVITY + rng.normal(0.0, noise_pm, (force.size, 5)) + 1.5e6
    return wl, force, force > 0.3


def _dataset(wl: np.ndarray, force: np.ndarray, contact: np.ndarray) -> Dataset:
    """The presses of :func:`_presses` as a dataset: one press_id per labelled run."""
    n = force.size
    xy = np.where(contact, 0.0, np.nan)
    return Dataset(t_s=np.arange(n) / RATE, wl_nm=wl / 1000.0, contact=contact, x_mm=xy,
                   y_mm=xy, force_N=force,
                   press_id=np.cumsum(np.r_[0, np.diff(contact.astype(int)) == 1]))


def _always_in_contact(wl: np.ndarray, force: np.ndarray) -> Dataset:
    """The same samples labelled in contact throughout: no rest to measure the noise on."""
    n = force.size
    return Dataset(t_s=np.arange(n) / RATE, wl_nm=wl / 1000.0, contact=np.ones(n, bool),
                   x_mm=np.zeros(n), y_mm=np.zeros(n), force_N=force + 1.0,
                   press_id=np.zeros(n, int))


def _reached(noise_pm: float, slope_N: float, per_min: float = 1.0) -> int:
    """The sample of the noise-free ramp (1 its first loaded one) at which its evidence, with
    the true sensitivity and noise, reaches log(60 * rate / per_min)."""
    q = float(SENSITIVITY @ SENSITIVITY) / noise_pm ** 2
    tau = np.arange(1, 1000)
    f = tau * slope_N
    evidence = 0.5 * q * np.cumsum(np.where(f > FORCE_FLOOR_N, f, 0.0) ** 2)
    return int(tau[np.argmax(evidence >= math.log(60.0 * RATE / per_min))])


def _expected_ms(noise_pm: float, slope_N: float, per_min: float = 1.0) -> float:
    """The bound in closed form: the delay after the label (the ramp's first sample above
    0.3 N) at which the evidence reaches log(60 * rate / per_min)."""
    label = int(np.argmax(np.arange(1, 1000) * slope_N > 0.3)) + 1
    return (_reached(noise_pm, slope_N, per_min) - label) * 1000.0 / RATE


@pytest.mark.parametrize("noise_pm", [2.0, 10.0])
def test_the_bound_is_the_closed_form_of_known_presses(noise_pm):
    wl, force, contact = _presses(noise_pm)
    cov = rest_noise_covariance(wl, contact)
    assert np.sqrt(np.diag(cov)) == pytest.approx(noise_pm, rel=0.05)
    got = press_bounds(wl, force, contact, cov, RATE)
    assert len(got) == 40          # every press has its rest before it
    bound = np.median([p["onset_bound_ms"] for p in got])
    assert bound == pytest.approx(max(_expected_ms(noise_pm, 0.02), 0.0), abs=1.0)
    noise = np.median([p["force_noise_N"] for p in got])
    assert noise == pytest.approx(noise_pm / np.linalg.norm(SENSITIVITY), rel=0.05)


@pytest.mark.parametrize("lag", [4, -3])
def test_shifts_that_trail_the_load_cell_give_the_bound_of_the_shifts(lag):
    # A pad whose rubber damps the rise answers the load `lag` samples late; a load cell
    # whose clock runs behind the interrogator's reads as a negative lag. The bound is the one
    # of the shifts as they come: the closed form moved by the lag, which it reports.
    wl, force, contact = _presses(5.0, slope_N=0.1)
    trailing = np.roll(wl - 1.5e6, lag, axis=0) + 1.5e6
    cov = rest_noise_covariance(trailing, contact)
    at_once = press_bounds(wl, force, contact, cov, RATE)
    got = press_bounds(trailing, force, contact, cov, RATE)
    assert {p["shift_lag_ms"] for p in at_once} == {0.0}
    assert {p["shift_lag_ms"] for p in got} == {lag * 1000.0 / RATE}
    expected = _expected_ms(5.0, 0.1) + lag * 1000.0 / RATE
    assert np.median([p["onset_bound_ms"] for p in got]) == pytest.approx(max(expected, 0.0),
                                                                          abs=1.0)
    # Every command says so after the noise, in the same words.
    from fbgforce.evaluation.onset_bound import lag_text
    from fbgforce.trainer.coverage import coverage, coverage_lines

    said = coverage_lines(coverage([_dataset(trailing, force, contact)]))[-1]
    words = f", the shifts {abs(lag)} ms {'behind' if lag > 0 else 'ahead of'} the load cell"
    assert lag_text({"shift_lag_ms": float(lag)}) == words and words + ";" in said
    assert lag_text({"shift_lag_ms": 0.0}) == lag_text(None) == ""
    # A slow rise under heavy noise cannot tell a few samples apart: no lag is taken there.
    noisy = _presses(30.0, slope_N=0.005, presses=8)
    assert {p["shift_lag_ms"] for p in press_bounds(*noisy, rest_noise_covariance(
        noisy[0], noisy[2]), RATE)} == {0.0}


def test_more_noise_or_fewer_false_events_take_longer_and_a_slow_press_gives_its_own_bound():
    wl, force, contact = _presses(5.0)
    cov = rest_noise_covariance(wl, contact)
    base = np.median([p["onset_bound_ms"] for p in press_bounds(wl, force, contact, cov, RATE)])
    quieter = np.median([p["onset_bound_ms"]
                         for p in press_bounds(wl, force, contact, cov, RATE, per_min=0.01)])
    noisier = np.median([p["onset_bound_ms"]
                         for p in press_bounds(wl, force, contact, 4.0 * cov, RATE)])
    assert 0 < base < quieter and base < noisier
    # A press four times as slow gives evidence for four times as long before its label (the
    # release before it none: it starts from the last unloaded sample).
    slow = _presses(5.0, slope_N=0.005)
    slower = np.median([p["onset_bound_ms"] for p in press_bounds(*slow, cov, RATE)])
    assert slower == pytest.approx(_expected_ms(5.0, 0.005), abs=1.5)


def test_the_command_prints_the_bound_and_refuses_a_log_without_rests(tmp_path, capsys):
    wl, force, contact = _presses(10.0, presses=8)
    save(_dataset(wl, force, contact), tmp_path / "presses.npz")
    assert main(["--data", str(tmp_path / "presses.npz")]) == 0
    out = capsys.readouterr().out
    assert "8 presses" in out and f"{_expected_ms(10.0, 0.02):.0f}" in out
    assert "% of their samples above 1 N" in out
    save(_always_in_contact(wl, force), tmp_path / "held.npz")
    assert main(["--data", str(tmp_path / "held.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "held.npz" in err and "rest" in err


def test_the_samples_above_1N_before_the_bound_are_the_ones_no_decision_finds():
    # 30 pm and one false event in 100 minutes: the bound lies past the ramp's 1 N.
    wl, force, contact = _presses(30.0)
    cov = rest_noise_covariance(wl, contact)
    got = press_bounds(wl, force, contact, cov, RATE, per_min=0.01)
    first_above = int(1.0 / 0.02) + 1              # the ramp's first sample above 1 N
    missed = _reached(30.0, 0.02, 0.01) - first_above
    assert missed > 0
    above = int((force[:force.size // 40] > 1.0).sum())
    assert all(p["above_1N"] == above for p in got)
    # Each press misses its samples above 1 N up to its own bound (the label at the ramp's
    # 16th sample, its first above 0.3 N) ...
    label = int(0.3 / 0.02) + 1
    for p in got:
        found = label + round(p["onset_bound_ms"] * RATE / 1000.0)
        assert p["missed_above_1N"] == max(found - first_above, 0)
    # ... which lies near the closed form's (the sensitivity and the noise estimated at 30 pm).
    assert np.median([p["missed_above_1N"] for p in got]) == pytest.approx(missed, abs=3)
    # At 2 pm and one a minute the evidence is there before 1 N: nothing missed.
    quiet = _presses(2.0)
    assert all(p["missed_above_1N"] == 0
               for p in press_bounds(*quiet, rest_noise_covariance(quiet[0], quiet[2]), RATE))


def test_coverage_says_what_the_calibrations_noise_allows():
    from fbgforce.trainer.coverage import coverage, coverage_lines

    wl, force, contact = _presses(10.0, presses=20)
    cov = coverage([_dataset(wl, force, contact)])
    allows = cov["noise_allows"]
    assert allows["presses"] == 20 and allows["noise_pm"] == pytest.approx(10.0, rel=0.05)
    assert allows["onset_bound_ms"]["median"] == pytest.approx(_expected_ms(10.0, 0.02), abs=1.5)
    assert 0.0 < allows["detected_above_1N"] <= 1.0
    line = coverage_lines(cov)[-1]
    assert line.startswith(f"  the noise allows: {allows['noise_pm']:.1f} pm per grating")
    assert f"{allows['onset_bound_ms']['median']:.1f} ms after the label" in line
    # Lost peaks (a non-finite value, one out of the window) give no evidence, no zero and no
    # noise: the bound reads as without them, and nothing raises.
    lost = wl.copy()
    lost[100, 2], lost[5000, 1], lost[310:330, 0] = np.nan, 0.0, np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        faulty = coverage([_dataset(lost, force, contact)])["noise_allows"]
    assert faulty["presses"] == allows["presses"]
    assert faulty["noise_pm"] == pytest.approx(allows["noise_pm"], rel=0.01)
    assert faulty["onset_bound_ms"]["median"] == pytest.approx(
        allows["onset_bound_ms"]["median"], abs=1.0)
    # Every command reads and prints the median onset through the same two helpers.
    from fbgforce.evaluation.onset_bound import delay_text, median_onset_ms
    assert median_onset_ms(allows) == allows["onset_bound_ms"]["median"]
    assert median_onset_ms(None) is None and median_onset_ms({"onset_bound_ms": None}) is None
    assert delay_text(None) == "never" and delay_text(12.34) == "12.3 ms"
    # No rest to measure the noise on: said, not guessed.
    none = coverage([_always_in_contact(wl, force)])
    assert none["noise_allows"] is None
    assert coverage_lines(none)[-1] == ("  the noise allows: not measured (no rest to measure "
                                        "the noise on)")


def test_evaluate_reports_the_bound_on_the_presses_it_scores(capsys, small_model_dir,
                                                             small_dataset_path):
    from fbgforce.cli import main as cli
    from fbgforce.evaluation.onset_bound import bound
    from fbgforce.recordings import dataset
    from fbgforce.trainer.data import split_rows
    from fbgforce.trainer.evaluate import evaluate

    ds = dataset.load(small_dataset_path)
    for split, keep in (("all", None), ("test", split_rows(ds, 0) == 2)):
        out = evaluate(small_model_dir, [small_dataset_path], split=split)
        allows = out["noise_allows"]
        assert allows == bound([ds], keeps=[keep])
        # The test split's presses only: those with a rest before them, of those it scores.
        assert 0 < allows["presses"] <= out["contact_timing"]["presses"]
    assert "noise_allows" not in evaluate(small_model_dir, [small_dataset_path], extras=False)
    assert cli(["evaluate", "--model", str(small_model_dir), "--data",
                str(small_dataset_path), "--split", "test"]) == 0
    line = capsys.readouterr().out.splitlines()[1]
    median = out["contact_timing"]["onset_delay_ms"]["median"]
    assert line.startswith(f"onset: median {median:.1f} ms after the label; the noise (")
    assert f"sooner than {allows['onset_bound_ms']['median']:.1f} ms on these " \
           f"{allows['presses']} presses" in line
