"""A lab's calibration from its own files: an interrogator log and a stage/load-cell log, each
on its own clock, turned into one dataset in the contract (docs/lab-import.md).

The work is done on arrays, so any reader of the two streams plugs in: an interrogator source
yields chunks of (time, wavelengths in nm, line numbers) and can be read twice (once to align,
once to write), and the stage log is a :class:`StageLog` of arrays. :class:`CsvFbgLog` and
:func:`read_stage_csv` are the CSV readers behind ``fbgforce import``.

Steps (:func:`import_logs`):

0. each log's times are checked (finite, increasing, regular, a sample rate that fits the
   time unit given: :func:`check_times`), stage rows holding no reading are dropped and
   counted (:func:`drop_bad_stage_rows`), and the force and position units are checked
   against what a calibration can show (:func:`check_stage_units`);
1. the four strain gratings' relative shifts (:func:`grating_strain`) are kept with the
   interrogator's times;
2. :func:`align` estimates the stage clock against the interrogator's,
   ``t_stage = t_fbg + offset + drift (t_fbg - t_fbg[0])``: a coarse normalised
   cross-correlation of the load against the gratings' sum; each press timed on its loading
   and unloading flanks (the gratings combined for that press by their gain over their
   noise, a gain per flank so the pad's friction loop does not bias it) and a weighted
   straight line through the presses, which gives the drift; the level from the pad's lag
   (a causal response of unknown shape: non-negative shares of first-order lags of the load
   over a range of time constants) fitted over the whole log together with it;
3. force and position are interpolated onto the interrogator's samples (:func:`stage_at`),
   contact is labelled by the dataset's rule, raised above a noisy load cell's noise
   (:func:`label_contact`, :func:`contact_threshold`), and presses numbered as
   the simulator numbers them (:func:`number_presses`);
4. the dataset is written chunk by chunk (:class:`fbgforce.dataset.CsvWriter`).
"""
from __future__ import annotations

import sys
import time
import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Iterator, Mapping, Protocol

import numpy as np

from fbgforce import dataset as fds
from fbgforce.errors import InputError

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
#: Default bound on the clock offset searched, s.
MAX_OFFSET_S = 10.0
#: The coarse alignment works on bins of this width, high-passed over :data:`HIGHPASS_S`.
COARSE_STEP_S = 0.01
HIGHPASS_S = 5.0
#: The two logs must share at least this long (or half the shorter log) at the offset found.
MIN_OVERLAP_S = 10.0
#: Refusals: coarse correlation below this; a second peak at least this fraction of the first.
MIN_CORRELATION = 0.5
AMBIGUOUS_RATIO = 0.9
#: Per-press refinement: search ± this around the running estimate, in steps of FINE_STEP_S,
#: on the flanks (below LOAD_FRACTION / UNLOAD_FRACTION of the press's peak) plus
#: FLANK_REST_S of rest.
FINE_WINDOW_S = 0.02
FINE_STEP_S = 0.0005
LOAD_FRACTION = 0.5
UNLOAD_FRACTION = 0.3
FLANK_REST_S = 0.06
#: The pad's lag: the gratings follow the load through a causal response of unknown shape,
#: modelled as the load itself plus first-order lags of it with these time constants (s), each
#: with a share fitted over the whole log together with the clock's level (searched over
#: ± LAG_SEARCH_S in steps of LAG_STEP_S around the plain flanks' line).
LAG_TIME_CONSTANTS_S = (0.03, 0.1, 0.3, 1.0)
LAG_SEARCH_S = 0.01
LAG_STEP_S = 0.0005
#: The creep the presses before left gets a scale of each press's own only where, at the
#: press's own scale, its sum of squares is at least this many times the press's noise
#: variance (:func:`_lag_fit`): a free scale on a tail the noise hides fits the noise.
TAIL_VISIBLE = 1.0
#: Presses lighter than this are not used to align (too little signal above the noise).
ALIGN_MIN_PEAK_N = 0.5
MIN_ALIGN_PRESSES = 3
#: The per-press offsets must sit on one straight line within this (weighted RMS), ms, with
#: at least half of them within 4 sd of it.
MAX_RESIDUAL_MS = 10.0
#: A per-press estimate's uncertainty is never taken below this, s (model error).
PRESS_SIGMA_FLOOR_S = 0.0003
#: Press numbering: contact runs closer than this merge into one press (load-cell chatter
#: around the threshold), and runs shorter than PRESS_MIN_S start no press.
PRESS_MERGE_GAP_S = 0.05
PRESS_MIN_S = 0.01
#: A press's unloading has ended once the load is within this of zero, N.
REST_BAND_N = 0.1 * fds.CONTACT_THRESHOLD_N
#: Contact is labelled above the dataset's threshold or this many standard deviations of the
#: load cell's noise, whichever is higher (:func:`contact_threshold`): at 5 a sample at rest
#: reads as contact once in 3.5 million.
LOAD_CELL_NOISE_SIGMAS = 5.0


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


@dataclass
class StageLog:
    """The stage/load-cell log on its own clock: time (s), force (N), position (mm, pad
    frame), and where each row came from (``line``: 1-based line of ``path``).

    ``time_flag``, ``force_flag`` and ``position_flag`` name the options that set the units,
    for the plausibility refusals (:func:`check_stage_units`)."""

    t: np.ndarray
    force_N: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    line: np.ndarray
    path: str = "<stage>"
    time_flag: str = "--stage-time-unit"
    force_flag: str = "--force-unit"
    position_flag: str = "--position-unit"

    def subset(self, keep: np.ndarray) -> "StageLog":
        """The rows where ``keep`` is True (a new log: its noise is measured again)."""
        return StageLog(t=np.ascontiguousarray(self.t[keep]), force_N=self.force_N[keep],
                        x_mm=self.x_mm[keep], y_mm=self.y_mm[keep], line=self.line[keep],
                        path=self.path, time_flag=self.time_flag, force_flag=self.force_flag,
                        position_flag=self.position_flag)

    @cached_property
    def noise_N(self) -> float:
        """The load cell's noise (standard deviation, N), from the second differences of the
        force: they cancel the slow loads of presses and rests alike, so their median absolute
        value is the noise's, whatever share of the log is pressed."""
        d2 = np.diff(np.asarray(self.force_N, dtype=np.float64), 2)
        return float(1.4826 * np.median(np.abs(d2)) / np.sqrt(6.0)) if d2.size else 0.0

    @property
    def contact_threshold_N(self) -> float:
        """:func:`contact_threshold` of this log's load cell."""
        return contact_threshold(self.noise_N)


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


def _time(t: float) -> str:
    """A time as read (every digit float64 holds: an epoch clock's milliseconds included)."""
    return repr(float(t))


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
        raise InputError(f"time not increasing ({_time(t[i])} after {_time(t[i - 1])}): the "
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


@dataclass
class Alignment:
    """The stage clock against the interrogator's:
    ``t_stage = t_fbg + offset_s + drift * (t_fbg - t_ref_s)``.

    ``correlation`` is the coarse peak's normalised correlation, ``second_peak`` the best
    one outside its lobe; ``residual_ms`` the weighted RMS of the per-press offsets about the
    line; ``line_sd_ms`` the line's standard error at the log's ends, the larger (what the
    presses' scatter leaves uncertain in the drift and level; the lag's fit adds to it);
    ``lag_ms`` how far the pad's lag moved the clock's level from the flanks' line;
    ``lag_shares`` the fitted share of the load reaching the gratings through each lag of
    :data:`LAG_TIME_CONSTANTS_S`; ``press_offsets`` the per-press estimates on the flanks
    (fbg time, offset, sd, used on the line)."""

    offset_s: float
    drift: float
    t_ref_s: float
    correlation: float
    second_peak: float
    residual_ms: float
    line_sd_ms: float
    lag_ms: float
    presses_used: int
    presses_rejected: int
    lag_shares: tuple[float, ...] = ()
    press_offsets: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))

    def to_stage(self, t_fbg: np.ndarray) -> np.ndarray:
        """Interrogator times -> stage clock."""
        return t_fbg + self.offset_s + self.drift * (t_fbg - self.t_ref_s)

    def summary(self) -> dict[str, Any]:
        """The JSON form (docs/cli.md#import)."""
        return {"offset_s": self.offset_s, "drift_ppm": self.drift * 1e6,
                "correlation": self.correlation, "second_peak": self.second_peak,
                "residual_ms": self.residual_ms, "line_sd_ms": self.line_sd_ms,
                "lag_ms": self.lag_ms,
                "lag_shares": {f"{tau:g}": share for tau, share in
                               zip(LAG_TIME_CONSTANTS_S, self.lag_shares)},
                "presses_used": self.presses_used,
                "presses_rejected": self.presses_rejected}


def _binned(t: np.ndarray, v: np.ndarray, t0: float, n: int) -> np.ndarray:
    """Means of ``v`` in :data:`COARSE_STEP_S` bins from ``t0`` (empty bins interpolated),
    high-passed by subtracting a centred :data:`HIGHPASS_S` moving mean."""
    idx = np.clip(((t - t0) / COARSE_STEP_S).astype(np.int64), 0, n - 1)
    count = np.bincount(idx, minlength=n)
    mean = np.bincount(idx, v, minlength=n) / np.maximum(count, 1)
    full = count > 0
    if not full.all():
        k = np.arange(n)
        mean = np.interp(k, k[full], mean[full])
    w = max(1, int(round(HIGHPASS_S / COARSE_STEP_S)))
    c = np.concatenate([[0.0], np.cumsum(mean)])
    lo = np.clip(np.arange(n) - w // 2, 0, n)
    hi = np.clip(np.arange(n) + w // 2 + 1, 0, n)
    return mean - (c[hi] - c[lo]) / (hi - lo)


def _coarse(t_f: np.ndarray, proxy: np.ndarray, stage: StageLog, max_offset_s: float,
            where: str) -> tuple[float, float, float, float]:
    """Coarse offset (stage minus interrogator clock), its correlation, the second peak and
    the most negative correlation (a signal that falls under load)."""
    tf0, ts0 = float(t_f[0]), float(stage.t[0])
    nf = int((t_f[-1] - tf0) / COARSE_STEP_S) + 1
    ns = int((stage.t[-1] - ts0) / COARSE_STEP_S) + 1
    f = _binned(t_f, proxy, tf0, nf)
    s = _binned(stage.t, stage.force_N, ts0, ns)
    # Lag k pairs fbg bin i with stage bin i + k: offset = ts0 - tf0 + k * step.
    size = 1 << int(np.ceil(np.log2(nf + ns)))
    xy = np.fft.irfft(np.fft.rfft(s, size) * np.conj(np.fft.rfft(f, size)), size)
    ks = np.arange(-(nf - 1), ns)
    sxy = xy[ks % size]
    lo = np.maximum(0, -ks)
    hi = np.minimum(nf, ns - ks)
    m = (hi - lo).astype(np.float64)
    cf, cf2 = np.concatenate([[0.0], np.cumsum(f)]), np.concatenate([[0.0], np.cumsum(f * f)])
    cs, cs2 = np.concatenate([[0.0], np.cumsum(s)]), np.concatenate([[0.0], np.cumsum(s * s)])
    sf, sff = cf[hi] - cf[lo], cf2[hi] - cf2[lo]
    ss, sss = cs[hi + ks] - cs[lo + ks], cs2[hi + ks] - cs2[lo + ks]
    offsets = ts0 - tf0 + ks * COARSE_STEP_S
    shorter = min(nf, ns) * COARSE_STEP_S
    need = min(MIN_OVERLAP_S, 0.5 * shorter) / COARSE_STEP_S
    allowed = (np.abs(offsets) <= max_offset_s) & (m >= need)
    if not allowed.any():
        raise InputError(
            f"no overlap: the interrogator log covers {_time(t_f[0])}-{_time(t_f[-1])} s and the "
            f"stage log {_time(stage.t[0])}-{_time(stage.t[-1])} s on their clocks; with offsets up to "
            f"±{max_offset_s:g} s they share less than {need * COARSE_STEP_S:.3g} s "
            "(give a larger --max-offset-s if the clocks count from different origins)",
            path=where)
    with np.errstate(invalid="ignore", divide="ignore"):
        den = np.sqrt(np.maximum(sff - sf * sf / m, 0) * np.maximum(sss - ss * ss / m, 0))
        r = np.where(allowed & (den > 0), (sxy - sf * ss / m) / den, -np.inf)
    best = int(np.argmax(r))
    r1 = float(r[best])
    # The main lobe: out to where the correlation first falls below half the peak.
    a = best
    while a > 0 and r[a - 1] > 0.5 * r1:
        a -= 1
    b = best
    while b < r.size - 1 and r[b + 1] > 0.5 * r1:
        b += 1
    rest = np.concatenate([r[:a], r[b + 1:]])
    r2 = float(rest.max()) if rest.size and np.isfinite(rest.max()) else 0.0
    shift = 0.0
    if 0 < best < r.size - 1 and np.isfinite(r[best - 1]) and np.isfinite(r[best + 1]):
        den2 = r[best - 1] - 2 * r1 + r[best + 1]
        if den2 < 0:
            shift = 0.5 * (r[best - 1] - r[best + 1]) / den2
    lowest = float(np.min(np.where(np.isfinite(r), r, np.inf)))
    return float(offsets[best] + shift * COARSE_STEP_S), r1, max(r2, 0.0), lowest


@dataclass
class _Press:
    on_s: float     # stage clock
    off_s: float
    peak_s: float
    peak_N: float


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and stop (exclusive) indices of the runs of True."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def _stage_presses(stage: StageLog) -> list[_Press]:
    starts, stops = _press_runs(stage.t, label_contact(stage.force_N, stage.contact_threshold_N))
    out = []
    for a, b in zip(starts, stops):
        k = a + int(np.argmax(stage.force_N[a:b]))
        out.append(_Press(float(stage.t[a]), float(stage.t[b - 1]), float(stage.t[k]),
                          float(stage.force_N[k])))
    return out


def first_order_lag(t: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """``x`` sampled at times ``t`` through a first-order lag of time constant ``tau_s``
    (``y' = (x - y) / tau``, starting at ``x[0]``; one backward step per interval, so
    irregular intervals are followed exactly for an input held over each interval).

    Vectorised in blocks short enough (:math:`300 \\tau`) that the exponential weights stay
    within floating point range."""
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    out = np.empty_like(x)
    decay = np.exp(-np.diff(t, prepend=t[0]) / tau_s)
    y = float(x[0])
    start = 0
    while start < t.size:
        stop = int(np.searchsorted(t, t[start] + 300.0 * tau_s, side="right"))
        stop = max(stop, start + 1)
        # y_n = E_n (y_prev + sum_k (1 - a_k) x_k / E_k), E_n = prod_{k <= n} a_k.
        e = np.exp(-(t[start:stop] - t[start]) / tau_s) * decay[start]
        out[start:stop] = e * (y + np.cumsum((1.0 - decay[start:stop]) * x[start:stop] / e))
        y = float(out[stop - 1])
        start = stop
    return out


def _press_signal(t: np.ndarray, strain: np.ndarray, force: np.ndarray) -> np.ndarray | None:
    """The four gratings combined for one press, in newtons: each grating's gain on the load
    (with a level and slope in time) over its noise variance weights it (the matched
    combination: a press near one support loads one grating most, and an equal sum would add
    the noise of the others). None when the gratings do not follow the load."""
    x = np.column_stack([np.ones(t.size), t - t[0], force])
    coef, *_ = np.linalg.lstsq(x, strain.astype(np.float64), rcond=None)
    resid = strain - x @ coef
    var = np.maximum((resid**2).sum(axis=0) / max(t.size - 3, 1), 1e-12)
    gain = coef[2]
    w = gain / var
    norm = float(w @ gain)
    if not np.isfinite(norm) or norm <= 0:
        return None
    return strain.astype(np.float64) @ (w / norm)


@dataclass
class _Window:
    """One press's interrogator samples used to time it: times, the combined gratings
    (:func:`_press_signal`), and the flanks' samples (loading, unloading) on the line."""

    t: np.ndarray
    signal: np.ndarray
    load: np.ndarray
    unload: np.ndarray


def _flanks(t_stage: np.ndarray, force: np.ndarray, press: _Press
            ) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the loading flank below :data:`LOAD_FRACTION` of the press's peak and the
    unloading flank below :data:`UNLOAD_FRACTION` (the rests beside them included), at the
    stage-clock times ``t_stage`` where the load is ``force``."""
    rising = t_stage <= press.peak_s
    return (rising & (force < LOAD_FRACTION * press.peak_N),
            ~rising & (force < UNLOAD_FRACTION * press.peak_N))


def _press_terms(t: np.ndarray, tail: np.ndarray | None = None) -> np.ndarray:
    """An orthonormal basis (columns) of what a press's gratings read besides its own load:
    a level and a slope in time (temperature) and, when given, ``tail``: the creep the
    presses before left in the pad (left at another place, so at a scale of its own)."""
    el = t - t[0]
    cols = np.column_stack([np.ones(t.size), el / max(float(el[-1]), 1e-9),
                            *(() if tail is None else (tail,))])
    u, sv, _ = np.linalg.svd(cols, full_matrices=False)
    return u[:, sv > 1e-9 * sv[0]]


def _fine(t: np.ndarray, signal: np.ndarray, stage: StageLog, press: _Press, tau0: float
          ) -> tuple[float, float] | None:
    """One press's offset (stage minus interrogator clock) near ``tau0`` and its sd, from its
    loading flank below :data:`LOAD_FRACTION` of its peak and its unloading flank below
    :data:`UNLOAD_FRACTION` with the rests beside them: a gain per flank (so the pad's
    friction loop does not bias it) and one level and slope in time; None when the best
    offset lies on the edge of the search or the press holds too little signal."""
    if t.size < 10:
        return None
    steps = np.arange(-FINE_WINDOW_S, FINE_WINDOW_S + FINE_STEP_S / 2, FINE_STEP_S)
    taus = tau0 + steps
    force = np.interp(t[None, :] + taus[:, None], stage.t, stage.force_N)
    load, unload = _flanks(t + tau0, force[steps.size // 2], press)
    if load.sum() < 5 or unload.sum() < 5:
        return None
    sel = load | unload
    # One level and slope in time over the press (temperature, the creep of the press
    # before), set by the rests on both sides, and one gain per flank (the pad's loop). They
    # are projected out of both sides, leaving a 2x2 problem per offset. (The lag's own
    # terms would take the lag out here too, at the cost of most of each press's precision:
    # the drift keeps it, the level is left to _lag_fit.)
    basis = _press_terms(t[sel])
    y = signal[sel] - basis @ (basis.T @ signal[sel])
    cols = []
    for m in (load[sel], unload[sel]):
        x = np.where(m[None, :], force[:, sel], 0.0)
        x -= (x @ basis) @ basis.T
        cols.append(x)
    g11, g22 = (cols[0] ** 2).sum(axis=1), (cols[1] ** 2).sum(axis=1)
    g12 = (cols[0] * cols[1]).sum(axis=1)
    h1, h2 = cols[0] @ y, cols[1] @ y
    det = g11 * g22 - g12 * g12
    if (det <= 1e-12 * np.maximum(g11 * g22, 1e-300)).any():
        return None
    rss = float(y @ y) - (g22 * h1 * h1 - 2 * g12 * h1 * h2 + g11 * h2 * h2) / det
    n_used = int(sel.sum())
    k = int(np.argmin(rss))
    if k == 0 or k == taus.size - 1:
        return None
    curv = (rss[k - 1] - 2 * rss[k] + rss[k + 1]) / FINE_STEP_S**2
    if curv <= 0:
        return None
    shift = 0.5 * (rss[k - 1] - rss[k + 1]) / (rss[k - 1] - 2 * rss[k] + rss[k + 1])
    sigma2 = max(rss[k], 0.0) / max(n_used - basis.shape[1] - 2, 1)
    return float(taus[k] + shift * FINE_STEP_S), float(np.sqrt(2 * sigma2 / curv))


def _line_fit(c: np.ndarray, tau: np.ndarray, sd: np.ndarray, t_ref: float
              ) -> tuple[float, float, np.ndarray]:
    """Weighted straight line ``tau = a + d (c - t_ref)`` with outliers (beyond 4 sd) left
    out; returns a, d and the mask of the points used."""
    sig = np.hypot(sd, PRESS_SIGMA_FLOOR_S)
    use = np.ones(c.size, dtype=bool)
    a, d = float(np.average(tau, weights=sig**-2)), 0.0
    for _ in range(6):
        w = sig[use] ** -2
        x = c[use] - t_ref
        if use.sum() >= 3 and np.ptp(x) > 0:
            d, a = np.polyfit(x, tau[use], 1, w=np.sqrt(w))
        else:
            a, d = float(np.average(tau[use], weights=w)), 0.0
        resid = tau - (a + d * (c - t_ref))
        new = np.abs(resid) <= 4 * sig
        if new.sum() < 1 or np.array_equal(new, use):
            break
        use = new
    return float(a), float(d), use


def _nonnegative_lstsq(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The non-negative ``x`` minimising ``x @ gram @ x - 2 rhs @ x`` (least squares from its
    normal equations): every subset of free variables tried, the best feasible one kept
    (exact, and cheap for the few lag time constants)."""
    n = rhs.size
    best, best_gain = np.zeros(n), 0.0
    for mask in range(1, 1 << n):
        free = np.array([(mask >> j) & 1 for j in range(n)], dtype=bool)
        try:
            x = np.linalg.solve(gram[np.ix_(free, free)], rhs[free])
        except np.linalg.LinAlgError:
            continue
        gain = float(rhs[free] @ x)
        if (x >= 0).all() and gain > best_gain:
            best = np.zeros(n)
            best[free] = x
            best_gain = gain
    return best


def _flank_basis(ts: np.ndarray, basis: np.ndarray, load: np.ndarray, unload: np.ndarray,
                 local: np.ndarray, shift: float) -> np.ndarray:
    """An orthonormal basis (columns) of a press's flank gains at the shifted stage times
    ``ts + shift``, its own terms ``basis`` taken out (``local``: its stage times and loads)."""
    f = np.interp(ts + shift, local[0], local[1])
    gains = np.column_stack([f * load, f * unload])
    gains -= basis @ (basis.T @ gains)
    return np.linalg.qr(gains)[0]


def _lag_decays(ts: np.ndarray) -> np.ndarray:
    """The free decay of each lag of :data:`LAG_TIME_CONSTANTS_S` over a press's samples
    ``ts`` (columns), one at its first sample."""
    return np.exp(-(ts - ts[0])[:, None] / np.asarray(LAG_TIME_CONSTANTS_S))


def _lag_starts(ts: np.ndarray, local: np.ndarray, shift: float) -> np.ndarray:
    """The lagged loads (``local[2:]``) at a press's first sample ``ts[0] + shift``: with
    :func:`_lag_decays`, what the presses before left in them over the press (a first-order
    lag is linear: the lagged load is that decay plus its response to the press's own load
    from rest)."""
    return np.array([np.interp(ts[0] + shift, local[0], lag) for lag in local[2:]])


def _lag_fit(windows: list[_Window], stage: StageLog, lags: list[np.ndarray], a: float,
             d: float, t_ref: float, tail_shares: np.ndarray | None = None
             ) -> tuple[float, np.ndarray]:
    """The clock's level and the pad's lag, fitted together over every timed press.

    The gratings are modelled, press by press, as a gain per flank times the load plus
    shares of the lagged loads ``lags`` (one share each for the whole log: it is one pad),
    with the press's own level and slope in time (:func:`_press_terms`). The clock's level
    is shifted over ± :data:`LAG_SEARCH_S` from the line ``a + d (t - t_ref)``; the shift of
    least weighted squares (each press weighted by its residual variance without lag) is
    returned with the shares. The shares are not negative: the gratings lag the load (their
    response to a step of load rises to its final value without overshoot), they never lead
    it. A lag moves a flank as a delay would, but not the start of a press, nor the rest
    after it (where the creep shows alone): those set the level.

    The lagged loads run over the whole stage log, so they hold the creep the presses before
    left, at the press's own scale. Those presses loaded other places, which each press's
    combination of gratings weighs otherwise: given ``tail_shares`` (the shares of a fit
    without them), a press on which that creep (the lags' decays from its first sample,
    :func:`_lag_decays`, weighted by ``tail_shares``) stands above its noise
    (:data:`TAIL_VISIBLE`) takes it as a term of its own scale, its lagged loads keeping the
    response to its own load. One term of a known shape and only where it shows: a free
    decay per time constant on every press takes most of what sets the level from a pad that
    does not creep (a millisecond of level on a noisy log)."""
    shifts = np.arange(-LAG_SEARCH_S, LAG_SEARCH_S + LAG_STEP_S / 2, LAG_STEP_S)
    n_lag = len(lags)
    prepared = []
    for w in windows:
        ts = w.t + a + d * (w.t - t_ref)
        sel = w.load | w.unload
        # The stage samples this press can reach, copied once: the search interpolates in
        # them many times over.
        j0, j1 = np.searchsorted(stage.t, [ts[0] - 2 * LAG_SEARCH_S, ts[-1] + 2 * LAG_SEARCH_S])
        j0, j1 = max(j0 - 1, 0), min(j1 + 1, stage.t.size)
        local = np.array([stage.t[j0:j1], stage.force_N[j0:j1], *(g[j0:j1] for g in lags)])
        basis = _press_terms(w.t[sel])
        y = w.signal[sel] - basis @ (basis.T @ w.signal[sel])
        # Weighted by its residual variance on the line without lag.
        q = _flank_basis(ts[sel], basis, w.load[sel], w.unload[sel], local, 0.0)
        yr = y - q @ (q.T @ y)
        weight = 1.0 / max(float(yr @ yr) / max(int(sel.sum()) - basis.shape[1] - 2, 1), 1e-12)
        decays = None
        if tail_shares is not None:
            decays = _lag_decays(ts[sel])
            tail = decays @ (_lag_starts(ts[sel], local, 0.0) * tail_shares)
            seen = tail - basis @ (basis.T @ tail)
            if weight * float(seen @ seen) >= TAIL_VISIBLE:
                basis = _press_terms(w.t[sel], tail)
                y = w.signal[sel] - basis @ (basis.T @ w.signal[sel])
            else:
                decays = None
        prepared.append((ts[sel], basis, y, w.load[sel], w.unload[sel], local, weight, decays))
    rss = np.empty(shifts.size)
    shares = np.zeros((shifts.size, n_lag))
    for i, shift in enumerate(shifts):
        za = np.zeros((n_lag, n_lag))
        zb = np.zeros(n_lag)
        yy = 0.0
        for ts, basis, y, load, unload, local, weight, decays in prepared:
            q = _flank_basis(ts, basis, load, unload, local, shift)
            f = np.interp(ts + shift, local[0], local[1])
            yr = y - q @ (q.T @ y)
            z = np.column_stack([np.interp(ts + shift, local[0], lag) - f for lag in local[2:]])
            if decays is not None:
                z -= decays * _lag_starts(ts, local, shift)
            z -= basis @ (basis.T @ z)
            zr = z - q @ (q.T @ z)
            za += weight * zr.T @ zr
            zb += weight * zr.T @ yr
            yy += weight * float(yr @ yr)
        shares[i] = _nonnegative_lstsq(za, zb)
        rss[i] = yy - float(zb @ shares[i])
    k = int(np.argmin(rss))
    shift = float(shifts[k])
    if 0 < k < shifts.size - 1:
        den = rss[k - 1] - 2 * rss[k] + rss[k + 1]
        if den > 0:
            shift += 0.5 * (rss[k - 1] - rss[k + 1]) / den * LAG_STEP_S
    return shift, shares[k]


def _time_presses(t_f: np.ndarray, strain: np.ndarray, stage: StageLog,
                  presses: list[_Press], bounds: list[tuple[float, float]], offset0: float,
                  t_ref: float) -> tuple[list[tuple[float, float, float]], list[_Window]]:
    """Time each press (:func:`_fine`), outwards from the middle of the log, each searched
    around the line fitted to those already done (refitted every 5 presses, starting from
    ``offset0`` without drift), so drift is followed over any length. Returns (fbg time,
    offset, sd) per timed press and its window."""
    mids = np.array([0.5 * (p.on_s + p.off_s) for p in presses]) - offset0
    order = np.argsort(np.abs(mids - 0.5 * (t_f[0] + t_f[-1])), kind="stable")
    found: list[tuple[float, float, float]] = []
    windows: list[_Window] = []
    a, d = offset0, 0.0
    for n_done, k in enumerate(order):
        if n_done >= 5 and n_done % 5 == 0 and found:
            arr = np.array(found)
            a, d, _ = _line_fit(arr[:, 0], arr[:, 1], arr[:, 2], t_ref)
        tau0 = a + d * (mids[k] - t_ref)
        lo, hi = bounds[k]
        i0, i1 = np.searchsorted(t_f, [lo - tau0, hi - tau0])
        t = t_f[i0:i1]
        if t.size < 10:
            continue
        signal = _press_signal(t, strain[i0:i1], np.interp(t + tau0, stage.t, stage.force_N))
        if signal is None:
            continue
        res = _fine(t, signal, stage, presses[k], tau0)
        if res is not None:
            found.append((float(mids[k]), res[0], res[1]))
            load, unload = _flanks(t + res[0], np.interp(t + res[0], stage.t, stage.force_N),
                                   presses[k])
            windows.append(_Window(t, signal, load, unload))
    return found, windows


def align(t_f: np.ndarray, strain: np.ndarray, stage: StageLog, *,
          max_offset_s: float = MAX_OFFSET_S, where: str = "<logs>") -> Alignment:
    """Estimate the stage clock against the interrogator's from the data (module docstring);
    ``strain`` is :func:`grating_strain` of the interrogator's samples ``t_f``.

    Refuses (:class:`InputError`) logs that share no time, a stage log without presses, a
    correlation below :data:`MIN_CORRELATION`, a second correlation peak within
    :data:`AMBIGUOUS_RATIO` of the first (a periodic protocol of equal presses), too few
    presses to refine, and per-press offsets off a straight line by more than
    :data:`MAX_RESIDUAL_MS`.
    """
    presses = [p for p in _stage_presses(stage) if p.peak_N >= ALIGN_MIN_PEAK_N]
    if not presses:
        raise InputError(f"no presses: the load cell never exceeds {ALIGN_MIN_PEAK_N:g} N "
                         f"(is {stage.force_flag} right: N or mN?)",
                         path=stage.path, column="force")
    # Gratings on the beams' other face are stretched by the load, not compressed: then the
    # sum falls under load, and its negative is what correlates. (Each press combines the
    # gratings by their own gains, whatever their signs: _press_signal.)
    total = strain.sum(axis=1, dtype=np.float64)
    offset0, r1, r2, lowest = _coarse(t_f, total, stage, max_offset_s, where)
    if -lowest > r1:
        offset0, r1, r2, _ = _coarse(t_f, -total, stage, max_offset_s, where)
    if r1 < MIN_CORRELATION:
        raise InputError(f"alignment failed: the load and the gratings' strain correlate at "
                         f"best {r1:.2f} (at least {MIN_CORRELATION:g} needed): are these logs "
                         "of the same session, the columns and units right?", path=where)
    if r2 >= AMBIGUOUS_RATIO * r1:
        raise InputError(f"alignment ambiguous: two clock offsets fit almost equally well "
                         f"(correlation {r1:.3f} and {r2:.3f}); a protocol of identical presses "
                         "at a fixed period cannot be aligned: vary the forces or the rests "
                         "(fbgforce protocol)", path=where)
    t_ref = float(t_f[0])
    bounds = [(p.on_s - FLANK_REST_S, p.off_s + FLANK_REST_S) for p in presses]
    # Never reach into the neighbouring press: clip to the middle of each rest.
    for k in range(len(presses) - 1):
        gap_mid = 0.5 * (presses[k].off_s + presses[k + 1].on_s)
        bounds[k] = (bounds[k][0], min(bounds[k][1], gap_mid))
        bounds[k + 1] = (max(bounds[k + 1][0], gap_mid), bounds[k + 1][1])
    found, windows = _time_presses(t_f, strain, stage, presses, bounds, offset0, t_ref)
    if len(found) < MIN_ALIGN_PRESSES:
        raise InputError(f"alignment failed: only {len(found)} of {len(presses)} presses could "
                         f"be timed against the gratings (at least {MIN_ALIGN_PRESSES} needed)",
                         path=where)
    arr = np.array(found)
    a_flanks, d, use = _line_fit(arr[:, 0], arr[:, 1], arr[:, 2], t_ref)
    resid = arr[use, 1] - (a_flanks + d * (arr[use, 0] - t_ref))
    w = np.hypot(arr[use, 2], PRESS_SIGMA_FLOOR_S) ** -2
    rms_ms = float(np.sqrt(np.average(resid**2, weights=w)) * 1e3)
    if use.sum() < max(MIN_ALIGN_PRESSES, 0.5 * len(found)) or rms_ms > MAX_RESIDUAL_MS:
        raise InputError(f"alignment ambiguous: the presses' offsets do not follow one clock "
                         f"(residual {rms_ms:.2g} ms, at most {MAX_RESIDUAL_MS:g}; "
                         f"{int(use.sum())} of {len(found)} presses agree)", path=where)
    # The line's covariance from the presses' sds, scaled up when they scatter more than
    # their sds say.
    design = np.column_stack([np.ones(int(use.sum())), arr[use, 0] - t_ref])
    chi2 = float(np.sum(w * resid**2)) / max(int(use.sum()) - 2, 1)
    cov = np.linalg.pinv(design.T @ (design * w[:, None])) * max(chi2, 1.0)
    ends = np.array([[1.0, 0.0], [1.0, float(t_f[-1]) - t_ref]])
    line_sd_ms = float(np.sqrt(np.max(np.einsum("ij,jk,ik->i", ends, cov, ends))) * 1e3)
    # The flanks time the load as the gratings see it through the pad: late by the pad's
    # lag, by about as much all through the log, so the line's drift holds and its level
    # does not. The level comes from the lag's shares fitted with it over every press.
    lags = [first_order_lag(stage.t, stage.force_N, tau) for tau in LAG_TIME_CONSTANTS_S]
    # Fitted twice when the pad lags: the creep the presses before left is then known in
    # shape (the first fit's shares), and takes a scale of each press's own where it shows.
    on_line = [w for w, u in zip(windows, use) if u]
    shift, shares = _lag_fit(on_line, stage, lags, a_flanks, d, t_ref)
    if shares.any():
        shift, shares = _lag_fit(on_line, stage, lags, a_flanks, d, t_ref, tail_shares=shares)
    a = a_flanks + shift
    table = np.column_stack([arr, use])
    return Alignment(offset_s=a, drift=d, t_ref_s=t_ref, correlation=r1, second_peak=r2,
                     residual_ms=rms_ms, line_sd_ms=line_sd_ms, lag_ms=shift * 1e3,
                     lag_shares=tuple(float(s) for s in shares),
                     presses_used=int(use.sum()),
                     presses_rejected=len(presses) - int(use.sum()), press_offsets=table)


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


def contact_threshold(noise_N: float) -> float:
    """The load above which a sample is labelled contact, N: the dataset's rule,
    :data:`fbgforce.dataset.CONTACT_THRESHOLD_N` (as the simulator labels), raised to
    :data:`LOAD_CELL_NOISE_SIGMAS` times a noisier load cell's noise ``noise_N``, so that its
    noise at rest is not labelled as touches."""
    return max(fds.CONTACT_THRESHOLD_N, LOAD_CELL_NOISE_SIGMAS * float(noise_N))


def label_contact(force_N: np.ndarray, threshold_N: float = fds.CONTACT_THRESHOLD_N
                  ) -> np.ndarray:
    """Contact where the load cell reads above ``threshold_N`` (default the dataset's rule;
    the import passes :func:`contact_threshold` of its load cell)."""
    return np.asarray(force_N) > threshold_N


def _press_runs(t: np.ndarray, contact: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The presses' contact runs (start, stop exclusive): runs closer than
    :data:`PRESS_MERGE_GAP_S` merged, runs shorter than :data:`PRESS_MIN_S` left out."""
    starts, stops = _runs(contact)
    if starts.size > 1:
        join = t[starts[1:]] - t[stops[:-1] - 1] < PRESS_MERGE_GAP_S
        keep_start = np.concatenate([[True], ~join])
        keep_stop = np.concatenate([~join, [True]])
        starts, stops = starts[keep_start], stops[keep_stop]
    long = t[stops - 1] - t[starts] >= PRESS_MIN_S
    return starts[long], stops[long]


def number_presses(t: np.ndarray, force_N: np.ndarray,
                   threshold_N: float = fds.CONTACT_THRESHOLD_N) -> np.ndarray:
    """Press ids as the simulator gives them, counting from 0: a press is its rest, its
    contact and the end of its unloading, which runs past the last contact sample to the
    first sample where the load stops falling or is within :data:`REST_BAND_N` of zero (the
    load back at rest). The samples after that carry the next press's id; those after the
    last press keep its id. ``threshold_N``: the contact threshold (:func:`label_contact`)."""
    force = np.asarray(force_N, dtype=np.float64)
    starts, stops = _press_runs(t, label_contact(force, threshold_N))
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
    from tqdm import tqdm

    t_start = time.perf_counter()
    where = f"{fbg.path} + {stage.path}"
    stage_dt = check_times(stage.t, stage.line, stage.path, "stage", stage.time_flag)
    stage_rows = int(stage.t.size)
    stage_rate = (stage.t.size - 1) / float(stage.t[-1] - stage.t[0])
    stage, stage_bad = drop_bad_stage_rows(stage)
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
    # Pass 1: times and the strain proxy (the wavelength table is not kept).
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
    al = align(t_f, strain, stage, max_offset_s=max_offset_s, where=where)
    # Contact and presses over the whole log (one bool and one id per sample).
    gap_s = STAGE_GAP_INTERVALS * stage_dt
    force, _, _, reason = stage_at(stage, al.to_stage(t_f), gap_s)
    reason[(reason == 0) & ~good] = 4
    keep = reason == 0
    if not label_contact(force[keep], threshold).any():
        raise InputError("no presses: no interrogator sample meets a load above "
                         f"{threshold:.3g} N after alignment", path=where)
    press = np.zeros(t_f.size, dtype=np.int64)
    press[keep] = number_presses(t_f[keep], force[keep], threshold)
    del force, strain
    # Pass 2: resample and write chunk by chunk.
    source = (f"import: {fbg.path} + {stage.path} offset={al.offset_s:.6f}s "
              f"drift={al.drift * 1e6:.2f}ppm")
    start = 0
    bar = tqdm(total=t_f.size, desc="import: write", unit="row", unit_scale=True,
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


def import_files(spec: ImportSpec, *, progress: bool | None = None) -> dict[str, Any]:
    """:func:`import_logs` on the CSV files an :class:`ImportSpec` names."""
    if spec.out.suffix.lower() != ".csv":
        raise InputError("the imported dataset is written as CSV: give a .csv path",
                         path=str(spec.out), column="--out")
    stage = read_stage_csv(spec.stage, spec.stage_columns, spec.force_unit, spec.position_unit,
                           spec.stage_time_unit)
    fbg = CsvFbgLog(spec.fbg, spec.fbg_columns, spec.fbg_unit, spec.fbg_time_unit)
    return import_logs(fbg, stage, spec.out, max_offset_s=spec.max_offset_s, progress=progress)
