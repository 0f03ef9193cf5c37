"""Framing under attack: corrupted streams through the readers' decoders (prints a table).

    python bench/bench_framing.py [--frames 1000000] [--seed 0] [--json FILE]

For each protocol a seeded generator writes a stream of frames whose peaks wander as a
fingertip's do, corrupts it, cuts it into random chunks and feeds it to exactly the decoding
code the readers run (no ports, so a million frames take seconds). Every delivered frame is
compared with what the device sent under that sequence number:

- ``good``: delivered and equal to the frame sent; ``intact``: frames that reached the line
  unharmed (the most a decoder can deliver);
- ``wrong``: delivered but not what was sent (the goal is 0);
- ``lost_reported`` vs ``lost_true``: the reader's lost-frame count against the frames really
  missing between the first and the last delivered one (``lost_error`` = difference).

Protocols and faults:

- ``native v2`` (CRC-32 + gate) and, for comparison, ``native v1`` (CRC-16 + gate) and
  ``native v1, CRC only`` (the decoder without plausibility rules). Faults per frame: drop,
  1-3 bit flips, a burst of up to 32 flipped bits, truncation (the next frame follows the cut),
  a burst of garbage before the frame, and garbage made of sync words and valid-looking
  headers.
- ``fispec``: per poll, junk before the reply (sometimes ending in ``Ende``), a payload that
  contains ``Ende`` (in an amplitude) with the reply split right after it, truncated and lost
  replies, junk-only replies. FiSpec frames carry no checksum, so bit flips inside a frame are
  not part of this model (nothing could detect them).
- ``fispec, 1 bit flipped``: replies polled once per sample, 1.7 % of them with one bit
  flipped anywhere (the audit's model of a line without a checksum); a flipped wavelength bit
  the window and step rules cannot see is counted apart (``wl_flips_passed``), not as wrong.
- ``hyperion``: TCP delivers bytes intact, so the faults are the ones TCP has: messages the
  device drops (serial number gaps), connections cut in mid-message (the reader reconnects and
  starts a fresh decoder), device restarts (serial number back to 0).
"""
from __future__ import annotations

import argparse
import json
import random
import sys
import time
from typing import Any, Callable

import numpy as np

from fbgforce.interrogator import protocol as P

CHANNELS = 5


def _walk(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 5) wavelengths in fm: FBGs near 1530..1550 nm moving a few pm per sample."""
    base = np.array([1_530_000_000, 1_535_000_000, 1_540_000_000, 1_545_000_000, 1_550_000_000])
    steps = rng.integers(-5_000, 5_001, size=(n, CHANNELS))
    return base + np.cumsum(steps, axis=0)


def _chunks(data: bytes, rng: np.random.Generator) -> list[bytes]:
    """``data`` cut into random pieces of 1..4096 bytes (how reads return a stream)."""
    sizes = rng.integers(1, 4097, size=len(data) // 1024 + 8)
    while sizes.sum() < len(data):
        sizes = np.concatenate([sizes, rng.integers(1, 4097, size=len(data) // 1024 + 8)])
    ends = np.minimum(np.cumsum(sizes), len(data))
    starts = np.concatenate([[0], ends[:-1]])
    return [data[a:b] for a, b in zip(starts.tolist(), ends.tolist()) if b > a]


def _score(delivered: list[P.Frame], truth: Callable[[int], P.Frame | None], lost_reported: int,
           intact: int, n: int, seconds: float, **extra: Any) -> dict[str, Any]:
    good = wrong = 0
    for f in delivered:
        if truth(f.seq) == f:
            good += 1
        else:
            wrong += 1
    seqs = [f.seq for f in delivered if truth(f.seq) == f]
    lost_true = (max(seqs) - min(seqs) + 1 - len(seqs)) if seqs else 0
    return {"frames": n, "intact": intact, "good": good, "wrong": wrong,
            "lost_reported": lost_reported, "lost_true": lost_true,
            "lost_error": lost_reported - lost_true, "seconds": round(seconds, 2), **extra}


# --------------------------------------------------------------------------------------------
# Native frame
# --------------------------------------------------------------------------------------------

def run_native(n: int, seed: int = 0, version: int = P.PROTOCOL_VERSION, gate: bool = True,
               fault_rate: float = 0.3) -> dict[str, Any]:
    """Corrupt ``n`` native frames and decode them; see the module docstring."""
    rng = np.random.default_rng([seed, version, int(gate)])
    wl = _walk(n, rng)
    t_us = np.arange(n, dtype=np.int64) * 1000 + 5_000_000
    kinds = rng.choice(7, size=n, p=[1 - fault_rate] + [fault_rate / 6] * 6)
    size = P.frame_size(CHANNELS, version)
    line = bytearray()
    intact = 0
    for k in range(n):
        fr = P.encode_frame(k, int(t_us[k]), wl[k].tolist(), version)
        kind = kinds[k]
        if kind == 0:
            line += fr
            intact += 1
        elif kind == 1:  # dropped
            continue
        elif kind == 2:  # 1-3 bit flips
            b = bytearray(fr)
            for bit in rng.choice(size * 8, size=int(rng.integers(1, 4)), replace=False):
                b[bit // 8] ^= 1 << (bit % 8)
            line += b
        elif kind == 3:  # burst of up to 32 flipped bits
            b = bytearray(fr)
            start = int(rng.integers(0, size * 8 - 32))
            length = int(rng.integers(2, 33))
            for bit in range(start, start + length):  # the burst's first and last bits flip
                if bit in (start, start + length - 1) or rng.random() < 0.5:
                    b[bit // 8] ^= 1 << (bit % 8)
            line += b
        elif kind == 4:  # cut short: the next frame's bytes follow
            line += fr[:int(rng.integers(1, size - 1))]
        elif kind == 5:  # random garbage, then the intact frame
            line += rng.integers(0, 256, size=int(rng.integers(1, 65)), dtype=np.uint8).tobytes()
            line += fr
            intact += 1
        else:  # garbage that looks like frames: sync, valid version and count, random rest
            fake = bytearray(rng.integers(0, 256, size=size, dtype=np.uint8).tobytes())
            fake[:4] = P.SYNC + bytes([version, CHANNELS])
            line += fake[:int(rng.integers(4, size + 1))]
            line += fr
            intact += 1
    dec = P.FrameDecoder(CHANNELS, P.FrameGate() if gate else None)
    got: list[P.Frame] = []
    t0 = time.perf_counter()
    data = bytes(line)
    for chunk in _chunks(data, rng):
        got += dec.feed(chunk)
    dec.flush()
    seconds = time.perf_counter() - t0
    if gate:
        lost = dec.gate.stats.lost_frames  # type: ignore[union-attr]
    else:  # the reader's old rule: every forward step counted, on whatever passed the CRC
        from fbgforce.interrogator.reader import SequenceTracker

        trk = SequenceTracker()
        got = [f for f in got if trk.accept(f.seq)]
        lost = trk.stats.lost_frames

    def truth(seq: int) -> P.Frame | None:
        if not 0 <= seq < n:
            return None
        return P.Frame(seq, int(t_us[seq]), tuple(int(v) for v in wl[seq]))

    label = f"native v{version}" + ("" if gate else ", CRC only")
    return _score(got, truth, lost, intact, n, seconds, protocol=label,
                  crc_errors=dec.stats.crc_errors,
                  implausible=dec.gate.stats.implausible_frames if gate  # type: ignore[union-attr]
                  else 0)


# --------------------------------------------------------------------------------------------
# FiSpec polling
# --------------------------------------------------------------------------------------------

ENDE_AMPLITUDE = int.from_bytes(P.FISPEC_TRAILER, "little")


class _TrailerOnlyReply:
    """The rule readers used before :class:`~fbgforce.interrogator.protocol.FiSpecReply`:
    the first ``Ende``-terminated tail of the right length is the frame (for comparison)."""

    def __init__(self, tracker: Any) -> None:
        self.buf = bytearray()
        self.tracker = tracker
        self.refused = 0

    def feed(self, chunk: bytes) -> list[P.Frame] | None:
        self.buf += chunk
        size = P.fispec_frame_size(CHANNELS)
        if len(self.buf) < size or not self.buf.endswith(P.FISPEC_TRAILER):
            return None
        fr = P.decode_fispec_frame(bytes(self.buf[-size:]), CHANNELS)
        assert fr is not None  # the length and trailer were just checked
        frame = fr.to_frame()
        return [frame] if self.tracker.accept(frame.seq) else []


def run_fispec(n: int, seed: int = 0, fault_rate: float = 0.3, gate: bool = True
               ) -> dict[str, Any]:
    """``n`` polls of a FiSpec device over a hostile line; see the module docstring.
    ``gate=False`` runs the trailer-only rule instead, for comparison."""
    from fbgforce.interrogator.reader import SequenceTracker

    tracker = SequenceTracker()
    rng = np.random.default_rng([seed, 11])
    wl_fm = _walk(n, rng)
    units = wl_fm // (P.FM_PER_NM // P.FISPEC_UNITS_PER_NM)
    counters = 1000 + np.cumsum(rng.integers(1, 4, size=n))  # polls skip a sample now and then
    size = P.fispec_frame_size(CHANNELS)
    use_gate = gate
    gate = P.FrameGate()  # type: ignore[assignment]
    got: list[P.Frame] = []
    sent: dict[int, P.Frame] = {}
    intact = 0
    refused = 0
    r = random.Random(seed)  # per-call cheap: this loop draws a dozen numbers per poll
    t0 = time.perf_counter()
    for k in range(n):
        amp = [12000] * CHANNELS
        ende_at = None
        if r.random() < 0.5:  # the payload contains "Ende" (an amplitude that spells it)
            ch = r.randrange(CHANNELS)
            amp[ch] = ENDE_AMPLITUDE
            ende_at = 8 * ch + 8  # just after the amplitude's bytes
        frame = P.encode_fispec_frame(units[k].tolist(), amp, 2500, int(counters[k]))
        counter = int(counters[k])
        sent[counter] = P.Frame(counter, -1, tuple(int(u) * 100 for u in units[k]))
        kind = r.randrange(5) if r.random() < fault_rate else -1
        junk = b""
        if kind in (0, 1):  # junk before the reply, sometimes ending in "Ende"
            junk = r.randbytes(r.randrange(1, 2 * size))
            if kind == 1:
                junk += P.FISPEC_TRAILER
        if kind == 2:  # truncated reply
            stream = frame[:r.randrange(1, size)]
        elif kind == 3:  # no reply at all
            stream = b""
        elif kind == 4:  # only junk, long enough and ending in the trailer
            stream = r.randbytes(size + r.randrange(size)) + P.FISPEC_TRAILER
        else:
            stream = junk + frame
            intact += 1
        # Chunks: random cuts, plus one right after an "Ende" inside the payload.
        cuts = {r.randrange(1, max(2, len(stream))) for _ in range(3)}
        if ende_at is not None and kind not in (2, 3, 4):
            cuts.add(len(junk) + ende_at)
        reply = P.FiSpecReply(CHANNELS, gate) if use_gate else _TrailerOnlyReply(tracker)
        prev = 0
        for c in sorted(cuts) + [len(stream)]:
            if c <= prev:
                continue
            verdict = reply.feed(stream[prev:c])
            prev = c
            if verdict is not None:
                got += verdict
                break
        refused += reply.refused
    seconds = time.perf_counter() - t0
    lost = (gate.stats.lost_frames if use_gate  # type: ignore[attr-defined]
            else tracker.stats.lost_frames)
    return _score(got, sent.get, lost, intact, n, seconds,
                  protocol="fispec" + ("" if use_gate else ", trailer only"), crc_errors=0,
                  implausible=gate.stats.implausible_frames,  # type: ignore[attr-defined]
                  refused_candidates=refused)


def run_fispec_flips(n: int, seed: int = 0, flip_rate: float = 0.017) -> dict[str, Any]:
    """``n`` FiSpec replies polled once per sample (consecutive counters), one random bit of
    ``flip_rate`` of them flipped anywhere in the frame (the audit's model of a line without
    a checksum). ``wrong``: delivered frames not what was sent under their counter, except
    ``wl_flips_passed``: a flipped wavelength bit the window and step rules cannot see (no
    checksum can be had); ``lost``: counter values missing between delivered frames."""
    rng = np.random.default_rng([seed, 17])
    wl_fm = _walk(n, rng)
    units = wl_fm // (P.FM_PER_NM // P.FISPEC_UNITS_PER_NM)
    flips = np.flatnonzero(rng.random(n) < flip_rate)
    bits = rng.integers(0, 8 * P.fispec_frame_size(CHANNELS), size=flips.size)
    flipped = dict(zip(flips.tolist(), bits.tolist()))
    gate = P.FrameGate()
    got: list[P.Frame] = []
    sent: dict[int, P.Frame] = {}
    t0 = time.perf_counter()
    for k in range(n):
        counter = 1000 + k
        raw = P.encode_fispec_frame(units[k].tolist(), [12000] * CHANNELS, 2500, counter)
        sent[counter] = P.Frame(counter, -1, tuple(int(u) * 100 for u in units[k]))
        if k in flipped:
            b = bytearray(raw)
            b[flipped[k] // 8] ^= 1 << (flipped[k] % 8)
            raw = bytes(b)
        got += P.FiSpecReply(CHANNELS, gate).feed(raw) or []
    seconds = time.perf_counter() - t0

    def wl_bit(k: int) -> bool:  # the flipped bit of reply k lies in a wavelength
        return k in flipped and flipped[k] < 64 * CHANNELS and flipped[k] % 64 < 32

    good = sum(1 for f in got if sent.get(f.seq) == f)
    wl_passed = sum(1 for f in got if f.seq in sent and sent[f.seq] != f and wl_bit(f.seq - 1000)
                    and sent[f.seq].seq == f.seq)
    seqs = [f.seq for f in got if f.seq in sent and (sent[f.seq] == f or wl_bit(f.seq - 1000))]
    lost_true = max(seqs) - min(seqs) + 1 - len(seqs) if seqs else 0
    lost = gate.stats.lost_frames
    return {"frames": n, "intact": n - int(flips.size), "good": good,
            "wrong": len(got) - good - wl_passed, "wl_flips_passed": wl_passed,
            "flipped": int(flips.size), "lost_reported": lost, "lost_true": lost_true,
            "lost_error": lost - lost_true, "seconds": round(seconds, 2),
            "protocol": "fispec, 1 bit flipped", "crc_errors": 0,
            "implausible": gate.stats.implausible_frames,
            "restarts": gate.stats.seq_restarts}


# --------------------------------------------------------------------------------------------
# Hyperion peak stream
# --------------------------------------------------------------------------------------------

def run_hyperion(n: int, seed: int = 0, fault_rate: float = 0.3) -> dict[str, Any]:
    """``n`` peak-stream messages with TCP's faults; see the module docstring."""
    from fbgforce.interrogator import hyperion as H

    rng = np.random.default_rng([seed, 13])
    wl_fm = _walk(n, rng)
    mapping = H.PeakMap.default(CHANNELS)
    t0_s = 1_700_000_000
    kinds = rng.choice(4, size=n, p=[1 - fault_rate, fault_rate * 0.66, fault_rate * 0.33,
                                     fault_rate * 0.01])
    sessions: list[bytearray] = [bytearray()]
    truth: dict[tuple[int, int], P.Frame] = {}
    serial = 0
    session = 0
    intact = 0
    for k in range(n):
        kind = kinds[k]
        if kind == 3:  # device restart: new session, serial number from 0
            sessions.append(bytearray())
            session += 1
            serial = 0
        t_ns = k * 1_000_000
        msg = H.encode_stream_message(H.encode_peaks(
            serial, t0_s + t_ns // 1_000_000_000, t_ns % 1_000_000_000,
            mapping.to_channels((wl_fm[k] / P.FM_PER_NM).tolist(), 4)))
        frame = P.Frame(serial & 0xFFFFFFFF, (t0_s * 1_000_000_000 + t_ns) // 1000,
                        tuple(int(v) for v in wl_fm[k]))
        truth[(session, frame.seq)] = frame
        serial += 1
        if kind == 1:  # dropped by the device
            continue
        if kind == 2:  # connection cut in mid-message; the reader reconnects
            sessions[-1] += msg[:int(rng.integers(1, len(msg)))]
            sessions.append(bytearray())
            continue
        sessions[-1] += msg
        intact += 1
    reader_gate = P.FrameGate()
    got: list[tuple[int, P.Frame]] = []
    t0 = time.perf_counter()
    for s_index, data in enumerate(sessions):
        dec = H.PeakStreamDecoder()  # each connection starts at a message boundary
        for chunk in _chunks(bytes(data), rng):
            for msg in dec.feed(chunk):
                for f in reader_gate.push(mapping.frame(msg)) or []:
                    got.append((s_index, f))
        dec.flush()
    seconds = time.perf_counter() - t0
    # Match delivered frames to what was sent by timestamp (a restart reuses serial numbers,
    # never timestamps).
    by_time = {f.t_us: (key[0], f) for key, f in truth.items()}
    delivered = [f for _, f in got]
    good_keys = [(by_time[f.t_us][0], f.seq) for f in delivered
                 if f.t_us in by_time and by_time[f.t_us][1] == f]
    good = len(good_keys)
    # True loss: within each device session, frames missing between its first and last
    # delivered one (what precedes or follows a restart cannot be known to be missing).
    per_session: dict[int, list[int]] = {}
    for sess, seq in good_keys:
        per_session.setdefault(sess, []).append(seq)
    missing = sum(max(v) - min(v) + 1 - len(v) for v in per_session.values())
    return {"frames": n, "intact": intact, "good": good, "wrong": len(delivered) - good,
            "lost_reported": reader_gate.stats.lost_frames, "lost_true": missing,
            "lost_error": reader_gate.stats.lost_frames - missing,
            "seconds": round(seconds, 2), "protocol": "hyperion", "crc_errors": 0,
            "implausible": reader_gate.stats.implausible_frames,
            "restarts": reader_gate.stats.seq_restarts, "restarts_true": len(per_session) - 1}


def run_all(n: int, seed: int = 0) -> list[dict[str, Any]]:
    return [run_native(n, seed, 2), run_native(n, seed, 1), run_native(n, seed, 1, gate=False),
            run_fispec(n, seed), run_fispec(n, seed, gate=False), run_fispec_flips(n, seed),
            run_hyperion(n, seed)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000, help="frames per protocol")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    args = ap.parse_args(argv)
    rows = []
    print(f"{'protocol':<22} {'frames':>9} {'intact':>9} {'good':>9} {'wrong':>6} "
          f"{'lost rep':>9} {'lost true':>9} {'lost err':>8} {'s':>6}")
    for fn in (lambda: run_native(args.frames, args.seed, 2),
               lambda: run_native(args.frames, args.seed, 1),
               lambda: run_native(args.frames, args.seed, 1, gate=False),
               lambda: run_fispec(args.frames, args.seed),
               lambda: run_fispec(args.frames, args.seed, gate=False),
               lambda: run_fispec_flips(args.frames, args.seed),
               lambda: run_hyperion(args.frames, args.seed)):
        r = fn()
        rows.append(r)
        print(f"{r['protocol']:<22} {r['frames']:>9} {r['intact']:>9} {r['good']:>9} "
              f"{r['wrong']:>6} {r['lost_reported']:>9} {r['lost_true']:>9} "
              f"{r['lost_error']:>8} {r['seconds']:>6.1f}", flush=True)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
