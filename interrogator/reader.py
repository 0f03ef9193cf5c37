"""Host side of the interrogator link: a pyserial reader that never dies on bad bytes.

Layers, bottom up:

- :class:`SerialLink` owns the pyserial port (any URL ``serial.serial_for_url`` accepts:
  ``/dev/ttyUSB0``, ``/dev/pts/7``, ``socket://host:port``, ``loop://``). A read or write error
  (device unplugged, pty closed) closes the port and the link reopens it with exponential
  backoff on later calls; nothing is raised to the caller.
- :class:`NativeReader` decodes native frames (:class:`fbgforce.interrogator.protocol.FrameDecoder`),
  :class:`FiSpecReader` polls a FiSpec-style device with ``P>``, :class:`LoadCellReader` decodes
  stage/load-cell lines. All three have ``read(wait) -> list`` and ``stats() -> dict``.
- :class:`SequenceTracker` turns sample counters into lost / duplicate / restart counts.

Everything the reader throws away is counted; ``stats()`` keys are documented in
docs/serial.md.
"""
from __future__ import annotations

import select
import time
from dataclasses import asdict, dataclass
from typing import Any, Iterator, Protocol

import serial

from fbgforce.interrogator.hyperion import HyperionReader
from fbgforce.interrogator.protocol import (
    CMD_IDENT,
    CMD_PEAKS,
    FISPEC_TRAILER,
    FiSpecReply,
    Frame,
    FrameDecoder,
    FrameGate,
    LineDecoder,
    LoadCellSample,
)

#: FiSpec devices run at 3 Mbaud 8N1; the native protocol needs >= 460800 Bd for 5 channels at
#: 1 kHz (38 kB/s), so the same default serves both. Ptys and sockets ignore it.
DEFAULT_BAUDRATE = 3_000_000


@dataclass
class LinkStats:
    """Connection counters of a :class:`SerialLink`."""

    bytes_read: int = 0
    bytes_written: int = 0
    opens: int = 0  #: successful opens (the first one included)
    open_failures: int = 0  #: attempts that failed (device absent); retried with backoff
    disconnects: int = 0  #: read/write errors that closed an open port
    reconnects: int = 0  #: opens after a disconnect

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class SerialLink:
    """A pyserial port that survives the device disappearing and coming back.

    Parameters
    ----------
    url
        Device path or pyserial URL.
    baudrate
        Line speed (8N1).
    reconnect
        Reopen after errors (backoff from ``backoff_min`` doubling to ``backoff_max`` seconds).
        If false, the link stays closed after the first error and :attr:`alive` turns false.
    """

    def __init__(self, url: str, *, baudrate: int = DEFAULT_BAUDRATE, reconnect: bool = True,
                 backoff_min: float = 0.05, backoff_max: float = 2.0) -> None:
        self.url = url
        self.baudrate = baudrate
        self.reconnect = reconnect
        self.backoff_min = backoff_min
        self.backoff_max = backoff_max
        self.stats = LinkStats()
        self.last_error: str | None = None
        self._ser: Any = None
        self._backoff = backoff_min
        self._next_attempt = 0.0
        self._ever_open = False
        self._dead = False

    # -- connection ----------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._ser is not None

    @property
    def alive(self) -> bool:
        """False once the link gave up (only with ``reconnect=False``)."""
        return not self._dead

    def open(self) -> bool:
        """Try to open now if closed and the backoff allows it; True if the port is open."""
        if self._ser is not None:
            return True
        if self._dead or time.monotonic() < self._next_attempt:
            return False
        try:
            # timeout=0: non-blocking reads; waiting is done with select in _wait_readable.
            ser = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0,
                                        write_timeout=0.5)
        except (serial.SerialException, OSError, ValueError) as exc:
            self.stats.open_failures += 1
            self.last_error = str(exc)
            if not self.reconnect and not self._ever_open:
                self._dead = True
            self._schedule_retry()
            return False
        self._ser = ser
        self.stats.opens += 1
        if self._ever_open:
            self.stats.reconnects += 1
        self._ever_open = True
        self._backoff = self.backoff_min
        return True

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except (serial.SerialException, OSError):
                pass
            self._ser = None

    def _schedule_retry(self) -> None:
        self._next_attempt = time.monotonic() + self._backoff
        self._backoff = min(self._backoff * 2.0, self.backoff_max)

    def _lost(self, exc: BaseException) -> None:
        self.last_error = str(exc)
        self.stats.disconnects += 1
        self.close()
        if not self.reconnect:
            self._dead = True
        self._schedule_retry()

    # -- I/O -----------------------------------------------------------------------------
    def _fd(self) -> Any:
        ser = self._ser
        fd = getattr(ser, "fd", None)  # posix Serial
        if isinstance(fd, int):
            return fd
        sock = getattr(ser, "_socket", None)  # socket://
        return sock

    def read(self, wait: float) -> bytes:
        """Return the bytes available within ``wait`` seconds (``b""`` if none or no device)."""
        if not self.open():
            time.sleep(min(wait, max(0.0, self._next_attempt - time.monotonic())))
            return b""
        try:
            fd = self._fd()
            if fd is not None:
                ready, _, _ = select.select([fd], [], [], wait)
                if not ready:
                    return b""
                data = self._ser.read(65536)
                if not data:
                    # Readable but empty: the pyserial posix backend raises for this itself;
                    # other backends (socket closed by peer) return b"".
                    raise serial.SerialException("device readable but returned no data")
            else:
                deadline = time.monotonic() + wait
                while True:
                    data = self._ser.read(65536)
                    if data or time.monotonic() >= deadline:
                        break
                    time.sleep(0.0005)
        except (serial.SerialException, OSError, ValueError, TypeError) as exc:
            # TypeError/ValueError: pyserial's posix backend trips over a closed fd.
            self._lost(exc)
            return b""
        self.stats.bytes_read += len(data)
        return bytes(data)

    def write(self, data: bytes) -> bool:
        """Write all of ``data``; False (and a disconnect) on error."""
        if not self.open():
            return False
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError, ValueError, TypeError) as exc:
            self._lost(exc)
            return False
        self.stats.bytes_written += len(data)
        return True

    def discard_input(self) -> None:
        """Drop whatever is buffered on input (stale replies)."""
        if self._ser is not None:
            try:
                self._ser.reset_input_buffer()
            except (serial.SerialException, OSError, ValueError, TypeError) as exc:
                self._lost(exc)


@dataclass
class SequenceStats:
    lost_frames: int = 0  #: counter gaps (frames the device sent but we never decoded)
    duplicates: int = 0  #: frames whose counter was already delivered (dropped)
    seq_restarts: int = 0  #: counter jumped backwards: device restarted (not counted lost)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class SequenceTracker:
    """Counts gaps in a 32-bit wrapping sample counter.

    A forward step ``d = (seq - last) mod 2**32`` with ``1 <= d < 2**31`` delivers the frame and
    counts ``d - 1`` lost; ``d == 0`` is a duplicate; a backward step is a device restart.
    """

    MOD = 1 << 32

    def __init__(self) -> None:
        self.stats = SequenceStats()
        self.last: int | None = None

    def accept(self, seq: int) -> bool:
        """Update with ``seq``; False if the frame must not be delivered (duplicate)."""
        if self.last is None:
            self.last = seq
            return True
        d = (seq - self.last) % self.MOD
        if d == 0:
            self.stats.duplicates += 1
            return False
        if d < self.MOD // 2:
            self.stats.lost_frames += d - 1
        else:
            self.stats.seq_restarts += 1
        self.last = seq
        return True


class Reader(Protocol):
    """What stream/record need from a reader."""

    def read(self, wait: float = ...) -> list[Frame]: ...

    def stats(self) -> dict[str, int]: ...

    def close(self) -> None: ...


class _PushReader:
    """A port that pushes records on its own: decode them, drop partial ones on a timeout or a
    disconnect, and track their sequence numbers. Subclasses name the decoder and the field
    that numbers a record (:meth:`_sequence_of`), or leave sequence checks to the decoder's
    :class:`FrameGate` (``seq=None``)."""

    def __init__(self, link: SerialLink, decoder: Any, timeout: float,
                 seq: SequenceTracker | None = None) -> None:
        self.link = link
        self.decoder = decoder
        self.seq = seq
        self.timeout = timeout
        self.timeouts = 0
        self._last_rx = time.monotonic()
        self._timed_out = False

    @staticmethod
    def _sequence_of(record: Any) -> int:
        raise NotImplementedError

    def read(self, wait: float = 0.02) -> list[Any]:
        """Records decoded within ``wait`` seconds (possibly none); never raises on line faults."""
        was_open = self.link.is_open
        data = self.link.read(wait)
        now = time.monotonic()
        if was_open and not self.link.is_open:
            self.decoder.flush()  # the rest of a record cut by the disconnect never comes
        if not data:
            if not self._timed_out and now - self._last_rx > self.timeout:
                self.timeouts += 1
                self._timed_out = True
                self.decoder.flush()
            return []
        self._last_rx = now
        self._timed_out = False
        records = self.decoder.feed(data)
        if self.seq is None:
            return records
        return [r for r in records if self.seq.accept(self._sequence_of(r))]

    def stats(self) -> dict[str, int]:
        d = self.decoder.stats.as_dict()
        gate = getattr(self.decoder, "gate", None)
        d.update((self.seq.stats if self.seq is not None else gate.stats).as_dict())
        d.update(self.link.stats.as_dict())
        d["timeouts"] = self.timeouts
        return d

    def close(self) -> None:
        self.link.close()


class NativeReader(_PushReader):
    """Reads native frames from a port that pushes them.

    Parameters
    ----------
    url
        Device path or pyserial URL.
    channels
        Expected channel count (5: gratings 1..4 and T); ``None`` accepts any.
    timeout
        A gap of this many seconds without bytes counts one timeout and drops a partial frame.
    gate
        Plausibility rules (:class:`FrameGate`; default: its defaults).
    """

    def __init__(self, url: str, *, channels: int | None = 5, baudrate: int = DEFAULT_BAUDRATE,
                 timeout: float = 0.25, reconnect: bool = True, gate: FrameGate | None = None
                 ) -> None:
        super().__init__(SerialLink(url, baudrate=baudrate, reconnect=reconnect),
                         FrameDecoder(channels, gate or FrameGate()), timeout)


class FiSpecReader:
    """Client of a FiSpec-style interrogator: polls ``P>`` and reads to the ``Ende`` trailer.

    A reply is accepted when the buffer ends in ``Ende``, holds at least ``8*N + 12`` bytes (the
    last that many form the frame; a binary frame may contain ``Ende`` by chance, so the
    length decides) and that frame is well-formed and plausible (:class:`FiSpecReply`,
    :class:`FrameGate`); otherwise reading continues until ``reply_timeout``, which counts as a
    timeout (nothing came) or a bad reply, and the client polls again. The frame's last four
    bytes before the trailer carry a sample counter on the fbgforce emulator; with a device
    that leaves them constant the counter checks are switched off by ``counter=False``.

    Parameters
    ----------
    channels
        N, the number of gratings; ``None`` learns it from the first reply's length.
    poll_interval
        Minimum time between polls (1 ms = the device's 1 kHz rate).
    gate
        Plausibility rules (:class:`FrameGate`; default: its defaults).
    """

    def __init__(self, url: str, *, channels: int | None = 5, baudrate: int = DEFAULT_BAUDRATE,
                 reply_timeout: float = 0.1, poll_interval: float = 0.001, counter: bool = True,
                 reconnect: bool = True, gate: FrameGate | None = None) -> None:
        self.link = SerialLink(url, baudrate=baudrate, reconnect=reconnect)
        self.channels = channels
        self.reply_timeout = reply_timeout
        self.poll_interval = poll_interval
        self.use_counter = counter
        self.gate = gate or FrameGate()
        self.polls = 0
        self.replies = 0
        self.frames = 0
        self.bad_replies = 0
        self.timeouts = 0
        self.refused_candidates = 0
        self.discarded_bytes = 0
        self.last_reply: bytes | None = None
        self._next_poll = 0.0
        self._synthetic_seq = 0

    def identify(self, wait: float = 0.3) -> str | None:
        """Send ``?>`` and return the identification line (``None`` if no answer)."""
        self.link.discard_input()
        if not self.link.write(CMD_IDENT):
            return None
        buf = bytearray()
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            buf += self.link.read(0.02)
            if buf.endswith(b"\n"):
                break
        text = bytes(buf).decode("ascii", errors="replace").strip()
        return text or None

    def _reply(self) -> FiSpecReply | None:
        if self.channels is None:
            return None
        return FiSpecReply(self.channels, self.gate,
                           None if self.use_counter else self._synthetic_seq)

    def poll(self) -> list[Frame] | None:
        """One ``P>`` round trip: the frames to deliver (``[]``: a duplicate, or a frame held
        until the next reply confirms it), or ``None`` (timeout / bad reply). The accepted
        frame's bytes are kept in :attr:`last_reply`."""
        self.link.discard_input()
        self.polls += 1
        if not self.link.write(CMD_PEAKS):
            return None
        reply = self._reply()
        buf = bytearray()
        deadline = time.monotonic() + self.reply_timeout
        quiet = None
        verdict = None
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            chunk = self.link.read(min(left, 0.01))
            if chunk:
                buf += chunk
                quiet = None
                if reply is not None:
                    verdict = reply.feed(chunk)
                    if verdict is not None:
                        break
            elif reply is None and buf.endswith(FISPEC_TRAILER):
                quiet = quiet or time.monotonic()
                if time.monotonic() - quiet > 0.005:  # reply over: learn N from its length
                    if len(buf) >= 20 and (len(buf) - 12) % 8 == 0:
                        self.channels = (len(buf) - 12) // 8
                        reply = self._reply()
                        verdict = reply.feed(bytes(buf))  # type: ignore[union-attr]
                    break
            if not self.link.is_open:
                break
        if verdict is None and reply is not None and reply.complete:
            verdict = []  # its frame is held: the next reply decides on it
        if reply is not None:
            self.refused_candidates += reply.refused
        if verdict is not None:
            self.replies += 1
            self.frames += len(verdict)
            self.last_reply = reply.frame_bytes  # type: ignore[union-attr]
            self.discarded_bytes += len(buf) - len(self.last_reply or b"")
            self._synthetic_seq += 1
            return verdict
        if buf:
            self.bad_replies += 1
            self.discarded_bytes += len(buf)
        else:
            self.timeouts += 1
        return None

    def read(self, wait: float = 0.02) -> list[Frame]:
        """Poll for up to ``wait`` seconds; return the new samples."""
        out: list[Frame] = []
        end = time.monotonic() + wait
        while True:
            now = time.monotonic()
            if now < self._next_poll:
                if self._next_poll > end:
                    break
                time.sleep(self._next_poll - now)
            self._next_poll = time.monotonic() + self.poll_interval
            frames = self.poll()
            if frames:
                out.extend(frames)
            if time.monotonic() >= end:
                break
        return out

    def stats(self) -> dict[str, int]:
        # Polling sees the device's latest sample: counter gaps are samples measured between
        # polls (skipped_samples), not line losses; a poll without a whole reply is lost.
        g = self.gate.stats
        d = {"frames": self.frames, "polls": self.polls,
             "replies": self.replies, "bad_replies": self.bad_replies, "timeouts": self.timeouts,
             "lost_frames": self.bad_replies + self.timeouts,
             "skipped_samples": g.lost_frames, "duplicates": g.duplicates,
             "seq_restarts": g.seq_restarts, "seq_jumps": g.seq_jumps,
             "implausible_frames": g.implausible_frames,
             "refused_candidates": self.refused_candidates,
             "discarded_bytes": self.discarded_bytes}
        d.update(self.link.stats.as_dict())
        return d

    def close(self) -> None:
        self.link.close()


class LoadCellReader(_PushReader):
    """Reads stage/load-cell lines (``$LC,...*HH``) from the second port."""

    def __init__(self, url: str, *, baudrate: int = 115200, timeout: float = 0.25,
                 reconnect: bool = True) -> None:
        super().__init__(SerialLink(url, baudrate=baudrate, reconnect=reconnect),
                         LineDecoder(), timeout, SequenceTracker())

    @staticmethod
    def _sequence_of(record: LoadCellSample) -> int:
        return record.counter


PROTOCOLS = ("native", "fispec", "hyperion")


def open_reader(url: str, protocol: str | None = None, *, channels: int | None = 5,
                baudrate: int = DEFAULT_BAUDRATE, reconnect: bool = True,
                peak_map: Any = None) -> Any:
    """A reader for ``protocol`` on ``url``: ``"native"``, ``"fispec"`` (serial ports and
    pyserial URLs) or ``"hyperion"`` (``hyperion://HOST[:PORT]``, which also selects it when
    ``protocol`` is ``None``; ``peak_map`` is its :class:`~fbgforce.interrogator.hyperion.PeakMap`).
    """
    if protocol is None:
        protocol = "hyperion" if url.startswith("hyperion://") else "native"
    if protocol == "hyperion" or url.startswith("hyperion://"):
        if protocol != "hyperion":
            raise ValueError(f"a hyperion:// source speaks the hyperion protocol, not {protocol!r}")
        return HyperionReader(url, peak_map=peak_map, reconnect=reconnect)
    if protocol == "native":
        return NativeReader(url, channels=channels, baudrate=baudrate, reconnect=reconnect)
    if protocol == "fispec":
        return FiSpecReader(url, channels=channels, baudrate=baudrate, reconnect=reconnect)
    raise ValueError(f"protocol must be one of {PROTOCOLS}, not {protocol!r}")


def iter_batches(reader: Reader, *, duration: float | None = None, max_samples: int | None = None,
                 idle_timeout: float | None = None, start_timeout: float | None = None,
                 wait: float = 0.02, empty: bool = False) -> Iterator[list[Frame]]:
    """Yield batches of frames until a stop condition (non-empty ones unless ``empty``).

    Parameters
    ----------
    duration
        Stop this many seconds after the first frame (wall clock).
    max_samples
        Stop after this many frames (the last batch is cut to it).
    idle_timeout
        Stop when no frame arrived for this long (after the first frame: a device that is not
        there yet is waited for, one that went away is given this long to come back).
    start_timeout
        Stop if the first frame has not arrived after this long.
    empty
        Also yield an empty batch after a read that returned nothing (at most ``wait``
        seconds apart): the caller gets its turn while the device is silent.
    """
    first = None
    started = last = time.monotonic()
    n = 0
    while True:
        batch = reader.read(wait)
        now = time.monotonic()
        if batch:
            if first is None:
                first = now
            last = now
            if max_samples is not None and n + len(batch) >= max_samples:
                yield batch[:max_samples - n]
                return
            n += len(batch)
            yield batch
        elif empty:
            yield batch
        if first is None:
            if start_timeout is not None and now - started >= start_timeout:
                return
        else:
            if duration is not None and now - first >= duration:
                return
            if idle_timeout is not None and now - last >= idle_timeout:
                return
