"""Framing you can trust: corrupted streams never deliver a wrong sample, one fabricated
or bit-flipped sequence number cannot move the loss counters, and the FiSpec ``Ende`` split is
handled. The large runs are bench/bench_framing.py; these use ~10^4 frames per protocol."""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fbgforce.bench import bench_framing as B
from fbgforce.interrogator import protocol as P
from fbgforce.interrogator import reader as R

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


def test_fispec_replies_with_one_flipped_bit_deliver_no_wrong_frame():
    """The audit's stream: FiSpec replies polled once per sample, 1.7 % with one bit flipped
    anywhere. No frame under a wrong counter, no false restart, lost counts exact (a flipped
    wavelength bit inside the step rule passes: FiSpec has no checksum)."""
    r = B.run_fispec_flips(N, 1)
    assert r["flipped"] > 100 and r["wrong"] == 0 and r["lost_error"] == 0, r
    assert r["restarts"] == 0 and r["good"] + r["wl_flips_passed"] >= r["intact"], r


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
    assert g.push(_f(10, 10_000)) is None  # a session's first frame waits for the next
    assert g.push(_f(11, 11_000)) == [_f(10, 10_000), _f(11, 11_000)]
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
        g.push(P.decode_fispec_frame(P.encode_fispec_frame(units, [12000] * 5, 2500, 40), 5
                                     ).to_frame())  # type: ignore[union-attr]
        g.push(P.decode_fispec_frame(first, 5).to_frame())  # type: ignore[union-attr]
        reply = P.FiSpecReply(5, g)
        junk = bytes((37 * i + junk_len) % 256 for i in range(junk_len))
        verdict = reply.feed(junk + frame[:cut])
        assert verdict is None, junk_len
        verdict = reply.feed(frame[cut:])
        assert verdict is not None and reply.frame_bytes == frame, junk_len
        assert verdict[0].seq == 42 and verdict[0].wl_fm == tuple(u * 100 for u in units)


# --------------------------------------------------------------------------------------------
# Single-bit corruption: what docs/protocol.md promises ("Plausibility gate")
# --------------------------------------------------------------------------------------------

MOD = 1 << 32
PERIOD_US = 1000


def _wl(k: int) -> tuple[int, ...]:
    return tuple(1_530_000_000 + 5_000_000 * c + 3_000 * k for c in range(5))


def _sessions_lost_and_restarts(delivered: list[P.Frame], session_of: dict[P.Frame, int]
                                ) -> tuple[int, int]:
    """Counter values missing between delivered frames of one device session, and the number
    of session changes among the delivered frames."""
    lost, restarts = 0, 0
    for a, b in zip(delivered, delivered[1:]):
        if session_of[a] != session_of[b]:
            restarts += 1
        else:
            lost += (b.seq - a.seq) % MOD - 1
    return lost, restarts


@settings(max_examples=300, deadline=None, derandomize=True)
@given(data=st.data(), timed=st.booleans(),
       seq0=st.sampled_from([10, 4_000, MOD - 7, 0x7FFF_FFF0]),
       n=st.integers(12, 40))
def test_gate_single_bit_flip_is_never_delivered_and_moves_no_counter(data, timed, seq0, n):
    """A stream (device time or none; drops when timed; maybe one device restart) with one bit
    of one frame's counter or timestamp flipped: every intact frame is delivered, nothing else,
    and the counters are those of the intact stream."""
    restart_at = data.draw(st.one_of(st.none(), st.integers(4, n - 4)), label="restart_at")
    bad = data.draw(st.integers(3, n - 3).filter(
        lambda i: restart_at is None or abs(i - restart_at) >= 3), label="bad")
    field = data.draw(st.sampled_from(["seq", "t_us"] if timed else ["seq"]), label="field")
    # Timestamps are u64; a flip below half a period cannot be told from jitter.
    bit = data.draw(st.integers(0, 31) if field == "seq" else st.integers(9, 63), label="bit")
    drops = set(data.draw(st.lists(st.integers(3, n - 1), max_size=n // 4), label="drops")
                ) if timed else set()
    drops -= {bad, bad + 1}
    if restart_at is not None:
        drops -= set(range(restart_at - 1, restart_at + 3))
    sent, session_of = [], {}
    seq, t = seq0, 5_000_000
    for k in range(n):
        if k == restart_at:
            seq -= data.draw(st.integers(2, 1 << 30), label="restart_back")
            if timed and data.draw(st.booleans(), label="clock_restarts"):
                t = data.draw(st.integers(0, t - 1), label="restart_t")
        fr = P.Frame(seq % MOD, t if timed else -1, _wl(k))
        session_of[fr] = int(restart_at is not None and k >= restart_at)
        if k not in drops:
            sent.append(fr)
        seq, t = seq + 1, t + PERIOD_US
    i = next(j for j, f in enumerate(sent) if f.wl_fm == _wl(bad))
    good = sent[i]
    damaged = P.Frame(good.seq ^ (1 << bit), good.t_us, good.wl_fm) if field == "seq" else \
        P.Frame(good.seq, good.t_us ^ (1 << bit), good.wl_fm)
    g = P.FrameGate()
    delivered = []
    for fr in sent[:i] + [damaged] + sent[i + 1:]:
        delivered += g.push(fr) or []
    intact = sent[:i] + sent[i + 1:]
    assert delivered == intact
    lost, restarts = _sessions_lost_and_restarts(delivered, session_of)
    assert g.stats.lost_frames == lost
    assert g.stats.seq_restarts == restarts == int(restart_at is not None)
    assert (g.stats.implausible_frames, g.stats.seq_jumps, g.stats.duplicates) == (1, 0, 0)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(bad=st.integers(2, 9), bit=st.integers(0, 8 * P.fispec_frame_size(5) - 1),
       counter0=st.integers(0, MOD - 1))
def test_fispec_single_bit_flip_anywhere_in_a_reply(bad, bit, counter0):
    """FiSpec replies (no checksum) polled once per sample, one bit of one reply flipped
    anywhere: no frame is delivered under a wrong counter or out of order, the counters count
    exactly the replies not delivered, and a reply whose counter was hit is not delivered."""
    replies, sent = [], {}
    for k in range(12):
        units = [v // 100 for v in _wl(k)]
        raw = P.encode_fispec_frame(units, [12000] * 5, 2500, counter0 + k)
        sent[(counter0 + k) % MOD] = P.Frame((counter0 + k) % MOD, -1, tuple(u * 100 for u in units))
        if k == bad:
            b = bytearray(raw)
            b[bit // 8] ^= 1 << (bit % 8)
            raw = bytes(b)
        replies.append(raw)
    g = P.FrameGate()
    delivered = []
    for raw in replies:
        delivered += P.FiSpecReply(5, g).feed(raw) or []
    seqs = [f.seq for f in delivered]
    assert all(f.seq in sent for f in delivered)
    assert all((b - a) % MOD < MOD // 2 for a, b in zip(seqs, seqs[1:]))  # in order
    assert len(set(seqs)) == len(seqs)
    counter_field = range(8 * (8 * 5 + 4), 8 * (8 * 5 + 8))
    if bit in counter_field:
        assert (counter0 + bad) % MOD not in seqs
    for f in delivered:
        if f.seq != (counter0 + bad) % MOD:
            assert f == sent[f.seq]
    # Only the damaged reply may be missing, and it is counted.
    assert len(delivered) >= 11
    assert g.stats.lost_frames == 12 - len(delivered)
    assert g.stats.seq_restarts == g.stats.seq_jumps == g.stats.duplicates == 0


def test_fispec_flipped_counter_bit_the_audit_reproduction():
    """Counters 100..104, bit 12 of the third flipped: that reply is refused, the others are
    delivered in order, one counter value is missing and nothing restarted."""
    gate = P.FrameGate()
    out = []
    for c in range(100, 105):
        counter = c ^ (1 << 12) if c == 102 else c
        raw = P.encode_fispec_frame([v // 100 for v in _wl(c)], [12000] * 5, 2500, counter)
        out += P.FiSpecReply(5, gate).feed(raw) or []
    assert [f.seq for f in out] == [100, 101, 103, 104]
    assert (gate.stats.lost_frames, gate.stats.seq_restarts, gate.stats.implausible_frames) == \
        (1, 0, 1)


class _ScriptedFiSpec:
    """Stands in for a FiSpec device's serial link: answers each ``P>`` with the next reply."""

    def __init__(self, replies: list[bytes]) -> None:
        self.replies = list(replies)
        self.pending = b""
        self.is_open = True
        self.stats = R.LinkStats()

    def discard_input(self) -> None:
        self.pending = b""

    def write(self, data: bytes) -> bool:
        if data == P.CMD_PEAKS and self.replies:
            self.pending = self.replies.pop(0)
        return True

    def read(self, wait: float) -> bytes:
        out, self.pending = self.pending, b""
        return out


def test_fispec_reader_counts_no_loss_across_a_device_restart():
    """Counters 100..103, then the device restarts at 5: every reply is delivered once the
    next confirms it, at once, and no poll counts as lost or bad."""
    counters = [100, 101, 102, 103, 5, 6, 7, 8]
    rd = R.FiSpecReader("loop://", channels=5, reply_timeout=0.05)
    rd.link = _ScriptedFiSpec([P.encode_fispec_frame([v // 100 for v in _wl(k)], [12000] * 5,
                                                     2500, c) for k, c in enumerate(counters)])
    got = []
    for _ in counters:
        got += rd.poll() or []
    assert [f.seq for f in got] == counters
    s = rd.stats()
    assert (s["frames"], s["replies"], s["bad_replies"], s["timeouts"], s["lost_frames"]) == \
        (8, 8, 0, 0, 0)
    assert (s["seq_restarts"], s["skipped_samples"], s["implausible_frames"]) == (1, 0, 0)
