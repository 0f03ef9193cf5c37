"""Wire protocols and reader logic without pseudo-terminals (fast): frames, CRC, resync,
FiSpec frames, load-cell lines, sequence tracking, fault plans, pyserial loop:// and socket://."""
from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fbgforce.interrogator import emulator as E
from fbgforce.interrogator import protocol as P
from fbgforce.interrogator import reader as R


def _frames(n: int, seed: int = 0, channels: int = 5) -> tuple[list[bytes], np.ndarray]:
    rng = np.random.default_rng(seed)
    # Peaks wander as a fingertip's do (a few pm per sample), so the reader's gate accepts them.
    wl = rng.integers(1_500_000_000, 1_600_000_000, size=(1, channels)) + np.cumsum(
        rng.integers(-20_000, 20_000, size=(n, channels)), axis=0)
    return P.encode_frames(100, np.arange(n) * 1000, wl), wl


def test_crc_is_ccitt_false_check_value():
    assert P.crc16_ccitt_false(b"123456789") == 0x29B1
    assert P.crc16_ccitt_false(b"") == 0xFFFF


def test_frame_layout_byte_by_byte():
    f = P.encode_frame(0x01020304, 0x1122334455667788, [1_546_213_456, -1, 0, 2**31 - 1, -(2**31)],
                       version=1)
    assert len(f) == P.frame_size(5, version=1) == 38
    assert f[:2] == b"\xa5\x5a" and f[2] == 1 and f[3] == 5
    assert f[4:8] == bytes([4, 3, 2, 1])  # little-endian sequence
    assert struct.unpack_from("<Q", f, 8)[0] == 0x1122334455667788
    assert struct.unpack_from("<5i", f, 16) == (1_546_213_456, -1, 0, 2**31 - 1, -(2**31))
    assert struct.unpack_from("<H", f, 36)[0] == P.crc16_ccitt_false(f[:36]) == 0x3053
    assert f.hex() == ("a55a0105040302018877665544332211" "5058295cffffffff00000000ffffff7f"
                       "000000805330")  # the example in docs/protocol.md


def test_frame_v2_layout_crc32_and_both_versions_read():
    f = P.encode_frame(0x01020304, 0x1122334455667788, [1_546_213_456, -1, 0, 2**31 - 1, -(2**31)])
    assert len(f) == P.frame_size(5) == 40 and f[2] == 2
    assert P.crc32(b"123456789") == 0xCBF43926
    assert struct.unpack_from("<I", f, 36)[0] == P.crc32(f[:36])
    assert f.hex() == ("a55a0205040302018877665544332211" "5058295cffffffff00000000ffffff7f"
                       "000000806e34fea8")  # the example in docs/protocol.md
    v1 = P.encode_frame(7, 8, [1, 2, 3, 4, 5], version=1)
    assert [fr.seq for fr in P.FrameDecoder(5).feed(v1 + v1[:3])] == [7]  # old devices still read
    # After the first good frame the stream is locked on its version: a v1 frame amid v2 ones is
    # refused, so a damaged version byte cannot select the weaker check.
    dec = P.FrameDecoder(5)
    got = dec.feed(P.encode_frame(1, 10, [1] * 5) + P.encode_frame(2, 11, [1] * 5, version=1)
                   + P.encode_frame(3, 12, [1] * 5))
    assert [fr.seq for fr in got] == [1, 3] and dec.stats.version_errors == 1


def test_decoder_byte_by_byte_and_split_anywhere():
    frames, wl = _frames(20)
    data = b"".join(frames)
    dec = P.FrameDecoder(5)
    got = [fr for b in data for fr in dec.feed(bytes([b]))]
    assert [g.seq for g in got] == list(range(100, 120))
    assert [list(g.wl_fm) for g in got] == wl.tolist()
    assert dec.stats.discarded_bytes == 0 and dec.stats.crc_errors == 0 and dec.pending == 0


# derandomize: a truncated frame completed by random garbage passes CRC-16 with probability
# 2**-16 per case; fixed examples keep the test deterministic while covering many layouts.
@settings(max_examples=60, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), chunk=st.integers(1, 97))
def test_decoder_delivers_every_good_frame_and_counts_every_bad_byte(seed, chunk):
    """Random corruption (bit flips, truncation, garbage, drops), fed in random chunk sizes:
    exactly the intact frames come out, and every other byte is counted as discarded."""
    rng = np.random.default_rng(seed)
    frames, _ = _frames(60, seed)
    kinds = rng.integers(0, 5, size=len(frames))  # codes of emulator.FAULTS
    line, good = bytearray(), []
    for i, (fr, kind) in enumerate(zip(frames, kinds)):
        name = E.FAULTS[kind]
        if name == "flip":
            b = bytearray(fr)
            for bit in rng.choice(len(b) * 8, size=int(rng.integers(1, 4)), replace=False):
                b[bit // 8] ^= 1 << (bit % 8)
            line += b
        elif name == "truncate":
            line += fr[:int(rng.integers(1, len(fr) - 2))]
        elif name == "garbage":
            line += rng.integers(0, 256, size=int(rng.integers(1, 80)), dtype=np.uint8).tobytes()
            line += fr
            good.append(100 + i)
        elif name == "none":
            line += fr
            good.append(100 + i)
    dec = P.FrameDecoder(5)
    trk = R.SequenceTracker()
    got = []
    for k in range(0, len(line), chunk):
        got += [f.seq for f in dec.feed(bytes(line[k:k + chunk])) if trk.accept(f.seq)]
    dec.flush()
    assert got == good
    assert dec.stats.frames * P.frame_size(5) + dec.stats.discarded_bytes == len(line)
    # Every frame not delivered shows as a sequence gap (except trailing ones after the last).
    assert trk.stats.lost_frames == (good[-1] - good[0] + 1) - len(good)


def test_decoder_rejects_wrong_channel_count_and_version():
    fr = P.encode_frame(1, 2, [1, 2, 3])
    dec = P.FrameDecoder(5)
    assert dec.feed(fr) == [] and dec.stats.header_errors == 1
    bad_version = bytearray(P.encode_frame(1, 2, [1, 2, 3, 4, 5]))
    bad_version[2] = 9
    dec = P.FrameDecoder(None)
    assert dec.feed(bytes(bad_version) + P.encode_frame(2, 3, [1])) != []
    assert dec.stats.header_errors == 1 and dec.stats.frames == 1


def test_sequence_tracker_gap_wrap_duplicate_restart():
    t = R.SequenceTracker()
    for s in (2**32 - 2, 2**32 - 1, 0, 3, 3, 4, 1):
        t.accept(s)
    assert t.stats.lost_frames == 2  # 1 and 2 missing after the wrap
    assert t.stats.duplicates == 1 and t.stats.seq_restarts == 1


def test_fispec_frame_round_trip_and_size():
    wl = [15_462_134, 15_300_000, 15_380_001, 15_540_000, 15_620_000]
    fr = P.encode_fispec_frame(wl, [1, 2, 3, 4, 5], 2512, 77)
    assert len(fr) == 8 * 5 + 12 and fr.endswith(b"Ende")
    dec = P.decode_fispec_frame(fr, 5)
    assert dec.wl_units == tuple(wl) and dec.amplitude == (1, 2, 3, 4, 5)
    assert dec.temperature_c100 == 2512 and dec.counter == 77
    assert dec.to_frame().wl_fm[0] == 1_546_213_400
    assert P.decode_fispec_frame(fr[:-1], 5) is None
    assert P.decode_fispec_frame(fr, 4) is None


def test_command_parser_splits_and_survives_noise():
    p = P.CommandParser()
    assert p.feed(b"?") == []
    assert p.feed(b">P>KA,5") == [b"?>", b"P>"]
    assert p.feed(b">\x00garbage\r\nP>") == [b"KA,5>", b"P>"]
    assert p.feed(b"x" * 100) == [] and p.overflows == 1


def test_loadcell_line_round_trip_and_bad_lines():
    s = P.LoadCellSample(123, 10.25, 13.5, 12.34567, 1, 4)
    line = P.encode_loadcell_line(s)
    assert line.startswith(b"$LC,123,") and line.endswith(b"\r\n")
    dec = P.LineDecoder()
    corrupt = bytearray(line)
    corrupt[10] ^= 0x01
    out = dec.feed(b"noise" + line + bytes(corrupt) + b"\r\n" + line[:7])
    assert out == [s]
    assert dec.stats.lines == 1 and dec.stats.bad_lines == 1
    assert dec.feed(line[7:]) == [s]


def test_nm_fm_conversion_is_exact_and_maps_nan_to_zero():
    wl = np.array([[1546.213456, 1530.0, np.nan, 1999.999999, 1000.000001]])
    fm = P.nm_to_fm(wl)
    assert fm.tolist() == [[1546213456, 1530000000, 0, 1999999999, 1000000001]]
    assert np.array_equal(P.nm_to_fm(P.fm_to_nm(fm)), fm)


def test_fault_plan_from_dropout_column_and_rates():
    dropout = np.array([0, 1, 2, 0, 3, 0, 0, 1], dtype=np.int8)
    plan = E.plan_faults(8, dropout=dropout, seed=0)
    assert plan[1] == E.FAULT_CODE["drop"] and plan[2] == E.FAULT_CODE["flip"]
    assert plan[4] in (E.FAULT_CODE["flip"], E.FAULT_CODE["truncate"], E.FAULT_CODE["garbage"])
    assert plan[0] == plan[3] == 0
    plan = E.plan_faults(20000, rates={"drop": 0.05, "garbage": 0.05}, seed=1)
    assert 800 < (plan == E.FAULT_CODE["drop"]).sum() < 1200
    assert np.array_equal(plan, E.plan_faults(20000, rates={"drop": 0.05, "garbage": 0.05}, seed=1))
    assert E.parse_fault_rates("drop=0.01, flip=0.5") == {"drop": 0.01, "flip": 0.5}
    for bad in ("drop", "zap=0.1", "drop=x", "drop=2"):
        with pytest.raises(ValueError):
            E.parse_fault_rates(bad)


def test_native_reader_on_loop_url():
    r = R.NativeReader("loop://")
    assert r.link.open()
    frames, _ = _frames(10)
    r.link.write(b"junk" + b"".join(frames))
    got = []
    deadline = time.monotonic() + 2
    while len(got) < 10 and time.monotonic() < deadline:
        got += r.read(0.01)
    assert [f.seq for f in got] == list(range(100, 110))
    s = r.stats()
    assert s["discarded_bytes"] == 4 and s["resyncs"] == 1 and s["lost_frames"] == 0
    r.close()


def test_native_reader_on_socket_url_survives_server_restart():
    """socket://host:port works, and a server that goes away and comes back is reconnected."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]
    frames, _ = _frames(40)

    def serve():
        for part in (frames[:20], frames[20:]):
            conn, _ = srv.accept()
            time.sleep(0.2)  # pyserial's socket:// open() discards what is already waiting
            conn.sendall(b"".join(part))
            time.sleep(0.1)
            conn.close()  # the "device" disappears

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    r = R.NativeReader(f"socket://127.0.0.1:{port}")
    got = []
    deadline = time.monotonic() + 10
    while len(got) < 40 and time.monotonic() < deadline:
        got += r.read(0.02)
    r.close()
    srv.close()
    assert [f.seq for f in got] == list(range(100, 140))
    s = r.stats()
    assert s["disconnects"] >= 1 and s["reconnects"] >= 1 and s["lost_frames"] == 0


def test_link_to_missing_device_does_not_raise():
    link = R.SerialLink("/dev/does-not-exist-fbg", backoff_min=0.01, backoff_max=0.02)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 0.1:
        assert link.read(0.01) == b""
    assert link.stats.open_failures >= 2 and not link.is_open
    assert not link.write(b"P>")


@pytest.mark.parametrize("engine", ["fixed", "float"])
def test_live_estimator_in_chunks_equals_offline_engine(engine, small_exported_dir,
                                                        small_dataset_path):
    """Tare on the first samples, then any chunking gives the offline engine's estimates."""
    from fbgforce.recordings import dataset
    from fbgforce.evaluation import engines
    from fbgforce.model import modeldir as fm
    from fbgforce.interrogator.stream import LiveEstimator

    wl_fm = P.nm_to_fm(dataset.load(small_dataset_path).wl_nm[:3000])
    est = LiveEstimator(small_exported_dir, engine=engine, tare_samples=200)
    rng = np.random.default_rng(0)
    parts, k = [], 0
    while k < len(wl_fm):
        step = int(rng.integers(1, 120))
        out = est.push(wl_fm[k:k + step])
        parts.append(out)
        k += step
    live = {key: np.concatenate([p[key] for p in parts]) for key in ("contact", "force_N", "x_mm")}
    assert len(live["contact"]) == len(wl_fm)
    off = engines.run_engine(engine, small_exported_dir, fm.load(small_exported_dir),
                             P.fm_to_nm(wl_fm), est.baseline_nm)
    if engine == "fixed":
        assert np.array_equal(off["force_N"], live["force_N"])
        assert np.array_equal(off["x_mm"], live["x_mm"], equal_nan=True)
    else:  # float: same arithmetic on a sliding window; equal to rounding
        np.testing.assert_allclose(off["force_N"], live["force_N"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(off["x_mm"], live["x_mm"], rtol=0, atol=1e-9)
    assert np.array_equal(off["contact"], live["contact"])
    assert np.abs(est.baseline_nm - P.fm_to_nm(wl_fm[:200]).mean(axis=0)).max() < 2e-6
