"""``fbgforce verify``: C fixed point vs the integer reference vs the float model, every sample.

- ``mismatches``: samples where the C runtime and :mod:`fbgforce.export.intref` differ in any
  bit of any output field (must be 0).
- ``contact_disagreements``: samples where the fixed-point contact flag differs from the float
  model's; ``max_abs_float_margin_at_disagreement`` shows they lie at the threshold.
- ``max_abs_err_*``: fixed vs float on samples where both say "contact".
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce import contract

from fbgforce.model import floatref, modeldir
from fbgforce.export import intref
from fbgforce.export.blob import load_model_blob
from fbgforce.export.exporter import recording_baseline

RAW_FIELDS = contract.OUTPUT_FIELDS


def verify(model_dir: str | Path, data: Sequence[str | Path]) -> dict[str, Any]:
    """Compare the three implementations on every sample of the recordings in ``data``."""
    from fbgforce.recordings import dataset as fds
    from fbgforce.pybind import Runtime

    model = modeldir.load(model_dir)
    q = load_model_blob(model_dir)
    res = {"samples": 0, "mismatches": 0, "contact_disagreements": 0, "max_abs_err_force_N": 0.0,
           "max_abs_err_x_mm": 0.0, "max_abs_err_y_mm": 0.0,
           "max_abs_float_margin_at_disagreement": 0.0, "sensor_fault_samples": 0,
           "saturated_samples": 0}
    for path in data:
        ds = fds.load(path)
        base = recording_baseline(ds, str(path))
        wl_fm, base_fm = intref.nm_to_fm(ds.wl_nm), intref.nm_to_fm(base)
        rt = Runtime(model_dir)
        rt.set_baseline(base_fm)
        c_out = rt.run_raw(wl_fm)
        ref = intref.run(q, wl_fm, base_fm)
        differs = np.zeros(len(ds), dtype=bool)
        for k in RAW_FIELDS:
            differs |= np.asarray(c_out[k], dtype=np.int64) != ref[k]
        fixed = intref.to_engine_dict(ref)
        flt = floatref.predict(model, ds.wl_nm, base)
        logits = model.contact.forward(
            floatref.features(model, ds.wl_nm, base)[:, :model.preprocess.n_features])
        margin = logits[:, 1] - logits[:, 0]
        dis = fixed["contact"] != flt["contact"]
        both = fixed["contact"] & flt["contact"]
        res["samples"] += len(ds)
        res["mismatches"] += int(differs.sum())
        res["contact_disagreements"] += int(dis.sum())
        if dis.any():
            res["max_abs_float_margin_at_disagreement"] = max(
                res["max_abs_float_margin_at_disagreement"], float(np.abs(margin[dis]).max()))
        for k in ("force_N", "x_mm", "y_mm"):
            if both.any():
                res[f"max_abs_err_{k}"] = max(res[f"max_abs_err_{k}"],
                                             float(np.abs(fixed[k][both] - flt[k][both]).max()))
        res["sensor_fault_samples"] += int((ref["status"] & intref.STATUS_SENSOR_FAULT != 0).sum())
        res["saturated_samples"] += int((ref["status"] & intref.STATUS_SATURATED != 0).sum())
    return res
