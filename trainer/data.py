"""The calibration recordings the trainer reads: loaded (:func:`load_datasets`), split by
press (:func:`split_rows`), prepared (:class:`Prepared`, made by
:func:`fbgforce.trainer.train.prepare`), and where they hold a load still (:func:`hold_mask`).

Why by press: consecutive samples at 1 kHz are nearly identical (the same press, a few µN and
a few pm apart); a split by sample puts the neighbours of every test sample in the training
set, so the test error measures interpolation between twins, not the error on a new press.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from fbgforce.model import artifact, floatref
from fbgforce.fileio import file_sha256
from fbgforce.trainer.creep import Creep

#: Training, validation and test presses of each recording, in this ratio (:func:`split_rows`).
SPLIT_RATIOS = (8, 1, 1)


@dataclass
class Recording:
    """One continuous recording, tared and filtered on its own."""

    ds: Any
    source: str
    baseline_nm: np.ndarray
    tare_info: dict[str, Any]
    rate_hz: float
    shift_pm: np.ndarray
    feats: np.ndarray | None = None
    split: np.ndarray | None = None  # 0 train, 1 val, 2 test per sample
    #: The recording as recorded, where ``ds`` is the at-rest tracker's view of it that the
    #: nets learn (:mod:`fbgforce.trainer.tracked`); None: ``ds`` itself.
    recorded: Any = None

    @property
    def as_recorded(self) -> Any:
        """The recording as the runtime will meet it: what scoring and export run."""
        return self.ds if self.recorded is None else self.recorded


@dataclass
class Prepared:
    """All recordings with a fitted preprocessing, ready to index by split."""

    recordings: list[Recording]
    pre: artifact.Preprocess
    temp_info: dict[str, Any]
    creep_fit: "Creep | None" = None    # the pad's creep the model corrects for (prepare())
    creep_held: "Creep | None" = None   # ... at a time constant the model can hold (held_creep)
    creep_found: "Creep | None" = None  # what the fit found, established or not
    creep_evidence: dict[str, Any] | None = None   # creep_evidence() on it, and the choice
    release_holds: dict[str, Any] | None = None    # friction_hold_choice() on the training rows
    wander_holds: dict[str, Any] | None = None     # the same, for the wandering holds
    feats: np.ndarray = field(init=False)
    split: np.ndarray = field(init=False)
    contact: np.ndarray = field(init=False)
    force_N: np.ndarray = field(init=False)
    x_mm: np.ndarray = field(init=False)
    y_mm: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        recs = self.recordings
        self.feats = np.concatenate([r.feats for r in recs])
        self.split = np.concatenate([r.split for r in recs])
        self.contact = np.concatenate([np.asarray(r.ds.contact, bool) for r in recs])
        self.force_N = np.concatenate([np.asarray(r.ds.force_N, float) for r in recs])
        self.x_mm = np.concatenate([np.asarray(r.ds.x_mm, float) for r in recs])
        self.y_mm = np.concatenate([np.asarray(r.ds.y_mm, float) for r in recs])

    @property
    def creep(self) -> "Creep | None":
        """The creep the synthetic holds carry: the pad's as fitted; with the creep inverse on
        (``pre.creep``), exactly what it undoes, so that they read flat as a real hold does."""
        return self.creep_held if self.pre.creep else self.creep_fit

    @property
    def rate_hz(self) -> float:
        """The recordings' median sample rate (the one the model runs at)."""
        return float(np.median([r.rate_hz for r in self.recordings]))

    def inputs(self, pre: artifact.Preprocess) -> np.ndarray:
        """Net inputs (n, F) of every sample under ``pre``'s standardisation and memory,
        computed recording by recording (the memory states run along each recording)."""
        return np.concatenate([floatref.standardise(pre, r.feats) for r in self.recordings])

    def rows(self, part: str) -> np.ndarray:
        """Sample indices of ``"train"``, ``"val"``, ``"test"`` or ``"all"``."""
        if part == "all":
            return np.arange(self.split.size)
        return np.flatnonzero(self.split == {"train": 0, "val": 1, "test": 2}[part])

    def recording_slices(self) -> Iterator[tuple[Recording, slice]]:
        """Each recording with the slice of the concatenated arrays that holds its rows."""
        start = 0
        for r in self.recordings:
            yield r, slice(start, start + len(r.ds))
            start += len(r.ds)

    def row_mask(self, rows: np.ndarray | None = None) -> np.ndarray:
        """Boolean mask over all rows: ``rows`` (every row when None)."""
        if rows is None:
            return np.ones(self.split.size, dtype=bool)
        keep = np.zeros(self.split.size, dtype=bool)
        keep[rows] = True
        return keep

    def truth(self, rows: np.ndarray) -> tuple[np.ndarray, ...]:
        return self.contact[rows], self.force_N[rows], self.x_mm[rows], self.y_mm[rows]


def count_presses(data: Prepared, rows: np.ndarray) -> int:
    """Distinct presses (per recording) among ``rows`` of ``data``."""
    total = 0
    for r, sl in data.recording_slices():
        sel = rows[(rows >= sl.start) & (rows < sl.stop)] - sl.start
        total += int(np.unique(np.asarray(r.ds.press_id)[sel]).size)
    return total


def load_datasets(datasets: Sequence[Any]) -> tuple[list[Any], list[dict[str, Any]]]:
    """Datasets from paths or objects, with a description (path, sha256) of each."""
    from fbgforce.recordings import dataset as fds

    out, described = [], []
    for item in datasets:
        if isinstance(item, (str, Path)):
            out.append(fds.load(item))
            described.append({"path": str(item), "sha256": file_sha256(item),
                              "samples": len(out[-1])})
        else:
            out.append(item)
            described.append({"path": None, "source": getattr(item, "source", ""),
                              "samples": len(item)})
    return out, described


def split_rows(ds: Any, seed: int, ratios: Sequence[int] = SPLIT_RATIOS) -> np.ndarray:
    """Per-sample split label (0 train, 1 val, 2 test) of one recording, by press."""
    from fbgforce.recordings import dataset as fds

    rows = np.arange(len(ds), dtype=np.int64)
    tagged = ds.subset(np.ones(len(ds), dtype=bool))
    tagged.extra = dict(tagged.extra)
    tagged.extra["_row"] = rows
    label = np.zeros(len(ds), dtype=np.int8)
    parts = fds.split_by_press(tagged, seed=seed, ratios=tuple(ratios))
    for value, part in enumerate(parts):
        label[np.asarray(part.extra["_row"], dtype=np.int64)] = value
    return label


#: A hold: the load standing still under contact for at least this long (within
#: :data:`HOLD_BAND`). Models whose memory has averages need some in their calibration data.
HOLD_MIN_S = 0.2
#: How still a hold is: its load stays within max(0.2 N, 3 % of the load).
HOLD_BAND = (0.2, 0.03)


def hold_mask(force_N: np.ndarray, contact: np.ndarray, rate_hz: float) -> np.ndarray:
    """Per sample of one recording: inside a hold, a stretch of at least :data:`HOLD_MIN_S`
    in ``contact`` with the load-cell force within :data:`HOLD_BAND` (found in 10 ms blocks;
    a last partial block is never inside)."""
    block = max(1, int(round(0.01 * rate_hz)))
    width = max(1, int(round(HOLD_MIN_S * rate_hz / block)))
    n = np.asarray(force_N).size
    m = (n // block) * block
    out = np.zeros(n, dtype=bool)
    if m // block < width:
        return out
    f = np.asarray(force_N, float)[:m].reshape(-1, block)
    c = np.asarray(contact, bool)[:m].reshape(-1, block).all(axis=1)
    win = np.lib.stride_tricks.sliding_window_view
    hi = win(f.max(axis=1), width).max(axis=1)
    lo = win(f.min(axis=1), width).min(axis=1)
    still = (hi - lo <= np.maximum(HOLD_BAND[0], HOLD_BAND[1] * hi)) & win(c, width).all(axis=1)
    # A block is inside a hold when any still window starting in the last `width` blocks
    # covers it.
    inside = np.convolve(still, np.ones(width, dtype=int))[:f.shape[0]] > 0
    out[:m] = np.repeat(inside, block)
    return out


def hold_seconds(data: Prepared, rows: np.ndarray | None = None) -> float:
    """Seconds of ``data`` (optionally only ``rows``) inside holds (:func:`hold_mask`).

    An average of the load reads a held load as it reads the instant a press turns round; a net
    that never saw a hold takes one for a release (docs/teleop.md measures a grip read 1.7 N
    low), which the trainer's synthetic holds
    (:func:`~fbgforce.trainer.synthetic.synthetic_holds`) teach it.
    """
    keep = data.row_mask(rows) & data.contact
    total = 0.0
    for r, sl in data.recording_slices():
        total += float(hold_mask(data.force_N[sl], keep[sl], r.rate_hz).sum()) / r.rate_hz
    return total
