"""Every subcommand, walked through a table of bad inputs: each ends with exit 2, exactly one
line on stderr naming the problem, and no traceback (docs/cli.md, "Errors").

Live commands (stream, record) with no device, a silent device or a device speaking another
protocol end the same way, bounded in time, instead of succeeding with "0 samples".
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fbgforce.model import modeldir as fm
from fbgforce.cli import build_parser, main

NO_DEVICE = "/dev/ttyFBG-no-such-device"


@pytest.fixture(scope="module")
def bad(tmp_path_factory, small_exported_dir, small_dataset_path):
    """Paths of good and deliberately broken inputs (one directory, built once)."""
    from fbgforce.recordings import dataset

    root = tmp_path_factory.mktemp("bad_inputs")
    p = {"good_model": small_exported_dir, "good_data": small_dataset_path,
         "missing": root / "missing.csv", "out": root / "out"}
    ds = dataset.load(small_dataset_path).subset(slice(0, 2000))
    npz = root / "data.npz"
    dataset.save(ds, npz)
    raw = npz.read_bytes()
    p["truncated_npz"] = root / "truncated.npz"
    p["truncated_npz"].write_bytes(raw[: len(raw) // 2])
    p["empty_npz"] = root / "empty.npz"
    p["empty_npz"].write_bytes(b"")
    p["garbage_csv"] = root / "garbage.csv"
    p["garbage_csv"].write_text("this,is,not\na,dataset,file\n")
    p["garbage_mcap"] = root / "garbage.mcap"
    p["garbage_mcap"].write_bytes(b"\x89MCAP0\r\n not really")
    p["garbage_toml"] = root / "scene.toml"
    p["garbage_toml"].write_text("[scene\nname = ")

    def model_copy(name: str) -> Path:
        d = root / name
        shutil.copytree(small_exported_dir, d)
        return d

    blob = (small_exported_dir / "model.fbgm").read_bytes()
    p["corrupt_blob"] = model_copy("corrupt_blob")
    flipped = bytearray(blob)
    flipped[len(blob) // 2] ^= 0x40
    (p["corrupt_blob"] / "model.fbgm").write_bytes(bytes(flipped))
    p["truncated_blob"] = model_copy("truncated_blob")
    (p["truncated_blob"] / "model.fbgm").write_bytes(blob[: len(blob) // 3])
    p["not_a_blob"] = model_copy("not_a_blob")
    (p["not_a_blob"] / "model.fbgm").write_bytes(b"PK\x03\x04" + bytes(100))
    p["bad_json"] = model_copy("bad_json")
    (p["bad_json"] / "model.json").write_text('{"format": ')
    p["truncated_weights"] = model_copy("truncated_weights")
    w = p["truncated_weights"] / fm.WEIGHTS_NPZ
    w.write_bytes(w.read_bytes()[:200])
    p["truncated_calibration"] = model_copy("truncated_calibration")
    c = p["truncated_calibration"] / fm.CALIBRATION_NPZ
    c.write_bytes(c.read_bytes()[:200])
    p["not_a_dir"] = root / "not_a_model"
    p["file_in_the_way"] = root / "a_file"
    p["file_in_the_way"].write_text("x")
    p.update(_lab_logs_in_other_units(root / "lab", small_dataset_path))
    return p


def _lab_logs_in_other_units(lab: Path, data: Path) -> dict[str, Path]:
    """The simulator's lab logs of ``data`` (s, N, mm: ``lab_map`` imports them) and copies
    with one log's column in the unit a thousand times smaller (clocks in ms, force in mN,
    positions in µm), which the default flags read 1000 times too large."""
    from fbgforce.recordings import dataset
    from fbgforce.sim.lablogs import write_lab_logs

    write_lab_logs(dataset.load(data), lab, rate_hz=500, offset_s=0.1, drift_ppm=80,
                   jitter_s=1e-4)
    out = {"lab_map": lab / "import.toml"}
    for name, log, columns in (("fbg_ms", "interrogator.csv", (0,)), ("stage_ms", "stage.csv", (0,)),
                               ("stage_mN", "stage.csv", (1,)), ("stage_um", "stage.csv", (2, 3))):
        lines = (lab / log).read_text().splitlines()
        rows = [lines[0]]
        for ln in lines[1:]:
            fields = ln.split(",")
            for j in columns:
                fields[j] = repr(float(fields[j]) * 1000.0)
            rows.append(",".join(fields))
        out[name] = lab / f"{name}.csv"
        out[name].write_text("\n".join(rows) + "\n")
    return out


# (subcommand, id, argv after the subcommand with {placeholders} from `bad`, expected words)
CASES = [
    ("simulate", "unknown scene", ["--scene", "no_such_scene", "--out", "{out}/x.csv"], "no_such_scene"),
    ("simulate", "broken scene TOML", ["--scene", "{garbage_toml}", "--out", "{out}/x.csv"], "scene.toml"),
    ("simulate", "bad output suffix", ["--scene", "smoke", "--out", "{out}/x.txt"], "x.txt"),
    ("train", "missing data file", ["--data", "{missing}", "--out", "{out}/m"], "missing.csv"),
    ("train", "truncated npz", ["--data", "{truncated_npz}", "--out", "{out}/m"], "truncated.npz"),
    ("train", "empty npz", ["--data", "{empty_npz}", "--out", "{out}/m"], "empty.npz"),
    ("train", "garbage CSV", ["--data", "{garbage_csv}", "--out", "{out}/m"], "garbage.csv"),
    ("train", "garbage rosbag2 MCAP", ["--data", "{garbage_mcap}", "--out", "{out}/m"],
     "garbage.mcap"),
    ("train", "zero restarts", ["--data", "{good_data}", "--out", "{out}/m", "--restarts",
                                "force=0"], "--restarts"),
    ("train", "restarts of no net", ["--data", "{good_data}", "--out", "{out}/m", "--restarts",
                                     "forse=2"], "forse"),
    ("train", "hold share above 1", ["--data", "{good_data}", "--out", "{out}/m",
                                     "--hold-augment", "1.5"], "--hold-augment"),
    ("train", "sizes not widths", ["--data", "{good_data}", "--out", "{out}/m", "--sizes",
                                   "contact=40x30"], "--sizes"),
    ("train", "a net wider than the runtime", ["--data", "{good_data}", "--out", "{out}/m",
                                               "--sizes", "location=200-50"], "--sizes"),
    ("evaluate", "no model dir", ["--model", "{not_a_dir}", "--data", "{good_data}"], "not_a_model"),
    ("evaluate", "truncated npz data", ["--model", "{good_model}", "--data", "{truncated_npz}"], "truncated.npz"),
    ("evaluate", "corrupt model.fbgm, fixed", ["--model", "{corrupt_blob}", "--data", "{good_data}",
                                              "--engine", "fixed"], "CRC"),
    ("evaluate", "truncated model.fbgm, fixed", ["--model", "{truncated_blob}", "--data",
                                                "{good_data}", "--engine", "fixed"], "model.fbgm"),
    ("evaluate", "not a blob, intref", ["--model", "{not_a_blob}", "--data", "{good_data}",
                                       "--engine", "intref"], "model.fbgm"),
    ("evaluate", "truncated model.fbgm, intref", ["--model", "{truncated_blob}", "--data",
                                                 "{good_data}", "--engine", "intref"], "model.fbgm"),
    ("evaluate", "broken model.json", ["--model", "{bad_json}", "--data", "{good_data}"], "model.json"),
    ("evaluate", "truncated weights", ["--model", "{truncated_weights}", "--data", "{good_data}"], ".npz"),
    ("analyze", "truncated npz", ["--data", "{truncated_npz}", "--epochs", "1"], "truncated.npz"),
    ("report", "truncated npz", ["--data", "{truncated_npz}", "--model", "{good_model}"], "truncated.npz"),
    ("report", "broken model.json", ["--data", "{good_data}", "--model", "{bad_json}"], "model.json"),
    ("export", "no model dir", ["--model", "{not_a_dir}"], "not_a_model"),
    ("export", "truncated weights", ["--model", "{truncated_weights}"], ".npz"),
    ("export", "truncated calibration.npz", ["--model", "{truncated_calibration}", "--no-onnx"],
     "calibration.npz"),
    ("export", "truncated calibration npz", ["--model", "{good_model}", "--calib", "{truncated_npz}",
                                            "--no-onnx"], "truncated.npz"),
    ("verify", "corrupt model.fbgm", ["--model", "{corrupt_blob}", "--data", "{good_data}"], "CRC"),
    ("verify", "truncated model.fbgm", ["--model", "{truncated_blob}", "--data", "{good_data}"], "model.fbgm"),
    ("verify", "truncated npz data", ["--model", "{good_model}", "--data", "{truncated_npz}"], "truncated.npz"),
    ("tradeoff", "truncated npz", ["--data", "{truncated_npz}", "--out", "{out}/t", "--quick"], "truncated.npz"),
    ("tradeoff", "unknown scene", ["--scene", "no_such_scene", "--out", "{out}/t", "--quick"], "no_such_scene"),
    ("bench-speed", "no model dir", ["--model", "{not_a_dir}", "--data", "{good_data}"], "not_a_model"),
    ("bench-speed", "corrupt model.fbgm", ["--model", "{corrupt_blob}", "--data", "{good_data}"], "CRC"),
    ("bench-speed", "int16 export given as --int8", ["--model", "{good_model}", "--int8",
                                                     "{good_model}", "--data", "{good_data}"], "--int8"),
    ("bench-speed", "truncated npz data", ["--model", "{good_model}", "--data", "{truncated_npz}"],
     "truncated.npz"),
    ("target-report", "no model dir", ["--model", "{not_a_dir}"], "not_a_model"),
    ("target-report", "truncated npz data", ["--model", "{good_model}", "--data", "{truncated_npz}"],
     "truncated.npz"),
    ("emulate", "truncated npz", ["--data", "{truncated_npz}", "--no-wait"], "truncated.npz"),
    ("emulate", "unknown scene", ["--scene", "no_such_scene", "--no-wait"], "no_such_scene"),
    ("emulate", "bad fault spec", ["--scene", "smoke", "--faults", "drop=2"], "--faults"),
    ("stream", "no device, --start-timeout", ["--port", NO_DEVICE, "--model", "{good_model}",
                                              "--start-timeout", "1"], "could not open"),
    ("stream", "port opens, silent", ["--port", "loop://", "--model", "{good_model}",
                                      "--start-timeout", "1"], "no byte arrived"),
    ("stream", "wrong protocol (bytes, no frame)", ["--port", "loop://", "--model", "{good_model}",
                                                    "--protocol", "fispec", "--start-timeout", "1"],
     "--protocol"),
    ("stream", "corrupt model.fbgm", ["--port", NO_DEVICE, "--model", "{corrupt_blob}",
                                      "--start-timeout", "1"], "CRC"),
    ("stream", "truncated model.fbgm", ["--port", NO_DEVICE, "--model", "{truncated_blob}",
                                        "--start-timeout", "1"], "model.fbgm"),
    ("stream", "broken model.json, float", ["--port", NO_DEVICE, "--model", "{bad_json}",
                                            "--engine", "float", "--start-timeout", "1"], "model.json"),
    ("record", "no interrogator", ["--port", NO_DEVICE, "--loadcell-port", "loop://", "--out",
                                   "{out}/rec.csv", "--start-timeout", "1"], "could not open"),
    ("stream", "bad ros2:// namespace", ["--port", NO_DEVICE, "--model", "{good_model}",
                                         "--publish", "ros2:///9lives", "--start-timeout", "1"],
     "--publish"),
    ("record", "--model without an .mcap output", ["--port", "loop://", "--loadcell-port",
                                                   "loop://", "--out", "{out}/rec.csv",
                                                   "--model", "{good_model}"], "--model"),
    ("record", "bad output suffix", ["--port", "loop://", "--loadcell-port", "loop://", "--out",
                                     "{out}/rec.txt", "--start-timeout", "1"], "rec.txt"),
    ("teleop", "unknown scene", ["--scene", "no_such_scene", "--out", "{out}/tele"], "no_such_scene"),
    ("teleop", "corrupt model.fbgm", ["--model", "{corrupt_blob}", "--out", "{out}/tele"], "CRC"),
    ("import", "no files given", ["--out", "{out}/imp.csv"], "--fbg"),
    ("import", "missing stage log", ["--fbg", "{good_data}", "--fbg-columns",
                                     "t=t_s,wl1=wl1_nm,wl2=wl2_nm,wl3=wl3_nm,wl4=wl4_nm,wlT=wlT_nm",
                                     "--stage", "{missing}", "--stage-columns",
                                     "t=t_s,force=force_N,x=x_mm,y=y_mm", "--out", "{out}/imp.csv"],
     "no such file"),
    ("import", "incomplete column map", ["--fbg", "{good_data}", "--fbg-columns", "t=t_s",
                                         "--stage", "{good_data}", "--stage-columns",
                                         "t=t_s,force=force_N,x=x_mm,y=y_mm", "--out",
                                         "{out}/imp.csv"], "missing key"),
    ("import", "column not in the log", ["--fbg", "{good_data}", "--fbg-columns",
                                         "t=time,wl1=wl1_nm,wl2=wl2_nm,wl3=wl3_nm,wl4=wl4_nm,wlT=wlT_nm",
                                         "--stage", "{good_data}", "--stage-columns",
                                         "t=t_s,force=force_N,x=wl1_nm,y=wl2_nm", "--out",
                                         "{out}/imp.csv"], "'time'"),
    ("import", "positions in mm read as um", ["--map", "{lab_map}", "--position-unit", "um",
                                              "--out", "{out}/imp.csv"], "--position-unit"),
    ("import", "positions in um read as mm", ["--map", "{lab_map}", "--stage", "{stage_um}",
                                              "--out", "{out}/imp.csv"], "--position-unit"),
    ("import", "force in N read as mN", ["--map", "{lab_map}", "--force-unit", "mN", "--out",
                                         "{out}/imp.csv"], "--force-unit"),
    ("import", "force in mN read as N", ["--map", "{lab_map}", "--stage", "{stage_mN}",
                                         "--out", "{out}/imp.csv"], "--force-unit"),
    ("import", "stage clock in ms read as s", ["--map", "{lab_map}", "--stage", "{stage_ms}",
                                               "--out", "{out}/imp.csv"], "--stage-time-unit"),
    ("import", "stage clock in s read as ms", ["--map", "{lab_map}", "--stage-time-unit", "ms",
                                               "--out", "{out}/imp.csv"], "--stage-time-unit"),
    ("import", "interrogator clock in ms read as s", ["--map", "{lab_map}", "--fbg",
                                                      "{fbg_ms}", "--out", "{out}/imp.csv"],
     "--fbg-time-unit"),
    ("import", "interrogator clock in s read as ms", ["--map", "{lab_map}", "--fbg-time-unit",
                                                      "ms", "--out", "{out}/imp.csv"],
     "--fbg-time-unit"),
    ("protocol", "fewer presses than groups", ["--out", "{out}/prog.csv", "--presses", "2"],
     "--presses"),
    ("coverage", "missing file", ["--data", "{missing}"], "no such file"),
    ("coverage", "truncated npz", ["--data", "{truncated_npz}"], "truncated.npz"),
    ("demo", "negative seed", ["--seed", "-1", "--out", "{out}/demo"], "--seed"),
    ("demo", "output is a file", ["--out", "{file_in_the_way}", "--quick"], "a_file"),
]


def _argv(command: str, args: list[str], paths: dict[str, Path]) -> list[str]:
    return [command, *(a.format(**{k: str(v) for k, v in paths.items()}) for a in args)]


def test_table_covers_every_subcommand():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    missing = sorted(set(sub.choices) - {c[0] for c in CASES})
    assert not missing, f"subcommands without a bad-input case: {missing}"
    print(f"\nbad-input table: {len(CASES)} cases over {len(sub.choices)} subcommands")
    doc = (Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()
    assert f"({len(CASES)} cases)" in doc, "docs/cli.md quotes another number of bad-input cases"


@pytest.mark.parametrize("command,case,args,words", CASES,
                         ids=[f"{c[0]}: {c[1]}" for c in CASES])
def test_bad_input_exits_2_one_line(command, case, args, words, bad, capsys):
    argv = _argv(command, args, bad)
    t0 = time.monotonic()
    code = main(argv)
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2, f"{argv}: exit {code}\n{captured.err}"
    assert len(lines) == 1, f"{argv}: {len(lines)} lines on stderr:\n{captured.err}"
    assert lines[0].startswith(f"fbgforce {command}: error: "), lines[0]
    assert words in lines[0], lines[0]
    assert "Traceback" not in captured.err
    assert time.monotonic() - t0 < 30


def _cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fbgforce.cli", *args], capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.slow
def test_stream_no_device_with_duration_ends_with_exit_2(bad):
    """The exact commands that used to succeed with "0 samples" or never return: a real
    process, a wall-clock limit, one line."""
    t0 = time.monotonic()
    r = _cli("stream", "--port", NO_DEVICE, "--model", str(bad["good_model"]), "--duration", "1")
    took = time.monotonic() - t0
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and NO_DEVICE in lines[0] and "could not open" in lines[0], r.stderr
    assert "Traceback" not in r.stderr
    assert took < 30


def test_stream_wrong_protocol_against_a_pushing_device(bad):
    """A device that pushes native frames, read as FiSpec: bytes arrive, no frame is valid."""
    from fbgforce.interrogator import protocol as P

    master, slave = os.openpty()
    stop = threading.Event()

    def device() -> None:
        seq = 0
        while not stop.is_set():
            try:
                os.write(master, P.encode_frame(seq, seq * 1000, [1_550_000_000] * 5) * 10)
            except OSError:
                return
            seq += 10
            time.sleep(0.01)

    thread = threading.Thread(target=device, daemon=True)
    thread.start()
    try:
        port = os.ttyname(slave)
        r = _cli("stream", "--port", port, "--model", str(bad["good_model"]), "--protocol",
                 "fispec", "--start-timeout", "1")
    finally:
        stop.set()
        thread.join(timeout=5)
        os.close(master)
        os.close(slave)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "bytes arrived" in lines[0] and "--protocol" in lines[0], r.stderr
