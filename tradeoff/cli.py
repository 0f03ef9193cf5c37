"""``fbgforce tradeoff``: what accuracy costs in time (docs/tradeoff.md)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from fbgforce import fileio
from fbgforce.cliargs import add_data, add_model, add_seed, command, positive_int
from fbgforce.errors import InputError


def register(subparsers: Any) -> None:
    """Add the ``tradeoff`` and ``bench-speed`` subcommands."""
    with command(subparsers, "tradeoff", _handler,
                 help="accuracy against compute time and filter delay over a grid",
                 description="Train (or reuse) models over filters x network widths, run every "
                             "engine (numpy float64, onnxruntime, C float, C int16, C int8 "
                             "with/without QAT) on the same held-out presses, time them in one "
                             "interleaved run, and write tradeoff.json, tradeoff.csv, "
                             "tradeoff.md and tradeoff.png to --out.") as p:
        _add_source(p, "recording(s) in the dataset contract", nargs="+")
        p.add_argument("--out", required=True, metavar="DIR", help="output directory (models are "
                       "kept in DIR/models and reused by a later run with the same settings)")
        p.add_argument("--quick", action="store_true",
                       help="small grid, few epochs, short timing: the CI smoke run (< 60 s)")
        add_seed(p, "split, training and simulation seed")
        _add_grid_options(p)
    with command(subparsers, "bench-speed", _bench_speed_handler,
                 help="every engine timed side by side in one run, with ratios",
                 description="Time one model in every engine on the same contact samples in one "
                             "run: the C runtime int16, int8 and float (batch and single-sample, "
                             "from Python through cffi and from C through a compiled driver), "
                             "numpy float64 and onnxruntime float32 (whole pipeline and nets "
                             "only, batch and single-sample); per-sample CPU time, the ratio to "
                             "onnxruntime's batch over the nets, and instructions per step "
                             "counted by callgrind (valgrind). Prints a Markdown table; --out "
                             "writes the JSON (keys in docs/cli.md).") as p:
        add_model(p, "trained model directory with its int16 export (fbgforce export)",
                  metavar="DIR")
        p.add_argument("--int8", metavar="DIR", help="the int8 export of the same model "
                       "(fbgforce export --bits 8 on a copy); default: exported here, calibrated "
                       "on the data")
        _add_source(p, "recording in the dataset contract", nargs=None)
        add_seed(p, "simulation seed for --scene")
        _add_bench_speed_options(p)
        p.add_argument("--out", metavar="FILE", help="write the JSON result here")


def _add_source(p: argparse.ArgumentParser, data_help: str, nargs: str | None) -> None:
    """``--data`` or ``--scene``, one of them required."""
    src = p.add_mutually_exclusive_group(required=True)
    add_data(src, data_help, nargs=nargs, required=False)
    src.add_argument("--scene", metavar="NAME", help="simulate this scene (name or TOML path)")


def _add_grid_options(p: argparse.ArgumentParser) -> None:
    """The ``tradeoff`` grid: its training, its axes, its engines."""
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
                   help="subset of: float onnx cfloat fixed fixed-int8 fixed-int8-qat "
                        "(also accepted: numpy-f64 onnx-f32 c-float c-int16 c-int8 c-int8-qat)")
    p.add_argument("--qat-epochs", type=int, default=None, help="QAT fine-tuning epochs")
    p.add_argument("--no-target", action="store_true",
                   help="skip the Cortex-M4 instruction counts (fbgforce target-report)")
    p.add_argument("--decision", metavar="MODEL",
                   help="instead of the grid of models: the contact decision's curve of this "
                        "exported model on --data/--scene, false contact events per minute at "
                        "rest against onset delay over the Schmitt trigger's rise margin and "
                        "count and the CUSUM's threshold and drift, with each rule's quickest "
                        "setting within 1 false event per minute (decision.json, decision.md, "
                        "decision.csv, decision.png in --out)")


def _add_bench_speed_options(p: argparse.ArgumentParser) -> None:
    """What ``bench-speed`` times, how long, and which builds."""
    p.add_argument("--samples", type=positive_int, default=5000,
                   help="contact samples timed (default 5000)")
    p.add_argument("--batch", type=positive_int, default=2000,
                   help="samples per batch call from Python, the same for every engine "
                        "(default 2000; from C one batch is all samples)")
    p.add_argument("--single-calls", type=positive_int, default=3000,
                   help="single-sample calls timed per engine from Python (default 3000)")
    p.add_argument("--rounds", type=positive_int, default=6,
                   help="interleaved rounds of the Python timing (default 6)")
    p.add_argument("--reps", type=positive_int, default=7,
                   help="passes over the samples from C; the best counts (default 7)")
    p.add_argument("--count-samples", type=positive_int, default=200,
                   help="consecutive contact steps counted by callgrind per engine and build "
                        "(default 200)")
    p.add_argument("--count-warmup", type=int, default=100, metavar="N",
                   help="the counted steps start at or after this step of the stream "
                        "(filter and memory warm-up; default 100)")
    p.add_argument("--c-build", action="append", default=None, metavar="NAME=FLAGS",
                   help="a driver build: compiler flags for runtime_c/src/*.c and the driver, "
                        "e.g. 'O2=-O2' or 'native=-O3 -march=native'; repeat for several. "
                        "Always measured: 'as-extension', the cffi extension's flags")
    p.add_argument("--no-kernels", action="store_true",
                   help="skip the builds per dense-layer kernel (FBG_OPT_KERNEL_*)")
    p.add_argument("--no-callgrind", action="store_true", help="skip the instruction counts")


def _bench_speed_handler(args: argparse.Namespace) -> dict[str, Any]:
    import json
    import tempfile

    from fbgforce.jsonutil import json_default
    from fbgforce.tradeoff.artifacts import prepare_data
    from fbgforce.tradeoff.cdriver import parse_build
    from fbgforce.tradeoff.speed import SpeedSettings, bench_speed, markdown_table

    builds = []
    for text in args.c_build or ():
        try:
            builds.append(parse_build(text))
        except ValueError as exc:
            raise InputError(str(exc), column="--c-build") from exc
    s = SpeedSettings(samples=args.samples, batch=args.batch, single_calls=args.single_calls, rounds=args.rounds,
                      c_reps=args.reps, count_samples=args.count_samples,
                      count_warmup=max(0, args.count_warmup),
                      callgrind=not args.no_callgrind, kernels=not args.no_kernels,
                      builds=tuple(builds))

    def log(msg: str) -> None:
        print(f"bench-speed: {msg}", file=sys.stderr, flush=True)

    out = Path(args.out) if args.out else None
    if out is not None:
        fileio.check_output_file(out, "--out")
    with tempfile.TemporaryDirectory(prefix="fbgforce-scene-") as tmp:
        data = prepare_data([args.data] if args.data else None, args.scene, Path(tmp), args.seed,
                            log)[0]
        # Stage lines where no progress bar shows (stderr not a terminal: logs, CI).
        res = bench_speed(args.model, data, s, int8_dir=args.int8,
                          log=(lambda m: None) if sys.stderr.isatty() else log)
    if args.scene:  # the simulated file was temporary: name what made it
        res["data"] = f"scene {args.scene} (seed {args.seed}, simulated)"
    if out is not None:
        fileio.write_text(out, json.dumps(res, indent=1, default=json_default) + "\n", "--out")
    if not args.json:
        print(markdown_table(res))
    return res


def _decision_handler(args: argparse.Namespace) -> dict[str, Any]:
    import json

    from fbgforce.recordings import dataset
    from fbgforce.jsonutil import json_default
    from fbgforce.tradeoff.artifacts import prepare_data
    from fbgforce.tradeoff.decision import csv_text, decision_curve, markdown, plot

    out = Path(args.out)
    model = Path(args.decision)
    if not (model / "model.fbgm").is_file():
        raise InputError("no exported model here; run 'fbgforce export --model DIR' first",
                         path=str(model), column="--decision")

    def log(msg: str) -> None:
        print(f"tradeoff: {msg}", file=sys.stderr, flush=True)

    paths = prepare_data(args.data, args.scene, out, args.seed, log)
    res = decision_curve(model, [dataset.load(p) for p in paths])
    res["data"] = [str(p) for p in paths]
    out.mkdir(parents=True, exist_ok=True)
    (out / "decision.json").write_text(json.dumps(res, indent=1, default=json_default) + "\n")
    (out / "decision.md").write_text(markdown(res) + "\n")
    (out / "decision.csv").write_text(csv_text(res))
    png = plot(res, out / "decision.png")
    if not args.json:
        print(markdown(res))
    return {"out": str(out), "figure": str(png), **res}


def _handler(args: argparse.Namespace) -> dict[str, Any]:
    if args.decision:
        return _decision_handler(args)
    # Imported here, not at the top: `fbgforce --help` loads every command module.
    from fbgforce.tradeoff.artifacts import prepare_data
    from fbgforce.tradeoff.grid import ENGINE_ALIASES, ENGINE_SPECS, Settings, quick_settings
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
        from fbgforce.trainer.memory import parse_memory

        for spec in args.memories:
            parse_memory(spec)                 # refuse a bad spec before any training
        s.memories = tuple(args.memories)
    if args.engines:
        known = [e.name for e in ENGINE_SPECS]
        names = [ENGINE_ALIASES.get(e, e) for e in args.engines]
        bad = [e for e, name in zip(args.engines, names) if name not in known]
        if bad:
            raise InputError(f"unknown engine(s) {', '.join(bad)}; choose from {', '.join(known)}",
                             column="--engines")
        s.engines = tuple(dict.fromkeys(names))
    if args.qat_epochs is not None:
        s.qat_epochs = args.qat_epochs
    if args.no_target:
        s.target = False
    out = Path(args.out)
    fileio.check_output_dir(out, "--out")

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
