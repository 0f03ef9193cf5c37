"""Engines ``fixed`` (C fixed point) and ``cfloat`` (C float build) for fbgforce.evaluation.engines.

Signature of every engine: ``(model_dir, model, wl_nm (n, 5), baseline_nm (5,)) -> dict`` with
``contact`` (bool), ``p_contact``, ``force_N`` (0 where no contact), ``x_mm``/``y_mm`` (NaN where
no contact), plus ``status`` (the runtime's flags).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fbgforce import contract
from fbgforce.model import artifact, modeldir
from fbgforce.pybind import FloatRuntime, Runtime


def _as_dict(out: np.ndarray) -> dict[str, np.ndarray]:
    return {k: np.asarray(out[k]) for k in ("contact", "p_contact", "force_N", "x_mm", "y_mm", "status")}


def run_fixed(model_dir: str | Path, model: artifact.HierarchicalModel | None, wl_nm: np.ndarray,
              baseline_nm: np.ndarray) -> dict[str, Any]:
    """The fixed-point C runtime on ``model_dir/model.fbgm`` (run ``fbgforce export`` first)."""
    rt = Runtime(model_dir, float_model=model)
    rt.set_baseline(np.asarray(baseline_nm, dtype=np.float64))
    return _as_dict(rt.run(np.asarray(wl_nm, dtype=np.float64)))


def run_cfloat(model_dir: str | Path | None, model: artifact.HierarchicalModel | None, wl_nm: np.ndarray,
               baseline_nm: np.ndarray) -> dict[str, Any]:
    """The C float build on the float weights (fault/overload thresholds from the blob if any)."""
    thresholds: dict[str, Any] = {}
    if model_dir is not None and (Path(model_dir) / contract.BLOB_FILE).is_file():
        thresholds = Runtime(model_dir, float_model=model).fault_thresholds
    m = modeldir.load(model_dir) if model is None else model
    rt = FloatRuntime(m, **thresholds)
    rt.set_baseline(np.asarray(baseline_nm, dtype=np.float64))
    return _as_dict(rt.run(np.asarray(wl_nm, dtype=np.float64)))
