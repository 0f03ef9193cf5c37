"""Virtual interrogator: plays a recording in real time on a pseudo-terminal.

The emulator is the device side of the protocols in :mod:`fbgforce.interrogator.protocol`:

- ``native``: pushes one frame per sample at ``rate`` samples per second;
- ``fispec``: answers ``?>``, ``p?>`` and ``P>`` polls with the latest sample (unknown
  commands are ignored, as a device would);
- with ``loadcell=True`` a second pty carries the stage/load-cell lines of the same samples,
  tagged with the same sample counter.

Line faults. Each sample gets a fault kind (:data:`FAULTS`): ``drop`` (frame never sent),
``flip`` (1–3 bits flipped), ``truncate`` (only a prefix sent), ``garbage`` (a burst of random
bytes sent before the intact frame). The kinds come from the recording's ``dropout`` column
when it has one (the simulator's ``dropout`` effect; mapping in :func:`faults_from_dropout`)
and/or from per-kind rates. The plan is drawn up front from a seeded generator, so a test
knows which frames are good.

Like a real UART device, bytes written while no client has the port open are lost; by default
playback starts only once every port has a client (``wait_client``), and after the last sample
the ports stay open until the clients close them or ``linger`` seconds pass.
"""
from __future__ import annotations

import errno
import math
import os
import select
import socket
import struct
import threading
import time
import tty
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from fbgforce.interrogator import hyperion as H
from fbgforce.interrogator import protocol as P

#: Fault kinds by code (the codes stored in a fault plan).
FAULTS = ("none", "drop", "flip", "truncate", "garbage")
FAULT_CODE = {name: code for code, name in enumerate(FAULTS)}
#: FiSpec frame fields the emulator reports besides the wavelengths.
FISPEC_AMPLITUDE = 12000
FISPEC_TEMPERATURE_C100 = 2500
FISPEC_IDENT = b"FiSpec FBGX-EMU (fbgforce virtual interrogator)"
#: Pause between the last client opening its port and the first sample (see Emulator._run).
START_DELAY_S = 0.25


@dataclass
class Playback:
    """What the emulator plays: per sample a device timestamp, wavelengths and stage data.

    Attributes
    ----------
    t_us
        (n,) int64 device timestamps, µs.
    wl_fm
        (n, c) int64 peak wavelengths, fm (0 = no peak).
    x_mm, y_mm, force_N
        (n,) stage position and load-cell force (x/y 0 where the dataset has NaN: the stage is
        somewhere, the dataset simply does not say where when there is no contact).
    contact, press
        (n,) int stage contact state and press number.
    dropout
        (n,) the dataset's ``dropout`` column if it has one, else ``None``.
    """

    t_us: np.ndarray
    wl_fm: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    force_N: np.ndarray
    contact: np.ndarray
    press: np.ndarray
    dropout: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_us.shape[0])

    @classmethod
    def from_dataset(cls, ds: Any) -> "Playback":
        """From a :class:`fbgforce.recordings.dataset.Dataset` (or anything with the same fields)."""
        t_us = np.round(np.asarray(ds.t_s, dtype=np.float64) * 1e6).astype(np.int64)
        extra = getattr(ds, "extra", None) or {}
        dropout = extra.get("dropout")
        return cls(
            t_us=t_us,
            wl_fm=P.nm_to_fm(ds.wl_nm),
            x_mm=np.nan_to_num(np.asarray(ds.x_mm, dtype=np.float64)),
            y_mm=np.nan_to_num(np.asarray(ds.y_mm, dtype=np.float64)),
            force_N=np.asarray(ds.force_N, dtype=np.float64),
            contact=np.asarray(ds.contact).astype(np.int64),
            press=np.asarray(ds.press_id).astype(np.int64),
            dropout=None if dropout is None else np.asarray(dropout),
        )


def faults_from_dropout(dropout: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Map a ``dropout`` column to fault codes.

    0 (or False/NaN) is a good sample. 1 (or True) is a lost sample: ``drop``. 2 is a garbled
    sample: ``flip``. Any other non-zero value is a generic line fault whose kind (flip,
    truncate, garbage) is drawn from ``rng``, so a boolean column still exercises all of them.
    """
    d = np.nan_to_num(np.asarray(dropout, dtype=np.float64)).astype(np.int64)
    out = np.zeros(d.shape[0], dtype=np.uint8)
    out[d == 1] = FAULT_CODE["drop"]
    out[d == 2] = FAULT_CODE["flip"]
    other = (d != 0) & (d != 1) & (d != 2)
    choice = rng.choice([FAULT_CODE["flip"], FAULT_CODE["truncate"], FAULT_CODE["garbage"]],
                        size=int(other.sum()))
    out[other] = choice
    return out


def plan_faults(n: int, *, rates: Mapping[str, float] | None = None,
                dropout: np.ndarray | None = None, seed: int | None = 0) -> np.ndarray:
    """Fault code per sample (uint8, codes of :data:`FAULTS`).

    ``dropout`` (the recording's column) is applied first; ``rates`` (probability per sample for
    ``drop``, ``flip``, ``truncate``, ``garbage``) then fault further good samples. Seeded.
    """
    rng = np.random.default_rng(seed)
    plan = np.zeros(n, dtype=np.uint8)
    if dropout is not None:
        plan[:] = faults_from_dropout(dropout[:n], rng)
    for name, rate in (rates or {}).items():
        if name not in FAULT_CODE or name == "none":
            raise ValueError(f"unknown fault {name!r}; choose from {', '.join(FAULTS[1:])}")
        if not 0.0 <= rate <= 1.0:
            raise ValueError(f"fault rate {name}={rate} must be within 0..1")
        hit = (rng.random(n) < rate) & (plan == 0)
        plan[hit] = FAULT_CODE[name]
    return plan


def parse_fault_rates(text: str | None) -> dict[str, float]:
    """``"drop=0.01,flip=0.005"`` -> ``{"drop": 0.01, "flip": 0.005}``."""
    rates: dict[str, float] = {}
    if not text:
        return rates
    for item in text.split(","):
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in FAULT_CODE or name == "none":
            raise ValueError(f"bad fault {item!r}: expected NAME=RATE with NAME one of "
                             f"{', '.join(FAULTS[1:])}")
        try:
            rates[name] = float(value)
        except ValueError:
            raise ValueError(f"bad fault rate in {item!r}: not a number") from None
        if not 0.0 <= rates[name] <= 1.0:
            raise ValueError(f"bad fault rate in {item!r}: must be within 0..1")
    return rates


class PtyEndpoint:
    """The device end of a pseudo-terminal pair.

    The slave side (the path clients open) is put in raw mode once so that the line
    discipline neither echoes nor translates bytes even for clients that do not configure
    the tty. The master is non-blocking: a device never waits for the host. The kernel's pty
    buffer is small (about 16 KiB, 80 ms at 5 kHz), so, like the TX FIFO of a USB-serial
    device, up to ``tx_buffer`` bytes wait here for a slow host; beyond that new bytes are
    lost (counted as overrun).
    """

    def __init__(self, link: str | os.PathLike[str] | None = None, tx_buffer: int = 1 << 20
                 ) -> None:
        self.master, slave = os.openpty()
        self.path = os.ttyname(slave)
        tty.setraw(slave)
        # Closing our slave fd lets POLLHUP on the master tell whether a client has it open.
        os.close(slave)
        os.set_blocking(self.master, False)
        self.link = Path(link) if link else None
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + f".tmp{os.getpid()}")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            os.symlink(self.path, tmp)
            os.replace(tmp, self.link)  # atomic: a reader never sees a missing link mid-swap
        self.overrun_bytes = 0
        self.bytes_sent = 0
        self.tx_buffer = tx_buffer
        self._backlog = bytearray()
        self._closed = False

    @property
    def name(self) -> str:
        """The path to hand to clients (the link if one was asked for)."""
        return str(self.link) if self.link is not None else self.path

    def client_connected(self) -> bool:
        ev = select.poll()
        ev.register(self.master, select.POLLHUP)
        return not any(flag & select.POLLHUP for _, flag in ev.poll(0))

    @property
    def backlog(self) -> int:
        """Bytes waiting for the host to read."""
        return len(self._backlog)

    def write(self, data: bytes) -> None:
        """Queue ``data`` (dropping it if the buffer is full) and push what the pty takes."""
        room = self.tx_buffer - len(self._backlog)
        if len(data) > room:
            self.overrun_bytes += len(data) - max(room, 0)
            data = data[:max(room, 0)]
        self._backlog += data
        self.flush()

    def flush(self) -> None:
        """Push queued bytes into the pty as far as it takes them (never blocks)."""
        while self._backlog:
            try:
                n = os.write(self.master, self._backlog)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno not in (errno.EIO, errno.EAGAIN):
                    raise
                return
            if n <= 0:
                return
            self.bytes_sent += n
            del self._backlog[:n]

    def read(self) -> bytes:
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        os.close(self.master)
        if self.link is not None:
            try:
                if os.readlink(self.link) == self.path:
                    self.link.unlink()
            except OSError:
                pass


@dataclass
class EmulatorStats:
    """What the emulator did (returned by :meth:`Emulator.run`)."""

    samples_played: int = 0  #: samples whose time came (sent, faulted or polled)
    frames_sent: int = 0  #: intact frames written (native) or replies sent (fispec)
    dropped: int = 0
    flipped: int = 0
    truncated: int = 0
    garbage_bursts: int = 0
    garbage_bytes: int = 0
    bytes_sent: int = 0  #: bytes the interrogator port delivered into its pty
    overrun_bytes: int = 0  #: bytes dropped because the host fell > tx_buffer behind (all ports)
    commands: int = 0  #: FiSpec commands received
    ignored_commands: int = 0  #: unknown commands (ignored, no reply)
    loadcell_lines: int = 0
    loops: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class _BackgroundPlayer:
    """Start/stop/join of an emulator that plays in a background thread: the subclass sets
    ``self._stop`` (an Event) and ``self._thread`` (None) and defines ``run`` and ``close``."""

    _thread_name = "fbgforce-emulator"
    _stop: threading.Event
    _thread: threading.Thread | None

    def run(self, max_samples: int | None = None) -> "EmulatorStats":
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def start(self, max_samples: int | None = None) -> "_BackgroundPlayer":
        """Run :meth:`run` in a background thread."""
        self._thread = threading.Thread(target=self.run, kwargs={"max_samples": max_samples},
                                        name=self._thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop playing and close the ports."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self.close()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)


class Emulator(_BackgroundPlayer):
    """A virtual interrogator (and optionally a stage/load-cell) on pseudo-terminals.

    Parameters
    ----------
    playback
        The samples to play (:meth:`Playback.from_dataset`).
    protocol
        ``"native"`` or ``"fispec"``.
    rate
        Samples per second of playback (wall clock).
    faults
        Fault code per sample (:func:`plan_faults`); ``None`` = no faults.
    loadcell
        Also open the stage/load-cell pty.
    seed
        Seeds the bits flipped, truncation lengths and garbage bytes.
    wait_client
        Start playing only when every port has a client.
    linger
        After the last sample, keep the ports open until the clients close (at most this long).
    loop
        Start over after the last sample (counter and timestamps keep increasing).
    link, loadcell_link
        Optional stable symlink paths to the ptys (a reader can reopen them after a restart).
    """

    def __init__(self, playback: Playback, *, protocol: str = "native", rate: float = 1000.0,
                 faults: np.ndarray | None = None, loadcell: bool = False, seed: int | None = 0,
                 wait_client: bool = True, linger: float = 2.0, loop: bool = False,
                 link: str | None = None, loadcell_link: str | None = None) -> None:
        if protocol not in ("native", "fispec"):
            raise ValueError(f"protocol must be 'native' or 'fispec', not {protocol!r}")
        if not rate > 0:
            raise ValueError("rate must be positive")
        if len(playback) == 0:
            raise ValueError("nothing to play: the recording has no samples")
        self.playback = playback
        self.protocol = protocol
        self.rate = float(rate)
        n = len(playback)
        self.faults = np.zeros(n, dtype=np.uint8) if faults is None else np.asarray(faults, np.uint8)
        if self.faults.shape != (n,):
            raise ValueError(f"fault plan has {self.faults.shape} entries, recording {n}")
        self.rng = np.random.default_rng(np.random.SeedSequence([0 if seed is None else seed, 7]))
        self.wait_client = wait_client
        self.linger = linger
        self.loop = loop
        self.stats = EmulatorStats()
        self.port = PtyEndpoint(link)
        self.loadcell_port = PtyEndpoint(loadcell_link) if loadcell else None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._parser = P.CommandParser()
        # A loop continues the device clock by one scene sample period after the last sample.
        step = int(np.median(np.diff(playback.t_us))) if n > 1 else int(round(1e6 / self.rate))
        self._span_us = int(playback.t_us[-1] - playback.t_us[0]) + step

    # -- public API ----------------------------------------------------------------------
    @property
    def paths(self) -> dict[str, str]:
        out = {"interrogator": self.port.name}
        if self.loadcell_port is not None:
            out["loadcell"] = self.loadcell_port.name
        return out

    def close(self) -> None:
        self.port.close()
        if self.loadcell_port is not None:
            self.loadcell_port.close()

    def run(self, max_samples: int | None = None) -> EmulatorStats:
        """Play (blocking) until the recording, ``max_samples`` or :meth:`stop` ends it."""
        try:
            self._run(max_samples)
        finally:
            self.stats.bytes_sent = self.port.bytes_sent
            self.stats.overrun_bytes = sum(p.overrun_bytes for p in self._ports())
            self.close()
        return self.stats

    # -- internals -----------------------------------------------------------------------
    def _ports(self) -> list[PtyEndpoint]:
        return [p for p in (self.port, self.loadcell_port) if p is not None]

    def _run(self, max_samples: int | None) -> None:
        n = len(self.playback)
        total: float = n if not self.loop else math.inf
        if max_samples is not None:
            total = min(total, max_samples)
        if self.wait_client:
            while not self._stop.is_set() and not all(p.client_connected() for p in self._ports()):
                self._service_commands(-1)
                time.sleep(0.002)
            # A client opening the port configures the tty and flushes its input (pyserial
            # does) just after the open that we detected: give it time, or the first frames go.
            settle = time.monotonic() + START_DELAY_S
            while not self._stop.is_set() and time.monotonic() < settle:
                self._service_commands(-1)
                time.sleep(0.002)
        t0 = time.monotonic()
        sent = 0  # samples whose time has come
        period = 1.0 / self.rate
        while not self._stop.is_set() and sent < total:
            due = int(min(total, int((time.monotonic() - t0) * self.rate) + 1))
            if due > sent:
                self._emit(sent, due)
                sent = due
                self.stats.samples_played = sent
            self._service_commands(sent - 1)
            wait = max(0.0, t0 + sent * period - time.monotonic())
            if self.protocol == "fispec":
                # Wake as soon as a poll arrives: a device answers P> at once.
                select.select([self.port.master], [], [], min(wait, 0.01))
            else:
                time.sleep(min(wait, 0.01))
        end = time.monotonic() + self.linger
        while not self._stop.is_set() and any(p.client_connected() for p in self._ports()) and (
                time.monotonic() < end or any(p.backlog for p in self._ports())):
            self._service_commands(sent - 1)
            time.sleep(0.002)

    def _index(self, k: int) -> tuple[int, int]:
        """Sample index into the playback and the loop count for the k-th played sample."""
        n = len(self.playback)
        return k % n, k // n

    def _emit(self, start: int, stop: int) -> None:
        """Push samples [start, stop) (native frames and/or load-cell lines)."""
        pb = self.playback
        chunks: list[bytes] = []
        lines: list[bytes] = []
        for k in range(start, stop):
            i, lap = self._index(k)
            if lap != self.stats.loops:
                self.stats.loops = lap
            if self.protocol == "native":
                frame = P.encode_frame(k, int(pb.t_us[i]) + lap * self._span_us,
                                       pb.wl_fm[i].tolist())
                chunks.append(self._fault(frame, int(self.faults[i])))
            if self.loadcell_port is not None:
                lines.append(P.encode_loadcell_line(P.LoadCellSample(
                    k, float(pb.x_mm[i]), float(pb.y_mm[i]), float(pb.force_N[i]),
                    int(pb.contact[i]), int(pb.press[i]))))
        if chunks:
            data = b"".join(chunks)
            if data:
                self.port.write(data)
        if lines:
            self.loadcell_port.write(b"".join(lines))  # type: ignore[union-attr]
            self.stats.loadcell_lines += len(lines)

    def _fault(self, frame: bytes, code: int) -> bytes:
        """The bytes actually put on the line for ``frame`` under fault ``code``."""
        st = self.stats
        rng = self.rng
        kind = FAULTS[code]
        if kind == "none":
            st.frames_sent += 1
            return frame
        if kind == "drop":
            st.dropped += 1
            return b""
        if kind == "flip":
            st.flipped += 1
            buf = bytearray(frame)
            # 1-3 distinct bits: both frame checks detect every such error in frames this short.
            for bit in rng.choice(len(buf) * 8, size=int(rng.integers(1, 4)), replace=False):
                buf[bit // 8] ^= 1 << (bit % 8)
            return bytes(buf)
        if kind == "truncate":
            st.truncated += 1
            # At least the CRC is cut: following bytes complete it only by a 2**-32 chance
            # (2**-16 with version-1 frames), and the reader's gate refuses what they make.
            return frame[:int(rng.integers(1, len(frame) - 2))]
        st.garbage_bursts += 1
        burst = rng.integers(0, 256, size=int(rng.integers(1, 65)), dtype=np.uint8).tobytes()
        st.garbage_bytes += len(burst)
        st.frames_sent += 1
        return burst + frame

    def _service_commands(self, latest: int) -> None:
        """Read what the host sent; answer FiSpec commands (native mode ignores input)."""
        for p in self._ports():
            p.flush()
            data = p.read()
            if not data or p is not self.port or self.protocol != "fispec":
                continue
            for cmd in self._parser.feed(data):
                self.stats.commands += 1
                self._answer(cmd, latest)

    def _answer(self, cmd: bytes, latest: int) -> None:
        n_ch = self.playback.wl_fm.shape[1]
        if cmd == P.CMD_IDENT:
            self.port.write(FISPEC_IDENT + b" N=%d\r\n" % n_ch)
        elif cmd == P.CMD_PARAMS:
            self.port.write(b"#Pixel_512#Channels_%d#Rate_%d#\r\n" % (n_ch, round(self.rate)))
        elif cmd == P.CMD_PEAKS:
            # Before playback starts the device already measures: it reports the first sample.
            latest = max(latest, 0)
            i, _lap = self._index(latest)
            wl = self.playback.wl_fm[i]
            units = np.round(wl / (P.FM_PER_NM // P.FISPEC_UNITS_PER_NM)).astype(np.int64)
            amp = np.where(wl != 0, FISPEC_AMPLITUDE, 0)
            frame = P.encode_fispec_frame(units.tolist(), amp.tolist(), FISPEC_TEMPERATURE_C100,
                                          latest)
            self.port.write(self._fault(frame, int(self.faults[i])))
        else:
            self.stats.ignored_commands += 1


def load_playback(scene: str | None = None, data: str | None = None, *, seed: int | None = None,
                  device: int | None = None) -> Playback:
    """The recording to play: a simulated scene or a dataset file."""
    if (scene is None) == (data is None):
        raise ValueError("give exactly one of scene or data")
    if data is not None:
        from fbgforce.recordings import dataset

        return Playback.from_dataset(dataset.load(data))
    from fbgforce import sim

    return Playback.from_dataset(sim.simulate(scene, seed=seed, device=device))


class HyperionEmulator(_BackgroundPlayer):
    """A virtual Hyperion interrogator on TCP: the command port and the peak stream.

    The command port answers ``#GetSerialNumber``, ``#GetFirmwareVersion``,
    ``#GetFPGAVersion``, ``#GetInstrumentName``, ``#isready``, ``#GetDutChannelCount``,
    ``#GetMaximumPeakCountPerDutChannel``, ``#GetLaserScanSpeed``,
    ``#GetAvailableLaserScanSpeeds`` and ``#GetPeaks`` (the latest sample); any other command
    gets an error status with a message, as the instrument does. The stream port pushes one
    peaks record per sample to every connected client, at ``rate`` samples per second, with
    the sample counter as serial number and the scene's time as timestamp (plus ``t0_s``).
    Each grating's peak goes on the channel the :class:`~fbgforce.interrogator.hyperion.PeakMap`
    gives it; a lost peak (NaN in the scene) is simply missing from its channel.

    TCP does not garble bytes, so of the line faults only ``drop`` applies (a record the device
    skips); any other fault code in the plan is played as a drop too.

    Parameters
    ----------
    address, command_port, stream_port
        Where to listen (port 0: any free port; the ports taken are :attr:`command_port` and
        :attr:`stream_port` after construction).
    wait_client, linger, loop, faults, rate, loadcell, loadcell_link
        As for :class:`Emulator` (playback waits for a client of the stream port, and of the
        load-cell pty if there is one; its lines carry the serial number as counter).
    """

    _thread_name = "fbgforce-hyperion-emulator"

    def __init__(self, playback: Playback, *, rate: float = 1000.0,
                 faults: np.ndarray | None = None, address: str = "127.0.0.1",
                 command_port: int = 51971, stream_port: int = 51972,
                 peak_map: Any = None, channels: int = 4, wait_client: bool = True,
                 linger: float = 2.0, loop: bool = False, t0_s: int = 1_700_000_000,
                 serial_number: str = "HYP-EMU-0001", loadcell: bool = False,
                 loadcell_link: str | None = None) -> None:
        if not rate > 0:
            raise ValueError("rate must be positive")
        if len(playback) == 0:
            raise ValueError("nothing to play: the recording has no samples")
        self.playback = playback
        self.rate = float(rate)
        n = len(playback)
        self.faults = (np.zeros(n, dtype=np.uint8) if faults is None
                       else np.asarray(faults, np.uint8))
        if self.faults.shape != (n,):
            raise ValueError(f"fault plan has {self.faults.shape} entries, recording {n}")
        self.peak_map = peak_map or H.PeakMap.default()
        if max(s.channel for s in self.peak_map.selectors) > channels:
            raise ValueError(f"the peak map uses a channel beyond the instrument's {channels}")
        self.channels = channels
        self.wait_client = wait_client
        self.linger = linger
        self.loop = loop
        self.t0_s = t0_s
        self.serial_number = serial_number
        self.stats = EmulatorStats()
        self.stream_clients_served = 0
        self._wl_nm = H.gratings_nm(playback.wl_fm)
        self.loadcell_port = PtyEndpoint(loadcell_link) if loadcell else None
        self._listen: dict[str, socket.socket] = {}
        try:
            for role, port in (("command", command_port), ("stream", stream_port)):
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind((address, port))
                s.listen(8)
                s.setblocking(False)
                self._listen[role] = s
        except OSError:
            self.close()
            raise
        self.address = address
        self.command_port = self._listen["command"].getsockname()[1]
        self.stream_port = self._listen["stream"].getsockname()[1]
        self._cmd_clients: dict[Any, bytearray] = {}
        self._stream_clients: dict[Any, bytearray] = {}
        self._latest = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        step = int(np.median(np.diff(playback.t_us))) if n > 1 else int(round(1e6 / self.rate))
        self._span_us = int(playback.t_us[-1] - playback.t_us[0]) + step

    @property
    def url(self) -> str:
        """The ``hyperion://`` URL a reader opens."""
        base = f"hyperion://{self.address}:{self.command_port}"
        return base if self.stream_port == self.command_port + 1 else (
            f"{base}?stream={self.stream_port}")

    @property
    def paths(self) -> dict[str, str]:
        out = {"interrogator": self.url}
        if self.loadcell_port is not None:
            out["loadcell"] = self.loadcell_port.name
        return out

    def close(self) -> None:
        for s in list(self._listen.values()) + list(getattr(self, "_cmd_clients", {})) + list(
                getattr(self, "_stream_clients", {})):
            try:
                s.close()
            except OSError:
                pass
        self._listen = {}
        self._cmd_clients = {}
        self._stream_clients = {}
        if getattr(self, "loadcell_port", None) is not None:
            self.loadcell_port.close()  # type: ignore[union-attr]

    def run(self, max_samples: int | None = None) -> EmulatorStats:
        """Play (blocking) until the recording, ``max_samples`` or :meth:`stop` ends it."""
        try:
            self._run(max_samples)
        finally:
            self.close()
        return self.stats

    # -- internals -----------------------------------------------------------------------
    def _record(self, k: int) -> bytes:
        i, lap = k % len(self.playback), k // len(self.playback)
        t_us = int(self.playback.t_us[i]) + lap * self._span_us
        chans = self.peak_map.to_channels(self._wl_nm[i], self.channels)
        t_ns = t_us * 1000
        return H.encode_peaks(k, self.t0_s + t_ns // 1_000_000_000, t_ns % 1_000_000_000,
                                   chans)

    def _service(self, wait: float) -> None:
        """Accept clients, answer commands, push queued stream bytes (waits at most ``wait``)."""
        if self.loadcell_port is not None:
            self.loadcell_port.flush()
            self.loadcell_port.read()  # a stage controller ignores what the host sends
        readable = list(self._listen.values()) + list(self._cmd_clients)
        writable = [c for c, q in self._stream_clients.items() if q]
        try:
            r, w, _ = select.select(readable, writable, [], max(0.0, wait))
        except (OSError, ValueError):
            return
        for s in r:
            if s is self._listen.get("command") or s is self._listen.get("stream"):
                try:
                    conn, _ = s.accept()
                except OSError:
                    continue
                conn.setblocking(False)
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                if s is self._listen["command"]:
                    self._cmd_clients[conn] = bytearray()
                else:
                    self._stream_clients[conn] = bytearray()
                    self.stream_clients_served += 1
                continue
            try:
                data = s.recv(4096)
            except OSError:
                data = b""
            if not data:
                self._drop(s)
                continue
            buf = self._cmd_clients[s]
            buf += data
            self._answer_all(s, buf)
        for s in w:
            self._push(s)

    def _drop(self, s: Any) -> None:
        self._cmd_clients.pop(s, None)
        self._stream_clients.pop(s, None)
        try:
            s.close()
        except OSError:
            pass

    def _push(self, s: Any) -> None:
        q = self._stream_clients.get(s)
        if not q:
            return
        try:
            n = s.send(q)
        except BlockingIOError:
            return
        except OSError:
            self._drop(s)
            return
        self.stats.bytes_sent += n
        del q[:n]

    def _answer_all(self, s: Any, buf: bytearray) -> None:
        while len(buf) >= H.REQUEST_HEADER.size:
            _opt, _res, cmd_len, arg_len = H.REQUEST_HEADER.unpack_from(buf, 0)
            end = H.REQUEST_HEADER.size + cmd_len + arg_len
            if len(buf) < end:
                return
            cmd = bytes(buf[H.REQUEST_HEADER.size:H.REQUEST_HEADER.size + cmd_len]).decode(
                "ascii", errors="replace")
            del buf[:end]
            self.stats.commands += 1
            reply = self._answer(cmd)
            try:
                s.sendall(reply)
            except OSError:
                self._drop(s)
                return

    def _answer(self, cmd: str) -> bytes:
        c = cmd.lower()
        text = {"#getserialnumber": self.serial_number, "#getfirmwareversion": "fbgforce-emu",
                "#getfpgaversion": "fbgforce-emu", "#getinstrumentname": "fbgforce virtual si155"}
        if c in text:
            return H.encode_response(text[c].encode("ascii"))
        if c == "#isready":
            return H.encode_response(b"\x01")
        if c == "#getdutchannelcount":
            return H.encode_response(struct.pack("<I", self.channels))
        if c == "#getmaximumpeakcountperdutchannel":
            return H.encode_response(struct.pack("<I", 16))
        if c == "#getlaserscanspeed":
            return H.encode_response(struct.pack("<I", int(round(self.rate))))
        if c == "#getavailablelaserscanspeeds":
            return H.encode_response(struct.pack("<I", int(round(self.rate))))
        if c == "#getpeaks":
            # Before playback the instrument already measures: it reports the first sample.
            return H.encode_response(self._record(max(self._latest, 0)))
        self.stats.ignored_commands += 1
        return H.encode_response(message=f"Unknown command {cmd}", status=1)

    def _run(self, max_samples: int | None) -> None:
        n = len(self.playback)
        total: float = n if not self.loop else math.inf
        if max_samples is not None:
            total = min(total, max_samples)
        lc = self.loadcell_port
        if self.wait_client:
            while not self._stop.is_set() and not (
                    self._stream_clients and (lc is None or lc.client_connected())):
                self._service(0.01)
            if lc is not None:  # let the load-cell client finish opening (see Emulator._run)
                settle = time.monotonic() + START_DELAY_S
                while not self._stop.is_set() and time.monotonic() < settle:
                    self._service(0.005)
        t0 = time.monotonic()
        sent = 0
        period = 1.0 / self.rate
        pb = self.playback
        while not self._stop.is_set() and sent < total:
            due = int(min(total, int((time.monotonic() - t0) * self.rate) + 1))
            if due > sent:
                chunks = []
                lines = []
                for k in range(sent, due):
                    i = k % n
                    self.stats.loops = k // n
                    if lc is not None:
                        lines.append(P.encode_loadcell_line(P.LoadCellSample(
                            k, float(pb.x_mm[i]), float(pb.y_mm[i]), float(pb.force_N[i]),
                            int(pb.contact[i]), int(pb.press[i]))))
                    if self.faults[i] != FAULT_CODE["none"]:
                        self.stats.dropped += 1
                        continue
                    chunks.append(H.encode_stream_message(self._record(k)))
                    self.stats.frames_sent += 1
                data = b"".join(chunks)
                for c, q in list(self._stream_clients.items()):
                    q += data
                    self._push(c)
                if lines and lc is not None:
                    lc.write(b"".join(lines))
                    self.stats.loadcell_lines += len(lines)
                sent = due
                self._latest = sent - 1
                self.stats.samples_played = sent
            self._service(max(0.0, min(t0 + sent * period - time.monotonic(), 0.01)))
        end = time.monotonic() + self.linger
        while not self._stop.is_set() and (
                self._stream_clients or self._cmd_clients
                or (lc is not None and lc.client_connected())) and (
                time.monotonic() < end or any(self._stream_clients.values())
                or (lc is not None and lc.backlog)):
            self._service(0.005)
