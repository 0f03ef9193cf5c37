"""Live estimation from an interrogator stream (``fbgforce stream``).

Samples from a reader (:mod:`fbgforce.interrogator.reader`) go through the shipped pipeline as
they arrive. The runtime is tared on the first ``tare_samples`` samples (the fingertip must be
unloaded when the stream starts, as at the start of every calibration file); those samples
are then run too, so the estimates of the whole stream are exactly what the offline engine
gives on the same samples with the same baseline::

    fbgforce.evaluation.engines.run_engine("fixed", model_dir, model, wl_nm, baseline_nm)

Lost frames are not filled in: the filter sees the samples that arrived (a gap of a few
samples shifts the filter's time base by as much; the count is in the status line and the
summary).

While it streams, :meth:`LiveEstimator.tare` and :meth:`LiveEstimator.reset` take a new
baseline (docs/serial.md, "Tare, reset and health while streaming"; docs/protocol.md, the UDP
control datagram; docs/ros2.md, the ROS 2 services): a tare averages the next
``tare_samples`` samples (the window) and takes their mean as the baseline, from the sample
after the window on; a sensor
fault inside the window (or a window that does not fill within ``command_timeout`` seconds)
fails it and keeps the baseline. A reset first starts the runtime's state afresh (filter
history, memory, decision, fault and at-rest trackers, the baseline back to the last tare's)
and then tares the same way. Commands are applied in the order given, between two samples,
never inside one; every one is answered once (:class:`Command`).
"""
from __future__ import annotations

import contextlib
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, Sequence, TextIO

import numpy as np

from fbgforce import contract, fileio, signals
from fbgforce.model import freshness
from fbgforce.model import floatref, modeldir
from fbgforce.errors import InputError
from fbgforce.interrogator.health import Health
from fbgforce.interrogator.protocol import Frame, fm_to_nm, nm_to_fm
from fbgforce.interrogator.publish import estimate_records
from fbgforce.interrogator.reader import Reader, iter_batches

ENGINES = ("fixed", "float")
#: Gratings the model reads per sample (FBG 1..4 and T): the first ones of a wider frame.
N_GRATINGS = 5
OUTPUT_KEYS = ("contact", "p_contact", "force_N", "x_mm", "y_mm", "status")
#: The fixed-point runtime's integer outputs, also returned by the fixed engine (publishing).
RAW_KEYS = ("force_mN", "x_um", "y_um", "contact_conf_q15")
CSV_COLUMNS = ("seq", "t_us", "host_s", "wl1_nm", "wl2_nm", "wl3_nm", "wl4_nm", "wlT_nm",
               *OUTPUT_KEYS)
#: Samples a tare command averages when the stream started on the model's baseline
#: (``tare_samples`` 0).
DEFAULT_TARE_SAMPLES = 200
#: Seconds a command's window may take to fill before it fails (no samples: a silent link).
COMMAND_TIMEOUT_S = 5.0
#: Commands waiting for their turn at most; one more is refused at once ("busy").
MAX_QUEUED_COMMANDS = 64
_SENSOR_FAULT = contract.STATUS_FLAG["SENSOR_FAULT"]
#: A peak outside these (fm) is lost: the runtime's tare skips such a sample.
_FM_MIN, _FM_MAX = contract.LIMIT["WL_MIN_FM"], contract.LIMIT["WL_MAX_FM"]


@dataclass
class Command:
    """A tare or reset given to a :class:`LiveEstimator` and, once applied, its answer.

    Attributes
    ----------
    name
        ``"tare"`` or ``"reset"``.
    token
        Whatever the caller gave to route the answer (a UDP sender, a ROS 2 request).
    done
        Answered: ``ok`` and ``message`` hold the answer.
    ok
        The new baseline was taken; False: the baseline is the one before.
    message
        What was done (the baseline's change per grating in pm) or why not.
    change_pm
        The baseline's change (new - old) per grating (FBG 1..4, T), pm; zeros on failure.
    samples
        Samples averaged for the new baseline (0 on failure).
    faults
        Samples of the window with a sensor fault (a failure when > 0).
    requested_s, started_s, answered_s
        When it was given, when its window opened and when it was answered
        (``time.monotonic()``; None until then).
    """

    name: str
    token: Any = None
    done: bool = False
    ok: bool = False
    message: str = ""
    change_pm: list[float] = field(default_factory=lambda: [0.0] * N_GRATINGS)
    samples: int = 0
    faults: int = 0
    requested_s: float = 0.0
    started_s: float | None = None
    answered_s: float | None = None


class LiveEstimator:
    """Tare, then estimate batch after batch with the filter state carried across batches.

    Parameters
    ----------
    model_dir
        Model directory (``fixed`` needs ``model.fbgm`` from ``fbgforce export``).
    engine
        ``"fixed"``: the C fixed-point runtime (what ships). ``"float"``: the float64 reference
        pipeline of :mod:`fbgforce.model`, for machines without the C extension.
    tare_samples
        Samples to tare on (their mean, as the C runtime's tare computes it). 0 = use the
        model's training baseline. A tare or reset command averages as many (or
        :data:`DEFAULT_TARE_SAMPLES` when 0).
    command_timeout
        Seconds a tare's window may take to fill before the tare fails (module docstring).
    """

    def __init__(self, model_dir: str | Path, *, engine: str = "fixed", tare_samples: int = 200,
                 command_timeout: float = COMMAND_TIMEOUT_S) -> None:
        if engine not in ENGINES:
            raise InputError(f"engine must be one of {', '.join(ENGINES)}", column="--engine")
        if tare_samples < 0:
            raise InputError("must be >= 0", column="--tare-samples")
        self.model_dir = Path(model_dir)
        self.model = modeldir.load(model_dir)
        self.engine = engine
        self.tare_samples = tare_samples
        self._pending: list[np.ndarray] = []
        self._n_pending = 0
        self.baseline_fm: np.ndarray | None = None
        self.compute_s = 0.0
        self.estimated = 0
        self.command_timeout = command_timeout
        self.window_samples = tare_samples or DEFAULT_TARE_SAMPLES
        #: Baseline of the last tare (the tracker moves :attr:`baseline_fm` from it).
        self.tared_fm: np.ndarray | None = None
        self._queue: deque[Command] = deque()
        self._active: Command | None = None
        self._window: list[np.ndarray] = []
        self._window_n = 0
        self._window_faults = 0
        self._answered: list[Command] = []
        #: Commands applied and failed, by name (``tare``, ``reset``, ``failed``).
        self.command_counts = {"tare": 0, "reset": 0, "failed": 0}
        if engine == "fixed":
            from fbgforce.pybind import Runtime

            self._rt = Runtime(self.model_dir, float_model=self.model)
        else:
            self._pipeline: floatref.FloatPipeline | None = None
        if tare_samples == 0:
            self._set_baseline(nm_to_fm(self.model.baseline_nm))

    @property
    def baseline_nm(self) -> np.ndarray | None:
        return None if self.baseline_fm is None else fm_to_nm(self.baseline_fm)

    def _set_baseline(self, base_fm: np.ndarray) -> None:
        self.baseline_fm = np.asarray(base_fm, dtype=np.int64)
        self.tared_fm = self.baseline_fm.copy()
        if self.engine == "fixed":
            self._rt.set_baseline(self.baseline_fm)  # also starts the filter from zero history
        else:
            self._pipeline = floatref.FloatPipeline(self.model, fm_to_nm(self.baseline_fm))

    @property
    def tracker_offset_pm(self) -> float:
        """The largest correction the at-rest tracker has made to a strain grating's baseline
        since the last tare, pm (the runtime flags BASELINE_LIMIT at its bound)."""
        if self.tared_fm is None:
            return 0.0
        if self.engine == "fixed":
            now = self._rt.baseline_fm
        else:
            assert self._pipeline is not None
            now = nm_to_fm(self._pipeline.baseline_nm)
        return float(np.max(np.abs(now[:N_GRATINGS - 1] - self.tared_fm[:N_GRATINGS - 1]))) / 1000

    @property
    def tracker_bound_pm(self) -> float:
        """The tracker's bound on that correction, pm (0: no tracker)."""
        iu = self.model.in_use
        return float(iu.track_limit_pm) if iu.track_shift else 0.0

    def digest(self) -> str:
        """The model's digest (:func:`fbgforce.model.freshness.model_digest`; the one its export
        recorded)."""
        return freshness.model_digest(self.model)

    def tare(self, token: Any = None) -> Command:
        """Tare while streaming: the mean of the next ``tare_samples`` samples becomes the
        baseline (module docstring). Returns the command; it is answered (``done``) by the
        :meth:`push` that completes its window, or by :meth:`expire`."""
        return self._give("tare", token)

    def reset(self, token: Any = None) -> Command:
        """Start the runtime's state afresh (the baseline back to the last tare's), then tare
        as :meth:`tare` does."""
        return self._give("reset", token)

    def _give(self, name: str, token: Any) -> Command:
        cmd = Command(name, token, requested_s=time.monotonic())
        if len(self._queue) >= MAX_QUEUED_COMMANDS:
            self._answer(cmd, False, f"busy: {MAX_QUEUED_COMMANDS} commands already waiting")
        else:
            self._queue.append(cmd)
        return cmd

    def answered(self) -> list[Command]:
        """The commands answered since the last call, in the order answered."""
        out, self._answered = self._answered, []
        return out

    @property
    def busy(self) -> bool:
        """A command is being applied or waits."""
        return self._active is not None or bool(self._queue)

    def expire(self, now: float | None = None) -> None:
        """Fail a command whose window has not filled ``command_timeout`` seconds after it
        was given (a silent link); the baseline stays. The next one starts afresh."""
        now = time.monotonic() if now is None else now
        cmd = self._active
        if cmd is not None and now - cmd.requested_s >= self.command_timeout:
            self._answer(cmd, False, f"only {self._window_n} of {self.window_samples} samples "
                                     f"arrived within {self.command_timeout:g} s; baseline kept")
            self._active = None
        while self._queue and now - self._queue[0].requested_s >= self.command_timeout:
            cmd = self._queue.popleft()
            self._answer(cmd, False, f"no sample within {self.command_timeout:g} s; "
                                     f"baseline kept")

    def cancel(self, reason: str) -> None:
        """Fail every command not yet answered (the stream ends); the baseline stays."""
        pending = ([self._active] if self._active is not None else []) + list(self._queue)
        self._active = None
        self._queue.clear()
        for cmd in pending:
            self._answer(cmd, False, f"{reason}; baseline kept")

    def _answer(self, cmd: Command, ok: bool, message: str) -> None:
        cmd.done, cmd.ok, cmd.message = True, ok, message
        cmd.answered_s = time.monotonic()
        if ok:
            self.command_counts[cmd.name] += 1
        else:
            self.command_counts["failed"] += 1
        self._answered.append(cmd)

    def _start_command(self) -> None:
        """Between two samples: take the next command and open its window."""
        if self._active is not None or not self._queue or self.baseline_fm is None:
            return
        cmd = self._active = self._queue.popleft()
        cmd.started_s = time.monotonic()
        self._window, self._window_n, self._window_faults = [], 0, 0
        if cmd.name == "reset":
            assert self.tared_fm is not None
            self._set_baseline(self.tared_fm)  # every state afresh, the tare's baseline
            if self.engine == "fixed":
                self._rt.reset()

    def _close_window(self) -> None:
        cmd = self._active
        assert cmd is not None and self.baseline_fm is not None
        self._active = None
        rows = np.concatenate(self._window)
        self._window = []
        cmd.faults = self._window_faults
        if self._window_faults:
            self._answer(cmd, False, f"sensor fault on {self._window_faults} of {len(rows)} "
                                     f"samples of the tare window; baseline kept"
                         + (" (the state was reset)" if cmd.name == "reset" else ""))
            return
        old = self.baseline_fm.copy()
        self._tare(rows)
        cmd.change_pm = [round(float(v) / 1000.0, 3) for v in (self.baseline_fm - old)]
        cmd.samples = len(rows)
        self._answer(cmd, True, f"{cmd.name}: new baseline from {len(rows)} samples, change "
                                + " ".join(f"{v:+.1f}" for v in cmd.change_pm)
                                + " pm (FBG 1..4, T)")

    def push(self, wl_fm: np.ndarray) -> dict[str, np.ndarray]:
        """Estimates for the samples that became computable (none while taring at start)."""
        wl_fm = np.asarray(wl_fm, dtype=np.int64).reshape(-1, 5)
        if self.baseline_fm is None:
            self._pending.append(wl_fm)
            self._n_pending += len(wl_fm)
            if self._n_pending < self.tare_samples:
                return _empty()
            rows = np.concatenate(self._pending)
            self._pending = []
            self._tare(rows[:self.tare_samples])
            # The samples of earlier batches came before any command given meanwhile.
            earlier = self._timed(rows[:len(rows) - len(wl_fm)])
            now = self._commanded(wl_fm)
            return {k: np.concatenate([earlier[k], now[k]]) for k in now}
        return self._commanded(wl_fm)

    def _commanded(self, wl_fm: np.ndarray) -> dict[str, np.ndarray]:
        """Estimates of a batch, the commands applied between its samples."""
        self._start_command()
        if self._active is None:
            return self._timed(wl_fm)
        # A window ends inside this batch: the samples after it run on the new baseline.
        parts = []
        i = 0
        while i < len(wl_fm):
            self._start_command()
            if self._active is None:
                parts.append(self._timed(wl_fm[i:]))
                break
            take = min(len(wl_fm) - i, self.window_samples - self._window_n)
            rows = wl_fm[i:i + take]
            out = self._timed(rows)
            parts.append(out)
            bad = (np.asarray(out["status"], dtype=np.uint32) & _SENSOR_FAULT) != 0
            bad |= ((rows < _FM_MIN) | (rows > _FM_MAX)).any(axis=1)
            self._window.append(rows)
            self._window_n += take
            self._window_faults += int(np.count_nonzero(bad))
            i += take
            if self._window_n >= self.window_samples:
                self._close_window()
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _timed(self, wl_fm: np.ndarray) -> dict[str, np.ndarray]:
        if not len(wl_fm):
            return {k: np.zeros(0) for k in OUTPUT_KEYS + (RAW_KEYS if self.engine == "fixed"
                                                            else ())}
        t0 = time.perf_counter()
        out = self._run(wl_fm)
        self.compute_s += time.perf_counter() - t0
        self.estimated += len(wl_fm)
        return out

    def _tare(self, rows: np.ndarray) -> None:
        if self.engine == "fixed":
            base = self._rt.tare(rows.astype(np.int32))
            self._set_baseline(nm_to_fm(base))
        else:
            self._set_baseline(np.round(rows.mean(axis=0)).astype(np.int64))

    def _run(self, wl_fm: np.ndarray) -> dict[str, np.ndarray]:
        if self.engine == "fixed":
            out = self._rt.run(wl_fm.astype(np.int32))
            return {k: np.asarray(out[k]) for k in OUTPUT_KEYS + RAW_KEYS}
        # Float: the reference pipeline fed batch by batch (its filter history, memory,
        # decision and tracker carry over, so every sample gets what the whole recording
        # would give it).
        assert self._pipeline is not None
        pred = self._pipeline.push(fm_to_nm(wl_fm))
        pred["status"] = np.zeros(len(wl_fm), dtype=np.uint32)
        return {k: np.asarray(pred[k]) for k in OUTPUT_KEYS}


def _bad_frames(stats: dict[str, int]) -> int:
    """Frames received but not delivered for being damaged or implausible."""
    return sum(stats.get(k, 0) for k in ("crc_errors", "header_errors", "bad_replies",
                                         "implausible_frames"))


def _empty() -> dict[str, np.ndarray]:
    return {k: np.zeros(0) for k in OUTPUT_KEYS}


class StatusLine:
    """One-line live status on stderr: rewritten in place on a terminal, else once a second."""

    def __init__(self, stream: TextIO | None = None, enabled: bool = True) -> None:
        # Looked up now, not at import: sys.stderr may have been replaced since.
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.tty = bool(getattr(stream, "isatty", lambda: False)())
        self.period = 0.2 if self.tty else 1.0
        self._last = time.monotonic()
        self._count = 0
        self.rate_hz = 0.0

    def update(self, n_new: int, last: dict[str, Any] | None, stats: dict[str, int],
               force: bool = False) -> None:
        self._count += n_new
        now = time.monotonic()
        dt = now - self._last
        if not force and dt < self.period:
            return
        if dt > 0:
            self.rate_hz = self._count / dt
        self._last, self._count = now, 0
        if not self.enabled:
            return
        if last is None:
            text = f"{self.rate_hz:7.1f} Hz  taring...  lost {stats.get('lost_frames', 0)}"
        else:
            x = last["x_mm"] if np.isfinite(last["x_mm"]) else float("nan")
            y = last["y_mm"] if np.isfinite(last["y_mm"]) else float("nan")
            text = (f"{self.rate_hz:7.1f} Hz  contact {int(last['contact'])} "
                    f"({last['p_contact']:.2f})  F {last['force_N']:7.2f} N  "
                    f"x {x:6.2f} mm  y {y:6.2f} mm  lost {stats.get('lost_frames', 0)}  "
                    f"bad {_bad_frames(stats)}")
        if self.tty:
            self.stream.write("\r" + text + "\x1b[K")
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()


class Publication(Protocol):
    """Where the stream's estimates go: :class:`~fbgforce.interrogator.publish.PublisherProcess`
    (what ``fbgforce stream --publish`` uses) or :class:`~fbgforce.interrogator.publish.Outputs`.
    ``status`` takes the health snapshot of every second (:mod:`fbgforce.interrogator.health`)."""

    def publish(self, records: np.ndarray) -> None: ...

    def status(self, health: dict[str, Any]) -> None: ...

    def finish(self) -> dict[str, Any]: ...


class CommandSource(Protocol):
    """Where tare and reset commands come from while streaming: the UDP control port
    (:class:`~fbgforce.interrogator.control.ControlServer`) or the ROS 2 services (through the
    publishing process). :meth:`poll` returns the new commands as (name, token) pairs,
    :meth:`answer` gets each one's answer, once."""

    def poll(self) -> list[tuple[str, Any]]: ...

    def answer(self, cmd: Command) -> None: ...


@dataclass
class _Tally:
    """What a stream has received and estimated so far."""

    #: Received, not yet estimated (taring): frame, host time, arrival ns (-1: before the tare).
    waiting: list[tuple[Frame, float, int]] = field(default_factory=list)
    estimated: int = 0
    contact: int = 0
    max_force_N: float = 0.0
    last: dict[str, Any] | None = None
    t_first: float | None = None
    t_last: float | None = None
    #: Failed commands counted at the last health snapshot.
    failed_at_tick: int = 0

    def command_counts(self, estimator: LiveEstimator, advance: bool = True) -> dict[str, int]:
        """The estimator's command counts with the failures since the last snapshot; with
        ``advance`` the next snapshot counts from here."""
        counts = dict(estimator.command_counts)
        counts["failed_last_s"] = counts["failed"] - self.failed_at_tick
        if advance:
            self.failed_at_tick = counts["failed"]
        return counts


def run_stream(reader: Reader, estimator: LiveEstimator, *, out: str | Path | None = None,
               duration: float | None = None, max_samples: int | None = None,
               idle_timeout: float | None = None, start_timeout: float | None = None,
               status: bool = True, publication: Publication | None = None,
               commands: Sequence[CommandSource] = ()) -> dict[str, Any]:
    """Read, estimate, publish (``publication``, :mod:`fbgforce.interrogator.publish`) and
    (optionally) write a CSV of estimates until a stop condition.

    Between two batches it takes the tare and reset commands of ``commands``, gives them to
    the estimator and hands back their answers; once a second it takes the stream's health
    (:class:`~fbgforce.interrogator.health.Health`) and hands it to the publication, also
    while the device is silent.

    Returns the summary printed by ``fbgforce stream --json`` (keys in docs/cli.md). With a
    publication it holds ``publish_latency_us``: time from a sample's arrival (its batch
    returned by the reader) to its publication (the last output's send returned), over the
    samples that arrived after the tare (those before wait for the tare by design).
    """
    # The CSV appears under its name when the stream ends, however it ends (a signal, a lost
    # device): every estimate made is in it, and a full disk leaves no partial file.
    files = fileio.Outputs("--out")
    opened = contextlib.ExitStack()
    out = None if out is None else Path(out)
    fh = None if out is None else _open_estimates_csv(out, files, opened)
    line = StatusLine(enabled=status)
    tally = _Tally()
    stopped_by = None
    health = Health(estimator.digest(), estimator.tracker_bound_pm)
    try:
        for batch in iter_batches(reader, duration=duration, max_samples=max_samples,
                                  idle_timeout=idle_timeout, start_timeout=start_timeout,
                                  empty=True):
            arrived_ns = time.monotonic_ns()
            now = arrived_ns / 1e9
            _take_commands(commands, estimator, now)
            if health.due(now):
                snapshot = health.snapshot(now, reader.stats(), estimator.tracker_offset_pm,
                                           tally.command_counts(estimator))
                if publication is not None:
                    publication.status(snapshot)
            if not batch:
                if tally.t_first is not None:  # a silent device shows as a falling rate
                    line.update(0, tally.last, reader.stats())
                continue
            _estimate_batch(batch, arrived_ns, now, estimator, tally, health, publication, fh)
            line.update(len(batch), tally.last, reader.stats())
    except KeyboardInterrupt as exc:
        # Ctrl-C or SIGTERM is how a live stream normally ends: still write and summarise.
        stopped_by = signals.signal_name(exc)
    finally:
        line.close()
        opened.close()
        files.commit()
    return _stream_summary(reader, estimator, tally, health, publication, out, stopped_by)


def _open_estimates_csv(out: Path, files: fileio.Outputs, opened: contextlib.ExitStack
                        ) -> TextIO:
    """The estimates' CSV, its header written; ``files`` gives it its name when it commits."""
    if out.suffix.lower() != ".csv":
        raise InputError("estimates are written as CSV: use a .csv name", path=str(out),
                         column="--out")
    fh = opened.enter_context(files.open(out, "w", encoding="utf-8", newline="\n"))
    fh.write("# fbgforce stream: raw samples and live estimates; host_s = receive time\n")
    fh.write(",".join(CSV_COLUMNS) + "\n")
    return fh


def _take_commands(commands: Sequence[CommandSource], estimator: LiveEstimator,
                   now: float) -> None:
    """Give the estimator the sources' new commands and hand back the answered ones."""
    for source in commands:
        for name, token in source.poll():
            give = estimator.reset if name == "reset" else estimator.tare
            give((source, token))
    estimator.expire(now)
    _hand_back_answers(estimator)


def _hand_back_answers(estimator: LiveEstimator) -> None:
    for cmd in estimator.answered():
        src, cmd.token = cmd.token
        src.answer(cmd)


def _estimate_batch(batch: list[Frame], arrived_ns: int, now: float, estimator: LiveEstimator,
                    tally: _Tally, health: Health, publication: Publication | None,
                    fh: TextIO | None) -> None:
    """Estimate one batch; publish and write the samples it completes."""
    health.samples(len(batch), now)
    tally.t_first = now if tally.t_first is None else tally.t_first
    tally.t_last = now
    arrival = arrived_ns if estimator.baseline_fm is not None else -1
    tally.waiting.extend((f, now, arrival) for f in batch)
    est = estimator.push(np.array([f.wl_fm[:N_GRATINGS] for f in batch], dtype=np.int64))
    k = len(est["contact"])
    if not k:
        return
    done, tally.waiting = tally.waiting[:k], tally.waiting[k:]
    if publication is not None:
        publication.publish(estimate_records([f for f, _, _ in done], est,
                                             [a for _, _, a in done]))
    if fh is not None:
        _write_rows(fh, done, est)
    tally.estimated += k
    health.estimates(est["status"])
    tally.contact += int(np.count_nonzero(est["contact"]))
    tally.max_force_N = max(tally.max_force_N, float(np.max(est["force_N"])))
    tally.last = {key: est[key][-1] for key in OUTPUT_KEYS}


def _stream_summary(reader: Reader, estimator: LiveEstimator, tally: _Tally, health: Health,
                    publication: Publication | None, out: Path | None,
                    stopped_by: str | None) -> dict[str, Any]:
    """The stream's summary once it ended (keys in docs/cli.md, ``stream``)."""
    stats = reader.stats()
    span = (tally.t_last - tally.t_first) \
        if tally.t_first is not None and tally.t_last is not None else 0.0
    estimator.cancel("the stream ended before the window filled")
    _hand_back_answers(estimator)  # answered by the last batch, after the loop's turn
    # The health at the end: the period since the last snapshot, not yet judged.
    last_health = health.snapshot(time.monotonic(), stats, estimator.tracker_offset_pm,
                                  tally.command_counts(estimator, advance=False), advance=False)
    n, received = tally.estimated, tally.estimated + len(tally.waiting)
    return {
        "samples": n,
        "received": received,
        "duration_s": round(span, 3),
        "rate_hz": round((received - 1) / span, 1) if span > 0 else 0.0,
        "lost_frames": stats.get("lost_frames", 0),
        "bad_frames": _bad_frames(stats),
        "engine": estimator.engine,
        "baseline_nm": None if estimator.baseline_nm is None else estimator.baseline_nm.tolist(),
        "contact_fraction": tally.contact / n if n else 0.0,
        "max_force_N": tally.max_force_N,
        "compute_us_per_sample": 1e6 * estimator.compute_s / estimator.estimated
        if estimator.estimated else None,
        "out": None if out is None else str(out),
        "interrupted": stopped_by is not None,
        "signal": stopped_by,
        "reader": stats,
        "health": last_health,
        "commands": dict(estimator.command_counts),
        **(publication.finish() if publication is not None else {}),
    }


def _write_rows(fh: TextIO, frames: list[tuple[Frame, float, int]], est: dict[str, np.ndarray]
                ) -> None:
    wl = fm_to_nm(np.array([f.wl_fm[:N_GRATINGS] for f, _, _ in frames], dtype=np.int64))
    rows = []
    for i, (f, host, _) in enumerate(frames):
        x, y = est["x_mm"][i], est["y_mm"][i]
        rows.append(
            f"{f.seq},{f.t_us},{host:.6f},"
            + ",".join(f"{v:.6f}" for v in wl[i])
            + f",{int(est['contact'][i])},{est['p_contact'][i]:.6f},{est['force_N'][i]:.6f},"
            + ("" if not np.isfinite(x) else f"{x:.6f}") + ","
            + ("" if not np.isfinite(y) else f"{y:.6f}") + f",{int(est['status'][i])}\n")
    fh.write("".join(rows))


def load_estimates(path: str | Path) -> dict[str, np.ndarray]:
    """Read a CSV written by :func:`run_stream` into arrays by column (``wl_nm`` (n, 5) too)."""
    path = Path(path)
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if not ln.startswith("#")]
    if not lines or lines[0].split(",") != list(CSV_COLUMNS):
        raise InputError(f"not a 'fbgforce stream' estimates file (header must be "
                         f"{','.join(CSV_COLUMNS)})", path=str(path))
    if len(lines) == 1:
        table = np.zeros((0, len(CSV_COLUMNS)))
    else:
        table = np.genfromtxt(lines[1:], delimiter=",", dtype=np.float64, filling_values=np.nan)
        table = table.reshape(-1, len(CSV_COLUMNS))
    cols = {name: table[:, i] for i, name in enumerate(CSV_COLUMNS)}
    for k in ("seq", "t_us", "status"):
        cols[k] = cols[k].astype(np.int64)
    cols["contact"] = cols["contact"].astype(bool)
    cols["wl_nm"] = np.column_stack([cols[c] for c in CSV_COLUMNS[3:8]])
    return cols
