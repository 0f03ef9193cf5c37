"""Calibration recording (``fbgforce record``): interrogator + stage/load cell -> dataset CSV.

The interrogator port gives wavelengths tagged with a sample counter; the stage/load-cell port
gives one line per sample tagged with the same counter (docs/protocol.md). Samples are joined
on the counter; a sample that only one side delivered is dropped and counted, never guessed.
The result is written with :func:`fbgforce.recordings.dataset.save`, so it is validated against the
dataset contract and is ready for ``fbgforce train``; an ``.mcap`` output is a rosbag2 log of
the same samples (:mod:`fbgforce.interrogator.mcaplog`), read back by
:func:`fbgforce.recordings.dataset.load`.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce import fileio, signals
from fbgforce.errors import InputError
from fbgforce.interrogator.protocol import Frame, LoadCellSample, fm_to_nm
from fbgforce.interrogator.reader import LoadCellReader, Reader

#: Unmatched samples older than this many counts behind the newest are given up on.
JOIN_WINDOW = 2000
WL_VALID_NM = (1000.0, 2000.0)


class Joiner:
    """Pairs interrogator frames with load-cell lines by sample counter."""

    def __init__(self, window: int = JOIN_WINDOW) -> None:
        self.window = window
        self.frames: dict[int, Frame] = {}
        self.lines: dict[int, LoadCellSample] = {}
        self.pairs: list[tuple[Frame, LoadCellSample]] = []
        self.unmatched_frames = 0
        self.unmatched_lines = 0
        self._newest = -1

    def add(self, frames: list[Frame], lines: list[LoadCellSample]) -> None:
        for f in frames:
            s = self.lines.pop(f.seq, None)
            if s is None:
                self.frames[f.seq] = f
            else:
                self.pairs.append((f, s))
            self._newest = max(self._newest, f.seq)
        for s in lines:
            f = self.frames.pop(s.counter, None)
            if f is None:
                self.lines[s.counter] = s
            else:
                self.pairs.append((f, s))
            self._newest = max(self._newest, s.counter)
        self._expire(self._newest - self.window)

    def _expire(self, before: int) -> None:
        for key in [k for k in self.frames if k < before]:
            del self.frames[key]
            self.unmatched_frames += 1
        for key in [k for k in self.lines if k < before]:
            del self.lines[key]
            self.unmatched_lines += 1

    def finish(self) -> None:
        self.unmatched_frames += len(self.frames)
        self.unmatched_lines += len(self.lines)
        self.frames.clear()
        self.lines.clear()
        self.pairs.sort(key=lambda p: p[0].seq)


def pairs_to_dataset(pairs: list[tuple[Frame, LoadCellSample]], *, rate_hz: float,
                     source: str) -> tuple[Any, int]:
    """Build a :class:`fbgforce.recordings.dataset.Dataset`; returns it and the rows dropped for a lost
    peak (a wavelength outside 1000–2000 nm, which the contract rejects)."""
    from fbgforce.recordings.dataset import Dataset

    seq = np.array([f.seq for f, _ in pairs], dtype=np.int64)
    t_us = np.array([f.t_us for f, _ in pairs], dtype=np.int64)
    wl = fm_to_nm(np.array([f.wl_fm for f, _ in pairs], dtype=np.int64).reshape(-1, 5))
    ok = np.all((wl >= WL_VALID_NM[0]) & (wl <= WL_VALID_NM[1]), axis=1)
    # Device timestamps where the protocol has them (native, Hyperion), from the first sample
    # (a Hyperion clock counts from 1970: seconds since then would not keep µs in a CSV); else
    # the counter at the rate.
    t0 = t_us[0] if len(t_us) else 0
    t_s = np.where(t_us >= 0, (t_us - t0) / 1e6, (seq - (seq[0] if len(seq) else 0)) / rate_hz)
    contact = np.array([s.contact for _, s in pairs], dtype=bool)
    x = np.array([s.x_mm for _, s in pairs], dtype=np.float64)
    y = np.array([s.y_mm for _, s in pairs], dtype=np.float64)
    ds = Dataset(
        t_s=t_s, wl_nm=wl, contact=contact,
        x_mm=np.where(contact, x, np.nan), y_mm=np.where(contact, y, np.nan),
        force_N=np.array([s.force_N for _, s in pairs], dtype=np.float64),
        press_id=np.array([s.press for _, s in pairs], dtype=np.int64),
        extra={"seq": seq}, source=source)
    return (ds if ok.all() else ds.subset(ok)), int((~ok).sum())


def run_record(reader: Reader, loadcell: LoadCellReader, out: str | Path, *,
               duration: float | None = None, max_samples: int | None = None,
               idle_timeout: float | None = None, start_timeout: float | None = None,
               rate_hz: float = 1000.0, status: bool = True,
               estimator: Any | None = None) -> dict[str, Any]:
    """Record until a stop condition and write ``out``: CSV or npz (dataset contract), or a
    rosbag2 MCAP log (:mod:`fbgforce.interrogator.mcaplog`) of the same samples, with the
    estimates of ``estimator`` (a :class:`~fbgforce.interrogator.stream.LiveEstimator`, fed
    the recorded samples in order) when one is given."""
    from fbgforce.recordings import dataset

    out = Path(out)
    _check_output(out, estimator)
    join = Joiner()
    stopped_by = _join_until_stopped(reader, loadcell, join, duration=duration,
                                     max_samples=max_samples, idle_timeout=idle_timeout,
                                     start_timeout=start_timeout, status=status)
    join.finish()
    pairs = join.pairs[:max_samples] if max_samples is not None else join.pairs
    if not pairs:
        raise InputError("no samples recorded: no interrogator frame matched a load-cell line "
                         "(check both ports and that the stage tags lines with the sample "
                         "counter)", column="--port")
    ds, invalid = pairs_to_dataset(pairs, rate_hz=rate_hz, source=f"fbgforce record {out.name}")
    if out.suffix.lower() == ".mcap":
        dataset.validate(ds, where=f"dataset to save as {out}")
        topics = _write_mcap(ds, out, first_t_us=pairs[0][0].t_us, estimator=estimator)
    else:
        dataset.save(ds, out)
    rs, ls = reader.stats(), loadcell.stats()
    return {
        "samples": len(ds),
        "presses": int(np.unique(ds.press_id).size),
        "contact_fraction": float(np.mean(ds.contact)) if len(ds) else 0.0,
        "unmatched_frames": join.unmatched_frames,
        "unmatched_loadcell_lines": join.unmatched_lines,
        "invalid_samples": invalid,
        "lost_frames": rs.get("lost_frames", 0),
        "loadcell_lost_lines": ls.get("lost_frames", 0),
        "loadcell_bad_lines": ls.get("bad_lines", 0),
        "out": str(out),
        "interrupted": stopped_by is not None,
        "signal": stopped_by,
        "reader": rs,
        "loadcell": ls,
        **({"topics": topics} if out.suffix.lower() == ".mcap" else {}),
    }


def _check_output(out: Path, estimator: Any | None) -> None:
    """Refuse an output the recording could not be written to, before it starts."""
    if out.suffix.lower() not in (".csv", ".npz", ".mcap"):
        raise InputError("output must end in .csv, .npz or .mcap", path=str(out),
                         column="--out")
    if estimator is not None and out.suffix.lower() != ".mcap":
        raise InputError("estimates are logged in an .mcap output only", path=str(out),
                         column="--model")
    if out.suffix.lower() == ".mcap":
        from fbgforce.interrogator.mcaplog import writer_class

        writer_class(out)  # a missing extra fails now, not after the recording
    fileio.check_output_file(out, "--out")


def _join_until_stopped(reader: Reader, loadcell: LoadCellReader, join: Joiner, *,
                        duration: float | None, max_samples: int | None,
                        idle_timeout: float | None, start_timeout: float | None,
                        status: bool) -> str | None:
    """Read both ports into ``join`` until a stop condition; the signal that stopped the
    recording, if one did."""
    started = time.monotonic()
    first = last = None
    last_report = started
    try:
        while True:
            frames = reader.read(0.01)
            lines = loadcell.read(0.0)
            now = time.monotonic()
            if frames or lines:
                first = now if first is None else first
                last = now
                join.add(frames, lines)
            # Nothing to report before the first sample (a silent port ends in one error line).
            if status and first is not None and now - last_report >= 1.0:
                last_report = now
                print(f"record: {len(join.pairs)} samples, lost "
                      f"{reader.stats().get('lost_frames', 0)} frames, unmatched "
                      f"{join.unmatched_frames}/{join.unmatched_lines}", file=sys.stderr, flush=True)
            if max_samples is not None and len(join.pairs) >= max_samples:
                break
            if first is None:
                if start_timeout is not None and now - started >= start_timeout:
                    break
                continue
            if duration is not None and now - first >= duration:
                break
            if idle_timeout is not None and now - last >= idle_timeout:
                break
    except KeyboardInterrupt as exc:
        # The operator (Ctrl-C) or a service manager (SIGTERM) ends the recording: keep what
        # was joined.
        return signals.signal_name(exc)
    return None


def _write_mcap(ds: Any, out: Path, *, first_t_us: int, estimator: Any | None
                ) -> dict[str, int]:
    """The recorded samples (and their estimates) as a rosbag2 MCAP log; messages per topic."""
    from fbgforce.interrogator.mcaplog import stamps_for, write_log
    from fbgforce.interrogator.protocol import nm_to_fm
    from fbgforce.interrogator.publish import estimate_integers

    wl_fm = nm_to_fm(ds.wl_nm)
    ints = None
    if estimator is not None:
        est = estimator.push(wl_fm)
        if len(est["contact"]) != len(ds):
            raise InputError(f"{len(ds)} samples recorded, fewer than the tare needs "
                             f"({estimator.tare_samples})", column="--tare-samples")
        ints = estimate_integers(est)
    stage = {"contact": ds.contact, "force_N": ds.force_N, "x_mm": ds.x_mm, "y_mm": ds.y_mm,
             "press_id": ds.press_id}
    return write_log(out, stamp_ns=stamps_for(ds.t_s, first_t_us, time.time_ns()),
                     sample_seq=ds.extra["seq"], wl_fm=wl_fm, stage=stage, estimates=ints)
