"""The one definition of fbgforce's accuracy metrics (docs/cli.md, "Metric definitions").

Every engine, command and benchmark scores predictions with :func:`compute` (or
:func:`from_dataset`), so a number printed by ``evaluate``, ``report`` or ``tradeoff`` always
means the same thing:

- ``contact_accuracy``: fraction of ALL samples whose predicted contact equals the true contact.
- ``rmse_force_N``: RMSE over samples with TRUE contact of what the pipeline outputs (0 N where
  it says "no contact") against the load-cell force. A missed contact therefore costs its whole
  force, as it would in a controller.
- ``rmse_x_mm`` / ``rmse_y_mm``: RMSE over samples where true AND predicted contact are both
  "contact" (a location only exists there).
- ``n_samples``: number of samples scored.

Extras (same conventions): ``contact_accuracy_above_5N`` (true contact with force > 5 N,
fraction detected, the paper's "100 % over 5 N"), ``false_contact_rate`` (fraction of true
no-contact samples flagged as contact), ``by_force`` (the three RMSEs and contact accuracy per
true-force range), ``boundary`` / ``interior`` (location and force RMSE for contacts within
``boundary_mm`` of the pad edge, and the rest). An RMSE over an empty set is ``None`` (JSON
``null``), never NaN, so the JSON stays standard.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

#: Upper edges (N) of the force ranges reported under ``by_force``; the last range is open.
FORCE_BINS_N: tuple[float, ...] = (5.0, 20.0, 40.0)
#: Contacts closer than this to the pad edge count as "boundary" (mm).
BOUNDARY_MM = 2.0
#: Force above which the paper reports a 100 % contact success rate.
HIGH_FORCE_N = 5.0


def _pad_size_mm() -> tuple[float, float]:
    """Sensing-area size (x, y) in mm of the nominal design."""
    from fbgforce.geometry import PAD_SIZE_MM

    return (float(PAD_SIZE_MM[0]), float(PAD_SIZE_MM[1]))


def _rmse(err: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(np.square(err)))) if err.size else None


def _core(pc: np.ndarray, pf: np.ndarray, px: np.ndarray, py: np.ndarray,
          tc: np.ndarray, tf: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> dict[str, Any]:
    both = tc & pc
    return {
        "contact_accuracy": float(np.mean(pc == tc)) if tc.size else None,
        "rmse_force_N": _rmse(pf[tc] - tf[tc]),
        "rmse_x_mm": _rmse(px[both] - tx[both]),
        "rmse_y_mm": _rmse(py[both] - ty[both]),
        "n_samples": int(tc.size),
    }


def compute(pred: Mapping[str, np.ndarray], contact: np.ndarray, force_N: np.ndarray,
            x_mm: np.ndarray, y_mm: np.ndarray, *, extras: bool = True,
            force_bins_N: Sequence[float] = FORCE_BINS_N, boundary_mm: float = BOUNDARY_MM,
            pad_mm: tuple[float, float] | None = None) -> dict[str, Any]:
    """Score predictions against ground truth.

    Parameters
    ----------
    pred
        Engine output with keys ``contact`` (bool), ``force_N``, ``x_mm``, ``y_mm`` (n,).
        ``force_N`` is taken as 0 wherever ``contact`` is False, whatever the engine put there.
    contact, force_N, x_mm, y_mm
        Ground truth (n,); x/y may be NaN where there is no contact.
    extras
        Add ``contact_accuracy_above_5N``, ``false_contact_rate``, ``by_force``, ``boundary``,
        ``interior`` to the five shared keys.
    force_bins_N, boundary_mm, pad_mm
        Range edges for ``by_force``; edge distance and pad size (x, y) for ``boundary``.

    Returns
    -------
    dict
        ``contact_accuracy``, ``rmse_force_N``, ``rmse_x_mm``, ``rmse_y_mm``, ``n_samples``
        (+ extras). RMSEs over empty sets are ``None``.
    """
    tc = np.asarray(contact).astype(bool).reshape(-1)
    n = tc.size
    tf = np.asarray(force_N, dtype=np.float64).reshape(-1)
    tx = np.asarray(x_mm, dtype=np.float64).reshape(-1)
    ty = np.asarray(y_mm, dtype=np.float64).reshape(-1)
    pc = np.asarray(pred["contact"]).astype(bool).reshape(-1)
    pf = np.where(pc, np.asarray(pred["force_N"], dtype=np.float64).reshape(-1), 0.0)
    px = np.asarray(pred["x_mm"], dtype=np.float64).reshape(-1)
    py = np.asarray(pred["y_mm"], dtype=np.float64).reshape(-1)
    for name, arr in (("truth force_N", tf), ("truth x_mm", tx), ("truth y_mm", ty),
                      ("pred contact", pc), ("pred force_N", pf), ("pred x_mm", px),
                      ("pred y_mm", py)):
        if arr.size != n:
            raise ValueError(f"{name} has {arr.size} samples, contact has {n}")
    out = _core(pc, pf, px, py, tc, tf, tx, ty)
    if not extras:
        return out
    high = tc & (tf > HIGH_FORCE_N)
    out["contact_accuracy_above_5N"] = float(np.mean(pc[high])) if high.any() else None
    out["false_contact_rate"] = float(np.mean(pc[~tc])) if (~tc).any() else None
    edges = [0.0, *map(float, force_bins_N), np.inf]
    by_force = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = tc & (tf > lo) & (tf <= hi)
        row = _core(pc[sel], pf[sel], px[sel], py[sel], tc[sel], tf[sel], tx[sel], ty[sel])
        row["range_N"] = [lo, None if np.isinf(hi) else hi]
        by_force.append(row)
    out["by_force"] = by_force
    w, h = pad_mm if pad_mm is not None else _pad_size_mm()
    with np.errstate(invalid="ignore"):
        edge_dist = np.minimum.reduce([tx, w - tx, ty, h - ty])
        near = tc & (edge_dist < boundary_mm)
    for key, sel in (("boundary", near), ("interior", tc & ~near)):
        row = _core(pc[sel], pf[sel], px[sel], py[sel], tc[sel], tf[sel], tx[sel], ty[sel])
        row["within_mm"] = boundary_mm
        out[key] = row
    return out


def from_dataset(pred: Mapping[str, np.ndarray], ds: Any, **kwargs: Any) -> dict[str, Any]:
    """:func:`compute` with the ground truth of a ``fbgforce.dataset.Dataset``."""
    return compute(pred, ds.contact, ds.force_N, ds.x_mm, ds.y_mm, **kwargs)


def headline(metrics: Mapping[str, Any]) -> str:
    """One line for progress bars and logs, e.g. ``acc 98.7% F 1.02 N x 0.41 y 0.88 mm``."""
    def fmt(v: Any, spec: str) -> str:
        return "-" if v is None else format(v, spec)
    acc = metrics.get("contact_accuracy")
    return (f"acc {fmt(None if acc is None else 100 * acc, '.1f')}% "
            f"F {fmt(metrics.get('rmse_force_N'), '.2f')} N "
            f"x {fmt(metrics.get('rmse_x_mm'), '.2f')} y {fmt(metrics.get('rmse_y_mm'), '.2f')} mm")
