"""``fbgforce demo``: the whole chain on the built-in simulator, in one command.

simulate the paper's calibration protocol → train the hierarchical nets (causal filter) →
export ONNX, the fixed-point blob and C source → verify the C runtime against the integer
reference and the float model on every sample → report against the paper's numbers.
Every step is an ordinary subcommand; this one only strings them together so a newcomer sees
the product work end to end, and prints the commands it ran so they can be repeated one by one.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from fbgforce.cli import add_json_flag
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
            "against the integer reference, and compare with the paper. Takes a few minutes "
            "on 2 cores; --quick uses a small scene and finishes in well under a minute."),
    )
    p.add_argument("--out", default="fbgforce-demo", metavar="DIR",
                   help="working directory for the data, model and report (default: %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="small scene and few epochs: a smoke test of the chain, not of accuracy")
    p.add_argument("--seed", type=int, default=0, help="seed for simulation and training")
    add_json_flag(p)
    p.set_defaults(handler=run)


def _step(title: str, command: str) -> float:
    print(f"\n== {title}\n   $ {command}", file=sys.stderr)
    return time.perf_counter()


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``fbgforce demo``."""
    from fbgforce import dataset
    from fbgforce import model as fm
    from fbgforce.export.exporter import export_model
    from fbgforce.export.verify import verify
    from fbgforce.metrics import headline
    from fbgforce.sim import simulate
    from fbgforce.trainer.evaluate import evaluate
    from fbgforce.trainer.report import build_report, to_markdown, write
    from fbgforce.trainer.train import train

    if args.seed < 0:
        raise InputError(f"must be >= 0, got {args.seed}", column="--seed")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = "smoke" if args.quick else "calibration"
    epochs = 15 if args.quick else 200
    data_path = out / f"{scene}.csv"
    model_dir = out / "model"
    seconds: dict[str, float] = {}

    t = _step("simulate", f"fbgforce simulate --scene {scene} --seed {args.seed} --out {data_path}")
    ds = simulate(scene, seed=args.seed)
    dataset.save(ds, data_path)
    seconds["simulate"] = time.perf_counter() - t
    print(f"   {len(ds)} samples, {len(set(ds.press_id.tolist()))} presses", file=sys.stderr)

    t = _step("train", f"fbgforce train --data {data_path} --out {model_dir} --epochs {epochs} "
                       f"--seed {args.seed} --filter causal")
    model = train([data_path], epochs=epochs, seed=args.seed, filter="causal")
    fm.save(model, model_dir)
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

    engines = {}
    for engine in ("float", "onnx", "fixed"):
        t = _step(f"evaluate ({engine})", f"fbgforce evaluate --model {model_dir} --data "
                                          f"{data_path} --engine {engine}")
        engines[engine] = evaluate(model_dir, [data_path], engine=engine, split="test")
        seconds[f"evaluate_{engine}"] = time.perf_counter() - t
        print(f"   test split: {headline(engines[engine])}", file=sys.stderr)

    t = _step("report", f"fbgforce report --data {data_path} --model {model_dir} "
                        f"--epochs {epochs} --out {out / 'report'}")
    rep = build_report([data_path], model_dir=model_dir, epochs=epochs, seed=args.seed)
    write(rep, out / "report")
    seconds["report"] = time.perf_counter() - t
    if not args.json:
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
        "checks": rep["checks"],
        "seconds": seconds,
    }
