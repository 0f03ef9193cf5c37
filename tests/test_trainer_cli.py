"""CLI round trip of the trainer on the small simulated scene: train -> evaluate, analyze."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fbgforce.model import modeldir as fm
from fbgforce.cli import main


def _run_json(capsys, argv):
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
def test_train_evaluate_round_trip(capsys, tmp_path, small_dataset_path):
    out = tmp_path / "model"
    assert main(["train", "--data", str(small_dataset_path), "--out", str(out), "--epochs", "15",
                 "--seed", "3", "--filter", "causal", "--sigma", "4", "--json"]) == 0
    printed = capsys.readouterr()
    res = json.loads(printed.out)
    model = fm.load(out)
    assert model.preprocess.filter_kind == "causal" and model.preprocess.filter_sigma == 4
    assert res["filter"]["group_delay_ms"] > 0 and res["test"]["n_samples"] > 0
    assert model.metadata["seed"] == 3 and len(model.metadata["data"][0]["sha256"]) == 64
    # The temperature reference's choice: in the JSON, the metadata, the model and the summary
    # line (the scene's gratings have independent noise: the average halves it).
    ref = res["temperature_reference"]
    assert ref == model.metadata["temperature"]["reference"]
    assert ref["ref_shift"] == model.preprocess.ref_shift == ref["candidate"] == 5
    assert ref["rest_noise_pm2"]["averaged"] < 0.6 * ref["rest_noise_pm2"]["raw"]
    assert "temperature reference averaged over 2^5 samples" in printed.err
    assert "from 40 idle pads of 2 minutes each" in printed.err
    ev = _run_json(capsys, ["evaluate", "--model", str(out), "--data", str(small_dataset_path),
                            "--split", "test", "--json"])
    for key in ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm", "n_samples"):
        assert ev[key] == pytest.approx(res["test"][key], rel=1e-9)
    # Learned something real even after a few epochs on a tiny scene.
    assert ev["contact_accuracy"] > 0.9 and ev["rmse_force_N"] < 8.0
    all_ = _run_json(capsys, ["evaluate", "--model", str(out), "--data", str(small_dataset_path),
                              "--json"])
    assert all_["n_samples"] > ev["n_samples"]


def test_cli_input_errors(capsys, tmp_path, small_dataset_path, small_model_dir):
    assert main(["train", "--data", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "m")]) == 2
    assert "missing.csv" in capsys.readouterr().err
    assert main(["evaluate", "--model", str(tmp_path), "--data", str(small_dataset_path)]) == 2
    assert "model" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    lines = small_dataset_path.read_text().splitlines()
    data_lines = [i for i, line in enumerate(lines) if line and not line.startswith("#")]
    row = data_lines[5]  # a data line after the header
    lines[row] = "not-a-number," + lines[row].split(",", 1)[1]
    bad.write_text("\n".join(lines) + "\n")
    assert main(["evaluate", "--model", str(small_model_dir), "--data", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "line" in err


def test_small_model_fixture_is_causal_and_accurate(small_model_dir, small_dataset_path):
    from fbgforce.trainer.evaluate import evaluate

    model = fm.load(small_model_dir)
    assert model.preprocess.filter_kind == "causal"
    ev = evaluate(small_model_dir, [small_dataset_path], split="test")
    assert ev["contact_accuracy"] > 0.9
    assert ev["rmse_force_N"] < 5.0


def test_analyze_needs_three_features(capsys, tmp_path, small_dataset_path):
    res = _run_json(capsys, ["analyze", "--data", str(small_dataset_path), "--epochs", "10",
                             "--plot", str(tmp_path / "ae.png"), "--json"])
    assert res["ks"] == [1, 2, 3]
    # Three features reconstruct the four channels far better than two (rigid-pad statics).
    assert res["rmse_pca"][2] < 0.3 * res["rmse_pca"][1]
    assert res["rmse"][2] < 0.5 * res["rmse"][1]
    if res.get("plot"):
        assert (tmp_path / "ae.png").stat().st_size > 1000


@pytest.mark.slow
def test_report_runs_end_to_end(capsys, tmp_path, small_dataset_path, small_model_dir):
    res = _run_json(capsys, ["report", "--data", str(small_dataset_path), "--model",
                             str(small_model_dir), "--epochs", "3", "--out", str(tmp_path / "r"),
                             "--json"])
    md = (tmp_path / "r" / "report.md").read_text()
    assert "| rmse_y_mm |" in md and "paper model" in md
    assert json.loads((tmp_path / "r" / "report.json").read_text())["test_samples"] == res["test_samples"]
    nominal = res["model_based"]["nominal"]["metrics"]
    fitted = res["model_based"]["fitted"]["metrics"]
    # The fitted beam model knows this device; the nominal one only the drawing.
    assert fitted["rmse_force_N"] < nominal["rmse_force_N"]
    assert set(res["network"]) == {"causal", "centred", "none"}
    assert res["network"]["causal"]["metrics"]["n_samples"] == res["test_samples"]
    assert isinstance(res["checks"]["network_beats_nominal_3x_force"], bool)
    # Location like for like: both scored on the same true contacts that both detect.
    common = res["model_based"]["fitted"]["common_with_network"]
    assert 0 < common["n_samples"] < res["test_samples"]
    for who in ("network", "fitted"):
        assert common[who]["rmse_x_mm"] > 0 and common[who]["rmse_y_mm"] > 0
    assert isinstance(res["checks"]["network_beats_fitted_on_every_metric"], bool)
    assert "both the causal network and the fitted baseline call contact" in md
    sc = res["smoothing_common_location"]
    assert 0 < sc["n_samples"] < res["test_samples"] and sc["none"]["rmse_x_mm"] > 0
    assert "both the causal and the unfiltered network call contact" in md
