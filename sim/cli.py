"""``fbgforce simulate``: run a scene and write the dataset (docs/cli.md#simulate)."""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from fbgforce.cli import add_json_flag
from fbgforce import fileio
from fbgforce.errors import InputError


def register(subparsers: Any) -> None:
    """Add the ``simulate`` subcommand."""
    p = subparsers.add_parser(
        "simulate",
        help="simulate a scene and write a dataset (CSV or npz)",
        description="Run a scene (built-in name or TOML path) through the end-effector "
                    "simulator and write the samples in the dataset format (docs/dataset.md).",
    )
    p.add_argument("--scene", help="built-in scene name or path to a scene TOML file")
    p.add_argument("--out", help="output file, .csv or .npz")
    p.add_argument("--seed", type=int, default=None, help="override the scene's seed (>= 0)")
    p.add_argument("--device", type=int, default=None,
                   help="override the scene's device number (>= 0): another toleranced device")
    p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    add_json_flag(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``fbgforce simulate``."""
    import sys

    from fbgforce import dataset
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
    for flag, value in (("--seed", args.seed), ("--device", args.device)):
        if value is not None and value < 0:
            raise InputError(f"must be >= 0, got {value}", column=flag)
    fileio.check_output_file(out, "--out")
    scene = load_scene(args.scene)
    t0 = time.perf_counter()
    ds = simulate(scene, seed=args.seed, device=args.device, progress=None)
    t_sim = time.perf_counter() - t0
    dataset.save(ds, out)
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
    }
    if not args.json:
        print(f"wrote {out}: {len(ds)} samples, {ds.n_presses} presses, "
              f"{summary['duration_s']:.1f} s of scene '{scene.name}'", file=sys.stderr)
    return summary
