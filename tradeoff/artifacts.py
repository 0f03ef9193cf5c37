"""Data, trained models and exported blobs of a run, kept under ``--out`` and reused by a later
run with the same settings (a key file next to each model says which settings made it)."""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fbgforce.model import artifact, modeldir
from fbgforce.errors import InputError

def prepare_data(data: Sequence[str | Path] | None, scene: str | None, out: Path, seed: int,
                 log: Callable[[str], None]) -> list[Path]:
    """Paths of the recordings to use; a scene is simulated once into ``out/data``."""
    if data:
        paths = [Path(p) for p in data]
        for p in paths:
            if not p.is_file():
                raise InputError("no such data file", path=str(p), column="--data")
        return paths
    if not scene:
        raise InputError("give --data FILE or --scene NAME")
    from fbgforce.recordings import dataset as fds
    from fbgforce.sim import simulate
    from fbgforce.sim.scene import load_scene

    target = out / "data" / f"{Path(scene).stem}-seed{seed}.npz"
    if not target.is_file():
        load_scene(scene)  # a bad scene fails here, before any progress line
        log(f"simulating scene {scene!r} -> {target}")
        target.parent.mkdir(parents=True, exist_ok=True)
        fds.save(simulate(scene, seed=seed), target)
    return [target]


def data_digest(paths: Sequence[Path]) -> str:
    from fbgforce.fileio import file_sha256

    return hashlib.sha256("".join(file_sha256(p) for p in paths).encode()).hexdigest()[:16]


def reusable_model(model_dir: Path, key: dict[str, Any]) -> artifact.HierarchicalModel | None:
    marker = model_dir / "tradeoff-key.json"
    try:
        if json.loads(marker.read_text()) == key:
            return modeldir.load(model_dir)
    except (OSError, ValueError, InputError):
        return None
    return None


def save_with_key(model: artifact.HierarchicalModel, model_dir: Path, key: dict[str, Any]) -> None:
    if model_dir.exists():
        shutil.rmtree(model_dir)
    modeldir.save(model, model_dir)
    (model_dir / "tradeoff-key.json").write_text(json.dumps(key, indent=1) + "\n")


#: Quantizer calibration uses at most this many samples (whole presses from the start of the
#: first recording): the export's cost grows with it, its scales hardly do.
CALIB_MAX_SAMPLES = 60000


def calibration_subset(ds_list: Sequence[Any], sources: Sequence[str], out: Path) -> list[str]:
    """Files to calibrate the fixed-point export on: the recordings, or a prefix of the first.

    The exporter derives its scales from the ranges the float pipeline reaches on this data;
    the first presses of a calibration protocol cover those ranges already, and exporting with
    all 234k samples costs about five times longer per model for the same scales.
    """
    ds = ds_list[0]
    if sum(len(d) for d in ds_list) <= CALIB_MAX_SAMPLES:
        return list(sources)
    from fbgforce.recordings import dataset as fds

    pid = np.asarray(ds.press_id)
    cut = CALIB_MAX_SAMPLES
    # End on a press boundary so no press is cut in half.
    while cut < len(ds) and pid[cut] == pid[cut - 1]:
        cut += 1
    path = out / "data" / f"calib-{Path(sources[0]).stem}-{cut}.npz"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        fds.save(ds.subset(np.arange(cut)), path)
    return [str(path)]


def export_fixed(model_dir: Path, bits: int, calib: Sequence[str]) -> str | None:
    """Write ``model.fbgm`` (and C source) for ``bits``-bit weights; None or the reason it failed.

    Uses :func:`fbgforce.export.exporter.export_model`, calibrated on the recordings of the
    run (the model's training data).
    """
    try:
        from fbgforce.export.exporter import REPORT_FILE, export_model
    except ImportError as exc:
        return f"exporter not available ({exc})"
    report = model_dir / REPORT_FILE
    try:
        # A rerun over reused models keeps a blob exported from these weights at these bits.
        if (model_dir / "model.fbgm").is_file() and json.loads(report.read_text()).get("bits") == bits:
            from fbgforce.pybind import Runtime

            # Refuses a stale export, and a blob this runtime no longer reads (format version).
            Runtime(model_dir)
            return None
    except Exception:  # stale, unreadable or from another blob version: export again
        pass
    try:
        export_model(model_dir, bits=bits, calib=calib)
    except Exception as exc:  # report it in the row, don't abort the whole grid
        return f"export --bits {bits} failed: {type(exc).__name__}: {exc}"
    return None
