"""Inference engines behind one signature, so every command can score any of them alike.

An engine runs the whole shipped pipeline on ONE continuous recording::

    fn(model_dir, model, wl_nm (n, 5) nm, baseline_nm (5,) nm) -> dict

and returns the keys of :func:`fbgforce.model.predict_from_features` that the metrics need:
``contact`` (bool), ``p_contact``, ``force_N`` (0 where no contact), ``x_mm``, ``y_mm`` (NaN
where no contact). ``model_dir`` is the model directory (engines that need exported files read
them from there); ``model`` the loaded :class:`fbgforce.model.HierarchicalModel`.

Every engine runs the float model's stages after the nets (the decision over time, the
settled-hold gain, the at-rest tracker) and gives its outputs within the engine's tolerance
(docs/export-onnx.md, "Every engine against the float model"; tests/test_engine_agreement.py).

Engines other than ``float`` live in the parts that own their runtimes and are imported lazily
from :data:`ENGINES`, so this module works (and says clearly what is missing) before they exist.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fbgforce import model as fm
from fbgforce import samples
from fbgforce.errors import InputError

EngineFn = Callable[[Any, fm.HierarchicalModel, np.ndarray, np.ndarray], dict[str, np.ndarray]]

#: Engine name -> "module:function". ``float`` is the float64 numpy reference below.
ENGINES: dict[str, str] = {
    "float": "fbgforce.engines:run_float",
    "onnx": "fbgforce.export.onnx_export:run_recording",
    "fixed": "fbgforce.pybind.engines:run_fixed",
    "cfloat": "fbgforce.pybind.engines:run_cfloat",
    "intref": "fbgforce.export.intref:run_recording",
}


def run_float(model_dir: str | Path | None, model: fm.HierarchicalModel, wl_nm: np.ndarray,
              baseline_nm: np.ndarray) -> dict[str, np.ndarray]:
    """The float64 reference: :func:`fbgforce.model.predict` with the given tare baseline."""
    return fm.predict(model, wl_nm, baseline_nm)


def get_engine(engine: str) -> EngineFn:
    """Look up an engine function by name.

    Raises
    ------
    InputError
        For an unknown name, or an engine whose module is not installed or built yet.
    """
    target = ENGINES.get(engine)
    if target is None:
        raise InputError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}",
                         column="--engine")
    module_name, func_name = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise InputError(f"engine {engine!r} is not available ({module_name} cannot be imported: "
                         f"{exc}); build or install that part first", column="--engine") from exc
    fn = getattr(module, func_name, None)
    if fn is None:
        raise InputError(f"engine {engine!r} is not available ({module_name} has no "
                         f"{func_name})", column="--engine")
    return fn


def available() -> dict[str, bool]:
    """Which engines can be used right now (importable), by name."""
    out = {}
    for name in ENGINES:
        try:
            get_engine(name)
            out[name] = True
        except InputError:
            out[name] = False
    return out


def run_engine(engine: str, model_dir: str | Path | None, model: fm.HierarchicalModel | None,
               wl_nm: np.ndarray, baseline_nm: np.ndarray) -> dict[str, np.ndarray]:
    """Run ``engine`` on one continuous recording, tared with ``baseline_nm``.

    Parameters
    ----------
    engine
        A key of :data:`ENGINES`.
    model_dir
        Model directory (needed by engines that read exported artifacts; may be None for
        ``float`` when ``model`` is given).
    model
        The loaded model; loaded from ``model_dir`` when None.
    wl_nm
        (n, 5) wavelengths of gratings 1..4 and T, nm, one continuous recording.
    baseline_nm
        (5,) unloaded wavelengths to tare against (see ``fbgforce.tare.tare``).

    Returns
    -------
    dict
        ``contact``, ``p_contact``, ``force_N``, ``x_mm``, ``y_mm`` (n,) and whatever else the
        engine adds.
    """
    fn = get_engine(engine)
    if model is None:
        if model_dir is None:
            raise InputError("run_engine needs a model or a model directory")
        model = fm.load(model_dir)
    wl = samples.wavelength_array(wl_nm, name="wl_nm")
    base = np.asarray(baseline_nm, dtype=np.float64).reshape(fm.N_STRAIN + 1)
    out = fn(model_dir, model, wl, base)
    out["contact"] = np.asarray(out["contact"]).astype(bool)
    return out
