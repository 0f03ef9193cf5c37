"""Luna / Micron Optics Hyperion interrogators (si155, x55 and relatives) over TCP.

The instrument speaks two TCP protocols (byte layouts in docs/protocol.md §4):

- the **command port** (51971): a request is an 8-byte header (options u8, 0 u8, command
  length u16, argument length u32) then the ASCII command (``#GetSerialNumber``) and its
  ASCII argument; the response an 8-byte header (status u8, type u8, message length u16,
  content length u32), an ASCII message and binary content;
- the **peak stream** (51972): the instrument pushes one message per acquisition, the same
  8-byte response header followed by a peaks record: a 24-byte peaks header (header length
  u16, version u16, reserved u32, serial number u64, timestamp seconds u32 and nanoseconds
  u32), an int16 peak count per channel, then every peak as a float64 wavelength in nm,
  channel after channel.

This module holds the codec (both directions), the :class:`PeakMap` that says which peak of
which channel is FBG 1..4 and T, a command client and :class:`HyperionReader`, the reader
``stream``/``record`` use for ``hyperion://HOST[:PORT]``. The device side (the emulator) is
:class:`fbgforce.interrogator.emulator.HyperionEmulator`.
"""
from __future__ import annotations

import json
import math
import select
import socket
import struct
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence
from urllib.parse import parse_qs, urlsplit

import numpy as np

from fbgforce.interrogator.protocol import FM_PER_NM, Frame, FrameGate

COMMAND_PORT = 51971
STREAM_PORT = 51972
#: Request (host -> instrument): options, reserved, command length, argument length.
REQUEST_HEADER = struct.Struct("<BBHI")
#: Response and stream message header: status (0 = success), type, message length, content
#: length.
RESPONSE_HEADER = struct.Struct("<BBHI")
#: Peaks record header: header length (24 + 2 * channels), version, reserved, serial number,
#: timestamp (whole seconds, nanoseconds).
PEAKS_HEADER = struct.Struct("<HHIQII")
PEAKS_VERSION = 1
SUCCESS = 0
#: Limits that make a stream header plausible (the largest instrument has 16 channels with
#: at most a few hundred peaks each).
MAX_CHANNELS = 64
MAX_CONTENT = 1 << 20
#: The channels of the emulated instrument (an si155 has 4).
DEFAULT_CHANNELS = 4
GRATINGS = ("wl1", "wl2", "wl3", "wl4", "wlT")


class HyperionError(Exception):
    """A command failed (status != 0) or the instrument could not be reached."""


def encode_request(command: str, argument: str = "", options: int = 0) -> bytes:
    """One command-port request."""
    cmd = command.encode("ascii")
    arg = argument.encode("ascii")
    return REQUEST_HEADER.pack(options, 0, len(cmd), len(arg)) + cmd + arg


def encode_response(content: bytes = b"", message: str = "", status: int = SUCCESS,
                    kind: int = 0) -> bytes:
    """One command-port response (also the frame of a stream message)."""
    msg = message.encode("ascii")
    return RESPONSE_HEADER.pack(status, kind, len(msg), len(content)) + msg + content


def encode_stream_message(peaks_record: bytes) -> bytes:
    """One peak-stream message: response header (no message) + peaks record."""
    return encode_response(peaks_record)


@dataclass(frozen=True)
class PeaksRecord:
    """A decoded peaks record: serial number, timestamp and the peaks of every channel (nm)."""

    serial: int
    t_s: int
    t_ns: int
    peaks: tuple[tuple[float, ...], ...]

    @property
    def t_us(self) -> int:
        return self.t_s * 1_000_000 + self.t_ns // 1000


def encode_peaks(serial: int, t_s: int, t_ns: int, channels: Sequence[Sequence[float]]) -> bytes:
    """A peaks record (``#GetPeaks`` content and stream payload)."""
    counts = [len(c) for c in channels]
    head = PEAKS_HEADER.pack(PEAKS_HEADER.size + 2 * len(counts), PEAKS_VERSION, 0,
                             serial & 0xFFFFFFFFFFFFFFFF, t_s & 0xFFFFFFFF, t_ns & 0xFFFFFFFF)
    flat = [float(v) for c in channels for v in c]
    return head + struct.pack(f"<{len(counts)}h", *counts) + struct.pack(f"<{len(flat)}d", *flat)


def decode_peaks(content: bytes | bytearray | memoryview) -> PeaksRecord:
    """Decode a peaks record; :class:`ValueError` if its lengths do not add up."""
    if len(content) < PEAKS_HEADER.size:
        raise ValueError(f"peaks record of {len(content)} bytes is shorter than its header")
    length, _version, _res, serial, t_s, t_ns = PEAKS_HEADER.unpack_from(content, 0)
    n_ch, odd = divmod(length - PEAKS_HEADER.size, 2)
    if odd or not 1 <= n_ch <= MAX_CHANNELS or length > len(content):
        raise ValueError(f"peaks header length {length} impossible")
    counts = struct.unpack_from(f"<{n_ch}h", content, PEAKS_HEADER.size)
    if min(counts) < 0 or length + 8 * sum(counts) != len(content):
        raise ValueError(f"peak counts {counts} do not match a record of {len(content)} bytes")
    flat = struct.unpack_from(f"<{sum(counts)}d", content, length)
    peaks, k = [], 0
    for c in counts:
        peaks.append(flat[k:k + c])
        k += c
    return PeaksRecord(serial, t_s, t_ns, tuple(peaks))


@dataclass
class StreamStats:
    """Counters of a :class:`PeakStreamDecoder`."""

    bytes: int = 0
    messages: int = 0  #: peaks records decoded
    header_errors: int = 0  #: impossible headers or records (the stream is cut and reopened)
    partial_frames: int = 0  #: messages cut by a disconnect
    discarded_bytes: int = 0  #: bytes of bad or partial messages

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class PeakStreamDecoder:
    """Splits the peak stream into records. TCP delivers bytes in order and intact, so the
    only faults are a peer that sends nonsense (then :attr:`broken` turns true: a byte stream
    without a sync word cannot be resynchronised, the connection must be reopened) and a
    connection cut in mid-message (:meth:`flush`)."""

    def __init__(self) -> None:
        self.stats = StreamStats()
        self.broken = False
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[PeaksRecord]:
        self.stats.bytes += len(data)
        if self.broken:
            self.stats.discarded_bytes += len(data)
            return []
        buf = self._buf
        buf += data
        out: list[PeaksRecord] = []
        pos = 0
        while len(buf) - pos >= RESPONSE_HEADER.size:
            status, _kind, msg_len, content_len = RESPONSE_HEADER.unpack_from(buf, pos)
            if status != SUCCESS or content_len > MAX_CONTENT or msg_len > 1024:
                self._break(len(buf) - pos)
                pos = len(buf)
                break
            end = pos + RESPONSE_HEADER.size + msg_len + content_len
            if len(buf) < end:
                break
            try:
                out.append(decode_peaks(memoryview(buf)[end - content_len:end]))
            except ValueError:
                self._break(len(buf) - pos)
                pos = len(buf)
                break
            self.stats.messages += 1
            pos = end
        del buf[:pos]
        return out

    def _break(self, n: int) -> None:
        self.stats.header_errors += 1
        self.stats.discarded_bytes += n
        self.broken = True

    def flush(self) -> None:
        """The connection ended: drop a partial message."""
        if self._buf:
            self.stats.partial_frames += 1
            self.stats.discarded_bytes += len(self._buf)
            self._buf.clear()

    def reset(self) -> None:
        """A new connection: start from a message boundary."""
        self.flush()
        self.broken = False


# --------------------------------------------------------------------------------------------
# Which peak is which grating
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PeakSelector:
    """Where one grating's peak is: ``channel`` (1-based) and either ``index`` (1-based, in
    ascending wavelength) or a wavelength window ``lo_nm..hi_nm`` holding exactly one peak."""

    channel: int
    index: int | None = None
    lo_nm: float | None = None
    hi_nm: float | None = None

    def text(self) -> str:
        if self.index is not None:
            return f"{self.channel}:{self.index}"
        return f"{self.channel}:{self.lo_nm:g}-{self.hi_nm:g}"


class PeakMap:
    """FBG 1..4 and T onto the instrument's channels and peaks.

    Text form (``--peak-map``, or ``"hyperion_peak_map"`` in the model's metadata): five
    comma-separated selectors in the order wl1, wl2, wl3, wl4, wlT, each ``CH:K`` (the K-th
    peak of channel CH, counting from the shortest wavelength) or ``CH:LO-HI`` (the one peak of
    channel CH between LO and HI nm). Default ``1:1,1:2,1:3,1:4,1:5``.

    A grating whose peak cannot be told for sure becomes a lost peak (0 fm; the runtime flags
    a sensor fault) and is counted in :attr:`unmapped`: a window with no peak or several, or an
    index on a channel whose peak count differs from the map's (a lost or extra peak would shift
    every index after it, so none of that channel's indices is trusted).
    """

    def __init__(self, selectors: Sequence[PeakSelector]) -> None:
        if len(selectors) != len(GRATINGS):
            raise ValueError(f"a peak map needs {len(GRATINGS)} selectors (wl1..wl4, wlT), "
                             f"not {len(selectors)}")
        self.selectors = tuple(selectors)
        self.unmapped = 0
        #: Peaks an index-mapped channel must report: its largest index.
        self.expected: dict[int, int] = {}
        for s in selectors:
            if s.index is not None:
                self.expected[s.channel] = max(self.expected.get(s.channel, 0), s.index)

    @classmethod
    def default(cls, n: int = len(GRATINGS)) -> "PeakMap":
        return cls([PeakSelector(1, k + 1) for k in range(n)])

    @classmethod
    def parse(cls, text: str) -> "PeakMap":
        """From the text form; :class:`ValueError` naming the bad item."""
        items = [t.strip() for t in text.split(",")]
        sels = []
        for name, item in zip(GRATINGS, items):
            ch, sep, rest = item.partition(":")
            try:
                channel = int(ch)
                if not sep or channel < 1:
                    raise ValueError
                if "-" in rest.lstrip("-"):
                    lo, hi = rest.split("-", 1)
                    lo_nm, hi_nm = float(lo), float(hi)
                    if not (math.isfinite(lo_nm) and math.isfinite(hi_nm) and lo_nm < hi_nm):
                        raise ValueError
                    sels.append(PeakSelector(channel, lo_nm=lo_nm, hi_nm=hi_nm))
                else:
                    index = int(rest)
                    if index < 1:
                        raise ValueError
                    sels.append(PeakSelector(channel, index))
            except ValueError:
                raise ValueError(f"bad peak selector {item!r} for {name}: expected CH:K "
                                 f"(K-th peak of channel CH) or CH:LO-HI (window in nm)") from None
        if len(items) != len(GRATINGS):
            raise ValueError(f"a peak map needs {len(GRATINGS)} selectors (wl1..wl4, wlT), "
                             f"not {len(items)}")
        return cls(sels)

    def text(self) -> str:
        return ",".join(s.text() for s in self.selectors)

    def frame(self, rec: PeaksRecord) -> Frame:
        """The record as a :class:`Frame` (fm, sequence = serial number mod 2**32)."""
        wl = []
        for s in self.selectors:
            peaks = rec.peaks[s.channel - 1] if s.channel <= len(rec.peaks) else ()
            value = 0.0
            if s.index is not None:
                if len(peaks) == self.expected[s.channel]:
                    value = sorted(peaks)[s.index - 1]
            else:
                inside = [p for p in peaks if s.lo_nm <= p <= s.hi_nm]  # type: ignore[operator]
                if len(inside) == 1:
                    value = inside[0]
            if value == 0.0 or not math.isfinite(value):
                self.unmapped += 1
                wl.append(0)
            else:
                wl.append(int(round(value * FM_PER_NM)))
        return Frame(rec.serial & 0xFFFFFFFF, rec.t_us, tuple(wl))

    def to_channels(self, wl_nm: Sequence[float], n_channels: int = DEFAULT_CHANNELS
                    ) -> list[list[float]]:
        """The device side: the gratings' wavelengths (nm; 0/NaN = no peak) as each channel's
        ascending peak list."""
        chans: list[list[float]] = [[] for _ in range(n_channels)]
        for s, v in zip(self.selectors, wl_nm):
            if v and math.isfinite(v):
                chans[s.channel - 1].append(float(v))
        for c in chans:
            c.sort()
        return chans


def peak_map_from_model(model_dir: str | Path) -> PeakMap | None:
    """The map stored in a model directory's metadata (``"hyperion_peak_map"`` in
    ``model.json``), or ``None``."""
    path = Path(model_dir) / "model.json"
    try:
        meta = json.loads(path.read_text(encoding="utf-8")).get("metadata", {})
    except (OSError, ValueError):
        return None
    text = meta.get("hyperion_peak_map")
    return PeakMap.parse(text) if text else None


# --------------------------------------------------------------------------------------------
# Host side
# --------------------------------------------------------------------------------------------

def parse_url(url: str) -> tuple[str, int, int]:
    """``hyperion://HOST[:PORT][?stream=PORT2]`` -> (host, command port, stream port); the
    stream port defaults to the command port + 1, as on the instrument."""
    parts = urlsplit(url)
    if parts.scheme != "hyperion" or not parts.hostname:
        raise ValueError(f"not a hyperion://HOST[:PORT] URL: {url!r}")
    cmd = parts.port or COMMAND_PORT
    q = parse_qs(parts.query)
    stream = int(q["stream"][0]) if "stream" in q else cmd + 1
    return parts.hostname, cmd, stream


def command(host: str, port: int, cmd: str, argument: str = "", timeout: float = 2.0
            ) -> tuple[str, bytes]:
    """Run one command (its own connection, as the vendor's client does): (message, content).
    :class:`HyperionError` on a failed command or an unreachable instrument."""
    try:
        with socket.create_connection((host, port), timeout=timeout) as s:
            s.sendall(encode_request(cmd, argument))
            head = _recv_exact(s, RESPONSE_HEADER.size)
            status, _kind, msg_len, content_len = RESPONSE_HEADER.unpack(head)
            if content_len > MAX_CONTENT:
                raise HyperionError(f"{cmd}: response of {content_len} bytes")
            message = _recv_exact(s, msg_len).decode("ascii", errors="replace")
            content = _recv_exact(s, content_len)
    except OSError as exc:
        raise HyperionError(f"{cmd}: {host}:{port}: {exc}") from None
    if status != SUCCESS:
        raise HyperionError(f"{cmd}: {message or f'status {status}'}")
    return message, content


def _recv_exact(s: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = s.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("connection closed in mid-response")
        buf += chunk
    return bytes(buf)


@dataclass
class TcpStats:
    """Connection counters of a :class:`HyperionReader` (as a serial link's)."""

    bytes_read: int = 0
    bytes_written: int = 0
    opens: int = 0
    open_failures: int = 0
    disconnects: int = 0
    reconnects: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class HyperionReader:
    """Reads the peak stream of a Hyperion instrument (or ``fbgforce emulate --protocol
    hyperion``) and maps it onto FBG 1..4 and T.

    On (re)connection it asks the command port for ``#GetSerialNumber`` and
    ``#GetDutChannelCount`` (:attr:`serial_number`, :attr:`channel_count`), then opens the
    stream port. Records go through the :class:`PeakMap` and a :class:`FrameGate` (sequence
    = serial number, timestamps, wavelength window); a lost connection is reopened with
    exponential backoff (50 ms doubling to 2 s) and the course of the stream is kept, so frames
    missed meanwhile count as lost and a restarted instrument as a restart. ``read``,
    ``stats`` and ``close`` work as the serial readers'.

    Parameters
    ----------
    url
        ``hyperion://HOST[:PORT][?stream=PORT2]`` (:func:`parse_url`).
    peak_map
        Which peak is which grating (default :meth:`PeakMap.default`).
    timeout
        A gap of this many seconds without bytes counts one timeout.
    """

    def __init__(self, url: str, *, peak_map: PeakMap | None = None, timeout: float = 0.25,
                 reconnect: bool = True, gate: FrameGate | None = None,
                 backoff_min: float = 0.05, backoff_max: float = 2.0) -> None:
        self.url = url
        self.host, self.command_port, self.stream_port = parse_url(url)
        self.peak_map = peak_map or PeakMap.default()
        self.gate = gate or FrameGate()
        self.decoder = PeakStreamDecoder()
        self.timeout = timeout
        self.reconnect = reconnect
        self.backoff_min = backoff_min
        self.backoff_max = backoff_max
        self.link_stats = TcpStats()
        self.serial_number: str | None = None
        self.channel_count: int | None = None
        self.last_error: str | None = None
        self.timeouts = 0
        self.delivered = 0
        self._sock: socket.socket | None = None
        self._backoff = backoff_min
        self._next_attempt = 0.0
        self._had_open = False
        self._dead = False
        self._last_rx = time.monotonic()
        self._timed_out = False
        self.link = self  # what record needs of a reader's link: open() and is_open

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    def open(self) -> bool:
        """Connect if not connected and the backoff allows; True when connected."""
        if self._sock is not None:
            return True
        if self._dead or time.monotonic() < self._next_attempt:
            return False
        try:
            serial = command(self.host, self.command_port, "#GetSerialNumber", timeout=1.0)[1]
            count = command(self.host, self.command_port, "#GetDutChannelCount", timeout=1.0)[1]
            sock = socket.create_connection((self.host, self.stream_port), timeout=1.0)
        except (HyperionError, OSError) as exc:
            self.last_error = str(exc)
            self.link_stats.open_failures += 1
            self._retry_later()
            return False
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.serial_number = serial.decode("ascii", errors="replace")
        self.channel_count = struct.unpack("<I", count[:4])[0] if len(count) >= 4 else None
        self._sock = sock
        self.link_stats.opens += 1
        if self._had_open:
            self.link_stats.reconnects += 1
        self._had_open = True
        self._backoff = self.backoff_min
        self.decoder.reset()
        return True

    def _retry_later(self) -> None:
        self._next_attempt = time.monotonic() + self._backoff
        self._backoff = min(self._backoff * 2.0, self.backoff_max)

    def _lost(self, why: str) -> None:
        self.last_error = why
        self.link_stats.disconnects += 1
        self.decoder.flush()
        self._close_socket()
        if not self.reconnect:
            self._dead = True
        self._retry_later()

    def _close_socket(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
            self._sock = None

    def read(self, wait: float = 0.02) -> list[Frame]:
        """Frames decoded within ``wait`` seconds (possibly none); never raises on faults."""
        if not self.open():
            time.sleep(min(wait, max(0.0, self._next_attempt - time.monotonic())))
            return []
        sock = self._sock
        assert sock is not None
        now = time.monotonic()
        try:
            ready, _, _ = select.select([sock], [], [], wait)
            data = sock.recv(1 << 16) if ready else None
        except OSError as exc:
            self._lost(str(exc))
            return []
        now = time.monotonic()
        if data is None:
            if not self._timed_out and now - self._last_rx > self.timeout:
                self.timeouts += 1
                self._timed_out = True
            return []
        if not data:
            self._lost("instrument closed the stream")
            return []
        self._last_rx = now
        self._timed_out = False
        self.link_stats.bytes_read += len(data)
        out: list[Frame] = []
        for rec in self.decoder.feed(data):
            out += self.gate.push(self.peak_map.frame(rec)) or []
        self.delivered += len(out)
        if self.decoder.broken:
            self._lost("peak stream out of step (impossible header)")
        return out

    def stats(self) -> dict[str, int]:
        d = self.decoder.stats.as_dict()
        d["frames"] = self.delivered
        d.update(self.gate.stats.as_dict())
        d["unmapped_peaks"] = self.peak_map.unmapped
        d["timeouts"] = self.timeouts
        d.update(self.link_stats.as_dict())
        return d

    def close(self) -> None:
        self._close_socket()


def gratings_nm(wl_fm: np.ndarray) -> np.ndarray:
    """fm (0 = lost peak) -> nm with NaN for lost peaks (what the emulator puts on a channel)."""
    wl = np.asarray(wl_fm, dtype=np.float64) / FM_PER_NM
    return np.where(wl_fm == 0, np.nan, wl)
