"""Serial I/O on real pseudo-terminals: virtual interrogator -> reader / stream / record.

The long test is the 10-second 1 kHz stream; the rest play at a few kHz so the
whole file stays around half a minute.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fbgforce import sim
from fbgforce.recordings import dataset
from fbgforce.cli import main
from fbgforce.interrogator import emulator as E
from fbgforce.interrogator import protocol as P
from fbgforce.interrogator import reader as R

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs POSIX pseudo-terminals")


@pytest.fixture(scope="module")
def dropout_recording():
    """The `dropout` scene (calibration effects + flagged lost/garbled samples), 5000 samples."""
    ds = sim.simulate("dropout", seed=0)
    return ds.subset(np.arange(5000))


@pytest.fixture
def emulate_process(tmp_path):
    """Starter of ``fbgforce emulate`` subprocesses; any still running at teardown (a test
    failed before its client connected) is killed."""
    procs: list[subprocess.Popen] = []

    def start(*args: str) -> tuple[subprocess.Popen, Path]:
        proc, link = _emulate_process(tmp_path, *args)
        procs.append(proc)
        return proc, link

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _emulate_process(tmp_path: Path, *args: str) -> tuple[subprocess.Popen, Path]:
    """Start ``fbgforce emulate`` in a subprocess with a symlink; wait until it exists."""
    link = tmp_path / "ttyFBG"
    proc = subprocess.Popen([sys.executable, "-m", "fbgforce.cli", "emulate", "--link", str(link),
                             *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not link.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"emulator did not start: {proc.communicate()[1][-2000:]}")
        time.sleep(0.02)
    return proc, link


def _finish(proc: subprocess.Popen) -> str:
    try:
        out, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    assert proc.returncode == 0, err[-2000:]
    return out


def test_corrupted_line_every_good_frame_delivered_every_bad_one_counted(dropout_recording):
    pb = E.Playback.from_dataset(dropout_recording)
    assert pb.dropout is not None and np.count_nonzero(pb.dropout) > 0
    plan = E.plan_faults(len(pb), dropout=pb.dropout, seed=3,
                         rates={"flip": 0.01, "truncate": 0.01, "garbage": 0.01, "drop": 0.01})
    # The scene's dropout column became real line faults: lost -> drop, garbled -> flip.
    assert np.all(plan[pb.dropout == 1] == E.FAULT_CODE["drop"])
    assert np.all(plan[pb.dropout == 2] == E.FAULT_CODE["flip"])
    for kind in E.FAULTS[1:]:
        assert np.count_nonzero(plan == E.FAULT_CODE[kind]) >= 20, kind
    em = E.Emulator(pb, rate=5000, faults=plan, seed=3, linger=1.0).start()
    rd = R.NativeReader(em.port.path)
    got = []
    try:
        for batch in R.iter_batches(rd, idle_timeout=0.5, start_timeout=10):
            got += batch
    finally:
        rd.close()
        em.stop()
    good = np.flatnonzero((plan == E.FAULT_CODE["none"]) | (plan == E.FAULT_CODE["garbage"]))
    assert [f.seq for f in got] == good.tolist()
    assert all(f.wl_fm == tuple(pb.wl_fm[f.seq]) for f in got)
    assert all(f.t_us == pb.t_us[f.seq] for f in got)
    s = rd.stats()
    bad_before_last = np.count_nonzero(plan[:good[-1]] != 0) - np.count_nonzero(
        plan[:good[-1]] == E.FAULT_CODE["garbage"])
    assert s["lost_frames"] == bad_before_last
    assert s["crc_errors"] + s["header_errors"] > 0 and s["resyncs"] > 0
    assert em.stats.overrun_bytes == 0
    # Every byte on the line is in a delivered frame or counted as discarded.
    assert s["frames"] * P.frame_size(5) == s["delivered_bytes"]
    assert s["delivered_bytes"] + s["discarded_bytes"] + rd.decoder.pending == s["bytes"]
    assert s["bytes"] == em.stats.bytes_sent


def test_fispec_polls_give_8n_plus_12_byte_frames_with_the_scene_wavelengths(dropout_recording):
    ds = dropout_recording.subset(np.arange(3000))
    ds.extra.pop("dropout")  # clean line: this test is about the frame format
    pb = E.Playback.from_dataset(ds)
    em = E.Emulator(pb, protocol="fispec", rate=1000, linger=0.5).start()
    rd = R.FiSpecReader(em.port.path, channels=None)
    try:
        ident = rd.identify()
        assert ident is not None and ident.startswith("FiSpec")
        rd.link.write(b"KA,5>XYZ>LED,1>")  # device set-up / unknown commands: ignored
        assert rd.poll() is not None and rd.channels == 5
        raw = rd.last_reply
        assert raw is not None and len(raw) == 8 * 5 + 12 and raw.endswith(b"Ende")
        got = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.8:
            got += rd.read(0.05)
    finally:
        rd.close()
        em.stop()
    assert len(got) > 100
    seqs = np.array([f.seq for f in got])
    assert np.all(np.diff(seqs) > 0)
    wl = np.array([f.wl_fm for f in got], dtype=np.float64) / 1e6
    assert np.max(np.abs(wl - ds.wl_nm[seqs])) <= 0.5e-4 + 1e-9
    assert em.stats.ignored_commands >= 2
    assert rd.stats()["bad_replies"] == 0


def test_device_disappears_and_comes_back(tmp_path, dropout_recording):
    ds = dropout_recording.subset(np.arange(600))
    ds.extra.pop("dropout")
    pb = E.Playback.from_dataset(ds)
    link = str(tmp_path / "ttyDEV")
    first = E.Emulator(pb, rate=2000, link=link, linger=0.3).start()
    rd = R.NativeReader(link)
    got = []
    try:
        t0 = time.monotonic()
        second = None
        while time.monotonic() - t0 < 8:
            got += rd.read(0.02)
            if second is None and not first._thread.is_alive():
                time.sleep(0.2)  # device away for a while
                second = E.Emulator(pb, rate=2000, link=link, linger=0.3).start()
            if second is not None and len(got) >= 2 * len(pb) - 50 and not second._thread.is_alive():
                break
    finally:
        rd.close()
        first.stop()
        if second is not None:
            second.stop()
    s = rd.stats()
    assert s["disconnects"] >= 1 and s["reconnects"] >= 1 and s["seq_restarts"] == 1
    seqs = [f.seq for f in got]
    restart = seqs.index(0, 1)
    assert seqs[:restart] == list(range(restart))  # first device: in order, nothing lost ...
    assert seqs[restart:] == list(range(len(seqs) - restart))  # ... second one too
    assert len(seqs) >= 2 * len(pb) - 50


@pytest.mark.slow
def test_stream_10s_at_1khz_no_lost_frames_and_equal_to_offline_fixed(tmp_path, small_exported_dir,
                                                                      capsys, emulate_process):
    from fbgforce.evaluation import engines
    from fbgforce.model import modeldir as fm
    from fbgforce.interrogator.stream import load_estimates

    proc, link = emulate_process("--scene", "smoke", "--seed", "5", "--duration", "10",
                                  "--rate", "1000")
    out_csv = tmp_path / "est.csv"
    code = main(["stream", "--port", str(link), "--model", str(small_exported_dir), "--out",
                 str(out_csv), "--idle-timeout", "1", "--start-timeout", "30", "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert f"interrogator: {link}" in _finish(proc)  # the device path is printed
    assert summary["samples"] == 10000 and summary["received"] == 10000
    assert summary["lost_frames"] == 0 and summary["bad_frames"] == 0
    assert 900 < summary["rate_hz"] < 1100
    est = load_estimates(out_csv)
    assert est["seq"].tolist() == list(range(10000))
    scene = sim.simulate("smoke", seed=5).subset(np.arange(10000))
    assert np.array_equal(est["wl_nm"], np.round(scene.wl_nm, 6))
    model = fm.load(small_exported_dir)
    off = engines.run_engine("fixed", small_exported_dir, model, est["wl_nm"],
                             np.asarray(summary["baseline_nm"]))
    assert np.array_equal(off["contact"], est["contact"])
    assert np.array_equal(off["force_N"], est["force_N"])
    assert np.array_equal(off["x_mm"], est["x_mm"], equal_nan=True)
    assert np.array_equal(off["y_mm"], est["y_mm"], equal_nan=True)
    assert np.array_equal(off["status"], est["status"])
    assert est["contact"].any() and est["force_N"].max() > 5.0


@pytest.mark.slow
def test_stream_fispec_protocol(tmp_path, small_exported_dir, capsys, emulate_process):
    """stream polls a FiSpec-style device: estimates of the polled samples, scene wavelengths
    to 1e-4 nm, the same as the offline engine on those samples."""
    from fbgforce.evaluation import engines
    from fbgforce.interrogator.stream import load_estimates

    proc, link = emulate_process("--scene", "smoke", "--seed", "5", "--duration", "4",
                                  "--protocol", "fispec", "--linger", "0.5")
    out_csv = tmp_path / "est.csv"
    assert main(["stream", "--port", str(link), "--protocol", "fispec", "--model",
                 str(small_exported_dir), "--out", str(out_csv), "--samples", "400",
                 "--start-timeout", "30", "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    _finish(proc)
    assert summary["samples"] == 400 and summary["bad_frames"] == 0
    est = load_estimates(out_csv)
    scene = sim.simulate("smoke", seed=5)
    assert np.all(np.diff(est["seq"]) > 0)
    assert np.max(np.abs(est["wl_nm"] - scene.wl_nm[est["seq"]])) <= 0.5e-4 + 1e-9
    off = engines.run_engine("fixed", small_exported_dir, None, est["wl_nm"],
                             np.asarray(summary["baseline_nm"]))
    assert np.array_equal(off["force_N"], est["force_N"])


@pytest.mark.slow
def test_emulate_record_train_gives_a_working_model(tmp_path, capsys, emulate_process):
    proc, link = emulate_process("--scene", "smoke", "--seed", "3", "--rate", "5000",
                                  "--loadcell", "--loadcell-link", str(tmp_path / "ttyLC"))
    rec = tmp_path / "rec.csv"
    code = main(["record", "--port", str(link), "--loadcell-port", str(tmp_path / "ttyLC"),
                 "--out", str(rec), "--idle-timeout", "1", "--start-timeout", "30", "--json",
                 "--quiet"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    _finish(proc)
    truth = sim.simulate("smoke", seed=3)
    assert summary["samples"] == len(truth) and summary["unmatched_frames"] == 0, json.dumps(summary)
    assert summary["lost_frames"] == 0 and summary["presses"] == truth.n_presses
    got = dataset.load(rec)
    assert np.array_equal(got.extra["seq"], np.arange(len(truth)))
    assert np.max(np.abs(got.wl_nm - truth.wl_nm)) < 1e-6
    assert np.max(np.abs(got.t_s - truth.t_s)) < 1e-6
    assert np.array_equal(got.contact, truth.contact)
    assert np.array_equal(got.press_id, truth.press_id)
    assert np.max(np.abs(got.force_N - truth.force_N)) < 1e-5
    assert np.nanmax(np.abs(got.x_mm - truth.x_mm)) < 1e-4
    # The recorded log trains a model that works on another recording of the same device.
    model_dir = tmp_path / "model"
    assert main(["train", "--data", str(rec), "--out", str(model_dir), "--epochs", "20",
                 "--idle-pads", "0", "--json"]) == 0
    capsys.readouterr()
    test_csv = tmp_path / "other.csv"
    dataset.save(sim.simulate("smoke", seed=11), test_csv)
    assert main(["evaluate", "--model", str(model_dir), "--data", str(test_csv), "--json"]) == 0
    metrics = json.loads(capsys.readouterr().out)
    # Far better than guessing (majority contact class; force std ~20 N; pad 21 x 27 mm).
    other = dataset.load(test_csv)
    majority = max(np.mean(other.contact), 1 - np.mean(other.contact))
    assert metrics["contact_accuracy"] > majority + 0.1
    assert metrics["rmse_force_N"] < 6.0
    assert metrics["rmse_x_mm"] < 3.0 and metrics["rmse_y_mm"] < 4.0


def test_cli_bad_input_exits_2(tmp_path, capsys):
    assert main(["emulate", "--scene", "smoke", "--faults", "zap=0.1"]) == 2
    assert "--faults" in capsys.readouterr().err
    assert main(["stream", "--port", "loop://", "--model", str(tmp_path / "nope")]) == 2
    assert main(["emulate", "--data", str(tmp_path / "missing.csv")]) == 2
