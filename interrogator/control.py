"""Tare and reset over UDP while streaming (``fbgforce stream --control udp://HOST:PORT``).

A controller sends a 24-byte command datagram to the port the stream listens on; the stream
answers the sender with a 124-byte acknowledgement, at once (``PENDING``: received, the tare
window is filling) and once the command is applied or has failed (``DONE`` / ``FAILED``, with
the baseline's change). Layouts (little-endian, docs/protocol.md, "Control datagram"):

Command, :data:`COMMAND_DTYPE`::

    0  magic   "FBGC"      4  version u16 = 1   6  size u16 = 24
    8  session u32 (the client's, random at its start)   12 seq u32 (+1 per new command)
    16 command u16 (1 tare, 2 reset)   18 reserved u16 = 0   20 crc32 of bytes 0..19

Acknowledgement, :data:`ACK_DTYPE`::

    0  magic   "FBGA"      4  version u16 = 1   6  size u16 = 124
    8  session u32, 12 seq u32, 16 command u16: the command's, echoed
    18 result u16 (0 DONE, 1 FAILED, 2 REFUSED, 3 PENDING)
    20 change_fm i32[5]: the baseline's change per grating (FBG 1..4, T), fm (1/1000 pm)
    40 samples u32: samples averaged   44 message: UTF-8, NUL-padded, 76 bytes
    120 crc32 of bytes 0..119

Exactly once: a command is applied once per (sender address, session, seq). A datagram that
repeats a seq being applied is answered ``PENDING`` again, one that repeats a seq already
answered gets the same answer again (the last :data:`REMEMBERED` of each session are kept),
and a seq at or below the session's highest that is no longer remembered is refused, never
applied. So a client that sends again until it has the final answer loses no command and
applies none twice. Anything else that arrives (a wrong size, magic, version or CRC) is
dropped and counted, never answered: the port is safe to expose to garbage.
"""
from __future__ import annotations

import socket
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from fbgforce.errors import InputError

COMMAND_MAGIC = b"FBGC"
ACK_MAGIC = b"FBGA"
VERSION = 1
TARE, RESET = 1, 2
COMMAND_CODES = {"tare": TARE, "reset": RESET}
COMMAND_NAMES = {v: k for k, v in COMMAND_CODES.items()}
DONE, FAILED, REFUSED, PENDING = 0, 1, 2, 3
RESULT_NAMES = ("DONE", "FAILED", "REFUSED", "PENDING")
COMMAND_DTYPE = np.dtype({
    "names": ["magic", "version", "size", "session", "seq", "command", "reserved", "crc32"],
    "formats": ["S4", "<u2", "<u2", "<u4", "<u4", "<u2", "<u2", "<u4"],
    "offsets": [0, 4, 6, 8, 12, 16, 18, 20], "itemsize": 24})
ACK_DTYPE = np.dtype({
    "names": ["magic", "version", "size", "session", "seq", "command", "result", "change_fm",
              "samples", "message", "crc32"],
    "formats": ["S4", "<u2", "<u2", "<u4", "<u4", "<u2", "<u2", ("<i4", (5,)), "<u4", "S76",
                "<u4"],
    "offsets": [0, 4, 6, 8, 12, 16, 18, 20, 40, 44, 120], "itemsize": 124})
COMMAND_SIZE = COMMAND_DTYPE.itemsize
ACK_SIZE = ACK_DTYPE.itemsize
MESSAGE_BYTES = ACK_DTYPE.fields["message"][0].itemsize  # type: ignore[index]
#: Answers kept per session for repeats.
REMEMBERED = 64
#: Sessions kept (the least recently heard of is forgotten first).
MAX_SESSIONS = 256
#: Datagrams read per :meth:`ControlServer.poll`: a flood costs the stream a bounded time per
#: turn (the kernel's buffer drops the rest, as it would any datagram).
MAX_PER_POLL = 256


def _crc(body: bytes) -> bytes:
    return (zlib.crc32(body) & 0xFFFFFFFF).to_bytes(4, "little")


def encode_command(session: int, seq: int, command: int) -> bytes:
    """A command datagram."""
    rec = np.zeros(1, dtype=COMMAND_DTYPE)[0]
    rec["magic"], rec["version"], rec["size"] = COMMAND_MAGIC, VERSION, COMMAND_SIZE
    rec["session"], rec["seq"], rec["command"] = session & 0xFFFFFFFF, seq & 0xFFFFFFFF, command
    body = rec.tobytes()[:COMMAND_SIZE - 4]
    return body + _crc(body)


def decode_command(data: bytes) -> np.void | None:
    """A command datagram as a record of :data:`COMMAND_DTYPE`; ``None`` if its size, magic,
    version or CRC is wrong."""
    if len(data) != COMMAND_SIZE or not data.startswith(COMMAND_MAGIC):
        return None
    if zlib.crc32(data[:COMMAND_SIZE - 4]) & 0xFFFFFFFF != int.from_bytes(data[-4:], "little"):
        return None
    rec = np.frombuffer(data, dtype=COMMAND_DTYPE)[0]
    if rec["version"] != VERSION or rec["size"] != COMMAND_SIZE:
        return None
    return rec


def encode_ack(session: int, seq: int, command: int, result: int, message: str = "",
               change_fm: Any = (0, 0, 0, 0, 0), samples: int = 0) -> bytes:
    """An acknowledgement datagram (the message cut to :data:`MESSAGE_BYTES` bytes)."""
    rec = np.zeros(1, dtype=ACK_DTYPE)[0]
    rec["magic"], rec["version"], rec["size"] = ACK_MAGIC, VERSION, ACK_SIZE
    rec["session"], rec["seq"], rec["command"] = session, seq, command
    rec["result"], rec["samples"] = result, samples
    rec["change_fm"] = np.clip(np.asarray(change_fm, dtype=np.int64), -2**31, 2**31 - 1)
    text = message.encode("utf-8")[:MESSAGE_BYTES]
    rec["message"] = text.decode("utf-8", "ignore").encode("utf-8")  # no cut character
    body = rec.tobytes()[:ACK_SIZE - 4]
    return body + _crc(body)


def decode_ack(data: bytes) -> np.void | None:
    """An acknowledgement as a record of :data:`ACK_DTYPE`; ``None`` if invalid."""
    if len(data) != ACK_SIZE or not data.startswith(ACK_MAGIC):
        return None
    if zlib.crc32(data[:ACK_SIZE - 4]) & 0xFFFFFFFF != int.from_bytes(data[-4:], "little"):
        return None
    rec = np.frombuffer(data, dtype=ACK_DTYPE)[0]
    if rec["version"] != VERSION or rec["size"] != ACK_SIZE:
        return None
    return rec


@dataclass
class _Session:
    highest: int | None = None
    pending: set[int] = field(default_factory=set)
    answers: OrderedDict[int, bytes] = field(default_factory=OrderedDict)


def _after(seq: int, ref: int) -> bool:
    """``seq`` comes after ``ref`` in 32-bit serial order."""
    return 0 < (seq - ref) & 0xFFFFFFFF < 1 << 31


class ControlServer:
    """The stream's UDP control port: a :class:`~fbgforce.interrogator.stream.CommandSource`.

    Parameters
    ----------
    url
        ``udp://HOST:PORT`` to listen on (port 0: any free port; :attr:`url` says which).
    """

    def __init__(self, url: str) -> None:
        parts = urlsplit(url)
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme != "udp" or not parts.hostname or port is None:
            raise InputError(f"expected udp://HOST:PORT, not {url!r}", column="--control")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # Room for a burst between two of the stream's turns (the kernel may grant less).
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        try:
            self.sock.bind((parts.hostname, port))
        except OSError as exc:
            self.sock.close()
            raise InputError(f"cannot listen on {parts.hostname}:{port}: "
                             f"{exc.strerror or exc}", column="--control") from None
        self.sock.setblocking(False)
        host, bound = self.sock.getsockname()[:2]
        self.url = f"udp://{host}:{bound}"
        self._sessions: OrderedDict[tuple[Any, int], _Session] = OrderedDict()
        self.counts = {"received": 0, "bad": 0, "commands": 0, "repeats": 0, "refused": 0,
                       "answered": 0, "send_errors": 0}

    def _send(self, data: bytes, address: Any) -> None:
        try:
            self.sock.sendto(data, address)
        except OSError:
            self.counts["send_errors"] += 1

    def poll(self) -> list[tuple[str, Any]]:
        """New commands (name, token) from the datagrams that arrived; repeats and refusals
        are answered here."""
        out: list[tuple[str, Any]] = []
        for _ in range(MAX_PER_POLL):
            try:
                data, address = self.sock.recvfrom(2048)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. an ICMP error of an earlier answer: nothing to read
                continue
            self.counts["received"] += 1
            rec = decode_command(data)
            if rec is None:
                self.counts["bad"] += 1
                continue
            session_id, seq, code = int(rec["session"]), int(rec["seq"]), int(rec["command"])
            key = (address, session_id)
            sess = self._sessions.get(key)
            if sess is None:
                sess = self._sessions[key] = _Session()
                while len(self._sessions) > MAX_SESSIONS:
                    self._sessions.popitem(last=False)
            else:
                self._sessions.move_to_end(key)
            if seq in sess.answers:
                self.counts["repeats"] += 1
                self._send(sess.answers[seq], address)
                continue
            if seq in sess.pending:
                self.counts["repeats"] += 1
                self._send(encode_ack(session_id, seq, code, PENDING, "applying"), address)
                continue
            if sess.highest is not None and not _after(seq, sess.highest):
                self.counts["refused"] += 1
                self._send(encode_ack(session_id, seq, code, REFUSED,
                                      f"stale sequence number {seq} (session at "
                                      f"{sess.highest}): not applied"), address)
                continue
            sess.highest = seq
            if code not in COMMAND_NAMES:
                self.counts["refused"] += 1
                self._remember(sess, seq, encode_ack(session_id, seq, code, REFUSED,
                                                     f"unknown command {code} (1 tare, 2 reset)"))
                self._send(sess.answers[seq], address)
                continue
            self.counts["commands"] += 1
            sess.pending.add(seq)
            self._send(encode_ack(session_id, seq, code, PENDING, "applying"), address)
            out.append((COMMAND_NAMES[code], (address, session_id, seq, code)))
        return out

    @staticmethod
    def _remember(sess: _Session, seq: int, ack: bytes) -> None:
        sess.answers[seq] = ack
        while len(sess.answers) > REMEMBERED:
            sess.answers.popitem(last=False)

    def answer(self, cmd: Any) -> None:
        """Send a command's final answer to its sender and remember it for repeats."""
        address, session_id, seq, code = cmd.token
        change_fm = [int(round(v * 1000.0)) for v in cmd.change_pm]
        ack = encode_ack(session_id, seq, code, DONE if cmd.ok else FAILED, cmd.message,
                         change_fm, cmd.samples)
        sess = self._sessions.get((address, session_id))
        if sess is not None:
            sess.pending.discard(seq)
            self._remember(sess, seq, ack)
        self.counts["answered"] += 1
        self._send(ack, address)

    def stats(self) -> dict[str, Any]:
        """``url`` and the counters (``received`` datagrams, ``bad`` ones dropped,
        ``commands`` given to the estimator, ``repeats`` answered again, ``refused``,
        ``answered``, ``send_errors``)."""
        return {"url": self.url, **self.counts}

    def close(self) -> None:
        self.sock.close()
