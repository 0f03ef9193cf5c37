"""What accuracy costs in time: a grid of models x engines on one held-out split.

For every trained variant (filter x network width) and every engine that can run it, the
same test presses are scored with :mod:`fbgforce.metrics`, and the cost is measured: host time
per sample (single-sample streaming calls and batches, all engines interleaved in one run,
:mod:`fbgforce.bench.timing`), the filter's delay, multiply-accumulates, model bytes and, when
the Cortex-M4 toolchain is there, instructions per step on target.

Variants
    ``filter``: ``none``, ``causal`` Gaussian at several sigmas (what ships), ``centred`` (the
    paper's offline smoothing, a reference that cannot run in a controller). ``width``: the
    paper's hidden widths, half and quarter. The default ``star`` grid varies the filter at the
    paper width and the width at the shipped filter (7 models); ``full`` is the product.
Engines
    ``numpy-f64`` (fbgforce.model), ``onnx-f32`` (onnxruntime), ``c-float`` (C single
    precision), ``c-int16`` (C fixed point, int16 weights), ``c-int8`` (int8 weights, same
    model), ``c-int8-qat`` (int8 weights after quantization-aware fine-tuning,
    :mod:`fbgforce.trainer.qat`). Engines not built yet are listed with ``status`` "missing".

The reference row is the paper-width model with the shipped causal filter on ``numpy-f64``.
``error_index`` is the geometric mean of four ratios to it (force, x and y RMSE, contact error
rate): 1.0 means the reference's accuracy, 1.1 about 10 % worse. A row ``matches`` the
reference when each RMSE is at most 5 % higher and contact accuracy at most 0.2 points lower.
"""
from __future__ import annotations

import csv
import hashlib
import json
import math
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fbgforce.jsonutil import json_default
from fbgforce import engines as fengines
from fbgforce import metrics as fmetrics
from fbgforce import model as fm
from fbgforce.bench import timing
from fbgforce.errors import InputError

WIDTHS = {"paper": 1.0, "half": 0.5, "quarter": 0.25}
METRIC_KEYS = ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm")
#: "Matches the reference": RMSE at most this factor higher, contact accuracy at most
#: CONTACT_SLACK lower.
MATCH_RMSE_FACTOR = 1.05
CONTACT_SLACK = 0.002
#: Floor on contact error rates in the error index, so a perfect contact net does not divide
#: by zero (0.1 % is below what any engine here distinguishes on a test split).
CONTACT_ERR_FLOOR = 1e-3


@dataclass(frozen=True)
class Variant:
    """One trained model of the grid."""

    filter: str
    sigma: float
    width: str

    @property
    def tag(self) -> str:
        f = "nofilter" if self.filter == "none" else f"{self.filter}-s{self.sigma:g}"
        return f"{self.width}-{f}"

    @property
    def causal(self) -> bool:
        return self.filter != "centred"


@dataclass(frozen=True)
class EngineSpec:
    """An engine column: which ``fbgforce.engines`` engine on which model artifact."""

    name: str
    engine: str
    artifact: str  # "float" (plain model dir), "int8" or "int8-qat" (sibling dirs)
    weight_bits: int | None
    act_bits: int | None
    dtype_bytes: float


ENGINE_SPECS = (
    EngineSpec("numpy-f64", "float", "float", None, None, 8),
    EngineSpec("onnx-f32", "onnx", "float", None, None, 4),
    EngineSpec("c-float", "cfloat", "float", None, None, 4),
    EngineSpec("c-int16", "fixed", "float", 16, 16, 2),
    EngineSpec("c-int8", "fixed", "int8", 8, 16, 1),
    EngineSpec("c-int8-qat", "fixed", "int8-qat", 8, 16, 1),
)


@dataclass
class Settings:
    """Everything that shapes a run (written to tradeoff.json)."""

    seed: int = 0
    epochs: int = 200
    time_budget_s: float | None = None
    sigmas: tuple[float, ...] = (2.0, 5.0, 10.0)
    default_sigma: float = 5.0
    widths: tuple[str, ...] = ("paper", "half", "quarter")
    grid: str = "star"
    centred: bool = True
    qat_epochs: int = 3
    single_calls: int = 3000
    batch_size: int = 2000
    batch_reps: int = 60
    rounds: int = 6
    target: bool = True
    engines: tuple[str, ...] = tuple(s.name for s in ENGINE_SPECS)
    #: Run the int8 engines (export, QAT) on every causal variant, or only on the reference
    #: variant (quick mode: each export costs seconds).
    int8_all_variants: bool = True


def quick_settings(seed: int = 0) -> Settings:
    """Small everything: for CI (< 60 s on a small scene)."""
    return Settings(seed=seed, epochs=4, time_budget_s=5.0, sigmas=(5.0,), widths=("paper", "quarter"),
                    qat_epochs=1, single_calls=300, batch_size=500, batch_reps=15, rounds=3,
                    target=False, int8_all_variants=False)


def variants(s: Settings) -> list[Variant]:
    """The models of the grid (see the module docstring)."""
    filters = [("none", 0.0)] + [("causal", sg) for sg in s.sigmas]
    if s.centred:
        filters.append(("centred", s.default_sigma))
    out: list[Variant] = []
    for kind, sg in filters:
        for w in s.widths:
            star_ok = w == "paper" or (kind == "causal" and sg == s.default_sigma)
            if s.grid == "full" or star_ok:
                out.append(Variant(kind, sg, w))
    return out


def scaled_sizes(width: str) -> dict[str, list[int]]:
    """Hidden widths of every net, the paper's scaled by the width factor (at least 2)."""
    from fbgforce.trainer.train import DEFAULT_SIZES

    f = WIDTHS[width]
    return {k: [max(2, int(round(h * f))) for h in v] for k, v in DEFAULT_SIZES.items()}


# --------------------------------------------------------------------------------------------
# Data, training (or reuse), artifacts
# --------------------------------------------------------------------------------------------

def prepare_data(data: Sequence[str | Path] | None, scene: str | None, out: Path, seed: int,
                 log: Callable[[str], None]) -> list[Path]:
    """Paths of the recordings to use; a scene is simulated once into ``out/data``."""
    if data:
        paths = [Path(p) for p in data]
        for p in paths:
            if not p.is_file():
                raise InputError("no such data file", path=str(p), column="--data")
        return paths
    if not scene:
        raise InputError("give --data FILE or --scene NAME")
    from fbgforce import dataset as fds
    from fbgforce.sim import simulate
    from fbgforce.sim.scene import load_scene

    target = out / "data" / f"{Path(scene).stem}-seed{seed}.npz"
    if not target.is_file():
        load_scene(scene)  # a bad scene fails here, before any progress line
        log(f"simulating scene {scene!r} -> {target}")
        target.parent.mkdir(parents=True, exist_ok=True)
        fds.save(simulate(scene, seed=seed), target)
    return [target]


def _data_digest(paths: Sequence[Path]) -> str:
    from fbgforce.trainer.train import file_sha256

    return hashlib.sha256("".join(file_sha256(p) for p in paths).encode()).hexdigest()[:16]


def _reusable(model_dir: Path, key: dict[str, Any]) -> fm.HierarchicalModel | None:
    marker = model_dir / "tradeoff-key.json"
    try:
        if json.loads(marker.read_text()) == key:
            return fm.load(model_dir)
    except (OSError, ValueError, InputError):
        return None
    return None


def _save_with_key(model: fm.HierarchicalModel, model_dir: Path, key: dict[str, Any]) -> None:
    if model_dir.exists():
        shutil.rmtree(model_dir)
    fm.save(model, model_dir)
    (model_dir / "tradeoff-key.json").write_text(json.dumps(key, indent=1) + "\n")


#: Quantizer calibration uses at most this many samples (whole presses from the start of the
#: first recording): the export's cost grows with it, its scales hardly do.
CALIB_MAX_SAMPLES = 60000


def calibration_subset(ds_list: Sequence[Any], sources: Sequence[str], out: Path) -> list[str]:
    """Files to calibrate the fixed-point export on: the recordings, or a prefix of the first.

    The exporter derives its scales from the ranges the float pipeline reaches on this data;
    the first presses of a calibration protocol cover those ranges already, and exporting with
    all 234k samples costs about five times longer per model for the same scales.
    """
    ds = ds_list[0]
    if sum(len(d) for d in ds_list) <= CALIB_MAX_SAMPLES:
        return list(sources)
    from fbgforce import dataset as fds

    pid = np.asarray(ds.press_id)
    cut = CALIB_MAX_SAMPLES
    # End on a press boundary so no press is cut in half.
    while cut < len(ds) and pid[cut] == pid[cut - 1]:
        cut += 1
    path = out / "data" / f"calib-{Path(sources[0]).stem}-{cut}.npz"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        fds.save(ds.subset(np.arange(cut)), path)
    return [str(path)]


def export_fixed(model_dir: Path, bits: int, calib: Sequence[str]) -> str | None:
    """Write ``model.fbgm`` (and C source) for ``bits``-bit weights; None or the reason it failed.

    Uses the Part 3 exporter (:func:`fbgforce.export.exporter.export_model`), calibrated on the
    recordings of the run (the model's training data).
    """
    try:
        from fbgforce.export.exporter import REPORT_FILE, check_fresh, export_model
    except ImportError as exc:
        return f"exporter not available ({exc})"
    report = model_dir / REPORT_FILE
    try:
        # A rerun over reused models keeps a blob exported from these weights at these bits.
        if (model_dir / "model.fbgm").is_file() and json.loads(report.read_text()).get("bits") == bits:
            check_fresh(model_dir, fm.load(model_dir))
            from fbgforce.pybind import Runtime

            Runtime(model_dir)  # and this runtime still reads it (blob format version)
            return None
    except Exception:  # stale, unreadable or from another blob version: export again
        pass
    try:
        export_model(model_dir, bits=bits, calib=calib)
    except Exception as exc:  # report it in the row, don't abort the whole grid
        return f"export --bits {bits} failed: {type(exc).__name__}: {exc}"
    return None


# --------------------------------------------------------------------------------------------
# Engines: outputs on whole recordings, and timers
# --------------------------------------------------------------------------------------------

def _c_callables(engine: str, model_dir: Path, model: fm.HierarchicalModel, wl: np.ndarray,
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

    numpy / onnxruntime: single samples through :class:`fbgforce.bench.timing.FloatStepper`,
    batches through the engine function. C: both straight onto the C API (:func:`_c_callables`).
    The centred filter cannot stream, so those rows have a batch time only.
    """
    streamable = model.preprocess.filter_kind != "centred"
    if spec.engine in ("float", "onnx"):
        fn = fengines.get_engine(spec.engine)
        single: Callable[[int], Any] | None = None
        if streamable:
            stepper = timing.FloatStepper(model, base, "numpy" if spec.engine == "float" else "onnx",
                                          model_dir)
            single = lambda i: stepper.step(wl[i])  # noqa: E731
        return timing.Timer(name, single=single,
                            batch=lambda a, b: fn(model_dir, model, wl[a:b], base))
    single_c, batch_c = _c_callables(spec.engine, model_dir, model, wl, base)
    return timing.Timer(name, single=single_c, batch=batch_c)


def target_instructions(model_dir: Path, data: Path | None = None, samples: int = 64,
                        timeout_s: float = 300.0) -> dict[str, Any]:
    """Cortex-M4 instruction counts per step from ``fbgforce target-report`` (Part 4).

    Returns ``{"m4_instructions_per_step": worst step of the DSP build (the shipped one),
    "m4_instructions_portable": worst step of the portable C build, "m4_bit_exact": ...}``,
    or ``{"m4_note": why not}`` when the command or its toolchain is missing or fails.
    """
    import subprocess

    from fbgforce.cli import build_parser

    parser = build_parser()
    sub = next((a for a in parser._actions if a.dest == "command"), None)
    if sub is None or "target-report" not in getattr(sub, "choices", {}):
        return {"m4_note": "fbgforce target-report not available"}
    cmd = [sys.executable, "-m", "fbgforce.cli", "target-report", "--model", str(model_dir),
           "--samples", str(samples), "--json"]
    if data is not None:
        cmd += ["--data", str(data)]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"m4_note": "target-report timed out"}
    if r.returncode != 0:
        return {"m4_note": (r.stderr.strip().splitlines() or ["target-report failed"])[-1]}
    try:
        rep = json.loads(r.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"m4_note": "target-report printed no JSON"}
    portable = rep.get("builds", {}).get("portable", {})
    return {"m4_instructions_per_step": rep.get("instructions_per_step"),
            "m4_instructions_portable": portable.get("instructions_per_step"),
            "m4_bit_exact": rep.get("bit_exact"),
            "m4_budget_fraction_at_168MHz": rep.get("budget_fraction_at_168MHz"),
            "m4_flash_bytes": rep.get("flash_bytes")}


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------

def _model_bytes(spec: EngineSpec, model: fm.HierarchicalModel, model_dir: Path) -> int:
    """Bytes of the model as the engine holds it: the blob for C fixed, parameters otherwise."""
    if spec.engine == "fixed":
        blob = model_dir / "model.fbgm"
        if blob.is_file():
            return blob.stat().st_size
    n = sum(w.size + b.size for net in model.nets.values() for w, b in zip(net.weights, net.biases))
    return int(n * spec.dtype_bytes)


def _filter_macs(model: fm.HierarchicalModel) -> int:
    pre = model.preprocess
    return 0 if pre.filter_kind == "none" else fm.N_STRAIN * int(pre.taps.size)


def _filter_delay_ms(model: fm.HierarchicalModel, rate_hz: float) -> float:
    """Group delay of a causal filter; for the centred filter, the look-ahead an online
    implementation would have to wait for (half its window)."""
    pre = model.preprocess
    if pre.filter_kind == "centred":
        return (pre.taps.size // 2) * 1000.0 / rate_hz
    return pre.group_delay_samples * 1000.0 / rate_hz


def run(paths: Sequence[Path], out: Path, s: Settings, log: Callable[[str], None] = print
        ) -> dict[str, Any]:
    """Train or reuse every variant, evaluate every engine, time them, write the outputs."""
    from fbgforce.tare import sample_rate_hz
    from fbgforce.trainer import qat
    from fbgforce.trainer import train as tr

    t_run = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    ds_list, described = tr.load_datasets([str(p) for p in paths])
    sources = [str(p) for p in paths]
    digest = _data_digest(paths)
    rate_hz = float(np.median([sample_rate_hz(ds.t_s) for ds in ds_list]))
    grid = variants(s)
    specs = [sp for sp in ENGINE_SPECS if sp.name in s.engines]
    calib = calibration_subset(ds_list, sources, out)
    prepared_cache: dict[tuple[str, float], Any] = {}
    rows: list[dict[str, Any]] = []
    timers: list[timing.Timer] = []
    timer_rows: dict[str, dict[str, Any]] = {}
    train_seconds: dict[str, float] = {}

    for v in grid:
        key_pf = (v.filter, v.sigma)
        if key_pf not in prepared_cache:
            prepared_cache[key_pf] = tr.prepare(ds_list, seed=s.seed, filter=v.filter,
                                                sigma=v.sigma, sources=sources)
        prep = prepared_cache[key_pf]
        test_rows = prep.rows("test")
        key = {"variant": v.tag, "filter": v.filter, "sigma": v.sigma,
               "sizes": scaled_sizes(v.width), "seed": s.seed, "epochs": s.epochs,
               "time_budget_s": s.time_budget_s, "data": digest}
        model_dir = out / "models" / v.tag
        model = _reusable(model_dir, key)
        if model is None:
            log(f"training {v.tag} ...")
            t0 = time.perf_counter()
            model = tr.train(sources, epochs=s.epochs, seed=s.seed, filter=v.filter,
                             sigma=v.sigma, sizes={k: h for k, h in key["sizes"].items()},
                             prepared=prep, time_budget_s=s.time_budget_s)
            train_seconds[v.tag] = time.perf_counter() - t0
            _save_with_key(model, model_dir, key)
        else:
            log(f"reusing {model_dir}")
        from fbgforce.export.onnx_export import ONNX_FILE, export_onnx

        export_onnx(model, model_dir / ONNX_FILE)
        dirs: dict[str, tuple[Path, fm.HierarchicalModel]] = {"float": (model_dir, model)}
        # Fixed-point blobs per artifact; an export failure only affects the fixed engines.
        export_err: dict[str, str | None] = {}
        int8_here = s.int8_all_variants or v == Variant("causal", s.default_sigma, "paper")
        if v.causal and any(sp.engine == "fixed" for sp in specs):
            export_err["float"] = export_fixed(model_dir, 16, calib)
            if any(sp.artifact == "int8" for sp in specs) and int8_here:
                d8 = out / "models" / f"{v.tag}-int8"
                if _reusable(d8, {**key, "artifact": "int8"}) is None:
                    _save_with_key(model, d8, {**key, "artifact": "int8"})
                dirs["int8"] = (d8, model)
                export_err["int8"] = export_fixed(d8, 8, calib)
            if any(sp.artifact == "int8-qat" for sp in specs) and int8_here:
                dq = out / "models" / f"{v.tag}-int8-qat"
                qkey = {**key, "artifact": "int8-qat", "qat_epochs": s.qat_epochs, "qat_rule": 2}
                qmodel = _reusable(dq, qkey)
                if qmodel is None:
                    log(f"QAT fine-tuning {v.tag} (int8 weights) ...")
                    qmodel = _qat_model(model, prep, s, qat)
                    _save_with_key(qmodel, dq, qkey)
                dirs["int8-qat"] = (dq, qmodel)
                export_err["int8-qat"] = export_fixed(dq, 8, calib)

        common = {
            "variant": v.tag, "width": v.width, "filter": v.filter,
            "sigma": v.sigma if v.filter != "none" else None, "causal": v.causal,
            "filter_taps": 0 if v.filter == "none" else int(model.preprocess.taps.size),
            "filter_delay_ms": _filter_delay_ms(model, rate_hz),
            "macs_nets": model.macs, "macs": model.macs + _filter_macs(model),
            "sizes": {k: net.sizes for k, net in model.nets.items()},
        }
        for sp in specs:
            row: dict[str, Any] = {**common, "engine": sp.name, "weight_bits": sp.weight_bits,
                                   "act_bits": sp.act_bits, "qat": sp.artifact == "int8-qat"}
            rows.append(row)
            if sp.engine != "float" and sp.engine != "onnx" and not v.causal:
                row["status"] = "n/a: the centred filter is offline only"
                continue
            if sp.artifact not in dirs:
                row["status"] = "n/a: int8 engines run on the reference variant only (--quick)"
                continue
            mdir, mdl = dirs[sp.artifact]
            err = export_err.get(sp.artifact) if sp.engine == "fixed" else None
            if err:
                row["status"] = f"missing: {err}"
                continue
            row["model_bytes"] = _model_bytes(sp, mdl, mdir)
            try:
                fn = fengines.get_engine(sp.engine)
            except InputError as exc:
                row["status"] = f"missing: {exc}"
                continue
            try:
                preds = [fn(mdir, mdl, r.ds.wl_nm, r.baseline_nm) for r in prep.recordings]
            except Exception as exc:  # one broken engine must not lose the rest of the grid
                row["status"] = f"error: {type(exc).__name__}: {exc}"
                log(f"{v.tag}/{sp.name}: {row['status']}")
                continue
            pred = {k: np.concatenate([np.asarray(p[k]) for p in preds])[test_rows]
                    for k in ("contact", "force_N", "x_mm", "y_mm")}
            row.update(fmetrics.compute(pred, *prep.truth(test_rows), extras=False))
            row["status"] = "ok"
            rec = prep.recordings[0]
            try:
                t = make_timer(sp, f"{v.tag}/{sp.name}", mdir, mdl, timing_samples(rec.ds),
                               rec.baseline_nm)
            except Exception as exc:  # a runtime that evaluates but cannot be timed: say so
                row["timing_error"] = f"{type(exc).__name__}: {exc}"
                continue
            timers.append(t)
            timer_rows[t.name] = row
            row["_dir"] = mdir

    log(f"timing {len(timers)} engine/model pairs (interleaved) ...")
    blas_threads = timing.limit_blas_threads(1)  # every engine on one thread (timing.py)
    n_time = len(timing_samples(ds_list[0]))  # every timer replays the same samples
    times = timing.measure(timers, n_time, single_calls=s.single_calls, batch_size=s.batch_size,
                           batch_reps=s.batch_reps, rounds=s.rounds)
    for name, tm in times.items():
        r = timer_rows[name]
        r["host_single_ns"] = tm["single_ns"]
        r["host_single_p99_ns"] = tm["single_p99_ns"]
        r["host_batch_ns"] = tm["batch_ns"]
        r["host_batch_min_ns"] = tm["batch_min_ns"]
        r["host_batch_size"] = tm["batch_size"]

    target_cache: dict[str, dict[str, Any]] = {}
    for r in rows:
        mdir = r.pop("_dir", None)
        r["m4_instructions_per_step"] = None
        if s.target and mdir is not None and r["engine"].startswith("c-int"):
            if str(mdir) not in target_cache:
                log(f"Cortex-M4 counts for {Path(mdir).name} ...")
                target_cache[str(mdir)] = target_instructions(mdir, Path(sources[0]))
            r.update(target_cache[str(mdir)])
    ref = _reference(rows, s)
    _score(rows, ref)
    _mark_pareto(rows)
    result = {
        "command": " ".join(sys.argv) if sys.argv and sys.argv[0] else None,
        "data": described, "sample_rate_hz": rate_hz, "quantizer_calibration": calib,
        "settings": {k: v for k, v in s.__dict__.items()},
        "reference": None if ref is None else {"variant": ref["variant"], "engine": ref["engine"]},
        "rows": rows,
        "ratios": _ratios(rows, s),
        "train_seconds": train_seconds,
        "seconds": time.perf_counter() - t_run,
        "platform": {**_platform(), "blas_threads_before_timing": blas_threads},
    }
    result["summary"] = summary_paragraph(result)
    write_outputs(result, out, log)
    return result


def _qat_model(model: fm.HierarchicalModel, prep: Any, s: Settings, qat: Any
               ) -> fm.HierarchicalModel:
    z = (prep.feats - model.preprocess.input_mean) / model.preprocess.input_std
    trn, val = prep.rows("train"), prep.rows("val")
    truth = (prep.contact, prep.force_N, prep.x_mm, prep.y_mm)
    tuned, _ = qat.finetune(model, z[trn], *(t[trn] for t in truth),
                            val=(z[val], *(t[val] for t in truth)) if val.size else None,
                            weight_bits=8, act_bits=16, epochs=s.qat_epochs, seed=s.seed)
    return tuned


def _platform() -> dict[str, Any]:
    import os
    import platform

    info: dict[str, Any] = {"python": platform.python_version(), "numpy": np.__version__,
                            "machine": platform.machine(), "cpus": os.cpu_count()}
    try:
        import onnxruntime

        info["onnxruntime"] = onnxruntime.__version__
    except ImportError:
        pass
    return info


# --------------------------------------------------------------------------------------------
# Scoring, Pareto front, ratios, the paragraph
# --------------------------------------------------------------------------------------------

def _reference(rows: list[dict[str, Any]], s: Settings) -> dict[str, Any] | None:
    for r in rows:
        if (r["width"] == "paper" and r["filter"] == "causal" and r["sigma"] == s.default_sigma
                and r["engine"] == "numpy-f64" and r.get("status") == "ok"):
            return r
    ok = [r for r in rows if r.get("status") == "ok" and r["causal"]]
    return ok[0] if ok else None


def _contact_err(acc: float) -> float:
    return max(1.0 - acc, CONTACT_ERR_FLOOR)


def _score(rows: list[dict[str, Any]], ref: dict[str, Any] | None) -> None:
    for r in rows:
        r["error_index"] = None
        r["matches_reference"] = None
        r["is_reference"] = r is ref
        if ref is None or r.get("status") != "ok":
            continue
        ratios = [_contact_err(r["contact_accuracy"]) / _contact_err(ref["contact_accuracy"])]
        for k in METRIC_KEYS[1:]:
            if r.get(k) is None or not ref.get(k):
                continue
            ratios.append(r[k] / ref[k])
        r["error_index"] = float(math.exp(np.mean(np.log(ratios))))
        r["matches_reference"] = bool(
            r["contact_accuracy"] >= ref["contact_accuracy"] - CONTACT_SLACK
            and all(r.get(k) is not None and ref.get(k) is not None
                    and r[k] <= MATCH_RMSE_FACTOR * ref[k] for k in METRIC_KEYS[1:]))


#: Error indices closer than this count as equal when deciding dominance: differences in
#: the third decimal (float32 vs float64, int16 rounding) are not accuracy differences.
PARETO_ERR_TOL = 0.01


def pareto_mask(points: Sequence[tuple[float, ...]], tol: Sequence[float] | None = None
                ) -> list[bool]:
    """True for points that no other point dominates (minimising every coordinate).

    ``q`` dominates ``p`` when ``q[k] <= p[k] + tol[k]`` for every k and ``q[k] < p[k] - tol[k]``
    for at least one k (``tol`` defaults to zeros: plain Pareto dominance).
    """
    pts = [tuple(float(v) for v in p) for p in points]
    t = [0.0] * (len(pts[0]) if pts else 0) if tol is None else [float(v) for v in tol]
    out = []
    for i, p in enumerate(pts):
        dominated = False
        for j, q in enumerate(pts):
            if j == i:
                continue
            if all(q[k] <= p[k] + t[k] for k in range(len(p))) and \
                    any(q[k] < p[k] - t[k] for k in range(len(p))):
                dominated = True
                break
        out.append(not dominated)
    return out


def _mark_pareto(rows: list[dict[str, Any]]) -> None:
    """Pareto fronts among deployable (causal) rows: error vs compute time, and error vs
    time including the filter delay (what a haptic loop feels)."""
    cand = [r for r in rows if r.get("status") == "ok" and r["causal"]
            and r.get("error_index") is not None and r.get("host_batch_ns") is not None]
    for r in rows:
        r["pareto_compute"] = False
        r["pareto_delay"] = False
    for key, coords in (("pareto_compute", lambda r: (r["error_index"], r["host_batch_ns"])),
                        ("pareto_delay", lambda r: (r["error_index"], r["filter_delay_ms"],
                                                    r["host_batch_ns"]))):
        pts = [coords(r) for r in cand]
        tol = [PARETO_ERR_TOL] + [0.0] * (len(pts[0]) - 1) if pts else None
        for r, front in zip(cand, pareto_mask(pts, tol)):
            r[key] = front


def _ratios(rows: list[dict[str, Any]], s: Settings) -> dict[str, Any]:
    """Host speed of C fixed int16 against onnxruntime and numpy, same model, same run."""
    by = {(r["variant"], r["engine"]): r for r in rows}
    ref_tag = Variant("causal", s.default_sigma, "paper").tag
    out: dict[str, Any] = {"variant": ref_tag}
    c = by.get((ref_tag, "c-int16"))
    for other in ("onnx-f32", "numpy-f64", "c-float"):
        o = by.get((ref_tag, other))
        for mode in ("single", "batch"):
            k = f"host_{mode}_ns"
            if c and o and c.get(k) and o.get(k):
                out[f"{other}_over_c-int16_{mode}"] = o[k] / c[k]
            else:
                out[f"{other}_over_c-int16_{mode}"] = None
    return out


def _fmt(v: Any, spec: str = ".3g") -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else ""
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def _ns(v: float | None) -> str:
    if v is None:
        return "–"
    return f"{v / 1000:.1f} µs" if v >= 10000 else f"{v:.0f} ns"


def summary_paragraph(res: dict[str, Any]) -> str:
    """One paragraph, written from the numbers: what each step in cost buys."""
    rows = [r for r in res["rows"] if r.get("status") == "ok"]
    ref = next((r for r in rows if r.get("is_reference")), None)
    if ref is None:
        return "No configuration could be evaluated, so there is nothing to compare."
    by = {(r["variant"], r["engine"]): r for r in rows}
    parts = []

    def acc(r: dict[str, Any]) -> str:
        return (f"force {r['rmse_force_N']:.2f} N, x {r['rmse_x_mm']:.2f} mm, y {r['rmse_y_mm']:.2f}"
                f" mm, contact {100 * r['contact_accuracy']:.1f} %")

    parts.append(f"The reference is the paper-size network ({ref['macs_nets']} MACs) with the "
                 f"shipped causal filter (σ = {ref['sigma']:g} samples, {ref['filter_delay_ms']:.1f}"
                 f" ms delay) in numpy float64: {acc(ref)}, {_ns(ref.get('host_batch_ns'))} per "
                 f"sample batched, {_ns(ref.get('host_single_ns'))} per single-sample call.")
    tag = ref["variant"]
    for name, what in (("onnx-f32", "onnxruntime float32"), ("c-float", "the C float build"),
                       ("c-int16", "the C int16 fixed-point runtime"),
                       ("c-int8", "int8 weights"), ("c-int8-qat", "int8 weights after QAT")):
        r = by.get((tag, name))
        if r is None:
            continue
        parts.append(f"{what[0].upper() + what[1:]} gives error index {r['error_index']:.3f} "
                     f"({acc(r)}) at {_ns(r.get('host_batch_ns'))} batched / "
                     f"{_ns(r.get('host_single_ns'))} single"
                     + (f", {r['model_bytes']} model bytes" if r.get("model_bytes") else "") + ".")
    ratios = res.get("ratios", {})

    def rel(x: float | None) -> str:
        if not x:
            return "–"
        return f"{x:.1f}× slower than" if x >= 1 else f"{1 / x:.1f}× faster than"

    if ratios.get("onnx-f32_over_c-int16_batch"):
        parts.append(
            f"Same model, same run, relative to the C int16 runtime: batched, onnxruntime is "
            f"{rel(ratios['onnx-f32_over_c-int16_batch'])} it and numpy "
            f"{rel(ratios['numpy-f64_over_c-int16_batch'])} it; in single-sample calls "
            f"onnxruntime is {rel(ratios['onnx-f32_over_c-int16_single'])} it and numpy "
            f"{rel(ratios['numpy-f64_over_c-int16_single'])} it.")
    # Filter: what delay buys.
    filt = sorted((r for r in rows if r["width"] == "paper" and r["engine"] == "numpy-f64"),
                  key=lambda r: (not r["causal"], r["filter_delay_ms"]))
    if len(filt) > 1:
        desc = "; ".join(
            f"{'no filter' if r['filter'] == 'none' else r['filter'] + ' σ=' + format(r['sigma'], 'g')}"
            f" ({r['filter_delay_ms']:.1f} ms{' look-ahead' if not r['causal'] else ''}): "
            f"force {r['rmse_force_N']:.2f} N, y {r['rmse_y_mm']:.2f} mm, "
            f"index {r['error_index']:.2f}" for r in filt)
        parts.append(f"Filter delay against accuracy at paper width: {desc}.")
    widths = sorted((r for r in rows if r["engine"] == "numpy-f64" and r["filter"] == ref["filter"]
                     and r["sigma"] == ref["sigma"]), key=lambda r: -r["macs_nets"])
    if len(widths) > 1:
        desc = "; ".join(f"{r['width']} ({r['macs_nets']} MACs): index {r['error_index']:.2f}, "
                         f"{_ns(r.get('host_batch_ns'))}" for r in widths)
        parts.append(f"Network width: {desc}.")
    paper_cfg = next((r for r in rows if not r["causal"] and r["width"] == "paper"
                      and r["engine"] == "numpy-f64"), None)
    if paper_cfg is not None:
        parts.append(f"The paper's own configuration (paper width, centred Gaussian σ = "
                     f"{paper_cfg['sigma']:g}) reaches error index {paper_cfg['error_index']:.3f} "
                     f"({acc(paper_cfg)}) but needs {paper_cfg['filter_delay_ms']:.0f} ms of future "
                     f"samples, so it is an offline reference, off the deployable front.")
    front = sorted((r for r in rows if r.get("pareto_compute")), key=lambda r: r["host_batch_ns"])
    if front:
        parts.append("Deployable Pareto front, error against host compute: " + ", ".join(
            f"{r['variant']}/{r['engine']} ({_ns(r['host_batch_ns'])}, index {r['error_index']:.3f})"
            for r in front) + ".")
    m4 = [r for r in rows if r["engine"] == "c-int16" and r.get("m4_instructions_per_step")]
    if m4:
        desc = "; ".join(
            f"{r['variant']} {r['m4_instructions_per_step']} instructions per step "
            f"({100 * r['m4_instructions_per_step'] / 168e3:.1f} % of a 1 kHz period at 168 MHz"
            f" at one instruction per cycle)"
            for r in sorted(m4, key=lambda r: -r["m4_instructions_per_step"]))
        parts.append(f"On the Cortex-M4 (DSP build, int16, worst step): {desc}.")
        r16, r8 = by.get((tag, "c-int16")), by.get((tag, "c-int8"))
        if r16 and r8 and r16.get("m4_instructions_per_step") and r8.get("m4_instructions_per_step"):
            parts.append(f"Int8 weights shrink the blob from {r16['model_bytes']} to "
                         f"{r8['model_bytes']} bytes but take {r8['m4_instructions_per_step']} "
                         f"instead of {r16['m4_instructions_per_step']} instructions per step on "
                         f"the M4 ({r8['m4_instructions_per_step'] / r16['m4_instructions_per_step']:.1f}×"
                         f"; the portable int16 build takes {r16.get('m4_instructions_portable')}).")
    cheaper = [r for r in rows if r.get("matches_reference") and r["causal"] and r is not ref
               and (r["macs"] < ref["macs"] or r["filter_delay_ms"] < ref["filter_delay_ms"] - 1e-9)]
    if cheaper:
        best = min(cheaper, key=lambda r: (r["macs"], r["filter_delay_ms"], r.get("host_batch_ns") or 0))
        engines = [r["engine"] for r in cheaper if r["variant"] == best["variant"]]
        parts.append(f"Cheapest configuration matching the reference (every RMSE within "
                     f"{100 * (MATCH_RMSE_FACTOR - 1):.0f} %, contact within "
                     f"{100 * CONTACT_SLACK:.1f} points): {best['variant']}, {best['macs']} MACs "
                     f"against the reference's {ref['macs']} ({ref['macs'] / best['macs']:.1f}× fewer), "
                     f"{best['filter_delay_ms']:.1f} ms delay, index {best['error_index']:.3f}; it "
                     f"matches on {', '.join(engines)}.")
    else:
        worse = sorted((r for r in rows if r["causal"] and r is not ref and r["engine"] == ref["engine"]
                        and (r["macs"] < ref["macs"] or r["filter_delay_ms"] < ref["filter_delay_ms"])),
                       key=lambda r: r["error_index"])
        if worse:
            w = worse[0]
            parts.append(f"No cheaper configuration matches the reference: the closest, {w['variant']}"
                         f" ({w['macs']} MACs, {w['filter_delay_ms']:.1f} ms), is at error index "
                         f"{w['error_index']:.3f} ({acc(w)}).")
    return " ".join(parts)


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------

CSV_COLUMNS = ("variant", "engine", "width", "filter", "sigma", "causal", "weight_bits",
               "act_bits", "qat", "status", *METRIC_KEYS, "n_samples", "error_index",
               "matches_reference", "is_reference", "host_single_ns", "host_single_p99_ns",
               "host_batch_ns", "host_batch_min_ns", "m4_instructions_per_step",
               "m4_instructions_portable", "m4_bit_exact", "filter_taps", "filter_delay_ms",
               "macs", "macs_nets", "model_bytes", "pareto_compute", "pareto_delay")


def markdown_table(res: dict[str, Any]) -> str:
    """The grid as a Markdown table, best error index first within each variant group."""
    head = ("| variant | engine | contact % | force N | x mm | y mm | error index | single | "
            "batch | M4 instr. | delay ms | MACs | bytes | Pareto |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in res["rows"]:
        if r.get("status") != "ok":
            continue
        mark = []
        if r.get("is_reference"):
            mark.append("**ref**")
        if r.get("pareto_compute"):
            mark.append("P-time")
        if r.get("pareto_delay"):
            mark.append("P-delay")
        if r.get("matches_reference") and not r.get("is_reference"):
            mark.append("≈ref")
        lines.append("| " + " | ".join([
            r["variant"] + ("" if r["causal"] else " (offline)"), r["engine"],
            _fmt(100 * r["contact_accuracy"], ".2f"), _fmt(r["rmse_force_N"], ".3f"),
            _fmt(r["rmse_x_mm"], ".3f"), _fmt(r["rmse_y_mm"], ".3f"), _fmt(r["error_index"], ".3f"),
            _ns(r.get("host_single_ns")), _ns(r.get("host_batch_ns")),
            _fmt(r.get("m4_instructions_per_step")), _fmt(r["filter_delay_ms"], ".1f"),
            str(r["macs"]), _fmt(r.get("model_bytes")), " ".join(mark)]) + " |")
    missing = [r for r in res["rows"] if r.get("status") != "ok"]
    if missing:
        seen = {}
        for r in missing:
            seen.setdefault((r["engine"], r["status"]), []).append(r["variant"])
        lines.append("")
        lines.append("Not measured: " + "; ".join(
            f"{eng} ({len(v)} variants): {st}" for (eng, st), v in seen.items()))
    return "\n".join(lines)


def write_plot(res: dict[str, Any], path: Path) -> str | None:
    """Accuracy against time per sample, Pareto front marked. Returns a note if skipped."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib not installed: no plot (pip install 'fbgforce[plot]')"
    rows = [r for r in res["rows"] if r.get("status") == "ok" and r.get("error_index") is not None]
    m4 = [r for r in rows if r.get("m4_instructions_per_step")]
    fig, axes = plt.subplots(1, 3 if m4 else 2, figsize=(19 if m4 else 13, 5.2))
    engines = sorted({r["engine"] for r in rows}, key=[s.name for s in ENGINE_SPECS].index)
    markers = dict(zip([s.name for s in ENGINE_SPECS], "osD^vP"))
    widths = {"paper": 90, "half": 50, "quarter": 25}
    cmap = plt.get_cmap("tab10")
    for ax, xkey, xlabel in ((axes[0], "host_batch_ns", "host time per sample, batched (ns, log)"),
                             (axes[1], "total_ms", "filter delay + single-sample call (ms)")):
        for i, eng in enumerate(engines):
            pts = [r for r in rows if r["engine"] == eng]
            xs = [(r["filter_delay_ms"] + (r.get("host_single_ns") or r.get("host_batch_ns") or 0) / 1e6)
                  if xkey == "total_ms" else r.get(xkey) for r in pts]
            keep = [(x, r) for x, r in zip(xs, pts) if x is not None]
            if not keep:
                continue
            for causal in (True, False):
                part = [(x, r) for x, r in keep if r["causal"] == causal]
                if part:
                    ax.scatter([x for x, _ in part], [r["error_index"] for _, r in part],
                               s=[widths.get(r["width"], 40) for _, r in part],
                               marker=markers.get(eng, "o"),
                               facecolors=cmap(i) if causal else "none", edgecolors=cmap(i),
                               linewidths=1.2, label=eng if causal else None, alpha=0.8)
        front_key = "pareto_compute" if xkey == "host_batch_ns" else "pareto_delay"
        front = sorted(((r["filter_delay_ms"] + (r.get("host_single_ns") or r.get("host_batch_ns") or 0) / 1e6
                         if xkey == "total_ms" else r["host_batch_ns"], r["error_index"])
                        for r in rows if r.get(front_key)))
        if front:
            # The front as a staircase through the non-dominated points in this projection.
            best, stair = math.inf, []
            for x, y in front:
                if y < best:
                    best = y
                    stair.append((x, y))
            ax.step([p[0] for p in stair], [p[1] for p in stair], where="post", color="k",
                    lw=1.2, ls="--", label="Pareto front")
        ref = next((r for r in rows if r.get("is_reference")), None)
        if ref is not None:
            x = (ref["filter_delay_ms"] + (ref.get("host_single_ns") or 0) / 1e6) if xkey == "total_ms" \
                else ref.get("host_batch_ns")
            if x is not None:
                ax.annotate("paper net, shipped filter (ref)", (x, ref["error_index"]),
                            textcoords="offset points", xytext=(8, 10), fontsize=8,
                            arrowprops={"arrowstyle": "-", "lw": 0.6})
        paper = [r for r in rows if not r["causal"] and r["width"] == "paper"
                 and r["engine"] == "numpy-f64"]
        for r in paper:
            x = (r["filter_delay_ms"] + (r.get("host_single_ns") or r.get("host_batch_ns") or 0) / 1e6) \
                if xkey == "total_ms" else r.get("host_batch_ns")
            if x is None:
                continue
            ax.annotate("paper config (centred, offline)", (x, r["error_index"]),
                        textcoords="offset points", xytext=(8, -14), fontsize=8)
        ax.set_xscale("log" if xkey == "host_batch_ns" else "linear")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("error index (1 = reference; lower is better)")
        ax.axhline(1.0, color="0.6", lw=0.6)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    axes[0].set_title("accuracy vs compute (marker size = width; hollow = offline filter)",
                      fontsize=9)
    axes[1].set_title("accuracy vs what the loop feels: filter delay + one step", fontsize=9)
    if m4:
        ax = axes[2]
        for i, eng in enumerate(engines):
            pts = [r for r in m4 if r["engine"] == eng]
            if pts:
                ax.scatter([r["m4_instructions_per_step"] for r in pts],
                           [r["error_index"] for r in pts], s=[widths.get(r["width"], 40) for r in pts],
                           marker=markers.get(eng, "o"), color=cmap(i), label=eng, alpha=0.8)
                for r in pts:
                    ax.annotate(r["variant"], (r["m4_instructions_per_step"], r["error_index"]),
                                textcoords="offset points", xytext=(4, 3), fontsize=6)
        front = sorted((r["m4_instructions_per_step"], r["error_index"]) for r in m4)
        best, stair = math.inf, []
        for x, y in front:
            if y < best:
                best = y
                stair.append((x, y))
        ax.step([p[0] for p in stair], [p[1] for p in stair], where="post", color="k", lw=1.2,
                ls="--", label="Pareto front")
        ax.axvline(16800, color="0.5", lw=0.8, ls=":")
        ax.text(16800, ax.get_ylim()[1], " 10 % of 1 kHz at 168 MHz", fontsize=7, va="top")
        ax.set_xlabel("Cortex-M4 instructions per step (worst step, DSP build)")
        ax.set_ylabel("error index")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        ax.set_title("accuracy vs firmware cost (QEMU instruction counts)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return None


def write_outputs(res: dict[str, Any], out: Path, log: Callable[[str], None]) -> None:
    """tradeoff.json, tradeoff.csv, tradeoff.md and tradeoff.png in ``out``."""
    (out / "tradeoff.json").write_text(json.dumps(res, indent=1, default=json_default) + "\n")
    with open(out / "tradeoff.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for r in res["rows"]:
            w.writerow(["" if r.get(c) is None else r.get(c) for c in CSV_COLUMNS])
    note = write_plot(res, out / "tradeoff.png")
    if note:
        log(note)
    res["plot"] = None if note else str(out / "tradeoff.png")
    md = ["# Accuracy against time", "", f"Data: {', '.join(str(d.get('path') or d.get('source')) for d in res['data'])}; "
          f"held-out test presses (split 8:1:1 by press, seed {res['settings']['seed']}).", "",
          markdown_table(res), "", res["summary"], ""]
    if res["plot"]:
        md += ["![accuracy against time](tradeoff.png)", ""]
    (out / "tradeoff.md").write_text("\n".join(md))

