"""``fbgforce export``: every artifact of a model directory in one call.

Writes into the model directory ``model.onnx`` (float reference, via
:func:`fbgforce.export.onnx_export.export_onnx`), ``model.fbgm`` (fixed-point blob), ``c/``
(generated C, :mod:`fbgforce.export.codegen`) and ``export_report.json`` (scales, the
accumulator bounds proven from the weights, the largest accumulators actually reached on the
calibration data, and the fixed-vs-float error on it).
"""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce import fileio
from fbgforce.model import freshness
from fbgforce.model import artifact, floatref, modeldir
from fbgforce.errors import InputError
from fbgforce.export import blob, codegen, intref
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import QModel
from fbgforce.units import nm_to_fm, to_engine_dict

REPORT_FILE = freshness.REPORT_FILE
C_DIR = freshness.C_DIR


def recording_baseline(ds: Any, path: str | None = None) -> np.ndarray:
    """The tare baseline of a recording, the same rule evaluate/verify use (trainer's tare)."""
    from fbgforce.recordings.tare import tare

    return tare(ds.wl_nm, ds.contact, ds.t_s, path=path)[0]


def calibration_recordings(model_dir: str | Path, model: artifact.HierarchicalModel,
                           calib: Sequence[str | Path] | None) -> artifact.CalibrationRecordings:
    """Calibration recordings: the ``calib`` files, else those the model directory keeps of
    its training data (:func:`fbgforce.model.modeldir.load_calibration`; the training files themselves
    are never reopened, they may have moved)."""
    from fbgforce.recordings import dataset as fds

    if not calib:
        kept = modeldir.load_calibration(model_dir, model)
        if kept is None:
            raise InputError(f"no calibration data: the model directory has no {modeldir.CALIBRATION_NPZ} "
                             "of its training data (train it again with 'fbgforce train'); or pass "
                             "--calib FILE (a recording in the dataset format)", column="--calib")
        return kept
    recs, forces, paths = [], [], [str(p) for p in calib]
    for p in paths:
        ds = fds.load(p)
        recs.append((ds.wl_nm, recording_baseline(ds, p)))
        forces.append(np.asarray(ds.force_N, dtype=np.float64)[np.asarray(ds.contact, dtype=bool)])
    return artifact.CalibrationRecordings(recs, forces, paths)


def export_model(model_dir: str | Path, *, bits: int = 16, calib: Sequence[str | Path] | None = None,
                 name: str = "fbgforce", jump_nm: float = qz.DEFAULT_JUMP_NM,
                 overload_N: float | None = None, stuck_samples: int | None = None,
                 onnx: bool = True, acc32_max_drop: float = qz.ACC32_MAX_DROP) -> dict[str, Any]:
    """Quantise and write every artifact; returns the export report (also written)."""
    t0 = time.perf_counter()
    root = Path(model_dir)
    model = modeldir.load(root)
    kept = calibration_recordings(root, model, calib)
    recs, paths = kept.recordings, kept.sources
    cal = qz.calibrate(model, recs, kept.contact_force_N)
    q, report = qz.quantize(model, cal, bits=bits, jump_nm=jump_nm, overload_N=overload_N,
                            stuck_samples=stuck_samples, acc32_max_drop=acc32_max_drop)
    data = blob.to_bytes(q)
    # Everything is made in memory first, then written as one atomic set: a failed write (a
    # full disk) leaves the previous export whole, never a new blob beside an old header.
    outputs: dict[str, bytes] = {}
    if onnx:
        from fbgforce.export.onnx_export import checked_graph

        outputs[freshness.ONNX_FILE] = checked_graph(model).SerializeToString()
    outputs[blob.FILE_NAME] = data
    for fname, text in codegen.c_sources(q, model, name).items():
        outputs[f"{C_DIR}/{fname}"] = text.encode()
    files = [str(root / rel) for rel in outputs]

    # Measured on the calibration data: the largest accumulators (to set beside the proven
    # bounds) and the fixed-vs-float error.
    trace: dict[str, int] = {}
    errs = {"force_N": 0.0, "x_mm": 0.0, "y_mm": 0.0}
    disagree = samples = 0
    for wl, base in recs:
        out = to_engine_dict(intref.run(q, nm_to_fm(wl), nm_to_fm(base), trace=trace))
        ref = floatref.predict(model, wl, base)
        both = out["contact"] & ref["contact"]
        disagree += int((out["contact"] != ref["contact"]).sum())
        samples += len(wl)
        for k in errs:
            if both.any():
                errs[k] = max(errs[k], float(np.abs(out[k][both] - ref[k][both]).max()))
    for name_net, infos in report["nets"].items():
        for i, info in enumerate(infos):
            info["calib_max_abs_acc"] = trace.get(f"{name_net}.{i}", 0)
    report["fir"]["calib_max_abs_acc"] = trace.get("fir", 0)
    report.update({
        "model": str(root), freshness.DIGEST_KEY: freshness.model_digest(model),
        freshness.FILES_KEY: {rel: hashlib.sha256(b).hexdigest() for rel, b in outputs.items()},
        "calibration_files": paths, "files": files, "blob_bytes": len(data),
        "const_bytes": const_bytes(q),
        "state_bytes": _state_bytes(),
        "calibration_check": {"samples": samples, "contact_disagreements": disagree,
                              **{f"max_abs_err_{k}": v for k, v in errs.items()}},
        "seconds": round(time.perf_counter() - t0, 3),
    })
    with fileio.Outputs("--model") as out:
        for rel, content in outputs.items():
            out.write_bytes(root / rel, content)
        # Written last of the set: whatever happens, the record never names files not there.
        out.write_text(root / REPORT_FILE, json.dumps(report, indent=2) + "\n")
    return report


def const_bytes(q: QModel) -> int:
    """Bytes of constant arrays a generated C model puts in flash: weights, per-row bias
    (int64) and multiplier (int32), FIR taps (int16). docs/runtime.md quotes it."""
    weight_bytes = sum(ly.w.size * ly.w_bits // 8 + ly.n_out * 12 for net in q.nets for ly in net)
    return int(weight_bytes + q.taps.size * 2)


def _state_bytes() -> int | None:
    try:
        from fbgforce._runtime import lib
    except ImportError:
        return None
    return int(lib.fbg_state_size())
