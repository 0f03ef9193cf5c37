"""``fbgforce simulate``: run a scene and write the dataset (docs/cli.md#simulate)."""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from fbgforce import fileio
from fbgforce.cliargs import add_seed, at_least, command, non_negative_float, positive_float
from fbgforce.errors import InputError


def register(subparsers: Any) -> None:
    """Add the ``simulate`` subcommand."""
    with command(subparsers, "simulate", run,
                 help="simulate a scene and write a dataset (CSV or npz)",
                 description="Run a scene (built-in name or TOML path) through the end-effector "
                             "simulator and write the samples in the dataset format "
                             "(docs/dataset.md).") as p:
        p.add_argument("--scene", help="built-in scene name or path to a scene TOML file")
        p.add_argument("--out", help="output file, .csv or .npz")
        add_seed(p, "override the scene's seed (>= 0)", default=None)
        p.add_argument("--device", type=int, default=None,
                       help="override the scene's device number (>= 0): another toleranced "
                            "device")
        p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
        p.add_argument("--lab-logs", metavar="DIR", default=None,
                       help="also write the raw files a lab would have: DIR/interrogator.csv, "
                            "DIR/stage.csv (load cell and position on the stage's own clock) "
                            "and DIR/import.toml (fbgforce import --map); docs/simulator.md")
        p.add_argument("--stage-rate-hz", type=positive_float, default=500.0,
                       help="stage log rate on its own clock (default 500 Hz)")
        p.add_argument("--stage-offset-s", type=float, default=0.1,
                       help="stage clock minus interrogator clock at the first sample (default "
                            "0.1 s)")
        p.add_argument("--stage-drift-ppm", type=float, default=80.0,
                       help="stage clock rate error against the interrogator's (default 80 ppm)")
        p.add_argument("--stage-jitter-ms", type=non_negative_float, default=0.1,
                       help="sd of the stage samples' timing jitter (default 0.1 ms)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``fbgforce simulate``."""
    import sys

    from fbgforce.recordings import dataset
    from fbgforce.sim import builtin_scenes, load_scene, simulate

    if args.list:
        scenes = {}
        for name in builtin_scenes():
            scenes[name] = load_scene(name).description
            if not args.json:
                print(f"{name:14s} {scenes[name]}")
        return {"scenes": scenes}
    if not args.scene:
        raise InputError("give --scene NAME|PATH (see --list)", column="--scene")
    if not args.out:
        raise InputError("give --out FILE.csv|FILE.npz", column="--out")
    out = Path(args.out)
    if out.suffix.lower() not in (".csv", ".npz"):
        raise InputError("output must end in .csv or .npz", path=str(out), column="--out")
    at_least(args.seed, 0, "--seed")
    at_least(args.device, 0, "--device")
    fileio.check_output_file(out, "--out")
    scene = load_scene(args.scene)
    t0 = time.perf_counter()
    ds = simulate(scene, seed=args.seed, device=args.device, progress=None)
    t_sim = time.perf_counter() - t0
    dataset.save(ds, out)
    lab_logs = None
    if args.lab_logs:
        from fbgforce.sim.lablogs import write_lab_logs

        lab_logs = write_lab_logs(ds, args.lab_logs, rate_hz=args.stage_rate_hz,
                                  offset_s=args.stage_offset_s, drift_ppm=args.stage_drift_ppm,
                                  jitter_s=args.stage_jitter_ms * 1e-3,
                                  seed=scene.seed if args.seed is None else args.seed)
    summary = {
        "scene": scene.name,
        "seed": scene.seed if args.seed is None else args.seed,
        "device": scene.device if args.device is None else args.device,
        "effects": list(scene.effects),
        "samples": len(ds),
        "presses": ds.n_presses,
        "duration_s": float(ds.t_s[-1] - ds.t_s[0] + 1.0 / scene.sample_rate_hz),
        "contact_fraction": float(ds.contact.mean()),
        "max_force_N": float(ds.force_N.max()),
        "simulate_time_s": round(t_sim, 3),
        "file": str(out),
        "lab_logs": lab_logs,
    }
    if not args.json:
        print(f"wrote {out}: {len(ds)} samples, {ds.n_presses} presses, "
              f"{summary['duration_s']:.1f} s of scene '{scene.name}'", file=sys.stderr)
    return summary
