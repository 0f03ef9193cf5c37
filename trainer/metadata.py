"""What ``model.json`` records of a training (:func:`model_metadata`): the data, the split,
the sizes, the corrections beyond the nets and why (:func:`corrections`), the metrics."""
from __future__ import annotations

import platform
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from fbgforce import __version__
from fbgforce.evaluation import metrics as fmetrics
from fbgforce.model import artifact as fm
from fbgforce.model.decision import REST_EXTEND_MINUTES
from fbgforce.trainer import preprocess as pp
from fbgforce.trainer.creep import Creep
from fbgforce.trainer.data import (HOLD_BAND, HOLD_MIN_S, SPLIT_RATIOS, Prepared, count_presses,
                                   hold_seconds)
from fbgforce.trainer.hold_gain import HOLD_GAIN_MIN_HOLDS
from fbgforce.trainer.params import TrainParams
from fbgforce.trainer.scoring import evaluate_rows, pad_extent_mm
from fbgforce.trainer.synthetic import (HOLD_AUGMENT_S, IDLE_MINUTES, REST_AUGMENT_S,
                                        REST_AUGMENT_STEP_S, Held)


def training_warnings(data: Prepared, pre: fm.Preprocess, tr: np.ndarray, te: np.ndarray,
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


def corrections(model: fm.HierarchicalModel, data: Prepared, params: TrainParams,
                settled: Mapping[str, Any], tracking: Mapping[str, Any] | None = None
                ) -> list[dict[str, Any]]:
    """Each correction beyond the nets the model makes, whether it is on, and why: what
    ``fbgforce train`` prints and ``model.json`` records (``metadata.corrections``)."""
    iu, pre = model.in_use, model.preprocess
    evidence = data.creep_evidence or {}
    creep = data.creep_fit or Creep()
    how = ("taken out before the filter" if pre.creep else
           "discounted by the at-rest tracker" if iu.track_creep else "carried by the holds")
    holds = params.hold_augment > 0 and model.preprocess.memory.n_states > 0
    friction = {"release_holds": (data.release_holds or {}, "on the releases"),
                "wander_holds": (data.wander_holds or {}, "wandering")}
    return [
        {"name": "temperature_coefficients",
         "applied": bool(np.any(np.asarray(data.temp_info.get("temp_coeff_identified", [0.0]))
                                > 0.0)),
         "why": _temperature_why(pre.temp_coeff, data.temp_info)},
        {"name": "creep", "applied": bool(creep.magnitude > 0),
         "why": (f"{100 * creep.magnitude:.1f} % over {creep.time_constant_s:.2g} s, {how}: "
                 if creep.magnitude > 0 else "") + evidence.get("why", "not fitted")},
        {"name": "synthetic_holds", "applied": holds,
         "why": (f"{100 * params.hold_augment:g} % of the presses held {HOLD_AUGMENT_S[0]:g}-"
                 f"{HOLD_AUGMENT_S[1]:g} s" + (", creeping as fitted" if creep.magnitude > 0
                                              else ", flat (no creep established)"))
         if holds else "--hold-augment 0 or a memoryless model"},
        *({"name": name, "applied": bool(holds and choice.get("applied")),
           "why": (f"{choice['why']}; the force net saw {choice['samples']['train']} held "
                   f"samples {where}" if choice.get("applied") else
                   choice.get("why", "no synthetic holds")) if holds else "no synthetic holds"}
          for name, (choice, where) in friction.items()),
        {"name": "settled_hold_gain", "applied": bool(iu.hold_gain),
         "why": (f"{iu.hold_gain:+.4f}, the nets' gain on {settled.get('holds', 0)} held-out "
                 f"synthetic holds, once the force has stood within {iu.hold_band_N:.2g} N "
                 f"({fm.HOLD_BAND_NOISE:g} times the nets' {settled.get('noise_N') or 0.0:.2g} N "
                 f"scatter there, at least {fm.HOLD_BAND_N:g} N) or {100 * iu.hold_band_frac:g} % "
                 f"for {iu.hold_settle} samples" if iu.hold_gain else
                 f"off: {settled.get('holds', 0)} synthetic holds to measure it on (at least "
                 f"{HOLD_GAIN_MIN_HOLDS} needed)" if not settled.get("gain") else "off")},
        {"name": "turn_guard", "applied": bool(params.turn_guard_s),
         "why": f"{1000 * params.turn_guard_s:g} ms after each turn left out of the force net"
         if params.turn_guard_s else "by default only with the creep inverse"},
        {"name": "decision_over_time", "applied": not iu.per_sample,
         "why": (f"CUSUM rise, threshold {iu.contact_cusum_h:.3g} over a drift of "
                 f"{iu.contact_cusum_k:.3g}: the threshold from the calibration's rests and "
                 f"synthetic long rests, each extended to {REST_EXTEND_MINUTES:g} minutes, "
                 + (f"and from {params.idle_pads} idle pads of {IDLE_MINUTES:g} minutes each; "
                    if params.idle_pads else "and no idle pads (--idle-pads 0); ")
                 + "the drift where the calibration's presses rise soonest"
                 if iu.contact_cusum_h else
                 f"Schmitt trigger at a margin of {iu.contact_on_margin:.3g} for "
                 f"{iu.contact_rise_samples} samples, from the rests")
         if not iu.per_sample else "per sample: the calibration's rests set no threshold above 0"},
        {"name": "at_rest_tracker", "applied": bool(iu.track_shift),
         "why": f"time constant 2^{iu.track_shift} samples, at most "
                f"{iu.track_limit_pm:g} pm" if iu.track_shift else "off"},
        {"name": "tracked_calibration", "applied": tracking is not None,
         "why": _tracking_why(tracking) if tracking is not None
         else "off: the nets learned the recordings as tared ("
         + ("the model runs no tracker)" if params.track_calibration
            else "--track-calibration off)")},
    ]


def _temperature_why(coeff: np.ndarray, info: Mapping[str, Any]) -> str:
    """One line on the strain gratings' temperature coefficients and the span that set them
    (:func:`fbgforce.trainer.preprocess.fit_temp_coeff`)."""
    span = float(info.get("temp_ref_range_pm") or 0.0)
    return (f"{', '.join(f'{k:.3f}' for k in coeff)} against the reference: fitted only from "
            f"rests whose temperature spans {pp.TEMP_MIN_SPAN_PM:g} pm or more (these span "
            f"{span:.0f} pm), else 1, the reference subtracted as it is and the at-rest "
            f"tracker carrying the difference")


def _tracking_why(tracking: Mapping[str, Any]) -> str:
    """One line on the tracker's corrections over the calibration the nets trained on."""
    recs = tracking.get("recordings", [])
    mean = max((abs(v) for r in recs for v in r["mean_pm"]), default=0.0)
    peak = max((v for r in recs for v in r["max_abs_pm"]), default=0.0)
    return (f"the nets learned the calibration as the at-rest tracker hands it on: it moved "
            f"the zero by up to {peak:.1f} pm, {mean:.1f} pm on average on the grating that "
            f"wandered most")


def model_metadata(model: fm.HierarchicalModel, data: Prepared, params: TrainParams,
                   described: Sequence[Mapping[str, Any]],
                   rows: tuple[np.ndarray, np.ndarray, np.ndarray], x_all: np.ndarray,
                   reports: Mapping[str, Any], data_coverage: Any, creep: Creep,
                   holds: tuple[Held, Held, dict[str, Any]], rests: tuple[Held, Held],
                   held_s: float, warnings: list[str], times: tuple[float, float],
                   tracking: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The facts ``model.json`` records: data, split, sizes, training, metrics, times, and
    the tracker's corrections of the calibration (``tracking``,
    :func:`fbgforce.trainer.tracked.drift_summary`; None: the nets learned it as tared)."""
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
        "contact_reads_plays": bool(params.contact_plays),
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
                            "settled_gain": settled,
                            "release": data.release_holds, "wander": data.wander_holds},
        "turn_guard_s": params.turn_guard_s,
        "corrections": corrections(model, data, params, settled, tracking),
        "tracked_calibration": None if tracking is None else dict(tracking),
        "synthetic_rests": {"share": params.rest_augment, "range_s": list(REST_AUGMENT_S),
                            "seconds": {name: REST_AUGMENT_STEP_S * rest[1].size
                                        for name, rest in zip(("train", "val"), rests)}},
        "idle_pads": {"count": params.idle_pads, "minutes": IDLE_MINUTES},
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


def _count_holds(rows: np.ndarray, data: Prepared) -> int:
    """How many presses the synthetic-hold ``rows`` (of
    :func:`~fbgforce.trainer.synthetic.synthetic_holds`) hold."""
    if not rows.size:
        return 0
    pids = np.concatenate([np.asarray(r.ds.press_id) for r in data.recordings])
    rec = np.searchsorted(np.cumsum([len(r.ds) for r in data.recordings]), rows, side="right")
    return int(np.unique(np.column_stack([rec, pids[rows]]), axis=0).shape[0])
