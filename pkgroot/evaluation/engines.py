"""Inference engines behind one signature, so every command can score any of them alike.

An engine runs the whole shipped pipeline on ONE continuous recording::

    fn(model_dir, model, wl_nm (n, 5) nm, baseline_nm (5,) nm) -> dict

and returns the keys of :func:`fbgforce.model.floatref.predict_from_features` that the metrics need:
``contact`` (bool), ``p_contact``, ``force_N`` (0 where no contact), ``x_mm``, ``y_mm`` (NaN
where no contact). ``model_dir`` is the model directory (engines that need exported files read
them from there); ``model`` the loaded :class:`fbgforce.model.artifact.HierarchicalModel`.

Every engine runs the float model's stages after the nets (the decision over time, the
settled-hold gain, the at-rest tracker) and gives its outputs within the engine's tolerance
(docs/export-onnx.md, "Every engine against the float model"; tests/test_engine_agreement.py).

Engines other than ``float`` live in the parts that own their runtimes (the exporter, the
runtime binding), which this module sits above; each is imported when first asked for
(:data:`ENGINES`), so this module works, and says clearly what is missing, before they are
built or installed.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from fbgforce import samples
from fbgforce.errors import InputError
from fbgforce.model import artifact, floatref, modeldir

EngineFn = Callable[[Any, artifact.HierarchicalModel, np.ndarray, np.ndarray],
                    dict[str, np.ndarray]]


def run_float(model_dir: str | Path | None, model: artifact.HierarchicalModel, wl_nm: np.ndarray,
              baseline_nm: np.ndarray) -> dict[str, np.ndarray]:
    """The float64 reference: :func:`fbgforce.model.floatref.predict` with the given tare
    baseline."""
    return floatref.predict(model, wl_nm, baseline_nm)


def _onnx() -> EngineFn:
    from fbgforce.export.onnx_export import run_recording
    return run_recording


def _fixed() -> EngineFn:
    from fbgforce.pybind.engines import run_fixed
    return run_fixed


def _cfloat() -> EngineFn:
    from fbgforce.pybind.engines import run_cfloat
    return run_cfloat


def _intref() -> EngineFn:
    from fbgforce.export.intref import run_recording
    return run_recording


#: Engine name -> its loader (which imports the engine's part; ImportError when that part is not
#: installed or built). ``float`` is the float64 numpy reference above.
ENGINES: dict[str, Callable[[], EngineFn]] = {
    "float": lambda: run_float,
    "onnx": _onnx,
    "fixed": _fixed,
    "cfloat": _cfloat,
    "intref": _intref,
}


def get_engine(engine: str) -> EngineFn:
    """Look up an engine function by name.

    Raises
    ------
    InputError
        For an unknown name, or an engine whose module is not installed or built yet.
    """
    load = ENGINES.get(engine)
    if load is None:
        raise InputError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}",
                         column="--engine")
    try:
        return load()
    except ImportError as exc:
        raise InputError(f"engine {engine!r} is not available ({exc}); build or install that "
                         f"part first", column="--engine") from exc


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


def run_engine(engine: str, model_dir: str | Path | None,
               model: artifact.HierarchicalModel | None, wl_nm: np.ndarray,
               baseline_nm: np.ndarray) -> dict[str, np.ndarray]:
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
        (5,) unloaded wavelengths to tare against (see ``fbgforce.recordings.tare.tare``).

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
        model = modeldir.load(model_dir)
    wl = samples.wavelength_array(wl_nm, name="wl_nm")
    base = np.asarray(baseline_nm, dtype=np.float64).reshape(artifact.N_STRAIN + 1)
    out = fn(model_dir, model, wl, base)
    out["contact"] = np.asarray(out["contact"]).astype(bool)
    return out
