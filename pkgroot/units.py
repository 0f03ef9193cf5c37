"""Unit conversions every engine shares, low in the tree (imports nothing from fbgforce but
the contract), so the runtime binding, the exporter and the serial protocols use one rule."""
from __future__ import annotations

import numpy as np

from fbgforce.contract import SAT32


def nm_to_fm(wl_nm: np.ndarray) -> np.ndarray:
    """Wavelengths nm (float) -> int32 femtometres as the runtime receives them.

    Rounded to nearest (ties to even); NaN/inf (a lost peak) -> 0; clipped to the int32 range.
    Every engine converts through this one function, so all see the same integers.
    """
    x = np.asarray(wl_nm, dtype=np.float64) * 1e6
    x = np.where(np.isfinite(x), x, 0.0)
    return np.clip(np.rint(x), -SAT32, SAT32).astype(np.int32)


def to_engine_dict(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Fixed-point outputs -> the engine keys of fbgforce.engines (SI-ish units, NaN gating)."""
    contact = np.asarray(out["contact"]).astype(bool)
    return {
        "contact": contact,
        "p_contact": np.asarray(out["contact_conf_q15"], dtype=np.float64) / 32768.0,
        "force_N": np.asarray(out["force_mN"], dtype=np.float64) / 1000.0,
        "x_mm": np.where(contact, np.asarray(out["x_um"], dtype=np.float64) / 1000.0, np.nan),
        "y_mm": np.where(contact, np.asarray(out["y_um"], dtype=np.float64) / 1000.0, np.nan),
        "status": np.asarray(out["status"], dtype=np.uint32),
    }
