"""``fbgforce demo``: the whole chain on the built-in simulator, in one command.

simulate the paper's calibration protocol → train the hierarchical nets (causal filter) →
export ONNX, the fixed-point blob and C source → verify the C runtime against the integer
reference and the float model on every sample → score every engine → report against the
paper's numbers → draw the figures (``fbgforce.evaluation.figures``) into ``<out>/figures/``.
Every step is an ordinary subcommand; this one only strings them together so a newcomer sees
the product work end to end, and prints the commands it ran so they can be repeated one by one.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.cliargs import add_json_flag, positive_int
from fbgforce.errors import InputError


def register(subparsers: Any) -> None:
    """Add the ``demo`` subcommand."""
    p = subparsers.add_parser(
        "demo",
        help="simulate → train → export → verify → report, on the built-in simulator",
        description=(
            "Run the whole chain on the built-in simulator: simulate the calibration scene "
            "(the paper's protocol, ~234k samples), train the three nets with the causal "
            "filter, export ONNX + fixed-point blob + C, verify the C runtime bit for bit "
            "against the integer reference, score each engine, compare with the paper and "
            "draw the figures (PNG, in DIR/figures/). Takes a few minutes on 2 cores; --quick "
            "uses a small scene and finishes in well under a minute."),
    )
    p.add_argument("--out", default="fbgforce-demo", metavar="DIR",
                   help="directory for everything the demo writes: data, model, report, "
                        "figures (default: %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="small scene and few epochs: a smoke test of the chain, not of accuracy")
    p.add_argument("--epochs", type=positive_int, default=None,
                   help="training epochs of every net (default: 200, or 15 with --quick)")
    p.add_argument("--seed", type=int, default=0, help="seed for simulation and training")
    add_json_flag(p)
    p.set_defaults(handler=run)


#: Engines the demo scores and times (the float reference, ONNX, the C fixed-point runtime the
#: firmware uses, the C float build).
ENGINES_SCORED = ("float", "onnx", "fixed", "cfloat")


def _step(title: str, command: str | None) -> float:
    print(f"\n== {title}" + (f"\n   $ {command}" if command else ""), file=sys.stderr)
    return time.perf_counter()


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``fbgforce demo``."""
    if args.seed < 0:
        raise InputError(f"must be >= 0, got {args.seed}", column="--seed")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a directory", path=str(out), column="--out")
    out.mkdir(parents=True, exist_ok=True)
    scene = "smoke" if args.quick else "calibration"
    epochs = args.epochs if args.epochs is not None else (15 if args.quick else 200)
    data_path = out / f"{scene}.csv"
    model_dir = out / "model"
    seconds: dict[str, float] = {}

    _simulate(scene, args.seed, data_path, seconds)
    model, verified = _train_export_verify(args.seed, epochs, data_path, model_dir, seconds)
    recording, engines, timings = _evaluate_engines(args.seed, model, data_path, model_dir,
                                                    seconds)
    rep = _report(args.seed, epochs, data_path, model_dir, out / "report", seconds)
    pngs = _figures(args.seed, out / "figures", model, model_dir, recording, data_path,
                    engines, timings, seconds)
    if not args.json:
        from fbgforce.trainer.report import to_markdown

        print(to_markdown(rep))
    if verified["mismatches"]:
        print(f"fbgforce demo: WARNING: {verified['mismatches']} samples where the C runtime "
              "and the integer reference differ", file=sys.stderr)
    return {
        "scene": scene,
        "data": str(data_path),
        "model": str(model_dir),
        "verify": verified,
        "evaluate": engines,
        "report": str(out / "report"),
        "figures": pngs,
        "checks": rep["checks"],
        "seconds": seconds,
    }


# The steps import their parts when they run: ``fbgforce --help`` loads every command module.

def _simulate(scene: str, seed: int, data_path: Path, seconds: dict[str, float]) -> None:
    """Simulate the scene into ``data_path``."""
    from fbgforce.recordings import dataset
    from fbgforce.sim import simulate

    t = _step("simulate", f"fbgforce simulate --scene {scene} --seed {seed} --out {data_path}")
    ds = simulate(scene, seed=seed)
    dataset.save(ds, data_path)
    seconds["simulate"] = time.perf_counter() - t
    print(f"   {len(ds)} samples, {len(set(ds.press_id.tolist()))} presses", file=sys.stderr)


def _train_export_verify(seed: int, epochs: int, data_path: Path, model_dir: Path,
                         seconds: dict[str, float]) -> tuple[Any, dict[str, Any]]:
    """Train into ``model_dir``, export and verify: the float model and the verdict."""
    from fbgforce.export.exporter import export_model
    from fbgforce.export.verify import verify
    from fbgforce.model import modeldir
    from fbgforce.trainer.train import train

    t = _step("train", f"fbgforce train --data {data_path} --out {model_dir} --epochs {epochs} "
                       f"--seed {seed} --filter causal")
    model = train([data_path], epochs=epochs, seed=seed, filter="causal")
    modeldir.save(model, model_dir)
    seconds["train"] = time.perf_counter() - t

    t = _step("export", f"fbgforce export --model {model_dir}")
    exported = export_model(model_dir)
    seconds["export"] = time.perf_counter() - t
    print(f"   blob {exported['blob_bytes']} B, files: "
          + ", ".join(Path(f).name for f in exported["files"]), file=sys.stderr)

    t = _step("verify", f"fbgforce verify --model {model_dir} --data {data_path} --json")
    verified = verify(model_dir, [data_path])
    seconds["verify"] = time.perf_counter() - t
    print(f"   {verified['samples']} samples, {verified['mismatches']} C/integer-reference "
          f"mismatches, {verified['contact_disagreements']} fixed/float contact disagreements",
          file=sys.stderr)
    return model, verified


def _evaluate_engines(seed: int, model: Any, data_path: Path, model_dir: Path,
                      seconds: dict[str, float]) -> tuple[Any, dict[str, Any], list[dict]]:
    """Score every engine of :data:`ENGINES_SCORED` on the test presses: the recording, the
    metrics by engine and the timings."""
    from fbgforce.evaluation.metrics import headline
    from fbgforce.recordings import dataset
    from fbgforce.trainer.evaluate import evaluate

    # Each engine runs the whole recording (loaded once, so the time is the engine's and the
    # scoring's, not the CSV parser's) and is scored on the test presses.
    recording = dataset.load(data_path)
    engines: dict[str, Any] = {}
    timings = []
    for engine in ENGINES_SCORED:
        t = _step(f"evaluate ({engine})", f"fbgforce evaluate --model {model_dir} --data "
                                          f"{data_path} --engine {engine} --split test")
        m = evaluate(model_dir, [recording], engine=engine, split="test", seed=seed,
                     model=model)
        run_s = time.perf_counter() - t
        m.update({"data": [str(data_path)], "us_per_sample": 1e6 * run_s / len(recording)})
        engines[engine] = m
        timings.append({"engine": engine, "us_per_sample": m["us_per_sample"],
                        "rmse_force_N": m["rmse_force_N"]})
        seconds[f"evaluate_{engine}"] = run_s
        print(f"   test split: {headline(m)}; {m['us_per_sample']:.2f} us/sample", file=sys.stderr)
    return recording, engines, timings


def _report(seed: int, epochs: int, data_path: Path, model_dir: Path, report_dir: Path,
            seconds: dict[str, float]) -> dict[str, Any]:
    """The report against the paper's numbers, written to ``report_dir``."""
    from fbgforce.trainer.report import build_report, write

    t = _step("report", f"fbgforce report --data {data_path} --model {model_dir} "
                        f"--epochs {epochs} --out {report_dir}")
    rep = build_report([data_path], model_dir=model_dir, epochs=epochs, seed=seed)
    write(rep, report_dir)
    seconds["report"] = time.perf_counter() - t
    return rep


def _figures(seed: int, figures_dir: Path, model: Any, model_dir: Path, recording: Any,
             data_path: Path, engines: dict[str, Any], timings: list[dict],
             seconds: dict[str, float]) -> list[dict[str, Any]]:
    """The figures of the fixed-point engine's outputs, what the firmware would compute."""
    from fbgforce.evaluation import figures
    from fbgforce.geometry import PAD_SIZE_MM
    from fbgforce.trainer.evaluate import SPLITS, run_recording
    from fbgforce.trainer.report import PAPER
    from fbgforce.trainer.data import split_rows
    from fbgforce.trainer.scoring import model_pad_mm

    t = _step("figures", None)
    shown = "fixed"
    pngs = figures.write_demo_figures(
        figures_dir, ds=recording,
        test_rows=np.flatnonzero(split_rows(recording, seed) == SPLITS.index("test") - 1),
        pred=run_recording(shown, model_dir, model, recording, str(data_path)), engine=shown,
        metrics=engines[shown], paper=PAPER["network"], timings=timings,
        pad_mm=model_pad_mm(model) or PAD_SIZE_MM)
    seconds["figures"] = time.perf_counter() - t
    for f in pngs:
        print(f"   {f['path']}: {f['title']}", file=sys.stderr)
    return pngs
