"""The float model scored on prepared calibration data (:func:`evaluate_rows`): what the
trainer records in ``metadata.metrics`` and the reports and benchmarks compare; scoring a
model directory with any engine is :mod:`fbgforce.trainer.evaluate`."""
from __future__ import annotations

from typing import Any

import numpy as np

from fbgforce.evaluation import metrics as fmetrics
from fbgforce.model import artifact, floatref
from fbgforce.geometry import PAD_SIZE_MM
from fbgforce.trainer.data import Prepared


def pad_extent_mm(x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[float, float]:
    """Pad size (x, y) for the boundary metrics: the nominal 21 x 27 mm design, or larger where
    the calibration data touched locations beyond it (another gripper's pad)."""
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
    own tare as ``fbgforce evaluate`` runs it (as recorded, not as the tracker handed it to
    the nets): through the decision over time and the at-rest tracker when the model has them
    (:func:`fbgforce.model.floatref.predict`), else on the prepared net inputs (``inputs``, if
    the caller has them: the memory states make them a pass over every recording)."""
    if model.runs_in_use:
        parts = [floatref.predict(model, r.as_recorded.wl_nm, r.baseline_nm)
                 for r in data.recordings]
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
