"""``fbgforce tradeoff``: what accuracy costs in time (docs/tradeoff.md)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from fbgforce.errors import InputError


def register(subparsers: Any) -> None:
    """Add the ``tradeoff`` subcommand."""
    from fbgforce.cli import add_json_flag

    p = subparsers.add_parser(
        "tradeoff", help="accuracy against compute time and filter delay over a grid",
        description="Train (or reuse) models over filters x network widths, run every engine "
                    "(numpy float64, onnxruntime, C float, C int16, C int8 with/without QAT) on "
                    "the same held-out presses, time them in one interleaved run, and write "
                    "tradeoff.json, tradeoff.csv, tradeoff.md and tradeoff.png to --out.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", nargs="+", metavar="FILE", help="recording(s) in the dataset contract")
    src.add_argument("--scene", metavar="NAME", help="simulate this scene (name or TOML path)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (models are "
                   "kept in DIR/models and reused by a later run with the same settings)")
    p.add_argument("--quick", action="store_true",
                   help="small grid, few epochs, short timing: the CI smoke run (< 60 s)")
    p.add_argument("--seed", type=int, default=0, help="split, training and simulation seed")
    p.add_argument("--epochs", type=int, default=None, help="max training epochs per net")
    p.add_argument("--time-budget", type=float, default=None, metavar="S",
                   help="wall-time cap per net in seconds (keeps the best weights so far)")
    p.add_argument("--sigmas", type=float, nargs="+", default=None, metavar="S",
                   help="causal Gaussian sigmas in samples (default 2 5 10; quick: 5)")
    p.add_argument("--memories", nargs="+", default=None, metavar="SPEC",
                   help="the memory axis, each as `fbgforce train --memory` takes it (default: "
                        "none, play, both, ema:4,7+play:0.03,0.1,0.25,0.5; quick: none, both)")
    p.add_argument("--grid", choices=("star", "full", "memory"), default="star",
                   help="star: filters at paper width + widths at the shipped filter + memories "
                        "at the shipped configuration; full: product; memory: the memories only")
    p.add_argument("--engines", nargs="+", default=None, metavar="NAME",
                   help="subset of: numpy-f64 onnx-f32 c-float c-int16 c-int8 c-int8-qat")
    p.add_argument("--qat-epochs", type=int, default=None, help="QAT fine-tuning epochs")
    p.add_argument("--no-target", action="store_true",
                   help="skip the Cortex-M4 instruction counts (fbgforce target-report)")
    add_json_flag(p)
    p.set_defaults(handler=_handler)


def _handler(args: argparse.Namespace) -> dict[str, Any]:
    # Imported here, not at the top: `fbgforce --help` loads every command module.
    from fbgforce.tradeoff.artifacts import prepare_data
    from fbgforce.tradeoff.grid import ENGINE_SPECS, Settings, quick_settings
    from fbgforce.tradeoff.outputs import markdown_table
    from fbgforce.tradeoff.run import run

    s = quick_settings(args.seed) if args.quick else Settings(seed=args.seed)
    if args.epochs is not None:
        if args.epochs < 1:
            raise InputError("must be at least 1", column="--epochs")
        s.epochs = args.epochs
    if args.time_budget is not None:
        s.time_budget_s = args.time_budget
    if args.sigmas:
        if any(v <= 0 for v in args.sigmas):
            raise InputError("sigmas must be positive (no filter is always in the grid)",
                             column="--sigmas")
        s.sigmas = tuple(args.sigmas)
        if s.default_sigma not in s.sigmas:
            s.default_sigma = s.sigmas[0]
    s.grid = args.grid
    if args.memories:
        from fbgforce.trainer.train import parse_memory

        for spec in args.memories:
            parse_memory(spec)                 # refuse a bad spec before any training
        s.memories = tuple(args.memories)
    if args.engines:
        known = [e.name for e in ENGINE_SPECS]
        bad = [e for e in args.engines if e not in known]
        if bad:
            raise InputError(f"unknown engine(s) {', '.join(bad)}; choose from {', '.join(known)}",
                             column="--engines")
        s.engines = tuple(args.engines)
    if args.qat_epochs is not None:
        s.qat_epochs = args.qat_epochs
    if args.no_target:
        s.target = False
    out = Path(args.out)

    def log(msg: str) -> None:
        print(f"tradeoff: {msg}", file=sys.stderr, flush=True)

    paths = prepare_data(args.data, args.scene, out, args.seed, log)
    res = run(paths, out, s, log)
    if not args.json:
        print(markdown_table(res))
        print()
        print(res["summary"])
    ok = [r for r in res["rows"] if r.get("status") == "ok"]
    return {
        "out": str(out),
        "rows": len(res["rows"]),
        "measured": len(ok),
        "missing": sorted({r["engine"] for r in res["rows"] if str(r.get("status", "")).startswith("missing")}),
        "reference": res["reference"],
        "ratios": res["ratios"],
        "pareto_compute": [f"{r['variant']}/{r['engine']}" for r in ok if r.get("pareto_compute")],
        "matches_reference": [f"{r['variant']}/{r['engine']}" for r in ok
                              if r.get("matches_reference") and not r.get("is_reference")],
        "summary": res["summary"],
        "files": {k: str(out / f"tradeoff.{k}") for k in ("json", "csv", "md", "png")
                  if (out / f"tradeoff.{k}").is_file()},
        "seconds": res["seconds"],
    }
