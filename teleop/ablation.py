"""Ablations over seeded operators: what force feedback, the estimator and its delay are worth.

Each condition is one feedback source (:mod:`fbgforce.teleop.feedback`); every condition sees
the same seeded operators and eggs (run ``k`` uses seed ``seed + k`` everywhere), so the
differences between rows come from the feedback alone.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from fbgforce import contract
from fbgforce.model.artifact import memory_attr
from fbgforce.teleop.feedback import Feedback, SensorFeedback, describe
from fbgforce.teleop.loop import TeleopResult, run_seeds, simulate
from fbgforce.teleop.scene import TeleopScene


@dataclass
class Condition:
    """A row of the ablation table: a label and a factory for its feedback source."""

    label: str
    make: Callable[[], Feedback]


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a success fraction (honest for rates near 0 or 1)."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def _nanmedian(v: np.ndarray) -> float | None:
    return None if np.all(np.isnan(v)) else round(float(np.nanmedian(v)), 3)


def summarize(label: str, fb: Feedback, result: TeleopResult, wall_s: float) -> dict[str, Any]:
    """One table row from a batch of runs."""
    o = result.outcomes
    n = int(o["success"].size)
    k = int(np.sum(o["success"]))
    lo, hi = wilson_interval(k, n)
    delays = o["estimator_delay_ms"]
    row: dict[str, Any] = {
        "condition": label,
        "n_runs": n,
        **result.rates(),
        "success_ci95": [round(lo, 3), round(hi, 3)],
        "median_max_force_N": round(float(np.median(o["max_force_N"])), 2),
        "p95_max_force_N": round(float(np.percentile(o["max_force_N"], 95)), 2),
        "mean_time_in_safe_band_fraction": round(float(np.mean(o["time_in_safe_band_fraction"])), 3),
        "median_estimator_delay_ms": (None if np.all(np.isnan(delays))
                                      else round(float(np.nanmedian(delays)), 1)),
        "median_force_rmse_N": _nanmedian(o["force_rmse_N"]),
        "median_force_bias_N": _nanmedian(o["force_bias_N"]),
        "failed_seeds": [int(v) for v in o["seed"][~o["success"]]],
        "wall_s": round(wall_s, 1),
        "feedback": describe(fb),
    }
    return row


def run_ablation(scene: TeleopScene, conditions: list[Condition], seed: int, n_runs: int,
                 progress: bool = False, log: Callable[[str], None] | None = None
                 ) -> list[dict[str, Any]]:
    """Simulate every condition on the same ``n_runs`` seeded runs; one row per condition."""
    rows = []
    seeds = run_seeds(seed, n_runs)
    for cond in conditions:
        fb = cond.make()
        t0 = time.perf_counter()
        result = simulate(scene, fb, seeds, progress=progress)
        row = summarize(cond.label, fb, result, time.perf_counter() - t0)
        rows.append(row)
        if log is not None:
            log(f"{cond.label:32s} success {row['success_rate']:.2f} "
                f"(broken {row['broken_rate']:.2f}, dropped {row['dropped_rate']:.2f}), "
                f"{row['wall_s']:.0f} s")
    return rows


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """The ablation rows as a Markdown table."""
    head = ("| condition | runs | success | 95 % CI | broken | dropped | max force median / p95 (N) "
            "| time in safe band | measured delay (ms) | filter delay (ms) "
            "| in-loop force RMSE / bias, median (N) |")
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        fb = r["feedback"]
        filt = fb.get("filter_group_delay_ms")
        delay = r["median_estimator_delay_ms"]
        lines.append(
            f"| {r['condition']} | {r['n_runs']} | {r['success_rate']:.0%} | "
            f"{r['success_ci95'][0]:.0%}-{r['success_ci95'][1]:.0%} | {r['broken_rate']:.0%} | "
            f"{r['dropped_rate']:.0%} | {r['median_max_force_N']:.1f} / {r['p95_max_force_N']:.1f} | "
            f"{r['mean_time_in_safe_band_fraction']:.2f} | "
            f"{'-' if delay is None else f'{delay:.0f}'} | "
            f"{'-' if filt is None else f'{filt:.1f}'} | {_error_cell(r)} |")
    return "\n".join(lines) + "\n"


def _error_cell(row: dict[str, Any]) -> str:
    rmse, bias = row["median_force_rmse_N"], row["median_force_bias_N"]
    return "-" if rmse is None else f"{rmse:.2f} / {bias:+.2f}"


def estimator_label(fb: SensorFeedback) -> str:
    """A readable label for an estimator condition: engine, filter, memory and added delay."""
    pre = fb.model.preprocess
    filt = "no filter" if pre.filter_kind == "none" or pre.taps.size == 1 else (
        f"{pre.filter_kind} sigma {pre.filter_sigma:g}")
    mem = pre.memory
    parts = [f"{kind.label} {','.join(f'{v:g}' for v in getattr(mem, memory_attr(kind, kind.counted_by)))}"
             for kind in contract.MEMORY_KINDS if mem.count(kind)]
    memory = f"memory {' + '.join(parts)}" if parts else "no memory"
    extra = f" +{fb.extra_delay_ms:g} ms link" if fb.extra_delay_ms else ""
    return f"estimator ({fb.engine}, {filt}, {memory}){extra}"
