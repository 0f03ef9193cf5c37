"""``fbgforce teleop``: the bilateral egg-grasp scene in closed loop (docs/cli.md#teleop)."""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any

from fbgforce import fileio
from fbgforce.cliargs import add_model, add_seed, at_least, command
from fbgforce.errors import InputError

FEEDBACK_CHOICES = ("estimator", "true", "none")


def register(subparsers: Any) -> None:
    """Add the ``teleop`` subcommand."""
    with command(subparsers, "teleop", run,
                 help="closed-loop teleoperation: pick up an egg with force feedback (paper "
                      "Fig. 7)",
                 description="Simulate the 1 kHz bilateral loop of the paper's §VI: an operator "
                             "on a Touch-like haptic master closes a two-finger gripper on an "
                             "egg, the fingertip (simulator + runtime) reports the force, the "
                             "master's stiffness follows it, and the arm then lifts and carries "
                             "the egg. Writes the Fig. 7 plot (run 0), summary.json and runs.csv "
                             "to --out.") as p:
        p.add_argument("--scene", default="egg_grasp",
                       help="built-in teleop scene name or TOML path (default egg_grasp)")
        add_model(p, "model directory (needed for --feedback estimator; the fixed engine needs "
                     "'fbgforce export' first)", metavar=None, required=False)
        p.add_argument("--out", required=True, help="output directory")
        add_seed(p, "seed of run 0 (operator, egg, noise); run k uses seed + k (default 0)")
        p.add_argument("--runs", type=int, default=1,
                       help="number of seeded runs (operators); rates over all, plot of run 0")
        p.add_argument("--feedback", choices=FEEDBACK_CHOICES, default="estimator",
                       help="what sets the master's stiffness: the runtime's estimate "
                            "(default), the true force, or nothing")
        p.add_argument("--engine", choices=("fixed", "cfloat"), default="fixed",
                       help="runtime for --feedback estimator: C fixed point (default) or C "
                            "float")
        p.add_argument("--delay-ms", type=float, default=0.0,
                       help="extra transport delay between the force source and the master, ms")
        p.add_argument("--allow-other-device", action="store_true",
                       help="run the estimator even if the scene's fingertip is not the device "
                            "the model was calibrated on (default: refuse; to measure what it "
                            "costs)")


def make_feedback(kind: str, model: str | None, engine: str, delay_ms: float,
                  allow_other_device: bool = False) -> Any:
    """The feedback source for the command-line options."""
    from fbgforce.teleop.feedback import NoFeedback, SensorFeedback, TrueForce

    if delay_ms < 0:
        raise InputError(f"must be >= 0, got {delay_ms:g}", column="--delay-ms")
    if kind == "none":
        return NoFeedback()
    if kind == "true":
        return TrueForce(delay_ms=delay_ms)
    if not model:
        raise InputError("--feedback estimator needs --model MODEL_DIR (or use --feedback "
                         "true|none)", column="--model")
    return SensorFeedback(model, engine=engine, extra_delay_ms=delay_ms,
                          allow_other_device=allow_other_device)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``fbgforce teleop``."""
    from fbgforce.teleop.feedback import describe
    from fbgforce.teleop.loop import run_seeds, simulate
    from fbgforce.teleop.plot import plot_run
    from fbgforce.teleop.scene import load_teleop_scene

    at_least(args.runs, 1, "--runs")
    at_least(args.seed, 0, "--seed")
    scene = load_teleop_scene(args.scene)
    fb = make_feedback(args.feedback, args.model, args.engine, args.delay_ms,
                       args.allow_other_device)
    out = Path(args.out)
    fileio.check_output_dir(out, "--out")
    result = simulate(scene, fb, run_seeds(args.seed, args.runs), progress=True)
    plot = plot_run(result, out / "fig7.png", 0)
    summary: dict[str, Any] = {
        **result.run_summary(0),
        "seed": args.seed,
        "feedback": describe(fb),
        "n_runs": args.runs,
        **result.rates(),
        "plot": None if plot is None else str(plot),
        "out": str(out),
    }
    with fileio.Outputs("--out") as files:
        files.write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
        with files.open(out / "runs.csv", "w", newline="") as fh:
            _write_runs_csv(result, fh)
    check = getattr(fb, "device_check", None)
    if check is not None and check["status"] != "verified":
        print(f"warning: device {check['status']}: {check['detail']}", file=sys.stderr)
    if not args.json:
        r = summary
        state = ("BROKEN" if r["egg_broken"] else "DROPPED" if r["egg_dropped"]
                 else "carried unbroken")
        print(f"run 0 (seed {args.seed}, feedback {fb.name}): egg {state}, max force "
              f"{r['max_force_N']:.1f} N, {r['time_in_safe_band_fraction']:.0%} of the carry in "
              f"the safe band, estimator delay {r['estimator_delay_ms']} ms")
        if r["force_rmse_N"] is not None:
            print(f"reported vs true force in contact: RMSE {r['force_rmse_N']:.2f} N, bias "
                  f"{r['force_bias_N']:+.2f} N")
        if args.runs > 1:
            print(f"{args.runs} runs: success {r['success_rate']:.0%}, broken "
                  f"{r['broken_rate']:.0%}, dropped {r['dropped_rate']:.0%}")
        print(f"wrote {out}/summary.json, runs.csv" + ("" if plot is None else ", fig7.png"),
              file=sys.stderr)
    return summary


def _write_runs_csv(result: Any, fh: Any) -> None:
    """One line per run to the text file ``fh``: seed and outcome."""
    o = result.outcomes
    keys = ("seed", "egg_broken", "egg_dropped", "success", "max_force_N",
            "time_in_safe_band_fraction", "estimator_delay_ms", "force_rmse_N", "force_bias_N",
            "contact_noticed_s")
    w = csv.writer(fh)
    w.writerow(keys)
    for k in range(o["seed"].size):
        w.writerow([_cell(o[key][k]) for key in keys])


def _cell(v: Any) -> Any:
    if isinstance(v, (bool,)) or getattr(v, "dtype", None) == bool:
        return int(v)
    f = float(v)
    return "" if f != f else (int(f) if f.is_integer() else round(f, 4))
