"""Training the hierarchical model (paper §III) from calibration recordings.

``train(datasets, ...)`` fits preprocessing (tare per recording, temperature coefficients,
Gaussian filter, standardisation; :func:`prepare`), splits every recording 8:1:1 BY PRESS
(:mod:`fbgforce.trainer.data`), trains the contact, force and location nets in that order with
Adam and early stopping (:mod:`fbgforce.trainer.fit_nets`), and returns a
:class:`fbgforce.model.artifact.HierarchicalModel` whose metadata records the data (files and sha256),
the seed, the sizes, the validation and test metrics and the times
(:mod:`fbgforce.trainer.metadata`).
"""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from fbgforce import contract
from fbgforce.evaluation import metrics as fmetrics
from fbgforce.model import artifact, modeldir
from fbgforce.recordings import tare as fbgtare
from fbgforce.recordings.stagelog import runs
from fbgforce.errors import InputError
from fbgforce.trainer import preprocess as pp
from fbgforce.trainer import tracked
from fbgforce.trainer.coverage import coverage
from fbgforce.trainer.creep import Creep
from fbgforce.trainer.creep_evidence import creep_choice, takes_creep_out
from fbgforce.trainer.hysteresis import PressLoops, friction_evidence, friction_hold_choice
from fbgforce.trainer.creep_fit import held_creep
from fbgforce.trainer.data import Prepared, Recording, load_datasets, split_rows
from fbgforce.trainer.fit_nets import (TURN_GUARD_S, NetFitter, Scaling, fit_contact, fit_force,
                                       fit_location)
from fbgforce.trainer.hold_gain import hold_gain
from fbgforce.trainer.memory import DEFAULT_MEMORY, fit_memory, memory_time_constant_s, parse_memory
from fbgforce.trainer.metadata import model_metadata, training_warnings
from fbgforce.trainer.nets import FlatMLP, drop_unread_units, predict_batched
from fbgforce.trainer.params import DECISION_RULES, DEFAULT_SIZES, TrainParams
from fbgforce.trainer.synthetic import (REST_AUGMENT_STEP_S, Held, decision_rests, idle_rests,
                                        synthetic_holds, synthetic_rests)


def prepare(datasets: Sequence[Any], *, seed: int = 0, filter: str = "causal",
            sigma: float | None = None, window: int | None = None,
            sources: Sequence[str] | None = None, ref_shift: int | None = None,
            creep_inverse: bool | None = False, memory: artifact.Memory | None = None,
            creep: str = "auto",
            temperature: tuple[np.ndarray, Mapping[str, Any]] | None = None) -> Prepared:
    """Tare, fit temperature coefficients, choose the temperature reference's average
    (:func:`~fbgforce.trainer.preprocess.choose_ref_shift`), fit the pad's creep
    (:func:`~fbgforce.trainer.creep_fit.fit_creep`; with ``creep_inverse`` its inverse runs
    before the filter), filter every recording, split each by press.

    ``creep`` (:data:`~fbgforce.trainer.creep_evidence.CREEP_MODES`): ``auto`` corrects for the
    fitted creep only where the calibration establishes it
    (:func:`~fbgforce.trainer.creep_evidence.creep_evidence`), ``on`` wherever the fit finds
    one, ``off`` never.

    ``creep_inverse`` None lets the creep choose
    (:func:`~fbgforce.trainer.creep_evidence.takes_creep_out`): the inverse when the pad creeps
    more slowly than the longest average of ``memory``, the nets' memory states.

    ``sigma`` is in samples; ``None`` means :data:`~fbgforce.trainer.preprocess.DEFAULT_SIGMA_MS`
    at the recordings' (median) sample rate, i.e. 5 samples at 1 kHz. ``ref_shift``: None
    lets the data choose the reference's average, a number sets it. ``temperature``: the
    coefficients and what :func:`~fbgforce.trainer.preprocess.fit_temp_coeff` found, taken
    as they are instead of fitted (the calibration as the tracker hands it on: its zero was
    read through the coefficients fitted on the recordings as tared, and has taken out part
    of what a fit would read as temperature).
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
    if temperature is None:
        coeff, temp_info = pp.fit_temp_coeff([r.shift_pm for r in recs], masks, rate_hz=rate)
    else:
        coeff, temp_info = np.asarray(temperature[0], dtype=np.float64), dict(temperature[1])
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
    held = held_creep(data, pre, fitted)
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


def _sizes(sizes: Mapping[str, Sequence[int]] | None, memory: artifact.Memory) -> dict[str, list[int]]:
    """Every net's layer sizes: its inputs under ``memory``, the hidden widths
    (:data:`~fbgforce.trainer.params.DEFAULT_SIZES`, ``sizes`` over them) and its outputs."""
    hidden = {k: list(v) for k, v in DEFAULT_SIZES.items()}
    for k, v in (sizes or {}).items():     # checked by TrainParams (_valid_sizes)
        hidden[k] = [int(s) for s in v]
    return {net.name: [contract.net_inputs(net.name, memory.n_states, memory.n_loc), *hidden[net.name],
                       net.float_outputs] for net in contract.NETS}


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
    decision_rests: np.random.Generator
    idle_rests: np.random.Generator
    release_holds: np.random.Generator
    wander_holds: np.random.Generator

    @classmethod
    def from_seed(cls, seed: int) -> "_Streams":
        # spawn(n)'s first children do not depend on n: a stream added last leaves the others.
        return cls(*(np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(13)))


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


def _scaling(data: Prepared, tr: np.ndarray, init_model: artifact.HierarchicalModel | None) -> Scaling:
    """The ``init`` model's scaling (its weights keep their meaning), else fitted on the
    training rows' contact samples."""
    if init_model is not None:
        return Scaling(pp.Standardisation(init_model.preprocess.input_mean,
                                           init_model.preprocess.input_std),
                       init_model.force_offset, init_model.force_scale,
                       init_model.xy_offset, init_model.xy_scale)
    ctr = tr[data.contact[tr]]
    xy = np.column_stack([data.x_mm[ctr], data.y_mm[ctr]])
    return Scaling(pp.Standardisation.fit(data.feats[tr]), float(np.mean(data.force_N[ctr])),
                   float(max(np.std(data.force_N[ctr]), 1e-6)), np.nanmean(xy, axis=0),
                   np.maximum(np.nanstd(xy, axis=0), 1e-6))


def _model_preprocess(data: Prepared, scaling: Scaling, init_model: artifact.HierarchicalModel | None,
                      memory: artifact.Memory, tr: np.ndarray) -> artifact.Preprocess:
    """The model's preprocessing: the prepared filter with this model's standardisation and
    memory (the ``init`` model's, else fitted on the training rows)."""
    pre = copy.deepcopy(data.pre)  # a shared Prepared must not see this model's scaling
    pre.input_mean, pre.input_std = scaling.std.mean, scaling.std.std
    pre.memory = init_model.preprocess.memory if init_model is not None \
        else fit_memory(memory, pre, data, tr)
    return pre


def _holds(data: Prepared, pre: artifact.Preprocess, params: TrainParams, tr: np.ndarray,
           va: np.ndarray, creep: Creep, rng: np.random.Generator) -> tuple[Held, Held]:
    """Synthetic holds for the nets that read the load's memory, of the training and the
    validation presses alike (so early stopping and the choice among restarts weigh them
    too), the pad creeping through them as ``creep`` says: ``(inputs, rows)`` of each."""
    no_holds = (np.empty((0, pre.n_inputs)), tr[:0])
    on = params.hold_augment > 0 and pre.memory.n_states
    hold_tr, hold_va = (synthetic_holds(data, pre, rows, params.hold_augment, creep, rng)
                        if on else no_holds for rows in (tr, va))
    return hold_tr, hold_va


def _friction_holds(data: Prepared, pre: artifact.Preprocess, params: TrainParams,
                    tr: np.ndarray, creep: Creep, streams: _Streams) -> Held:
    """Synthetic holds of the training presses ``tr`` for the force net alone, where
    :func:`~fbgforce.trainer.hysteresis.friction_hold_choice` applies them: as many again on
    the releases (``params.release_holds``) and as many wandering
    (``params.wander_holds``), ``(inputs, rows)`` of both. Each choice and how many held
    samples it gave are kept in ``data.release_holds`` and ``data.wander_holds``.

    Not for the contact net: the holds at the peaks already show it a load standing still,
    and its decision's threshold and onset are set on what it reads. Not for validation: the
    force net is validated on the recorded presses alone (:func:`fit_force`)."""
    none = (np.empty((0, pre.n_inputs)), tr[:0])
    if not (params.hold_augment > 0 and pre.memory.n_states):
        return none
    # Read once for both kinds; "on" still reports what the calibration shows.
    evidence = (friction_evidence(PressLoops.of(data, pre, tr), params.seed)
                if {params.release_holds, params.wander_holds} != {"off"} else None)
    made = []
    for kind, mode, option, rng in (
            ("release", params.release_holds, "--release-holds", streams.release_holds),
            ("wander", params.wander_holds, "--wander-holds", streams.wander_holds)):
        choice = friction_hold_choice(data, pre, tr, mode, params.seed, option, evidence)
        held = (synthetic_holds(data, pre, tr, params.hold_augment, creep, rng,
                                on_release=kind == "release", wander=kind == "wander")
                if choice["applied"] else none)
        setattr(data, f"{kind}_holds", {**choice, "samples": {"train": int(held[1].size)}})
        made.append(held)
    return _joined(*made)


def _rests(data: Prepared, pre: artifact.Preprocess, params: TrainParams, tr: np.ndarray,
           va: np.ndarray, rng: np.random.Generator) -> tuple[Held, Held]:
    """Synthetic long rests of the training and the validation presses: ``(inputs, rows)``
    of each."""
    if params.rest_augment <= 0:
        return (np.empty((0, pre.n_inputs)), tr[:0]), (np.empty((0, pre.n_inputs)), va[:0])
    step = max(1, int(round(REST_AUGMENT_STEP_S * data.rate_hz)))
    rest_tr, rest_va = (synthetic_rests(data, pre, rows, params.rest_augment, step, rng)
                        for rows in (tr, va))
    return rest_tr, rest_va


def _joined(*augmented: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Synthetic samples (inputs, rows) of several kinds, one after the other."""
    return (np.concatenate([a[0] for a in augmented]),
            np.concatenate([a[1] for a in augmented]))


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


def _assemble(data: Prepared, pre: artifact.Preprocess, scaling: Scaling,
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
        [(np.asarray(r.as_recorded.wl_nm, dtype=np.float64), r.baseline_nm)
         for r in data.recordings],
        [np.asarray(r.ds.force_N, dtype=np.float64)[np.asarray(r.ds.contact, dtype=bool)]
         for r in data.recordings], [d.get("path") or r.source for d, r in zip(described, data.recordings)])
    return model


#: The window of each calibration press the CUSUM's drift is chosen on (:func:`_press_windows`):
#: from this long before its first labelled contact sample, where the sum is back at 0 but for
#: rare excursions, ...
ONSET_LEAD_S = 0.1
#: ... to this long after it: longer than any onset the goals allow, and what a press that
#: never rises counts.
ONSET_WINDOW_S = 0.1


def _press_windows(data: Prepared, logits: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """The contact net's margins around each training and validation press's first labelled
    contact sample, for the CUSUM's drift (:func:`fbgforce.model.decision.mean_onset_samples`):
    from :data:`ONSET_LEAD_S` before it (no nearer than ``REST_GAP_S`` to the previous
    press's contact, past the filter's warm-up) to :data:`ONSET_WINDOW_S` after it, with its
    index in the window."""
    margin = logits[:, 1] - logits[:, 0]
    lead = max(1, int(round(ONSET_LEAD_S * data.rate_hz)))
    after = max(1, int(round(ONSET_WINDOW_S * data.rate_hz)))
    gap = max(1, int(round(fmetrics.REST_GAP_S * data.rate_hz)))
    windows = []
    for _, sl in data.recording_slices():
        firsts, stops = runs(data.contact[sl])
        for first in firsts:
            if data.split[sl.start + first] == 2:
                continue
            before = stops[stops <= first]
            start = max(first - lead, int(before[-1]) - 1 + gap if before.size else 0,
                        data.pre.taps.size)
            if start < first:
                windows.append((margin[sl][start:first + after], int(first - start)))
    return windows


#: Quantiles of the contact net's margin at rest that ``model.json`` records for the rests the
#: decision's threshold was read on (``decision_rests``), to set beside a pad's real long rests
#: (``python -m fbgforce.bench.bench_decision_rests``).
DECISION_REST_QUANTILES = (0.999, 0.9999)


def _margin_quantiles(margins: np.ndarray, rate_hz: float) -> dict[str, Any]:
    """The minutes of ``margins`` and their :data:`DECISION_REST_QUANTILES` (None without)."""
    return {"minutes": margins.size / rate_hz / 60.0,
            "margin_quantiles": {f"{100 * q:g}": float(np.quantile(margins, q))
                                 if margins.size else None for q in DECISION_REST_QUANTILES}}


def _decision_rules(data: Prepared, pre: artifact.Preprocess, logits: np.ndarray,
                    cnet: FlatMLP, rests: tuple[Held, Held], settled: Mapping[str, Any],
                    streams: _Streams, idle_pads: int
                    ) -> tuple[dict[str, artifact.InUse], dict[str, Any]]:
    """The in-use stages each rule of :data:`~fbgforce.trainer.params.DECISION_RULES` would
    set from the training data: its decision over time, the tracker and the settled-hold
    gain with its steadiness band (``settled``, what
    :func:`~fbgforce.trainer.hold_gain.hold_gain` measured; empty: the stage off); and what
    the rests the CUSUM's threshold was read on hold (``calibration`` and ``long`` rests, each
    :func:`_margin_quantiles`).

    The decision's thresholds weigh every sample at rest, the synthetic long rests'
    included: the calibration's own rests end within a second of a release, before the
    memory settles. The CUSUM reads its threshold on the calibration's rests, on long rests
    of its own (:func:`~fbgforce.trainer.synthetic.decision_rests`) and on ``idle_pads``
    idle pads (:func:`~fbgforce.trainer.synthetic.idle_rests`), drawn with
    ``streams``, and its drift on the calibration's presses (:func:`_press_windows`). The tracker
    discounts the recovery the pad's creep (``data.creep_held``) predicts after a release,
    which it would otherwise learn as drift (docs/runtime.md, "In use"), unless the creep
    inverse has already taken it out."""
    rested = np.concatenate([rests[0][0], rests[1][0]])[:, :pre.n_features]
    long = predict_batched(cnet, rested) if len(rested) else np.empty((0, 2))
    left = Creep() if pre.creep else data.creep_held
    calibration_rests = _rest_margins(data, logits)
    # The Schmitt trigger's threshold weighs the synthetic long rests too; the CUSUM's false
    # events are estimated from excursions in time order, on the recordings' own rests and on
    # long rests whose every sample is kept, which the training's sparse samples are not.
    rest_margins = {"schmitt": np.concatenate([calibration_rests, long[:, 1] - long[:, 0]]),
                    "cusum": calibration_rests}
    rows = np.flatnonzero(data.split != 2)
    inputs = decision_rests(data, pre, rows, streams.decision_rests)
    lg = predict_batched(cnet, inputs[:, :pre.n_features]) if len(inputs) else np.empty((0, 2))
    idle = [np.diff(predict_batched(cnet, x), axis=1).ravel()
            for x in idle_rests(data, pre, rows, streams.idle_rests, idle_pads)]
    cusum = {"long_rests": lg[:, 1] - lg[:, 0], "presses": _press_windows(data, logits),
             "idle": idle}
    rules = {rule: artifact.InUse.recommended(
        data.rate_hz, rest_margins=rest_margins[rule], creep_magnitude=left.magnitude,
        creep_time_constant_samples=left.time_constant_s * data.rate_hz,
        hold_gain=settled.get("gain", 0.0), hold_noise_N=settled.get("noise_N") or 0.0,
        decision=rule, **(cusum if rule == "cusum" else {})) for rule in DECISION_RULES}
    return rules, {"calibration": _margin_quantiles(calibration_rests, data.rate_hz),
                   "long": _margin_quantiles(cusum["long_rests"], data.rate_hz)}


def _in_use(model: artifact.HierarchicalModel, data: Prepared, stage: "_ContactStage",
            settled: Mapping[str, Any], decision: str, idle_pads: int
            ) -> tuple[dict[str, dict[str, Any]], dict[str, Any]]:
    """Set the model's in-use stages (:func:`_decision_rules`, by the rule ``decision``, with
    ``idle_pads`` idle pads) and
    input range from the training data; return the decision's fields of every rule
    (``metadata.decision_rules``: what the others would have set) and what its rests hold
    (``metadata.decision_rests``)."""
    rules, rested = _decision_rules(data, model.preprocess, stage.logits, stage.cnet,
                                    (stage.rest_tr, stage.rest_va), settled, stage.streams,
                                    idle_pads)
    model.in_use = rules[decision]
    model.input_range = artifact.input_range_of(stage.z[stage.tr])
    return ({rule: {k: v for k, v in iu.to_json().items() if k.startswith("contact_")}
             for rule, iu in rules.items()}, rested)


def _asked(params: TrainParams | None, options: Mapping[str, Any]) -> TrainParams:
    """The parameters :func:`train` is asked for: ``params`` (every default when None) with
    the fields ``options`` names one by one over them; an unknown name is a ``TypeError``."""
    unknown = sorted(set(options) - {f.name for f in fields(TrainParams)})
    if unknown:
        raise TypeError(f"train() got unknown parameters: {', '.join(unknown)}")
    return replace(params or TrainParams(), **options)


def _prepared(ds_list: Sequence[Any], described: Sequence[Mapping[str, Any]],
              params: TrainParams, memory: artifact.Memory,
              temperature: tuple[np.ndarray, Mapping[str, Any]] | None = None) -> Prepared:
    """The recordings prepared as ``params`` asks (:func:`prepare`; ``temperature`` as it
    takes it), each named by its path or source in the tare's messages."""
    sources = [d.get("path") or d.get("source") or f"recording {i}"
               for i, d in enumerate(described)]
    return prepare(ds_list, seed=params.seed, filter=params.filter, sigma=params.sigma,
                   window=params.window, sources=sources, ref_shift=params.ref_shift,
                   creep_inverse=params.creep_inverse, memory=memory, creep=params.creep,
                   temperature=temperature)


def _creep_of_prepared(data: Prepared, pre: artifact.Preprocess, tr: np.ndarray,
                       params: TrainParams) -> Creep:
    """The creep the synthetic holds carry (:attr:`~fbgforce.trainer.data.Prepared.creep`); for
    a :class:`~fbgforce.trainer.data.Prepared` made without :func:`prepare`, chosen first on the
    training rows ``tr`` (:func:`~fbgforce.trainer.creep_evidence.creep_choice`)."""
    if data.creep_fit is None:
        data.creep_found, data.creep_evidence = creep_choice(data, pre, tr, params.creep,
                                                             params.seed)
        data.creep_fit = data.creep_found if data.creep_evidence["applied"] else Creep()
        data.creep_held = held_creep(data, pre, data.creep_fit)
    return data.creep


def _settled_gain(model: artifact.HierarchicalModel, data: Prepared, pre: artifact.Preprocess,
                  rows: np.ndarray, creep: Creep, trained_holds: bool,
                  rng: np.random.Generator) -> dict[str, Any]:
    """The settled-hold gain (:func:`~fbgforce.trainer.hold_gain.hold_gain`), measured when
    the nets trained on synthetic holds (``trained_holds``) on holds of every press among
    ``rows`` drawn apart from those: the nets fit the ones they trained on, and would promise
    too little."""
    return hold_gain(model, data, [synthetic_holds(data, pre, np.sort(rows), 1.0, creep, rng)]
                     if trained_holds else [])


def train(datasets: Sequence[Any], params: TrainParams | None = None, *,
          prepared: Prepared | None = None, **options: Any) -> artifact.HierarchicalModel:
    """Train the hierarchical model on calibration recordings, step by step: the starting
    point, the prepared data, the split, the scaling and preprocessing, synthetic holds and
    rests, the contact, force and location nets, the model and its metadata.

    Parameters
    ----------
    datasets
        Paths (CSV/npz in the dataset contract) or ``fbgforce.recordings.dataset.Dataset`` objects; each
        one is a continuous recording of one device.
    params
        What to do (:class:`~fbgforce.trainer.params.TrainParams`); default every default.
    prepared
        Reuse the output of :func:`prepare` (same data, filter and seed) to save time.
    **options
        Fields of :class:`~fbgforce.trainer.params.TrainParams` given one by one (over
        ``params``'), e.g. ``train(files, epochs=50, seed=1)``.

    Returns
    -------
    fbgforce.model.artifact.HierarchicalModel

    Raises
    ------
    InputError
        A parameter out of its range (naming the option), or data training cannot use.
    """
    params = _asked(params, options)
    t_start = time.perf_counter()
    ds_list, described = load_datasets(datasets)
    data_coverage = coverage(ds_list)
    init_model, memory, net_sizes = _starting_point(params)
    data = prepared if prepared is not None else _prepared(ds_list, described, params, memory)
    tracking = None
    if params.track_calibration:
        data, tracking = _tracked_calibration(data, described, params, init_model, memory,
                                              net_sizes)
    if params.turn_guard_s is None:
        params = replace(params, turn_guard_s=TURN_GUARD_S if data.pre.creep else 0.0)
    t_prep = time.perf_counter() - t_start
    stage = _contact_stage(data, params, init_model, memory, net_sizes)
    tr, va, te, pre, fit_net = stage.tr, stage.va, stage.te, stage.pre, stage.fit_net
    pred_contact = stage.logits[:, 1] > stage.logits[:, 0]
    friction_tr = _friction_holds(data, pre, params, tr, stage.creep, stage.streams)
    fnet = fit_force(fit_net, data, stage.z, stage.cnet, pred_contact, stage.scaling, tr, va,
                     _joined(stage.synth_tr, friction_tr), stage.streams.force)
    lnet = fit_location(fit_net, data, pre, stage.x_all, pred_contact, fnet, stage.scaling,
                        params, tr, va, stage.streams.location, stage.streams.location_augment)
    warnings, held_s = training_warnings(data, pre, tr, te, stage.hold_tr)
    reports = fit_net.reports
    model = _assemble(data, pre, stage.scaling,
                      {"contact": stage.cnet, "force": fnet, "location": lnet}, reports, described)
    t_train = time.perf_counter() - t_start - t_prep
    settled = _settled_gain(model, data, pre, np.concatenate([tr, va]), stage.creep,
                            bool(stage.hold_tr[1].size), stage.streams.hold_gain)
    rules, rested = _in_use(model, data, stage, settled, params.decision, params.idle_pads)
    model.metadata = model_metadata(model, data, params, described, (tr, va, te), stage.x_all,
                                    reports, data_coverage, stage.creep,
                                    (stage.hold_tr, stage.hold_va, settled),
                                    (stage.rest_tr, stage.rest_va), held_s, warnings,
                                    (t_prep, t_train), tracking)
    model.metadata["decision_rules"] = rules
    model.metadata["decision_rests"] = rested
    return model


@dataclass
class _ContactStage:
    """A training run up to its contact net: the split, the scaling and preprocessing, the
    synthetic holds and rests, the contact net and its logits on every row, and what the
    force and location nets go on with (the fitter, the random streams)."""

    tr: np.ndarray
    va: np.ndarray
    te: np.ndarray
    scaling: Scaling
    pre: artifact.Preprocess
    x_all: np.ndarray
    z: np.ndarray
    fit_net: NetFitter
    streams: _Streams
    creep: Creep
    hold_tr: Held
    hold_va: Held
    rest_tr: Held
    rest_va: Held
    synth_tr: Held
    synth_va: Held
    cnet: FlatMLP
    logits: np.ndarray


def _contact_stage(data: Prepared, params: TrainParams,
                   init_model: artifact.HierarchicalModel | None, memory: artifact.Memory,
                   net_sizes: dict[str, list[int]], desc: str = "contact net") -> _ContactStage:
    """Train on ``data`` as ``params`` asks up to the contact net (:class:`_ContactStage`;
    ``desc`` names the net on the progress bar)."""
    streams = _Streams.from_seed(params.seed)
    tr, va, te = _split(data, params, streams.subsample)
    scaling = _scaling(data, tr, init_model)
    pre = _model_preprocess(data, scaling, init_model, memory, tr)
    x_all = data.inputs(pre)
    z = x_all[:, :pre.n_features]    # what the contact and force nets read
    fit_net = NetFitter(params, net_sizes, init_model, streams.init, bool(va.size))
    creep = _creep_of_prepared(data, pre, tr, params)
    hold_tr, hold_va = _holds(data, pre, params, tr, va, creep, streams.holds)
    rest_tr, rest_va = _rests(data, pre, params, tr, va, streams.rests)
    synth_tr, synth_va = _joined(hold_tr, rest_tr), _joined(hold_va, rest_va)
    cnet, logits = fit_contact(fit_net, data, z, tr, va, synth_tr, synth_va, streams.contact,
                               desc, () if params.contact_plays else pre.memory.columns("play"))
    return _ContactStage(tr, va, te, scaling, pre, x_all, z, fit_net, streams, creep, hold_tr,
                         hold_va, rest_tr, rest_va, synth_tr, synth_va, cnet, logits)


def _tracked_calibration(data: Prepared, described: Sequence[Mapping[str, Any]],
                         params: TrainParams, init_model: artifact.HierarchicalModel | None,
                         memory: artifact.Memory, net_sizes: dict[str, list[int]]
                         ) -> tuple[Prepared, dict[str, Any] | None]:
    """The calibration prepared as the at-rest tracker hands it to the nets
    (:mod:`fbgforce.trainer.tracked`), the tracker driven by a contact net and decision
    trained on ``data`` as tared; and what ``model.json`` records of the tracker's
    corrections. ``data`` itself, and None, for a model that runs no tracker (an offline
    model's centred filter, a decision without one)."""
    if data.pre.filter_kind == "centred":
        return data, None
    t_start = time.perf_counter()
    stage = _contact_stage(data, params, init_model, memory, net_sizes,
                           "the tracker's contact net")
    # Without the idle pads: they guard minutes of unbroken rest, which a calibration never
    # holds, and the tracker's pass over it then finds the rests the calibration itself sets.
    in_use = _decision_rules(data, stage.pre, stage.logits, stage.cnet,
                             (stage.rest_tr, stage.rest_va), {},
                             stage.streams, idle_pads=0)[0][params.decision]
    if not in_use.track_shift:
        return data, None
    model = tracked.tracker_model(stage.pre, stage.cnet.to_mlp(), in_use, stage.scaling,
                                  artifact.input_range_of(stage.z[stage.tr]),
                                  np.median([r.baseline_nm for r in data.recordings], axis=0))
    drifts = [tracked.tracker_drift_nm(model, r.ds, r.baseline_nm) for r in data.recordings]
    summary = tracked.drift_summary(drifts)
    if not any(np.any(d) for d in drifts):    # the tracker never moved: the data as tared
        return data, {**summary, "seconds": time.perf_counter() - t_start}
    seen = _prepared([tracked.tracked_dataset(r.ds, d) for r, d in zip(data.recordings, drifts)],
                     described, params, memory, (data.pre.temp_coeff, data.temp_info))
    for mine, recorded in zip(seen.recordings, data.recordings):
        mine.recorded = recorded.as_recorded
    return seen, {**summary, "seconds": time.perf_counter() - t_start}
