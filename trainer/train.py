"""Training the hierarchical model (paper §III) from calibration recordings.

``train(datasets, ...)`` fits preprocessing (tare per recording, temperature coefficients,
Gaussian filter, standardisation), splits every recording 8:1:1 BY PRESS, trains the contact,
force and location nets in that order with Adam and early stopping, and returns a
:class:`fbgforce.model.artifact.HierarchicalModel` whose metadata records the data (files and sha256),
the seed, the sizes, the validation and test metrics and the times.

Why by press: consecutive samples at 1 kHz are nearly identical (the same press, a few µN and
a few pm apart); a split by sample puts the neighbours of every test sample in the training
set, so the test error measures interpolation between twins, not the error on a new press.
"""
from __future__ import annotations

import copy
import hashlib
import math
import platform
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from fbgforce import __version__
from fbgforce import contract
from fbgforce.evaluation import metrics as fmetrics
from fbgforce.model import artifact, floatref, modeldir
from fbgforce.errors import InputError
from fbgforce.trainer import preprocess as pp
from fbgforce.recordings import tare as fbgtare
from fbgforce.trainer.nets import FlatMLP, drop_unread_units, fit, predict_batched

#: Hidden-layer widths of the paper's Fig. 4 (the `paper` width of ``fbgforce tradeoff``).
PAPER_SIZES: dict[str, tuple[int, ...]] = {
    "contact": (70, 50, 20),
    "force": (70, 50, 20),
    "location": (70, 50, 40),
}
#: Hidden-layer widths the trainer starts from (``--sizes`` changes them; the force net's
#: weight decay then switches off the units it does not need): about half the paper's, which
#: brings a contact step within a tenth of a 168 MHz Cortex-M4 at 1 kHz by estimated cycles
#: at the paper widths' accuracy within the spread of training seeds (docs/trainer.md,
#: "Widths and the Cortex-M4").
DEFAULT_SIZES: dict[str, tuple[int, ...]] = {
    "contact": (36, 26, 10),
    "force": (50, 30, 16),
    "location": (36, 26, 20),
}
SPLIT_RATIOS = (8, 1, 1)
#: The default L2 weight decay of each net, as a prior of fixed strength: the decay is this
#: many training samples' worth divided by the number of samples the net trains on. A fit
#: with a fixed Gaussian prior on the weights weighs it so against a loss averaged over n
#: samples, and so a short calibration log is regularised harder than a long one: 1.1e-4 for
#: the force net on the calibration scene (132,000 samples), 4.7e-4 on a 60-press log
#: (docs/trainer.md, "What limits training" and "Restarts and force weight decay").
DEFAULT_DECAY_SAMPLES: dict[str, float] = {"contact": 0.0, "force": 15.0, "location": 0.0}
#: The location net also trains on copies of the training presses scaled by a factor drawn
#: per press from [1, LOCATION_AUGMENT] (see :func:`_scaled_presses`); 1 turns this off.
LOCATION_AUGMENT = 3.0
#: Synthetic holds (:func:`_synthetic_holds`): the contact and force nets also train on this
#: share of the training presses with their peak stretched into a hold of a length drawn in
#: :data:`HOLD_AUGMENT_S` (seconds), of which one sample every :data:`HOLD_AUGMENT_STEP_S`
#: trains (consecutive held samples differ only by noise and the averages' slow decay); 0 turns
#: this off (docs/trainer.md, "Held grips").
HOLD_AUGMENT = 0.2
HOLD_AUGMENT_S = (1.5, 6.0)
HOLD_AUGMENT_STEP_S = 0.004
#: A press turns at its last sample at this fraction of its peak force or more
#: (:func:`after_turns`, ``turn_guard_s``).
TURN_FRACTION = 0.995
#: The turn guard a model that takes the pad's creep out before the filter trains with by
#: default (``turn_guard_s`` None): the causal filter's length (docs/trainer.md, "The turn").
TURN_GUARD_S = 0.015
#: Synthetic long rests (:func:`_synthetic_rests`): the contact and force nets also train on
#: rests of a length drawn in :data:`REST_AUGMENT_S` (seconds) inserted before this share of
#: the training presses, one sample every :data:`REST_AUGMENT_STEP_S` from
#: :data:`REST_AUGMENT_SETTLE_S` into the rest on; 0 turns this off (docs/trainer.md, "Long
#: rests"). Up to a minute: the play operators' states keep creeping with the noise's extremes
#: for minutes of rest; one sample in 50 ms trains as many samples per rest as one in 10 ms
#: over 12 s did.
REST_AUGMENT = 0.2
REST_AUGMENT_S = (3.0, 60.0)
REST_AUGMENT_STEP_S = 0.05
REST_AUGMENT_SETTLE_S = 0.5
#: Relaxation times (s) tried by :func:`fit_creep` (0.01-3.8 s, 12 per decade), how long after
#: a release its samples show the pad creeping back (the creep recovery the fit reads), and
#: the span over which the unloaded zero may wander on its own (one offset per span).
CREEP_TIME_CONSTANTS_S = tuple(0.01 * 10.0 ** (k / 12) for k in range(32))
CREEP_TAIL_S = 0.15
CREEP_ZERO_SPAN_S = 10.0
#: Initialisations tried per net, the one with the lowest validation loss kept
#: (:func:`_fit_best_of`). The force net lands 0.38-0.42 N from one initialisation to the next
#: on the calibration scene and its validation loss ranks the draws as the test presses do;
#: the location net's draws differ by less than its validation presses can rank (the lowest
#: validation loss had a worse test y), and the contact net's errors are light touches in the
#: noise (docs/trainer.md, "Restarts and force weight decay").
DEFAULT_RESTARTS: dict[str, int] = {"contact": 1, "force": 3, "location": 1}


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


@dataclass
class Prepared:
    """All recordings with a fitted preprocessing, ready to index by split."""

    recordings: list[Recording]
    pre: artifact.Preprocess
    temp_info: dict[str, Any]
    creep_fit: "Creep | None" = None    # the pad's creep the model corrects for (prepare())
    creep_held: "Creep | None" = None   # ... at a time constant the model can hold (_held_creep)
    creep_found: "Creep | None" = None  # what the fit found, established or not
    creep_evidence: dict[str, Any] | None = None   # creep_evidence() on it, and the choice
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


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


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


def prepare(datasets: Sequence[Any], *, seed: int = 0, filter: str = "causal",
            sigma: float | None = None, window: int | None = None,
            sources: Sequence[str] | None = None, ref_shift: int | None = None,
            creep_inverse: bool | None = False, memory: artifact.Memory | None = None,
            creep: str = "auto") -> Prepared:
    """Tare, fit temperature coefficients, choose the temperature reference's average
    (:func:`~fbgforce.trainer.preprocess.choose_ref_shift`), fit the pad's creep
    (:func:`fit_creep`; with ``creep_inverse`` its inverse runs before the filter), filter
    every recording, split each by press.

    ``creep`` (:data:`CREEP_MODES`): ``auto`` corrects for the fitted creep only where the
    calibration establishes it (:func:`creep_evidence`), ``on`` wherever the fit finds one,
    ``off`` never.

    ``creep_inverse`` None lets the creep choose (:func:`takes_creep_out`): the inverse when the
    pad creeps more slowly than the longest average of ``memory``, the nets' memory states.

    ``sigma`` is in samples; ``None`` means :data:`~fbgforce.trainer.preprocess.DEFAULT_SIGMA_MS`
    at the recordings' (median) sample rate, i.e. 5 samples at 1 kHz. ``ref_shift``: None
    lets the data choose the reference's average, a number sets it.
    """
    if not datasets:
        raise InputError("no training data given", column="--data")
    recs = []
    for i, ds in enumerate(datasets):
        src = sources[i] if sources else getattr(ds, "source", f"recording {i}")
        base, info = fbgtare.tare(ds.wl_nm, ds.contact, ds.t_s, path=src)
        shift = (np.asarray(ds.wl_nm, float) - base) * 1000.0
        recs.append(Recording(ds, src, base, info, fbgtare.sample_rate_hz(ds.t_s), shift))
    rate = float(np.median([r.rate_hz for r in recs]))
    masks = [fbgtare.contact_free_mask(r.ds.contact, r.ds.t_s) for r in recs]
    coeff, temp_info = pp.fit_temp_coeff([r.shift_pm for r in recs], masks, rate_hz=rate)
    if sigma is None:
        sigma = pp.default_sigma(rate)
    pre = pp.make_preprocess(filter, sigma, coeff, window)
    ref_shift, temp_info["reference"] = pp.choose_ref_shift(
        pre, [(r.ds.wl_nm, r.baseline_nm, mask) for r, mask in zip(recs, masks)], rate,
        given=ref_shift)
    pre = replace(pre, ref_shift=ref_shift)
    for r in recs:
        r.feats = pp.recording_features(pre, r.ds.wl_nm, r.baseline_nm)
        r.split = split_rows(r.ds, seed)
    data = Prepared(recs, pre, temp_info)
    # The pad's creep, fitted on the training presses' releases (on shifts compensated row by
    # row, which the creep inverse never touches). Taken out before the filter
    # (creep_inverse), the nets read a pad that recovers at once whatever the rests and holds
    # in use; otherwise the at-rest tracker discounts its recovery (_in_use).
    found, evidence = creep_choice(data, pre, data.rows("train"), creep, seed)
    fitted = found if evidence["applied"] else Creep()
    held = _held_creep(data, pre, fitted)
    if creep_inverse is None:
        creep_inverse = takes_creep_out(
            held, memory_time_constant_s(memory, rate) if memory is not None else 0.0)
    if held.magnitude > 0 and creep_inverse:
        pre = replace(pre, creep=held.magnitude,
                      creep_shift=artifact.creep_parameters(held.magnitude, held.time_constant_s * rate)[1])
        for r in recs:
            r.feats = pp.recording_features(pre, r.ds.wl_nm, r.baseline_nm)
        data = Prepared(recs, pre, temp_info)
    data.creep_fit, data.creep_held = fitted, held
    data.creep_found, data.creep_evidence = found, evidence
    return data


#: What ``creep`` (``fbgforce train --creep``) may say: correct for the fitted creep where the
#: calibration establishes it, wherever the fit finds one, or never.
CREEP_MODES = ("auto", "on", "off")


def creep_choice(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, mode: str,
                 seed: int = 0) -> tuple[Creep, dict[str, Any]]:
    """The creep :func:`fit_creep` finds on the releases among ``rows``, and
    :func:`creep_evidence` on it with whether the model corrects for it in ``mode``
    (:data:`CREEP_MODES`): ``applied`` (bool) and ``mode`` beside the evidence's keys; ``why``
    says why it is applied or not."""
    if mode not in CREEP_MODES:
        raise InputError(f"must be one of {', '.join(CREEP_MODES)}, not {mode!r}",
                         column="--creep")
    tails = CreepTails.of(data, pre, rows)
    found = creep_of(tails)
    if mode == "off":
        return found, {"applied": False, "mode": mode, "established": None, "tests": {},
                       "why": "--creep off"}
    evidence = creep_evidence(tails, found, seed,
                              lambda: creep_press_check(data, pre, rows, found))
    applied = found.magnitude > 0 and (mode == "on" or evidence["established"])
    why = evidence["why"] if mode == "auto" or not found.magnitude else (
        f"--creep on (established: {evidence['established']}; {evidence['why']})")
    return found, {**evidence, "applied": applied, "mode": mode, "why": why}


#: The smallest creep magnitude the trainer takes out before the filter by itself
#: (:func:`takes_creep_out`): the fit finds up to 0.5 % on a pad without creep (the synthetic
#: device of tests/conftest.py: 0.5 % with a 4 s time constant), the pads that creep 5 %.
CREEP_INVERSE_MIN = 0.02


def takes_creep_out(creep: Creep, memory_s: float) -> bool:
    """Whether a model whose memory's longest average has the time constant ``memory_s``
    (seconds, 0 without averages) should take the pad's ``creep`` out before the filter.

    A creep faster than the memory's averages is one the nets see whole in their inputs: they
    learn it from the calibration's presses, and the inverse only adds its fit's error. A
    slower one outlasts every average: the nets read the part a press leaves behind as load,
    after a long hold as a light press (the flicker after each release of docs/trainer.md
    "The pad's creep in use"), and only the inverse takes it out. A model without averages
    keeps the at-rest tracker's creep term, and so does a creep below
    :data:`CREEP_INVERSE_MIN`.
    """
    return (creep.magnitude >= CREEP_INVERSE_MIN and memory_s > 0
            and creep.time_constant_s > memory_s)


def memory_time_constant_s(memory: artifact.Memory, rate_hz: float) -> float:
    """The longest time constant of ``memory``'s averages, seconds (0 without averages)."""
    return 2.0 ** max(memory.ema_shifts) / rate_hz if memory.ema_shifts else 0.0


def _held_creep(data: Prepared, pre: artifact.Preprocess, fitted: Creep) -> Creep:
    """``fitted`` at a time constant the model can hold (2^k samples, the nearest:
    :func:`fbgforce.model.artifact.creep_parameters`), its magnitude fitted again for it: a shorter
    time constant needs more magnitude to give back what the pad gives back after a release.
    """
    m, k = artifact.creep_parameters(fitted.magnitude, fitted.time_constant_s * data.rate_hz)
    if m <= 0:
        return Creep()
    tau = 2.0 ** k / data.rate_hz
    m, _ = artifact.creep_parameters(fit_creep(data, pre, data.rows("train"), (tau,)).magnitude, 2.0 ** k)
    return Creep(m, tau) if m > 0 else Creep()


def _sizes(sizes: Mapping[str, Sequence[int]] | None, memory: artifact.Memory) -> dict[str, list[int]]:
    hidden = {k: list(v) for k, v in DEFAULT_SIZES.items()}
    for k, v in (sizes or {}).items():     # checked by TrainParams (_valid_sizes)
        hidden[k] = [int(s) for s in v]
    return {net.name: [contract.net_inputs(net.name, memory.n_states, memory.n_loc), *hidden[net.name],
                       net.float_outputs] for net in contract.NETS}


def parse_memory(text: str) -> artifact.Memory:
    """``none``, a preset name of :data:`MEMORY_PRESETS`, or ``<kind>:V,V,...`` for a kind of
    ``contract.MEMORY_KINDS`` (``ema:S,S``: average shifts; ``play:W,W``: play half-widths in
    standardised units) and ``loc:S`` joined by ``+`` (the location averages' shift)."""
    text = text.strip()
    if text in MEMORY_PRESETS:
        return MEMORY_PRESETS[text]
    states: dict[str, list[float]] = {k.name: [] for k in contract.MEMORY_KINDS}
    loc = 0
    try:
        for part in text.split("+"):
            kind, _, values = part.partition(":")
            nums = [v for v in values.split(",") if v.strip()]
            if kind.strip() in contract.MEMORY_KIND:
                spec = contract.MEMORY_KIND[kind.strip()]
                states[spec.name] += [(float if spec.counted_by.standardised else int)(v) for v in nums]
            elif kind.strip() == "loc":
                if len(nums) != 1 or loc:
                    raise ValueError("loc takes one shift")
                loc = int(nums[0])
                if loc < 1:
                    raise ValueError("the loc shift must be at least 1 (leave loc out for none)")
            else:
                raise ValueError(f"unknown memory kind {kind!r}")
        return artifact.Memory(**{artifact.memory_attr(k, k.counted_by): tuple(states[k.name])
                            for k in contract.MEMORY_KINDS}, loc_shift=loc)
    except ValueError as exc:
        raise InputError(f"bad memory {text!r}: {exc}; use none, "
                         f"{', '.join(MEMORY_PRESETS)}, or e.g. ema:3,6+play:0.1+loc:5",
                         column="--memory") from exc


#: Named memories (docs/trainer.md, "memory"): averages of about 16 and 128 ms at 1 kHz;
#: play operators of half-width 0.05 and 0.25 standard deviations of the load signal (about
#: 1 % and 5 % of the force range of a calibration run). Even counts keep the first layers'
#: widths even, which the Cortex-M4 kernels take in pairs. The default, ``both``, also gives
#: the location net the location averages of about 32 ms (``loc:5``; shifts 4 and 6 were
#: worse on the calibration scene, docs/trainer.md).
MEMORY_PRESETS: dict[str, artifact.Memory] = {
    "none": artifact.Memory(),
    "ema": artifact.Memory(ema_shifts=(4, 7)),
    "play": artifact.Memory(play_widths=(0.05, 0.25)),
    "loc": artifact.Memory(loc_shift=5),
    "both": artifact.Memory(ema_shifts=(4, 7), play_widths=(0.05, 0.25), loc_shift=5),
}
DEFAULT_MEMORY = "both"


def fit_memory(memory: artifact.Memory, pre: artifact.Preprocess, data: "Prepared", rows: np.ndarray
               ) -> artifact.Memory:
    """The memory's load signal and gains, fitted on the training ``rows``.

    Weights: least squares of the load-cell force (0 at rest) on the standardised channels,
    scaled so that ``u`` has unit spread: u tracks the load, and the play widths are fractions
    of its spread. Gains: the power of two that brings each feature's spread near 0.5, like
    the standardised inputs' (small recent changes would otherwise reach the nets as nearly
    constant inputs)."""
    if memory.n_states == 0:
        return memory
    loc_shift = memory.loc_shift
    memory = replace(memory, loc_shift=0)
    plain = copy.deepcopy(pre)
    plain.memory = artifact.Memory()
    z = data.inputs(plain)[rows]
    force = np.where(data.contact[rows], np.nan_to_num(data.force_N[rows]), 0.0)
    w, *_ = np.linalg.lstsq(np.column_stack([z, np.ones(len(z))]), force, rcond=None)
    u = z @ w[:artifact.N_STRAIN]
    weights = w[:artifact.N_STRAIN] / max(float(np.std(u)), 1e-12)
    gain_of = {k.name: artifact.memory_attr(k, k.gain) for k in contract.MEMORY_KINDS}
    trial = replace(memory, weights=tuple(weights), **{a: () for a in gain_of.values()})
    pre_trial = copy.deepcopy(pre)
    pre_trial.memory = trial
    x = data.inputs(pre_trial)[rows]
    gains = []
    for k in range(trial.n_states):
        sd = float(np.std(x[:, artifact.N_STRAIN + k]))
        g = int(np.floor(np.log2(0.5 / sd))) if sd > 0 else 0
        gains.append(int(np.clip(g, 0, contract.LIMIT["MAX_MEM_GAIN"])))
    fitted, start = {}, 0
    for kind in contract.MEMORY_KINDS:     # the features' order: every kind's in turn
        fitted[gain_of[kind.name]] = tuple(gains[start:start + trial.count(kind)])
        start += trial.count(kind)
    return replace(trial, loc_shift=loc_shift, **fitted)


#: A hold: the load standing still under contact for at least this long (within
#: :data:`HOLD_BAND`). Models whose memory has averages need some in their calibration data.
HOLD_MIN_S = 0.2
#: How still a hold is: its load stays within max(0.2 N, 3 % of the load).
HOLD_BAND = (0.2, 0.03)


def _rest_margins(data: Prepared, logits: np.ndarray) -> np.ndarray:
    """The contact net's margins on the samples of the training and validation presses that
    are at rest (at least ``fbgforce.evaluation.metrics.REST_GAP_S`` from any labelled contact, past the filter's
    warm-up): what noise and drift alone make of it, for the decision's thresholds."""
    keep = data.row_mask(np.flatnonzero(data.split != 2))
    margin = logits[:, 1] - logits[:, 0]
    out = []
    warm = data.pre.taps.size
    for r, sl in data.recording_slices():
        rest = fmetrics.use_masks(data.contact[sl], data.contact[sl], data.force_N[sl],
                                 np.asarray(r.ds.t_s))["rest"]
        rest[:warm] = False
        out.append(margin[sl][rest & keep[sl]])
    return np.concatenate(out) if out else np.empty(0)


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

    An average of the load reads a held load as it reads the instant a press turns round; a
    net that never saw a hold takes one for a release (docs/teleop.md measures a grip read
    1.7 N low), which the trainer's synthetic holds (:func:`_synthetic_holds`) teach it.
    """
    keep = data.row_mask(rows) & data.contact
    total = 0.0
    for r, sl in data.recording_slices():
        total += float(hold_mask(data.force_N[sl], keep[sl], r.rate_hz).sum()) / r.rate_hz
    return total


def _per_net(value: Any, defaults: Mapping[str, Any], what: str, kind: Callable[[Any], Any]
             ) -> dict[str, Any]:
    """A per-net setting: the defaults, one value for all, or per-net overrides."""
    if value is None:
        return dict(defaults)
    if isinstance(value, Mapping):
        unknown = set(value) - set(defaults)
        if unknown:
            raise InputError(f"unknown net {sorted(unknown)[0]!r} in {what}; nets are "
                             f"{', '.join(defaults)}")
        return {**defaults, **{k: kind(v) for k, v in value.items()}}
    return {k: kind(value) for k in defaults}


def _weight_decays(weight_decay: float | Mapping[str, float] | None) -> dict[str, float | None]:
    """L2 weight decay per net as given (one value for all, or per-net overrides); None
    where the net takes the default (:func:`default_weight_decay`)."""
    return _per_net(weight_decay, {k: None for k in DEFAULT_DECAY_SAMPLES}, "weight_decay", float)


def default_weight_decay(name: str, n_samples: int) -> float:
    """The default L2 weight decay of net ``name`` trained on ``n_samples`` samples:
    :data:`DEFAULT_DECAY_SAMPLES` over ``n_samples``."""
    return DEFAULT_DECAY_SAMPLES[name] / max(int(n_samples), 1)


def _fit_best_of(tries: int, name: str, seed: int, sizes: Sequence[int],
                 rng_init: np.random.Generator, rng_fit: np.random.Generator,
                 init: Any, *args: Any, **kwargs: Any) -> tuple[FlatMLP, dict[str, Any]]:
    """Train ``tries`` initialisations of one net and keep the lowest validation loss.

    The first draw uses the caller's generators, so ``tries == 1`` is a plain :func:`fit`;
    the others get their own streams from ``(seed, the net's index in NET_NAMES, draw)``, so
    adding draws leaves the first one and every other net unchanged. The report is the kept
    draw's, with ``restarts``: every draw's best validation loss and the index of the kept one.
    """
    if tries < 1:
        raise InputError(f"restarts for the {name} net must be at least 1, not {tries}")
    best: tuple[FlatMLP, dict[str, Any]] | None = None
    losses, kept = [], 0
    desc = kwargs.pop("desc", f"{name} net")
    for i in range(tries):
        if i == 0:
            r_init, r_fit = rng_init, rng_fit
        else:
            r_init, r_fit = (np.random.default_rng(s) for s in
                             np.random.SeedSequence([seed, artifact.NET_NAMES.index(name), i]).spawn(2))
        net = FlatMLP(sizes, r_init, init=init)
        rep = fit(net, *args, desc=desc if tries == 1 else f"{desc} {i + 1}/{tries}",
                  rng=r_fit, **kwargs)
        losses.append(rep["best_val_loss"])
        if best is None or rep["best_val_loss"] < best[1]["best_val_loss"]:
            best, kept = (net, rep), i
    assert best is not None
    best[1]["restarts"] = {"val_losses": losses, "kept": kept}
    return best


def _loc_inputs(x: np.ndarray, contact: np.ndarray, f_raw: np.ndarray, n_loc: int) -> np.ndarray:
    """Location-net input exactly as :func:`fbgforce.model.floatref.predict_from_features` builds it."""
    return floatref.location_inputs(x, contact, f_raw, n_loc)


def pad_extent_mm(x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[float, float]:
    """Pad size (x, y) for the boundary metrics: the nominal 21 x 27 mm design, or larger where
    the calibration data touched locations beyond it (another gripper's pad)."""
    from fbgforce.geometry import PAD_SIZE_MM

    xmax = float(np.nanmax(x_mm)) if np.isfinite(x_mm).any() else 0.0
    ymax = float(np.nanmax(y_mm)) if np.isfinite(y_mm).any() else 0.0
    return max(float(PAD_SIZE_MM[0]), xmax), max(float(PAD_SIZE_MM[1]), ymax)


def model_pad_mm(model: artifact.HierarchicalModel) -> tuple[float, float] | None:
    """The pad size a model was calibrated on (metadata ``pad_mm``), None for older models."""
    pad = model.metadata.get("pad_mm") if model.metadata else None
    return (float(pad[0]), float(pad[1])) if pad else None


def predict_prepared(model: artifact.HierarchicalModel, data: Prepared,
                     inputs: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The float pipeline's outputs on every row of ``data``, each recording run whole on its
    own tare as ``fbgforce evaluate`` runs it: through the decision over time and the at-rest
    tracker when the model has them (:func:`fbgforce.model.floatref.predict`), else on the prepared
    net inputs (``inputs``, if the caller has them: the memory states make them a pass over
    every recording)."""
    if model.runs_in_use:
        parts = [floatref.predict(model, r.ds.wl_nm, r.baseline_nm) for r in data.recordings]
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return floatref.predict_from_features(model, data.inputs(model.preprocess) if inputs is None
                                    else inputs)


def evaluate_rows(model: artifact.HierarchicalModel, data: Prepared, rows: np.ndarray,
                  extras: bool = True, inputs: np.ndarray | None = None) -> dict[str, Any]:
    """Float-pipeline metrics on given rows of prepared data (:func:`predict_prepared`)."""
    pred = predict_prepared(model, data, inputs)
    if not extras:
        return fmetrics.compute({k: v[rows] for k, v in pred.items()}, *data.truth(rows),
                                extras=False)
    delays = press_delays(data, pred["contact"], rows)
    return fmetrics.compute({k: v[rows] for k, v in pred.items()}, *data.truth(rows),
                            extras=extras, pad_mm=model_pad_mm(model), delays=delays)


def press_delays(data: Prepared, pred_contact: np.ndarray, rows: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Onset and release delays (ms) of the presses whose onset lies in ``rows``, from a
    contact prediction over ALL rows of ``data`` (each recording scored as one time series)."""
    keep = data.row_mask(rows)
    onsets, releases = [], []
    for r, sl in data.recording_slices():
        o, rel = fmetrics.press_delays(pred_contact[sl], data.contact[sl], r.ds.t_s,
                                       r.ds.press_id, keep[sl])
        onsets.append(o)
        releases.append(rel)
    return np.concatenate(onsets), np.concatenate(releases)


_TRAIN_FLAGS = {"epochs": "--epochs", "seed": "--seed", "filter": "--filter", "sigma": "--sigma",
                "window": "--window", "init": "--init", "train_fraction": "--train-fraction",
                "memory": "--memory", "restarts": "--restarts", "hold_augment": "--hold-augment",
                "rest_augment": "--rest-augment", "ref_shift": "--ref-shift",
                "creep_inverse": "--creep-inverse", "creep": "--creep", "decision": "--decision",
                "turn_guard_s": "--turn-guard", "sizes": "--sizes"}


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) \
        and not isinstance(value, (bool, np.bool_)) and bool(np.isfinite(value))


def _valid_sizes(sizes: Any) -> bool:
    """Hidden widths the runtime can hold: known nets, each 1 .. MAX_LAYERS - 1 hidden layers
    (the output layer is one more) of 1 .. MAX_WIDTH units (an odd width is padded to the next
    even one on export, which stays within the even MAX_WIDTH)."""
    if not isinstance(sizes, Mapping) or not set(sizes) <= set(DEFAULT_SIZES):
        return False
    for widths in sizes.values():
        if not isinstance(widths, Sequence) or isinstance(widths, str):
            return False
        if not 1 <= len(widths) <= contract.LIMIT["MAX_LAYERS"] - 1:
            return False
        if not all(_is_int(w) and 1 <= w <= contract.LIMIT["MAX_WIDTH"] for w in widths):
            return False
    return True


@dataclass
class TrainParams:
    """What :func:`train` is asked to do, checked when made: a value out of its range is an
    :class:`~fbgforce.errors.InputError` naming the ``fbgforce train`` option (or the
    parameter, for those the command does not offer) and the allowed range.

    Attributes
    ----------
    epochs, seed, learning_rate, decay, patience, batch_size
        Training loop (see :func:`fbgforce.trainer.nets.fit`); ``seed`` fixes the split, the
        initial weights and the shuffling, so a run is reproducible.
    filter, sigma, window
        Smoothing: ``causal`` (shipped), ``centred`` (offline, the paper's) or ``none``;
        sigma in samples, default 5 ms at the data's sample rate (5 samples at 1 kHz).
    ref_shift
        The temperature reference's average (:attr:`fbgforce.model.artifact.Preprocess.ref_shift`):
        None lets the data choose (:func:`~fbgforce.trainer.preprocess.choose_ref_shift`),
        0 keeps the raw reference, 1 .. 8 averages over 2^ref_shift samples.
    creep_inverse
        Take the pad's fitted creep out before the filter (:func:`fbgforce.model.floatref.creep_inverse`)
        instead of letting the at-rest tracker discount its recovery (docs/trainer.md, "The
        pad's creep in use", measures what each costs); None (default): the inverse when the
        fitted creep is slower than the memory's longest average (:func:`takes_creep_out`).
    decision
        The contact decision's rule (:data:`DECISION_RULES`): ``cusum`` (default: quicker
        and quieter than the Schmitt trigger on the worst member of the family of fingertips,
        docs/robustness.md) or ``schmitt``; the fields the other would set are kept in
        ``metadata.decision_rules``.
    creep
        ``auto`` (default): correct for the fitted creep (the synthetic holds' creep, the
        inverse or the tracker's term) only where the calibration establishes it
        (:func:`creep_evidence`); ``on``: wherever the fit finds one; ``off``: never.
    init
        A model (or model directory) of another device to start from (paper §VII-C). Its input
        standardisation and output scaling are kept so its weights keep their meaning; tare and
        temperature coefficients are fitted on the new data.
    sizes
        Hidden widths per net, e.g. ``{"location": (70, 50, 40)}``; defaults :data:`DEFAULT_SIZES`.
        What a smaller net saves on the Cortex-M4 and costs in accuracy: docs/trainer.md,
        "Widths and the Cortex-M4".
    progress
        Progress bars on stderr (None: when stderr is a terminal).
    train_fraction
        Use only this fraction of the training presses (transfer study: "how much less data").
    time_budget_s
        Per-net wall-time cap (keeps the best weights so far).
    plateau, plateau_factor
        Reduce the learning rate on a validation plateau (see :func:`~fbgforce.trainer.nets.fit`;
        off by default).
    weight_decay
        L2 weight decay: one value for every net or per net (``{"force": 1e-2}``); a net
        given none takes :func:`default_weight_decay` (it falls with the number of samples the
        net trains on). The model records each net's in ``metadata.training.NET.weight_decay``.
    location_augment
        The location net also trains on the training presses pressed up to this many times
        harder (:func:`_scaled_presses`); 1 turns it off.
    hold_augment
        The contact and force nets also train on this share of the training (and validation)
        presses held at their peak for 1.5-6 s (:func:`_synthetic_holds`); 0 turns it off.
        Only a model with memory states uses it (a memoryless net reads a hold as its peak).
    rest_augment
        The contact and force nets also train on rests of 3-60 s inserted before this share of
        the training (and validation) presses (:func:`_synthetic_rests`); 0 turns it off.
    turn_guard_s
        The force net leaves out the samples within this many seconds after each press's turn
        (:func:`after_turns`): a held grip then reads less low, the first milliseconds of each
        unloading worse (docs/trainer.md, "The turn"); 0 keeps them; None (default):
        :data:`TURN_GUARD_S` with the creep inverse, else 0.
    memory
        The memory states (:class:`fbgforce.model.artifact.Memory`, or text for :func:`parse_memory`);
        ``None``: the ``init`` model's, else :data:`DEFAULT_MEMORY`. Gains are fitted.
    restarts
        Initialisations tried per net (one value for every net or per net, ``None``:
        :data:`DEFAULT_RESTARTS`); the net with the lowest validation loss is kept. The first
        draw is the one a single initialisation would make. Without validation presses, or
        with ``init`` (every draw would start from the same weights), one is trained.
    """

    epochs: int = 200
    seed: int = 0
    filter: str = "causal"
    sigma: float | None = None
    window: int | None = None
    ref_shift: int | None = None
    creep_inverse: bool | None = None
    creep: str = "auto"
    decision: str = "cusum"
    init: str | Path | artifact.HierarchicalModel | None = None
    sizes: Mapping[str, Sequence[int]] | None = None
    learning_rate: float = 1e-3
    decay: float = 0.97
    patience: int = 10
    batch_size: int = 128
    progress: bool | None = None
    train_fraction: float = 1.0
    time_budget_s: float | None = None
    plateau: int | None = None
    plateau_factor: float = 0.3
    weight_decay: float | Mapping[str, float] | None = None
    location_augment: float = LOCATION_AUGMENT
    hold_augment: float = HOLD_AUGMENT
    rest_augment: float = REST_AUGMENT
    turn_guard_s: float | None = None
    memory: artifact.Memory | str | None = None
    restarts: int | Mapping[str, int] | None = None

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, allowed: str) -> None:
            if not ok:
                raise InputError(f"must be {allowed}, not {getattr(self, name)!r}",
                                 column=_TRAIN_FLAGS.get(name, name))

        need(_is_int(self.epochs) and self.epochs >= 1, "epochs", "a whole number >= 1")
        need(_is_int(self.seed), "seed", "a whole number")
        need(self.filter in artifact.FILTER_KINDS, "filter", "one of " + ", ".join(artifact.FILTER_KINDS))
        need(self.sigma is None or (_is_real(self.sigma) and self.sigma >= 0), "sigma",
             "a number >= 0 (samples)")
        need(self.window is None or (_is_int(self.window) and self.window >= 1), "window",
             "a whole number >= 1")
        need(self.ref_shift is None or (_is_int(self.ref_shift)
                                        and 0 <= self.ref_shift <= contract.LIMIT["MAX_REF_SHIFT"]),
             "ref_shift", f"None or 0 .. {contract.LIMIT['MAX_REF_SHIFT']}")
        need(_is_real(self.learning_rate) and self.learning_rate > 0, "learning_rate", "> 0")
        need(_is_real(self.decay) and 0 < self.decay <= 1, "decay", "in (0, 1]")
        need(_is_int(self.patience) and self.patience >= 1, "patience", "a whole number >= 1")
        need(_is_int(self.batch_size) and self.batch_size >= 1, "batch_size", "a whole number >= 1")
        need(_is_real(self.train_fraction) and 0 < self.train_fraction <= 1, "train_fraction",
             "in (0, 1]")
        need(self.time_budget_s is None or (_is_real(self.time_budget_s) and self.time_budget_s > 0),
             "time_budget_s", "None or > 0 (seconds)")
        need(self.plateau is None or (_is_int(self.plateau) and self.plateau >= 1), "plateau",
             "None or a whole number >= 1")
        need(_is_real(self.plateau_factor) and 0 < self.plateau_factor < 1, "plateau_factor",
             "in (0, 1)")
        need(_is_real(self.location_augment) and self.location_augment >= 1, "location_augment",
             ">= 1 (1: off)")
        for share in ("hold_augment", "rest_augment"):
            need(_is_real(getattr(self, share)) and 0 <= getattr(self, share) <= 1, share,
                 "in [0, 1]")
        need(self.turn_guard_s is None or (_is_real(self.turn_guard_s) and 0 <= self.turn_guard_s <= 1),
             "turn_guard_s", "None or in [0, 1] s (--turn-guard takes milliseconds: 0 .. 1000)")
        need(self.creep_inverse in (None, True, False), "creep_inverse", "None, True or False")
        need(self.creep in CREEP_MODES, "creep", "one of " + ", ".join(CREEP_MODES))
        need(self.decision in DECISION_RULES, "decision", "one of " + ", ".join(DECISION_RULES))
        need(self.sizes is None or _valid_sizes(self.sizes), "sizes",
             f"hidden widths per net ({', '.join(DEFAULT_SIZES)}): 1 .. "
             f"{contract.LIMIT['MAX_LAYERS'] - 1} layers of 1 .. {contract.LIMIT['MAX_WIDTH']} "
             f"units (the runtime's limits)")

    def fit_settings(self) -> dict[str, Any]:
        """The keyword arguments of :func:`fbgforce.trainer.nets.fit` every net shares."""
        return dict(epochs=self.epochs, batch_size=self.batch_size,
                    learning_rate=self.learning_rate, decay=self.decay, patience=self.patience,
                    progress=self.progress, time_budget_s=self.time_budget_s,
                    plateau=self.plateau, plateau_factor=self.plateau_factor)


def _starting_point(params: TrainParams) -> tuple[artifact.HierarchicalModel | None, artifact.Memory,
                                                  dict[str, list[int]]]:
    """The ``init`` model (None without one), the memory states and every net's sizes."""
    init_model = modeldir.load(params.init) if isinstance(params.init, (str, Path)) else params.init
    memory = params.memory
    if memory is None:
        memory = init_model.preprocess.memory if init_model else DEFAULT_MEMORY
    if isinstance(memory, str):
        memory = parse_memory(memory)
    net_sizes = _sizes(params.sizes, memory)
    if init_model is not None:
        for name, net in init_model.nets.items():
            if params.sizes is None:
                net_sizes[name] = net.sizes
            elif net.sizes != net_sizes[name]:
                raise InputError(f"--init model's {name} net has sizes {net.sizes}, not "
                                 f"{net_sizes[name]}", column="--init")
    return init_model, memory, net_sizes


@dataclass
class _Streams:
    """The random streams of one training run, one per use, all from ``seed``."""

    init: np.random.Generator
    contact: np.random.Generator
    force: np.random.Generator
    location: np.random.Generator
    subsample: np.random.Generator
    location_augment: np.random.Generator
    holds: np.random.Generator
    rests: np.random.Generator
    hold_gain: np.random.Generator

    @classmethod
    def from_seed(cls, seed: int) -> "_Streams":
        # spawn(n)'s first children do not depend on n: a stream added last leaves the others.
        return cls(*(np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(9)))


def _split(data: Prepared, params: TrainParams, rng: np.random.Generator
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training, validation and test rows (the training presses cut to ``train_fraction``)."""
    tr, va, te = data.rows("train"), data.rows("val"), data.rows("test")
    if params.train_fraction < 1.0:
        tr = _subsample_presses(data, tr, params.train_fraction, rng)
    if tr.size == 0 or not data.contact[tr].any() or data.contact[tr].all():
        raise InputError("training split needs both contact and contact-free samples; "
                         "give more presses or check the contact column", column="contact")
    return tr, va, te


@dataclass
class _Scaling:
    """Input standardisation and output scaling (``force_N = offset + scale * f``, x/y alike)."""

    std: pp.Standardisation
    force_offset: float
    force_scale: float
    xy_offset: np.ndarray
    xy_scale: np.ndarray


def _scaling(data: Prepared, tr: np.ndarray, init_model: artifact.HierarchicalModel | None) -> _Scaling:
    """The ``init`` model's scaling (its weights keep their meaning), else fitted on the
    training rows' contact samples."""
    if init_model is not None:
        return _Scaling(pp.Standardisation(init_model.preprocess.input_mean,
                                           init_model.preprocess.input_std),
                        init_model.force_offset, init_model.force_scale,
                        init_model.xy_offset, init_model.xy_scale)
    ctr = tr[data.contact[tr]]
    xy = np.column_stack([data.x_mm[ctr], data.y_mm[ctr]])
    return _Scaling(pp.Standardisation.fit(data.feats[tr]), float(np.mean(data.force_N[ctr])),
                    float(max(np.std(data.force_N[ctr]), 1e-6)), np.nanmean(xy, axis=0),
                    np.maximum(np.nanstd(xy, axis=0), 1e-6))


def _model_preprocess(data: Prepared, scaling: _Scaling, init_model: artifact.HierarchicalModel | None,
                      memory: artifact.Memory, tr: np.ndarray) -> artifact.Preprocess:
    """The model's preprocessing: the prepared filter with this model's standardisation and
    memory (the ``init`` model's, else fitted on the training rows)."""
    pre = copy.deepcopy(data.pre)  # a shared Prepared must not see this model's scaling
    pre.input_mean, pre.input_std = scaling.std.mean, scaling.std.std
    pre.memory = init_model.preprocess.memory if init_model is not None \
        else fit_memory(memory, pre, data, tr)
    return pre


class _NetFitter:
    """Fits each net as :func:`train` is asked to: the best of its restarts, its weight decay,
    the shared loop settings; keeps each net's report in :attr:`reports`."""

    def __init__(self, params: TrainParams, net_sizes: Mapping[str, Sequence[int]],
                 init_model: artifact.HierarchicalModel | None, rng_init: np.random.Generator,
                 has_validation: bool) -> None:
        self.params, self.net_sizes, self.init_model, self.rng_init = (params, net_sizes,
                                                                       init_model, rng_init)
        self.decays = _weight_decays(params.weight_decay)
        self.tries = _per_net(params.restarts, DEFAULT_RESTARTS, "restarts", int)
        if not has_validation or init_model is not None:
            self.tries = {k: 1 for k in self.tries}
        self.reports: dict[str, Any] = {}

    def __call__(self, name: str, rng_fit: np.random.Generator, loss: str, x: np.ndarray,
                 *args: Any, **kwargs: Any) -> FlatMLP:
        given = self.decays[name]
        wd = default_weight_decay(name, len(x)) if given is None else given
        net, self.reports[name] = _fit_best_of(
            self.tries[name], name, self.params.seed, self.net_sizes[name], self.rng_init, rng_fit,
            self.init_model.nets[name] if self.init_model else None, loss, x, *args,
            weight_decay=wd, **kwargs, **self.params.fit_settings())
        self.reports[name].update(weight_decay=wd, train_samples=int(len(x)))
        return net


Held = tuple[np.ndarray, np.ndarray]


def _holds(data: Prepared, pre: artifact.Preprocess, params: TrainParams, tr: np.ndarray,
           va: np.ndarray, creep: Creep, rng: np.random.Generator) -> tuple[Held, Held]:
    """Synthetic holds for the nets that read the load's memory, of the training and the
    validation presses alike (so early stopping and the choice among restarts weigh them
    too), the pad creeping through them as ``creep`` says: ``(inputs, rows)`` of each."""
    no_holds = (np.empty((0, pre.n_inputs)), tr[:0])
    on = params.hold_augment > 0 and pre.memory.n_states
    hold_tr, hold_va = (_synthetic_holds(data, pre, rows, params.hold_augment, creep, rng)
                        if on else no_holds for rows in (tr, va))
    return hold_tr, hold_va


def _rests(data: Prepared, pre: artifact.Preprocess, params: TrainParams, tr: np.ndarray,
           va: np.ndarray, rng: np.random.Generator) -> tuple[Held, Held]:
    """Synthetic long rests of the training and the validation presses: ``(inputs, rows)``
    of each."""
    if params.rest_augment <= 0:
        return (np.empty((0, pre.n_inputs)), tr[:0]), (np.empty((0, pre.n_inputs)), va[:0])
    step = max(1, int(round(REST_AUGMENT_STEP_S * data.rate_hz)))
    rest_tr, rest_va = (_synthetic_rests(data, pre, rows, params.rest_augment, step, rng)
                        for rows in (tr, va))
    return rest_tr, rest_va


def _fit_contact(fit_net: _NetFitter, data: Prepared, z: np.ndarray, tr: np.ndarray,
                 va: np.ndarray, synth_tr: Held, synth_va: Held, rng: np.random.Generator
                 ) -> tuple[FlatMLP, np.ndarray]:
    """The contact net on every sample and the synthetic ones (softmax cross-entropy);
    returns it and its logits on every row."""
    nf = z.shape[1]
    labels = data.contact.astype(np.int64)
    zc_tr = np.concatenate([z[tr], synth_tr[0][:, :nf]])
    zc_va = np.concatenate([z[va], synth_va[0][:, :nf]])
    yc_tr = labels[np.concatenate([tr, synth_tr[1]])]
    yc_va = labels[np.concatenate([va, synth_va[1]])]

    def contact_val(net: FlatMLP) -> dict[str, float]:
        return {"val_acc": float(np.mean((np.argmax(predict_batched(net, z[va]), 1) == 1)
                                         == data.contact[va])) if va.size else float("nan")}

    cnet = fit_net("contact", rng, "xent", zc_tr, yc_tr, zc_va, yc_va,
                   val_metrics=contact_val, desc="contact net")
    return cnet, predict_batched(cnet, z)


def after_turns(data: Prepared, guard_s: float) -> np.ndarray:
    """Rows (a mask over every row of ``data``) within ``guard_s`` seconds after each press's
    turn, the last of its samples at :data:`TURN_FRACTION` of its peak force or more.

    There the load has begun to fall, but the causal filter still averages the samples before
    the turn, and a pad with friction holds or even raises its strain while the load starts
    down: the inputs are those of a held load, the labels a few percent lower. No causal
    estimator can tell the two apart for that long, and a net fitted to both reads every held
    grip low (docs/trainer.md, "The turn").
    """
    mask = np.zeros(data.split.size, dtype=bool)
    if guard_s <= 0:                      # the default: no press needs grouping
        return mask
    for r, sl in data.recording_slices():
        force = np.nan_to_num(np.asarray(r.ds.force_N, dtype=np.float64))
        loaded = np.flatnonzero(np.asarray(r.ds.contact, dtype=bool))
        if not loaded.size:
            continue
        # The contact rows grouped by press, in time order within each.
        press_id = np.asarray(r.ds.press_id)
        rows = loaded[np.argsort(press_id[loaded], kind="stable")]
        pid = press_id[rows]
        first = np.flatnonzero(np.r_[True, pid[1:] != pid[:-1]])
        sizes = np.diff(np.r_[first, rows.size])
        peak = np.maximum.reduceat(force[rows], first)
        high = np.flatnonzero(force[rows] >= TURN_FRACTION * np.repeat(peak, sizes))
        last = np.full(first.size, -1)
        np.maximum.at(last, np.repeat(np.arange(first.size), sizes)[high], high)
        turns = rows[last[last >= 0]]
        n = len(r.ds)
        for k in range(1, int(round(guard_s * r.rate_hz)) + 1):
            mask[sl.start + turns[turns + k < n] + k] = True
    return mask


def _fit_force(fit_net: _NetFitter, data: Prepared, z: np.ndarray, cnet: FlatMLP,
               pred_contact: np.ndarray, scaling: _Scaling, tr: np.ndarray, va: np.ndarray,
               synth_tr: Held, synth_va: Held, rng: np.random.Generator) -> FlatMLP:
    """The force net on the samples the contact net passes (its output is 0 N elsewhere,
    whatever the net says), with the load-cell force as target: where the contact is real
    this is the force the metric scores; on false contacts (light touches below the label
    threshold, pad creep) it teaches ~0 N, which is what a controller should see. Missed
    contacts are left out: their output is gated to 0 N, so fitting them would only spend
    capacity; so are the samples within ``turn_guard_s`` after each press's turn
    (:func:`after_turns`), when asked: they teach the net to read every hold low."""
    nf = z.shape[1]
    f_off, f_scale = scaling.force_offset, scaling.force_scale
    fit = pred_contact & ~after_turns(data, fit_net.params.turn_guard_s)
    ftr, fva = tr[fit[tr]], va[fit[va]]
    if ftr.size == 0:  # a contact net that never fires: fall back to the true contacts
        ftr, fva = tr[data.contact[tr]], va[data.contact[va]]
    ft = ((data.force_N - f_off) / f_scale)[:, None]

    def with_synthetic(rows: np.ndarray, held: Held) -> tuple[np.ndarray, np.ndarray]:
        """Force-net inputs and targets of ``rows`` and of the synthetic (held, rested)
        samples the contact net passes (the same gate as the recorded samples)."""
        zh = held[0][:, :nf]
        hl = predict_batched(cnet, zh) if len(zh) else np.empty((0, 2))
        passed = hl[:, 1] > hl[:, 0]
        return (np.concatenate([z[rows], zh[passed]]),
                np.concatenate([ft[rows], ft[held[1][passed]]]))

    (zf_tr, yf_tr), (zf_va, yf_va) = with_synthetic(ftr, synth_tr), with_synthetic(fva, synth_va)

    def force_val(net: FlatMLP) -> dict[str, float]:
        e = (predict_batched(net, z[fva])[:, 0] * f_scale + f_off) - data.force_N[fva]
        return {"val_rmse_N": float(np.sqrt(np.mean(e * e))) if e.size else float("nan")}

    return fit_net("force", rng, "mse", zf_tr, yf_tr, zf_va, yf_va,
                   val_metrics=force_val, desc="force net")


def _fit_location(fit_net: _NetFitter, data: Prepared, pre: artifact.Preprocess, x_all: np.ndarray,
                  pred_contact: np.ndarray, fnet: FlatMLP, scaling: _Scaling, params: TrainParams,
                  tr: np.ndarray, va: np.ndarray, streams: _Streams) -> FlatMLP:
    """The location net on the samples where true and predicted contact agree (where a
    location is both defined and output), fed the contact net's decision and the force net's
    OWN estimate, and on the training presses pressed harder (``location_augment``)."""
    n_loc = pre.memory.n_loc
    f_raw = predict_batched(fnet, x_all[:, :pre.n_features])[:, 0]
    loc_x = _loc_inputs(x_all, pred_contact, f_raw, n_loc)
    xy_t = (np.column_stack([data.x_mm, data.y_mm]) - scaling.xy_offset) / scaling.xy_scale
    ltr = tr[data.contact[tr] & pred_contact[tr]]
    lva = va[data.contact[va] & pred_contact[va]]

    def loc_val(net: FlatMLP) -> dict[str, float]:
        e = (predict_batched(net, loc_x[lva]) - xy_t[lva]) * scaling.xy_scale
        if not e.size:
            return {}
        r = np.sqrt(np.mean(e * e, axis=0))
        return {"val_x_mm": float(r[0]), "val_y_mm": float(r[1])}

    loc_train_x, loc_train_y = loc_x[ltr], xy_t[ltr]
    if params.location_augment > 1.0:
        z_aug, rows_aug = _scaled_presses(data, pre, ltr, params.location_augment,
                                          streams.location_augment)
        aug_x = _loc_inputs(z_aug, np.ones(rows_aug.size, bool),
                            predict_batched(fnet, z_aug[:, :pre.n_features])[:, 0], n_loc)
        loc_train_x = np.concatenate([loc_train_x, aug_x])
        loc_train_y = np.concatenate([loc_train_y, xy_t[rows_aug]])
    return fit_net("location", streams.location, "mse", loc_train_x, loc_train_y, loc_x[lva],
                   xy_t[lva], val_metrics=loc_val, desc="location net")


def _training_warnings(data: Prepared, pre: artifact.Preprocess, tr: np.ndarray, te: np.ndarray,
                       hold_tr: Held) -> tuple[list[str], float]:
    """What the data leaves the model short of (few test presses, no holds for the memory's
    averages), and the training presses' held seconds."""
    warnings = []
    few = fmetrics.few_presses_warning("test", count_presses(data, te))
    if few:
        warnings.append(few)
    held_s = hold_seconds(data, tr)
    if pre.memory.ema_shifts and held_s == 0.0 and not hold_tr[1].size:
        warnings.append(
            "the training presses hold no load (no %.1f s in contact within %.1f N or %d %%): "
            "the memory's averages will read a held grip low; calibrate with holds (scene "
            "calibration_holds, docs/teleop.md) or train with synthetic holds (--hold-augment)"
            % (HOLD_MIN_S, HOLD_BAND[0], round(100 * HOLD_BAND[1])))
    return warnings, held_s


def _assemble(data: Prepared, pre: artifact.Preprocess, scaling: _Scaling,
              nets: Mapping[str, FlatMLP], reports: dict[str, Any],
              described: Sequence[Mapping[str, Any]]) -> artifact.HierarchicalModel:
    """The float model of the trained nets, with the calibration recordings export needs."""
    # Units weight decay switched off cost multiply-adds in every engine and change no float32
    # output: leave them out of the model.
    mlps: dict[str, artifact.MLP] = {}
    for name, net in nets.items():
        mlps[name], reports[name]["dropped_units"] = drop_unread_units(net.to_mlp())
    model = artifact.HierarchicalModel(
        preprocess=pre, contact=mlps["contact"], force=mlps["force"], location=mlps["location"],
        force_offset=scaling.force_offset, force_scale=scaling.force_scale,
        xy_offset=scaling.xy_offset, xy_scale=scaling.xy_scale,
        baseline_nm=np.median([r.baseline_nm for r in data.recordings], axis=0))
    model.calibration = artifact.CalibrationRecordings(
        [(np.asarray(r.ds.wl_nm, dtype=np.float64), r.baseline_nm) for r in data.recordings],
        [np.asarray(r.ds.force_N, dtype=np.float64)[np.asarray(r.ds.contact, dtype=bool)]
         for r in data.recordings], [d.get("path") or r.source for d, r in zip(described, data.recordings)])
    return model


#: The settled-hold gain is measured on at least this many synthetic holds, else left off.
HOLD_GAIN_MIN_HOLDS = 3


def hold_gain(model: artifact.HierarchicalModel, data: Prepared, holds: Sequence[Held]) -> dict[str, Any]:
    """The settled-hold gain (:class:`fbgforce.model.artifact.InUse`) the trained nets need: their
    least-squares gain on the samples of the synthetic ``holds`` (:func:`_synthetic_holds`)
    at least :data:`fbgforce.model.artifact.HOLD_SETTLE_S` into each hold, minus 1.

    The nets read a hold a little low (docs/trainer.md, "The turn": a causal estimator cannot
    tell a load that stands from one that has just begun to fall, and they compromise); once
    a load has stood still longer than a turn lasts the runtime may take that compromise
    back, by as much as the nets leave on synthetic holds.

    Returns
    -------
    dict
        ``gain`` (0.0 with fewer than :data:`HOLD_GAIN_MIN_HOLDS` holds), ``holds``,
        ``samples``, and the force bias over those samples (N) ``bias_before_N`` and
        ``bias_after_N``.
    """
    x = np.concatenate([h[0] for h in holds]) if holds else np.empty((0, 0))
    src = np.concatenate([h[1] for h in holds]) if holds else np.empty(0, dtype=np.int64)
    if src.size < 2:
        return {"gain": 0.0, "holds": 0, "samples": 0, "bias_before_N": None, "bias_after_N": None}
    # A hold is a run of samples that take one row's labels (each sample after it takes its
    # own); HOLD_AUGMENT_STEP_S apart.
    new_run = np.r_[True, src[1:] != src[:-1]]
    starts = np.flatnonzero(new_run)
    lengths = np.diff(np.r_[starts, src.size])
    position = np.arange(src.size) - np.repeat(starts, lengths)
    step_s = max(1, int(round(HOLD_AUGMENT_STEP_S * data.rate_hz))) / data.rate_hz
    held = np.repeat(lengths > 1, lengths)
    settled = held & (position * step_s >= artifact.HOLD_SETTLE_S)
    label = data.force_N[src]
    settled &= np.isfinite(label) & (label > 0)
    n_holds = int(np.unique(src[settled]).size)
    if n_holds < HOLD_GAIN_MIN_HOLDS:
        return {"gain": 0.0, "holds": n_holds, "samples": int(settled.sum()),
                "bias_before_N": None, "bias_after_N": None}
    f = floatref.predict_from_features(model, x[settled])["force_raw_N"]
    y = label[settled]
    gain = float(np.clip(np.dot(y, f) / max(float(np.dot(f, f)), 1e-12) - 1.0,
                         -artifact.HOLD_GAIN_MAX, artifact.HOLD_GAIN_MAX))
    return {"gain": gain, "holds": n_holds, "samples": int(settled.sum()),
            "bias_before_N": float(np.mean(f - y)), "bias_after_N": float(np.mean(f * (1 + gain) - y))}


#: The contact decision's rules the trainer can set (``fbgforce train --decision``): the
#: Schmitt trigger with a rise count, or the CUSUM rise (docs/runtime.md, "In use").
DECISION_RULES = ("schmitt", "cusum")


def _in_use(model: artifact.HierarchicalModel, data: Prepared, logits: np.ndarray, z: np.ndarray,
            tr: np.ndarray, cnet: FlatMLP, rests: tuple[Held, Held], gain: float,
            decision: str) -> dict[str, dict[str, Any]]:
    """Set the model's decision over time (by the rule ``decision``), tracker and input range
    from the training data; return the decision's fields of every rule of
    :data:`DECISION_RULES` (``metadata.decision_rules``: what the others would have set).

    The decision's thresholds weigh every sample at rest, the synthetic long rests'
    included: the calibration's own rests end within a second of a release, before the
    memory settles. The tracker discounts the recovery the pad's creep (``data.creep_held``)
    predicts after a release, which it would otherwise learn as drift (docs/runtime.md, "In
    use"), unless the creep inverse has already taken it out. ``gain``: the settled-hold
    gain (:func:`hold_gain`)."""
    rested = np.concatenate([rests[0][0], rests[1][0]])[:, :z.shape[1]]
    long = predict_batched(cnet, rested) if len(rested) else np.empty((0, 2))
    left = Creep() if model.preprocess.creep else data.creep_held
    calibration_rests = _rest_margins(data, logits)
    # The Schmitt trigger's threshold weighs the synthetic long rests too; the CUSUM's false
    # events are estimated from excursions along the recordings' own rests, in their order,
    # which spliced-in synthetic stretches would not keep.
    rest_margins = {"schmitt": np.concatenate([calibration_rests, long[:, 1] - long[:, 0]]),
                    "cusum": calibration_rests}
    rules = {rule: artifact.InUse.recommended(
        data.rate_hz, rest_margins=rest_margins[rule], creep_magnitude=left.magnitude,
        creep_time_constant_samples=left.time_constant_s * data.rate_hz, hold_gain=gain,
        decision=rule) for rule in DECISION_RULES}
    model.in_use = rules[decision]
    model.input_range = artifact.input_range_of(z[tr])
    return {rule: {k: v for k, v in iu.to_json().items() if k.startswith("contact_")}
            for rule, iu in rules.items()}


def train(datasets: Sequence[Any], params: TrainParams | None = None, *,
          prepared: Prepared | None = None, **options: Any) -> artifact.HierarchicalModel:
    """Train the hierarchical model on calibration recordings, step by step: the starting
    point, the prepared data, the split, the scaling and preprocessing, synthetic holds and
    rests, the
    contact, force and location nets, the model and its metadata.

    Parameters
    ----------
    datasets
        Paths (CSV/npz in the dataset contract) or ``fbgforce.recordings.dataset.Dataset`` objects; each
        one is a continuous recording of one device.
    params
        What to do (:class:`TrainParams`); default every default.
    prepared
        Reuse the output of :func:`prepare` (same data, filter and seed) to save time.
    **options
        Fields of :class:`TrainParams` given one by one (over ``params``'), e.g.
        ``train(files, epochs=50, seed=1)``.

    Returns
    -------
    fbgforce.model.artifact.HierarchicalModel

    Raises
    ------
    InputError
        A parameter out of its range (naming the option), or data training cannot use.
    """
    unknown = sorted(set(options) - {f.name for f in fields(TrainParams)})
    if unknown:
        raise TypeError(f"train() got unknown parameters: {', '.join(unknown)}")
    params = replace(params or TrainParams(), **options)
    t_start = time.perf_counter()
    ds_list, described = load_datasets(datasets)
    from fbgforce.trainer.coverage import coverage   # it reads this module's hold band

    data_coverage = coverage(ds_list)
    sources = [d.get("path") or d.get("source") or f"recording {i}"
               for i, d in enumerate(described)]
    init_model, memory, net_sizes = _starting_point(params)
    data = prepared if prepared is not None else prepare(
        ds_list, seed=params.seed, filter=params.filter, sigma=params.sigma,
        window=params.window, sources=sources, ref_shift=params.ref_shift,
        creep_inverse=params.creep_inverse, memory=memory, creep=params.creep)
    if params.turn_guard_s is None:
        params = replace(params, turn_guard_s=TURN_GUARD_S if data.pre.creep else 0.0)
    t_prep = time.perf_counter() - t_start
    streams = _Streams.from_seed(params.seed)
    tr, va, te = _split(data, params, streams.subsample)
    scaling = _scaling(data, tr, init_model)
    pre = _model_preprocess(data, scaling, init_model, memory, tr)
    x_all = data.inputs(pre)
    z = x_all[:, :pre.n_features]    # what the contact and force nets read
    fit_net = _NetFitter(params, net_sizes, init_model, streams.init, bool(va.size))
    if data.creep_fit is None:    # a Prepared made without prepare()
        data.creep_found, data.creep_evidence = creep_choice(data, pre, tr, params.creep,
                                                             params.seed)
        data.creep_fit = data.creep_found if data.creep_evidence["applied"] else Creep()
        data.creep_held = _held_creep(data, pre, data.creep_fit)
    creep = data.creep
    hold_tr, hold_va = _holds(data, pre, params, tr, va, creep, streams.holds)
    rest_tr, rest_va = _rests(data, pre, params, tr, va, streams.rests)
    synth_tr, synth_va = _joined(hold_tr, rest_tr), _joined(hold_va, rest_va)
    cnet, logits = _fit_contact(fit_net, data, z, tr, va, synth_tr, synth_va, streams.contact)
    pred_contact = logits[:, 1] > logits[:, 0]
    fnet = _fit_force(fit_net, data, z, cnet, pred_contact, scaling, tr, va, synth_tr, synth_va,
                      streams.force)
    lnet = _fit_location(fit_net, data, pre, x_all, pred_contact, fnet, scaling, params, tr, va,
                         streams)
    warnings, held_s = _training_warnings(data, pre, tr, te, hold_tr)
    reports = fit_net.reports
    model = _assemble(data, pre, scaling, {"contact": cnet, "force": fnet, "location": lnet},
                      reports, described)
    t_train = time.perf_counter() - t_start - t_prep
    # The gain is measured on holds of every training and validation press, drawn apart
    # from the ones the nets trained on: the nets fit those, and would promise too little.
    settled = hold_gain(model, data, [_synthetic_holds(
        data, pre, np.sort(np.concatenate([tr, va])), 1.0, creep, streams.hold_gain)]
        if hold_tr[1].size else [])
    rules = _in_use(model, data, logits, z, tr, cnet, (rest_tr, rest_va), settled["gain"],
                    params.decision)
    model.metadata = _metadata(model, data, params, described, (tr, va, te), x_all, reports,
                               data_coverage, creep, (hold_tr, hold_va, settled),
                               (rest_tr, rest_va), held_s, warnings, (t_prep, t_train))
    model.metadata["decision_rules"] = rules
    return model


def corrections(model: artifact.HierarchicalModel, data: Prepared, params: TrainParams,
                settled: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Each correction beyond the nets the model makes, whether it is on, and why: what
    ``fbgforce train`` prints and ``model.json`` records (``metadata.corrections``)."""
    iu, pre = model.in_use, model.preprocess
    evidence = data.creep_evidence or {}
    creep = data.creep_fit or Creep()
    how = ("taken out before the filter" if pre.creep else
           "discounted by the at-rest tracker" if iu.track_creep else "carried by the holds")
    holds = params.hold_augment > 0 and model.preprocess.memory.n_states > 0
    return [
        {"name": "creep", "applied": bool(creep.magnitude > 0),
         "why": (f"{100 * creep.magnitude:.1f} % over {creep.time_constant_s:.2g} s, {how}: "
                 if creep.magnitude > 0 else "") + evidence.get("why", "not fitted")},
        {"name": "synthetic_holds", "applied": holds,
         "why": (f"{100 * params.hold_augment:g} % of the presses held {HOLD_AUGMENT_S[0]:g}-"
                 f"{HOLD_AUGMENT_S[1]:g} s" + (", creeping as fitted" if creep.magnitude > 0
                                              else ", flat (no creep established)"))
         if holds else "--hold-augment 0 or a memoryless model"},
        {"name": "settled_hold_gain", "applied": bool(iu.hold_gain),
         "why": (f"{iu.hold_gain:+.4f}, the nets' gain on {settled.get('holds', 0)} held-out "
                 "synthetic holds" if iu.hold_gain else
                 f"off: {settled.get('holds', 0)} synthetic holds to measure it on (at least "
                 f"{HOLD_GAIN_MIN_HOLDS} needed)" if not settled.get("gain") else "off")},
        {"name": "turn_guard", "applied": bool(params.turn_guard_s),
         "why": f"{1000 * params.turn_guard_s:g} ms after each turn left out of the force net"
         if params.turn_guard_s else "by default only with the creep inverse"},
        {"name": "decision_over_time", "applied": not iu.per_sample,
         "why": (f"CUSUM rise, threshold {iu.contact_cusum_h:.3g} over a drift of "
                 f"{iu.contact_cusum_k:.3g}, from the calibration's rests"
                 if iu.contact_cusum_h else
                 f"Schmitt trigger at a margin of {iu.contact_on_margin:.3g} for "
                 f"{iu.contact_rise_samples} samples, from the rests")
         if not iu.per_sample else "per sample: the calibration's rests set no threshold above 0"},
        {"name": "at_rest_tracker", "applied": bool(iu.track_shift),
         "why": f"time constant 2^{iu.track_shift} samples, at most "
                f"{iu.track_limit_pm:g} pm" if iu.track_shift else "off"},
    ]


def _metadata(model: artifact.HierarchicalModel, data: Prepared, params: TrainParams,
              described: Sequence[Mapping[str, Any]],
              rows: tuple[np.ndarray, np.ndarray, np.ndarray], x_all: np.ndarray,
              reports: Mapping[str, Any], data_coverage: Any, creep: Creep,
              holds: tuple[Held, Held, dict[str, Any]], rests: tuple[Held, Held], held_s: float,
              warnings: list[str], times: tuple[float, float]) -> dict[str, Any]:
    """The facts ``model.json`` records: data, split, sizes, training, metrics, times."""
    tr, va, te = rows
    hold_tr, hold_va, settled = holds
    pre = model.preprocess
    rate = data.rate_hz
    pad = list(pad_extent_mm(data.x_mm[tr], data.y_mm[tr]))
    model.metadata = {"pad_mm": pad}  # read by evaluate_rows below
    return {
        "fbgforce_version": __version__,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "data": [{**d, **r.tare_info, "baseline_nm": r.baseline_nm.tolist(),
                  "sample_rate_hz": r.rate_hz} for d, r in zip(described, data.recordings)],
        "seed": params.seed,
        "split": {"by": "press", "ratios": list(SPLIT_RATIOS),
                  "train_fraction": params.train_fraction,
                  "samples": {"train": int(tr.size), "val": int(va.size), "test": int(te.size)}},
        "sizes": {name: net.sizes for name, net in model.nets.items()},
        "memory": pre.memory.to_json(),
        "train_hold_s": held_s,
        "coverage": data_coverage,
        "creep": {"magnitude": creep.magnitude, "time_constant_s": creep.time_constant_s,
                  "inverse": bool(pre.creep),
                  **({"fitted": {"magnitude": data.creep_found.magnitude,
                                 "time_constant_s": data.creep_found.time_constant_s}}
                     if data.creep_found is not None else {}),
                  **({"evidence": data.creep_evidence} if data.creep_evidence else {})},
        "synthetic_holds": {"share": params.hold_augment, "range_s": list(HOLD_AUGMENT_S),
                            "presses": {"train": _count_holds(hold_tr[1], data),
                                        "val": _count_holds(hold_va[1], data)},
                            "samples": {"train": int(hold_tr[1].size),
                                        "val": int(hold_va[1].size)},
                            "settled_gain": settled},
        "turn_guard_s": params.turn_guard_s,
        "corrections": corrections(model, data, params, settled),
        "synthetic_rests": {"share": params.rest_augment, "range_s": list(REST_AUGMENT_S),
                            "seconds": {name: REST_AUGMENT_STEP_S * rest[1].size
                                        for name, rest in zip(("train", "val"), rests)}},
        "warnings": warnings,
        "pad_mm": pad,
        "filter": {"kind": pre.filter_kind, "sigma_samples": pre.filter_sigma,
                   "taps": int(pre.taps.size), "group_delay_ms": pp.group_delay_ms(pre, rate),
                   "sample_rate_hz": rate},
        "temperature": {"temp_coeff": pre.temp_coeff.tolist(), **data.temp_info},
        "init": str(params.init) if isinstance(params.init, (str, Path))
        else (None if params.init is None else "model"),
        "optimizer": {"name": "adam", "learning_rate": params.learning_rate,
                      "decay_per_epoch": params.decay, "batch_size": params.batch_size,
                      "max_epochs": params.epochs, "patience": params.patience},
        "training": {name: {k: v for k, v in rep.items() if k != "history"}
                     for name, rep in reports.items()},
        "history": {name: rep["history"] for name, rep in reports.items()},
        "times_s": {"prepare": times[0], "train": times[1],
                    **{name: rep["seconds"] for name, rep in reports.items()}},
        "metrics": {"val": evaluate_rows(model, data, va, inputs=x_all) if va.size else None,
                    "test": evaluate_rows(model, data, te, inputs=x_all) if te.size else None},
        "platform": {"python": platform.python_version(), "numpy": np.__version__},
    }


def _scaled_presses(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, max_scale: float,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Net inputs of the training presses pressed ``k`` times harder, ``k ~ U(1, max_scale)``
    per press, and the rows (of ``data``) they stand for.

    Where a press lands does not depend on how hard: the strain part of every grating's
    compensated shift is scaled by ``k`` (temperature and tare untouched) and the inputs are
    recomputed with the model's own preprocessing ``pre`` (filter, standardisation, memory) on
    the whole recording, so the memory states see a consistent time series. The location net
    then sees each spot at forces the calibration did not reach there; without it, it
    interpolates between the few presses that reached high force (docs/trainer.md).
    """
    inputs, kept = [], []
    for r, sl in data.recording_slices():
        start = sl.start
        sel = rows[(rows >= start) & (rows < sl.stop)] - start
        if sel.size:
            _, inverse = np.unique(np.asarray(r.ds.press_id), return_inverse=True)
            k = rng.uniform(1.0, max_scale, inverse.max() + 1)[inverse]
            comp = pp.compensated(pre, r.ds.wl_nm, r.baseline_nm)
            wl = np.array(r.ds.wl_nm, dtype=np.float64, copy=True)
            wl[:, :artifact.N_STRAIN] += (k[:, None] - 1.0) * comp / 1000.0
            feats = pp.recording_features(pre, wl, r.baseline_nm)
            inputs.append(floatref.standardise(pre, feats)[sel])
            kept.append(sel + start)
    if not inputs:
        return np.empty((0, pre.n_inputs)), rows[:0]
    return np.concatenate(inputs), np.concatenate(kept)


@dataclass(frozen=True)
class Creep:
    """The pad's viscoelastic creep as a standard linear solid: the beams carry
    ``F + magnitude * (lag(F) - F)``, ``lag`` a first-order lag of the load with
    ``time_constant_s`` (0, 0: none found)."""

    magnitude: float = 0.0
    time_constant_s: float = 0.0

    def lag(self, force_N: np.ndarray, rate_hz: float) -> np.ndarray:
        """The first-order lag of ``force_N`` (one recording) at ``rate_hz``."""
        a = 1.0 - np.exp(-1.0 / (rate_hz * self.time_constant_s))
        out = np.empty(len(force_N))
        state = 0.0
        for k, f in enumerate(np.asarray(force_N, float).tolist()):
            state += a * (f - state)
            out[k] = state
        return out

    def still_to_come(self, force_N: np.ndarray, at: np.ndarray, rate_hz: float) -> np.ndarray:
        """At samples ``at`` of a recording: how much more the beams would carry if the load
        stood still from there on, relative to what they carry (``m (F - lag) / (F + m (lag
        - F))``; 0 without creep)."""
        if self.magnitude <= 0:
            return np.zeros(len(at))
        f, lag = force_N[at], self.lag(force_N, rate_hz)[at]
        carried = f + self.magnitude * (lag - f)
        return self.magnitude * (f - lag) / np.maximum(carried, 1e-9)

    def settling(self, n: int, rate_hz: float) -> np.ndarray:
        """``1 - exp(-k / (tau rate))`` for ``k = 0 .. n-1``: how far the creep has run ``k``
        samples into a hold (1 without creep)."""
        if self.magnitude <= 0:
            return np.ones(n)
        return 1.0 - np.exp(-np.arange(n) / (self.time_constant_s * rate_hz))


@dataclass
class CreepTails:
    """What the creep fit reads: the samples just after the releases among some rows.

    Every :data:`CREEP_ZERO_SPAN_S` span of the recordings has an offset of its own, so the
    fits below work on values less their span's mean (which is what a least-squares fit with
    one indicator column per span does to the other columns).

    Attributes
    ----------
    excess
        (m,) the load signal minus the load-cell force on those samples, N.
    span
        (m,) the span of each sample (0 ..).
    release
        (m,) which release each sample follows (0 .., numbered across recordings).
    lags
        (m, len(time_constants_s)) ``lag(F) - F`` at each relaxation time.
    time_constants_s
        The relaxation times of ``lags``' columns.
    """

    excess: np.ndarray
    span: np.ndarray
    release: np.ndarray
    lags: np.ndarray
    time_constants_s: tuple[float, ...]

    @classmethod
    def of(cls, data: Prepared, pre: artifact.Preprocess, rows: np.ndarray,
           time_constants_s: Sequence[float] = CREEP_TIME_CONSTANTS_S) -> "CreepTails | None":
        """The tails of the releases among ``rows``; None when they hold fewer than 100
        samples or ``rows`` no contact."""
        keep = data.row_mask(rows)
        comps, forces, tails, spans, releases = [], [], [], [], []
        for r, sl in data.recording_slices():
            contact = np.asarray(r.ds.contact, bool)
            idx = np.arange(contact.size)
            last = np.maximum.accumulate(np.where(contact, idx, -contact.size))
            nxt = np.minimum.accumulate(np.where(contact, idx, 2 * contact.size)[::-1])[::-1]
            tail = int(round(CREEP_TAIL_S * r.rate_hz))
            tails.append(~contact & (idx - last <= tail) & (nxt - idx > tail // 2) & keep[sl])
            comps.append(pp.compensated(pre, r.ds.wl_nm, r.baseline_nm))
            forces.append(np.nan_to_num(np.asarray(r.ds.force_N, float)))
            # Numbered across recordings: each recording's zero wanders on its own.
            first = spans[-1][-1] + 1 if spans else 0
            spans.append(first + idx // max(1, int(round(CREEP_ZERO_SPAN_S * r.rate_hz))))
            releases.append(last + (releases[-1].max() + contact.size + 1 if releases else 0))
        comp, force, tail = np.concatenate(comps), np.concatenate(forces), np.concatenate(tails)
        loaded = keep & data.contact
        if tail.sum() < 100 or not loaded.any():
            return None
        _, span = np.unique(np.concatenate(spans)[tail], return_inverse=True)
        _, release = np.unique(np.concatenate(releases)[tail], return_inverse=True)
        w, *_ = np.linalg.lstsq(np.column_stack([comp[loaded], np.ones(loaded.sum())]),
                                force[loaded], rcond=None)
        excess = (comp @ w[:artifact.N_STRAIN] + w[artifact.N_STRAIN] - force)[tail]
        lags = np.column_stack([
            np.concatenate([Creep(1.0, tau).lag(force[sl], r.rate_hz) - force[sl]
                            for r, sl in data.recording_slices()])[tail]
            for tau in time_constants_s])
        return cls(excess, span, release, lags, tuple(time_constants_s))

    def subset(self, mask: np.ndarray) -> "CreepTails":
        """The samples of ``mask``."""
        return CreepTails(self.excess[mask], np.unique(self.span[mask], return_inverse=True)[1],
                          self.release[mask], self.lags[mask], self.time_constants_s)

    def _centred(self, x: np.ndarray) -> np.ndarray:
        """``x`` (m,) or (m, k) less its span's mean, column by column."""
        n = np.bincount(self.span).astype(float)
        cols = x.reshape(x.shape[0], -1)
        means = np.stack([np.bincount(self.span, weights=c) for c in cols.T], axis=1) / n[:, None]
        return (cols - means[self.span]).reshape(x.shape)

    def rss_offsets(self) -> float:
        """The residual of the offsets alone (no creep)."""
        return float(np.sum(self._centred(self.excess) ** 2))

    def fit(self, lags: np.ndarray | None = None) -> tuple[float, Creep]:
        """The best relaxation time's residual and creep (slope clipped to 0 .. 0.9) on these
        samples; ``lags`` replaces :attr:`lags` (the sign-flip test's)."""
        e = self._centred(self.excess)
        g = self._centred(self.lags if lags is None else lags)
        gg = np.maximum(np.einsum("ij,ij->j", g, g), 1e-300)
        ge = g.T @ e
        rss = float(e @ e) - ge ** 2 / gg
        j = int(np.argmin(rss))
        return float(rss[j]), Creep(float(np.clip(ge[j] / gg[j], 0.0, 0.9)),
                                    self.time_constants_s[j])

    def rss_with(self, creep: Creep) -> float:
        """The residual on these samples of ``creep`` as given (only the offsets fitted)."""
        j = int(np.argmin(np.abs(np.log(np.asarray(self.time_constants_s)
                                         / creep.time_constant_s))))
        return float(np.sum(self._centred(self.excess - creep.magnitude * self.lags[:, j]) ** 2))


def fit_creep(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray,
              time_constants_s: Sequence[float] = CREEP_TIME_CONSTANTS_S) -> Creep:
    """The pad's creep, fitted on the creep recovery after the releases among ``rows``.

    After a release the rate-independent friction of the pad has let go (its loop closes at
    zero load), so what the gratings still report there is the viscoelastic lag running
    down. A load signal ``u`` (least squares of the load-cell force on the compensated
    shifts over the contact samples of ``rows``) minus the force is regressed on
    ``lag(F) - F`` over the first :data:`CREEP_TAIL_S` after each release, for each
    relaxation time of ``time_constants_s`` (:data:`CREEP_TIME_CONSTANTS_S`); the best fit's
    slope is the magnitude (:class:`CreepTails`).
    Beside the slope, each :data:`CREEP_ZERO_SPAN_S` of the recording has an offset of its
    own: the unloaded zero wanders (interrogator, fibre mounts), and a slow creep's residual
    (a second's time constant in rests of a fraction of one) is itself nearly an offset,
    which one offset for the whole log confused with that wander. On the calibration_paper
    scene (5 % and 0.08 s simulated) it finds 0.051 and 0.083 s; on tests/foreign.py's in-use
    fingertip (5 %, 1 s) 0.046 and 0.83 s, 0.052 and 1.0 s on its two calibration logs, where
    one offset found 0.031 and 0.56 s on the first.

    A fit is a hypothesis: :func:`creep_evidence` says whether the calibration establishes it.
    """
    return creep_of(CreepTails.of(data, pre, rows, time_constants_s))


def creep_of(tails: CreepTails | None) -> Creep:
    """:func:`fit_creep` on tails already gathered (none: no creep)."""
    if tails is None:
        return Creep()
    creep = tails.fit()[1]
    return creep if creep.magnitude > 0 else Creep()


#: The creep a calibration must establish before the trainer corrects for it
#: (:func:`creep_evidence`): a relaxation time clear of the fit's shortest (a rate effect at
#: the release, a damper's, reads as a creep there), and more of the tails' residual removed,
#: in sample and on releases the fit never saw, than the fit removes from any of
#: :data:`CREEP_EVIDENCE_DRAWS` sign-flipped draws of the noise.
CREEP_EVIDENCE_MIN_TAU_S = 0.02
CREEP_EVIDENCE_DRAWS = 19


#: Folds of the training presses for :func:`creep_press_check`, and the one-sided level of
#: its sign test.
CREEP_PRESS_FOLDS = 5
CREEP_PRESS_LEVEL = 0.05


def creep_press_check(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, creep: Creep
                      ) -> dict[str, Any]:
    """Whether taking ``creep`` out of the shifts reads held-out presses better.

    A least-squares load signal (the force on the compensated shifts of the contact samples,
    with an offset) is fitted on all but one of :data:`CREEP_PRESS_FOLDS` folds of the
    presses among ``rows`` and scored on the fold left out, once on the shifts as recorded and
    once after the creep inverse (:func:`fbgforce.model.floatref.creep_inverse` with ``creep`` at a
    time constant the model can hold). A creep that outlasts the rests leaves a load-history
    offset on every press that the inverse takes away, and which the release tails, whose
    10 s offsets absorb it, cannot show. Each press's mean squared error counts as better or
    worse; a one-sided sign test at :data:`CREEP_PRESS_LEVEL` says whether the inverse reads
    more held-out presses better than chance would.

    Returns
    -------
    dict
        ``presses``, ``better`` (presses read better with the inverse), ``p_value``,
        ``rmse_N`` and ``rmse_inverse_N`` (over the held-out contact samples), ``passes``.
    """
    m, k = artifact.creep_parameters(creep.magnitude, creep.time_constant_s * data.rate_hz)
    keep = data.row_mask(rows) & data.contact & np.isfinite(data.force_N)
    if m <= 0 or not keep.any():
        return {"presses": 0, "better": 0, "p_value": 1.0, "rmse_N": None,
                "rmse_inverse_N": None, "passes": False}
    inv_pre = replace(pre, creep=m, creep_shift=k)
    plain, inverted, pids = [], [], []
    for r, sl in data.recording_slices():
        comp = pp.compensated(pre, r.ds.wl_nm, r.baseline_nm, recording=True)
        plain.append(comp)
        inverted.append(floatref.creep_inverse(inv_pre, comp))
        pids.append(np.asarray(r.ds.press_id))
    force = data.force_N[keep]
    press = np.unique(np.concatenate(pids)[keep], return_inverse=True)[1]
    fold = press % CREEP_PRESS_FOLDS
    errors = []
    for shifts in (plain, inverted):
        x = np.column_stack([np.concatenate(shifts)[keep], np.ones(keep.sum())])
        err = np.empty(force.size)
        for f in range(CREEP_PRESS_FOLDS):
            out = fold == f
            if out.all() or not out.any():
                err[out] = np.nan
                continue
            w, *_ = np.linalg.lstsq(x[~out], force[~out], rcond=None)
            err[out] = x[out] @ w - force[out]
        errors.append(err)
    n = int(press.max()) + 1
    per_press = [np.bincount(press, weights=np.nan_to_num(e) ** 2, minlength=n) for e in errors]
    better, worse = int(np.sum(per_press[1] < per_press[0])), int(np.sum(per_press[1] > per_press[0]))
    # One-sided sign test: the chance of this many better presses or more if better and worse
    # were equally likely.
    trials = better + worse
    p = float(sum(math.comb(trials, j) for j in range(better, trials + 1)) / 2.0 ** trials) \
        if trials else 1.0
    scored = np.isfinite(errors[0])
    if not scored.any():      # the presses fall in one fold: nothing is held out
        return {"presses": n, "better": 0, "p_value": 1.0, "rmse_N": None,
                "rmse_inverse_N": None, "passes": False}
    rmse = [float(np.sqrt(np.mean(e[scored] ** 2))) for e in errors]
    return {"presses": n, "better": better, "p_value": p, "rmse_N": rmse[0],
            "rmse_inverse_N": rmse[1], "passes": bool(p < CREEP_PRESS_LEVEL and rmse[1] < rmse[0])}


def creep_evidence(tails: CreepTails | None, fitted: Creep, seed: int = 0,
                   presses: Callable[[], dict[str, Any]] | None = None) -> dict[str, Any]:
    """Whether the releases whose ``tails`` (:class:`CreepTails`) :func:`fit_creep` read
    establish the creep ``fitted`` on them, or, for the held-out check, the presses
    (``presses()``: :func:`creep_press_check` of the same creep, run only when the held-out
    releases do not show it).

    Three tests:

    - the relaxation time: above :data:`CREEP_EVIDENCE_MIN_TAU_S`. At the shortest times of
      the fit's grid a creep is indistinguishable from a rate-dependent hysteresis (a
      damper's, which lets go the moment the load stands still): the release's last
      milliseconds read as a creep that a hold would never show;
    - against the noise: the share of the residual the fit removes must exceed what it
      removes from each of :data:`CREEP_EVIDENCE_DRAWS` draws in which every release's
      ``lag(F) - F`` has its sign flipped at random (a draw keeps the noise, the wander and
      the offsets, and breaks any creep), a test at the 5 % level;
    - held out: the releases are split in two halves (every other release); the creep fitted
      on each half must lower the other half's residual (beside its offsets) by a larger
      share than the noise's largest; or, where the releases cannot show it (a creep slower
      than the rests is an offset 150 ms into one), taking it out must read the calibration's
      held-out presses better (``presses``, :func:`creep_press_check`, run only then and
      only when the other tests pass).

    Returns
    -------
    dict
        ``established`` (bool), ``why`` (one line), ``tests`` (each test's figures).
    """
    if fitted.magnitude <= 0:
        return {"established": False, "why": "the fit found no creep", "tests": {}}
    if tails is None:
        return {"established": False, "why": "too few samples after releases to test a creep",
                "tests": {}}
    tests: dict[str, Any] = {"time_constant_s": fitted.time_constant_s}
    fails = []
    if fitted.time_constant_s < CREEP_EVIDENCE_MIN_TAU_S:
        fails.append(f"its time constant ({1000 * fitted.time_constant_s:.0f} ms) is at the "
                     "fit's shortest, where a rate-dependent hysteresis reads the same")
    half = tails.release % 2 == 0
    gains = []
    for fit_on, check in ((half, ~half), (~half, half)):
        if not fit_on.any() or not check.any():
            gains.append(0.0)
            continue
        held = tails.subset(check)
        creep = tails.subset(fit_on).fit()[1]
        gains.append(1.0 - held.rss_with(creep) / max(held.rss_offsets(), 1e-300))
    rss0 = tails.rss_offsets()
    removed = rss0 - tails.fit()[0]
    rng = np.random.default_rng(seed)
    null = []
    for _ in range(CREEP_EVIDENCE_DRAWS):
        sign = rng.choice([-1.0, 1.0], int(tails.release.max()) + 1)[tails.release]
        null.append(rss0 - tails.fit(tails.lags * sign[:, None])[0])
    noise = float(max(null) / max(rss0, 1e-300))
    tests.update(removed_share=float(removed / max(rss0, 1e-300)), noise_removed_share_max=noise,
                 held_out_gain=[float(g) for g in gains])
    if removed <= max(null):
        fails.append(f"it removes {100 * tests['removed_share']:.2f} % of the residual, no "
                     f"more than sign-flipped noise does ({100 * noise:.2f} %)")
    held_out = min(gains) > noise
    checked = presses() if presses is not None and not held_out and not fails else None
    if checked is not None:
        tests["presses"] = checked
    if not held_out and not (checked is not None and checked["passes"]):
        fails.append(f"fitted on half the releases it explains {100 * min(gains):.2f} % of the "
                     f"other half's residual, no more than noise does ({100 * noise:.2f} %)"
                     + (f", and taking it out reads {checked['better']} of {checked['presses']}"
                        f" held-out presses better (p = {checked['p_value']:.2g})"
                        if checked is not None else ""))
    if fails:
        return {"established": False, "why": "; ".join(fails), "tests": tests}
    if held_out:
        why = (f"held out it explains {100 * min(gains):.1f}-{100 * max(gains):.1f} % of the "
               f"residual after releases, noise at most {100 * noise:.2f} %")
    else:
        why = (f"taking it out reads {checked['better']} of {checked['presses']} held-out "
               f"presses better (p = {checked['p_value']:.2g}; load signal RMSE "
               f"{checked['rmse_N']:.3f} -> {checked['rmse_inverse_N']:.3f} N)")
    return {"established": True, "why": why, "tests": tests}


def _synthetic_holds(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, share: float,
                     creep: Creep, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Net inputs of presses among ``rows`` held at their peak, and the rows (of ``data``)
    whose labels they take.

    A calibration stage that turns round at every peak never shows the memory a load standing
    still: its averages then decay towards the load, a state the nets meet first in a held
    grip. A ``share`` of the presses (drawn per press) gets a hold of
    ``U(*HOLD_AUGMENT_S)`` seconds inserted after its peak sample: the five wavelengths at the
    mean of the six raw samples up to the peak, scaled to the peak force, plus interrogator
    noise drawn (one row of all five channels at a time) from the recording's own first
    differences at rest over √2, the labels those of the peak. Through the hold the pad keeps creeping as ``creep`` says
    (:func:`fit_creep`): the strain part of the held shifts (temperature and tare untouched)
    rises by ``m (F - lag(F))`` of the force it carried at the peak, with the creep's time
    constant, and the samples after the hold carry what is left of that rise as the lag
    runs down; without it the nets would learn the peak's still-lagging shifts as the held
    load and read a real hold high by that creep (1.8 % on the calibration scene). The
    inputs are recomputed with ``pre`` over the whole lengthened recording, so the filter and
    the memory states run through the hold as the runtime's would; the held samples (one
    every :data:`HOLD_AUGMENT_STEP_S`) and the rest of the press after the hold are returned.
    """
    inputs, kept = [], []
    for r, sl, sel, contact, noise, pid in _augmented_recordings(data, rows):
        wl = np.asarray(r.ds.wl_nm, dtype=np.float64)
        presses = np.unique(pid[contact[sel]])
        peaks, after = [], np.zeros(len(wl), dtype=bool)
        for p in presses[rng.random(presses.size) < share]:
            loaded = sel[(pid == p) & contact[sel]]
            peak = int(loaded[np.argmax(np.asarray(r.ds.force_N)[loaded])])
            peaks.append(peak)
            after[sel[(pid == p) & (sel > peak)]] = True
        if not peaks:
            continue
        lengths = np.round(rng.uniform(*HOLD_AUGMENT_S, len(peaks)) * r.rate_hz).astype(np.int64)
        # The mean of the 6 samples up to the peak, its strain part scaled by the peak force
        # over their mean force (the load still rises there). Not the samples after it: past
        # a turn the pad's friction holds the strain while the load falls.
        force = np.nan_to_num(np.asarray(r.ds.force_N, float))
        around = [slice(max(0, k - 5), k + 1) for k in peaks]
        level = np.array([wl[a].mean(axis=0) for a in around])
        base = np.asarray(r.baseline_nm, float)
        scale = force[peaks] / np.maximum([force[a].mean() for a in around], 1e-12)
        level[:, :artifact.N_STRAIN] = (base[:artifact.N_STRAIN]
                                  + (level[:, :artifact.N_STRAIN] - base[:artifact.N_STRAIN]) * scale[:, None])
        rise = creep.still_to_come(force, np.asarray(peaks), r.rate_hz)
        # After the hold the lag runs down from the held load instead of the peak's lagging
        # value: the rise reached in the hold decays over 10 time constants.
        tail = 1.0 - creep.settling(int(10 * creep.time_constant_s * r.rate_hz) + 1, r.rate_hz)
        strain = pp.compensated(pre, level, r.baseline_nm) / 1000.0     # nm
        wl = wl.copy()
        ramp = []
        for i, (k, n) in enumerate(zip(peaks, lengths)):
            ramp.append(rise[i] * creep.settling(n, r.rate_hz))
            left = ramp[-1][-1] * tail[1:len(wl) - k]
            wl[k + 1:k + 1 + left.size, :artifact.N_STRAIN] += left[:, None] * strain[i]
        held = (np.repeat(level, lengths, axis=0)
                + noise[rng.integers(0, len(noise), int(lengths.sum()))])
        held[:, :artifact.N_STRAIN] += np.concatenate(ramp)[:, None] * np.repeat(strain, lengths, axis=0)
        in_hold = np.concatenate([np.arange(n) for n in lengths])
        step = max(1, int(round(HOLD_AUGMENT_STEP_S * r.rate_hz)))
        x, src = _lengthened_inputs(pre, r, wl, peaks, lengths, held, in_hold % step == 0, after)
        inputs.append(x)
        kept.append(src + sl.start)
    if not inputs:
        return np.empty((0, pre.n_inputs)), rows[:0]
    return np.concatenate(inputs), np.concatenate(kept)


def _synthetic_rests(data: Prepared, pre: artifact.Preprocess, rows: np.ndarray, share: float,
                     step: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Net inputs of long rests inserted among the presses of ``rows``, and the rows (of
    ``data``) whose labels they take.

    A calibration stage that presses again within a second never shows the nets a fingertip
    that has rested for long: the pad's creep recovered, the at-rest tracker's correction
    taken (docs/runtime.md, "In use"), the memory's averages settled at zero and its play
    operators where the last release left them. Nets that never saw that state read its
    noise as light presses (false contact events at rest). A ``share`` of the presses (drawn
    per press) gets a rest of ``U(*REST_AUGMENT_S)`` seconds inserted midway between its first
    contact sample and the previous press's last (when they lie more than ``2 * REST_GAP_S``
    apart): the five wavelengths of the six samples there, their strain part moved to zero
    compensated shift (temperature untouched), plus interrogator noise as in
    :func:`_synthetic_holds`. Zero, not the level there: a short rest still carries the pad's
    creep recovery, and a long one held at it would teach the nets that a light press is no
    contact. The inputs are recomputed with ``pre`` over the lengthened recording; returned is
    one rest sample in ``step`` from :data:`REST_AUGMENT_SETTLE_S` on, past the step down to
    zero, labelled as the sample where the rest was inserted (contact-free). The press after
    the rest is not: it would start with a step up from zero to the residual.
    """
    inputs, kept = [], []
    for r, sl, sel, contact, noise, pid in _augmented_recordings(data, rows):
        gap = int(round(fmetrics.REST_GAP_S * r.rate_hz))
        touched = np.flatnonzero(contact)
        starts = []
        for p in np.unique(pid[contact[sel]]):
            if rng.random() >= share:
                continue
            first = int(sel[(pid == p) & contact[sel]].min())
            before = touched[touched < first]
            prev = int(before[-1]) if before.size else -gap
            if first - prev > 2 * gap + 6:
                starts.append((prev + first) // 2)
        if not starts:
            continue
        wl = np.asarray(r.ds.wl_nm, dtype=np.float64)
        level = np.array([wl[max(0, k - 5):k + 1].mean(axis=0) for k in starts])
        level[:, :artifact.N_STRAIN] -= pp.compensated(pre, level, r.baseline_nm) / 1000.0
        lengths = np.round(rng.uniform(*REST_AUGMENT_S, len(starts)) * r.rate_hz).astype(np.int64)
        rest = (np.repeat(level, lengths, axis=0)
                + noise[rng.integers(0, len(noise), int(lengths.sum()))])
        in_rest = np.concatenate([np.arange(n) for n in lengths])
        settle = int(round(REST_AUGMENT_SETTLE_S * r.rate_hz))
        x, src = _lengthened_inputs(pre, r, wl, starts, lengths, rest,
                                    (in_rest >= settle) & ((in_rest - settle) % step == 0),
                                    np.zeros(len(wl), dtype=bool))
        inputs.append(x)
        kept.append(src + sl.start)
    if not inputs:
        return np.empty((0, pre.n_inputs)), rows[:0]
    return np.concatenate(inputs), np.concatenate(kept)


def _lengthened_inputs(pre: artifact.Preprocess, r: Recording, wl: np.ndarray, points: Sequence[int],
                       lengths: np.ndarray, inserted: np.ndarray, keep_inserted: np.ndarray,
                       keep_recorded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Net inputs of recording ``r`` (wavelengths ``wl``) lengthened by ``inserted`` (the
    rows of all insertions, ``lengths[i]`` of them after sample ``points[i]``), recomputed
    with ``pre`` over the whole lengthened recording as the runtime would run it; returned
    are the inserted rows ``keep_inserted`` marks and the recorded samples ``keep_recorded``
    marks, and the samples of ``r`` whose labels they take (an inserted row its point's)."""
    at = np.repeat(np.asarray(points) + 1, lengths)
    keep = np.insert(keep_recorded, at, keep_inserted)
    source = np.insert(np.arange(len(wl)), at, np.repeat(points, lengths))
    feats = pp.recording_features(pre, np.insert(wl, at, inserted, axis=0), r.baseline_nm)
    return floatref.standardise(pre, feats)[keep], source[keep]


def _augmented_recordings(data: Prepared, rows: np.ndarray
                          ) -> Iterator[tuple[Recording, slice, np.ndarray, np.ndarray,
                                              np.ndarray, np.ndarray]]:
    """The recordings synthetic holds and rests are made in: per recording with some of
    ``rows`` and rest noise to draw from, ``(r, sl, sel, contact, noise, pid)``: the recording,
    its slice of the prepared rows, its rows among ``rows`` (recording-local), its contact
    labels, its :func:`_rest_noise` and the press ids of ``sel``."""
    for r, sl in data.recording_slices():
        sel = rows[(rows >= sl.start) & (rows < sl.stop)] - sl.start
        noise = _rest_noise(r)
        if not sel.size or noise is None:
            continue
        yield (r, sl, sel, np.asarray(r.ds.contact, bool), noise,
               np.asarray(r.ds.press_id)[sel])


def _rest_noise(r: Recording) -> np.ndarray | None:
    """Interrogator noise of recording ``r``: its first differences between contact-free
    samples over √2 (one row of all five channels each), or None without two in a row."""
    rest = fbgtare.contact_free_mask(np.asarray(r.ds.contact, bool), r.ds.t_s)
    still = rest[1:] & rest[:-1]
    if not still.any():
        return None
    return np.diff(np.asarray(r.ds.wl_nm, dtype=np.float64), axis=0)[still] / np.sqrt(2.0)


def _joined(*augmented: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Synthetic samples (inputs, rows) of several kinds, one after the other."""
    return (np.concatenate([a[0] for a in augmented]),
            np.concatenate([a[1] for a in augmented]))


def _count_holds(rows: np.ndarray, data: Prepared) -> int:
    """How many presses the synthetic-hold ``rows`` (of :func:`_synthetic_holds`) hold."""
    if not rows.size:
        return 0
    pids = np.concatenate([np.asarray(r.ds.press_id) for r in data.recordings])
    rec = np.searchsorted(np.cumsum([len(r.ds) for r in data.recordings]), rows, side="right")
    return int(np.unique(np.column_stack([rec, pids[rows]]), axis=0).shape[0])


def _subsample_presses(data: Prepared, rows: np.ndarray, fraction: float,
                       rng: np.random.Generator) -> np.ndarray:
    """Keep a random ``fraction`` of the presses among ``rows`` (whole presses, per recording)."""
    keep = []
    for r, sl in data.recording_slices():
        sel = rows[(rows >= sl.start) & (rows < sl.stop)]
        pid = np.asarray(r.ds.press_id)[sel - sl.start]
        presses = np.unique(pid)
        k = max(1, int(round(fraction * presses.size)))
        chosen = rng.choice(presses, size=k, replace=False)
        keep.append(sel[np.isin(pid, chosen)])
    return np.concatenate(keep) if keep else rows[:0]
