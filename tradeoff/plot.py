"""tradeoff.png: accuracy against host time, against filter delay + one step, and (with the
Cortex-M4 counts) against estimated cycles per step, Pareto fronts marked."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from fbgforce.target.report import CLOCK_HZ, PERIOD_S
from fbgforce.tradeoff.grid import ENGINE_SPECS


#: Marker area per network width.
WIDTH_MARKER_AREA = {"paper": 90, "half": 50, "quarter": 25}


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
    cmap = plt.get_cmap("tab10")
    for ax, xkey, xlabel in ((axes[0], "host_batch_ns", "host time per sample, batched (ns, log)"),
                             (axes[1], "total_ms", "filter delay + single-sample call (ms)")):
        _host_axis(ax, rows, engines, cmap, xkey, xlabel)
    axes[0].legend(fontsize=8, loc="best")
    axes[0].set_title("accuracy vs compute (marker size = width; hollow = offline filter)",
                      fontsize=9)
    axes[1].set_title("accuracy vs what the loop feels: filter delay + one step", fontsize=9)
    if m4:
        _m4_axis(axes[2], m4, engines, cmap)
    fig.tight_layout()
    from fbgforce import fileio

    try:
        fileio.write_with(path, lambda fh: fig.savefig(fh, dpi=110, format="png"), "--out")
    finally:
        plt.close(fig)
    return None


def _markers() -> dict[str, str]:
    """One marker shape per engine, in the grid's engine order."""
    return dict(zip([s.name for s in ENGINE_SPECS], "osD^vP"))


def _host_x(r: dict[str, Any], xkey: str, single_fallback: bool = True) -> float | None:
    """A row's position on a host axis: its batched time, or (``total_ms``) its filter delay
    plus one single-sample call, the batched time standing in for a missing single call
    unless ``single_fallback`` is off."""
    if xkey != "total_ms":
        return r.get(xkey)
    step_ns = r.get("host_single_ns") or (r.get("host_batch_ns") if single_fallback else 0) or 0
    return r["filter_delay_ms"] + step_ns / 1e6


def _staircase(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The non-dominated points of ``points`` sorted by x: each one lower than every point
    to its left (the Pareto front drawn as a staircase)."""
    best, stair = math.inf, []
    for x, y in sorted(points):
        if y < best:
            best = y
            stair.append((x, y))
    return stair


def _host_axis(ax: Any, rows: list[dict[str, Any]], engines: list[str], cmap: Any, xkey: str,
               xlabel: str) -> None:
    """One host panel: every engine's rows (hollow when the filter is offline), the Pareto
    front of that projection, the reference and the paper's own configuration annotated."""
    markers = _markers()
    for i, eng in enumerate(engines):
        keep = [(x, r) for r in rows if r["engine"] == eng
                for x in [_host_x(r, xkey)] if x is not None]
        for causal in (True, False):
            part = [(x, r) for x, r in keep if r["causal"] == causal]
            if part:
                ax.scatter([x for x, _ in part], [r["error_index"] for _, r in part],
                           s=[WIDTH_MARKER_AREA.get(r["width"], 40) for _, r in part],
                           marker=markers.get(eng, "o"),
                           facecolors=cmap(i) if causal else "none", edgecolors=cmap(i),
                           linewidths=1.2, label=eng if causal else None, alpha=0.8)
    front_key = "pareto_compute" if xkey == "host_batch_ns" else "pareto_delay"
    front = [(_host_x(r, xkey) if xkey == "total_ms" else r["host_batch_ns"], r["error_index"])
             for r in rows if r.get(front_key)]
    if front:
        stair = _staircase(front)
        ax.step([p[0] for p in stair], [p[1] for p in stair], where="post", color="k",
                lw=1.2, ls="--", label="Pareto front")
    ref = next((r for r in rows if r.get("is_reference")), None)
    if ref is not None:
        x = _host_x(ref, xkey, single_fallback=False)
        if x is not None:
            ax.annotate("paper net, shipped filter (ref)", (x, ref["error_index"]),
                        textcoords="offset points", xytext=(8, 10), fontsize=8,
                        arrowprops={"arrowstyle": "-", "lw": 0.6})
    for r in rows:
        if r["causal"] or r["width"] != "paper" or r["engine"] != "float":
            continue
        x = _host_x(r, xkey)
        if x is not None:
            ax.annotate("paper config (centred, offline)", (x, r["error_index"]),
                        textcoords="offset points", xytext=(8, -14), fontsize=8)
    ax.set_xscale("log" if xkey == "host_batch_ns" else "linear")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("error index (1 = reference; lower is better)")
    ax.axhline(1.0, color="0.6", lw=0.6)
    ax.grid(True, which="both", alpha=0.3)


def _m4_axis(ax: Any, m4: list[dict[str, Any]], engines: list[str], cmap: Any) -> None:
    """The firmware panel: error against the Cortex-M4's cost per step, its Pareto front and
    the line at a tenth of the 1 kHz budget."""
    markers = _markers()
    # Estimated cycles where every row has them (the budget is in cycles); instruction
    # counts (one per cycle, a lower bound) otherwise, so the axis never mixes the two.
    mkey = ("m4_cycles_per_step_estimate"
            if all(r.get("m4_cycles_per_step_estimate") for r in m4) else "m4_instructions_per_step")
    for i, eng in enumerate(engines):
        pts = [r for r in m4 if r["engine"] == eng]
        if pts:
            ax.scatter([r[mkey] for r in pts],
                       [r["error_index"] for r in pts],
                       s=[WIDTH_MARKER_AREA.get(r["width"], 40) for r in pts],
                       marker=markers.get(eng, "o"), color=cmap(i), label=eng, alpha=0.8)
            for r in pts:
                ax.annotate(r["variant"], (r[mkey], r["error_index"]),
                            textcoords="offset points", xytext=(4, 3), fontsize=6)
    stair = _staircase([(r[mkey], r["error_index"]) for r in m4])
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
