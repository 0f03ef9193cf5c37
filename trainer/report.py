"""``fbgforce report``: the paper's results section (§V, §VII) side by side with ours.

Everything is measured on the held-out test presses (split 8:1:1 by press with the given seed)
of the recordings given, with the shared metric definitions of :mod:`fbgforce.evaluation.metrics`:

- model-based baseline, nominal and fitted (:mod:`fbgforce.trainer.baseline`), on the same
  compensated, causally filtered shifts the network sees;
- the hierarchical network with the causal (shipped) filter, the centred (paper's offline)
  filter and no filter (smoothing on/off, paper §VII-A);
- contact success overall and above 5 N, errors by force range and near the boundary
  (paper §VII-B);
- light touch: contact detected per finer force bin, and the per-press onset and release
  delays (ms).
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce.jsonutil import json_default
from fbgforce.evaluation import metrics as fmetrics
from fbgforce.evaluation.onset_bound import lag_text, median_onset_ms
from fbgforce.model import artifact, modeldir
from fbgforce.trainer import baseline as bl
from fbgforce.trainer.data import load_datasets
from fbgforce.trainer.scoring import evaluate_rows, predict_prepared
from fbgforce.trainer.train import prepare, train

#: The paper's numbers (Kim et al. 2019, §V and §VII-A).
PAPER = {
    "model_based": {"rmse_x_mm": 1.67, "rmse_y_mm": 9.72, "rmse_force_N": 10.18},
    "network": {"rmse_x_mm": 0.43, "rmse_y_mm": 1.11, "rmse_force_N": 1.16,
                "contact_accuracy": 0.984, "contact_accuracy_above_5N": 1.0},
    "network_unfiltered": {"rmse_force_N": 1.53, "contact_accuracy": 0.953},
    "training_time_s": 20 * 60,
}
KEYS = ("rmse_x_mm", "rmse_y_mm", "rmse_force_N", "contact_accuracy", "contact_accuracy_above_5N")
#: What each of the report's ``checks`` tests, in one line (``check_notes`` in the JSON, beside
#: each check in report.md and the demo's output).
CHECK_MEANING = {
    "network_beats_nominal_3x_y": "the causal network's y RMSE is at least 3x smaller than the "
                                  "nominal model-based estimate's (the paper's claim).",
    "network_beats_nominal_3x_force": "the same for the force RMSE.",
    "network_beats_fitted_on_every_metric": "the network is better than the model-based "
                                            "estimate fitted to this data on contact accuracy, "
                                            "force RMSE and x/y RMSE (on samples both detect).",
    "smoothing_improves_every_metric": "the net trained on causally filtered inputs is no worse "
                                       "than one trained on unfiltered inputs on contact "
                                       "accuracy, force RMSE and x/y RMSE (on samples both "
                                       "detect); the filter also costs delay, so a small loss on "
                                       "one metric can be a fair trade.",
    "errors_concentrate_below_5N": "location errors are largest and contact accuracy lowest "
                                   "below 5 N (the paper's observation).",
    "errors_concentrate_at_boundary": "location errors within 2 mm of the pad edge exceed "
                                      "those inside (the paper's observation).",
    "beats_paper_network": "per metric, whether ours is at least as good as the paper's "
                           "network (different data: the paper's device, ours simulated).",
}


def baselines(data: Any, network_test: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """Nominal and fitted model-based estimates scored on the test rows of prepared data.

    With ``network_test`` (the network's output on the test rows of ``data``), each baseline also
    gets ``common_with_network``: its x/y and the network's on the test samples both detect
    (:func:`fbgforce.evaluation.metrics.common_location`), since a baseline that misses the light touches
    is otherwise scored on easier samples.
    """
    tr, te = data.rows("train"), data.rows("test")
    free = tr[~data.contact[tr]]
    ctr = tr[data.contact[tr]]
    out = {}
    base_nm = np.median([r.baseline_nm for r in data.recordings], axis=0)
    # The beam model reads the filtered, compensated shifts: the first feature columns
    # (features with memory, if any, come after them).
    shifts = data.feats[:, :artifact.N_STRAIN]
    models = {"nominal": bl.nominal(base_nm),
              "fitted": bl.fit(shifts[ctr], data.force_N[ctr], data.x_mm[ctr], data.y_mm[ctr])}
    truth = data.truth(te)
    for name, m in models.items():
        m.set_threshold(shifts[free])
        pred = m.predict(shifts[te])
        out[name] = {"metrics": fmetrics.compute(pred, *truth), "params": m.to_dict()}
        if network_test is not None:
            out[name]["common_with_network"] = fmetrics.common_location(
                {"network": network_test, name: pred}, truth[0], truth[2], truth[3])
    return out


def _fmt(v: Any, key: str) -> str:
    if v is None:
        return "–"
    if key.startswith("contact"):
        return f"{100 * v:.1f} %"
    return f"{v:.2f}"


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b == 0 else a / b


def _given_model(model_dir: str | Path, ds_list: Sequence[Any],
                 described: Sequence[dict[str, Any]], seed: int
                 ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The given model in place of the causal net: its float outputs on every row, each
    recording run whole through its own preprocessing, and its entry of ``network`` (the
    test presses of the same split scored)."""
    from fbgforce.trainer.evaluate import evaluate, run_recording

    model = modeldir.load(model_dir)
    runs = [run_recording("float", model_dir, model, ds, d.get("path"))
            for ds, d in zip(ds_list, described)]
    m = evaluate(model_dir, ds_list, split="test", seed=seed, model=model, predictions=runs)
    preds = {k: np.concatenate([np.asarray(r[k]) for r in runs])
             for k in ("contact", "force_N", "x_mm", "y_mm")}
    return preds, {"metrics": m, "model": str(model_dir),
                   "train_seconds": model.metadata.get("times_s", {}).get("train"),
                   "group_delay_ms": model.metadata.get("filter", {}).get("group_delay_ms")}


def _checks(ours: dict[str, Any], base: dict[str, Any], nets: dict[str, Any],
            smoothing_common: dict[str, Any]) -> tuple[dict[str, Any], dict[str, str]]:
    """The report's checks (:data:`CHECK_MEANING`) on the causal net's test metrics ``ours``
    against the model-based baselines and the other filters, and a note on each: what it
    means and, where it fails, on what."""
    nominal = base["nominal"]["metrics"]
    checks = {
        "network_beats_nominal_3x_y": (_ratio(nominal["rmse_y_mm"], ours["rmse_y_mm"]) or 0) >= 3,
        "network_beats_nominal_3x_force":
            (_ratio(nominal["rmse_force_N"], ours["rmse_force_N"]) or 0) >= 3,
        "network_beats_fitted_on_every_metric": _beats_fitted(ours, base["fitted"]),
        "smoothing_improves_every_metric": _smoothing_improves(
            nets["causal"]["metrics"], nets["none"]["metrics"], smoothing_common),
        "errors_concentrate_below_5N": _below_5n_worse(ours),
        "errors_concentrate_at_boundary": _boundary_worse(ours),
        "beats_paper_network": {k: (ours.get(k) is not None and
                                    (ours[k] >= PAPER["network"][k] if k.startswith("contact")
                                     else ours[k] <= PAPER["network"][k]))
                                for k in KEYS},
    }
    failed_on = {
        "network_beats_fitted_on_every_metric": _not_better(
            ours, base["fitted"]["metrics"], base["fitted"].get("common_with_network", {}),
            "network", "fitted", strict=True),
        "smoothing_improves_every_metric": _not_better(
            nets["causal"]["metrics"], nets["none"]["metrics"], smoothing_common, "causal",
            "none", strict=False),
    }
    notes = {k: CHECK_MEANING[k] + (f" Not met on: {'; '.join(failed_on[k])}."
                                    if failed_on.get(k) else "")
             for k in checks}
    return checks, notes


def build_report(data_paths: Sequence[Any], *, model_dir: str | Path | None = None,
                 epochs: int = 200, seed: int = 0, sigma: float | None = None,
                 progress: bool | None = None) -> dict[str, Any]:
    """Run every comparison and return the report as a dict (see module docstring)."""
    t0 = time.perf_counter()
    ds_list, described = load_datasets(data_paths)
    sources = [d.get("path") or d.get("source") or "" for d in described]
    prepared = {kind: prepare(ds_list, seed=seed, filter=kind, sigma=sigma, sources=sources)
                for kind in ("causal", "centred", "none")}
    te = prepared["causal"].rows("test")
    nets: dict[str, Any] = {}
    preds: dict[str, dict[str, np.ndarray]] = {}  # each network's output on every row
    for kind, data in prepared.items():
        if kind == "causal" and model_dir is not None:
            preds[kind], nets[kind] = _given_model(model_dir, ds_list, described, seed)
            continue
        t1 = time.perf_counter()
        model = train(ds_list, epochs=epochs, seed=seed, filter=kind, sigma=sigma,
                      prepared=data, progress=progress)
        preds[kind] = predict_prepared(model, data)
        nets[kind] = {"metrics": evaluate_rows(model, data, data.rows("test")),
                      "train_seconds": time.perf_counter() - t1,
                      "group_delay_ms": model.metadata["filter"]["group_delay_ms"]}
    # The causal and unfiltered nets on the test rows: the baselines are compared with the
    # first, and smoothing on/off like for like (the unfiltered net misses more light touches,
    # so its own x/y come from heavier ones).
    test_preds = {kind: {k: np.asarray(v)[te] for k, v in preds[kind].items()}
                  for kind in ("causal", "none")}
    base = baselines(prepared["causal"], test_preds["causal"])
    truth = prepared["causal"].truth(te)
    smoothing_common = fmetrics.common_location(test_preds, truth[0], truth[2], truth[3])
    ours = nets["causal"]["metrics"]
    nominal = base["nominal"]["metrics"]
    checks, check_notes = _checks(ours, base, nets, smoothing_common)
    return {
        "data": described,
        "seed": seed,
        "test_samples": int(te.size),
        "filter_sigma_samples": prepared["causal"].pre.filter_sigma,
        "paper": PAPER,
        "model_based": base,
        "network": nets,
        "smoothing_common_location": smoothing_common,
        "ratios_nominal_over_network": {k: _ratio(nominal[k], ours[k])
                                        for k in ("rmse_x_mm", "rmse_y_mm", "rmse_force_N")},
        "checks": checks,
        "check_notes": check_notes,
        "seconds": time.perf_counter() - t0,
    }


def _not_better(a: dict[str, Any], b: dict[str, Any], common: dict[str, Any],
                a_name: str, b_name: str, *, strict: bool) -> list[str]:
    """The metrics on which estimator ``a`` is worse than ``b`` (not better, if ``strict``),
    with both values: contact and force as scored (``a``/``b`` metrics), x and y on the
    samples both detect (``common``, :func:`fbgforce.evaluation.metrics.common_location` of ``a_name``
    and ``b_name``). Empty when ``a`` wins everywhere."""
    if not common.get("n_samples"):
        return ["location (no sample that both detect)"]
    pairs = [("contact_accuracy", a.get("contact_accuracy"), b.get("contact_accuracy"), True),
             ("rmse_force_N", a.get("rmse_force_N"), b.get("rmse_force_N"), False)]
    pairs += [(k, common[a_name][k], common[b_name][k], False) for k in ("rmse_x_mm", "rmse_y_mm")]
    out = []
    for key, x, y, higher in pairs:
        if x is None or y is None:
            out.append(f"{key} (not measured)")
            continue
        ok = ((x > y) if higher else (x < y)) if strict else ((x >= y) if higher else (x <= y))
        if not ok:
            out.append(f"{key} {x:.4g} against {y:.4g}")
    return out


def _better_everywhere(a: dict[str, Any], b: dict[str, Any], common: dict[str, Any],
                       a_name: str, b_name: str, *, strict: bool) -> bool:
    """Estimator ``a`` at least as good as ``b`` (better, if ``strict``) on every metric
    (:func:`_not_better` finds none)."""
    return not _not_better(a, b, common, a_name, b_name, strict=strict)


def _beats_fitted(ours: dict[str, Any], fitted: dict[str, Any]) -> bool:
    """Better than the fitted baseline on every metric, location like for like."""
    return _better_everywhere(ours, fitted["metrics"], fitted.get("common_with_network", {}),
                              "network", "fitted", strict=True)


def _smoothing_improves(on: dict[str, Any], off: dict[str, Any], common: dict[str, Any]) -> bool:
    """The causal net no worse than the unfiltered one on every metric, location like for like."""
    return _better_everywhere(on, off, common, "causal", "none", strict=False)


def _below_5n_worse(m: dict[str, Any]) -> bool:
    low, rest = m["by_force"][0], m["by_force"][1:]
    worse = []
    for k in ("rmse_x_mm", "rmse_y_mm", "contact_accuracy"):
        others = [r[k] for r in rest if r[k] is not None]
        if low[k] is None or not others:
            continue
        worse.append(low[k] < min(others) if k.startswith("contact") else low[k] > max(others))
    return bool(worse) and all(worse)


def _boundary_worse(m: dict[str, Any]) -> bool:
    b, i = m["boundary"], m["interior"]
    pairs = [(b[k], i[k]) for k in ("rmse_x_mm", "rmse_y_mm") if b[k] is not None and i[k] is not None]
    return bool(pairs) and all(bv > iv for bv, iv in pairs)


def to_markdown(rep: dict[str, Any]) -> str:
    """The report as Markdown tables."""
    P = rep["paper"]
    nom, fit_ = rep["model_based"]["nominal"]["metrics"], rep["model_based"]["fitted"]["metrics"]
    nets = rep["network"]
    lines = ["# fbgforce report: paper vs ours", "",
             f"Data: {', '.join(str(d.get('path') or d.get('source')) for d in rep['data'])}; "
             f"held-out test presses ({rep['test_samples']} samples, split 8:1:1 by press, "
             f"seed {rep['seed']}). Metric definitions: docs/cli.md.", "",
             "## Model-based vs network (§V)", "",
             "| metric | paper model | ours nominal | ours fitted | paper network | "
             "ours causal | ours centred | ours unfiltered |",
             "|---|---|---|---|---|---|---|---|"]
    for k in KEYS:
        lines.append("| " + " | ".join([
            k, _fmt(P["model_based"].get(k), k), _fmt(nom.get(k), k), _fmt(fit_.get(k), k),
            _fmt(P["network"].get(k), k), _fmt(nets["causal"]["metrics"].get(k), k),
            _fmt(nets["centred"]["metrics"].get(k), k), _fmt(nets["none"]["metrics"].get(k), k)])
            + " |")
    common = rep["model_based"]["fitted"].get("common_with_network")
    if common and common["n_samples"]:
        net, fit_c = common["network"], common["fitted"]
        lines += ["", f"Location on the {common['n_samples']} test samples that both the causal "
                  "network and the fitted baseline call contact (like for like; each one's own "
                  f"x/y above leave out the touches it misses): network x {net['rmse_x_mm']:.2f}, "
                  f"y {net['rmse_y_mm']:.2f} mm; fitted x {fit_c['rmse_x_mm']:.2f}, "
                  f"y {fit_c['rmse_y_mm']:.2f} mm."]
    r = rep["ratios_nominal_over_network"]
    lines += ["", "Nominal baseline / causal network: " + ", ".join(
        f"{k} {v:.1f}×" for k, v in r.items() if v is not None), "",
        "## Smoothing on/off (§VII-A)", "",
        "| metric | paper off | paper on | ours off | ours causal | ours centred |",
        "|---|---|---|---|---|---|"]
    for k in ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm"):
        lines.append("| " + " | ".join([
            k, _fmt(P["network_unfiltered"].get(k), k), _fmt(P["network"].get(k), k),
            _fmt(nets["none"]["metrics"].get(k), k), _fmt(nets["causal"]["metrics"].get(k), k),
            _fmt(nets["centred"]["metrics"].get(k), k)]) + " |")
    sc = rep.get("smoothing_common_location")
    if sc and sc["n_samples"]:
        lines += ["", f"Location on the {sc['n_samples']} test samples that both the causal and the "
                  f"unfiltered network call contact: causal x {sc['causal']['rmse_x_mm']:.2f}, "
                  f"y {sc['causal']['rmse_y_mm']:.2f} mm; unfiltered x "
                  f"{sc['none']['rmse_x_mm']:.2f}, y {sc['none']['rmse_y_mm']:.2f} mm."]
    gd = nets["causal"].get("group_delay_ms")
    if gd is not None:
        lines += ["", f"Causal filter group delay: {gd:.2f} ms."]
    m = nets["causal"]["metrics"]
    lines += ["", "## Errors by force range and at the boundary (§VII-B), causal network", "",
              "| samples | n | contact | force RMSE N | x RMSE mm | y RMSE mm |",
              "|---|---|---|---|---|---|"]
    rows = [(f"{lo:g}–{hi:g} N" if hi is not None else f"> {lo:g} N", b)
            for b in m["by_force"] for lo, hi in [b["range_N"]]]
    rows += [(f"boundary (< {m['boundary']['within_mm']:g} mm from edge)", m["boundary"]),
             ("interior", m["interior"])]
    for label, b in rows:
        lines.append(f"| {label} | {b['n_samples']} | {_fmt(b['contact_accuracy'], 'contact')} | "
                     f"{_fmt(b['rmse_force_N'], 'f')} | {_fmt(b['rmse_x_mm'], 'x')} | "
                     f"{_fmt(b['rmse_y_mm'], 'y')} |")
    lines += ["", "## Light touch and timing, causal network", "",
              "| true force | n | contact detected |", "|---|---|---|"]
    for b in m.get("contact_by_force", []):
        lo, hi = b["range_N"]
        label = f"{lo:g}–{hi:g} N" if hi is not None else f"> {lo:g} N"
        lines.append(f"| {label} | {b['n_samples']} | {_fmt(b['contact_accuracy'], 'contact')} |")
    timing = m.get("contact_timing")
    if timing:
        on, off = timing["onset_delay_ms"], timing["release_delay_ms"]
        lines += ["", f"Per press ({timing['presses']} presses, {timing['missed_presses']} "
                  "missed): onset delay " + _delay(on) + "; release delay " + _delay(off) + "."]
        best = median_onset_ms(m.get("noise_allows"))
        if best is not None:
            lines += ["", f"The recordings' own noise ({m['noise_allows']['noise_pm']:.1f} pm a "
                      f"grating{lag_text(m['noise_allows'])}) lets no contact decision within one "
                      f"false event a minute at rest find these presses sooner than {best:.1f} ms "
                      "median (docs/lab-import.md, \"Coverage\")."]
    lines += ["", "## Checks", "", *check_lines(rep), ""]
    return "\n".join(lines)


def check_lines(rep: dict[str, Any]) -> list[str]:
    """One Markdown list item per check: its value and what it means (``check_notes``)."""
    notes = rep.get("check_notes", {})
    return [f"- {k}: {v}" + (f" ({notes[k]})" if k in notes else "")
            for k, v in rep["checks"].items()]


def _delay(stats: dict[str, Any]) -> str:
    if stats.get("median") is None:
        return "–"
    return (f"median {stats['median']:.1f} ms, mean {stats['mean']:.1f} ms, "
            f"90th percentile {stats['p90']:.1f} ms, max {stats['max']:.1f} ms")


def write(rep: dict[str, Any], out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``report.md`` and ``report.json`` into ``out_dir``."""
    from fbgforce import fileio

    out = Path(out_dir)
    md, js = out / "report.md", out / "report.json"
    with fileio.Outputs("--out") as files:
        files.write_text(md, to_markdown(rep))
        files.write_text(js, json.dumps(rep, indent=2, default=json_default) + "\n")
    return md, js

