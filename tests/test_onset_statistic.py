"""The quickest CUSUM within a false-event rate on recordings (bench/bench_onset_statistic.py):
its threshold, its onsets on series whose crossing is known, and the command."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fbgforce.bench.bench_onset_statistic import main, onsets_ms, quiet_threshold, rest_peaks


def test_the_threshold_is_the_least_that_keeps_the_rate():
    peaks = np.array([1.0, 5.0, 3.0, 2.0, 4.0])
    h = quiet_threshold(peaks, minutes=2.0, per_min=1.0)
    assert np.sum(peaks >= h) == 2 and 3.0 < h < 3.0 + 1e-12
    # No more peaks than allowed: any h above 0 keeps the rate, and 0 would call every sample
    # contact.
    assert 0.0 < quiet_threshold(peaks, minutes=10.0, per_min=1.0) < 1e-300


def _recording(level: float, spikes: tuple[int, ...] = ()) -> dict:
    """Rest at -1 with one press at ``level`` from sample 1000 to 1100, 1 kHz; ``spikes``:
    rest samples at +10."""
    s = np.full(2000, -1.0)
    s[1000:1100] = level
    s[list(spikes)] = 10.0
    contact = np.zeros(2000, bool)
    contact[1000:1100] = True
    rest = np.ones(2000, bool)
    rest[900:1200] = False
    return {"margin": s, "contact": contact, "rest": rest, "rate_hz": 1000.0}


def test_a_step_is_found_where_the_sum_reaches_the_threshold():
    rec = _recording(3.0)
    # S over the press: 3, 6, 9 with k 0: h 7.5 is reached on its third sample, 2 ms late.
    assert onsets_ms([rec], "margin", 0.0, -np.inf, np.inf, 7.5).tolist() == [2.0]
    # Clipped at 2, S grows by 2 a sample: the fourth sample, 3 ms.
    assert onsets_ms([rec], "margin", 0.0, -np.inf, 2.0, 7.5).tolist() == [3.0]
    # A press below the drift is never found.
    assert onsets_ms([_recording(0.5)], "margin", 1.0, -np.inf, np.inf, 7.5).tolist() == [np.inf]


def test_an_alarm_just_before_the_press_restarts_the_sum_and_rest_spikes_count():
    # A spike 1 sample before the press would carry S = 10 into it; the alarm it raises is a
    # false event, and S starts again from the press.
    rec = _recording(3.0, spikes=(999, 300))
    assert onsets_ms([rec], "margin", 0.0, -np.inf, np.inf, 7.5).tolist() == [2.0]
    peaks, minutes = rest_peaks([rec], "margin", 0.0, -np.inf, np.inf)
    assert peaks.tolist() == [10.0] and minutes == pytest.approx(1700 / 60000)


def test_the_command_reports_each_statistics_frontier(small_model_dir, small_dataset_path,
                                                        capsys):
    assert main(["--model", str(small_model_dir), "--data", str(small_dataset_path),
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["frontier"]) == {"margin", "force"}
    for row in out["frontier"].values():
        assert row["false_events_per_min"] <= out["per_min"]
        assert row["h"] > 0 and 0.0 < row["found"] <= 1.0 and row["onset_median_ms"] >= 0
    # The small model decides with the Schmitt trigger: it has no CUSUM setting of its own.
    assert out["own"] is None and out["own_drift"] is None
    assert main(["--model", str(small_model_dir), "--data", str(small_dataset_path)]) == 0
    assert "quickest CUSUM on the force" in capsys.readouterr().out
    assert main(["--model", str(small_model_dir), "--data", str(small_dataset_path),
                 "--per-min", "0"]) == 2
