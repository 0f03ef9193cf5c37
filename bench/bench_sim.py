"""Benchmark of the simulator and the dataset I/O on the full calibration scene.

Times (median of ``--repeat`` runs, one process; wall clock and CPU time):

- simulating the ``calibration_paper`` scene (the paper's protocol, 234,300 samples;
  goal < 10 s),
- saving and loading it as CSV (load goal < 2 s) and as npz,

and prints a table (``--json`` for one JSON object instead). Run from anywhere::

    python -m fbgforce.bench.bench_sim [--scene calibration_paper] [--repeat 3] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

GOALS_S = {"simulate": 10.0, "load_csv": 2.0}


def _time(fn: Callable[[], Any], repeat: int) -> tuple[float, float, Any]:
    """Median wall-clock and CPU seconds of ``fn`` over ``repeat`` runs, and its result.

    CPU time is reported too because these machines are shared: under contention the wall
    clock includes time spent waiting for a core, the CPU time does not."""
    walls, cpus, result = [], [], None
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        result = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus), result


def run(scene: str = "calibration_paper", repeat: int = 3) -> dict[str, Any]:
    """Measure and return ``{"scene", "samples", "timings_s": {...}, "goals_s", "file_bytes"}``."""
    from fbgforce.recordings import dataset
    from fbgforce.sim import simulate

    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}
    timings["simulate"], cpu["simulate"], ds = _time(lambda: simulate(scene), repeat)
    sizes = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("csv", "npz"):
            path = Path(tmp) / f"data.{kind}"
            timings[f"save_{kind}"], cpu[f"save_{kind}"], _ = _time(
                lambda: dataset.save(ds, path), repeat)
            timings[f"load_{kind}"], cpu[f"load_{kind}"], back = _time(
                lambda: dataset.load(path), repeat)
            sizes[kind] = path.stat().st_size
            if len(back) != len(ds):
                raise RuntimeError(f"{kind} round trip lost samples")
    return {"scene": scene, "samples": len(ds), "repeat": repeat,
            "timings_s": {k: round(v, 4) for k, v in timings.items()},
            "cpu_s": {k: round(v, 4) for k, v in cpu.items()},
            "load_average": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
            "goals_s": GOALS_S, "file_bytes": sizes}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="calibration_paper")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    res = run(args.scene, args.repeat)
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"scene {res['scene']}: {res['samples']} samples, median of {res['repeat']} runs, "
          f"1-min load average {res['load_average']}")
    print(f"{'step':<12}{'wall (s)':>10}{'cpu (s)':>10}{'goal (s)':>10}  ok")
    for step, t in res["timings_s"].items():
        goal = GOALS_S.get(step)
        ok = "" if goal is None else ("yes" if t < goal else "NO")
        goal_text = "" if goal is None else f"{goal:.1f}"
        print(f"{step:<12}{t:>10.3f}{res['cpu_s'][step]:>10.3f}{goal_text:>10}  {ok}")
    print(f"files: CSV {res['file_bytes']['csv'] / 1e6:.1f} MB, npz {res['file_bytes']['npz'] / 1e6:.1f} MB",
          file=sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
