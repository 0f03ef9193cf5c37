"""Scoring: the reference row, the error index, "matches the reference", Pareto fronts and the
host speed ratios of one run."""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from fbgforce.tradeoff.grid import Settings, Variant

METRIC_KEYS = ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm")
#: "Matches the reference": RMSE at most this factor higher, contact accuracy at most
#: CONTACT_SLACK lower.
MATCH_RMSE_FACTOR = 1.05
CONTACT_SLACK = 0.002
#: Floor on contact error rates in the error index, so a perfect contact net does not divide
#: by zero (0.1 % is below what any engine here distinguishes on a test split).
CONTACT_ERR_FLOOR = 1e-3


def reference(rows: list[dict[str, Any]], s: Settings) -> dict[str, Any] | None:
    """The shipped configuration (paper width, default causal filter, default memory) in
    numpy float64; else the first measured causal row."""
    ref_tag = Variant("causal", s.default_sigma, "paper").tag
    for r in rows:
        if r["variant"] == ref_tag and r["engine"] == "float" and r.get("status") == "ok":
            return r
    ok = [r for r in rows if r.get("status") == "ok" and r["causal"]]
    return ok[0] if ok else None


def _contact_err(acc: float) -> float:
    return max(1.0 - acc, CONTACT_ERR_FLOOR)


def score(rows: list[dict[str, Any]], ref: dict[str, Any] | None) -> None:
    for r in rows:
        r["error_index"] = None
        r["matches_reference"] = None
        r["is_reference"] = r is ref
        if ref is None or r.get("status") != "ok":
            continue
        ratios = [_contact_err(r["contact_accuracy"]) / _contact_err(ref["contact_accuracy"])]
        for k in METRIC_KEYS[1:]:
            if r.get(k) is None or not ref.get(k):
                continue
            ratios.append(r[k] / ref[k])
        r["error_index"] = float(math.exp(np.mean(np.log(ratios))))
        r["matches_reference"] = bool(
            r["contact_accuracy"] >= ref["contact_accuracy"] - CONTACT_SLACK
            and all(r.get(k) is not None and ref.get(k) is not None
                    and r[k] <= MATCH_RMSE_FACTOR * ref[k] for k in METRIC_KEYS[1:]))


#: Error indices closer than this count as equal when deciding dominance: differences in
#: the third decimal (float32 vs float64, int16 rounding) are not accuracy differences.
PARETO_ERR_TOL = 0.01


def pareto_mask(points: Sequence[tuple[float, ...]], tol: Sequence[float] | None = None
                ) -> list[bool]:
    """True for points that no other point dominates (minimising every coordinate).

    ``q`` dominates ``p`` when ``q[k] <= p[k] + tol[k]`` for every k and ``q[k] < p[k] - tol[k]``
    for at least one k (``tol`` defaults to zeros: plain Pareto dominance).
    """
    pts = [tuple(float(v) for v in p) for p in points]
    t = [0.0] * (len(pts[0]) if pts else 0) if tol is None else [float(v) for v in tol]
    out = []
    for i, p in enumerate(pts):
        dominated = False
        for j, q in enumerate(pts):
            if j == i:
                continue
            if all(q[k] <= p[k] + t[k] for k in range(len(p))) and \
                    any(q[k] < p[k] - t[k] for k in range(len(p))):
                dominated = True
                break
        out.append(not dominated)
    return out


def mark_pareto(rows: list[dict[str, Any]]) -> None:
    """Pareto fronts among deployable (causal) rows: error vs compute time, and error vs
    time including the filter delay (what a haptic loop feels)."""
    cand = [r for r in rows if r.get("status") == "ok" and r["causal"]
            and r.get("error_index") is not None and r.get("host_batch_ns") is not None]
    for r in rows:
        r["pareto_compute"] = False
        r["pareto_delay"] = False
    for key, coords in (("pareto_compute", lambda r: (r["error_index"], r["host_batch_ns"])),
                        ("pareto_delay", lambda r: (r["error_index"], r["filter_delay_ms"],
                                                    r["host_batch_ns"]))):
        pts = [coords(r) for r in cand]
        tol = [PARETO_ERR_TOL] + [0.0] * (len(pts[0]) - 1) if pts else None
        for r, front in zip(cand, pareto_mask(pts, tol)):
            r[key] = front


def ratios(rows: list[dict[str, Any]], s: Settings) -> dict[str, Any]:
    """Host speed of C fixed int16 against onnxruntime and numpy, same model, same run."""
    by = {(r["variant"], r["engine"]): r for r in rows}
    ref_tag = Variant("causal", s.default_sigma, "paper").tag
    out: dict[str, Any] = {"variant": ref_tag}
    c = by.get((ref_tag, "fixed"))
    for other in ("onnx", "float", "cfloat"):
        o = by.get((ref_tag, other))
        for mode in ("single", "batch"):
            k = f"host_{mode}_ns"
            if c and o and c.get(k) and o.get(k):
                out[f"{other}_over_fixed_{mode}"] = o[k] / c[k]
            else:
                out[f"{other}_over_fixed_{mode}"] = None
    return out
