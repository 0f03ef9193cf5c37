"""The whole run: train or reuse every variant, evaluate and time every engine, count on the
Cortex-M4, score, and write the outputs."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fbgforce.evaluation import engines as fengines
from fbgforce.evaluation import metrics as fmetrics
from fbgforce.model import artifact as fm
from fbgforce.errors import InputError
from fbgforce.tradeoff import artifacts, scoring, timing
from fbgforce.tradeoff.grid import (ENGINE_SPECS, SPECS_BY_NAME, EngineSpec, Settings, Variant,
                                    scaled_sizes, step_macs, variants)
from fbgforce.tradeoff.outputs import summary_paragraph, write_outputs
from fbgforce.tradeoff.timers import make_timer, timing_samples


def target_instructions(model_dir: Path, data: Path | None = None, samples: int = 64,
                        timeout_s: float = 300.0) -> dict[str, Any]:
    """Cortex-M4 instruction counts per step from ``fbgforce target-report``.

    Returns ``{"m4_instructions_per_step": worst step of the DSP build (the shipped one),
    "m4_instructions_portable": worst step of the portable C build,
    "m4_cycles_per_step_estimate": the DSP worst step's cycles estimated from its instruction
    mix (docs/firmware.md), "m4_bit_exact": ...}``,
    or ``{"m4_note": why not}`` when the toolchain is missing or the command fails. The report
    runs in a child process, so a hung QEMU is bounded by ``timeout_s``.
    """
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
            "m4_cycles_per_step_estimate": rep.get("cycles_per_step_estimate"),
            "m4_budget_fraction_cycles_at_168MHz": rep.get("budget_fraction_cycles_at_168MHz"),
            "m4_flash_bytes": rep.get("flash_bytes")}


def _model_bytes(spec: EngineSpec, model: fm.HierarchicalModel, model_dir: Path) -> int:
    """Bytes of the model as the engine holds it: the blob for C fixed, parameters otherwise."""
    if spec.engine == "fixed":
        blob = model_dir / "model.fbgm"
        if blob.is_file():
            return blob.stat().st_size
    n = sum(w.size + b.size for net in model.nets.values() for w, b in zip(net.weights, net.biases))
    return int(n * spec.dtype_bytes)


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
    from fbgforce.recordings.tare import sample_rate_hz
    from fbgforce.trainer import train as tr
    from fbgforce.trainer.data import load_datasets

    t_run = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    ds_list, described = load_datasets([str(p) for p in paths])
    sources = [str(p) for p in paths]
    digest = artifacts.data_digest(paths)
    rate_hz = float(np.median([sample_rate_hz(ds.t_s) for ds in ds_list]))
    specs = [sp for sp in ENGINE_SPECS if sp.name in s.engines]
    calib = artifacts.calibration_subset(ds_list, sources, out)
    prepared_cache: dict[tuple[str, float], Any] = {}
    rows: list[dict[str, Any]] = []
    timers: list[timing.Timer] = []
    timer_rows: dict[str, dict[str, Any]] = {}
    train_seconds: dict[str, float] = {}

    for v in variants(s):
        key_pf = (v.filter, v.sigma)
        if key_pf not in prepared_cache:
            prepared_cache[key_pf] = tr.prepare(ds_list, seed=s.seed, filter=v.filter,
                                                sigma=v.sigma, sources=sources)
        prep = prepared_cache[key_pf]
        key = {"variant": v.tag, "filter": v.filter, "sigma": v.sigma, "memory": v.memory,
               "sizes": scaled_sizes(v.width), "seed": s.seed, "epochs": s.epochs,
               "time_budget_s": s.time_budget_s, "idle_pads": s.idle_pads, "data": digest}
        model_dir = out / "models" / v.tag
        model = _variant_model(v, key, model_dir, prep, sources, s, log, train_seconds)
        dirs, export_err = _variant_artifacts(v, key, model, model_dir, prep, specs, calib, out,
                                              s, log)
        common = _common_columns(v, model, rate_hz)
        for sp in specs:
            row, timer = _engine_row(sp, v, common, dirs, export_err, prep, log)
            rows.append(row)
            if timer is not None:
                timers.append(timer)
                timer_rows[timer.name] = row

    log(f"timing {len(timers)} engine/model pairs (interleaved) ...")
    blas_threads = _time_engines(timers, timer_rows, ds_list, s)
    _count_on_target(rows, s, Path(sources[0]), log)
    ref = scoring.reference(rows, s)
    scoring.score(rows, ref)
    scoring.mark_pareto(rows)
    result = {
        "command": " ".join(sys.argv) if sys.argv and sys.argv[0] else None,
        "data": described, "sample_rate_hz": rate_hz, "quantizer_calibration": calib,
        "settings": {k: v for k, v in s.__dict__.items()},
        "reference": None if ref is None else {"variant": ref["variant"], "engine": ref["engine"]},
        "rows": rows,
        "ratios": scoring.ratios(rows, s),
        "train_seconds": train_seconds,
        "seconds": time.perf_counter() - t_run,
        "platform": {**timing.platform_info(), "blas_threads_before_timing": blas_threads},
    }
    result["summary"] = summary_paragraph(result)
    write_outputs(result, out, log)
    return result


def _variant_model(v: Variant, key: dict[str, Any], model_dir: Path, prep: Any,
                   sources: list[str], s: Settings, log: Callable[[str], None],
                   train_seconds: dict[str, float]) -> fm.HierarchicalModel:
    """The variant's float model: the one saved under ``model_dir`` when its key matches
    (same settings, same data), else trained now, saved with its key and its training time
    noted in ``train_seconds``; its ONNX export is written either way."""
    from fbgforce.export.onnx_export import ONNX_FILE, export_onnx
    from fbgforce.trainer import train as tr

    model = artifacts.reusable_model(model_dir, key)
    if model is None:
        log(f"training {v.tag} ...")
        t0 = time.perf_counter()
        model = tr.train(sources, epochs=s.epochs, seed=s.seed, filter=v.filter,
                         sigma=v.sigma, sizes={k: h for k, h in key["sizes"].items()},
                         prepared=prep, time_budget_s=s.time_budget_s, memory=v.memory,
                         idle_pads=s.idle_pads)
        train_seconds[v.tag] = time.perf_counter() - t0
        artifacts.save_with_key(model, model_dir, key)
    else:
        log(f"reusing {model_dir}")
    export_onnx(model, model_dir / ONNX_FILE)
    return model


def _variant_artifacts(v: Variant, key: dict[str, Any], model: fm.HierarchicalModel,
                       model_dir: Path, prep: Any, specs: list[EngineSpec], calib: Any,
                       out: Path, s: Settings, log: Callable[[str], None]
                       ) -> tuple[dict[str, tuple[Path, fm.HierarchicalModel]],
                                  dict[str, str | None]]:
    """The model directory each artifact (float, int8, int8-qat) of the variant lives in, and
    each fixed-point export's error (None: exported). Only causal variants are exported, and
    the int8 artifacts only for the reference variant unless every variant is asked for; an
    export failure only affects the fixed engines."""
    from fbgforce.trainer import qat

    dirs: dict[str, tuple[Path, fm.HierarchicalModel]] = {"float": (model_dir, model)}
    export_err: dict[str, str | None] = {}
    int8_here = s.int8_all_variants or v == Variant("causal", s.default_sigma, "paper")
    if not (v.causal and any(sp.engine == "fixed" for sp in specs)):
        return dirs, export_err
    export_err["float"] = artifacts.export_fixed(model_dir, 16, calib)
    if any(sp.artifact == "int8" for sp in specs) and int8_here:
        d8 = out / "models" / f"{v.tag}-int8"
        if artifacts.reusable_model(d8, {**key, "artifact": "int8"}) is None:
            artifacts.save_with_key(model, d8, {**key, "artifact": "int8"})
        dirs["int8"] = (d8, model)
        export_err["int8"] = artifacts.export_fixed(d8, 8, calib)
    if any(sp.artifact == "int8-qat" for sp in specs) and int8_here:
        dq = out / "models" / f"{v.tag}-int8-qat"
        qkey = {**key, "artifact": "int8-qat", "qat_epochs": s.qat_epochs, "qat_rule": 2}
        qmodel = artifacts.reusable_model(dq, qkey)
        if qmodel is None:
            log(f"QAT fine-tuning {v.tag} (int8 weights) ...")
            qmodel = _qat_model(model, prep, s, qat)
            artifacts.save_with_key(qmodel, dq, qkey)
        dirs["int8-qat"] = (dq, qmodel)
        export_err["int8-qat"] = artifacts.export_fixed(dq, 8, calib)
    return dirs, export_err


def _common_columns(v: Variant, model: fm.HierarchicalModel, rate_hz: float) -> dict[str, Any]:
    """The columns every engine's row of the variant shares: its filter, memory and cost."""
    return {
        "variant": v.tag, "width": v.width, "filter": v.filter,
        "sigma": v.sigma if v.filter != "none" else None, "causal": v.causal,
        "filter_taps": 0 if v.filter == "none" else int(model.preprocess.taps.size),
        "filter_delay_ms": _filter_delay_ms(model, rate_hz),
        "memory": v.memory, "memory_states": model.preprocess.memory.state_words,
        # one int32 in fbg_state per state: load averages, plays, location averages
        "memory_state_bytes": 4 * model.preprocess.memory.state_words,
        "macs_nets": model.macs, "macs": step_macs(model),
        "sizes": {k: net.sizes for k, net in model.nets.items()},
    }


def _engine_row(sp: EngineSpec, v: Variant, common: dict[str, Any],
                dirs: dict[str, tuple[Path, fm.HierarchicalModel]],
                export_err: dict[str, str | None], prep: Any, log: Callable[[str], None]
                ) -> tuple[dict[str, Any], timing.Timer | None]:
    """One engine on one variant: its row with the test presses' metrics, or with the status
    that says why it was not measured, and the timer that will time it (None when it cannot
    be timed). A failing engine is recorded in its row and does not stop the grid."""
    row: dict[str, Any] = {**common, "engine": sp.name, "weight_bits": sp.weight_bits,
                           "act_bits": sp.act_bits, "qat": sp.artifact == "int8-qat"}
    if sp.engine != "float" and sp.engine != "onnx" and not v.causal:
        row["status"] = "n/a: the centred filter is offline only"
        return row, None
    if sp.artifact not in dirs:
        row["status"] = "n/a: int8 engines run on the reference variant only (--quick)"
        return row, None
    mdir, mdl = dirs[sp.artifact]
    err = export_err.get(sp.artifact) if sp.engine == "fixed" else None
    if err:
        row["status"] = f"missing: {err}"
        return row, None
    row["model_bytes"] = _model_bytes(sp, mdl, mdir)
    try:
        fn = fengines.get_engine(sp.engine)
    except InputError as exc:
        row["status"] = f"missing: {exc}"
        return row, None
    test_rows = prep.rows("test")
    try:
        preds = [fn(mdir, mdl, r.ds.wl_nm, r.baseline_nm) for r in prep.recordings]
    except Exception as exc:  # one broken engine must not lose the rest of the grid
        row["status"] = f"error: {type(exc).__name__}: {exc}"
        log(f"{v.tag}/{sp.name}: {row['status']}")
        return row, None
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
        return row, None
    row["_dir"] = mdir
    return row, t


def _time_engines(timers: list[timing.Timer], timer_rows: dict[str, dict[str, Any]],
                  ds_list: list[Any], s: Settings) -> int | None:
    """Times every engine in one interleaved run on one BLAS thread and writes the figures
    into its row; returns the BLAS thread count found before."""
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
    return blas_threads


def _count_on_target(rows: list[dict[str, Any]], s: Settings, data: Path,
                     log: Callable[[str], None]) -> None:
    """The Cortex-M4 counts of every timed fixed-point row when ``s.target`` asks for them,
    one ``target-report`` per model directory; every row loses its private ``_dir``."""
    target_cache: dict[str, dict[str, Any]] = {}
    for r in rows:
        mdir = r.pop("_dir", None)
        r["m4_instructions_per_step"] = None
        if s.target and mdir is not None and SPECS_BY_NAME[r["engine"]].engine == "fixed":
            if str(mdir) not in target_cache:
                log(f"Cortex-M4 counts for {Path(mdir).name} ...")
                target_cache[str(mdir)] = target_instructions(mdir, data)
            r.update(target_cache[str(mdir)])


def _qat_model(model: fm.HierarchicalModel, prep: Any, s: Settings, qat: Any
               ) -> fm.HierarchicalModel:
    z = prep.inputs(model.preprocess)
    trn, val = prep.rows("train"), prep.rows("val")
    truth = (prep.contact, prep.force_N, prep.x_mm, prep.y_mm)
    tuned, _ = qat.finetune(model, z[trn], *(t[trn] for t in truth),
                            val=(z[val], *(t[val] for t in truth)) if val.size else None,
                            weight_bits=8, act_bits=16, epochs=s.qat_epochs, seed=s.seed)
    return tuned
