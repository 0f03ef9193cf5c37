"""The paper's Fig. 7 for one simulated run: measured force, gripper opening, master motion.

matplotlib is an optional extra (``pip install -e ".[plot]"``): :func:`plot_run` returns None
and says so when it is missing.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from fbgforce.teleop.loop import TeleopResult


def plot_run(result: TeleopResult, path: str | Path, k: int = 0, title: str | None = None
             ) -> Path | None:
    """Write the Fig. 7 style plot of run ``k`` to ``path`` (PNG); None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot (pip install matplotlib)", file=sys.stderr)
        return None
    tr, t = result.traces, result.t_s
    o = result.outcomes
    fig, (ax, ax_zoom) = plt.subplots(2, 1, figsize=(9, 6.5), height_ratios=(3, 1.3),
                                      sharex=True)
    lo, hi = result.safe_band_N
    ax.axhspan(lo, hi, color="tab:green", alpha=0.08, label=f"safe band {lo:g}-{hi:g} N")
    ax.axhline(float(result.extra["break_force_N"][k]), color="tab:red", lw=0.8, ls="--",
               label="this egg's breaking force")
    ax.plot(t, tr["force_reported_N"][:, k], color="tab:blue", lw=1.4,
            label=f"force reported to master ({result.feedback})")
    ax.plot(t, tr["force_true_N"][:, k], color="black", lw=0.7, alpha=0.6, label="true force")
    ax.plot(t, tr["required_N"][:, k], color="tab:purple", lw=0.8, ls=":",
            label="grip needed (arm moving)")
    ax.set_ylabel("force, N")
    ax.axvline(result.lift_s, color="gray", lw=0.6)
    ax.text(result.lift_s, ax.get_ylim()[1] * 0.97, " arm starts", va="top", fontsize=8,
            color="gray")
    ax2 = ax.twinx()
    ax2.plot(t, tr["opening_mm"][:, k], color="tab:orange", lw=1.4, label="gripper opening")
    ax2.plot(t, tr["command_mm"][:, k], color="tab:orange", lw=1.0, ls=":",
             label="master motion (as opening)")
    ax2.set_ylabel("opening, mm")
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], loc="upper right", fontsize=7.5,
              framealpha=0.9)
    outcome = ("BROKEN" if o["egg_broken"][k] else "DROPPED" if o["egg_dropped"][k]
               else "carried unbroken")
    rmse, bias = float(o["force_rmse_N"][k]), float(o["force_bias_N"][k])
    error = ("" if np.isnan(rmse) else
             f"\nreported vs true force in contact: RMSE {rmse:.2f} N, bias {bias:+.2f} N")
    ax.set_title((title or f"egg grasp, seed {int(o['seed'][k])}, feedback {result.feedback}: "
                  f"{outcome}") + error, fontsize=10)
    ax_zoom.plot(t, tr["felt_N"][:, k], color="tab:brown", lw=1.0, label="force on the hand")
    ax_zoom.set_ylabel("master, N")
    ax_zoom.set_xlabel("time, s")
    ax_zoom.legend(loc="upper right", fontsize=7.5)
    ax_zoom.set_xlim(t[0], t[-1])
    fig.tight_layout()
    from fbgforce import fileio

    out = Path(path)
    try:
        fileio.write_with(out, lambda fh: fig.savefig(fh, dpi=110, format="png"), "--out")
    finally:
        plt.close(fig)
    return out


def first_failure(result: TeleopResult) -> int | None:
    """Index of the first failed run, to plot an example failure; None if all succeeded."""
    bad = np.flatnonzero(~result.outcomes["success"])
    return int(bad[0]) if bad.size else None
