"""Every inference engine timed side by side in one run, with ratios and instruction counts
(``fbgforce bench-speed``, docs/runtime.md "Speed (host)").

One model, one set of samples (contact samples, so every net runs: :func:`timing_samples`),
three kinds of figure:

- **from Python**, in one interleaved :func:`fbgforce.tradeoff.timing.measure` run: the C
  runtime's batch (``fbg_run`` / ``fbgf_run`` through cffi on int32 femtometres) and its
  single-sample API (``Runtime.step`` / ``FloatRuntime.step``); numpy float64 and onnxruntime
  float32 (one thread) over the whole pipeline (batch: the engine functions; single:
  :class:`~fbgforce.model.floatref.FloatPipeline`) and over the nets alone (standardised
  features precomputed), onnxruntime's single-row ``session.run`` included;
- **from C**, per driver build (:mod:`fbgforce.tradeoff.cdriver`): ``*_run`` over all samples
  and one ``*_step`` call per sample, best of ``reps`` passes in CPU time, the fixed-point
  outputs compared byte for byte with the extension's;
- **instructions per step** from callgrind for every driver build (noise-free).

Every time is per sample; ``ratio`` is a row's time over the reference row's, onnxruntime's
batch over the nets (below 1: faster than onnxruntime).
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fbgforce.model import artifact, floatref, modeldir
from fbgforce.errors import InputError
from fbgforce.tradeoff import cdriver, timing
from fbgforce.tradeoff.grid import step_macs
from fbgforce.tradeoff.timers import c_callables, timing_samples

#: The row every ratio divides by: (engine, call, scope).
REFERENCE = ("onnx", "batch", "nets")


@dataclass
class SpeedSettings:
    """How much is measured (``fbgforce bench-speed`` options)."""

    samples: int = 5000
    batch: int = 2000
    single_calls: int = 3000
    batch_reps: int = 60
    rounds: int = 6
    c_reps: int = 7
    count_samples: int = 200
    count_warmup: int = 100
    callgrind: bool = True
    kernels: bool = True
    builds: tuple[cdriver.CBuild, ...] = field(default_factory=tuple)


def default_builds(kernels: bool = True) -> tuple[cdriver.CBuild, ...]:
    """The driver built as the extension is (packed weights where the kernel has them, as
    :class:`fbgforce.Runtime` runs), and (``kernels``) once more per dense-layer kernel the
    header offers (``FBG_OPT_KERNEL_*`` values for ``fbg_init``, AUTO excepted: that is the
    first build) on the weights as the model holds them, and once more packed for each kernel
    with a packed form (``kernel-avx2-packed``, ...); empty where the extension's flags are
    unknown."""
    from fbgforce.target.sources import CSourcesMissing, header_constants

    flags = cdriver.extension_flags()
    if flags is None:
        return ()
    try:
        from fbgforce.pybind import PACKED_KERNELS
    except ImportError:  # no extension: c_rows reports that
        PACKED_KERNELS = ()
    builds = [cdriver.CBuild("as-extension", flags, packed=bool(PACKED_KERNELS))]
    if not kernels:
        return tuple(builds)
    try:
        consts = header_constants()
    except CSourcesMissing:
        consts = {}
    for name, value in sorted(consts.items(), key=lambda kv: kv[1]):
        kernel = name.removeprefix("FBG_OPT_KERNEL_")
        if name.startswith("FBG_OPT_KERNEL_") and kernel not in ("AUTO", "MASK"):
            builds.append(cdriver.CBuild(f"kernel-{kernel.lower()}", flags, value))
            if kernel.lower() in PACKED_KERNELS:
                builds.append(cdriver.CBuild(f"kernel-{kernel.lower()}-packed", flags, value, packed=True))
    return tuple(builds)


def _fixed_bits(model_dir: Path) -> int | None:
    from fbgforce.export.exporter import REPORT_FILE

    try:
        return int(json.loads((model_dir / REPORT_FILE).read_text())["bits"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _check_fixed_dir(model_dir: Path, model: artifact.HierarchicalModel, bits: int, option: str) -> None:
    """A directory whose model.fbgm is a current ``bits``-bit export of ``model``."""
    from fbgforce.model.modeldir import check_export
    from fbgforce.pybind import Runtime

    Runtime(model_dir)  # missing, unreadable or stale blob: InputError naming the file
    got = _fixed_bits(model_dir)
    if got is not None and got != bits:
        raise InputError(f"model.fbgm has {got}-bit weights; {option} takes the {bits}-bit export "
                         f"(fbgforce export --bits {bits})", path=str(model_dir), column=option)
    check_export(model_dir, model)


def contact_window(contact: np.ndarray, warmup: int, n_max: int) -> tuple[int, int] | None:
    """The steps to count: the first ``n_max`` steps at or after ``warmup`` during which the
    engine decided "contact" at every step (all three nets run), else the longest such run
    there; None when the engine never decided contact after the warm-up.

    Returns ``(start, n)``: ``n`` steps from sample ``start`` of the stream.
    """
    c = np.asarray(contact, dtype=bool)
    best: tuple[int, int] | None = None
    i = max(0, warmup)
    while i < c.size:
        if not c[i]:
            i += 1
            continue
        j = i
        while j < c.size and c[j] and j - i < n_max:
            j += 1
        if j - i == n_max:
            return i, n_max
        if best is None or j - i > best[1]:
            best = (i, j - i)
        i = j
    return best


def _row(engine: str, call: str, caller: str, scope: str, how: str, *, build: str | None = None,
         ns: float | None = None, note: str | None = None) -> dict[str, Any]:
    return {"engine": engine, "call": call, "caller": caller, "scope": scope, "how": how,
            "build": build, "batch_size": None, "ns_per_sample": ns, "ratio": None,
            "instructions_per_step": None, "counted_steps": None, "profile_per_step": None,
            "bit_exact": None,
            "note": note}


def python_timers(model_dir: Path, int8_dir: Path, model: artifact.HierarchicalModel, wl: np.ndarray,
                  base: np.ndarray) -> list[tuple[timing.Timer, dict[str, Any], dict[str, Any]]]:
    """The in-process timers and, for each, the rows its single and batch figures fill."""
    from fbgforce.evaluation.engines import get_engine
    from fbgforce.export.onnx_export import DECISION_NAME, INPUT_NAME, run_features, session_for
    from fbgforce.pybind import FloatRuntime, Runtime

    out: list[tuple[timing.Timer, dict[str, Any], dict[str, Any]]] = []
    for name, kind, mdir in (("fixed", "fixed", model_dir), ("fixed-int8", "fixed", int8_dir),
                             ("cfloat", "cfloat", model_dir)):
        rt: Any = Runtime(mdir) if kind == "fixed" else FloatRuntime(model)
        rt.set_baseline(base)
        _, batch = c_callables(kind, mdir, model, wl, base)
        api = "Runtime.step" if kind == "fixed" else "FloatRuntime.step"
        run = "fbg_run" if kind == "fixed" else "fbgf_run"
        out.append((timing.Timer(name, single=lambda i, rt=rt: rt.step(wl[i]), batch=batch),
                    _row(name, "single", "python", "pipeline", api),
                    _row(name, "batch", "python", "pipeline", f"{run} through cffi")))
    z = np.ascontiguousarray(floatref.features(model, wl, base))
    z32 = np.ascontiguousarray(z, dtype=np.float32)
    for name, engine, nets in (("float", "float", "numpy"), ("onnx", "onnx", "onnx")):
        fn = get_engine(engine)
        pipe = timing.float_pipeline(model, base, nets, model_dir)
        out.append((timing.Timer(name, single=lambda i, p=pipe: p.push(wl[i]),
                                 batch=lambda a, b, fn=fn: fn(model_dir, model, wl[a:b], base)),
                    _row(name, "single", "python", "pipeline", f"FloatPipeline.push ({nets})"),
                    _row(name, "batch", "python", "pipeline",
                         "fbgforce.model.floatref.predict" if nets == "numpy"
                         else "numpy preprocessing + onnxruntime nets")))
    out.append((timing.Timer("float/nets",
                             single=lambda i: floatref.predict_from_features(model, z[i:i + 1]),
                             batch=lambda a, b: floatref.predict_from_features(model, z[a:b])),
                _row("float", "single", "python", "nets", "predict_from_features, one row"),
                _row("float", "batch", "python", "nets", "predict_from_features")))
    sess = session_for(model, model_dir)
    names = [o.name for o in sess.get_outputs()]
    # The nets alone: one run of the graph, its location fed the nets' own decision (the
    # engine runs the samples it decides in contact a second time, onnx_export.onnx_nets).
    decided = np.ascontiguousarray(floatref.predict_from_features(model, z)["contact"], dtype=bool)
    out.append((timing.Timer("onnx/nets",
                             single=lambda i: sess.run(names, {INPUT_NAME: z32[i:i + 1],
                                                               DECISION_NAME: decided[i:i + 1]}),
                             batch=lambda a, b: run_features(model, z32[a:b], model_dir,
                                                             decision=decided[a:b])),
                _row("onnx", "single", "python", "nets", "session.run, one row"),
                _row("onnx", "batch", "python", "nets", "session.run, 1 thread")))
    return out


def c_rows(builds: tuple[cdriver.CBuild, ...], work: Path, model_dir: Path, int8_dir: Path,
           base_fm: np.ndarray, wl_fm: np.ndarray, s: SpeedSettings,
           tick: Callable[[str], None]) -> list[dict[str, Any]]:
    """Rows timed and counted from C, for every build."""
    from fbgforce.pybind import Runtime

    rows: list[dict[str, Any]] = []
    from fbgforce import contract

    samples = work / "samples.bin"
    cdriver.write_samples(samples, base_fm, wl_fm)
    reference: dict[str, bytes] = {}
    for name, mdir in (("fixed", model_dir), ("fixed-int8", int8_dir)):
        rt = Runtime(mdir)
        rt.set_baseline(base_fm)
        reference[name] = rt.run_raw(wl_fm).tobytes()
    float_src = cdriver.float_model_source(model_dir)
    vg = cdriver.valgrind() if s.callgrind else None
    for b in builds:
        engines: list[tuple[str, str, Path | None]] = [
            ("fixed", "fixed", model_dir / "model.fbgm"), ("fixed-int8", "fixed", int8_dir / "model.fbgm")]
        if float_src is not None and b.init_options is None:  # options: fixed point only
            engines.append(("cfloat", "float", None))
        try:
            tick(f"compiling the driver ({b.name}: {b.flags or 'no flags'})")
            exe = cdriver.build(b, work / f"build-{len(rows)}", float_src)
        except RuntimeError as exc:
            for name, kind, _ in engines:
                for call in ("batch", "single"):
                    rows.append(_row(name, call, "c", "pipeline", "", build=b.name,
                                     note=f"n/a: {exc}"))
            continue
        for name, kind, blob in engines:
            run = "fbg_run" if kind == "fixed" else "fbgf_run"
            step = "fbg_step" if kind == "fixed" else "fbgf_step"
            batch_row = _row(name, "batch", "c", "pipeline", f"{run} from C", build=b.name)
            batch_row["batch_size"] = int(wl_fm.shape[0])
            single_row = _row(name, "single", "c", "pipeline", f"{step} from C", build=b.name)
            rows += [batch_row, single_row]
            tick(f"{name} from C ({b.name})")
            outputs = work / "out.bin"
            try:
                batch_row["ns_per_sample"], single_row["ns_per_sample"] = cdriver.time_run(
                    exe, kind, blob, samples, s.c_reps, outputs)
            except RuntimeError as exc:
                batch_row["note"] = single_row["note"] = f"n/a: {exc}"
                continue
            raw = outputs.read_bytes()
            if kind == "fixed":
                batch_row["bit_exact"] = raw == reference[name]
            dtype = np.dtype(contract.numpy_dtype(contract.OUTPUT if kind == "fixed"
                                                  else contract.FLOAT_OUTPUT))
            window = contact_window(np.frombuffer(raw, dtype=dtype)["contact"] != 0,
                                    s.count_warmup, s.count_samples)
            if vg is None:
                single_row["note"] = ("n/a: valgrind not found (apt-get install valgrind)"
                                      if s.callgrind else "callgrind skipped (--no-callgrind)")
                continue
            if window is None:
                single_row["note"] = "n/a: no contact step after the warm-up to count"
                continue
            tick(f"{name} under callgrind ({b.name})")
            try:
                ipc, profile = cdriver.count_instructions(exe, kind, blob, samples, *window)
            except RuntimeError as exc:
                single_row["note"] = f"n/a: {exc}"
                continue
            single_row["instructions_per_step"] = ipc
            single_row["profile_per_step"] = {f: v for f, v in profile.items() if v >= 0.01 * ipc}
            single_row["counted_steps"] = {"start": window[0], "n": window[1]}
            if window[1] < s.count_samples:
                single_row["note"] = f"counted over {window[1]} contact steps"
    if not builds:
        rows.append(_row("fixed", "single", "c", "pipeline", "fbg_step from C",
                         note="n/a: no C build (runtime_c/build_runtime.py not found; give "
                              "--c-build NAME=FLAGS)"))
    return rows


def bench_speed(model_dir: str | Path, data: Path, s: SpeedSettings, *,
                int8_dir: str | Path | None = None, progress: bool | None = None,
                log: Callable[[str], None] = lambda m: None) -> dict[str, Any]:
    """Time every engine on ``model_dir`` over the contact samples of ``data``.

    Parameters
    ----------
    model_dir
        A trained model directory with its int16 export (``fbgforce export``).
    data
        A recording in the dataset contract (its contact samples are timed).
    s
        What to measure.
    int8_dir
        The int8 export of the same model; by default made here in a temporary copy,
        calibrated on ``data`` (its first presses: :func:`~fbgforce.tradeoff.artifacts.calibration_subset`).
    progress
        progress bar on stderr (None: only on a terminal, where ``log`` is quiet).
    log
        Progress lines.

    Returns
    -------
    dict
        The keys of docs/cli.md "bench-speed".
    """
    from fbgforce import progress as fprogress
    from fbgforce.pybind import to_fm

    t_start = time.perf_counter()
    model_dir, model, int8_dir = _speed_models(model_dir, int8_dir)
    ds, base, wl = _speed_samples(data, s)
    base_builds = default_builds(s.kernels)
    builds = base_builds + tuple(b for b in s.builds if b not in base_builds)
    n_c = len(builds) * (1 + 3 * (2 if s.callgrind else 1))
    # Off a terminal the command's stage lines (``log``) say what is going on instead.
    bar = fprogress.bar(total=2 + (int8_dir is None) + n_c, desc="bench-speed", leave=False,
                        enabled=sys.stderr.isatty() if progress is None else progress)
    tick = _ticker(bar, log)
    with tempfile.TemporaryDirectory(prefix="fbgforce-bench-") as tmp:
        work = Path(tmp)
        made_int8 = int8_dir is None
        if int8_dir is None:
            tick("exporting the int8 model")
            int8_dir = _export_int8(model, model_dir, ds, data, work)
        tick("timing from Python (interleaved)")
        rows, blas = _python_rows(python_timers(model_dir, int8_dir, model, wl, base), wl, s)
        tick("timing from C")
        rows += c_rows(builds, work, model_dir, int8_dir, to_fm(base), to_fm(wl), s, tick)
        bar.close()
    _set_ratios(rows)
    return {
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "model": str(model_dir),
        "int8_model": "exported here (temporary copy, calibrated on the data)" if made_int8
        else str(int8_dir),
        "data": str(data),
        "samples": int(wl.shape[0]),
        "count_warmup": s.count_warmup,
        "count_samples": s.count_samples,
        "sizes": {k: net.sizes for k, net in model.nets.items()},
        "memory_states": model.preprocess.memory.state_words,
        "macs_per_step": step_macs(model),
        "reference": dict(zip(("engine", "call", "scope"), REFERENCE)),
        "builds": [{"name": b.name, "flags": b.flags, "init_options": b.init_options,
                    "packed": b.packed}
                   for b in builds],
        "rows": rows,
        "platform": {**timing.platform_info(), "blas_threads_before_timing": blas},
        "settings": {k: v for k, v in s.__dict__.items() if k != "builds"},
        "seconds": round(time.perf_counter() - t_start, 1),
    }


def _speed_models(model_dir: str | Path, int8_dir: str | Path | None
                  ) -> tuple[Path, artifact.HierarchicalModel, Path | None]:
    """The model and its exports to time: refuses a missing directory or an export of the
    wrong width (``--model`` int16, ``--int8`` int8) before anything is measured."""
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise InputError("no such model directory", path=str(model_dir), column="--model")
    model = modeldir.load(model_dir)
    _check_fixed_dir(model_dir, model, 16, "--model")
    if int8_dir is not None:
        int8_dir = Path(int8_dir)
        if not int8_dir.is_dir():
            raise InputError("no such model directory", path=str(int8_dir), column="--int8")
        _check_fixed_dir(int8_dir, model, 8, "--int8")
    return model_dir, model, int8_dir


def _speed_samples(data: Path, s: SpeedSettings) -> tuple[Any, np.ndarray, np.ndarray]:
    """The recording, its tare baseline and the samples to time (its contact samples, at most
    ``s.samples``); refuses fewer than two."""
    from fbgforce.recordings import dataset as fds
    from fbgforce.recordings.tare import tare

    ds = fds.load(data)
    base = tare(ds.wl_nm, ds.contact, ds.t_s, path=str(data))[0]
    wl = timing_samples(ds)[:s.samples]
    if wl.shape[0] < 2:
        raise InputError("fewer than 2 samples to time", path=str(data))
    return ds, base, wl


def _ticker(bar: Any, log: Callable[[str], None]) -> Callable[[str], None]:
    """One call per finished stage: advances the progress bar and logs the stage's name."""
    def tick(what: str) -> None:
        bar.set_postfix_str(what, refresh=False)
        bar.update(1)
        log(what)

    return tick


def _export_int8(model: artifact.HierarchicalModel, model_dir: Path, ds: Any, data: Path,
                 work: Path) -> Path:
    """The int8 export when none was given: a copy of the model in ``work``, calibrated on the
    first presses of ``data``; an export failure stops the run."""
    from fbgforce.tradeoff.artifacts import calibration_subset, export_fixed

    int8_dir = work / "int8"
    modeldir.save(model, int8_dir)
    err = export_fixed(int8_dir, 8, calibration_subset([ds], [str(data)], work))
    if err:
        raise InputError(err, path=str(model_dir))
    return int8_dir


def _python_rows(timers: list[tuple[Any, dict[str, Any], dict[str, Any]]], wl: np.ndarray,
                 s: SpeedSettings) -> tuple[list[dict[str, Any]], Any]:
    """The rows timed from Python, in one interleaved run on one BLAS thread, and the thread
    count found before it."""
    blas = timing.limit_blas_threads(1)
    # One batch length for every engine: a Python engine's per-call cost is spread over
    # as many samples as a C engine's, so the batch figures compare the engines, not the
    # lengths (measure() would otherwise size each engine's batch to a fixed time).
    batch = min(s.batch, wl.shape[0])
    times = timing.measure([t for t, _, _ in timers], wl.shape[0], single_calls=s.single_calls,
                           batch_size=batch, batch_reps=s.batch_reps, rounds=s.rounds,
                           min_batch=batch)
    rows: list[dict[str, Any]] = []
    for t, single, batch_row in timers:
        single["ns_per_sample"] = times[t.name]["single_ns"]
        batch_row["ns_per_sample"] = times[t.name]["batch_ns"]
        batch_row["batch_size"] = times[t.name]["batch_size"]
        rows += [batch_row, single]
    return rows, blas


def _set_ratios(rows: list[dict[str, Any]]) -> None:
    """Sorts the rows into table order and gives each timed row its time over the reference
    row's (:data:`REFERENCE`)."""
    rows.sort(key=_order)
    ref = next(r for r in rows if (r["engine"], r["call"], r["scope"]) == REFERENCE)
    for r in rows:
        if r["ns_per_sample"] is not None and ref["ns_per_sample"]:
            r["ratio"] = r["ns_per_sample"] / ref["ns_per_sample"]


#: Table order: engine, then call, caller and scope (build order kept within).
ENGINE_ORDER = ("fixed", "fixed-int8", "cfloat", "float", "onnx")


def _order(r: dict[str, Any]) -> tuple[int, int, int, int]:
    return (ENGINE_ORDER.index(r["engine"]), ("batch", "single").index(r["call"]),
            ("python", "c").index(r["caller"]), ("pipeline", "nets").index(r["scope"]))


def _fmt_us(ns: float | None) -> str:
    return "n/a" if ns is None else f"{ns / 1000:.3g}" if ns < 1e6 else f"{ns / 1000:.0f}"


def markdown_table(res: dict[str, Any]) -> str:
    """The result as a Markdown table (what the command prints), with a header line."""
    ref = res["reference"]
    sizes = sorted({r["batch_size"] for r in res["rows"]
                    if r["call"] == "batch" and r["caller"] == "python" and r["batch_size"]})
    lines = [f"{res['samples']} contact samples of {res['data']} (batches from Python: "
             f"{'/'.join(map(str, sizes)) or 'n/a'} samples per call; from C: all); "
             f"model {res['model']} "
             f"({res['macs_per_step']} MACs per step); {res['platform'].get('cpu', res['platform']['machine'])}, "
             f"{res['date_utc']} UTC; ratio = time / {ref['engine']} {ref['call']} ({ref['scope']} "
             f"only); instructions/step: callgrind, mean over {res['count_samples']} consecutive "
             f"steps that decided contact (all three nets run), from step "
             f">= {res['count_warmup']}",
             "",
             "| engine | call | from | scope | how | build | µs/sample | ratio | instructions/step | note |",
             "|---|---|---|---|---|---|---:|---:|---:|---|"]
    for r in res["rows"]:
        note = r["note"] or ""
        if r.get("profile_per_step"):
            top = list(r["profile_per_step"].items())[:3]
            note = ", ".join(f"{f} {100 * v / r['instructions_per_step']:.0f} %" for f, v in top) + \
                (f"; {note}" if note else "")
        if r["bit_exact"] is not None:
            note = ("bit-exact vs extension" if r["bit_exact"] else "DIFFERS from extension") + \
                (f"; {note}" if note else "")
        lines.append(
            f"| {r['engine']} | {r['call']} | {r['caller']} | {r['scope']} | {r['how']} | "
            f"{r['build'] or ''} | {_fmt_us(r['ns_per_sample'])} | "
            f"{'n/a' if r['ratio'] is None else format(r['ratio'], '.2f')} | "
            f"{'' if r['instructions_per_step'] is None else format(round(r['instructions_per_step']), ',')} | "
            f"{note} |")
    return "\n".join(lines)
