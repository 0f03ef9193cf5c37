"""Hours of use at 1 kHz through one C fixed-point state: drift, growth, quiet rests, exactness.

Usage::

    fbgforce simulate --scene calibration --out cal.npz
    fbgforce train --data cal.npz --out MODEL && fbgforce export --model MODEL
    python -m fbgforce.bench.bench_long_run --model MODEL [--hours 2] [--seed 0] [--json]

The run is a cycle of four segments of ``--segment-s`` seconds each (default 300) on the
simulator's calibration device, repeated until ``--hours`` (or ``--minutes``) are covered:

1. ``warm``: the fingertip warms by 40 K at 20 K/min, presses every few seconds;
2. ``grips``: at +40 K, presses that hold their load for 3 s;
3. ``cool``: back down by 40 K at 10 K/min, presses every few seconds;
4. ``rest``: nothing touches the pad.

Every segment also carries lost peaks (the interrogator reports 0 for one grating, in bursts
of 1-30 samples starting at 0.05 % of the samples), which the runtime must flag and ride out. One :class:`fbgforce.Runtime` state runs the whole stream
in 60 s chunks, tared once on the first segment's quiet lead-in, as a controller would run it
for hours. Per segment the table reports contact on samples at rest, false contact events per
minute of rest, the force at rest (99th percentile), the force RMSE under contact, the force
bias over holds, and how far the at-rest tracker has moved each strain grating's baseline
from the tare. Then the checks that hours of use could break:

- **no drift**: the rest figures of the last cycle against the first;
- **no state growth**: ``fbg_state`` is caller-owned and fixed in size, its counters
  saturate and the tracker's correction stays within its bound (never BASELINE_LIMIT);
- **bit-exact**: in the middle of the run the state is reset (it keeps the tracked baseline)
  and the next ``--exact-s`` seconds are compared with the integer reference started afresh on
  that baseline, every output field of every sample.

The simulation dominates the wall time (about a minute per simulated hour and core); the
runtime's own time is printed too.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce import contract
from fbgforce.evaluation import metrics as fmetrics
from fbgforce import sim
from fbgforce.bench.bench_generalisation import fail
from fbgforce.errors import InputError
from fbgforce.export import intref
from fbgforce.export.blob import load_model_blob
from fbgforce.pybind import Runtime, ffi

PROG = "bench_long_run"
RAMP_K = 40.0
#: Scene text of each segment kind: {seconds} and {seed} are filled in; every segment is the
#: calibration device with link faults, a 2 s quiet lead-in and its own noise.
SEGMENTS: dict[str, str] = {
    "warm": """
[schedule]
n_presses = {presses}
rest_s = 3.0
lead_in_s = 2.0
[effects.temperature]
offset_K = 0.0
ramp_K = {ramp}
ramp_start_s = 20.0
ramp_duration_s = {warm_s}
drift_K_per_sqrt_s = 0.01
""",
    "grips": """
[schedule]
n_presses = {grip_presses}
rest_s = 2.0
hold_s = 3.0
lead_in_s = 2.0
[effects.temperature]
offset_K = {ramp}
ramp_K = 0.0
drift_K_per_sqrt_s = 0.01
""",
    "cool": """
[schedule]
n_presses = {presses}
rest_s = 3.0
lead_in_s = 2.0
[effects.temperature]
offset_K = {ramp}
ramp_K = -{ramp}
ramp_start_s = 20.0
ramp_duration_s = {cool_s}
drift_K_per_sqrt_s = 0.01
""",
    "rest": """
[schedule]
kind = "rest"
duration_s = {seconds}
[effects.temperature]
offset_K = 0.0
ramp_K = 0.0
drift_K_per_sqrt_s = 0.01
""",
}
HEADER = """base = "calibration"
description = "long run: {kind}"
seed = {seed}
"""
#: Lost peaks: bursts of 1-30 samples on one grating, starting at this rate per sample.
FAULT_RATE = 0.0005
PRESS_S = 0.58  # load and unload of the calibration schedule


def segment_scene(kind: str, seconds: float, seed: int) -> str:
    """TOML text of one segment of ``kind`` lasting about ``seconds``."""
    presses = max(1, int((seconds - 2.0) / (3.0 + PRESS_S)))
    grip_presses = max(1, int((seconds - 2.0) / (2.0 + 3.0 + PRESS_S)))
    body = SEGMENTS[kind].format(presses=presses, grip_presses=grip_presses, ramp=RAMP_K,
                                 warm_s=RAMP_K / 20.0 * 60.0 if seconds >= 200 else 0.4 * seconds,
                                 cool_s=RAMP_K / 10.0 * 60.0 if seconds >= 300 else 0.8 * seconds,
                                 seconds=seconds)
    return HEADER.format(kind=kind, seed=seed) + body


def lose_peaks(wl_fm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``wl_fm`` with bursts of lost peaks (0 fm) on random gratings (:data:`FAULT_RATE`)."""
    out = wl_fm.copy()
    for start in np.flatnonzero(rng.random(out.shape[0]) < FAULT_RATE):
        out[start:start + int(rng.integers(1, 31)), int(rng.integers(contract.N_CHANNELS))] = 0
    return out


def _segment_figures(out: np.ndarray, ds: Any) -> dict[str, Any]:
    pc = out["contact"].astype(bool)
    pf = np.where(pc, out["force_mN"] / 1000.0, 0.0)
    masks = fmetrics.use_masks(pc, ds.contact, ds.force_N, ds.t_s)
    rest = fmetrics.rest_summary(pc, pf, masks)
    holds = fmetrics.hold_summary(pf, np.asarray(ds.force_N), masks)
    c = np.asarray(ds.contact, dtype=bool)
    rmse = float(np.sqrt(np.mean((pf[c] - ds.force_N[c]) ** 2))) if c.any() else None
    return {"seconds": float(ds.t_s[-1] - ds.t_s[0]), "rest_s": rest["seconds"],
            "rest_contact_pct": None if rest["contact_fraction"] is None else 100 * rest["contact_fraction"],
            "false_events_per_min": rest["false_events_per_min"],
            "force_rest_p99_N": rest["force_p99_N"], "rmse_force_N": rmse,
            "hold_bias_N": holds["force_bias_N"],
            "faults": int(np.sum((out["status"] & contract.STATUS_FLAG["SENSOR_FAULT"]) != 0)),
            "baseline_limit": int(np.sum((out["status"] & contract.STATUS_FLAG["BASELINE_LIMIT"]) != 0))}


def run(model: Path, seconds: float, segment_s: float, seed: int, exact_s: float,
        progress: bool = True) -> dict[str, Any]:
    """Stream the cycle of segments through one runtime state; returns the figures."""
    q = load_model_blob(model)
    rt = Runtime(model)
    kinds = list(SEGMENTS)
    n_seg = max(len(kinds), int(round(seconds / segment_s)))
    rows, tared, t_sim, t_rt, exact = [], None, 0.0, 0.0, None
    chunk = 60_000
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(n_seg):
            kind = kinds[i % len(kinds)]
            path = Path(tmp) / f"{kind}.toml"
            path.write_text(segment_scene(kind, segment_s, seed * 1000 + i))
            t0 = time.perf_counter()
            ds = sim.simulate(path)
            t_sim += time.perf_counter() - t0
            wl_fm = lose_peaks(intref.nm_to_fm(ds.wl_nm), np.random.default_rng(seed * 1000 + i))
            if tared is None:
                rt.tare(ds.wl_nm[:1000])       # the first lead-in: quiet, at the tare temperature
                tared = np.asarray(rt.baseline_fm, dtype=np.int64)
            if i == n_seg // 2 and exact is None:
                rt.reset()
                start = np.asarray(rt.baseline_fm, dtype=np.int64)
                m = min(wl_fm.shape[0], int(exact_s * 1000))
                t0 = time.perf_counter()
                head = rt.run_raw(wl_fm[:m])
                t_rt += time.perf_counter() - t0
                ref = intref.run(q, wl_fm[:m], start)
                bad = sum(int(np.sum(head[k].astype(np.int64) != ref[k])) for k in contract.OUTPUT_FIELDS)
                exact = {"segment": i, "samples": m, "mismatched_values": bad}
                rest = [rt.run_raw(wl_fm[a:a + chunk]) for a in range(m, wl_fm.shape[0], chunk)]
                out = np.concatenate([head, *rest]) if rest else head
            else:
                t0 = time.perf_counter()
                out = np.concatenate([rt.run_raw(wl_fm[a:a + chunk])
                                      for a in range(0, wl_fm.shape[0], chunk)])
                t_rt += time.perf_counter() - t0
            row = {"segment": i, "kind": kind, **_segment_figures(out, ds)}
            moved = (np.asarray(rt.baseline_fm, dtype=np.int64) - tared)[:contract.N_STRAIN] / 1000.0
            row["tracked_pm"] = [round(float(v), 2) for v in moved]
            rows.append(row)
            if progress:
                print(f"{PROG}: {i + 1}/{n_seg} {kind}: " + ", ".join(
                    f"{k} {_fmt(row[k])}" for k in ("rest_contact_pct", "false_events_per_min",
                                                     "force_rest_p99_N", "rmse_force_N")),
                      file=sys.stderr, flush=True)
    per_cycle = len(kinds)
    first = rows[:per_cycle]
    last = rows[-per_cycle:]

    def rest_figure(rs: list[dict], key: str) -> float:
        vals = [r[key] for r in rs if r[key] is not None]
        return float(max(vals)) if vals else 0.0

    total_rest = sum(r["rest_s"] for r in rows)
    events = sum((r["false_events_per_min"] or 0.0) * r["rest_s"] / 60.0 for r in rows)
    return {
        "model": str(model), "hours": sum(r["seconds"] for r in rows) / 3600.0,
        "segments": rows,
        "false_events_per_min": 60.0 * events / total_rest if total_rest else None,
        "drift": {"first_cycle_force_rest_p99_N": rest_figure(first, "force_rest_p99_N"),
                  "last_cycle_force_rest_p99_N": rest_figure(last, "force_rest_p99_N"),
                  "first_cycle_rest_contact_pct": rest_figure(first, "rest_contact_pct"),
                  "last_cycle_rest_contact_pct": rest_figure(last, "rest_contact_pct")},
        "state": {"fbg_state_bytes": int(ffi.sizeof("fbg_state")),
                  "baseline_limit_samples": sum(r["baseline_limit"] for r in rows),
                  "largest_tracked_pm": max(abs(v) for r in rows for v in r["tracked_pm"]),
                  "track_limit_pm": q.track_limit_fm / 1000.0},
        "exact": exact,
        "seconds_simulating": t_sim, "seconds_in_runtime": t_rt,
    }


def _fmt(v: Any) -> str:
    return "-" if v is None else (f"{v:.3g}" if isinstance(v, float) else str(v))


def table(res: dict[str, Any]) -> str:
    keys = ("rest_contact_pct", "false_events_per_min", "force_rest_p99_N", "rmse_force_N",
            "hold_bias_N", "faults", "tracked_pm")
    lines = ["| segment | kind | " + " | ".join(keys) + " |", "|---" * (len(keys) + 2) + "|"]
    for r in res["segments"]:
        lines.append(f"| {r['segment']} | {r['kind']} | " + " | ".join(_fmt(r[k]) for k in keys) + " |")
    ex = res["exact"]
    lines += ["",
              f"{res['hours']:.2f} h; false contact events at rest: {_fmt(res['false_events_per_min'])} /min",
              f"drift: force at rest p99 {res['drift']['first_cycle_force_rest_p99_N']:.3g} N (first cycle) "
              f"-> {res['drift']['last_cycle_force_rest_p99_N']:.3g} N (last); contact at rest "
              f"{res['drift']['first_cycle_rest_contact_pct']:.3g} % -> "
              f"{res['drift']['last_cycle_rest_contact_pct']:.3g} %",
              f"state: fbg_state {res['state']['fbg_state_bytes']} B; tracker at most "
              f"{res['state']['largest_tracked_pm']:.3g} pm of {res['state']['track_limit_pm']:.3g}; "
              f"BASELINE_LIMIT on {res['state']['baseline_limit_samples']} samples",
              f"bit-exact: {ex['mismatched_values']} mismatched values in {ex['samples']} samples "
              f"after a reset in segment {ex['segment']}",
              f"time: simulation {res['seconds_simulating']:.1f} s, runtime {res['seconds_in_runtime']:.2f} s"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=f"python -m fbgforce.bench.{PROG}", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, type=Path, help="an exported model directory")
    span = ap.add_mutually_exclusive_group()
    span.add_argument("--hours", type=float, default=None, help="length of the run (default 2)")
    span.add_argument("--minutes", type=float, default=None, help="length of the run in minutes")
    ap.add_argument("--segment-s", type=float, default=300.0, help="seconds per segment (default 300)")
    ap.add_argument("--exact-s", type=float, default=120.0,
                    help="seconds compared with the integer reference (default 120)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    seconds = 60.0 * args.minutes if args.minutes is not None else 3600.0 * (args.hours or 2.0)
    if seconds <= 0 or args.segment_s < 20 or args.exact_s <= 0:
        fail("--hours/--minutes and --exact-s must be positive, --segment-s at least 20", PROG)
    try:
        res = run(args.model, seconds, args.segment_s, args.seed, args.exact_s,
                  progress=not args.json)
    except InputError as exc:
        fail(str(exc), PROG)
    print(json.dumps(res, default=float) if args.json else table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
