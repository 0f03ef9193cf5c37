"""What a quiet contact decision costs in onset delay: ``fbgforce tradeoff --decision MODEL``.

The decision over time (docs/runtime.md, "In use") rises once the contact net's margin has
stayed at or above ``contact_on_margin`` for ``contact_rise_samples`` samples and falls below
``contact_off_margin`` (half the rise threshold, negated). Higher thresholds and longer counts
raise fewer false contact events at rest and detect a press later (and the lightest touches
not at all). This module runs one exported model through the C fixed-point runtime on the
given recordings for a grid of those two parameters, everything else as exported, and scores
each with the keys of ``fbgforce evaluate --json``: false contact events per minute at rest,
onset delay (median and 90th percentile) and the detection rate by force bin.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce import metrics as fmetrics
from fbgforce import model as fm
from fbgforce import tare as ftare
from fbgforce.export import blob
from fbgforce.export.quantize import quantize_in_use
from fbgforce.pybind import Runtime

#: Rise thresholds as multiples of the model's own (its calibration rest margins' quantile).
ON_SCALES = (0.0, 0.5, 1.0, 1.5, 2.0)
#: Rise counts, in samples.
RISE_COUNTS = (1, 3, 6)


def _score(q: Any, recordings: Sequence[Any]) -> dict[str, Any]:
    events, rest_s, onsets, det = 0, 0.0, [], []
    bins: dict[str, list[float]] = {}
    for ds in recordings:
        base, _ = ftare.tare(ds.wl_nm, ds.contact, ds.t_s)
        rt = Runtime(blob.to_bytes(q))
        rt.set_baseline(base)
        out = rt.run(ds.wl_nm)
        pc = out["contact"].astype(bool)
        pf = np.asarray(out["force_N"])
        masks = fmetrics.use_masks(pc, ds.contact, ds.force_N, ds.t_s)
        rest = fmetrics.rest_summary(pc, pf, masks)
        events += rest["false_events"]
        rest_s += rest["seconds"]
        onset, _ = fmetrics.press_delays(pc, ds.contact, ds.t_s, ds.press_id)
        onsets.append(onset)
        tf = np.asarray(ds.force_N)
        det.append(pc[tf > 1.0])
        edges = (0.0, *fmetrics.CONTACT_BINS_N, np.inf)
        c = np.asarray(ds.contact, dtype=bool)
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = c & (tf > lo) & (tf <= hi)
            bins.setdefault(f"{lo:g}-{hi:g}", []).extend(pc[sel].tolist())
    on = np.concatenate(onsets) if onsets else np.empty(0)
    on = on[np.isfinite(on)]
    above = np.concatenate(det) if det else np.empty(0)
    return {"false_events_per_min": 60.0 * events / rest_s if rest_s else None,
            "rest_s": rest_s,
            "onset_median_ms": float(np.median(on)) if on.size else None,
            "onset_p90_ms": float(np.percentile(on, 90)) if on.size else None,
            "detected_above_1N": float(above.mean()) if above.size else None,
            "detected_by_force_N": {k: (float(np.mean(v)) if v else None) for k, v in bins.items()}}


def decision_curve(model_dir: str | Path, recordings: Sequence[Any],
                   on_scales: Sequence[float] = ON_SCALES,
                   rise_counts: Sequence[int] = RISE_COUNTS) -> dict[str, Any]:
    """The grid's rows (``contact_on_margin``, ``contact_rise_samples`` and the scores), the
    model's own setting marked ``default``."""
    model = fm.load(model_dir)
    q0 = blob.load_model_blob(model_dir)
    own = model.in_use
    base_on = own.contact_on_margin
    rows = []
    for scale in on_scales:
        for rise in rise_counts:
            on = scale * base_on
            iu = dataclasses.replace(own, contact_on_margin=on, contact_off_margin=-0.5 * on,
                                     contact_rise_samples=rise)
            q = dataclasses.replace(q0, **quantize_in_use(iu, q0.z_mult, q0.z_shift))
            rows.append({"contact_on_margin": on, "contact_rise_samples": rise,
                         "default": scale == 1.0 and rise == own.contact_rise_samples,
                         **_score(q, recordings)})
    return {"model": str(model_dir), "model_on_margin": base_on, "rows": rows}


def markdown(res: dict[str, Any]) -> str:
    lines = ["| rise margin | rise samples | false events /min at rest | onset median ms | "
             "onset p90 ms | detected > 1 N |", "|---|---|---|---|---|---|"]
    for r in res["rows"]:
        mark = " (default)" if r["default"] else ""

        def f(v: Any, fmt: str) -> str:
            return "-" if v is None else format(v, fmt)
        lines.append(f"| {r['contact_on_margin']:.2f}{mark} | {r['contact_rise_samples']} | "
                     f"{f(r['false_events_per_min'], '.2f')} | {f(r['onset_median_ms'], '.1f')} | "
                     f"{f(r['onset_p90_ms'], '.1f')} | "
                     f"{f(None if r['detected_above_1N'] is None else 100 * r['detected_above_1N'], '.2f')} % |")
    return "\n".join(lines)


def plot(res: dict[str, Any], path: Path) -> Path:
    """False events per minute against median onset delay, one line per rise count."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for rise in sorted({r["contact_rise_samples"] for r in res["rows"]}):
        pts = [(r["onset_median_ms"], r["false_events_per_min"], r["contact_on_margin"])
               for r in res["rows"] if r["contact_rise_samples"] == rise
               and r["onset_median_ms"] is not None and r["false_events_per_min"] is not None]
        if not pts:
            continue
        x, y, on = zip(*pts)
        ax.plot(x, np.maximum(y, 0.05), marker="o", label=f"rise after {rise} sample(s)")
        for xi, yi, oi in zip(x, y, on):
            ax.annotate(f"{oi:.1f}", (xi, max(yi, 0.05)), textcoords="offset points",
                        xytext=(4, 3), fontsize=7)
    for r in res["rows"]:
        if r["default"] and r["onset_median_ms"] is not None:
            ax.plot([r["onset_median_ms"]], [max(r["false_events_per_min"] or 0.0, 0.05)], "k*",
                    markersize=12, label="exported default")
    ax.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_xlabel("median onset delay, ms (first labelled contact sample to detection)")
    ax.set_ylabel("false contact events per minute at rest (0 drawn at 0.05)")
    ax.set_title("A quiet decision costs onset delay (labels: rise margin)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
