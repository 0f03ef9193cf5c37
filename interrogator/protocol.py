"""Wire protocols of the interrogator link (byte layouts in docs/protocol.md).

Three protocols, each with an encoder (what a device sends) and an incremental decoder (what
the host runs on whatever bytes arrive, in pieces of any size):

1. The **native streaming frame**: the device pushes one CRC-protected binary frame per sample
   (version 2: CRC-32; version 1, CRC-16, is still read). :func:`encode_frame` /
   :class:`FrameDecoder`, with :class:`FrameGate` refusing implausible frames.
2. The **FiSpec-style command protocol** (3 Mbaud 8N1): the host sends ASCII commands ending in
   ``>``; ``?>`` returns an identification string starting with ``FiSpec``, ``P>`` one
   measurement frame of ``8*N + 12`` bytes ending in ``Ende``. :func:`encode_fispec_frame`,
   :func:`decode_fispec_frame`, :class:`CommandParser` (device side).
3. The **load-cell / stage line protocol**: one ASCII line per sample on a second port, tagged
   with the interrogator's sample counter so the two streams can be joined.
   :func:`encode_loadcell_line` / :class:`LineDecoder`.

Units: wavelengths travel as integers, femtometres (1e-6 nm, the C runtime's input unit) in
the native frame and 1e-4 nm in the FiSpec frame. The decoders never raise on bad bytes; they
count what they discard in :class:`DecoderStats`.
"""
from __future__ import annotations

import binascii
import struct
import zlib
from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np

from fbgforce import units
from fbgforce.recordings.dataset import WL_RANGE_NM

# --------------------------------------------------------------------------------------------
# Shared
# --------------------------------------------------------------------------------------------

FM_PER_NM = 1_000_000
#: FiSpec wavelength unit: 1e-4 nm.
FISPEC_UNITS_PER_NM = 10_000


def crc16_ccitt_false(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, not reflected, no final XOR.

    ``crc16_ccitt_false(b"123456789") == 0x29B1`` (the catalogue check value). ``binascii``'s
    ``crc_hqx`` is exactly this polynomial without reflection, in C, so the host decoder keeps
    up with 1 kHz easily.
    """
    return binascii.crc_hqx(bytes(data), crc)


def crc32(data: bytes | bytearray | memoryview) -> int:
    """CRC-32/ISO-HDLC (zlib, Ethernet): reflected poly 0x04C11DB7, init and final XOR
    0xFFFFFFFF; ``crc32(b"123456789") == 0xCBF43926``."""
    return zlib.crc32(data) & 0xFFFFFFFF


def nm_to_fm(wl_nm: np.ndarray) -> np.ndarray:
    """Wavelengths in nm to femtometres as int64, by the runtime's one conversion rule.

    That rule is :func:`fbgforce.units.nm_to_fm` (nearest, ties to even; non-finite,
    i.e. a lost peak, becomes 0, which the runtime flags as a sensor fault), so what travels on
    the wire is exactly what an offline engine feeds the runtime.
    """
    return units.nm_to_fm(wl_nm).astype(np.int64)


def fm_to_nm(wl_fm: np.ndarray) -> np.ndarray:
    """Femtometres (integers) to nm (float64); exact inverse of :func:`nm_to_fm` on its range."""
    return np.asarray(wl_fm, dtype=np.float64) / FM_PER_NM


@dataclass
class DecoderStats:
    """Counters of one decoder. Every byte received ends up in exactly one of: a delivered
    frame, ``discarded_bytes``, or the decoder's pending buffer."""

    bytes: int = 0  #: bytes fed
    frames: int = 0  #: good frames delivered
    crc_errors: int = 0  #: candidate frames (sync and header plausible) whose CRC failed
    header_errors: int = 0  #: sync word found but version or channel count impossible
    resyncs: int = 0  #: times the decoder lost lock and hunted for the next sync word
    discarded_bytes: int = 0  #: bytes not part of any delivered frame
    partial_frames: int = 0  #: incomplete frames dropped by :meth:`FrameDecoder.flush`
    delivered_bytes: int = 0  #: bytes of delivered frames (frames of two versions differ in size)
    version_errors: int = 0  #: frames of another version than the one the stream locked on

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


# --------------------------------------------------------------------------------------------
# 1. Native streaming frame
# --------------------------------------------------------------------------------------------

SYNC = b"\xa5\x5a"
#: Version written by :func:`encode_frame`: CRC-32. Version 1 (CRC-16) frames are still read.
PROTOCOL_VERSION = 2
#: Header: sync (2), version (1), channel count (1), sequence u32, timestamp u64 µs.
HEADER = struct.Struct("<2sBBIQ")
HEADER_SIZE = HEADER.size  # 16
#: Check size by version: 1 = CRC-16/CCITT-FALSE, 2 = CRC-32.
CRC_SIZES = {1: 2, 2: 4}
CRC_SIZE = CRC_SIZES[PROTOCOL_VERSION]
MAX_CHANNELS = 32


def frame_size(n_channels: int, version: int = PROTOCOL_VERSION) -> int:
    """Bytes in one native frame: ``16 + 4 * n`` plus the check (2 bytes in version 1, 4 in 2)."""
    return HEADER_SIZE + 4 * n_channels + CRC_SIZES[version]


def _check(version: int, body: bytes | bytearray | memoryview) -> int:
    return crc32(body) if version == 2 else crc16_ccitt_false(body)


@dataclass(frozen=True)
class Frame:
    """One decoded sample.

    Attributes
    ----------
    seq
        Sample counter (native: 32-bit wrapping sequence number; FiSpec: the counter in the
        frame's last four bytes; Hyperion: the peaks header's serial number, low 32 bits).
    t_us
        Device timestamp in microseconds (FiSpec frames carry none: -1).
    wl_fm
        Peak wavelengths in femtometres, gratings 1..4 then T (any channel count).
    """

    seq: int
    t_us: int
    wl_fm: tuple[int, ...]


def encode_frame(seq: int, t_us: int, wl_fm: Sequence[int], version: int = PROTOCOL_VERSION
                 ) -> bytes:
    """Encode one native frame (see docs/protocol.md for the byte layout)."""
    n = len(wl_fm)
    if not 1 <= n <= MAX_CHANNELS:
        raise ValueError(f"channel count must be 1..{MAX_CHANNELS}, not {n}")
    if version not in CRC_SIZES:
        raise ValueError(f"version must be one of {sorted(CRC_SIZES)}, not {version}")
    body = HEADER.pack(SYNC, version, n, seq & 0xFFFFFFFF, t_us & 0xFFFFFFFFFFFFFFFF)
    body += struct.pack(f"<{n}i", *(int(v) for v in wl_fm))
    if version == 2:
        return body + struct.pack("<I", crc32(body))
    return body + struct.pack("<H", crc16_ccitt_false(body))


def encode_frames(seq0: int, t_us: np.ndarray, wl_fm: np.ndarray, version: int = PROTOCOL_VERSION
                  ) -> list[bytes]:
    """Encode consecutive samples ``seq0, seq0 + 1, ...`` (one frame each)."""
    t = np.asarray(t_us, dtype=np.int64)
    wl = np.asarray(wl_fm, dtype=np.int64)
    return [encode_frame(seq0 + i, int(t[i]), wl[i].tolist(), version) for i in range(len(t))]


# --------------------------------------------------------------------------------------------
# Plausibility: refuse a frame that cannot follow the last one
# --------------------------------------------------------------------------------------------

#: Wavelength window of a real peak (the dataset contract's); 0 = lost peak, always allowed.
WL_WINDOW_NM = WL_RANGE_NM
#: Largest forward sequence step taken without confirmation (65 s at 1 kHz).
MAX_SEQ_STEP = 1 << 16
#: Largest device-time step per sample step (1 s: rates down to 1 Hz).
MAX_PERIOD_US = 1_000_000
#: Largest wavelength change per sample step (the fingertip moves < 0.05 nm per ms).
MAX_STEP_NM = 2.0


@dataclass
class GateStats:
    """Counters of a :class:`FrameGate`."""

    lost_frames: int = 0  #: sequence gaps between frames delivered (confirmed jumps included)
    duplicates: int = 0  #: repeats of the last delivered or the held frame (dropped)
    seq_restarts: int = 0  #: confirmed backward jumps (device restarted; not counted lost)
    seq_jumps: int = 0  #: confirmed forward jumps beyond ``max_seq_step`` (their gap is lost)
    implausible_frames: int = 0  #: refused: wavelength outside the window, or held, never confirmed

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class FrameGate:
    """Decides whether a well-formed frame is a plausible next sample.

    A frame must have every wavelength inside ``window_nm`` (or 0, a lost peak). Frame ``b``
    *follows* frame ``a`` when its sequence step ``d = (b.seq - a.seq) mod 2**32`` is
    ``1..max_seq_step``, its device time (when both have one) advanced by ``1 µs .. d *
    max_period_us``, and no wavelength moved more than ``d * max_step_nm`` (lost peaks
    excepted).

    Only a frame *on course* is delivered at once: it follows the last delivered one with
    ``d == 1``, or, when both have device time and the sample period is known
    (:attr:`period_us`), with a ``d`` its time step agrees with. Any other frame (a gap
    without device time, a restart, a jump, a damaged counter or timestamp) is *held*. The next frame *vouches* for the held one when it follows the held frame and does
    not make it out of order (it does not follow the last delivered frame, or the held one lies
    between the two); the held frame is then delivered, its step counted (a restart when the
    counter or the time went backwards, else ``d - 1`` lost frames, and a jump when ``d``
    exceeds ``max_seq_step``), and the vouching frame is judged against it in turn. A held
    frame nobody vouches for is refused. An identical repeat of the last delivered or the held
    frame is a duplicate. The first frame of a session is held like any other.

    What this keeps under single-bit corruption (docs/protocol.md, "Plausibility gate"): a frame
    whose counter was damaged is never delivered unless the damaged counter lies strictly
    between those of its intact neighbours, which needs a gap there (never with consecutive
    counters); ``lost_frames`` counts exactly the counter values missing between delivered
    frames, and ``seq_restarts`` and ``seq_jumps`` only confirmed ones.

    :meth:`push` returns the frames to deliver, ``[]`` for a duplicate, or ``None`` when nothing
    is delivered and the frame was refused or held (:attr:`held` tells which; a byte-stream
    decoder then resumes its hunt one byte further, so a good frame starting inside the refused
    one's bytes is still found). A delivered list may start with the frame held before, and
    ends with the pushed frame unless that one is held in its turn.
    """

    MOD = 1 << 32

    def __init__(self, *, window_nm: tuple[float, float] = WL_WINDOW_NM,
                 max_seq_step: int = MAX_SEQ_STEP, max_period_us: int = MAX_PERIOD_US,
                 max_step_nm: float = MAX_STEP_NM) -> None:
        self.lo_fm = int(round(window_nm[0] * FM_PER_NM))
        self.hi_fm = int(round(window_nm[1] * FM_PER_NM))
        self.max_seq_step = max_seq_step
        self.max_period_us = max_period_us
        self.max_step_fm = int(round(max_step_nm * FM_PER_NM))
        self.stats = GateStats()
        self.last: Frame | None = None
        self.held: Frame | None = None
        #: Device sample period (µs) once two one-sample steps in a row agreed on it.
        self.period_us: int | None = None
        self._last_dt: int | None = None

    def in_window(self, frame: Frame) -> bool:
        lo, hi = self.lo_fm, self.hi_fm
        return all(v == 0 or lo <= v <= hi for v in frame.wl_fm)

    def _step(self, a: Frame, b: Frame) -> int | None:
        """Sequence step from ``a`` to ``b`` if ``b`` follows ``a``, else ``None``."""
        d = (b.seq - a.seq) % self.MOD
        if not 1 <= d <= self.max_seq_step or len(a.wl_fm) != len(b.wl_fm):
            return None
        if a.t_us >= 0 and b.t_us >= 0 and not 1 <= b.t_us - a.t_us <= d * self.max_period_us:
            return None
        lim = d * self.max_step_fm
        for x, y in zip(a.wl_fm, b.wl_fm):
            if x and y and abs(x - y) > lim:
                return None
        return d

    def _on_course(self, a: Frame, b: Frame) -> bool:
        """Whether ``b`` follows ``a`` as a sample delivered at once: a step of one, or, for
        frames with device time once the period is known, a step its time agrees with within
        half a period (so a counter that disagrees with the time is held)."""
        d = self._step(a, b)
        if d is None:
            return False
        p = self.period_us
        if p is None or a.t_us < 0 or b.t_us < 0:
            return d == 1
        return 2 * abs(b.t_us - a.t_us - d * p) <= p

    def _advance(self, frame: Frame) -> None:
        """Make ``frame`` the last delivered one, learning the period from one-sample steps."""
        last = self.last
        if last is not None and last.t_us >= 0 and frame.t_us >= 0 and (
                frame.seq - last.seq) % self.MOD == 1:
            dt = frame.t_us - last.t_us
            prev = self._last_dt
            if prev is not None and 8 * abs(dt - prev) <= prev:
                self.period_us = dt
            self._last_dt = dt
        self.last = frame

    def _vouches(self, held: Frame, frame: Frame) -> bool:
        """Whether ``frame`` confirms ``held`` as the sample after :attr:`last`."""
        if self._step(held, frame) is None:
            return False
        last = self.last
        if last is None or self._step(last, frame) is None:
            return True
        # Both follow the last delivered frame: the held one must come between them.
        return 1 <= (held.seq - last.seq) % self.MOD < (frame.seq - last.seq) % self.MOD

    def _count_course(self, frame: Frame) -> None:
        """Count the step from :attr:`last` to a confirmed ``frame``."""
        last, st = self.last, self.stats
        if last is None:
            return
        d = (frame.seq - last.seq) % self.MOD
        if d == 0 or d >= self.MOD // 2 or (last.t_us >= 0 and 0 <= frame.t_us <= last.t_us):
            st.seq_restarts += 1
            return
        st.lost_frames += d - 1
        if d > self.max_seq_step:
            st.seq_jumps += 1

    def push(self, frame: Frame) -> list[Frame] | None:
        st = self.stats
        if not self.in_window(frame):
            st.implausible_frames += 1
            return None
        last, held = self.last, self.held
        if frame == last or frame == held:
            st.duplicates += 1
            return []
        if last is not None and self._on_course(last, frame):
            if held is not None:
                st.implausible_frames += 1
                self.held = None
            self._count_course(frame)
            self._advance(frame)
            return [frame]
        if held is not None:
            self.held = None
            if self._vouches(held, frame):
                self._count_course(held)
                self._advance(held)
                if self._on_course(held, frame):
                    self._count_course(frame)
                    self._advance(frame)
                    return [held, frame]
                self.held = frame
                return [held]
            st.implausible_frames += 1
        self.held = frame
        return None

    def reset(self) -> None:
        """Forget the course (a new device session); counters are kept."""
        if self.held is not None:
            self.stats.implausible_frames += 1
        self.last = self.held = None
        self._last_dt = None


class FrameDecoder:
    """Incremental decoder of native frames that never raises on bad bytes.

    Feed it bytes as they arrive; it returns the complete, CRC-valid frames found. On garbage it
    hunts for the sync word; on a failed CRC, an implausible or a held frame it advances by one
    byte only, so that a good frame hidden inside the bytes of a truncated or corrupted one is
    still found. Version 1 (CRC-16) and 2 (CRC-32) frames are read; after the first good frame
    the stream is locked on that version, so a damaged version byte cannot select the weaker
    check.

    Parameters
    ----------
    channels
        Expected channel count; frames with another count are header errors. ``None`` accepts
        any count 1..:data:`MAX_CHANNELS`.
    gate
        A :class:`FrameGate` that every CRC-valid frame must pass (``None``: CRC only).
    """

    def __init__(self, channels: int | None = None, gate: FrameGate | None = None) -> None:
        if channels is not None and not 1 <= channels <= MAX_CHANNELS:
            raise ValueError(f"channels must be 1..{MAX_CHANNELS}")
        self.channels = channels
        self.gate = gate
        self.version: int | None = None
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._locked = True  # so that a stream starting with garbage counts one resync
        self._held_size = 0

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Consume ``data`` and return the frames it completes, in order."""
        self.stats.bytes += len(data)
        buf = self._buf
        buf += data
        out: list[Frame] = []
        pos = 0
        st = self.stats
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                # Keep a trailing first sync byte: it may be the start of the next frame.
                keep = 1 if len(buf) > pos and buf[-1] == SYNC[0] else 0
                self._discard(len(buf) - keep - pos)
                pos = len(buf) - keep
                break
            if start > pos:
                self._discard(start - pos)
                pos = start
            if len(buf) - pos < HEADER_SIZE:
                break
            _, version, n, seq, t_us = HEADER.unpack_from(buf, pos)
            if version not in CRC_SIZES or not 1 <= n <= MAX_CHANNELS or (
                    self.channels is not None and n != self.channels):
                st.header_errors += 1
                self._discard(1)
                pos += 1
                continue
            if self.version is not None and version != self.version:
                st.version_errors += 1
                self._discard(1)
                pos += 1
                continue
            size = frame_size(n, version)
            if len(buf) - pos < size:
                break
            end = pos + size
            crc_size = CRC_SIZES[version]
            crc = int.from_bytes(buf[end - crc_size:end], "little")
            if crc != _check(version, memoryview(buf)[pos:end - crc_size]):
                st.crc_errors += 1
                self._discard(1)
                pos += 1
                continue
            frame = Frame(seq, t_us, struct.unpack_from(f"<{n}i", buf, pos + HEADER_SIZE))
            if self.gate is not None:
                before = self.gate.held
                verdict = self.gate.push(frame)
                if verdict and verdict[0] is before:
                    # The held frame was confirmed: its bytes, discarded while hunting, count
                    # as delivered after all.
                    st.discarded_bytes -= self._held_size
                    st.delivered_bytes += self._held_size
                    st.frames += 1
                    self._held_size = 0
                    out.append(before)
                    verdict = verdict[1:]
                if self.gate.held is frame:
                    self._held_size = size
                if verdict is None or (not verdict and self.gate.held is frame):
                    # Held or refused: its bytes are discarded one by one while hunting; a held
                    # frame confirmed later takes its bytes back (above).
                    self._discard(1)
                    pos += 1
                    continue
            else:
                verdict = [frame]
            self.version = version
            if verdict:
                out.extend(verdict)
                st.frames += 1
                st.delivered_bytes += size
            else:  # a duplicate: consumed, not delivered
                st.discarded_bytes += size
            self._locked = True
            pos = end
        del buf[:pos]
        return out

    def flush(self) -> None:
        """Drop a partial frame (after a timeout or a disconnect), counting it."""
        if self._buf:
            if self._buf.startswith(SYNC):
                self.stats.partial_frames += 1
            self.stats.discarded_bytes += len(self._buf)
            self._buf.clear()
            self._locked = True

    def _discard(self, n: int) -> None:
        if n <= 0:
            return
        if self._locked:
            self.stats.resyncs += 1
            self._locked = False
        self.stats.discarded_bytes += n


# --------------------------------------------------------------------------------------------
# 2. FiSpec-style command protocol
# --------------------------------------------------------------------------------------------

FISPEC_TRAILER = b"Ende"
FISPEC_IDENT_PREFIX = b"FiSpec"
CMD_IDENT = b"?>"
CMD_PEAKS = b"P>"
CMD_PARAMS = b"p?>"
#: Longest command a device buffers before it gives up on the line (garbage protection).
MAX_COMMAND = 64


def fispec_frame_size(n_channels: int) -> int:
    """``8 * N + 12`` bytes."""
    return 8 * n_channels + 12


def encode_fispec_frame(wl_units: Sequence[int], amplitude: Sequence[int], temperature_c100: int,
                        counter: int) -> bytes:
    """One FiSpec measurement frame.

    Parameters
    ----------
    wl_units
        Peak wavelengths, int32 in 1e-4 nm, one per grating.
    amplitude
        The second int32 per grating (peak amplitude; 0 when no peak was found).
    temperature_c100
        Device temperature, °C × 100, int16.
    counter
        Written as u32 into the "4 further bytes" (this emulator's frame counter).
    """
    n = len(wl_units)
    parts = [struct.pack("<ii", int(w), int(a)) for w, a in zip(wl_units, amplitude)]
    parts.append(struct.pack("<hHI", int(temperature_c100), 0, counter & 0xFFFFFFFF))
    parts.append(FISPEC_TRAILER)
    frame = b"".join(parts)
    assert len(frame) == fispec_frame_size(n)
    return frame


@dataclass(frozen=True)
class FiSpecFrame:
    """A decoded FiSpec frame: wavelengths in 1e-4 nm and the raw extra fields."""

    wl_units: tuple[int, ...]
    amplitude: tuple[int, ...]
    temperature_c100: int
    counter: int
    empty: int = 0  #: the two bytes after the temperature, 0 on a well-formed frame

    def to_frame(self) -> Frame:
        """As a :class:`Frame` in femtometres (no device timestamp: ``t_us = -1``)."""
        scale = FM_PER_NM // FISPEC_UNITS_PER_NM
        return Frame(self.counter, -1, tuple(int(w) * scale for w in self.wl_units))


def decode_fispec_frame(data: bytes, n_channels: int) -> FiSpecFrame | None:
    """Decode exactly one frame; ``None`` if its length or trailer is wrong."""
    if len(data) != fispec_frame_size(n_channels) or not data.endswith(FISPEC_TRAILER):
        return None
    vals = struct.unpack_from(f"<{2 * n_channels}i", data, 0)
    temp, empty, counter = struct.unpack_from("<hHI", data, 8 * n_channels)
    return FiSpecFrame(vals[0::2], vals[1::2], temp, counter, empty)


class FiSpecReply:
    """Collects the reply to one ``P>`` poll, chunk by chunk, and decides when it is complete.

    A candidate is the last ``8*N + 12`` bytes whenever the bytes so far end in ``Ende``. Junk
    before the reply and a payload that happens to contain ``Ende`` can make a candidate out of
    junk and part of the reply; such a candidate is refused unless it is well-formed (empty
    field 0) *and* passes the :class:`FrameGate` (wavelength window, counter and step
    continuity), and reading goes on, so the rest of the reply still completes the right frame.
    A candidate the gate holds (a counter gap, a restart: its delivery waits for the next
    reply) completes the reply when it is all the bytes received; after junk, reading goes on
    in case the rest of the reply completes another candidate, and the held one stands if none
    does (:attr:`held`).

    Parameters
    ----------
    channels
        N, the number of gratings.
    gate
        The reader's gate (carries the course of the stream from poll to poll).
    seq
        Sequence number to give the frame instead of its counter (devices without one).
    """

    def __init__(self, channels: int, gate: FrameGate, seq: int | None = None) -> None:
        self.channels = channels
        self.size = fispec_frame_size(channels)
        self.gate = gate
        self.seq = seq
        self.buf = bytearray()
        self.refused = 0  #: candidates refused while this reply was read
        self.frame_bytes: bytes | None = None  #: the accepted (or held) frame's bytes
        self.held: Frame | None = None  #: this reply's frame while the gate holds it

    @property
    def complete(self) -> bool:
        """Whether the reply holds a frame the gate delivered or still holds."""
        return self.frame_bytes is not None and (self.held is None or self.gate.held is self.held)

    def feed(self, chunk: bytes) -> list[Frame] | None:
        """Add ``chunk``; the frames to deliver once the reply is accepted (``[]``: nothing yet,
        a duplicate or a held frame), else ``None``."""
        self.buf += chunk
        if len(self.buf) < self.size or not self.buf.endswith(FISPEC_TRAILER):
            return None
        raw = bytes(self.buf[-self.size:])
        fr = decode_fispec_frame(raw, self.channels)
        if fr is None or fr.empty != 0:
            self.refused += 1
            return None
        frame = fr.to_frame()
        if self.seq is not None:
            frame = Frame(self.seq, frame.t_us, frame.wl_fm)
        if self.held is not None:  # an earlier candidate of this reply: this one replaces it
            self.refused += 1
            self.held = self.frame_bytes = None
        verdict = self.gate.push(frame)
        if verdict is None and self.gate.held is frame:
            self.held, self.frame_bytes = frame, raw
            return [] if len(self.buf) == self.size else None
        if verdict is None:
            self.refused += 1
            return None
        self.frame_bytes = raw
        return verdict


class CommandParser:
    """Device side of the FiSpec command protocol: split incoming bytes into commands.

    A command is the bytes up to and including ``>``, after the last CR or LF (noise on an
    earlier line does not spoil the next command); spaces and NULs around it are ignored. A line
    longer than :data:`MAX_COMMAND` without ``>`` is discarded (counted), as a device's
    command buffer would overflow.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.overflows = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        cmds = []
        while True:
            i = self._buf.find(b">")
            if i < 0:
                if len(self._buf) > MAX_COMMAND:
                    self.overflows += 1
                    self._buf.clear()
                return cmds
            cmd = bytes(self._buf[:i + 1])
            # Anything before the last line break belongs to an earlier, broken line.
            cmd = cmd[max(cmd.rfind(b"\n"), cmd.rfind(b"\r")) + 1:].strip(b" \x00")
            del self._buf[:i + 1]
            if cmd:
                cmds.append(cmd)


# --------------------------------------------------------------------------------------------
# 3. Load-cell / stage line protocol
# --------------------------------------------------------------------------------------------

LOADCELL_TAG = b"LC"


@dataclass(frozen=True)
class LoadCellSample:
    """One stage/load-cell line.

    ``counter`` is the interrogator sample counter the line belongs to (native ``seq``);
    ``x_mm``/``y_mm`` the stage position in the pad frame; ``force_N`` the load cell;
    ``contact`` the stage's contact state; ``press`` the press number of the protocol.
    """

    counter: int
    x_mm: float
    y_mm: float
    force_N: float
    contact: int
    press: int


def _nmea_checksum(payload: bytes) -> int:
    c = 0
    for b in payload:
        c ^= b
    return c


def encode_loadcell_line(s: LoadCellSample) -> bytes:
    """``$LC,<counter>,<x_mm>,<y_mm>,<force_N>,<contact>,<press>*HH\\r\\n``.

    Fixed decimals: 4 for x/y (0.1 µm, finer than any stage), 5 for force (10 µN). ``HH`` is
    the XOR of the bytes between ``$`` and ``*`` in upper-case hex, as in NMEA 0183.
    """
    payload = b"LC,%d,%.4f,%.4f,%.5f,%d,%d" % (s.counter, s.x_mm, s.y_mm, s.force_N,
                                             s.contact, s.press)
    return b"$%s*%02X\r\n" % (payload, _nmea_checksum(payload))


@dataclass
class LineStats:
    """Counters of the line decoder."""

    lines: int = 0  #: good lines delivered
    bad_lines: int = 0  #: lines with a wrong checksum, tag or field
    discarded_bytes: int = 0  #: bytes outside good lines (noise, bad lines, overlong lines)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class LineDecoder:
    """Incremental decoder of load-cell lines; bad lines are counted, never raised."""

    MAX_LINE = 160

    def __init__(self) -> None:
        self.stats = LineStats()
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[LoadCellSample]:
        self._buf += data
        out: list[LoadCellSample] = []
        while True:
            i = self._buf.find(b"\n")
            if i < 0:
                if len(self._buf) > self.MAX_LINE:
                    self.stats.bad_lines += 1
                    self.stats.discarded_bytes += len(self._buf)
                    self._buf.clear()
                return out
            raw = bytes(self._buf[:i + 1])
            del self._buf[:i + 1]
            sample = self._parse(raw)
            if sample is None:
                if raw.strip():
                    self.stats.bad_lines += 1
                self.stats.discarded_bytes += len(raw)
            else:
                self.stats.lines += 1
                out.append(sample)

    def flush(self) -> None:
        """Drop a partial line (after a timeout or disconnect)."""
        self.stats.discarded_bytes += len(self._buf)
        self._buf.clear()

    @staticmethod
    def _parse(raw: bytes) -> LoadCellSample | None:
        # A line may follow noise on the same line: start at the last '$'.
        start = raw.rfind(b"$")
        star = raw.rfind(b"*")
        if start < 0 or star < start or len(raw) < star + 3:
            return None
        payload = raw[start + 1:star]
        try:
            if int(raw[star + 1:star + 3], 16) != _nmea_checksum(payload):
                return None
            f = payload.split(b",")
            if len(f) != 7 or f[0] != LOADCELL_TAG:
                return None
            return LoadCellSample(int(f[1]), float(f[2]), float(f[3]), float(f[4]), int(f[5]),
                                  int(f[6]))
        except ValueError:
            return None


__all__ = [
    "CMD_IDENT", "CMD_PARAMS", "CMD_PEAKS", "CommandParser", "DecoderStats", "FISPEC_TRAILER",
    "FISPEC_UNITS_PER_NM", "FM_PER_NM", "FiSpecFrame", "FiSpecReply", "Frame", "FrameDecoder",
    "FrameGate", "GateStats", "LineDecoder", "crc32",
    "LineStats", "LoadCellSample", "MAX_CHANNELS", "PROTOCOL_VERSION", "SYNC",
    "crc16_ccitt_false", "decode_fispec_frame", "encode_fispec_frame", "encode_frame",
    "encode_frames", "encode_loadcell_line", "fispec_frame_size", "fm_to_nm", "frame_size",
    "nm_to_fm",
]
