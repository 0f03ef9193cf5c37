"""Tare or reset a running ``fbgforce stream --control udp://HOST:PORT`` in plain Python (no
fbgforce, no numpy: copy it into a controller). Datagram layouts: docs/protocol.md,
"Control datagram".

    python control.py 127.0.0.1 9871 tare [COUNT]

Sends the command (COUNT times, one after the other; default once) and prints the final
answer of each as one CSV line: seq,result,command,change_fm1..5,samples,message. A command
is sent again every 0.1 s until its final answer (DONE, FAILED or REFUSED) arrives; the
stream applies it once however often it arrives (sequence numbers). Exit 0 when every
command was DONE, 1 when one failed or was refused, 2 when one got no answer in time.
"""
from __future__ import annotations

import os
import socket
import struct
import sys
import time
import zlib
from typing import NamedTuple

#: magic, version, size, session, seq, command, reserved, crc32: 24 bytes.
COMMAND = struct.Struct("<4sHHIIHHI")
#: magic, version, size, session, seq, command, result, change_fm[5], samples, message,
#: crc32: 124 bytes.
ACK = struct.Struct("<4sHHIIHH5iI76sI")
COMMANDS = {"tare": 1, "reset": 2}
RESULTS = ("DONE", "FAILED", "REFUSED", "PENDING")
PENDING = 3


class Ack(NamedTuple):
    session: int
    seq: int
    command: int
    result: int
    change_fm: tuple[int, ...]
    samples: int
    message: str


def encode_command(session: int, seq: int, command: int) -> bytes:
    body = COMMAND.pack(b"FBGC", 1, COMMAND.size, session, seq, command, 0, 0)[:-4]
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


def decode_ack(data: bytes) -> Ack | None:
    """One acknowledgement, or ``None`` if it is not a valid version-1 one."""
    if len(data) != ACK.size:
        return None
    magic, version, size, session, seq, command, result, *rest = ACK.unpack(data)
    change, samples, message, crc = tuple(rest[:5]), rest[5], rest[6], rest[7]
    if magic != b"FBGA" or version != 1 or size != ACK.size:
        return None
    if zlib.crc32(data[:-4]) & 0xFFFFFFFF != crc:
        return None
    return Ack(session, seq, command, result, change, samples,
               message.rstrip(b"\0").decode("utf-8", "replace"))


class Client:
    """Sends commands to one stream; the session is random, so a restarted client is a new
    one to the stream."""

    def __init__(self, host: str, port: int, session: int | None = None) -> None:
        self.address = (host, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.session = int.from_bytes(os.urandom(4), "little") if session is None else session
        self.seq = 0

    def send(self, command: str, timeout: float = 10.0, resend: float = 0.1) -> Ack | None:
        """Send ``command`` until its final answer (``None`` after ``timeout`` seconds)."""
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        data = encode_command(self.session, self.seq, COMMANDS[command])
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.sock.sendto(data, self.address)
            wait_until = min(end, time.monotonic() + resend)
            while True:
                left = wait_until - time.monotonic()
                if left <= 0:
                    break
                self.sock.settimeout(left)
                try:
                    ack = decode_ack(self.sock.recv(512))
                except socket.timeout:
                    break
                if ack is None or ack.session != self.session or ack.seq != self.seq:
                    continue  # garbage, or the late answer of an earlier command
                if ack.result != PENDING:
                    return ack
        return None

    def close(self) -> None:
        self.sock.close()


def main(argv: list[str]) -> int:
    if len(argv) < 4 or argv[3] not in COMMANDS:
        print(f"usage: {argv[0]} ADDRESS PORT tare|reset [COUNT]", file=sys.stderr)
        return 2
    count = int(argv[4]) if len(argv) > 4 else 1
    client = Client(argv[1], int(argv[2]))
    code = 0
    try:
        for _ in range(count):
            ack = client.send(argv[3])
            if ack is None:
                print(f"no answer to {argv[3]} #{client.seq}", file=sys.stderr)
                return 2
            print(f"{ack.seq},{RESULTS[ack.result]},{ack.command},"
                  + ",".join(str(v) for v in ack.change_fm)
                  + f",{ack.samples},{ack.message}", flush=True)
            if ack.result != 0:
                code = 1
    finally:
        client.close()
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv))
