"""Timers of the engines: the same samples through every engine's single-sample and batch
paths, for :func:`fbgforce.tradeoff.timing.measure`."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from fbgforce.evaluation import engines as fengines
from fbgforce.model import artifact as fm
from fbgforce.tradeoff import timing
from fbgforce.tradeoff.grid import EngineSpec

def c_callables(engine: str, model_dir: Path, model: fm.HierarchicalModel, wl: np.ndarray,
                 base: np.ndarray) -> tuple[Callable[[int], Any], Callable[[int, int], Any]]:
    """Single-sample and batch callables straight onto the C API (``fbg_run``/``fbgf_run``).

    Input is pre-converted to int32 femtometres, the runtime's input unit (what the
    interrogator protocol delivers), and outputs go to a preallocated buffer, so the figure is
    the C pipeline plus one cffi call, not numpy conversions around it.
    """
    from fbgforce._runtime import ffi, lib
    from fbgforce.pybind import FloatRuntime, Runtime, check, to_fm

    if engine == "cfloat":
        rt: Any = FloatRuntime(model)
        run, out_type = lib.fbgf_run, "fbgf_output[]"
    else:
        rt = Runtime(model_dir)
        run, out_type = lib.fbg_run, "fbg_output[]"
    rt.set_baseline(base)
    rows = np.ascontiguousarray(to_fm(wl))
    ptr = ffi.cast("int32_t *", ffi.from_buffer(rows))
    out = ffi.new(out_type, rows.shape[0])
    state = rt._state  # the wrapper's own state; the Python API has no zero-copy batch call
    check(run(state, ptr, min(rows.shape[0], 100), out), f"{engine} run")
    keep = (rt, rows)  # noqa: F841 (the buffers must outlive the lambdas)

    def single(i: int) -> Any:
        return run(state, ptr + 5 * i, 1, out)

    def batch(a: int, b: int) -> Any:
        _ = keep
        return run(state, ptr + 5 * a, b - a, out)

    return single, batch


def timing_samples(ds: Any) -> np.ndarray:
    """The samples every engine is timed on: the first recording's true-contact samples.

    On contact every engine runs all three nets; the C runtime skips the force and location
    nets when it decides "no contact", so timing it over rests would flatter it against the
    engines that always run everything, and would not be the worst case a 1 kHz budget must
    hold. (Gaps between presses are far below the runtime's sensor-fault jump threshold.)
    """
    c = np.asarray(ds.contact, dtype=bool)
    wl = np.asarray(ds.wl_nm, dtype=np.float64)
    return np.ascontiguousarray(wl[c] if c.sum() >= 100 else wl)


def make_timer(spec: EngineSpec, name: str, model_dir: Path, model: fm.HierarchicalModel,
               wl: np.ndarray, base: np.ndarray) -> timing.Timer:
    """Timed callables running the whole pipeline of ``spec`` on recording ``wl``.

    numpy / onnxruntime: single samples through :func:`fbgforce.tradeoff.timing.float_pipeline`,
    batches through the engine function. C: both straight onto the C API (:func:`c_callables`).
    The centred filter cannot stream, so those rows have a batch time only.
    """
    streamable = model.preprocess.filter_kind != "centred"
    if spec.engine in ("float", "onnx"):
        fn = fengines.get_engine(spec.engine)
        single: Callable[[int], Any] | None = None
        if streamable:
            pipe = timing.float_pipeline(model, base, "numpy" if spec.engine == "float" else "onnx",
                                         model_dir)
            single = lambda i: pipe.push(wl[i])  # noqa: E731
        return timing.Timer(name, single=single,
                            batch=lambda a, b: fn(model_dir, model, wl[a:b], base))
    single_c, batch_c = c_callables(spec.engine, model_dir, model, wl, base)
    return timing.Timer(name, single=single_c, batch=batch_c)
