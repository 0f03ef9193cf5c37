"""A lab's calibration from its own files: an interrogator log and a stage/load-cell log, each
on its own clock, turned into one dataset in the contract (docs/lab-import.md).

The work is done on arrays, so any reader of the two streams plugs in: an interrogator source
yields chunks of (time, wavelengths in nm, line numbers) and can be read twice (once to align,
once to write), and the stage log is a :class:`~fbgforce.recordings.stagelog.StageLog` of
arrays. :class:`CsvFbgLog` and :func:`read_stage_csv` are the CSV readers behind ``fbgforce
import``.

Steps (:func:`import_logs`):

0. each log's times are checked (finite, increasing, regular, a sample rate that fits the
   time unit given: :func:`check_times`), stage rows holding no reading are dropped and
   counted (:func:`drop_bad_stage_rows`), and the force and position units are checked
   against what a calibration can show (:func:`check_stage_units`);
1. the four strain gratings' relative shifts (:func:`grating_strain`) are kept with the
   interrogator's times;
2. :func:`fbgforce.recordings.stagelog.align` estimates the stage clock against the
   interrogator's, ``t_stage = t_fbg + offset + drift (t_fbg - t_fbg[0])``: a coarse normalised
   cross-correlation of the load against the gratings' sum; each press timed on its loading
   and unloading flanks (the gratings combined for that press by their gain over their
   noise, a gain per flank so the pad's friction loop does not bias it) and a weighted
   straight line through the presses, which gives the drift; the level from the pad's lag
   (a causal response of unknown shape: non-negative shares of first-order lags of the load
   over a range of time constants) fitted over the whole log together with it;
3. force and position are interpolated onto the interrogator's samples (:func:`stage_at`),
   contact is labelled by the dataset's rule, raised above a noisy load cell's noise
   (:func:`~fbgforce.recordings.stagelog.label_contact`,
   :func:`~fbgforce.recordings.stagelog.contact_threshold`), and presses numbered as
   the simulator numbers them (:func:`number_presses`);
4. the dataset is written chunk by chunk (:class:`fbgforce.recordings.dataset.CsvWriter`).
"""
from __future__ import annotations

import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Protocol

import numpy as np

from fbgforce.recordings import dataset as fds
from fbgforce.errors import InputError
from fbgforce.recordings.stagelog import (ALIGN_MIN_PEAK_N, MAX_OFFSET_S, Alignment, StageLog,
                                          align, label_contact, press_runs, time_text)

#: Column keys of each log, as given to ``--fbg-columns`` / ``--stage-columns``.
FBG_KEYS = ("t", "wl1", "wl2", "wl3", "wl4", "wlT")
STAGE_KEYS = ("t", "force", "x", "y")
#: Units each log may be in, with the factor to the dataset's unit (nm, N, mm).
FBG_UNITS = {"nm": 1.0, "pm": 1e-3}
FORCE_UNITS = {"N": 1.0, "mN": 1e-3}
POSITION_UNITS = {"mm": 1.0, "um": 1e-3}
#: Units of each log's clock, with the divisor to seconds (a divisor, not a factor: an
#: integer count of ms or ns divided by 10^k is the float nearest the time it stands for).
TIME_UNITS = {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9}
#: Keys of a ``--map`` file: the flags' names without the dashes.
MAP_KEYS = ("fbg", "fbg-columns", "fbg-unit", "fbg-time-unit", "stage", "stage-columns",
            "stage-time-unit", "force-unit", "position-unit", "out", "max-offset-s")

# Plausibility of the units (docs/lab-import.md, "Units"): each bound is what a fingertip's
# calibration can physically show, and a value beyond it is a unit flag set wrong, which the
# refusal names. The two units of each flag differ by 1000, so a wrong flag lands three
# orders of magnitude off and the bounds leave room on both sides of real logs.
#: Sample rates a log may have, Hz. Below 10 Hz a stage log cannot follow the fastest presses
#: a calibration holds (fbgforce protocol's taps load in 50-100 ms) nor an interrogator the
#: load: a 1 kHz log whose clock counts ms reads 1 Hz. The interrogators and stage
#: controllers of a fingertip's calibration log at 0.1-20 kHz (the trainer's models run at the
#: interrogator's rate, 1 kHz by default); above 50 kHz is a clock in seconds read as ms
#: (a 100 Hz stage log then reads 100 kHz). A 10-50 Hz log read as ms stays inside and is
#: refused later, as logs that do not overlap or align.
SAMPLE_RATE_RANGE_HZ = (10.0, 50e3)
#: The largest load a fingertip's load cell reads in a calibration, N. The paper's pad is
#: calibrated to 70 N and a gripper's fingertip load cells reach a few hundred newtons (a
#: human grip is about 500 N); a log in mN read as N puts a 2 N press at 2000 N.
LOAD_CELL_MAX_N = 1000.0
#: The spread of the contact locations over a calibration (the larger of their x and y
#: extents), mm. A fingertip pad is 5-100 mm across (the paper's 21 x 27 mm, a gripper jaw's
#: pad under 100 mm) and a calibration presses over it (fbgforce protocol: the whole pad but
#: 0.5 mm at each edge); presses within 2 mm of each other over a whole log are µm read as mm
#: (or a calibration that cannot teach the location net anything), beyond 150 mm mm read as µm.
CONTACT_SPREAD_RANGE_MM = (2.0, 150.0)
#: A stage row whose force or position lies beyond what the largest plausible value reads in
#: the smallest unit its flag offers (1000 N as mN, 150 mm as µm), or is not a finite number,
#: holds no reading at all (a logger's error code, an overflow): such rows are dropped and
#: counted, as interrogator rows with bad wavelengths are.
NOT_A_FORCE_N = LOAD_CELL_MAX_N / min(FORCE_UNITS.values())
NOT_A_POSITION_MM = CONTACT_SPREAD_RANGE_MM[1] / min(POSITION_UNITS.values())
#: At most this share of either log's rows may be dropped for bad values; more is refused,
#: naming the first (a wrong unit or column, not a few glitches).
MAX_BAD_FRACTION = 0.01

#: Rows parsed per chunk: bounds the memory of the wavelength table.
CHUNK_ROWS = 50_000
#: A log is irregular when more than this fraction of its sample intervals lie outside
#: :data:`REGULAR_BAND` times the median interval.
IRREGULAR_FRACTION = 0.01
REGULAR_BAND = (0.2, 2.0)
#: Interrogator samples between two stage samples further apart than this many median stage
#: intervals are dropped (a hole in the stage log: nothing to interpolate from).
STAGE_GAP_INTERVALS = 3.0
#: A press's unloading has ended once the load is within this of zero, N.
REST_BAND_N = 0.1 * fds.CONTACT_THRESHOLD_N


# ------------------------------------------------------------------------------ the mapping

@dataclass
class ImportSpec:
    """What to import: the two files, their columns and units, the output."""

    fbg: Path
    fbg_columns: dict[str, str]
    stage: Path
    stage_columns: dict[str, str]
    out: Path
    fbg_unit: str = "nm"
    force_unit: str = "N"
    position_unit: str = "mm"
    max_offset_s: float = MAX_OFFSET_S
    fbg_time_unit: str = "s"
    stage_time_unit: str = "s"


def parse_columns(value: str | Mapping[str, Any], keys: tuple[str, ...], flag: str,
                  where: str | None = None) -> dict[str, str]:
    """``t=COL,wl1=COL,...`` (or a TOML table) -> ``{key: column name}``; every key of
    ``keys`` exactly once."""
    if isinstance(value, str):
        pairs = []
        for part in value.split(","):
            if "=" not in part:
                wanted = ",".join(k + "=COL" for k in keys)
                raise InputError(f"expected KEY=COLUMN pairs ({wanted}), got {part.strip()!r}",
                                 path=where, column=flag)
            k, v = part.split("=", 1)
            pairs.append((k.strip(), v.strip()))
    elif isinstance(value, Mapping):
        pairs = [(str(k), str(v).strip()) for k, v in value.items()]
    else:
        raise InputError("must be a string KEY=COLUMN,... or a table", path=where, column=flag)
    out: dict[str, str] = {}
    for k, v in pairs:
        if k not in keys:
            raise InputError(f"unknown key {k!r}; keys: {', '.join(keys)}", path=where, column=flag)
        if k in out:
            raise InputError(f"key {k!r} given twice", path=where, column=flag)
        if not v:
            raise InputError(f"key {k!r} names no column", path=where, column=flag)
        out[k] = v
    missing = [k for k in keys if k not in out]
    if missing:
        raise InputError(f"missing key(s) {', '.join(missing)}; give all of {', '.join(keys)}",
                         path=where, column=flag)
    return out


def load_map(path: str | Path) -> dict[str, Any]:
    """A ``--map`` TOML file: the flags' keys (:data:`MAP_KEYS`); file paths in it are taken
    relative to the map file."""
    p = Path(path)
    try:
        values = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=str(p), column="--map") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not TOML: {exc}", path=str(p)) from None
    unknown = [k for k in values if k not in MAP_KEYS]
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)}; allowed: {', '.join(MAP_KEYS)}",
                         path=str(p))
    for key in ("fbg", "stage", "out"):
        if key in values:
            if not isinstance(values[key], str):
                raise InputError("must be a file path (a string)", path=str(p), column=key)
            values[key] = str(p.parent / values[key])
    return values


def make_spec(values: Mapping[str, Any], where: str | None = None) -> ImportSpec:
    """An :class:`ImportSpec` from the flags' values by key (``None`` = not given; a map
    file's values fill the rest before this is called)."""
    for key in ("fbg", "fbg-columns", "stage", "stage-columns", "out"):
        if values.get(key) is None:
            raise InputError(f"give --{key}" + (" (or --map)" if where is None else ""),
                             path=where, column=None if where else f"--{key}")
    units = {}
    for key, table, default in (("fbg-unit", FBG_UNITS, "nm"), ("force-unit", FORCE_UNITS, "N"),
                                ("position-unit", POSITION_UNITS, "mm"),
                                ("fbg-time-unit", TIME_UNITS, "s"),
                                ("stage-time-unit", TIME_UNITS, "s")):
        unit = values.get(key) or default
        if unit not in table:
            raise InputError(f"unknown unit {unit!r}; one of {', '.join(table)}", path=where,
                             column=f"--{key}" if where is None else key)
        units[key] = unit
    max_offset = values.get("max-offset-s")
    max_offset = MAX_OFFSET_S if max_offset is None else max_offset
    if not isinstance(max_offset, (int, float)) or not 0 < max_offset < 1e9:
        raise InputError(f"must be a number of seconds > 0, not {max_offset!r}", path=where,
                         column="max-offset-s")
    return ImportSpec(
        fbg=Path(values["fbg"]), stage=Path(values["stage"]), out=Path(values["out"]),
        fbg_columns=parse_columns(values["fbg-columns"], FBG_KEYS,
                                  "fbg-columns" if where else "--fbg-columns", where),
        stage_columns=parse_columns(values["stage-columns"], STAGE_KEYS,
                                    "stage-columns" if where else "--stage-columns", where),
        fbg_unit=units["fbg-unit"], force_unit=units["force-unit"],
        position_unit=units["position-unit"], max_offset_s=float(max_offset),
        fbg_time_unit=units["fbg-time-unit"], stage_time_unit=units["stage-time-unit"])


# ------------------------------------------------------------------------------ CSV reading

class CsvColumns:
    """Named numeric columns of a delimited text log, read in chunks of :data:`CHUNK_ROWS`.

    Lines starting with ``#`` and blank lines are skipped; the first other line is the header.
    The delimiter is the header's: comma, else tab, else semicolon. Iterating yields
    ``(values (k, len(columns)) float64, line numbers (k,) 1-based)``; every iteration reads
    the file again.
    """

    def __init__(self, path: str | Path, columns: Mapping[str, str], flag: str) -> None:
        self.path = Path(path)
        self.columns = dict(columns)
        self.flag = flag
        if not self.path.is_file():
            raise InputError("no such file", path=str(self.path), column=f"--{flag}")
        with self._open() as fh:
            for line_no, line in enumerate(fh, 1):
                if line.strip() and not line.lstrip().startswith("#"):
                    break
            else:
                raise InputError("empty file: no header", path=str(self.path))
        self.header_line = line_no
        self.delimiter = next((d for d in (",", "\t", ";") if d in line), ",")
        names = [n.strip().strip('"') for n in line.rstrip("\r\n").split(self.delimiter)]
        self.n_fields = len(names)
        missing = [c for c in self.columns.values() if c not in names]
        if missing:
            raise InputError(f"no column(s) {', '.join(repr(c) for c in missing)} in the header "
                             f"(columns: {', '.join(names)}); check --{flag}-columns",
                             path=str(self.path), line=line_no)
        self.index = [names.index(c) for c in self.columns.values()]

    def _open(self) -> Any:
        try:
            return open(self.path, encoding="utf-8", errors="replace", newline="")
        except OSError as exc:
            raise InputError(f"cannot read: {exc.strerror}", path=str(self.path)) from None

    def __iter__(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        rows: list[str] = []
        lines: list[int] = []
        with self._open() as fh:
            for line_no, line in enumerate(fh, 1):
                if line_no <= self.header_line:
                    continue
                stripped = line.strip()
                if not stripped or stripped.startswith("#"):
                    continue
                rows.append(stripped)
                lines.append(line_no)
                if len(rows) == CHUNK_ROWS:
                    yield self._parse(rows, lines)
                    rows, lines = [], []
        if rows:
            yield self._parse(rows, lines)

    def _parse(self, rows: list[str], lines: list[int]) -> tuple[np.ndarray, np.ndarray]:
        try:
            values = np.loadtxt(rows, delimiter=self.delimiter, usecols=self.index,
                                dtype=np.float64, ndmin=2, comments=None)
            if all(r.count(self.delimiter) == self.n_fields - 1 for r in rows):
                return values, np.asarray(lines, dtype=np.int64)
        except ValueError:
            pass
        names = list(self.columns.values())
        for row, line_no in zip(rows, lines):        # find the first bad line to name it
            fields = row.split(self.delimiter)
            if len(fields) != self.n_fields:
                raise InputError(f"{len(fields)} fields, the header has {self.n_fields}",
                                 path=str(self.path), line=line_no)
            for name, i in zip(names, self.index):
                try:
                    float(fields[i].strip().strip('"'))
                except ValueError:
                    raise InputError(f"not a number: {fields[i].strip()!r}", path=str(self.path),
                                     line=line_no, column=name) from None
        raise InputError("unreadable rows", path=str(self.path), line=lines[0])  # pragma: no cover


class FbgSource(Protocol):
    """An interrogator log: iterating yields ``(t_s, wl_nm (k, 5), line)`` chunks on the
    interrogator's clock, and can be repeated."""

    path: str

    def __iter__(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]: ...


class CsvFbgLog:
    """An interrogator CSV log (:class:`FbgSource`) with its column mapping and units."""

    #: The options that set its units, for the plausibility refusals.
    time_flag = "--fbg-time-unit"
    unit_flag = "--fbg-unit"

    def __init__(self, path: str | Path, columns: Mapping[str, str], unit: str = "nm",
                 time_unit: str = "s") -> None:
        self.reader = CsvColumns(path, {k: columns[k] for k in FBG_KEYS}, "fbg")
        self.path = str(path)
        self.scale = FBG_UNITS[unit]
        self.time_divisor = TIME_UNITS[time_unit]

    def __iter__(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        for values, lines in self.reader:
            t = values[:, 0] if self.time_divisor == 1.0 else values[:, 0] / self.time_divisor
            yield t, values[:, 1:] * self.scale, lines


def read_stage_csv(path: str | Path, columns: Mapping[str, str], force_unit: str = "N",
                   position_unit: str = "mm", time_unit: str = "s") -> StageLog:
    """The stage log of a CSV (all of it: four numbers a row)."""
    reader = CsvColumns(path, {k: columns[k] for k in STAGE_KEYS}, "stage")
    parts = list(reader)
    if not parts:
        raise InputError("no data rows after the header", path=str(path))
    values = np.concatenate([v for v, _ in parts])
    pos = POSITION_UNITS[position_unit]
    t = values[:, 0] if time_unit == "s" else values[:, 0] / TIME_UNITS[time_unit]
    # Contiguous columns: the alignment interpolates in them press by press.
    return StageLog(t=np.ascontiguousarray(t),
                    force_N=values[:, 1] * FORCE_UNITS[force_unit],
                    x_mm=values[:, 2] * pos, y_mm=values[:, 3] * pos,
                    line=np.concatenate([ln for _, ln in parts]), path=str(path))


# ------------------------------------------------------------------------------ array steps

def grating_strain(wl_nm: np.ndarray, ref_nm: np.ndarray) -> np.ndarray:
    """The load signal of each strain grating: minus its relative shift from ``ref_nm``, in
    parts per million, (n, 4) float32. Positive under load (the gratings are compressed);
    their sum is about proportional to the normal force wherever it acts (the beam forces sum
    to it).

    The temperature grating is not subtracted sample by sample: temperature moves slowly, so
    the coarse high-pass and the level fitted to each press take it out, while subtracting it
    would add its noise to every grating."""
    return (-(wl_nm[:, :4] / ref_nm[:4] - 1.0) * 1e6).astype(np.float32)


def check_times(t: np.ndarray, line: np.ndarray, path: str, what: str,
                flag: str | None = None) -> float:
    """Refuse non-finite, non-increasing or irregular time stamps, and a sample rate outside
    :data:`SAMPLE_RATE_RANGE_HZ` (a clock in another unit than ``flag``, the option of its
    time unit, says); return the median sample interval, s."""
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"time is not a finite number ({t[i]})", path=path,
                         line=int(line[i]), column="t")
    if t.size < 3:
        raise InputError(f"only {t.size} samples in the {what} log", path=path)
    dt = np.diff(t)
    if (dt <= 0).any():
        i = int(np.argmax(dt <= 0)) + 1
        raise InputError(f"time not increasing ({time_text(t[i])} after {time_text(t[i - 1])}): the "
                         f"{what} log must be in time order, one row per sample", path=path,
                         line=int(line[i]), column="t")
    med = float(np.median(dt))
    lo, hi = SAMPLE_RATE_RANGE_HZ
    if not lo <= 1.0 / med <= hi:
        i = int(np.argmin(np.abs(dt - med))) + 1
        raise InputError(
            f"the {what} log's median step reads {med:.4g} s ({1.0 / med:.4g} Hz) in its time "
            f"unit, where {what} logs run at {lo:g} Hz to {hi / 1e3:g} kHz: is "
            f"{flag or 'its time unit'} right (s, ms, us or ns)?", path=path,
            line=int(line[i]), column="t")
    off = (dt < REGULAR_BAND[0] * med) | (dt > REGULAR_BAND[1] * med)
    if off.mean() > IRREGULAR_FRACTION:
        i = int(np.argmax(off)) + 1
        raise InputError(
            f"irregular sampling: {100 * off.mean():.1f} % of the {what} log's intervals lie "
            f"outside {REGULAR_BAND[0]:g}-{REGULAR_BAND[1]:g} x the median {1e3 * med:.3g} ms "
            f"(at most {100 * IRREGULAR_FRACTION:g} % may), the first here", path=path,
            line=int(line[i]), column="t")
    return med


def drop_bad_stage_rows(stage: StageLog) -> tuple[StageLog, int]:
    """The stage log without its rows holding no reading (a force or position that is not a
    finite number, or beyond :data:`NOT_A_FORCE_N` / :data:`NOT_A_POSITION_MM`), and how many
    were dropped. More than :data:`MAX_BAD_FRACTION` of the rows is refused, naming the first
    with its column (as the interrogator's bad wavelengths are)."""
    columns = (("force", stage.force_N, NOT_A_FORCE_N, stage.force_flag),
               ("x", stage.x_mm, NOT_A_POSITION_MM, stage.position_flag),
               ("y", stage.y_mm, NOT_A_POSITION_MM, stage.position_flag))
    bads = []
    for _, values, limit, _ in columns:
        with np.errstate(invalid="ignore"):
            bads.append(~(np.abs(values) <= limit))       # NaN fails the comparison too
    bad = np.logical_or.reduce(bads)
    n_bad = int(bad.sum())
    if n_bad == 0:
        return stage, 0
    if n_bad > MAX_BAD_FRACTION * bad.size:
        i = int(np.argmax(bad))
        k = next(j for j, b in enumerate(bads) if b[i])
        name, values, limit, flag = columns[k]
        raise InputError(f"{100 * n_bad / bad.size:.1f} % of the stage rows hold a value that is "
                         f"no reading ({float(values[i])!r}: not a number or beyond {limit:g}), the "
                         f"first here (at most {100 * MAX_BAD_FRACTION:g} % are dropped): is "
                         f"{flag} or --stage-columns right?", path=stage.path,
                         line=int(stage.line[i]), column=name)
    return stage.subset(~bad), n_bad


def check_stage_units(stage: StageLog, threshold_N: float) -> None:
    """Refuse a stage log whose force or position unit cannot be right: its largest load
    above :data:`LOAD_CELL_MAX_N` or below :data:`ALIGN_MIN_PEAK_N` (no press), or its contact
    locations (where the load is above ``threshold_N``) spread less or more than
    :data:`CONTACT_SPREAD_RANGE_MM`; each refusal names the unit's option."""
    i = int(np.argmax(stage.force_N))
    peak = float(stage.force_N[i])
    if peak > LOAD_CELL_MAX_N:
        raise InputError(f"the load cell reads {peak:.4g} N, more than a fingertip's load cell "
                         f"measures (up to {LOAD_CELL_MAX_N:g} N): is {stage.force_flag} right "
                         "(N or mN)?", path=stage.path, line=int(stage.line[i]), column="force")
    if peak < ALIGN_MIN_PEAK_N:
        raise InputError(f"no presses: the load cell never exceeds {ALIGN_MIN_PEAK_N:g} N (its "
                         f"largest reading {peak:.3g} N; a calibration presses to several "
                         f"newtons): is {stage.force_flag} right (N or mN)?", path=stage.path,
                         line=int(stage.line[i]), column="force")
    touch = stage.force_N > threshold_N
    if not touch.any():
        return
    extents = {"x": float(np.ptp(stage.x_mm[touch])), "y": float(np.ptp(stage.y_mm[touch]))}
    axis = max(extents, key=lambda k: extents[k])
    spread = extents[axis]
    lo, hi = CONTACT_SPREAD_RANGE_MM
    if not lo <= spread <= hi:
        raise InputError(f"the contact locations span {spread:.3g} mm in {axis} (the larger "
                         f"extent) over {int(touch.sum())} rows in contact; a fingertip pad's "
                         f"presses span {lo:g}-{hi:g} mm: is {stage.position_flag} right "
                         "(mm or um)?", path=stage.path, column=axis)


def stage_at(stage: StageLog, t_stage: np.ndarray, gap_s: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Force, x, y interpolated at stage-clock times, and the reason code of each sample
    (0 kept, 1 before the stage log, 2 after it, 3 in a hole longer than ``gap_s``)."""
    force = np.interp(t_stage, stage.t, stage.force_N)
    x = np.interp(t_stage, stage.t, stage.x_mm)
    y = np.interp(t_stage, stage.t, stage.y_mm)
    reason = np.zeros(t_stage.size, dtype=np.int8)
    reason[t_stage < stage.t[0]] = 1
    reason[t_stage > stage.t[-1]] = 2
    j = np.clip(np.searchsorted(stage.t, t_stage), 1, stage.t.size - 1)
    hole = (stage.t[j] - stage.t[j - 1] > gap_s) & (reason == 0)
    reason[hole] = 3
    return force, x, y, reason


#: Reason codes of :func:`stage_at` and the bad-wavelength code, by JSON key.
DROP_REASONS = {1: "before_stage_log", 2: "after_stage_log", 3: "stage_gap", 4: "bad_wavelength"}


def number_presses(t: np.ndarray, force_N: np.ndarray,
                   threshold_N: float = fds.CONTACT_THRESHOLD_N) -> np.ndarray:
    """Press ids as the simulator gives them, counting from 0: a press is its rest, its
    contact and the end of its unloading, which runs past the last contact sample to the
    first sample where the load stops falling or is within :data:`REST_BAND_N` of zero (the
    load back at rest). The samples after that carry the next press's id; those after the
    last press keep its id. ``threshold_N``: the contact threshold (:func:`label_contact`)."""
    force = np.asarray(force_N, dtype=np.float64)
    starts, stops = press_runs(t, label_contact(force, threshold_N))
    if starts.size == 0:
        return np.zeros(t.size, dtype=np.int64)
    # Where the load is back at rest: it stops falling, or it is all but zero.
    still = np.flatnonzero((force[1:] >= force[:-1]) | (force[1:] <= REST_BAND_N)) + 1
    k = np.searchsorted(still, stops)
    ends = np.where(k < still.size, still[np.minimum(k, still.size - 1)], t.size)
    nxt = np.append(starts[1:], t.size)
    ends = np.minimum(ends + 1, nxt)                           # the stopping sample included
    ids = np.searchsorted(ends, np.arange(t.size), side="right")
    return np.minimum(ids, starts.size - 1).astype(np.int64)


# ------------------------------------------------------------------------------ the import

def import_logs(fbg: FbgSource, stage: StageLog, out: str | Path, *,
                max_offset_s: float = MAX_OFFSET_S, progress: bool | None = None
                ) -> dict[str, Any]:
    """Align, resample, label, number and write (module docstring); return the summary that
    ``fbgforce import --json`` prints (docs/cli.md#import)."""
    t_start = time.perf_counter()
    where = f"{fbg.path} + {stage.path}"
    stage_dt = check_times(stage.t, stage.line, stage.path, "stage", stage.time_flag)
    stage_rows = int(stage.t.size)
    stage_rate = (stage.t.size - 1) / float(stage.t[-1] - stage.t[0])
    stage, stage_bad = drop_bad_stage_rows(stage)
    threshold = _check_stage_load(stage)
    t_f, strain, good = _read_strain(fbg, progress)
    al = align(t_f, strain, stage, max_offset_s=max_offset_s, where=where)
    del strain
    gap_s = STAGE_GAP_INTERVALS * stage_dt
    keep, press, reason = _presses(stage, al, t_f, good, gap_s, threshold, where)
    _write_dataset(fbg, stage, al, out, keep, press, gap_s, threshold, progress)
    dropped = {name: int((reason == code).sum()) for code, name in DROP_REASONS.items()}
    return {
        "dataset": str(out), "samples": int(keep.sum()),
        "presses": int(np.unique(press[keep]).size),
        "offset_s": al.offset_s, "drift_ppm": al.drift * 1e6,
        "alignment": al.summary(),
        "fbg": {"file": fbg.path, "rows": int(t_f.size),
                "rate_hz": (t_f.size - 1) / float(t_f[-1] - t_f[0])},
        "stage": {"file": stage.path, "rows": stage_rows, "bad_rows": stage_bad,
                  "rate_hz": stage_rate},
        "dropped": dropped,
        "load_cell_noise_N": stage.noise_N, "contact_threshold_N": threshold,
        "seconds": round(time.perf_counter() - t_start, 3),
    }


def _check_stage_load(stage: StageLog) -> float:
    """Refuse a load cell that reads below the dataset's floor or is not tared; return the
    contact threshold of its noise."""
    low = stage.force_N < fds.FORCE_NEGATIVE_LIMIT_N
    if low.any():
        i = int(np.argmax(low))
        raise InputError(f"force {stage.force_N[i]:g} N below {fds.FORCE_NEGATIVE_LIMIT_N:g} N "
                         f"(sign or tare error, or the wrong {stage.force_flag})",
                         path=stage.path, line=int(stage.line[i]), column="force")
    threshold = stage.contact_threshold_N
    check_stage_units(stage, threshold)
    rest = float(np.percentile(stage.force_N, 5))
    if rest > threshold:
        raise InputError(f"the load cell reads {rest:.3g} N or more for 95 % of the log: tare "
                         f"it (contact is a force above {threshold:.3g} N)",
                         path=stage.path, column="force")
    return threshold


def _read_strain(fbg: FbgSource, progress: bool | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pass 1 over the interrogator log: its times, the gratings' strain proxy and which rows
    hold valid wavelengths (the wavelength table is not kept), its times checked."""
    from tqdm import tqdm

    ts, strains, goods, lines = [], [], [], []
    ref = None
    bar = tqdm(desc="import: read", unit="row", unit_scale=True, file=sys.stderr,
               disable=None if progress is None else not progress)
    for t, wl, line in fbg:
        ok = np.all(np.isfinite(wl) & (wl >= fds.WL_RANGE_NM[0]) & (wl <= fds.WL_RANGE_NM[1]),
                    axis=1)
        if ref is None and ok.any():
            ref = np.median(wl[ok][:1000], axis=0)
        ts.append(t)
        strains.append(grating_strain(np.where(ok[:, None], wl, ref if ref is not None else 1.0),
                                      ref if ref is not None else np.ones(5)))
        goods.append(ok)
        lines.append(line)
        bar.update(t.size)
    bar.close()
    if not ts:
        raise InputError("no data rows after the header", path=fbg.path)
    t_f, strain = np.concatenate(ts), np.concatenate(strains)
    good, line_f = np.concatenate(goods), np.concatenate(lines)
    check_times(t_f, line_f, fbg.path, "interrogator",
                getattr(fbg, "time_flag", "--fbg-time-unit"))
    if good.mean() < 1.0 - MAX_BAD_FRACTION:
        i = int(np.argmax(~good))
        raise InputError(f"{100 * (1 - good.mean()):.1f} % of the wavelengths are missing or "
                         f"outside {fds.WL_RANGE_NM[0]:g}-{fds.WL_RANGE_NM[1]:g} nm, the first "
                         f"here: is {getattr(fbg, 'unit_flag', '--fbg-unit')} right (nm or pm)?",
                         path=fbg.path, line=int(line_f[i]))
    if ref is None:  # pragma: no cover - excluded by the 99 % check above
        raise InputError("no valid wavelength row", path=fbg.path)
    return t_f, strain, good


def _presses(stage: StageLog, al: Alignment, t_f: np.ndarray, good: np.ndarray, gap_s: float,
             threshold: float, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contact and presses over the whole log (one bool and one id per sample): the samples
    kept, their press ids and each sample's drop reason (0: kept, :data:`DROP_REASONS`)."""
    force, _, _, reason = stage_at(stage, al.to_stage(t_f), gap_s)
    reason[(reason == 0) & ~good] = 4
    keep = reason == 0
    if not label_contact(force[keep], threshold).any():
        raise InputError("no presses: no interrogator sample meets a load above "
                         f"{threshold:.3g} N after alignment", path=where)
    press = np.zeros(t_f.size, dtype=np.int64)
    press[keep] = number_presses(t_f[keep], force[keep], threshold)
    return keep, press, reason


def _write_dataset(fbg: FbgSource, stage: StageLog, al: Alignment, out: str | Path,
                   keep: np.ndarray, press: np.ndarray, gap_s: float, threshold: float,
                   progress: bool | None) -> None:
    """Pass 2 over the interrogator log: resample the stage onto the samples kept and write
    the dataset chunk by chunk."""
    from tqdm import tqdm

    source = (f"import: {fbg.path} + {stage.path} offset={al.offset_s:.6f}s "
              f"drift={al.drift * 1e6:.2f}ppm")
    start = 0
    bar = tqdm(total=keep.size, desc="import: write", unit="row", unit_scale=True,
               file=sys.stderr, disable=None if progress is None else not progress)
    with fds.CsvWriter(out, source) as writer:
        for t, wl, _ in fbg:
            sl = slice(start, start + t.size)
            start += t.size
            k = keep[sl]
            f, x, y, _ = stage_at(stage, al.to_stage(t[k]), gap_s)
            c = label_contact(f, threshold)
            writer.write(fds.Dataset(t_s=t[k], wl_nm=wl[k], contact=c,
                                     x_mm=np.where(c, x, np.nan), y_mm=np.where(c, y, np.nan),
                                     force_N=f, press_id=press[sl][k], source=source))
            bar.update(t.size)
    bar.close()


def import_files(spec: ImportSpec, *, progress: bool | None = None) -> dict[str, Any]:
    """:func:`import_logs` on the CSV files an :class:`ImportSpec` names."""
    if spec.out.suffix.lower() != ".csv":
        raise InputError("the imported dataset is written as CSV: give a .csv path",
                         path=str(spec.out), column="--out")
    stage = read_stage_csv(spec.stage, spec.stage_columns, spec.force_unit, spec.position_unit,
                           spec.stage_time_unit)
    fbg = CsvFbgLog(spec.fbg, spec.fbg_columns, spec.fbg_unit, spec.fbg_time_unit)
    return import_logs(fbg, stage, spec.out, max_offset_s=spec.max_offset_s, progress=progress)
