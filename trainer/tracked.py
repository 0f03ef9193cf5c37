"""The calibration as the at-rest tracker hands it to the nets.

A fingertip's unloaded zero wanders while it is recorded: each grating drifts on its own,
a residual of the temperature stays, a pad recovers slowly after a release. Over a
calibration log its rests lie a few picometres from the start-up tare, and nets trained on
the log as tared learn every load on top of that log's wander. In use the at-rest tracker
takes the wander out before the nets read a load, so such nets read every load off by the
calibration's mean wander: on the family of fingertips (docs/robustness.md) held grips
read up to 0.4 N low, and the float model read its own training presses 0.15-0.26 N low.

So the trainer runs the tracker over the calibration first, as the runtime will run it,
and the nets learn the recordings as the tracker hands them on (:func:`tracked_dataset`):
each strain grating's wavelength less the tracker's correction at that sample. The tracker
reads only the contact decision, so a contact net and decision fitted for the purpose drive
it (:func:`tracker_model`); the nets of the model are then trained on the tracked
recordings from the start.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from fbgforce import contract
from fbgforce.model import artifact, floatref
from fbgforce.trainer.fit_nets import Scaling


def tracker_model(pre: artifact.Preprocess, contact: artifact.MLP, in_use: artifact.InUse,
                  scaling: Scaling, input_range: np.ndarray, baseline_nm: np.ndarray
                  ) -> artifact.HierarchicalModel:
    """The model that drives the tracker over a calibration: the front, filter and memory
    stages of ``pre``, the ``contact`` net and the decision over time of ``in_use``. Its force
    and location nets read 0 and the settled-hold gain is off: the tracker never reads them."""
    mem = pre.memory
    zero = {net.name: artifact.MLP(
        [np.zeros((net.float_outputs, contract.net_inputs(net.name, mem.n_states, mem.n_loc)))],
        [np.zeros(net.float_outputs)]) for net in contract.NETS if net.name != "contact"}
    model = artifact.HierarchicalModel(
        preprocess=pre, contact=contact, force=zero["force"], location=zero["location"],
        force_offset=scaling.force_offset, force_scale=scaling.force_scale,
        xy_offset=scaling.xy_offset, xy_scale=scaling.xy_scale, baseline_nm=baseline_nm,
        input_range=input_range)
    model.in_use = dataclasses.replace(in_use, hold_gain=0.0)
    return model


def tracker_drift_nm(model: artifact.HierarchicalModel, ds: Any, tare_nm: np.ndarray
                     ) -> np.ndarray:
    """(n, 4) how far the tracker of ``model`` has moved each strain grating's baseline from
    the tare ``tare_nm`` at each sample of the recording ``ds``, nm."""
    tare = np.asarray(tare_nm, dtype=np.float64)
    held = floatref.tracked_baselines(model, np.asarray(ds.wl_nm, dtype=np.float64), tare)
    return held[:, :artifact.N_STRAIN] - tare[:artifact.N_STRAIN]


def tracked_dataset(ds: Any, drift_nm: np.ndarray) -> Any:
    """The recording ``ds`` as the tracker hands it on: the strain gratings' wavelengths less
    its correction ``drift_nm`` (n, 4); the temperature grating and the labels as they were."""
    wl = np.array(ds.wl_nm, dtype=np.float64)
    wl[:, :artifact.N_STRAIN] -= drift_nm
    return dataclasses.replace(ds, wl_nm=wl)


def drift_summary(drifts_nm: Sequence[np.ndarray]) -> dict[str, Any]:
    """What ``model.json`` records of the tracker's corrections over the calibration
    (``metadata.tracked_calibration``): per recording, per strain grating, the mean and the
    largest magnitude, pm."""
    return {"recordings": [{"mean_pm": np.round(1000.0 * d.mean(axis=0), 3).tolist(),
                            "max_abs_pm": np.round(1000.0 * np.abs(d).max(axis=0), 3).tolist()}
                           for d in drifts_nm]}
