"""Hyperion (Luna / Micron Optics) TCP protocol: codec byte by byte, peak map, emulator +
reader on loopback (commands, stream, drops, restart), and record from hyperion://."""
from __future__ import annotations

import json
import struct
import subprocess
import sys
import time

import numpy as np
import pytest

from fbgforce import sim
from fbgforce.recordings import dataset
from fbgforce.cli import main
from fbgforce.interrogator import emulator as E
from fbgforce.interrogator import hyperion as H
from fbgforce.interrogator.reader import iter_batches


@pytest.fixture(scope="module")
def playback():
    ds = sim.simulate("smoke", seed=2).subset(np.arange(3000))
    return E.Playback.from_dataset(ds)


def test_request_response_and_peaks_layout_byte_by_byte():
    req = H.encode_request("#GetSerialNumber", "ab")
    assert req[:8] == bytes([0, 0, 16, 0, 2, 0, 0, 0]) and req[8:] == b"#GetSerialNumberab"
    resp = H.encode_response(b"\x01\x02\x03", "ok")
    assert resp[:8] == bytes([0, 0, 2, 0, 3, 0, 0, 0]) and resp[8:] == b"ok\x01\x02\x03"
    rec = H.encode_peaks(0x0102030405060708, 1_700_000_000, 250_000_000,
                         [[1530.5, 1540.25], [], [1550.0], []])
    # peaks header: length 24 + 2*4, version, reserved, serial u64, seconds, nanoseconds
    assert struct.unpack_from("<HHIQII", rec) == (32, 1, 0, 0x0102030405060708, 1_700_000_000,
                                                  250_000_000)
    assert struct.unpack_from("<4h", rec, 24) == (2, 0, 1, 0)
    assert struct.unpack_from("<3d", rec, 32) == (1530.5, 1540.25, 1550.0)
    assert len(rec) == 32 + 3 * 8
    got = H.decode_peaks(rec)
    assert got.peaks == ((1530.5, 1540.25), (), (1550.0,), ()) and got.t_us == (
        1_700_000_000 * 1_000_000 + 250_000)
    with pytest.raises(ValueError):
        H.decode_peaks(rec[:-8])  # counts say 3 peaks, record holds 2
    dec = H.PeakStreamDecoder()
    msg = H.encode_stream_message(rec)
    out = [r for b in msg + msg for r in dec.feed(bytes([b]))]  # split anywhere
    assert out == [got, got] and dec.stats.messages == 2
    assert dec.feed(H.encode_response(b"", "err", status=1)) == [] and dec.broken


def test_peak_map_parse_index_and_window_rules():
    m = H.PeakMap.parse("1:1, 1:2, 2:1545-1547.5, 2:1550-1552, 1:3")
    assert m.text() == "1:1,1:2,2:1545-1547.5,2:1550-1552,1:3"
    rec = H.PeaksRecord(7, 1, 0, ((1530.0, 1535.0, 1560.0), (1546.0, 1551.0)))
    assert m.frame(rec).wl_fm == (1530000000, 1535000000, 1546000000, 1551000000, 1560000000)
    # A lost peak on channel 1 would shift the indices after it: none of them is trusted.
    lost = H.PeaksRecord(8, 1, 0, ((1530.0, 1560.0), (1546.0, 1547.0)))
    f = m.frame(lost)
    assert f.wl_fm[:2] == (0, 0) and f.wl_fm[4] == 0  # channel 1 by index: all lost
    assert f.wl_fm[2] == 0  # two peaks inside the window 1545-1547.5: ambiguous
    assert f.wl_fm[3] == 0  # no peak in 1550-1552
    assert m.unmapped == 5
    for bad in ("1:1,1:2", "0:1,1:2,1:3,1:4,1:5", "1:x,1:2,1:3,1:4,1:5", "1:5-4,1:2,1:3,1:4,1:5"):
        with pytest.raises(ValueError):
            H.PeakMap.parse(bad)


def test_emulator_commands_and_stream_with_drops_on_loopback(playback):
    plan = E.plan_faults(len(playback), rates={"drop": 0.02}, seed=4)
    em = E.HyperionEmulator(playback, rate=5000, faults=plan, command_port=0, stream_port=0,
                            linger=0.5).start()
    try:
        assert H.command("127.0.0.1", em.command_port, "#GetSerialNumber")[1] == b"HYP-EMU-0001"
        count = H.command("127.0.0.1", em.command_port, "#GetDutChannelCount")[1]
        assert struct.unpack("<I", count)[0] == 4
        peaks = H.decode_peaks(H.command("127.0.0.1", em.command_port, "#GetPeaks")[1])
        assert len(peaks.peaks) == 4 and len(peaks.peaks[0]) == 5
        with pytest.raises(H.HyperionError, match="Unknown command"):
            H.command("127.0.0.1", em.command_port, "#NoSuchCommand")
        rd = H.HyperionReader(em.url)
        got = []
        for batch in iter_batches(rd, idle_timeout=0.5, start_timeout=10):
            got += batch
        rd.close()
    finally:
        em.stop()
    good = np.flatnonzero(plan == 0)
    assert [f.seq for f in got] == good.tolist()
    assert all(f.wl_fm == tuple(playback.wl_fm[f.seq]) for f in got)
    assert all(f.t_us == 1_700_000_000_000_000 + playback.t_us[f.seq] for f in got)
    s = rd.stats()
    assert rd.serial_number == "HYP-EMU-0001" and rd.channel_count == 4
    assert s["lost_frames"] == np.count_nonzero(plan[:good[-1]])
    assert s["implausible_frames"] == 0 and s["unmapped_peaks"] == 0


def test_reader_reconnects_and_counts_an_instrument_restart(playback):
    pb = E.Playback(**{k: (v[:400] if isinstance(v, np.ndarray) else v)
                       for k, v in playback.__dict__.items()})
    first = E.HyperionEmulator(pb, rate=2000, command_port=0, stream_port=0, linger=0.2).start()
    ports = (first.command_port, first.stream_port)
    rd = H.HyperionReader(first.url)
    got = []
    second = None
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10:
            got += rd.read(0.02)
            if second is None and not first._thread.is_alive():
                time.sleep(0.2)  # instrument away for a while, then back on the same ports
                second = E.HyperionEmulator(pb, rate=2000, command_port=ports[0],
                                            stream_port=ports[1], linger=0.2,
                                            t0_s=1_700_000_100).start()
            if second is not None and len(got) >= 800 and not second._thread.is_alive():
                break
    finally:
        rd.close()
        first.stop()
        if second is not None:
            second.stop()
    s = rd.stats()
    assert [f.seq for f in got] == list(range(400)) * 2
    assert s["seq_restarts"] == 1 and s["lost_frames"] == 0
    assert s["disconnects"] >= 1 and s["reconnects"] >= 1


@pytest.mark.slow
def test_record_from_hyperion_source(tmp_path, capsys):
    """emulate --protocol hyperion --loadcell -> record --source hyperion:// -> a dataset equal
    to the scene (peak map given on both sides, FBG T on channel 2)."""
    pmap = "1:1,1:2,1:3,1:4,2:1"
    proc = subprocess.Popen([sys.executable, "-m", "fbgforce.cli", "emulate", "--scene", "smoke",
                             "--seed", "3", "--rate", "5000", "--protocol", "hyperion",
                             "--command-port", "0", "--stream-port", "0", "--peak-map", pmap,
                             "--loadcell", "--loadcell-link", str(tmp_path / "ttyLC"),
                             "--linger", "0.5"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().split(":", 1)[1].strip()  # type: ignore[union-attr]
        assert url.startswith("hyperion://")
        rec = tmp_path / "rec.csv"
        assert main(["record", "--source", url, "--peak-map", pmap, "--loadcell-port",
                     str(tmp_path / "ttyLC"), "--out", str(rec), "--idle-timeout", "1",
                     "--start-timeout", "30", "--json", "--quiet"]) == 0
        summary = json.loads(capsys.readouterr().out)
        proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    truth = sim.simulate("smoke", seed=3)
    assert summary["samples"] == len(truth) and summary["lost_frames"] == 0, summary
    got = dataset.load(rec)
    assert np.array_equal(got.extra["seq"], np.arange(len(truth)))
    assert np.max(np.abs(got.wl_nm - truth.wl_nm)) < 1e-6
    assert np.array_equal(got.contact, truth.contact)


def test_peak_map_from_model_metadata_and_bad_options(tmp_path, small_exported_dir, capsys):
    import shutil

    model_dir = tmp_path / "model"
    shutil.copytree(small_exported_dir, model_dir)
    doc = json.loads((model_dir / "model.json").read_text())
    doc.setdefault("metadata", {})["hyperion_peak_map"] = "1:1,1:2,1:3,1:4,2:1"
    (model_dir / "model.json").write_text(json.dumps(doc))
    found = H.peak_map_from_model(model_dir)
    assert found is not None and found.text() == "1:1,1:2,1:3,1:4,2:1"
    assert H.peak_map_from_model(tmp_path) is None
    assert main(["stream", "--source", "hyperion://127.0.0.1:1", "--model", str(model_dir),
                 "--peak-map", "1:1"]) == 2
    assert "--peak-map" in capsys.readouterr().err
    assert main(["stream", "--source", "hyperion://127.0.0.1:1", "--model", str(model_dir),
                 "--protocol", "native"]) == 2
    assert main(["emulate", "--scene", "smoke", "--protocol", "hyperion", "--link", "x"]) == 2


def test_reader_reopens_a_stream_that_is_out_of_step(playback):
    """A peak stream whose header makes no sense cannot be resynchronised (no sync word): the
    reader counts a header error, closes and reconnects, and goes on from the new connection."""
    import socket
    import threading

    cmd = E.HyperionEmulator(playback, command_port=0, stream_port=0, wait_client=False,
                             linger=0.0)  # serves the commands the reader asks on connect
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(2)
    wl = [1530.0, 1535.0, 1540.0, 1545.0, 1550.0]

    def message(k: int) -> bytes:
        return H.encode_stream_message(H.encode_peaks(k, 1, k * 1_000_000, [wl, [], [], []]))

    def serve() -> None:
        conn, _ = srv.accept()
        conn.sendall(message(0) + message(1) + b"\x07" * 8 + message(2))  # nonsense, then more
        conn2, _ = srv.accept()
        conn2.sendall(message(3) + message(4))
        time.sleep(0.5)
        conn.close()
        conn2.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    stop = threading.Event()

    def commands() -> None:
        while not stop.is_set():
            cmd._service(0.01)

    tc = threading.Thread(target=commands, daemon=True)
    tc.start()
    rd = H.HyperionReader(f"hyperion://127.0.0.1:{cmd.command_port}?stream="
                          f"{srv.getsockname()[1]}")
    got = []
    try:
        t0 = time.monotonic()
        while len(got) < 4 and time.monotonic() - t0 < 5:
            got += rd.read(0.02)
    finally:
        rd.close()
        stop.set()
        tc.join(2)
        cmd.close()
        srv.close()
    s = rd.stats()
    assert [f.seq for f in got] == [0, 1, 3, 4]
    assert s["header_errors"] == 1 and s["reconnects"] == 1 and s["lost_frames"] == 1
