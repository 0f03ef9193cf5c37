"""The pictures ``fbgforce demo`` ends with, drawn headless (matplotlib's Agg backend).

Every figure is one PNG of :data:`SIZE_PX` pixels, so a reader (or a test) knows what to
expect; :func:`write_demo_figures` returns one record per file (path, title, pixel size),
which the demo lists in its JSON summary.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

#: Figure size in inches and resolution: every PNG is SIZE_PX = (900, 500) pixels.
FIGSIZE_IN = (9.0, 5.0)
DPI = 100
SIZE_PX = (int(FIGSIZE_IN[0] * DPI), int(FIGSIZE_IN[1] * DPI))
#: Test presses drawn in the predicted-versus-true force figure.
PRESSES_SHOWN = 4


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # no display needed, on a server or in CI
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path, title: str) -> dict[str, Any]:
    from fbgforce import fileio

    plt = _pyplot()
    try:
        # No bbox_inches="tight": the pixel size stays SIZE_PX.
        fileio.write_with(path, lambda fh: fig.savefig(fh, dpi=DPI, format="png"))
    finally:
        plt.close(fig)
    return {"path": str(path), "title": title, "width_px": SIZE_PX[0], "height_px": SIZE_PX[1]}


def force_over_presses(t_s: np.ndarray, true_N: np.ndarray, pred_N: np.ndarray,
                       press_id: np.ndarray, test_rows: np.ndarray, path: Path,
                       engine: str) -> dict[str, Any]:
    """Predicted against true force over the first :data:`PRESSES_SHOWN` test presses."""
    plt = _pyplot()
    presses = [p for p in dict.fromkeys(press_id[test_rows].tolist()) if p >= 0][:PRESSES_SHOWN]
    fig, axes = plt.subplots(1, max(1, len(presses)), figsize=FIGSIZE_IN, sharey=True,
                             squeeze=False)
    for ax, press in zip(axes[0], presses):
        rows = test_rows[press_id[test_rows] == press]
        t = t_s[rows] - t_s[rows[0]]
        ax.plot(t, true_N[rows], color="0.3", lw=1.5, label="true (load cell)")
        ax.plot(t, pred_N[rows], color="tab:red", lw=1.0, label=f"predicted ({engine})")
        ax.set_title(f"press {press}", fontsize=9)
        ax.set_xlabel("time in press (s)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("normal force (N)")
    axes[0][0].legend(fontsize=8, loc="upper left")
    title = "Predicted against true force, test presses"
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path, title)


def error_map(x_mm: np.ndarray, y_mm: np.ndarray, err_mm: np.ndarray, pad_mm: Sequence[float],
              path: Path) -> dict[str, Any]:
    """Mean location error at each pressed point of the pad (pad frame: origin top-left, y
    down), beside the error against the distance to the nearest edge."""
    plt = _pyplot()
    w, h = float(pad_mm[0]), float(pad_mm[1])
    ok = np.isfinite(x_mm) & np.isfinite(y_mm) & np.isfinite(err_mm)
    x, y, err = x_mm[ok], y_mm[ok], err_mm[ok]
    # One point per pressed location (a press holds its location; 0.1 mm groups them).
    keys = np.round(np.column_stack([x, y]) * 10.0).astype(np.int64)
    uniq, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    mean = np.bincount(inverse, weights=err, minlength=len(uniq)) / np.maximum(counts, 1)
    px, py = uniq[:, 0] / 10.0, uniq[:, 1] / 10.0
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=FIGSIZE_IN,
                                  gridspec_kw={"width_ratios": [1.0, 1.3]})
    ax.add_patch(plt.Rectangle((0.0, 0.0), w, h, fill=False, color="0.4", lw=1.0))
    sc = ax.scatter(px, py, c=mean, s=60, cmap="viridis", edgecolors="k", linewidths=0.4)
    fig.colorbar(sc, ax=ax, label="mean location error (mm)")
    ax.set_xlim(-1.0, w + 1.0)
    ax.set_ylim(h + 1.0, -1.0)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm, down)")
    ax.set_title("pressed points on the pad", fontsize=9)
    edge = np.minimum.reduce([px, w - px, py, h - py])
    ax2.scatter(edge, mean, s=25, color="tab:blue")
    ax2.set_xlabel("distance of the pressed point to the nearest edge (mm)")
    ax2.set_ylabel("mean location error (mm)")
    ax2.grid(alpha=0.3)
    title = "Location error over the pad, test contact samples"
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path, title)


def contact_by_force(by_force: Sequence[Mapping[str, Any]], false_contact_rate: float | None,
                     path: Path) -> dict[str, Any]:
    """Contact accuracy per true-force range (``metrics.compute``'s ``by_force`` rows)."""
    plt = _pyplot()
    labels, acc, n = [], [], []
    for row in by_force:
        lo, hi = row["range_N"]
        labels.append(f"{lo:g}–{hi:g} N" if hi is not None else f"> {lo:g} N")
        acc.append(100.0 * row["contact_accuracy"] if row.get("contact_accuracy") is not None
                   else np.nan)
        n.append(row.get("n_samples", 0))
    if false_contact_rate is not None:
        labels.insert(0, "no contact")
        acc.insert(0, 100.0 * (1.0 - false_contact_rate))
        n.insert(0, None)
    fig, ax = plt.subplots(figsize=FIGSIZE_IN)
    bars = ax.bar(range(len(labels)), np.nan_to_num(acc), color="tab:blue")
    for bar, a, k in zip(bars, acc, n):
        text = "–" if not np.isfinite(a) else f"{a:.1f}%" + (f"\nn={k}" if k else "")
        ax.annotate(text, (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                    textcoords="offset points", xytext=(0, 2), ha="center", fontsize=8)
    ax.set_xticks(range(len(labels)), labels, fontsize=8)
    ax.set_ylim(0, 110)
    ax.set_ylabel("correctly classified (%)")
    title = "Contact accuracy by true force, test samples"
    ax.set_title(title, fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return _save(fig, path, title)


def paper_vs_ours(paper: Mapping[str, Any], ours: Mapping[str, Any], path: Path,
                  ours_label: str) -> dict[str, Any]:
    """The paper's network results beside ours as bars from zero: contact accuracy (%) on the
    left, the errors (force N, x and y mm) on the right, each value written on its bar."""
    plt = _pyplot()
    panels = [("correct (%)", [("contact_accuracy", "contact"),
                               ("contact_accuracy_above_5N", "contact > 5 N")], 100.0),
              ("RMSE (N or mm)", [("rmse_force_N", "force (N)"), ("rmse_x_mm", "x (mm)"),
                                  ("rmse_y_mm", "y (mm)")], 1.0)]
    fig, axes = plt.subplots(1, 2, figsize=FIGSIZE_IN, gridspec_kw={"width_ratios": [2, 3]})
    width = 0.38
    for ax, (ylabel, keys, scale) in zip(axes, panels):
        x = np.arange(len(keys))
        for offset, source, label, colour in ((-width / 2, paper, "paper (Kim et al. 2019)", "0.6"),
                                              (width / 2, ours, ours_label, "tab:blue")):
            values = [source.get(k) for k, _ in keys]
            heights = [scale * v if v is not None else 0.0 for v in values]
            bars = ax.bar(x + offset, heights, width, color=colour, label=label)
            for bar, v in zip(bars, values):
                text = "–" if v is None else (f"{scale * v:.1f}" if scale != 1.0 else f"{v:.2f}")
                ax.annotate(text, (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                            textcoords="offset points", xytext=(0, 2), ha="center", fontsize=8)
        ax.set_xticks(x, [name for _, name in keys], fontsize=9)
        ax.set_ylabel(ylabel)
        ax.set_ylim(0, 130 if scale != 1.0 else None)
        ax.grid(axis="y", alpha=0.3)
    axes[1].set_ylim(bottom=0)
    axes[0].legend(fontsize=8, loc="upper center", ncol=1)
    title = "Paper against ours, test split (bars from zero; lower RMSE is better)"
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path, title)


def accuracy_vs_time(points: Sequence[Mapping[str, Any]], path: Path) -> dict[str, Any]:
    """Force RMSE against host time per sample, one point per engine, on an axis from zero;
    each point is labelled with its RMSE and its difference from the first engine's (the
    engines usually differ by fractions of a mN, invisible at this scale but not hidden).

    ``points``: dicts with ``engine``, ``us_per_sample`` and ``rmse_force_N``.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=FIGSIZE_IN)
    ref = next((p for p in points if p["rmse_force_N"] is not None), None)
    top = 0.0
    for i, p in enumerate(points):
        rmse = p["rmse_force_N"]
        if rmse is None:
            continue
        top = max(top, rmse)
        ax.scatter([p["us_per_sample"]], [rmse], s=60)
        diff = "" if p is ref else f", {1000 * (rmse - ref['rmse_force_N']):+.2f} mN"
        ax.annotate(f"{p['engine']}: {rmse:.4f} N{diff}", (p["us_per_sample"], rmse),
                    textcoords="offset points", xytext=(6, 4 + 10 * (i % 3)),
                    fontsize=8)
    ax.set_xscale("log")
    ax.set_ylim(0, 1.25 * top if top > 0 else 1.0)
    ax.set_xlabel("host time per sample, evaluating the whole recording (µs, log)")
    ax.set_ylabel("force RMSE, test split (N, from zero)")
    title = ("Accuracy against time per sample, by engine"
             + (f" (differences from {ref['engine']} in mN)" if ref is not None else ""))
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return _save(fig, path, title)


def write_demo_figures(out_dir: str | Path, *, ds: Any, test_rows: np.ndarray,
                       pred: Mapping[str, np.ndarray], engine: str,
                       metrics: Mapping[str, Any], paper: Mapping[str, Any],
                       timings: Sequence[Mapping[str, Any]],
                       pad_mm: Sequence[float]) -> list[dict[str, Any]]:
    """Write every demo figure into ``out_dir``; one record per PNG.

    Parameters
    ----------
    ds
        The recording (``fbgforce.recordings.dataset.Dataset``) the predictions were made on.
    test_rows
        Row indices of its test split.
    pred
        One engine's predictions on the whole recording (``contact``, ``force_N``, ``x_mm``,
        ``y_mm``), named ``engine``.
    metrics
        That engine's test-split metrics (``fbgforce.evaluation.metrics.compute`` with extras).
    paper
        The paper's network figures (``fbgforce.trainer.report.PAPER["network"]``).
    timings
        Per engine: ``engine``, ``us_per_sample``, ``rmse_force_N``.
    pad_mm
        Pad width and height (mm).
    """
    out = Path(out_dir)
    pc = np.asarray(pred["contact"], dtype=bool)
    pf = np.where(pc, np.asarray(pred["force_N"], dtype=np.float64), 0.0)
    tc = np.asarray(ds.contact, dtype=bool)
    both = test_rows[tc[test_rows] & pc[test_rows]]
    err = np.hypot(np.asarray(pred["x_mm"])[both] - ds.x_mm[both],
                   np.asarray(pred["y_mm"])[both] - ds.y_mm[both])
    return [
        force_over_presses(ds.t_s, ds.force_N, pf, ds.press_id, test_rows,
                           out / "force_vs_true.png", engine),
        error_map(ds.x_mm[both], ds.y_mm[both], err, pad_mm, out / "error_map.png"),
        contact_by_force(metrics["by_force"], metrics.get("false_contact_rate"),
                         out / "contact_by_force.png"),
        paper_vs_ours(paper, metrics, out / "paper_vs_ours.png", f"ours ({engine} engine)"),
        accuracy_vs_time(timings, out / "accuracy_vs_time.png"),
    ]
