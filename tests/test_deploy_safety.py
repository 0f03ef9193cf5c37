"""Deployment safety: no stale export goes live, no failed write leaves debris, no silent wrong
answer from the Python API, signals end live commands cleanly (docs/cli.md, docs/python-api.md).
"""
from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import fbgforce
from fbgforce.recordings import dataset as fds
from fbgforce.model import modeldir as fm
from fbgforce.cli import main
from fbgforce.errors import InputError


def _one_line_exit_2(capsys, argv, words):
    """Exit 2 with one error line (progress lines of work done before may precede it)."""
    code = main(argv)
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if ln.startswith("fbgforce ")]
    assert code == 2, err
    assert "Traceback" not in err and len(errors) == 1 and words in errors[0], err
    return errors[0]


def _no_temp_files(directory: Path) -> None:
    from fbgforce import fileio

    left = [p for p in Path(directory).rglob(fileio.TMP_PREFIX + "*")]
    assert not left, left


@pytest.fixture
def exported_copy(small_exported_dir, tmp_path):
    d = tmp_path / "model"
    shutil.copytree(small_exported_dir, d)
    return d


@pytest.fixture(scope="module")
def other_model(small_model_dir):
    """The small model with one weight changed: another float model."""
    m = fm.load(small_model_dir)
    m.force.weights[0][0, 0] += 0.5
    return m


# ------------------------------------------------------------------------------------------
# 1. A model directory knows what it holds
# ------------------------------------------------------------------------------------------

def test_stale_export_refused_by_every_reader(exported_copy, other_model, small_dataset_path,
                                              tmp_path, capsys):
    # Another model's files copied over the float model (not through fbgforce's save).
    elsewhere = tmp_path / "elsewhere"
    fm.save(other_model, elsewhere)
    for name in (fm.MODEL_JSON, fm.WEIGHTS_NPZ):
        shutil.copy(elsewhere / name, exported_copy / name)
    data = str(small_dataset_path)
    for argv in (["verify", "--model", str(exported_copy), "--data", data],
                 ["evaluate", "--model", str(exported_copy), "--data", data, "--engine", "fixed"],
                 ["evaluate", "--model", str(exported_copy), "--data", data, "--engine", "intref"],
                 ["evaluate", "--model", str(exported_copy), "--data", data, "--engine", "cfloat"],
                 ["target-report", "--model", str(exported_copy)],
                 ["stream", "--port", "loop://", "--model", str(exported_copy), "--samples", "1"]):
        line = _one_line_exit_2(capsys, argv, "stale")
        assert "model.fbgm" in line and "fbgforce export" in line
    with pytest.raises(InputError, match="stale"):
        fbgforce.Runtime(exported_copy)


def test_a_decision_changed_after_export_is_stale(exported_copy):
    """The blob carries the decision over time, the tracker and the input range, so a
    model.json whose in-use settings were changed after export (a threshold tuned by hand)
    must not run on the blob made before."""
    import dataclasses

    model = fm.load(exported_copy)
    fbgforce.Runtime(exported_copy)
    model.in_use = dataclasses.replace(model.in_use,
                                       contact_on_margin=model.in_use.contact_on_margin + 1.0)
    doc = json.loads((exported_copy / fm.MODEL_JSON).read_text())
    doc["in_use"] = model.in_use.to_json()
    (exported_copy / fm.MODEL_JSON).write_text(json.dumps(doc))
    with pytest.raises(InputError, match="stale"):
        fbgforce.Runtime(exported_copy)


def test_blob_other_than_the_export_wrote_is_refused(exported_copy, small_dataset_path, capsys):
    from fbgforce.export.exporter import export_model

    int8 = exported_copy.parent / "int8"
    shutil.copytree(exported_copy, int8)
    export_model(int8, bits=8, onnx=False)
    shutil.copy(int8 / "model.fbgm", exported_copy / "model.fbgm")
    _one_line_exit_2(capsys, ["verify", "--model", str(exported_copy), "--data",
                              str(small_dataset_path)], "not the blob its export wrote")


def test_retraining_into_an_exported_directory_removes_the_export(exported_copy, other_model):
    (exported_copy / "c" / "notes.txt").write_text("mine")
    fm.save(other_model, exported_copy)
    for name in ("model.fbgm", "model.onnx", "export_report.json", "c/fbgforce_model.c",
                 "c/fbgforce_model_f32.h"):
        assert not (exported_copy / name).exists(), name
    assert (exported_copy / "c" / "notes.txt").read_text() == "mine"
    # Saving the same model again keeps its export.
    from fbgforce.export.exporter import export_model

    export_model(exported_copy, onnx=False)
    fm.save(fm.load(exported_copy), exported_copy)
    assert (exported_copy / "model.fbgm").is_file()


@pytest.mark.slow
def test_export_never_reopens_the_training_files(small_dataset_path, tmp_path, capsys):
    """The model directory keeps its calibration recordings: export runs after the training
    file has moved, and quantises exactly as from that file given with --calib."""
    from fbgforce.export.exporter import export_model
    from fbgforce.trainer.train import train

    data = tmp_path / "cal.csv"
    shutil.copy(small_dataset_path, data)
    model_dir = tmp_path / "model"
    fm.save(train([data], epochs=2, seed=0, progress=False, restarts=1, hold_augment=0.0,
                  idle_pads=0),
            model_dir)
    moved = data.rename(tmp_path / "moved.csv")
    assert main(["export", "--model", str(model_dir), "--json"]) == 0, capsys.readouterr().err
    kept = (model_dir / "model.fbgm").read_bytes()
    export_model(model_dir, calib=[moved], onnx=False)
    assert (model_dir / "model.fbgm").read_bytes() == kept
    # A model of other training data saved over it takes its recordings' file with it.
    other = fm.load(model_dir)
    other.metadata["data"] = [{"path": None, "source": "elsewhere", "samples": 1}]
    fm.save(other, model_dir)
    assert not (model_dir / fm.CALIBRATION_NPZ).exists()
    _one_line_exit_2(capsys, ["export", "--model", str(model_dir)], "no calibration data")


def test_verify_exits_1_on_mismatch(exported_copy, small_dataset_path, monkeypatch, capsys):
    from fbgforce.export import intref

    real = intref.run

    def off_by_one(*args, **kwargs):
        out = real(*args, **kwargs)
        out["force_mN"] = out["force_mN"] + 1
        return out

    monkeypatch.setattr(intref, "run", off_by_one)
    with pytest.raises(SystemExit) as stop:
        main(["verify", "--model", str(exported_copy), "--data", str(small_dataset_path),
              "--json"])
    captured = capsys.readouterr()
    assert stop.value.code == 1
    assert json.loads(captured.out)["mismatches"] > 0


# ------------------------------------------------------------------------------------------
# 2. Atomic writes, locations checked first
# ------------------------------------------------------------------------------------------

def _full_disk(monkeypatch):
    """Every write fails as on a full disk: when it is flushed to the device (where a real
    ENOSPC shows up with delayed allocation), or, for a file opened by name, after the open
    has created or emptied it."""
    import builtins

    def fsync(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    real_open = builtins.open

    def open_full(file, mode="r", *args, **kwargs):
        if any(c in mode for c in "wax+") and not isinstance(file, int):
            real_open(file, mode).close()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(file))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(builtins, "open", open_full)


@pytest.mark.slow
def test_full_disk_keeps_the_previous_files(exported_copy, small_dataset_path, tmp_path,
                                            monkeypatch, capsys):
    out = tmp_path / "sim.csv"
    out.write_text("previous")
    before = {p: p.read_bytes() for p in exported_copy.rglob("*") if p.is_file()}
    _full_disk(monkeypatch)
    _one_line_exit_2(capsys, ["simulate", "--scene", "smoke", "--out", str(out)], "no space left")
    assert out.read_text() == "previous"
    _one_line_exit_2(capsys, ["export", "--model", str(exported_copy), "--calib",
                              str(small_dataset_path)], "no space left")
    with pytest.raises(InputError, match="no space left"):
        fm.save(fm.load(exported_copy), exported_copy / "again")
    after = {p: p.read_bytes() for p in exported_copy.rglob("*") if p.is_file()}
    assert after == before
    assert not (exported_copy / "again" / fm.MODEL_JSON).exists()
    _no_temp_files(tmp_path)


class _Killed(BaseException):
    """The process stopped at a step of a commit: nothing after it runs, nothing cleans up."""


def _two_models(model_dir):
    """The model of ``model_dir`` and another one differing in ``weights.npz`` and in
    ``model.json``, so that a directory holding one file of each loads as neither."""
    old = fm.load(model_dir)
    new = fm.load(model_dir)
    new.force.weights[0][0, 0] += 0.5
    new.force_scale *= 1.01
    return old, new


def _what_a_loader_sees(directory, old, new) -> str:
    """``old`` or ``new`` (the complete model), ``refused`` (one line naming a file), or
    ``mixed`` (it loads, as neither)."""
    from fbgforce.model import freshness

    try:
        loaded = fm.load(directory)
    except InputError as exc:
        assert "\n" not in str(exc) and str(directory) in str(exc)
        return "refused"
    digest = freshness.model_digest(loaded)
    return {freshness.model_digest(old): "old", freshness.model_digest(new): "new"}.get(
        digest, "mixed")


def test_a_crash_at_every_step_of_a_commit_never_mixes_two_models(small_model_dir, tmp_path,
                                                                  monkeypatch):
    """A model saved over another, stopped before each file operation of the commit in turn
    (every ``os.unlink`` and ``os.replace``, the renames included): a loader finds the old
    model, the new one, or a refusal naming a missing file; never one file of each (renamed
    one at a time, weights.npz first, an old model.json beside new weights loaded as a model
    nobody trained)."""
    old, new = _two_models(small_model_dir)
    seen = []
    for k in range(40):
        directory = tmp_path / f"m{k}"
        shutil.copytree(small_model_dir, directory)
        steps: list[tuple[str, str]] = []
        with monkeypatch.context() as m:
            for name in ("unlink", "replace"):
                def step(path, *args, _real=getattr(os, name), _name=name, **kwargs):
                    if len(steps) == k:
                        raise _Killed
                    steps.append((_name, Path(path).name))
                    return _real(path, *args, **kwargs)
                m.setattr(os, name, step)
            try:
                fm.save(new, directory)
                finished = True
            except _Killed:
                finished = False
        seen.append(_what_a_loader_sees(directory, old, new))
        assert seen[-1] != "mixed", (k, steps)
        if finished:
            break
    assert finished and seen[0] == "old" and seen[-1] == "new" and "refused" in seen, seen
    assert [s for s in seen if s != "refused"] == ["old", "new"], seen


_KILL_AT_STEP = """
import os, signal, sys
from fbgforce.model import modeldir as fm

model = fm.load(sys.argv[1])
k, steps = int(sys.argv[3]), [0]
for name in ("unlink", "replace"):
    def step(path, *args, _real=getattr(os, name), **kwargs):
        if steps[0] == k:
            os.kill(os.getpid(), signal.SIGKILL)
        steps[0] += 1
        return _real(path, *args, **kwargs)
    setattr(os, name, step)
fm.save(model, sys.argv[2])
"""


@pytest.mark.slow
def test_a_kill_at_every_step_of_a_commit_never_mixes_two_models(small_model_dir, tmp_path):
    """``kill -9`` of a process saving a model over another, at each file operation of the
    commit in turn (a hook on ``os.unlink`` and ``os.replace`` sends the SIGKILL: the
    renames themselves are hit, where kills from outside during training landed before any
    file was replaced): what it leaves loads as the old model, the new one, or is refused."""
    old, new = _two_models(small_model_dir)
    fm.save(new, tmp_path / "new")
    seen = []
    for k in range(40):
        directory = tmp_path / f"m{k}"
        shutil.copytree(small_model_dir, directory)
        proc = subprocess.run([sys.executable, "-c", _KILL_AT_STEP, str(tmp_path / "new"),
                               str(directory), str(k)], capture_output=True, text=True,
                              timeout=120)
        assert proc.returncode in (0, -signal.SIGKILL), proc.stderr
        seen.append(_what_a_loader_sees(directory, old, new))
        assert seen[-1] != "mixed", (k, seen)
        if proc.returncode == 0:
            break
    assert seen[0] == "old" and seen[-1] == "new" and "refused" in seen, seen
    assert [s for s in seen if s != "refused"] == ["old", "new"], seen


def test_bad_output_location_fails_before_the_work(small_dataset_path, tmp_path, capsys,
                                                   monkeypatch):
    from fbgforce.trainer import report as rp
    from fbgforce.trainer import train as tr

    def no_training(*args, **kwargs):
        raise AssertionError("trained although the output location is impossible")

    # The report binds train when first imported: imported above, before the patch, and
    # patched where it looks, so no later test inherits the stand-in.
    monkeypatch.setattr(tr, "train", no_training)
    monkeypatch.setattr(rp, "train", no_training)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    data = str(small_dataset_path)
    _one_line_exit_2(capsys, ["train", "--data", data, "--out", str(blocker / "model")],
                     "is a file, not a directory")
    _one_line_exit_2(capsys, ["report", "--data", data, "--out", str(blocker / "report")],
                     "is a file, not a directory")
    _one_line_exit_2(capsys, ["train", "--data", str(tmp_path), "--out", str(tmp_path / "m")],
                     "is a directory, not a file")


# ------------------------------------------------------------------------------------------
# 3. The Python API validates like the CLI
# ------------------------------------------------------------------------------------------

def test_predict_refuses_pm_and_wrong_shape(small_model_dir, small_dataset_path):
    model = fm.load(small_model_dir)
    wl = fds.load(small_dataset_path).wl_nm[:200]
    with pytest.raises(InputError, match="pm"):
        fbgforce.predict(model, wl * 1000.0)
    with pytest.raises(InputError, match=r"\(n, 5\)"):
        fbgforce.predict(model, wl[:, :4])
    with pytest.raises(InputError, match="complex"):
        fbgforce.predict(model, wl.astype(complex))


def test_nan_sample_is_a_sensor_fault_in_every_engine(small_exported_dir, small_dataset_path):
    from fbgforce.evaluation import engines
    from fbgforce.export.exporter import recording_baseline

    ds = fds.load(small_dataset_path)
    rows = np.flatnonzero(ds.contact)[:1]
    start = max(0, int(rows[0]) - 300)
    wl = ds.wl_nm[start:start + 600].copy()
    k = int(rows[0]) - start + 50            # a sample in contact
    wl[k, 2] = np.nan
    base = recording_baseline(ds)
    model = fm.load(small_exported_dir)
    fault = fbgforce.contract.STATUS_FLAG["SENSOR_FAULT"]
    for name in ("float", "onnx", "fixed", "intref", "cfloat"):
        out = engines.run_engine(name, small_exported_dir, model, wl, base)
        assert int(out["status"][k]) & fault, name
        assert not out["contact"][k] and out["force_N"][k] == 0.0, name
        assert not (np.asarray(out["status"])[k + 1:k + 20] & fault).any(), name
    pred = fbgforce.predict(model, wl, base)
    assert pred["status"][k] & fault and np.isnan(pred["x_mm"][k])


def test_float_fault_handling_matches_the_c_rule(small_exported_dir, small_dataset_path):
    """Lost peaks in the float engine follow the fixed-point runtime: same flags, and after
    the fault the same contact decisions (the filter held, the memory frozen)."""
    from fbgforce.evaluation import engines
    from fbgforce.export.exporter import recording_baseline

    ds = fds.load(small_dataset_path)
    wl = ds.wl_nm[:4000].copy()
    wl[1000:1010, 1] = np.nan
    wl[2500, 4] = 900.0
    base = recording_baseline(ds)
    model = fm.load(small_exported_dir)
    flt = engines.run_engine("float", small_exported_dir, model, wl, base)
    fix = engines.run_engine("fixed", small_exported_dir, model, wl, base)
    fault = fbgforce.contract.STATUS_FLAG["SENSOR_FAULT"]
    assert np.array_equal(flt["status"] & fault != 0, fix["status"] & fault != 0)
    assert (flt["contact"] == fix["contact"]).mean() > 0.99


def test_runtime_refuses_what_is_not_a_real_number_array(small_exported_dir):
    rt = fbgforce.Runtime(small_exported_dir)
    good = np.full((3, 5), 1550.0)
    for bad, words in ((good.astype(complex), "complex"), (good.astype(str), "text"),
                       (np.ones((3, 5), bool), "booleans"), ([[1550.0] * 5, [1550.0] * 4], "rectangular"),
                       (np.full((3, 4), 1550.0), "(n, 5)"), ("1550", "text")):
        with pytest.raises(InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
            rt.run(bad)
    with pytest.raises(InputError):
        rt.step(good.astype(complex)[0])
    with pytest.raises(InputError, match="model directory"):
        fbgforce.Runtime(123)


def test_sample_rate_must_agree(small_model_dir, small_dataset_path, tmp_path, capsys):
    half = fds.load(small_dataset_path).subset(slice(0, None, 2))
    path = tmp_path / "500hz.csv"
    fds.save(half, path)
    line = _one_line_exit_2(capsys, ["evaluate", "--model", str(small_model_dir), "--data",
                                     str(path)], "500 Hz")
    assert "1000 Hz" in line and "--resample" in line
    assert main(["evaluate", "--model", str(small_model_dir), "--data", str(path), "--resample",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n_samples"] >= 2 * len(half) - 2
    model = fm.load(small_model_dir)
    with pytest.raises(InputError, match="500 Hz"):
        fbgforce.predict(model, half.wl_nm, rate_hz=500.0)


def test_too_few_test_presses_is_a_warning(small_model_dir, small_dataset_path, tmp_path, capsys):
    ds = fds.load(small_dataset_path)
    few = ds.subset(np.isin(ds.press_id, np.unique(ds.press_id)[:3]))
    path = tmp_path / "three.csv"
    fds.save(few, path)
    assert main(["evaluate", "--model", str(small_model_dir), "--data", str(path), "--split",
                 "test", "--json"]) == 0
    captured = capsys.readouterr()
    res = json.loads(captured.out)
    assert res["presses"] < 5 and any("test split holds" in w for w in res["warnings"])
    assert "warning" in captured.err


# ------------------------------------------------------------------------------------------
# 4. Signals end live commands cleanly
# ------------------------------------------------------------------------------------------

def _cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "fbgforce.cli", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs POSIX pseudo-terminals")
@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_ends_stream_and_emulate_cleanly(small_exported_dir, tmp_path, sig, status):
    link = tmp_path / "ttyFBG"
    emu = _cli("emulate", "--scene", "smoke", "--rate", "2000", "--loop", "--link", str(link),
               "--json")
    try:
        deadline = time.monotonic() + 60
        while not link.exists():
            assert emu.poll() is None and time.monotonic() < deadline, emu.communicate()[1]
            time.sleep(0.05)
        out = tmp_path / "est.csv"
        stream = _cli("stream", "--port", str(link), "--model", str(small_exported_dir),
                      "--out", str(out), "--tare-samples", "50", "--json", "--quiet")
        time.sleep(4.0)
        stream.send_signal(sig)
        s_out, s_err = stream.communicate(timeout=30)
        assert stream.returncode == status, s_err[-2000:]
        summary = json.loads(s_out)
        assert summary["interrupted"] and summary["signal"] == sig.name
        assert summary["samples"] > 100
        rows = fds_rows(out)
        assert rows == summary["samples"]
        emu.send_signal(sig)
        e_out, e_err = emu.communicate(timeout=30)
        assert emu.returncode == status, e_err[-2000:]
        played = json.loads(e_out)
        assert played["interrupted"] and played["samples_played"] >= summary["received"]
    finally:
        if emu.poll() is None:
            emu.kill()
            emu.communicate()


def fds_rows(path: Path) -> int:
    from fbgforce.interrogator.stream import load_estimates

    return int(load_estimates(path)["seq"].size)


# ------------------------------------------------------------------------------------------
# 5. Rough edges
# ------------------------------------------------------------------------------------------

def test_json_errors_are_json(tmp_path, capsys):
    for argv in (["evaluate", "--model", str(tmp_path / "none"), "--data", str(tmp_path / "x.csv"),
                  "--json"],
                 ["simulate", "--scene", "smoke", "--out", str(tmp_path / "x.txt"), "--json"],
                 ["train", "--json"]):
        code = main(argv)
        captured = capsys.readouterr()
        doc = json.loads(captured.out)
        assert code == 2 and doc["code"] == 2 and doc["error"] in captured.err


def test_csv_quoted_header_and_delimiter_message(small_dataset_path, tmp_path):
    lines = Path(small_dataset_path).read_text().splitlines()[:300]
    header = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    quoted = list(lines)
    quoted[header] = ",".join(f'"{name}"' for name in lines[header].split(","))
    (tmp_path / "quoted.csv").write_text("\n".join(quoted) + "\n")
    assert len(fds.load(tmp_path / "quoted.csv")) == 300 - header - 1
    semi = [ln if ln.startswith("#") else ln.replace(",", ";") for ln in lines]
    (tmp_path / "semi.csv").write_text("\n".join(semi) + "\n")
    with pytest.raises(InputError, match="semicolons"):
        fds.load(tmp_path / "semi.csv")


def test_stream_with_too_few_channels_and_tcp_hint(small_exported_dir, capsys):
    _one_line_exit_2(capsys, ["stream", "--port", "loop://", "--model", str(small_exported_dir),
                              "--channels", "4"], "--channels")
    line = _one_line_exit_2(capsys, ["stream", "--port", "socket://127.0.0.1:9", "--model",
                                     str(small_exported_dir), "--start-timeout", "1"], "no sample")
    assert "dialout" not in line and "host and port" in line


def test_progress_shows_as_lines_off_a_terminal(monkeypatch):
    import io

    from fbgforce import progress

    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    bar = progress.bar(total=3, desc="work")
    for _ in range(3):
        bar.update(1)
    bar.close()
    text = err.getvalue()
    assert "work" in text and "\r" not in text


def test_demo_figures_start_at_zero_and_draw_no_table(tmp_path, monkeypatch):
    from fbgforce.evaluation import figures
    from fbgforce.trainer.report import PAPER

    seen = {}

    def keep(fig, path, title):
        seen[Path(path).name] = fig
        return {"path": str(path), "title": title}

    monkeypatch.setattr(figures, "_save", keep)
    points = [{"engine": "float", "us_per_sample": 3.0, "rmse_force_N": 0.36868},
              {"engine": "fixed", "us_per_sample": 0.3, "rmse_force_N": 0.36884}]
    figures.accuracy_vs_time(points, tmp_path / "a.png")
    ax = seen["a.png"].axes[0]
    assert ax.get_ylim()[0] == 0.0
    assert any("+0.16 mN" in t.get_text() for t in ax.texts)
    ours = {"contact_accuracy": 0.98, "rmse_force_N": 0.4, "rmse_x_mm": 0.5, "rmse_y_mm": 0.6}
    figures.paper_vs_ours(PAPER["network"], ours, tmp_path / "p.png", "ours")
    for ax in seen["p.png"].axes:
        assert not ax.tables and ax.containers and ax.get_ylim()[0] == 0.0


def test_every_report_check_is_explained():
    from fbgforce.trainer import report

    on = {"contact_accuracy": 0.9, "rmse_force_N": 0.5}
    off = {"contact_accuracy": 0.95, "rmse_force_N": 0.4}
    common = {"n_samples": 10, "causal": {"rmse_x_mm": 0.3, "rmse_y_mm": 0.3},
              "none": {"rmse_x_mm": 0.4, "rmse_y_mm": 0.2}}
    worse = report._not_better(on, off, common, "causal", "none", strict=False)
    assert [w.split()[0] for w in worse] == ["contact_accuracy", "rmse_force_N", "rmse_y_mm"]
    rep = {"checks": {"smoothing_improves_every_metric": False},
           "check_notes": {"smoothing_improves_every_metric": "why"}}
    assert report.check_lines(rep) == ["- smoothing_improves_every_metric: False (why)"]
    assert set(report.CHECK_MEANING) >= {"smoothing_improves_every_metric",
                                         "network_beats_fitted_on_every_metric"}
