"""Training speed on the full calibration set: all three nets, wall and CPU time.

Usage::

    python bench/bench_train.py [--data FILE | --scene calibration_paper] [--epochs N] [--seed N]
                                [--json OUT.json]

Simulates the scene (default ``calibration_paper``, the paper's protocol, 234,300 samples)
unless ``--data`` is given, then runs :func:`fbgforce.trainer.train.train` with the default
settings (causal filter, paper sizes, Adam, mini-batch 128, early stopping) and prints a table:
preparation time, epochs and seconds per net, total wall and process CPU time, test metrics.
Goal: < 180 s on the 2-core machine (the paper quotes about 20 minutes with TensorFlow).
"""
from __future__ import annotations

import argparse
import json
import sys
import time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--data", help="recording to train on (CSV/npz)")
    src.add_argument("--scene", default="calibration_paper",
                     help="scene to simulate (default calibration_paper)")
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args(argv)

    from fbgforce.recordings import dataset
    from fbgforce.evaluation.metrics import headline
    from fbgforce.trainer.train import train

    if args.data:
        ds, what = dataset.load(args.data), args.data
    else:
        from fbgforce.sim import simulate

        ds, what = simulate(args.scene), f"scene {args.scene}"
    print(f"training on {what}: {len(ds)} samples, {ds.n_presses} presses", file=sys.stderr)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    model = train([ds], epochs=args.epochs, seed=args.seed)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    md = model.metadata
    rows = [("prepare (tare, temperature fit, filter, split)", "", md["times_s"]["prepare"])]
    for name, rep in md["training"].items():
        rows.append((f"{name} net {md['sizes'][name]}", f"{rep['epochs_run']} (best {rep['best_epoch']})",
                     rep["seconds"]))
    print(f"\n{'step':<52} {'epochs':>14} {'seconds':>9}")
    for step, ep, sec in rows:
        print(f"{step:<52} {ep:>14} {sec:9.1f}")
    print(f"{'total wall time':<52} {'':>14} {wall:9.1f}")
    print(f"{'total process CPU time':<52} {'':>14} {cpu:9.1f}")
    print(f"\ngoal < 180 s: {'met' if wall < 180 else 'NOT met'}; test split: "
          f"{headline(md['metrics']['test'])}")
    result = {"data": what, "samples": len(ds), "wall_s": wall, "cpu_s": cpu,
              "prepare_s": md["times_s"]["prepare"],
              "nets": {k: {"epochs": v["epochs_run"], "seconds": v["seconds"]}
                       for k, v in md["training"].items()},
              "test": {k: md["metrics"]["test"][k] for k in
                       ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm", "n_samples")}}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
