"""The dataset contract: 1 kHz samples of five peak wavelengths plus ground truth.

One :class:`Dataset` holds one recording (simulated or converted from a real calibration log:
x-y-z stage + load cell + interrogator). On disk it is a CSV (ARCHITECTURE.md §4) or an npz
with the same arrays. Every file is validated on load and on save; a problem raises
:class:`fbgforce.errors.InputError` naming the file, the 1-based line (header and comment
lines count), the column, and how many lines share the problem. Nothing is dropped silently.

Validation rules (docs/dataset.md):

- required columns (any order): ``t_s``, ``wl1_nm`` … ``wl4_nm``, ``wlT_nm``, ``contact``,
  ``x_mm``, ``y_mm``, ``force_N``, ``press_id``; other columns are kept in :attr:`Dataset.extra`;
- every field numeric; only ``x_mm``/``y_mm`` (and extra columns) may be empty;
- ``t_s`` finite and strictly increasing;
- wavelengths within 1000–2000 nm (anything else is almost always a unit mistake);
- ``contact`` exactly 0 or 1; ``x_mm``/``y_mm`` given (finite) exactly where ``contact`` is 1;
- ``force_N`` finite and not below :data:`FORCE_NEGATIVE_LIMIT_N` (small negatives are load-cell
  noise around zero and are kept as they are);
- ``press_id`` an integer.
"""
from __future__ import annotations

import csv
import io
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from fbgforce import fileio, samples
from fbgforce.recordings.bag import read_bag_columns
from fbgforce.units import nm_to_fm
from fbgforce.errors import InputError

#: Wavelength columns in array order (``wl_nm[:, k]``).
WL_COLUMNS = ("wl1_nm", "wl2_nm", "wl3_nm", "wl4_nm", "wlT_nm")
#: Every required CSV column, in the order :func:`save` writes them.
REQUIRED_COLUMNS = ("t_s",) + WL_COLUMNS + ("contact", "x_mm", "y_mm", "force_N", "press_id")
#: Accepted peak-wavelength range, nm. FBG interrogators work around 1300 or 1550 nm; a value
#: outside this range is a unit mistake (µm, pm, m) or a garbled line, not a measurement.
WL_RANGE_NM = samples.WL_RANGE_NM
#: Forces below this are rejected. A tared load cell reads a little below zero at rest
#: (noise, drift); such values are genuine data and are kept. Anything more negative means
#: a sign convention or tare error in the log.
FORCE_NEGATIVE_LIMIT_N = -0.5
#: Ground-truth contact is ``force_N`` above this (the simulator's default and the rule
#: ``fbgforce import`` labels a lab's load-cell log by; docs/dataset.md "Contact and presses").
CONTACT_THRESHOLD_N = 0.05
#: CSV number formats per column (npz is lossless). ``%g`` drops trailing zeros, which keeps
#: files short and loading fast: wavelengths 10 significant digits = 1 fm in 1000-2000 nm,
#: force 8 digits (≤ 10 µN below 1000 N), x/y 0.1 µm. Time is written as the shortest decimal
#: that reads back as the same float64 (``%r`` of a Python float): a fixed count of
#: significant digits has a resolution that depends on the magnitude (12 digits are 10 ms on
#: a Unix-epoch clock near 1.8e9 s, where 1 ms samples would collide), the shortest exact
#: form keeps whatever resolution the clock had, and a simulator's 0.001 s steps stay short.
_CSV_FORMATS = {
    "t_s": "%r",
    **{c: "%.10g" for c in WL_COLUMNS},
    "contact": "%d",
    "x_mm": "%.4f",
    "y_mm": "%.4f",
    "force_N": "%.8g",
    "press_id": "%d",
}
_MAGIC = "fbgforce-dataset"
_VERSION = 1
_DTYPE_COMMENT = "extra-dtypes:"
_EXTRA_DTYPES = ("float64", "int64", "bool", "str")
_MAX_PROBLEMS_SHOWN = 3


@dataclass
class Dataset:
    """One recording: ``n`` samples of wavelengths and ground truth.

    Attributes
    ----------
    t_s
        (n,) time, s, strictly increasing within one recording.
    wl_nm
        (n, 5) peak wavelengths of FBG 1..4 and T, nm.
    contact
        (n,) bool ground-truth contact.
    x_mm, y_mm
        (n,) contact location in the pad frame, NaN where ``contact`` is False.
    force_N
        (n,) load-cell force, N.
    press_id
        (n,) int64, groups the samples of one press (its rest and its load/unload).
    extra
        Further per-sample columns by name, each of shape (n,) (e.g. ``dropout``).
    source
        Where the data came from (a file path, or the scene/seed/device that simulated it).
    """

    t_s: np.ndarray
    wl_nm: np.ndarray
    contact: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    force_N: np.ndarray
    press_id: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""

    def __post_init__(self) -> None:
        self.t_s = np.asarray(self.t_s, dtype=np.float64).reshape(-1)
        n = self.t_s.size
        self.wl_nm = np.asarray(self.wl_nm, dtype=np.float64)
        if self.wl_nm.shape != (n, len(WL_COLUMNS)):
            raise ValueError(f"wl_nm must have shape ({n}, 5), not {self.wl_nm.shape}")
        self.contact = np.asarray(self.contact).astype(bool, copy=False).reshape(-1)
        self.x_mm = np.asarray(self.x_mm, dtype=np.float64).reshape(-1)
        self.y_mm = np.asarray(self.y_mm, dtype=np.float64).reshape(-1)
        self.force_N = np.asarray(self.force_N, dtype=np.float64).reshape(-1)
        self.press_id = np.asarray(self.press_id).astype(np.int64, copy=False).reshape(-1)
        for name in ("contact", "x_mm", "y_mm", "force_N", "press_id"):
            if getattr(self, name).size != n:
                raise ValueError(f"{name} has {getattr(self, name).size} samples, t_s has {n}")
        extra = {}
        for name, values in dict(self.extra).items():
            arr = np.asarray(values).reshape(-1)
            if arr.size != n:
                raise ValueError(f"extra column {name!r} has {arr.size} samples, t_s has {n}")
            if name in REQUIRED_COLUMNS:
                raise ValueError(f"extra column {name!r} clashes with a required column")
            extra[str(name)] = arr
        self.extra = extra
        self.source = str(self.source)

    def __len__(self) -> int:
        return int(self.t_s.size)

    def __repr__(self) -> str:
        return (f"Dataset(n={len(self)}, presses={np.unique(self.press_id).size}, "
                f"extra={sorted(self.extra)}, source={self.source!r})")

    @property
    def n_presses(self) -> int:
        """Number of distinct ``press_id`` values."""
        return int(np.unique(self.press_id).size)

    def subset(self, mask_or_index: np.ndarray | Sequence[int] | slice) -> "Dataset":
        """The samples selected by a boolean mask, an index array or a slice (copies)."""
        sel = mask_or_index
        if not isinstance(sel, slice):
            sel = np.asarray(sel)
            if sel.dtype == bool and sel.shape != (len(self),):
                raise ValueError(f"boolean mask has shape {sel.shape}, dataset has {len(self)} samples")
        return Dataset(
            t_s=self.t_s[sel].copy(),
            wl_nm=self.wl_nm[sel].copy(),
            contact=self.contact[sel].copy(),
            x_mm=self.x_mm[sel].copy(),
            y_mm=self.y_mm[sel].copy(),
            force_N=self.force_N[sel].copy(),
            press_id=self.press_id[sel].copy(),
            extra={k: v[sel].copy() for k, v in self.extra.items()},
            source=self.source,
        )

    def columns(self) -> dict[str, np.ndarray]:
        """All columns by CSV name (required first, then extras), as views."""
        cols: dict[str, np.ndarray] = {"t_s": self.t_s}
        for k, name in enumerate(WL_COLUMNS):
            cols[name] = self.wl_nm[:, k]
        cols.update(contact=self.contact, x_mm=self.x_mm, y_mm=self.y_mm,
                    force_N=self.force_N, press_id=self.press_id)
        cols.update(self.extra)
        return cols


def concat(datasets: Iterable[Dataset]) -> Dataset:
    """Concatenate datasets sample-wise, in the given order.

    Extra columns present in only some inputs are kept, filled with NaN (numeric columns,
    which become float) or ``""`` (text columns) where absent.
    Time and press ids are taken as they are: concatenating separate recordings can give a
    non-increasing ``t_s`` (which :func:`save` then rejects) and colliding press ids; shift
    them first if the result is one recording.
    """
    parts = list(datasets)
    if not parts:
        raise ValueError("concat needs at least one dataset")
    names: list[str] = []
    for ds in parts:
        names += [k for k in ds.extra if k not in names]
    extra = {}
    for name in names:
        present = [ds.extra[name] for ds in parts if name in ds.extra]
        text = any(c.dtype.kind in "US" for c in present)
        cols = []
        for ds in parts:
            if name in ds.extra:
                c = ds.extra[name]
                cols.append(c if text or len(present) == len(parts) else c.astype(np.float64))
            else:
                cols.append(np.full(len(ds), "" if text else np.nan))
        extra[name] = np.concatenate(cols)
    sources = []
    for ds in parts:
        if ds.source and ds.source not in sources:
            sources.append(ds.source)
    return Dataset(
        t_s=np.concatenate([d.t_s for d in parts]),
        wl_nm=np.concatenate([d.wl_nm for d in parts]),
        contact=np.concatenate([d.contact for d in parts]),
        x_mm=np.concatenate([d.x_mm for d in parts]),
        y_mm=np.concatenate([d.y_mm for d in parts]),
        force_N=np.concatenate([d.force_N for d in parts]),
        press_id=np.concatenate([d.press_id for d in parts]),
        extra=extra,
        source=" + ".join(sources),
    )


def resample(ds: Dataset, rate_hz: float) -> Dataset:
    """The recording on a uniform time grid at ``rate_hz`` from its first sample.

    Wavelengths and force are interpolated linearly; contact, location, press and extra
    columns are taken from the nearest original sample (a location only where that sample is
    in contact), so the result keeps the contract.
    """
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"sample rate must be a positive number, not {rate_hz!r}")
    t = ds.t_s
    if len(ds) < 2:
        return ds.subset(slice(None))
    grid = t[0] + np.arange(int(np.floor((t[-1] - t[0]) * rate_hz + 1e-9)) + 1) / rate_hz
    wl = np.column_stack([np.interp(grid, t, ds.wl_nm[:, k]) for k in range(ds.wl_nm.shape[1])])
    right = np.clip(np.searchsorted(t, grid), 1, len(t) - 1)
    nearest = np.where(grid - t[right - 1] <= t[right] - grid, right - 1, right)
    contact = ds.contact[nearest]
    return Dataset(t_s=grid, wl_nm=wl, contact=contact,
                   x_mm=np.where(contact, ds.x_mm[nearest], np.nan),
                   y_mm=np.where(contact, ds.y_mm[nearest], np.nan),
                   force_N=np.interp(grid, t, ds.force_N), press_id=ds.press_id[nearest],
                   extra={k: v[nearest] for k, v in ds.extra.items()},
                   source=f"{ds.source} resampled to {rate_hz:g} Hz")


def split_by_press(
    ds: Dataset, seed: int = 0, ratios: Sequence[float] = (8, 1, 1)
) -> tuple[Dataset, Dataset, Dataset]:
    """Split into train/validation/test sets by whole presses.

    Presses (distinct ``press_id``) are shuffled with ``numpy.random.default_rng(seed)`` and
    dealt out in proportion to ``ratios``; every sample of a press lands in the same part, so
    a held-out press was never seen (not even its neighbours in time). Within each part the
    samples keep their original order. With at least three presses no part is empty.
    """
    r = np.asarray(ratios, dtype=np.float64)
    if r.shape != (3,) or np.any(r < 0) or r.sum() <= 0:
        raise ValueError(f"ratios must be three non-negative numbers, not {ratios!r}")
    ids = np.unique(ds.press_id)
    order = np.random.default_rng(seed).permutation(ids)
    n = ids.size
    counts = np.floor(r / r.sum() * n).astype(int)
    # Deal the rounding remainder to the parts with the largest fractional share first.
    remainder = n - counts.sum()
    frac = r / r.sum() * n - counts
    for k in np.argsort(-frac, kind="stable")[:remainder]:
        counts[k] += 1
    if n >= 3:
        for k in range(3):
            if counts[k] == 0 and r[k] > 0:
                donor = int(np.argmax(counts))
                counts[donor] -= 1
                counts[k] += 1
    bounds = np.cumsum(counts)
    groups = (order[: bounds[0]], order[bounds[0]: bounds[1]], order[bounds[1]:])
    parts = tuple(ds.subset(np.isin(ds.press_id, g)) for g in groups)
    return parts  # type: ignore[return-value]


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------

@dataclass
class Problem:
    """One kind of problem in a file: where it first occurs and how often."""

    column: str
    reason: str
    first_row: int  # 0-based data row
    count: int
    line: int | None = None  # 1-based file line, when the file has lines


class DatasetError(InputError):
    """A dataset file (or array set) failed validation; :attr:`problems` lists every problem."""

    def __init__(self, problems: list[Problem], *, path: str | None, unit: str = "line") -> None:
        self.problems = problems
        first = problems[0]
        more = ""
        if first.count > 1:
            more = f" ({first.count} {unit}s like this)"
        others = []
        for p in problems[1:1 + _MAX_PROBLEMS_SHOWN]:
            where = f"{unit} {p.line if p.line is not None else p.first_row}"
            plural = "s" if p.count != 1 else ""
            others.append(f"{where} column {p.column!r}: {p.reason} ({p.count} {unit}{plural})")
        if len(problems) > 1 + _MAX_PROBLEMS_SHOWN:
            others.append(f"{len(problems) - 1 - _MAX_PROBLEMS_SHOWN} more")
        tail = f"; also {'; '.join(others)}" if others else ""
        line = first.line
        reason = first.reason
        if line is None and unit == "row":
            reason = f"row {first.first_row}: {reason}"
        super().__init__(reason + more + tail, path=path, line=line, column=first.column)


def _num(v: Any) -> str:
    """A number as the user wrote it (no numpy type in the message)."""
    return repr(float(v))


def _check(problems: list[Problem], column: str, bad: np.ndarray, reason: Any) -> None:
    """Record a problem for the rows where ``bad`` is True (``reason`` may be a callable of
    the first bad row, to quote its value)."""
    idx = np.flatnonzero(bad)
    if idx.size:
        first = int(idx[0])
        text = reason(first) if callable(reason) else reason
        problems.append(Problem(column, text, first, int(idx.size)))


def validate_columns(cols: dict[str, np.ndarray]) -> list[Problem]:
    """Check parsed numeric required columns against the contract (see module docstring)."""
    problems: list[Problem] = []
    t = cols["t_s"]
    _check(problems, "t_s", ~np.isfinite(t), 
           lambda i: "missing value" if np.isnan(t[i]) else f"time must be finite, got {_num(t[i])}")
    if t.size > 1:
        with np.errstate(invalid="ignore"):
            step_bad = ~(np.diff(t) > 0)
        step_bad &= np.isfinite(t[1:]) & np.isfinite(t[:-1])
        _check(problems, "t_s", np.concatenate([[False], step_bad]),
               lambda i: f"time not increasing: {_num(t[i])} s follows {_num(t[i - 1])} s")
    lo, hi = WL_RANGE_NM
    for name in WL_COLUMNS:
        wl = cols[name]
        with np.errstate(invalid="ignore"):
            bad = ~((wl >= lo) & (wl <= hi))
        _check(problems, name, bad,
               lambda i, wl=wl: (samples.unit_hint(wl[i]) if np.isfinite(wl[i])
                                 else "missing wavelength"))
    c = cols["contact"]
    contact_bad = ~((c == 0) | (c == 1))
    _check(problems, "contact", contact_bad,
           lambda i: "missing value" if np.isnan(c[i]) else f"contact must be 0 or 1, got {_num(c[i])}")
    on = c == 1
    off = c == 0
    for name in ("x_mm", "y_mm"):
        v = cols[name]
        given = ~np.isnan(v)
        _check(problems, name, off & given,
               lambda i, v=v, name=name: f"{name[0]} given ({_num(v[i])}) without contact: leave it "
                                         "empty where contact is 0")
        _check(problems, name, on & ~given, f"{name[0]} missing where contact is 1")
        _check(problems, name, on & given & ~np.isfinite(v),
               lambda i, v=v: f"location must be finite, got {_num(v[i])}")
    f = cols["force_N"]
    _check(problems, "force_N", np.isnan(f), "missing force")
    with np.errstate(invalid="ignore"):
        _check(problems, "force_N", np.isinf(f) | (f < FORCE_NEGATIVE_LIMIT_N),
               lambda i: f"force {_num(f[i])} N is not allowed: negative forces below "
                         f"{FORCE_NEGATIVE_LIMIT_N:g} N mean a sign or tare error")
    p = cols["press_id"]
    with np.errstate(invalid="ignore"):
        _check(problems, "press_id", ~np.isfinite(p) | (p != np.round(p)) | (np.abs(p) > 2**62),
               lambda i: "missing value" if np.isnan(p[i]) else f"press_id must be an integer, got {_num(p[i])}")
    problems.sort(key=lambda q: q.first_row)
    return problems


def _dataset_from_columns(cols: dict[str, np.ndarray], extra: dict[str, np.ndarray],
                          source: str) -> Dataset:
    return Dataset(
        t_s=cols["t_s"],
        wl_nm=np.column_stack([cols[c] for c in WL_COLUMNS]),
        contact=cols["contact"] == 1,
        x_mm=cols["x_mm"],
        y_mm=cols["y_mm"],
        force_N=cols["force_N"],
        press_id=np.round(cols["press_id"]).astype(np.int64),
        extra=extra,
        source=source,
    )


# --------------------------------------------------------------------------------------------
# CSV
# --------------------------------------------------------------------------------------------

def _read_text(path: Path) -> str:
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError("no such file", path=str(path)) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=str(path)) from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise InputError(f"not UTF-8 text (byte 0x{raw[exc.start]:02x})", path=str(path),
                         line=line) from None


def _parse_dtype_comment(comments: list[str]) -> dict[str, str]:
    dtypes: dict[str, str] = {}
    for c in comments:
        body = c.lstrip("#").strip()
        if body.startswith(_DTYPE_COMMENT):
            for item in body[len(_DTYPE_COMMENT):].split():
                name, _, dt = item.partition("=")
                if dt in _EXTRA_DTYPES:
                    dtypes[name] = dt
    return dtypes


def _load_csv(path: Path) -> Dataset:
    text = _read_text(path)
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    spath = str(path)
    comments, names, header_line, pos = _csv_header(text, spath)
    body = text[pos:].rstrip("\n")
    cols_num, extra_raw, line_no = _csv_columns(body, names, header_line, comments, spath)
    dtypes = _parse_dtype_comment(comments)
    required = {c: cols_num[c] for c in REQUIRED_COLUMNS}
    # An empty field parses as NaN; outside x/y the checks report it as a missing value.
    problems = validate_columns(required)
    if problems:
        for p in problems:
            p.line = int(line_no[p.first_row])
        raise DatasetError(problems, path=spath)

    extra: dict[str, np.ndarray] = {}
    for name in names:
        if name in REQUIRED_COLUMNS:
            continue
        values = extra_raw.get(name, cols_num.get(name))
        extra[name] = _typed_extra(values, dtypes.get(name))
    return _dataset_from_columns(required, extra, spath)


def _csv_header(text: str, spath: str) -> tuple[list[str], list[str], int, int]:
    """The comments before the header, the header's column names (checked: none empty, none
    twice, every required one), its 1-based line and where the data begin in ``text``."""
    # Header: the first line that is neither blank nor a comment. Scanned line by line only
    # up to the header, so a large file is never split into Python strings on the fast path.
    pos, line = 0, 0
    comments: list[str] = []
    header = None
    while pos < len(text):
        nl = text.find("\n", pos)
        nl = len(text) if nl < 0 else nl
        line += 1
        s = text[pos:nl].strip()
        pos = nl + 1
        if not s:
            continue
        if s.startswith("#"):
            comments.append(s)
            continue
        header = s
        break
    if header is None:
        raise InputError("empty file: no header row (expected columns "
                         + ", ".join(REQUIRED_COLUMNS) + ")", path=spath)
    header_line = line
    names = _header_names(header, spath, header_line)
    seen: dict[str, int] = {}
    for j, name in enumerate(names):
        if not name:
            raise InputError(f"header field {j + 1} is empty", path=spath, line=header_line)
        if name in seen:
            raise InputError(f"duplicate column (fields {seen[name] + 1} and {j + 1})", path=spath,
                             line=header_line, column=name)
        seen[name] = j
    missing = [c for c in REQUIRED_COLUMNS if c not in seen]
    if missing:
        raise InputError(f"missing required column{'s' if len(missing) > 1 else ''} "
                         f"{', '.join(missing)} (header has: {', '.join(names)})",
                         path=spath, line=header_line, column=missing[0])
    return comments, names, header_line, pos


def _csv_columns(body: str, names: list[str], header_line: int, comments: list[str], spath: str
                 ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], np.ndarray]:
    """The data rows after the header: numeric columns by name, text columns by name and each
    row's file line. Comments among the rows are added to ``comments``."""
    ncol = len(names)
    matrix = None
    text_columns = {k for k, v in _parse_dtype_comment(comments).items() if v == "str"}
    if body and "#" not in body and "\n\n" not in body and not text_columns:
        # Fast path: every line after the header is a data row, so row i is file line
        # header_line + 1 + i; loadtxt (C) parses all of it or fails on the first oddity.
        matrix = _parse_numeric_fast(body)
        if matrix is not None and matrix.shape[1] != ncol:
            matrix = None
    if matrix is not None:
        line_no = np.arange(matrix.shape[0], dtype=np.int64) + header_line + 1
        return {name: matrix[:, j] for j, name in enumerate(names)}, {}, line_no
    # Slow path (comments or blank lines among the data, text columns, or a bad field):
    # keep every data line's file line number so each error points at the real line.
    lines = body.split("\n")
    keep = [i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    comments.extend(ln.strip() for ln in lines if ln.lstrip().startswith("#"))
    if not keep:
        raise InputError("no data rows after the header", path=spath, line=header_line)
    data = [lines[i] for i in keep]
    line_no = np.asarray(keep, dtype=np.int64) + header_line + 1
    fields = _split_rows(data, spath, line_no)
    nfields = np.fromiter((len(f) for f in fields), dtype=np.int64, count=len(fields))
    bad = np.flatnonzero(nfields != ncol)
    if bad.size:
        i = int(bad[0])
        raise InputError(f"expected {ncol} comma-separated fields (as in the header), found "
                         f"{nfields[i]}" + (f" ({bad.size} lines like this)" if bad.size > 1 else ""),
                         path=spath, line=int(line_no[i]))
    matrix = None if text_columns else _parse_numeric_fast("\n".join(data))
    if matrix is None:
        cols_num, extra_raw = _parse_slow(fields, names, line_no, spath, text_columns)
        return cols_num, extra_raw, line_no
    return {name: matrix[:, j] for j, name in enumerate(names)}, {}, line_no


def _parse_numeric_fast(data: str) -> np.ndarray | None:
    """All fields of newline-separated rows as float64 (empty fields NaN), or None if any
    field is not a number or the rows differ in length."""
    # Empty fields (no location without contact) become "nan" by plain substring replacement,
    # an order of magnitude faster than a regex on a 20 MB file. Blank-but-spaced fields make
    # loadtxt fail and take the slow path, which handles them.
    joined = "\n" + data + "\n"
    for old, new in ((",,", ",nan,"), (",,", ",nan,"), ("\n,", "\nnan,"), (",\n", ",nan\n")):
        if old in joined:  # a scan is much cheaper than copying 20 MB for nothing
            joined = joined.replace(old, new)
    try:
        return np.loadtxt(io.StringIO(joined), delimiter=",", dtype=np.float64, ndmin=2,
                          comments=None)
    except ValueError:
        return None


def _header_names(header: str, spath: str, line: int) -> list[str]:
    """The column names of the header line, read by :mod:`csv` (quoted names allowed); a
    header separated by another delimiter is refused naming it."""
    names = [h.strip() for h in next(csv.reader([header]))]
    if len(names) == 1:
        for delimiter, label in ((";", "semicolons"), ("\t", "tabs"), ("|", "bars")):
            if delimiter in header:
                raise InputError(f"the header is separated by {label} ({delimiter!r}); dataset "
                                 "CSV files are comma-separated (save or export with ',' as the "
                                 "delimiter and '.' as the decimal point)", path=spath, line=line)
    return names


def _split_rows(data: list[str], spath: str, line_no: np.ndarray) -> list[list[str]]:
    """The fields of each data line, read by :mod:`csv` (quoted fields allowed)."""
    try:
        return list(csv.reader(data, strict=True))
    except csv.Error:
        pass
    for i, ln in enumerate(data):  # again line by line, to name the line at fault
        try:
            next(csv.reader([ln], strict=True))
        except csv.Error as exc:
            raise InputError(f"not valid CSV: {exc}", path=spath, line=int(line_no[i])) from None
    raise InputError("not valid CSV", path=spath)


def _parse_slow(fields: list[list[str]], names: list[str], line_no: np.ndarray, spath: str,
                text_columns: set[str]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Per-field parsing, used only when the fast path cannot be: finds the non-numeric fields
    of required columns (first line and count per column) and keeps text extra columns (and
    those the dtype comment declares text, even if they look numeric) as text."""
    problems: list[Problem] = []
    numeric: dict[str, np.ndarray] = {}
    text_extra: dict[str, np.ndarray] = {}
    for j, name in enumerate(names):
        raw = [f[j].strip() for f in fields]
        if name in text_columns and name not in REQUIRED_COLUMNS:
            text_extra[name] = np.asarray(raw, dtype=str)
            continue
        values = np.empty(len(raw))
        bad_idx = []
        for i, s in enumerate(raw):
            if not s:
                values[i] = np.nan
                continue
            try:
                values[i] = float(s)
            except ValueError:
                bad_idx.append(i)
                values[i] = np.nan
        if not bad_idx:
            numeric[name] = values
        elif name in REQUIRED_COLUMNS:
            i = bad_idx[0]
            problems.append(Problem(name, f"not a number: {raw[i]!r}", i, len(bad_idx),
                                    int(line_no[i])))
        else:
            text_extra[name] = np.asarray(raw, dtype=str)
    if problems:
        problems.sort(key=lambda q: q.first_row)
        raise DatasetError(problems, path=spath)
    return numeric, text_extra


def _typed_extra(values: np.ndarray, dtype: str | None) -> np.ndarray:
    if values.dtype.kind in "US":
        return values
    if dtype in ("int64", "bool") and np.all(np.isfinite(values)) \
            and np.all(values == np.round(values)):
        return values.astype(np.int64) if dtype == "int64" else values != 0
    return values


def _extra_kind(arr: np.ndarray) -> str:
    if arr.dtype == bool:
        return "bool"
    if arr.dtype.kind in "iu":
        return "int64"
    if arr.dtype.kind in "US":
        return "str"
    return "float64"


class CsvWriter:
    """Writes a dataset CSV in pieces: the header once, then each :class:`Dataset` chunk given
    to :meth:`write` (validated, and later than the chunk before), so a long recording never
    has to be held whole. :func:`save` writes through it in one piece.

    Parameters
    ----------
    path
        The CSV to write.
    source
        :attr:`Dataset.source` recorded in the header comment.
    extra_kinds
        Extra column name -> dtype name (``float64``, ``int64``, ``bool``, ``str``), in order;
        every chunk must carry exactly these extra columns.
    """

    def __init__(self, path: str | Path, source: str = "",
                 extra_kinds: dict[str, str] | None = None) -> None:
        self.path = Path(path)
        self.extra_kinds = dict(extra_kinds or {})
        self.rows = 0
        self._last_t = -np.inf
        names = list(REQUIRED_COLUMNS) + list(self.extra_kinds)
        fmts = [_CSV_FORMATS.get(name) or
                {"bool": "%d", "int64": "%d", "str": "%s", "float64": "%.9g"}[self.extra_kinds[name]]
                for name in names]
        self._names = names
        self._row_fmt = ",".join(fmts)
        header = [f"# {_MAGIC} v{_VERSION}: peak wavelengths (nm) and ground truth, one row per sample"]
        if source:
            header.append("# source: " + source.replace("\n", " "))
        if self.extra_kinds:
            header.append(f"# {_DTYPE_COMMENT} "
                          + " ".join(f"{k}={v}" for k, v in self.extra_kinds.items()))
        header.append(",".join(names))
        # Written under a temporary name and renamed by close(): a failed recording or import
        # leaves whatever the path held before (fbgforce.fileio).
        self._outputs = fileio.Outputs()
        self._file: Any = self._outputs.open(self.path, "w", encoding="utf-8", newline="\n")
        self._fh = self._file.__enter__()
        try:
            self._fh.write("\n".join(header) + "\n")
        except OSError as exc:
            self._abandon()
            raise fileio.write_error(exc, self.path) from None

    def write(self, ds: Dataset, *, check: bool = True) -> None:
        """Append one chunk's rows, validated first unless the caller already did
        (``check=False``)."""
        if len(ds) == 0:
            return
        if list(ds.extra) != list(self.extra_kinds):
            raise ValueError(f"chunk extras {list(ds.extra)} differ from {list(self.extra_kinds)}")
        if check:
            validate(ds, where=f"dataset to save as {self.path}")
        if ds.t_s[0] <= self._last_t:
            raise InputError(f"time not increasing between chunks ({ds.t_s[0]!r} after "
                             f"{self._last_t!r})", path=str(self.path), column="t_s")
        cols = ds.columns()
        arrays = []
        for name in self._names:
            arr = cols[name]
            if self.extra_kinds.get(name) == "str" and any("," in v or "\n" in v
                                                          for v in arr.tolist()):
                raise InputError("text values must not contain commas or newlines in CSV",
                                 path=str(self.path), column=name)
            arrays.append((arr.astype(np.int64) if arr.dtype == bool else arr).tolist())
        body = "\n".join(self._row_fmt % row for row in zip(*arrays))
        # NaN location (no contact) and NaN extras are written as empty fields, as the contract says.
        body = "\n" + body + "\n"
        body = body.replace(",nan,", ",,").replace(",nan,", ",,")
        body = body.replace("\nnan,", "\n,").replace(",nan\n", ",\n")[1:]
        try:
            self._fh.write(body)
        except OSError as exc:
            self._abandon()
            raise fileio.write_error(exc, self.path) from None
        self.rows += len(ds)
        self._last_t = float(ds.t_s[-1])

    def close(self) -> None:
        """Finish the file: it appears under its name only now."""
        if self._file is not None:
            file, self._file = self._file, None
            try:
                file.__exit__(None, None, None)
            except BaseException:
                self._outputs.discard()
                raise
            self._outputs.commit()

    def _abandon(self) -> None:
        if self._file is not None:
            file, self._file = self._file, None
            try:
                file.__exit__(None, None, None)
            except InputError:
                pass
        self._outputs.discard()

    def __enter__(self) -> "CsvWriter":
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self._abandon()


def _save_csv(ds: Dataset, path: Path) -> None:
    with CsvWriter(path, ds.source, {k: _extra_kind(v) for k, v in ds.extra.items()}) as w:
        w.write(ds, check=False)


# --------------------------------------------------------------------------------------------
# npz
# --------------------------------------------------------------------------------------------

_EXTRA_PREFIX = "extra/"


def _load_npz(path: Path) -> Dataset:
    spath = str(path)
    try:
        npz = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError("no such file", path=spath) from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"not a readable npz file (truncated or corrupt?): {exc}",
                         path=spath) from None
    with npz:
        try:
            arrays = {k: npz[k] for k in npz.files}
        except ValueError as exc:  # object arrays need pickle, which we never allow
            raise InputError(f"unsupported array in npz: {exc}", path=spath) from None
        except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise InputError(f"npz file truncated or corrupt: {exc}", path=spath) from None
    if not arrays:
        raise InputError("empty file: no arrays", path=spath)
    cols: dict[str, np.ndarray] = {}
    if "wl_nm" in arrays:
        try:
            # Shape and dtype here; each row's values are checked below, line by line.
            wl = samples.wavelength_array(arrays["wl_nm"], name="wl_nm", check_unit=False)
        except InputError as exc:
            raise InputError(exc.reason, path=spath, column="wl_nm") from None
        for k, name in enumerate(WL_COLUMNS):
            cols[name] = wl[:, k]
    for name in REQUIRED_COLUMNS:
        if name in cols:
            continue
        if name not in arrays:
            raise InputError(f"missing array {name!r} (arrays present: {', '.join(sorted(arrays))})",
                             path=spath, column=name)
        cols[name] = arrays[name]
    n = None
    for name in REQUIRED_COLUMNS:
        arr = np.asarray(cols[name])
        if arr.ndim != 1:
            raise InputError(f"must be one-dimensional, has shape {arr.shape}", path=spath,
                             column=name)
        if n is None:
            n = arr.size
        elif arr.size != n:
            raise InputError(f"has {arr.size} samples, t_s has {n}", path=spath, column=name)
        if arr.dtype.kind not in "biuf":
            raise InputError(f"must be numeric, has dtype {arr.dtype}", path=spath, column=name)
        cols[name] = arr.astype(np.float64)
    if not n:
        raise InputError("empty file: no samples", path=spath)
    problems = validate_columns(cols)
    if problems:
        raise DatasetError(problems, path=spath, unit="row")
    extra = {}
    for key, arr in arrays.items():
        if key.startswith(_EXTRA_PREFIX):
            name = key[len(_EXTRA_PREFIX):]
            if arr.shape != (n,):
                raise InputError(f"extra array has shape {arr.shape}, expected ({n},)", path=spath,
                                 column=key)
            extra[name] = arr
    return _dataset_from_columns(cols, extra, spath)


def _save_npz(ds: Dataset, path: Path) -> None:
    arrays = {
        "t_s": ds.t_s, "wl_nm": ds.wl_nm, "contact": ds.contact, "x_mm": ds.x_mm,
        "y_mm": ds.y_mm, "force_N": ds.force_N, "press_id": ds.press_id,
        "format": np.asarray(f"{_MAGIC} v{_VERSION}"), "source": np.asarray(ds.source),
    }
    for name, arr in ds.extra.items():
        arrays[_EXTRA_PREFIX + name] = arr
    fileio.write_with(path, lambda fh: np.savez(fh, **arrays))


# --------------------------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------------------------

def _kind(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return "csv"
    if suffix == ".npz":
        return "npz"
    raise InputError(f"unknown dataset file type {suffix or '(none)'!r}: use .csv or .npz",
                     path=str(path))


def is_bag(path: str | Path) -> bool:
    """A rosbag2 log: an ``.mcap`` file or a bag directory (with ``metadata.yaml``)."""
    p = Path(path)
    return p.suffix.lower() == ".mcap" or (p / "metadata.yaml").is_file()


def load(path: str | Path, fields: dict[str, str] | None = None) -> Dataset:
    """Load and validate a dataset file (``.csv`` or ``.npz``, by suffix) or a rosbag2 log
    (an ``.mcap`` file or a bag directory, :func:`fbgforce.recordings.dataset.load_bag`).

    ``fields`` maps dataset columns to bag topics and fields for a log recorded by another
    driver (:mod:`fbgforce.recordings.bag`); by default a bag is read as ``fbgforce record`` writes it.

    Raises
    ------
    fbgforce.errors.InputError
        If the file is missing or violates the contract; the message names the file, the
        1-based line (CSV; header and comments count) or 0-based row (npz, bags), the column
        and the problem, with how many lines share it.
    """
    p = Path(path)
    if is_bag(p):
        if not p.exists():
            raise InputError("no such file", path=str(p))
        return load_bag(p, fields)
    if fields is not None:
        raise InputError("a field map is for rosbag2 logs (.mcap or a bag directory)",
                         path=str(p), column="fields")
    return _load_csv(p) if _kind(p) == "csv" else _load_npz(p)


def load_bag(path: str | Path, fields: Mapping[str, str] | None = None) -> Dataset:
    """A :class:`Dataset` from a rosbag2 log, validated like any file.

    ``fields`` is the field map (default :data:`FBGFORCE_FIELDS`). Rows before every joined
    topic has spoken are dropped (the count is in the dataset's ``source``) and ``t_s`` counts
    from the first row kept. The extra column ``stamp_ns`` keeps each row's stamp.
    """
    path = Path(path)
    cols = read_bag_columns(path, fields)
    keep = cols["complete"]
    dropped = int((~keep).sum())
    cols = {k: v[keep] for k, v in cols.items()}
    contact = cols["contact"]
    wl = np.column_stack([cols[c] for c in WL_COLUMNS])
    wl = np.where(np.isfinite(wl), nm_to_fm(wl) / 1e6, wl)
    where = str(path) + (f" (rosbag2; {dropped} rows before the first message of every "
                         f"joined topic dropped)" if dropped else " (rosbag2)")
    gate = contact == 1
    stamp = cols["stamp_ns"]
    ds = Dataset(
        t_s=(stamp - stamp[0]) / 1e9 if len(stamp) else stamp, wl_nm=wl, contact=gate,
        x_mm=np.where(gate, cols["x_mm"], np.nan), y_mm=np.where(gate, cols["y_mm"], np.nan),
        force_N=cols["force_N"],
        press_id=cols["press_id"].astype(np.int64) if "press_id" in cols
        else np.zeros(len(contact), dtype=np.int64),
        extra={"stamp_ns": cols["stamp_ns"]}, source=where)
    bad = ~np.isin(contact, (0.0, 1.0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"row {i}: contact must be 0 or 1, got {contact[i]!r} "
                         f"({int(bad.sum())} rows like this)", path=str(path), column="contact")
    validate(ds, where=str(path))
    return ds


# --------------------------------------------------------------------------------------------
# pandas (optional: only these two functions need it)
# --------------------------------------------------------------------------------------------

def _pandas() -> Any:
    try:
        import pandas
    except ImportError:
        raise ImportError("pandas is not installed; `pip install pandas` to convert datasets "
                          "to and from DataFrames") from None
    return pandas


def to_dataframe(ds: Dataset) -> Any:
    """``ds`` as a pandas DataFrame with the CSV column names (required columns first, then
    the extra columns); ``df.attrs["source"]`` keeps :attr:`Dataset.source`. Needs pandas."""
    pd = _pandas()
    df = pd.DataFrame({name: np.array(col, copy=True) for name, col in ds.columns().items()})
    df.attrs["source"] = ds.source
    return df


def from_dataframe(df: Any, source: str | None = None) -> Dataset:
    """A :class:`Dataset` from a DataFrame with the CSV column names (any order; columns
    beyond the required ones become :attr:`Dataset.extra`), validated exactly as a file is:
    a problem raises :class:`InputError` naming the row (0-based position) and column. ``source`` defaults to ``df.attrs["source"]`` or ``"<DataFrame>"``."""
    where = source or getattr(df, "attrs", {}).get("source") or "<DataFrame>"
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)} (required: "
                         f"{', '.join(REQUIRED_COLUMNS)})", path=where)
    cols: dict[str, np.ndarray] = {}
    for name in REQUIRED_COLUMNS:
        try:
            cols[name] = np.asarray(df[name].to_numpy(dtype=np.float64, na_value=np.nan))
        except (TypeError, ValueError) as exc:
            raise InputError(f"not numeric: {exc}", path=where, column=name) from None
    if len(df) == 0:
        raise InputError("empty dataset: no samples", path=where)
    problems = validate_columns(cols)
    if problems:
        raise DatasetError(problems, path=where, unit="row")
    extra = {}
    for name in df.columns:
        if name in REQUIRED_COLUMNS:
            continue
        values = df[name].to_numpy()
        extra[str(name)] = values.astype(str) if values.dtype == object else values
    return _dataset_from_columns(cols, extra, where)


def validate(ds: Dataset, where: str = "<dataset>") -> None:
    """Check an in-memory dataset against the contract (raises :class:`DatasetError`)."""
    cols = {name: np.asarray(v, dtype=np.float64) for name, v in ds.columns().items()
            if name in REQUIRED_COLUMNS}
    if len(ds) == 0:
        raise InputError("empty dataset: no samples", path=where)
    problems = validate_columns(cols)
    if problems:
        raise DatasetError(problems, path=where, unit="row")


def save(ds: Dataset, path: str | Path) -> None:
    """Validate ``ds`` and write it as CSV or npz (by suffix).

    CSV stores time exactly (the shortest decimal that reads back as the same float64, at
    any magnitude: Unix-epoch clocks included) and the rest at fixed resolutions
    (wavelengths 1 fm, force 8 significant digits, x/y 0.1 µm; float extras 9 significant
    digits), and records extra-column dtypes in a comment so that they load back as written;
    npz is lossless. Refuses to write data :func:`load` would reject.
    """
    p = Path(path)
    kind = _kind(p)
    validate(ds, where=f"dataset to save as {p}")
    if kind == "csv":
        _save_csv(ds, p)
    else:
        _save_npz(ds, p)
