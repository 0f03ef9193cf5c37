"""The light-touch breakdown (bench/bench_light_touch.py): consistent with the shared metrics."""
import json

import numpy as np
import pytest

from fbgforce.bench import bench_light_touch as blt

#: Slow (pytest -m slow): trains and scores a model for the benchmark.
pytestmark = pytest.mark.slow


def test_breakdown_adds_up_to_the_shared_metrics(small_model_dir, small_dataset_path, tmp_path, capsys):
    out = tmp_path / "lt.json"
    assert blt.main(["--model", str(small_model_dir), "--data", str(small_dataset_path),
                     "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert "share of squared error" in capsys.readouterr().out
    loc = res["location"]
    assert [r["range_N"][1] for r in loc] == [*blt.EDGES_N, None]
    shares_x = [r["share_sq_err_x"] for r in loc if r["n_samples"]]
    assert sum(shares_x) == pytest.approx(1.0)
    # The ranges partition the scored samples: their pooled RMSE is the model's test RMSE.
    from fbgforce.model import modeldir as fm
    test = fm.load(small_model_dir).metadata["metrics"]["test"]
    n = sum(r["n_samples"] for r in loc)
    pooled = np.sqrt(sum(r["rmse_x_mm"] ** 2 * r["n_samples"] for r in loc if r["n_samples"]) / n)
    assert pooled == pytest.approx(test["rmse_x_mm"], rel=1e-9)
    c = res["contact"]
    assert c["errors"] == c["missed"] + c["false"]
    assert c["samples"] == test["n_samples"]
    assert 1 - c["errors"] / c["samples"] == pytest.approx(test["contact_accuracy"], abs=1e-12)
    below = list(c["missed_below_N"].values())
    assert below == sorted(below) and below[-1] <= c["missed"]


def test_bad_model_dir_is_one_line_exit_2(tmp_path, small_dataset_path, capsys):
    assert blt.main(["--model", str(tmp_path / "nope"), "--data", str(small_dataset_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench_light_touch:")
