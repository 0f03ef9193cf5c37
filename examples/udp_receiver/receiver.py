"""Receiver of ``fbgforce stream --publish udp://HOST:PORT`` in plain Python (no fbgforce, no
numpy: copy it into a controller). Datagram layout: docs/protocol.md, "Estimate datagram".

    python receiver.py 127.0.0.1 9870 [COUNT]

Prints one CSV line per valid datagram (seq,sample_seq,t_us,status,contact,conf_q15,force_mN,
x_um,y_um) and, on stderr at the end, how many datagrams were bad or missing.
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


def main(argv: list[str]) -> int:
    if len(argv) < 3:
        print(f"usage: {argv[0]} ADDRESS PORT [COUNT]", file=sys.stderr)
        return 2
    count = int(argv[3]) if len(argv) > 3 else -1
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sock.bind((argv[1], int(argv[2])))
    print("listening", file=sys.stderr, flush=True)
    got = bad = missing = 0
    expected = None
    try:
        while count < 0 or got < count:
            e = decode(sock.recv(256))
            if e is None:
                bad += 1
                continue
            if expected is not None and e.seq != expected:
                missing += (e.seq - expected) & 0xFFFFFFFF
            expected = (e.seq + 1) & 0xFFFFFFFF
            got += 1
            print(",".join(str(v) for v in e))
    except KeyboardInterrupt:
        pass
    sys.stdout.flush()
    print(f"received {got}, bad {bad}, missing {missing}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
