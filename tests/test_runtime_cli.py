"""``fbgforce export`` / ``verify`` from the command line, and ``evaluate --engine fixed``."""
from __future__ import annotations

import pytest

import json
import shutil

from fbgforce.cli import main

VERIFY_KEYS = {"samples", "mismatches", "contact_disagreements", "max_abs_err_force_N",
               "max_abs_err_x_mm", "max_abs_err_y_mm"}


def _json(capsys, argv):
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
def test_export_and_verify_cli(small_model_dir, small_dataset_path, tmp_path, capsys):
    mdir = tmp_path / "model"
    shutil.copytree(small_model_dir, mdir)
    rep = _json(capsys, ["export", "--model", str(mdir), "--calib", str(small_dataset_path), "--json"])
    for name in ("model.onnx", "model.fbgm", "export_report.json", "c/fbgforce_model.c",
                 "c/fbgforce_model.h", "c/fbgforce_model_f32.c", "c/fbgforce_model_f32.h"):
        assert (mdir / name).is_file(), name
    assert rep["bits"] == 16 and rep["blob_bytes"] == (mdir / "model.fbgm").stat().st_size
    for infos in rep["nets"].values():
        for info in infos:
            assert info["calib_max_abs_acc"] <= info["acc_bound"]
            assert info["product_bound_log2"] < 63
    res = _json(capsys, ["verify", "--model", str(mdir), "--data", str(small_dataset_path), "--json"])
    assert VERIFY_KEYS <= set(res)
    assert res["samples"] > 10_000 and res["mismatches"] == 0
    assert res["max_abs_err_force_N"] < 0.05 and res["max_abs_err_x_mm"] < 0.05

    # int8 weights: still bit-exact, larger but bounded error.
    rep8 = _json(capsys, ["export", "--model", str(mdir), "--bits", "8", "--no-onnx", "--json"])
    assert rep8["bits"] == 8 and rep8["blob_bytes"] < rep["blob_bytes"]
    res8 = _json(capsys, ["verify", "--model", str(mdir), "--data", str(small_dataset_path), "--json"])
    assert res8["mismatches"] == 0

    # Retrained after export: saving the new model removes the export it no longer matches.
    from fbgforce.model import modeldir as fm

    m = fm.load(mdir)
    m.force_scale *= 1.01
    fm.save(m, mdir)
    assert not (mdir / "model.fbgm").exists() and not (mdir / "export_report.json").exists()
    assert main(["evaluate", "--model", str(mdir), "--data", str(small_dataset_path),
                 "--engine", "fixed"]) == 2
    assert "fbgforce export" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_bad_inputs_exit_2(small_model_dir, small_dataset_path, tmp_path, capsys):
    mdir = tmp_path / "model"
    shutil.copytree(small_model_dir, mdir)
    # Not exported yet.
    assert main(["verify", "--model", str(mdir), "--data", str(small_dataset_path)]) == 2
    assert "fbgforce export" in capsys.readouterr().err
    # Training files gone and no --calib: a clear error.
    doc = json.loads((mdir / "model.json").read_text())
    doc["metadata"]["data"] = [{"path": str(tmp_path / "missing.csv")}]
    (mdir / "model.json").write_text(json.dumps(doc))
    assert main(["export", "--model", str(mdir)]) == 2
    assert "--calib" in capsys.readouterr().err
    # A corrupt blob is refused with the reason.
    assert main(["export", "--model", str(mdir), "--calib", str(small_dataset_path), "--no-onnx"]) == 0
    data = bytearray((mdir / "model.fbgm").read_bytes())
    data[-3] ^= 0xFF
    (mdir / "model.fbgm").write_bytes(bytes(data))
    capsys.readouterr()
    assert main(["verify", "--model", str(mdir), "--data", str(small_dataset_path)]) == 2
    assert "CRC" in capsys.readouterr().err


def test_evaluate_fixed_within_2_percent_of_float(small_exported_dir, small_dataset_path):
    from fbgforce.trainer.evaluate import evaluate

    flt = evaluate(small_exported_dir, [small_dataset_path], engine="float", extras=False)
    fix = evaluate(small_exported_dir, [small_dataset_path], engine="fixed", extras=False)
    for key in ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm"):
        assert abs(fix[key] - flt[key]) <= 0.02 * abs(flt[key]), (key, fix[key], flt[key])
    assert fix["n_samples"] == flt["n_samples"]
    cf = evaluate(small_exported_dir, [small_dataset_path], engine="cfloat", extras=False)
    ir = evaluate(small_exported_dir, [small_dataset_path], engine="intref", extras=False)
    assert ir["rmse_force_N"] == fix["rmse_force_N"]
    assert abs(cf["rmse_force_N"] - flt["rmse_force_N"]) < 1e-3
