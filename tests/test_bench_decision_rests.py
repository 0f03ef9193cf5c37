"""The decision's rests beside a pad's real long rests (bench/bench_decision_rests.py), and what
``model.json`` records of the rests the CUSUM's threshold was read on."""
import json

import numpy as np
import pytest

from fbgforce.bench import bench_decision_rests as bdr
from fbgforce import sim
from fbgforce.model import modeldir as fm
from fbgforce.model.floatref import predict
from fbgforce.recordings import dataset
from fbgforce.recordings import tare as ftare


def test_long_rests_are_read_from_the_settling_to_before_the_next_press():
    rate = 1000.0
    contact = np.zeros(20_000, dtype=bool)
    contact[3000:3200] = True      # the start's rest (3 s) is no rest after a press
    contact[4200:4400] = True      # 1 s after the first press: too short
    contact[9400:9600] = True      # 5 s after the second: read
    margin = np.arange(contact.size, dtype=np.float64)
    got = bdr.long_rest_margins(margin, contact, rate, min_rest_s=3.0)
    settle, gap = 500, 50
    want = np.concatenate([margin[4400 + settle:9400 - gap], margin[9600 + settle:]])
    np.testing.assert_array_equal(got, want)
    assert bdr.long_rest_margins(margin, contact, rate, min_rest_s=11.0).size == 0


@pytest.fixture(scope="module")
def rests_path(tmp_path_factory):
    """The small model's device in the ``smoke`` scene (other presses), with 4 s of rest after
    its last press."""
    path = tmp_path_factory.mktemp("rests") / "rests.csv"
    scene = sim.load_scene("smoke").replace(seed=5, schedule={"n_presses": 6, "tail_s": 4.0})
    dataset.save(sim.simulate(scene), path)
    return path


def test_the_model_records_its_decisions_rests_and_the_bench_reads_a_recording(
        small_model_dir, rests_path, capsys):
    rested = fm.load(small_model_dir).metadata["decision_rests"]
    for kind in ("calibration", "long"):
        q = rested[kind]["margin_quantiles"]
        assert list(q) == ["99.9", "99.99"] and rested[kind]["minutes"] > 0
        assert q["99.9"] <= q["99.99"]
    out = bdr.measure(small_model_dir, [rests_path])
    ds = dataset.load(rests_path)
    base, _ = ftare.tare(ds.wl_nm, ds.contact, ds.t_s)
    margin = predict(fm.load(small_model_dir), ds.wl_nm, base)["margin"]
    read = bdr.long_rest_margins(np.asarray(margin), np.asarray(ds.contact), 1000.0, 3.0)
    assert 3400 <= read.size <= 3600     # the 4 s tail from 0.5 s after the last release
    assert out["recorded"]["margin_quantiles"]["99.99"] == pytest.approx(
        np.quantile(read, 0.9999), abs=1e-12)
    assert out["recorded"]["minutes"] == pytest.approx(read.size / 60_000.0)
    assert bdr.main(["--model", str(small_model_dir), "--data", str(rests_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["long"] == rested["long"]
    assert bdr.main(["--model", str(small_model_dir), "--data", str(rests_path)]) == 0
    text = capsys.readouterr().out
    assert "synthetic long rests" in text and "99.99 %" in text


@pytest.mark.parametrize("case", ["no_record", "no_long_rest", "bad_min", "no_file"])
def test_what_it_cannot_read_is_one_line_exit_2(case, small_model_dir, rests_path, tmp_path,
                                                 capsys):
    model_dir, args = small_model_dir, ["--data", str(rests_path)]
    if case == "no_record":
        model = fm.load(small_model_dir)
        del model.metadata["decision_rests"]
        model_dir = tmp_path / "model"
        fm.save(model, model_dir)
    elif case == "no_long_rest":
        args += ["--min-rest-s", "600"]
    elif case == "bad_min":
        args += ["--min-rest-s", "0.5"]
    else:
        args = ["--data", str(tmp_path / "missing.csv")]
    assert bdr.main(["--model", str(model_dir), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench_decision_rests:"), err
