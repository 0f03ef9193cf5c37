"""What a model directory holds: is its export (``model.fbgm``, ``model.onnx``, ``c/``) made
from the float model beside it?

``fbgforce export`` records in ``export_report.json`` the digest of the float model it
quantised (:func:`model_digest`) and the SHA-256 of every file it wrote. Every reader of the
exported blob (the C runtime binding, the Python blob reader, hence ``stream``, ``verify``,
``evaluate --engine fixed|intref|cfloat``, ``bench-speed``, ``target-report``) calls
:func:`fbgforce.model.modeldir.check_export` and refuses a blob that another model, or another
export, left behind. :func:`remove_stale_export` is how saving a model into an exported
directory drops the export that no longer matches it.

This module needs no model type, only the model's parts, so the model directory's reader and
writer (:mod:`fbgforce.model.modeldir`), the runtime binding and the exporter can all use it.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce import contract

#: The export's files, relative to the model directory.
BLOB_FILE = contract.BLOB_FILE
ONNX_FILE = "model.onnx"
REPORT_FILE = "export_report.json"
C_DIR = "c"
#: Report keys: the float model's digest and the SHA-256 of each file written (by name
#: relative to the model directory).
DIGEST_KEY = "model_digest"
FILES_KEY = "file_sha256"

FIX = "run 'fbgforce export --model {dir}' again"


def weights_digest(model: Any) -> str:
    """SHA-256 over everything the float nets depend on (net weights and output scaling).

    Stored in ``model.onnx``'s metadata so that a stale graph is recognised instead of used.
    """
    h = hashlib.sha256()
    for name, net in model.nets.items():
        h.update(name.encode())
        for w, b in zip(net.weights, net.biases):
            h.update(np.ascontiguousarray(w, dtype="<f8").tobytes())
            h.update(np.ascontiguousarray(b, dtype="<f8").tobytes())
    scaling = np.concatenate([[model.force_offset, model.force_scale], model.xy_offset,
                              model.xy_scale])
    h.update(np.ascontiguousarray(scaling, dtype="<f8").tobytes())
    return h.hexdigest()


#: The preprocessing fields model_digest hashes on their own, and filter_sigma, which only
#: describes the taps (every other field is hashed by name).
_DIGESTED = ("temp_coeff", "filter_kind", "filter_sigma", "taps", "input_mean", "input_std",
             "memory")


#: The ``in_use`` fields model_digest hashes as one JSON object (every other field by name).
_IN_USE_DIGESTED = ("contact_on_margin", "contact_off_margin", "contact_rise_samples",
                    "track_shift", "track_settle", "track_step_max_pm", "track_limit_pm")


def model_digest(model: Any) -> str:
    """SHA-256 of everything the fixed-point model is quantised from: the nets and output
    scaling (:func:`weights_digest`), the preprocessing (every field of
    :class:`fbgforce.model.artifact.Preprocess`), the nominal baseline, and what the runtimes do in
    use (the decision over time, the tracker: ``in_use``; the input range)."""
    pre = model.preprocess
    h = hashlib.sha256(weights_digest(model).encode())
    h.update(pre.filter_kind.encode())
    for arr in (pre.temp_coeff, pre.taps, pre.input_mean, pre.input_std, model.baseline_nm):
        h.update(np.ascontiguousarray(arr, dtype="<f8").tobytes())
    h.update(json.dumps(pre.memory.to_json(), sort_keys=True).encode())
    # Every other preprocessing parameter (ref_shift, ...) by name, where it differs from its
    # default: a model that leaves it at the default keeps the digest its export recorded.
    for f in dataclasses.fields(pre):
        if f.name not in _DIGESTED and getattr(pre, f.name) != f.default:
            h.update(f"{f.name}={getattr(pre, f.name)!r}".encode())
    # What the runtimes do in use: the decision's and the tracker's first fields together,
    # every later one (the creep term, ...) by name where it differs from its default, as above.
    in_use = model.in_use.to_json()
    h.update(json.dumps({k: v for k, v in in_use.items() if k in _IN_USE_DIGESTED},
                        sort_keys=True).encode())
    for f in dataclasses.fields(model.in_use):
        if f.name not in _IN_USE_DIGESTED and in_use[f.name] != f.default:
            h.update(f"in_use.{f.name}={in_use[f.name]!r}".encode())
    if model.input_range is not None:
        h.update(np.ascontiguousarray(model.input_range, dtype="<f8").tobytes())
    return h.hexdigest()


def read_report(root: Path) -> dict[str, Any] | None:
    """The export report of the model directory ``root`` (None: missing or unreadable)."""
    try:
        doc = json.loads((root / REPORT_FILE).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


def remove_stale_export(model_dir: str | Path, model: Any) -> list[str]:
    """Delete the export of ``model_dir`` (blob, ONNX graph, generated C, report) unless it was
    made from ``model``; returns the names removed. :func:`fbgforce.model.modeldir.save` calls it, so
    retraining into an exported directory never leaves the old export to be run."""
    root = Path(model_dir)
    report = read_report(root)
    if report is not None and report.get(DIGEST_KEY) == model_digest(model):
        return []
    removed = []
    for name in (BLOB_FILE, ONNX_FILE, REPORT_FILE):
        if (root / name).is_file():
            (root / name).unlink()
            removed.append(name)
    c_dir = root / C_DIR
    if c_dir.is_dir():
        # Only what the exporter generates: other files a user keeps there stay.
        for pattern in ("*_model.[ch]", "*_model_f32.[ch]"):
            for path in sorted(c_dir.glob(pattern)):
                path.unlink()
                removed.append(f"{C_DIR}/{path.name}")
        if not any(c_dir.iterdir()):
            c_dir.rmdir()
    return removed
