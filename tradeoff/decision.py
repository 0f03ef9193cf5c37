"""What a quiet contact decision costs in onset delay: ``fbgforce tradeoff --decision MODEL``.

The decision over time (docs/runtime.md, "In use") rises by one of two rules. The Schmitt
trigger rises once the contact net's margin has stayed at or above ``contact_on_margin`` for
``contact_rise_samples`` samples; the CUSUM once the margin's clipped excess over the drift
``k``, summed and never below 0, reaches ``h``. Both fall below ``contact_off_margin``.
Higher thresholds, longer counts and larger ``h`` raise fewer false contact events at rest and
detect a press later (and the lightest touches not at all). This module runs one exported
model through the C fixed-point runtime on the given recordings for a grid of each rule's
parameters, everything else as exported, and scores each with the keys of ``fbgforce evaluate
--json``: false contact events per minute at rest, onset delay (median and 90th percentile) and
the detection rate by force bin. The Schmitt rows sweep the rise margin (a factor of the
model's own) for a few counts, the CUSUM rows its threshold ``h`` for a few drifts ``k``
around the model's; :func:`quickest_quiet` reads off each rule's quickest setting that stays
within a false-event rate (where the frontier lies on these recordings).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce.evaluation import metrics as fmetrics
from fbgforce.evaluation import onset_bound
from fbgforce.model import artifact, decision, modeldir
from fbgforce.recordings import tare as ftare
from fbgforce.export import blob
from fbgforce.export.quantize import quantize_in_use
from fbgforce.pybind import Runtime

#: Rise thresholds as multiples of the model's own (its calibration rest margins' quantile).
ON_SCALES = (0.0, 0.5, 1.0, 1.5, 2.0)
#: Rise counts, in samples.
RISE_COUNTS = (1, 3, 6)
#: CUSUM thresholds as multiples of the base ``h`` (:func:`cusum_base`).
H_SCALES = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
#: CUSUM drifts as offsets from the base ``k``, margin units (a logit difference; the contact
#: net's margin at rest spreads about 2 on the family of tests/foreign.py): below the rest
#: quantile a larger ``h`` waits out the noise, above it a sample needs more margin to count.
K_OFFSETS = (-1.0, 0.0, 1.0)
#: False contact events per minute at rest :func:`quickest_quiet` allows by default: the goal
#: of docs/robustness.md, "Use in the field".
QUIET_PER_MIN = 1.0
#: The median onset goal of the same page, ms: drawn on the figure beside the false-event goal.
ONSET_GOAL_MS = 10.0
#: The columns of ``decision.csv``, one row per setting.
CSV_COLUMNS = ("rule", "contact_on_margin", "contact_rise_samples", "cusum_h", "cusum_k",
               "cusum_lo", "cusum_hi", "default", "false_events_per_min", "rest_s",
               "onset_median_ms", "onset_p90_ms", "detected_above_1N")


def cusum_base(own: artifact.InUse, sample_rate_hz: float = 1000.0) -> tuple[float, float, float]:
    """``(h, k, lo)`` the CUSUM rows sweep around: the model's own when it has the CUSUM on;
    else ``k`` its rest quantile (``contact_on_margin / REST_MARGIN_FACTOR``, the lowest drift
    the trainer's :func:`fbgforce.model.decision.cusum_parameters` tries) and ``h`` what the
    Schmitt trigger asks of a rise above it (``contact_rise_samples`` samples of ``max(k,
    0.5)``, the trainer's least ``h``), ``lo`` unclipped."""
    if own.contact_cusum_h:
        return own.contact_cusum_h, own.contact_cusum_k, own.contact_cusum_lo
    k = own.contact_on_margin / decision.REST_MARGIN_FACTOR
    rise = max(own.contact_rise_samples, int(round(decision.RISE_S * sample_rate_hz)))
    return rise * max(k, 0.5), k, -decision.CUSUM_MAX


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
                   rise_counts: Sequence[int] = RISE_COUNTS,
                   h_scales: Sequence[float] = H_SCALES,
                   k_offsets: Sequence[float] = K_OFFSETS) -> dict[str, Any]:
    """The grid's rows (``rule``, its parameters and the scores), the model's own setting
    marked ``default``: the Schmitt trigger over ``on_scales`` times the model's rise margin
    (the factor the trainer sets) and ``rise_counts``, the CUSUM over ``h_scales`` times
    :func:`cusum_base`'s ``h`` for each drift ``k + offset`` of ``k_offsets`` (:func:`cusum_base`'s
    ``k``), with its ``lo`` and ``hi = k + h / 2``. Both keep the model's
    ``contact_off_margin``. ``quickest`` holds :func:`quickest_quiet` of the rows,
    ``noise_allows`` what the recordings' own noise allows any decision at that quiet
    (:func:`fbgforce.evaluation.onset_bound.bound`; None without rests to measure it on)."""
    model = modeldir.load(model_dir)
    q0 = blob.load_model_blob(model_dir)
    own = model.in_use
    schmitt = dataclasses.replace(own, contact_cusum_h=0.0, contact_cusum_k=0.0,
                                  contact_cusum_lo=0.0, contact_cusum_hi=0.0)
    base_on = own.contact_on_margin
    if own.contact_cusum_h:       # a CUSUM model: its Schmitt rows around its drift
        base_on = decision.REST_MARGIN_FACTOR * own.contact_cusum_k
    rows = []
    for scale in on_scales:
        for rise in rise_counts:
            on = scale * base_on
            iu = dataclasses.replace(schmitt, contact_on_margin=on, contact_off_margin=-0.5 * on,
                                     contact_rise_samples=rise)
            q = dataclasses.replace(q0, **quantize_in_use(iu, q0.z_mult, q0.z_shift))
            rows.append({"rule": "schmitt", "contact_on_margin": on, "contact_rise_samples": rise,
                         "default": (not own.contact_cusum_h and scale == 1.0
                                     and rise == own.contact_rise_samples),
                         **_score(q, recordings)})
    h0, k0, lo = cusum_base(own)
    top = decision.CUSUM_MAX    # the contract's range: a threshold past it is one no press reaches
    for offset in k_offsets:
        k = float(np.clip(k0 + offset, -top, top))
        for scale in h_scales:
            h = min(scale * h0, top)
            own_setting = bool(own.contact_cusum_h) and scale == 1.0 and offset == 0.0
            hi = own.contact_cusum_hi if own_setting else min(k + 0.5 * h, top)
            iu = dataclasses.replace(schmitt, contact_on_margin=0.0, contact_rise_samples=1,
                                     contact_off_margin=own.contact_off_margin, contact_cusum_h=h,
                                     contact_cusum_k=k, contact_cusum_lo=lo, contact_cusum_hi=hi)
            q = dataclasses.replace(q0, **quantize_in_use(iu, q0.z_mult, q0.z_shift))
            rows.append({"rule": "cusum", "cusum_h": h, "cusum_k": k, "cusum_lo": lo,
                         "cusum_hi": hi, "default": own_setting, **_score(q, recordings)})
    return {"model": str(model_dir), "model_on_margin": own.contact_on_margin,
            "cusum_base": {"h": h0, "k": k0, "lo": lo}, "rows": rows,
            "quickest": quickest_quiet(rows),
            "noise_allows": onset_bound.bound(recordings, QUIET_PER_MIN)}


def quickest_quiet(rows: Sequence[dict[str, Any]], per_min: float = QUIET_PER_MIN
                   ) -> dict[str, dict[str, Any] | None]:
    """Each rule's row with the least median onset among those with at most ``per_min``
    false contact events per minute at rest (ties: the higher detection above 1 N), or None
    when no row of the rule is that quiet: how quick the decision can be on these recordings
    at that quiet, whatever the trainer would set."""
    def quiet(r: dict[str, Any]) -> bool:
        return (r["false_events_per_min"] is not None and r["onset_median_ms"] is not None
                and r["false_events_per_min"] <= per_min)

    return {rule: min((r for r in rows if r["rule"] == rule and quiet(r)), default=None,
                      key=lambda r: (r["onset_median_ms"], -(r["detected_above_1N"] or 0.0)))
            for rule in dict.fromkeys(r["rule"] for r in rows)}


def _fmt(v: Any, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def _setting(r: dict[str, Any]) -> str:
    if r["rule"] == "cusum":
        return f"CUSUM k {r['cusum_k']:.2f}, h {r['cusum_h']:.2f}"
    return f"Schmitt {r['contact_on_margin']:.2f} / {r['contact_rise_samples']}"


def markdown(res: dict[str, Any]) -> str:
    """The grid as a markdown table, then each rule's quickest setting within
    :data:`QUIET_PER_MIN` false events per minute (``res["quickest"]``)."""
    lines = ["| rule | rise margin or k | rise samples or h | false events /min at rest | "
             "onset median ms | onset p90 ms | detected > 1 N |", "|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        mark = " (default)" if r["default"] else ""
        if r["rule"] == "cusum":
            a, b = f"{r['cusum_k']:.2f}", f"{r['cusum_h']:.2f}"
        else:
            a, b = f"{r['contact_on_margin']:.2f}", f"{r['contact_rise_samples']}"
        det = r["detected_above_1N"]
        lines.append(f"| {r['rule']}{mark} | {a} | {b} | {_fmt(r['false_events_per_min'], '.2f')} | "
                     f"{_fmt(r['onset_median_ms'], '.1f')} | {_fmt(r['onset_p90_ms'], '.1f')} | "
                     f"{_fmt(None if det is None else 100 * det, '.2f')} % |")
    lines.append("")
    for rule, r in res.get("quickest", {}).items():
        if r is None:
            lines.append(f"- {rule}: no setting of the grid stays within {QUIET_PER_MIN:g} false "
                         "event(s) per minute at rest")
        else:
            det = r["detected_above_1N"]
            lines.append(f"- quickest {rule} within {QUIET_PER_MIN:g} false event(s) per minute "
                         f"at rest: {_setting(r)}, {r['false_events_per_min']:.2f} /min, onset "
                         f"{r['onset_median_ms']:.1f} ms (p90 {_fmt(r['onset_p90_ms'], '.1f')}), "
                         f"detected > 1 N {_fmt(None if det is None else 100 * det, '.2f')} %")
    best = onset_bound.median_onset_ms(res.get("noise_allows"))
    if best is not None:
        found = res["noise_allows"]["detected_above_1N"]
        lines.append(f"- the recordings' own noise ({res['noise_allows']['noise_pm']:.1f} pm"
                     f"{onset_bound.lag_text(res['noise_allows'])}) "
                     f"allows no decision within {QUIET_PER_MIN:g} false event(s) per minute "
                     f"at rest an onset before {best:.1f} ms median, nor more than "
                     f"{_fmt(None if found is None else 100 * found, '.2f')} % detected > 1 N "
                     "(docs/tradeoff.md, \"The information bound\")")
    return "\n".join(lines)


def csv_text(res: dict[str, Any]) -> str:
    """``decision.csv``: one line per row of the grid, :data:`CSV_COLUMNS` (empty where a
    column is not the row's rule's)."""
    lines = [",".join(CSV_COLUMNS)]
    for r in res["rows"]:
        cells = []
        for c in CSV_COLUMNS:
            v = r.get(c)
            cells.append("" if v is None else (str(int(v)) if isinstance(v, bool) else
                                                format(v, ".6g") if isinstance(v, float) else str(v)))
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def plot(res: dict[str, Any], path: Path) -> Path:
    """False events per minute against median onset delay: one line per rise count of the
    Schmitt trigger (labels: its rise margin), one per drift ``k`` of the CUSUM (labels: its
    ``h``)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    curves: list[tuple[str, list[dict[str, Any]], str]] = [
        (f"Schmitt, rise after {rise} sample(s)",
         [r for r in res["rows"] if r["rule"] == "schmitt" and r["contact_rise_samples"] == rise],
         "contact_on_margin")
        for rise in sorted({r["contact_rise_samples"] for r in res["rows"] if r["rule"] == "schmitt"})]
    curves += [(f"CUSUM, k = {k:.2f} (labels: h)",
                [r for r in res["rows"] if r["rule"] == "cusum" and r["cusum_k"] == k], "cusum_h")
               for k in sorted({r["cusum_k"] for r in res["rows"] if r["rule"] == "cusum"})]
    for label, rows, key in curves:
        pts = [(r["onset_median_ms"], r["false_events_per_min"], r[key]) for r in rows
               if r["onset_median_ms"] is not None and r["false_events_per_min"] is not None]
        if not pts:
            continue
        x, y, par = zip(*pts)
        ax.plot(x, np.maximum(y, 0.05), marker="s" if key == "cusum_h" else "o",
                ls="-" if key == "cusum_h" else "--", label=label)
        for xi, yi, pi in zip(x, y, par):
            ax.annotate(f"{pi:.1f}", (xi, max(yi, 0.05)), textcoords="offset points",
                        xytext=(4, 3), fontsize=7)
    for r in res["rows"]:
        if r["default"] and r["onset_median_ms"] is not None:
            ax.plot([r["onset_median_ms"]], [max(r["false_events_per_min"] or 0.0, 0.05)], "k*",
                    markersize=12, label="exported default")
    ax.axhline(QUIET_PER_MIN, color="grey", lw=0.8, ls="--")
    ax.axvline(ONSET_GOAL_MS, color="grey", lw=0.8, ls=":")
    ax.set_yscale("log")
    best = onset_bound.median_onset_ms(res.get("noise_allows"))
    if best is not None:
        # Quicker than the bound and as quiet as the line, no decision can be: the noise's
        # corner, not the rule's.
        (x0, x1), (y0, _) = ax.get_xlim(), ax.get_ylim()
        left = min(x0, best - 1.0)
        ax.fill_between([left, best], y0, QUIET_PER_MIN, color="0.85", zorder=0,
                        label=f"out of reach at this noise (bound {best:.1f} ms)")
        ax.set_xlim(left, max(x1, best + 1.0))
        ax.set_ylim(bottom=y0)
    ax.set_xlabel("median onset delay, ms (first labelled contact sample to detection)")
    ax.set_ylabel("false contact events per minute at rest (0 drawn at 0.05)")
    ax.set_title("A quiet decision costs onset delay: Schmitt trigger and CUSUM")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
