"""Receiver of ``fbgforce stream --publish udp://HOST:PORT`` in plain Python (no fbgforce, no
numpy: copy it into a controller). Datagram layout: docs/protocol.md, "Estimate datagram".

    python receiver.py 127.0.0.1 9870 [COUNT]

Prints one CSV line per valid datagram (seq,sample_seq,t_us,status,contact,conf_q15,force_mN,
x_um,y_um) and, on stderr at the end, how many datagrams were bad, missing (publication counter
gaps), duplicated (the last counter again: dropped) and how often the publisher restarted (its
counter went backwards; counting goes on from there). The stream's status record (once a
second, docs/protocol.md "Status record") is printed on stderr as it arrives and counted.
"""
from __future__ import annotations

import socket
import struct
import sys
import zlib
from typing import NamedTuple

#: magic, version, size, seq, sample_seq, t_us, status, contact, reserved, conf_q15,
#: force_mN, x_um, y_um, crc32 -- little-endian, no padding: 48 bytes.
LAYOUT = struct.Struct("<4sHHIIqIBBHiiiI")
#: magic, version, size, seq, level, reserved[3], received, lost, reconnects, rate_mhz,
#: silent_ms, flags[8], tracker_offset_fm, tracker_bound_fm, tares, resets, failed,
#: digest[8], crc32 -- little-endian: 92 bytes.
STATUS = struct.Struct("<4sHHIB3xQQIII8HiiIII8sI")
LEVELS = ("OK", "WARN", "ERROR", "STALE")


class Estimate(NamedTuple):
    seq: int
    sample_seq: int
    t_us: int
    status: int
    contact: int
    conf_q15: int
    force_mN: int
    x_um: int
    y_um: int


def decode(data: bytes) -> Estimate | None:
    """One datagram, or ``None`` if it is not a valid version-1 estimate."""
    if len(data) != LAYOUT.size:
        return None
    (magic, version, size, seq, sample_seq, t_us, status, contact, _reserved, conf, force,
     x, y, crc) = LAYOUT.unpack(data)
    if magic != b"FBGO" or version != 1 or size != LAYOUT.size:
        return None
    if zlib.crc32(data[:44]) & 0xFFFFFFFF != crc:
        return None
    return Estimate(seq, sample_seq, t_us, status, contact, conf, force, x, y)


class Status(NamedTuple):
    seq: int
    level: int
    received: int
    lost: int
    reconnects: int
    rate_mhz: int
    silent_ms: int
    flags: tuple[int, ...]
    tracker_offset_fm: int
    tracker_bound_fm: int
    tares: int
    resets: int
    failed: int
    digest: str


def decode_status(data: bytes) -> Status | None:
    """One status record, or ``None`` if it is not a valid version-1 one."""
    if len(data) != STATUS.size:
        return None
    magic, version, size, seq, level, *rest = STATUS.unpack(data)
    if magic != b"FBGS" or version != 1 or size != STATUS.size:
        return None
    if zlib.crc32(data[:-4]) & 0xFFFFFFFF != rest[-1]:
        return None
    received, lost, reconnects, rate, silent = rest[:5]
    flags = tuple(rest[5:13])
    offset, bound, tares, resets, failed, digest = rest[13:19]
    return Status(seq, level, received, lost, reconnects, rate, silent, flags, offset, bound,
                  tares, resets, failed, digest.hex())


def follow(last: int | None, seq: int) -> tuple[str, int]:
    """What publication counter ``seq`` means after ``last`` (``None``: nothing yet).

    ``("next", gap)``: a new estimate, ``gap`` datagrams missing before it (a forward step of
    less than 2**31); ``("duplicate", 0)``: the last counter again (drop it); ``("restart", 0)``:
    any other backward step, the publisher started again.
    """
    if last is None:
        return "next", 0
    step = (seq - last) & 0xFFFFFFFF
    if step == 0:
        return "duplicate", 0
    if step >= 1 << 31:
        return "restart", 0
    return "next", step - 1


def main(argv: list[str]) -> int:
    if len(argv) < 3:
        print(f"usage: {argv[0]} ADDRESS PORT [COUNT]", file=sys.stderr)
        return 2
    count = int(argv[3]) if len(argv) > 3 else -1
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sock.bind((argv[1], int(argv[2])))
    print("listening", file=sys.stderr, flush=True)
    got = bad = missing = duplicates = restarts = statuses = 0
    last = None
    try:
        while count < 0 or got < count:
            data = sock.recv(256)
            e = decode(data)
            if e is None:
                st = decode_status(data)
                if st is None:
                    bad += 1
                    continue
                statuses += 1
                print(f"status {st.seq}: {LEVELS[min(st.level, 3)]}, {st.rate_mhz / 1000:.1f} Hz, "
                      f"received {st.received}, lost {st.lost}, reconnects {st.reconnects}, "
                      f"silent {st.silent_ms} ms", file=sys.stderr, flush=True)
                continue
            what, gap = follow(last, e.seq)
            if what == "duplicate":
                duplicates += 1
                continue
            restarts += what == "restart"
            missing += gap
            last = e.seq
            got += 1
            print(",".join(str(v) for v in e))
    except KeyboardInterrupt:
        pass
    sys.stdout.flush()
    print(f"received {got}, bad {bad}, missing {missing}, duplicates {duplicates}, "
          f"restarts {restarts}, status records {statuses}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
