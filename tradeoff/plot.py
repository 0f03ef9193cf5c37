"""tradeoff.png: accuracy against host time, against filter delay + one step, and (with the
Cortex-M4 counts) against estimated cycles per step, Pareto fronts marked."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from fbgforce.target.report import CLOCK_HZ, PERIOD_S
from fbgforce.tradeoff.grid import ENGINE_SPECS

def write_plot(res: dict[str, Any], path: Path) -> str | None:
    """Accuracy against time per sample, Pareto front marked. Returns a note if skipped."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib not installed: no plot (pip install 'fbgforce[plot]')"
    rows = [r for r in res["rows"] if r.get("status") == "ok" and r.get("error_index") is not None]
    m4 = [r for r in rows if r.get("m4_instructions_per_step")]
    fig, axes = plt.subplots(1, 3 if m4 else 2, figsize=(19 if m4 else 13, 5.2))
    engines = sorted({r["engine"] for r in rows}, key=[s.name for s in ENGINE_SPECS].index)
    markers = dict(zip([s.name for s in ENGINE_SPECS], "osD^vP"))
    widths = {"paper": 90, "half": 50, "quarter": 25}
    cmap = plt.get_cmap("tab10")
    for ax, xkey, xlabel in ((axes[0], "host_batch_ns", "host time per sample, batched (ns, log)"),
                             (axes[1], "total_ms", "filter delay + single-sample call (ms)")):
        for i, eng in enumerate(engines):
            pts = [r for r in rows if r["engine"] == eng]
            xs = [(r["filter_delay_ms"] + (r.get("host_single_ns") or r.get("host_batch_ns") or 0) / 1e6)
                  if xkey == "total_ms" else r.get(xkey) for r in pts]
            keep = [(x, r) for x, r in zip(xs, pts) if x is not None]
            if not keep:
                continue
            for causal in (True, False):
                part = [(x, r) for x, r in keep if r["causal"] == causal]
                if part:
                    ax.scatter([x for x, _ in part], [r["error_index"] for _, r in part],
                               s=[widths.get(r["width"], 40) for _, r in part],
                               marker=markers.get(eng, "o"),
                               facecolors=cmap(i) if causal else "none", edgecolors=cmap(i),
                               linewidths=1.2, label=eng if causal else None, alpha=0.8)
        front_key = "pareto_compute" if xkey == "host_batch_ns" else "pareto_delay"
        front = sorted(((r["filter_delay_ms"] + (r.get("host_single_ns") or r.get("host_batch_ns") or 0) / 1e6
                         if xkey == "total_ms" else r["host_batch_ns"], r["error_index"])
                        for r in rows if r.get(front_key)))
        if front:
            # The front as a staircase through the non-dominated points in this projection.
            best, stair = math.inf, []
            for x, y in front:
                if y < best:
                    best = y
                    stair.append((x, y))
            ax.step([p[0] for p in stair], [p[1] for p in stair], where="post", color="k",
                    lw=1.2, ls="--", label="Pareto front")
        ref = next((r for r in rows if r.get("is_reference")), None)
        if ref is not None:
            x = (ref["filter_delay_ms"] + (ref.get("host_single_ns") or 0) / 1e6) if xkey == "total_ms" \
                else ref.get("host_batch_ns")
            if x is not None:
                ax.annotate("paper net, shipped filter (ref)", (x, ref["error_index"]),
                            textcoords="offset points", xytext=(8, 10), fontsize=8,
                            arrowprops={"arrowstyle": "-", "lw": 0.6})
        paper = [r for r in rows if not r["causal"] and r["width"] == "paper"
                 and r["engine"] == "float"]
        for r in paper:
            x = (r["filter_delay_ms"] + (r.get("host_single_ns") or r.get("host_batch_ns") or 0) / 1e6) \
                if xkey == "total_ms" else r.get("host_batch_ns")
            if x is None:
                continue
            ax.annotate("paper config (centred, offline)", (x, r["error_index"]),
                        textcoords="offset points", xytext=(8, -14), fontsize=8)
        ax.set_xscale("log" if xkey == "host_batch_ns" else "linear")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("error index (1 = reference; lower is better)")
        ax.axhline(1.0, color="0.6", lw=0.6)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    axes[0].set_title("accuracy vs compute (marker size = width; hollow = offline filter)",
                      fontsize=9)
    axes[1].set_title("accuracy vs what the loop feels: filter delay + one step", fontsize=9)
    if m4:
        ax = axes[2]
        # Estimated cycles where every row has them (the budget is in cycles); instruction
        # counts (one per cycle, a lower bound) otherwise, so the axis never mixes the two.
        mkey = ("m4_cycles_per_step_estimate"
                if all(r.get("m4_cycles_per_step_estimate") for r in m4) else "m4_instructions_per_step")
        for i, eng in enumerate(engines):
            pts = [r for r in m4 if r["engine"] == eng]
            if pts:
                ax.scatter([r[mkey] for r in pts],
                           [r["error_index"] for r in pts], s=[widths.get(r["width"], 40) for r in pts],
                           marker=markers.get(eng, "o"), color=cmap(i), label=eng, alpha=0.8)
                for r in pts:
                    ax.annotate(r["variant"], (r[mkey], r["error_index"]),
                                textcoords="offset points", xytext=(4, 3), fontsize=6)
        front = sorted((r[mkey], r["error_index"]) for r in m4)
        best, stair = math.inf, []
        for x, y in front:
            if y < best:
                best = y
                stair.append((x, y))
        ax.step([p[0] for p in stair], [p[1] for p in stair], where="post", color="k", lw=1.2,
                ls="--", label="Pareto front")
        tenth = CLOCK_HZ * PERIOD_S / 10
        ax.axvline(tenth, color="0.5", lw=0.8, ls=":")
        ax.text(tenth, ax.get_ylim()[1], " 10 % of 1 kHz at 168 MHz", fontsize=7, va="top")
        ax.set_xlabel("Cortex-M4 estimated cycles per step (worst step, DSP build)"
                      if mkey == "m4_cycles_per_step_estimate" else
                      "Cortex-M4 instructions per step (worst step, DSP build; one per cycle)")
        ax.set_ylabel("error index")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        ax.set_title("accuracy vs firmware cost (QEMU instruction counts, TRM cycle estimate)",
                     fontsize=9)
    fig.tight_layout()
    from fbgforce import fileio

    try:
        fileio.write_with(path, lambda fh: fig.savefig(fh, dpi=110, format="png"), "--out")
    finally:
        plt.close(fig)
    return None
