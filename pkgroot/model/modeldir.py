"""The model directory on disk: ``model.json`` (readable parameters and metadata),
``weights.npz``, the calibration recordings export needs (``calibration.npz``) and the check
that an export beside them was made from them."""
from __future__ import annotations

import hashlib
import json
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce import fileio
from fbgforce.errors import InputError
from fbgforce.jsonutil import json_default
from fbgforce.model.artifact import (NET_NAMES, MLP, CalibrationRecordings, HierarchicalModel,
                                     InUse, Memory, Preprocess)
from fbgforce.model.freshness import (BLOB_FILE, DIGEST_KEY, FILES_KEY, FIX, REPORT_FILE,
                                      model_digest, read_report, remove_stale_export)

FORMAT_NAME = "fbgforce-model"
FORMAT_VERSION = 2
MODEL_JSON = "model.json"
WEIGHTS_NPZ = "weights.npz"
CALIBRATION_NPZ = "calibration.npz"


def training_data_key(model: HierarchicalModel) -> str:
    """What identifies a model's training data: a digest of ``metadata["data"]`` (paths, file
    digests, sample counts, tare baselines). A ``calibration.npz`` under another key belongs
    to another model."""
    text = json.dumps(model.metadata.get("data"), sort_keys=True, default=json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def load_calibration(directory: str | Path, model: HierarchicalModel) -> CalibrationRecordings | None:
    """The calibration recordings :func:`save` kept for ``model`` in ``directory``; None when
    there are none, or they belong to other training data (:func:`training_data_key`).

    Raises
    ------
    InputError
        If ``calibration.npz`` cannot be read (naming the file).
    """
    path = Path(directory) / CALIBRATION_NPZ
    if not path.is_file():
        return None
    try:
        with np.load(path) as npz:
            if str(npz["data_key"]) != training_data_key(model):
                return None
            return CalibrationRecordings.from_arrays(npz)
    except CALIBRATION_READ_ERRORS as exc:
        raise InputError(f"cannot read calibration recordings (truncated or corrupt?): {exc}",
                         path=str(path)) from exc


#: What reading a damaged ``calibration.npz`` raises.
CALIBRATION_READ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error)


def _stored_data_key(path: Path) -> str | None:
    """The training-data key a ``calibration.npz`` was written under (None: unreadable)."""
    try:
        with np.load(path) as npz:
            return str(npz["data_key"])
    except CALIBRATION_READ_ERRORS:
        return None


def save(model: HierarchicalModel, directory: str | Path, flag: str | None = None) -> Path:
    """Write ``model.json`` (readable parameters and metadata), ``weights.npz`` and, when the
    model carries them, its calibration recordings (``calibration.npz``,
    :class:`~fbgforce.model.artifact.CalibrationRecordings`).

    The files are written atomically as a set (:class:`fbgforce.fileio.Outputs`): a failed
    write leaves the directory as it was. A ``calibration.npz`` of other training data is
    removed. An export in the directory made from another model
    is removed (:func:`fbgforce.model.freshness.remove_stale_export`). ``flag`` names the
    command-line option of ``directory`` in errors.
    """
    out = Path(directory)
    pre = model.preprocess
    doc = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "preprocess": {
            "temp_coeff": pre.temp_coeff.tolist(),
            "filter_kind": pre.filter_kind,
            "filter_sigma": pre.filter_sigma,
            "taps": pre.taps.tolist(),
            "input_mean": pre.input_mean.tolist(),
            "input_std": pre.input_std.tolist(),
            "memory": pre.memory.to_json(),
            "ref_shift": pre.ref_shift,
            "creep": pre.creep,
            "creep_shift": pre.creep_shift,
            "group_delay_ms_at_1kHz": pre.group_delay_samples,
        },
        "nets": {name: {"sizes": net.sizes} for name, net in model.nets.items()},
        "force_offset": model.force_offset,
        "force_scale": model.force_scale,
        "xy_offset": model.xy_offset.tolist(),
        "xy_scale": model.xy_scale.tolist(),
        "baseline_nm": model.baseline_nm.tolist(),
        "in_use": model.in_use.to_json(),
        "input_range": None if model.input_range is None else model.input_range.tolist(),
        "metadata": model.metadata,
    }
    arrays = {}
    for name, net in model.nets.items():
        for layer, (w, b) in enumerate(zip(net.weights, net.biases)):
            arrays[f"{name}.W{layer}"] = w
            arrays[f"{name}.b{layer}"] = b
    key = training_data_key(model)
    with fileio.Outputs(flag) as files:
        files.write_with(out / WEIGHTS_NPZ, lambda fh: np.savez(fh, **arrays))
        if model.calibration is not None:
            cal = model.calibration.to_arrays(key)
            files.write_with(out / CALIBRATION_NPZ, lambda fh: np.savez_compressed(fh, **cal))
        files.write_text(out / MODEL_JSON, json.dumps(doc, indent=2, default=json_default) + "\n")
    stale = out / CALIBRATION_NPZ
    if model.calibration is None and stale.is_file() and _stored_data_key(stale) != key:
        try:
            stale.unlink()          # another model's training data: export must not use it
        except OSError as exc:
            raise fileio.write_error(exc, stale, flag) from None
    try:
        remove_stale_export(out, model)
    except OSError as exc:
        raise fileio.write_error(exc, exc.filename or out, flag) from None
    return out


def load(directory: str | Path) -> HierarchicalModel:
    """Read a model directory written by :func:`save`.

    Raises
    ------
    InputError
        If the directory or its files are missing, of another format or version, or
        inconsistent (naming the file and the key).
    """
    root = Path(directory)
    json_path = root / MODEL_JSON
    npz_path = root / WEIGHTS_NPZ
    if not root.is_dir():
        raise InputError("not a model directory (train one with 'fbgforce train')", path=str(root))
    for p in (json_path, npz_path):
        if not p.is_file():
            raise InputError("missing; is this a model directory written by 'fbgforce train'?",
                             path=str(p))
    try:
        doc = json.loads(json_path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg}", path=str(json_path), line=exc.lineno) from exc
    if doc.get("format") != FORMAT_NAME:
        raise InputError(f"format is {doc.get('format')!r}, expected {FORMAT_NAME!r}",
                         path=str(json_path), column="format")
    if doc.get("version") not in (1, FORMAT_VERSION):   # version 1: no memory
        raise InputError(f"format version {doc.get('version')!r} is not supported "
                         f"(this fbgforce reads version {FORMAT_VERSION})",
                         path=str(json_path), column="version")
    try:
        with np.load(npz_path) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"cannot read weights (truncated or corrupt?): {exc}",
                         path=str(npz_path)) from exc
    try:
        nets = {}
        for name in NET_NAMES:
            n_layers = len(doc["nets"][name]["sizes"]) - 1
            nets[name] = MLP([arrays[f"{name}.W{i}"] for i in range(n_layers)],
                             [arrays[f"{name}.b{i}"] for i in range(n_layers)])
        p = doc["preprocess"]
        pre = Preprocess(p["temp_coeff"], p["filter_kind"], p["filter_sigma"], p["taps"],
                         p["input_mean"], p["input_std"], Memory(**p.get("memory", {})),
                         p.get("ref_shift", 0),   # models trained before it: the raw reference
                         p.get("creep", 0.0), p.get("creep_shift", 0))   # ... and no creep inverse
        return HierarchicalModel(
            preprocess=pre, force_offset=doc["force_offset"], force_scale=doc["force_scale"],
            xy_offset=doc["xy_offset"], xy_scale=doc["xy_scale"], baseline_nm=doc["baseline_nm"],
            metadata=doc.get("metadata", {}), in_use=InUse(**doc.get("in_use", {})),
            input_range=doc.get("input_range"), **nets)
    except KeyError as exc:
        raise InputError(f"missing entry {exc.args[0]!r}", path=str(root)) from exc
    except ValueError as exc:
        raise InputError(str(exc), path=str(root)) from exc


def check_export(model_dir: str | Path, model: Any = None) -> None:
    """Refuse an exported blob that does not belong to the float model of ``model_dir``.

    Nothing to check (returns) when the directory has no ``model.json`` (a blob shipped on
    its own) or no ``model.fbgm`` (the reader says to export).

    Parameters
    ----------
    model_dir
        The model directory.
    model
        Its float model when the caller has loaded it already (else read here).

    Raises
    ------
    InputError
        One line naming ``model.fbgm`` and the fix: the export has no record of its model, was
        made from other weights, or its blob is not the one the export wrote.
    """
    root = Path(model_dir)
    blob = root / BLOB_FILE
    if not root.is_dir() or not (root / MODEL_JSON).is_file() or not blob.is_file():
        return
    fix = FIX.format(dir=root)
    report = read_report(root)
    if report is None or DIGEST_KEY not in report:
        raise InputError(f"no export record ({REPORT_FILE} missing or unreadable): which "
                         f"model it was exported from is unknown; {fix}", path=str(blob))
    if model is None:
        model = load(root)
    if report[DIGEST_KEY] != model_digest(model):
        raise InputError(f"stale: exported from another model than {MODEL_JSON} "
                         f"(retrained after export); {fix}", path=str(blob))
    recorded = (report.get(FILES_KEY) or {}).get(BLOB_FILE)
    if recorded is not None and recorded != fileio.file_sha256(blob):
        raise InputError(f"not the blob its export wrote ({REPORT_FILE} records another); "
                         f"{fix}", path=str(blob))
