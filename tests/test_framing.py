"""Framing you can trust: corrupted streams never deliver a wrong sample, one fabricated
sequence number cannot move the loss counters, and the FiSpec ``Ende`` split is handled.
The large runs are bench/bench_framing.py; these use ~10^4 frames per protocol."""
from __future__ import annotations

import pytest

from fbgforce.bench import bench_framing as B
from fbgforce.interrogator import protocol as P

N = 10_000


@pytest.mark.parametrize("run", [
    lambda: B.run_native(N, 1, version=2),
    lambda: B.run_native(N, 1, version=1),
    lambda: B.run_fispec(N, 1),
    lambda: B.run_hyperion(N, 1),
], ids=["native-v2", "native-v1", "fispec", "hyperion"])
def test_corrupted_streams_deliver_no_wrong_frame_and_count_losses_exactly(run):
    r = run()
    assert r["wrong"] == 0, r
    assert r["lost_error"] == 0, r
    # Every frame that reached the line intact is delivered.
    assert r["good"] == r["intact"], r


def test_trailer_only_rule_is_fooled_by_the_same_fispec_stream():
    """The comparison row of the benchmark: the rule readers used before delivers wrong
    samples on this stream, so the test above can fail."""
    r = B.run_fispec(2000, 1, gate=False)
    assert r["wrong"] > 0


def _f(seq: int, t_us: int, wl: int = 1_546_000_000) -> P.Frame:
    return P.Frame(seq, t_us, (wl, wl + 5_000_000, wl + 10_000_000, wl - 5_000_000,
                               wl - 10_000_000))


def test_gate_one_fabricated_sequence_number_moves_no_counter():
    g = P.FrameGate()
    assert g.push(_f(10, 10_000)) == [_f(10, 10_000)]
    assert g.push(_f(11, 11_000)) == [_f(11, 11_000)]
    assert g.push(_f(0x9ABCDEF0, 12_000)) is None  # fabricated: held, not delivered
    assert g.push(_f(12, 12_000)) == [_f(12, 12_000)]  # the course goes on: held one refused
    assert g.stats.lost_frames == 0 and g.stats.seq_restarts == 0
    assert g.stats.implausible_frames == 1
    # Time running backwards, a wavelength outside the window, a jump of 3 nm in 1 ms: refused.
    assert g.push(_f(13, 5_000)) is None
    assert g.push(_f(13, 13_000, wl=900_000_000)) is None
    assert g.push(_f(13, 13_000, wl=1_549_000_000)) is None
    assert g.push(_f(13, 13_000)) == [_f(13, 13_000)]
    assert g.push(_f(13, 13_000)) == []  # duplicate
    assert g.stats.duplicates == 1 and g.stats.lost_frames == 0


def test_gate_confirmed_restart_and_jump_are_counted_once():
    g = P.FrameGate()
    for k in range(5):
        g.push(_f(100 + k, 1000 * k))
    assert g.push(_f(0, 500)) is None  # a restart looks like any bad frame at first ...
    assert g.push(_f(1, 1500)) == [_f(0, 500), _f(1, 1500)]  # ... until the next one agrees
    assert g.stats.seq_restarts == 1 and g.stats.lost_frames == 0
    assert g.push(_f(200_001, 60_000_000)) is None  # a forward jump beyond 2**16
    assert g.push(_f(200_003, 60_002_000)) is not None
    assert g.stats.seq_jumps == 1 and g.stats.lost_frames == (200_001 - 1 - 1) + 1


def _forge_crc32(body: bytearray, free: int, target: int) -> None:
    """Set ``body[free:free + 4]`` so that ``crc32(body) == target`` (CRC-32 is affine in the
    message bits: solve the 32 x 32 system over GF(2))."""
    base = P.crc32(body)
    cols = []
    for bit in range(32):
        b = bytearray(body)
        b[free + bit // 8] ^= 1 << (bit % 8)
        cols.append(P.crc32(b) ^ base)
    want = target ^ base
    # Gaussian elimination on rows = output bits, columns = input bits.
    rows = [(sum(((cols[j] >> i) & 1) << j for j in range(32)), (want >> i) & 1) for i in range(32)]
    solution, pivots = 0, []
    for col in range(32):
        k = next(r for r in range(len(pivots), 32) if (rows[r][0] >> col) & 1)
        rows[len(pivots)], rows[k] = rows[k], rows[len(pivots)]
        p = rows[len(pivots)]
        rows = [(r[0] ^ p[0], r[1] ^ p[1]) if i != len(pivots) and (r[0] >> col) & 1 else r
                for i, r in enumerate(rows)]
        pivots.append(col)
    for i, col in enumerate(pivots):
        solution |= rows[i][1] << col
    for bit in range(32):
        if (solution >> bit) & 1:
            body[free + bit // 8] ^= 1 << (bit % 8)
    assert P.crc32(body) == target


def test_native_decoder_finds_the_good_frame_inside_a_refused_one():
    """The fault found with a hostile device: a cut-short frame completed by the next frame's
    bytes that passes the check (forged here: CRC-32 makes it a 2**-32 event). The gate refuses
    it (its last wavelength is the next frame's sync word: 84 nm) and the decoder resumes one
    byte further, so the next frame is not swallowed and no loss is counted."""
    good = [P.encode_frame(k, 1000 * k, [1_546_000_000] * 5) for k in range(4)]
    overlap = good[2][:8]
    fake = bytearray(P.encode_frame(1, 1000, [0] * 5)[:36])
    fake[32:36] = overlap[:4]  # last wavelength = the next frame's sync, version, count
    _forge_crc32(fake, 16, int.from_bytes(overlap[4:8], "little"))
    fake += overlap[4:8]
    assert P.FrameDecoder(5).feed(bytes(fake)) != []  # a frame by every byte-level rule
    line = good[0] + good[1] + bytes(fake[:-8]) + good[2] + good[3]
    dec = P.FrameDecoder(5, P.FrameGate())
    assert [f.seq for f in dec.feed(line)] == [0, 1, 2, 3]
    assert dec.gate.stats.lost_frames == 0  # type: ignore[union-attr]
    # Without the gate the fabricated frame is delivered and frame 2 is lost.
    assert [f.seq for f in P.FrameDecoder(5).feed(line)] == [0, 1, 1, 3]


def test_fispec_junk_then_reply_split_after_ende_in_payload():
    """The fault found with a hostile device: junk before a reply whose payload contains
    ``Ende``, the reply arriving split right after those bytes."""
    gate = P.FrameGate()
    units = [15_300_000, 15_350_000, 15_400_000, 15_450_000, 15_500_000]
    ende = int.from_bytes(b"Ende", "little")
    first = P.encode_fispec_frame(units, [12000] * 5, 2500, 41)
    reply = P.FiSpecReply(5, gate)
    assert reply.feed(first) is not None
    frame = P.encode_fispec_frame(units, [12000, ende, 12000, 12000, 12000], 2500, 42)
    cut = frame.index(b"Ende") + 4
    assert cut < len(frame) - 4  # the trailer is not the first "Ende"
    for junk_len in range(1, 70):
        g = P.FrameGate()
        g.push(P.decode_fispec_frame(first, 5).to_frame())  # type: ignore[union-attr]
        reply = P.FiSpecReply(5, g)
        junk = bytes((37 * i + junk_len) % 256 for i in range(junk_len))
        verdict = reply.feed(junk + frame[:cut])
        assert verdict is None, junk_len
        verdict = reply.feed(frame[cut:])
        assert verdict is not None and reply.frame_bytes == frame, junk_len
        assert verdict[0].seq == 42 and verdict[0].wl_fm == tuple(u * 100 for u in units)
