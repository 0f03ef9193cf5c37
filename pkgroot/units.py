"""Unit conversions every engine shares, low in the tree (imports nothing from fbgforce but
the contract), so the runtime binding, the exporter and the serial protocols use one rule."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from fbgforce.contract import SAT32, STATUS_FLAG

_RELEASING = STATUS_FLAG["RELEASING"]


def nm_to_fm(wl_nm: np.ndarray) -> np.ndarray:
    """Wavelengths nm (float) -> int32 femtometres as the runtime receives them.

    Rounded to nearest (ties to even); NaN/inf (a lost peak) -> 0; clipped to the int32 range.
    Every engine converts through this one function, so all see the same integers.
    """
    x = np.asarray(wl_nm, dtype=np.float64) * 1e6
    x = np.where(np.isfinite(x), x, 0.0)
    return np.clip(np.rint(x), -SAT32, SAT32).astype(np.int32)


def estimate_shown(contact: Any, status: Any) -> Any:
    """Where an engine shows a force and location: in contact, and in the release band after it
    (status RELEASING: contact has ended at the contact net's own margin while the decision
    still holds, and the estimate follows the falling load). A bool array (n,) from arrays, or
    one sample's bool."""
    if np.ndim(contact) == 0:
        return bool(contact) or bool(int(status) & _RELEASING)
    return np.asarray(contact, dtype=bool) | ((np.asarray(status).astype(np.uint32) & _RELEASING) != 0)


def gate_outputs(shown: Any, force_N: Any, x_mm: Any, y_mm: Any) -> tuple[Any, Any, Any]:
    """The output rule of every engine: where no estimate is shown (no contact and no release
    band, :func:`estimate_shown`) force 0 N and location NaN.

    Parameters
    ----------
    shown
        Where the estimate is shown: a bool array (n,), or one sample's bool.
    force_N, x_mm, y_mm
        What the nets say, whatever the decision (arrays (n,), or one sample's numbers).

    Returns
    -------
    tuple
        ``(force_N, x_mm, y_mm)`` gated: float64 arrays (n,), or Python floats for one sample
        (the single-sample path of a 1 kHz loop, which numpy's array calls would slow down).
    """
    if np.ndim(shown) == 0:
        if shown:
            return float(force_N), float(x_mm), float(y_mm)
        return 0.0, math.nan, math.nan
    c = np.asarray(shown, dtype=bool)
    return (np.where(c, np.asarray(force_N, dtype=np.float64), 0.0),
            np.where(c, np.asarray(x_mm, dtype=np.float64), np.nan),
            np.where(c, np.asarray(y_mm, dtype=np.float64), np.nan))


def to_engine_dict(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Fixed-point outputs -> the engine keys of fbgforce.evaluation.engines (SI-ish units, gated by
    :func:`gate_outputs`)."""
    contact = np.asarray(out["contact"]).astype(bool)
    force_N, x_mm, y_mm = gate_outputs(
        estimate_shown(contact, out["status"]), np.asarray(out["force_mN"], dtype=np.float64) / 1000.0,
        np.asarray(out["x_um"], dtype=np.float64) / 1000.0,
        np.asarray(out["y_um"], dtype=np.float64) / 1000.0)
    return {
        "contact": contact,
        "p_contact": np.asarray(out["contact_conf_q15"], dtype=np.float64) / 32768.0,
        "force_N": force_N, "x_mm": x_mm, "y_mm": y_mm,
        "status": np.asarray(out["status"], dtype=np.uint32),
    }
