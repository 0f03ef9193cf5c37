"""Scoring a model directory on recordings with any engine (``fbgforce evaluate``)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce.evaluation import engines
from fbgforce.evaluation import metrics as fmetrics
from fbgforce.evaluation import onset_bound
from fbgforce.model import artifact, modeldir
from fbgforce.recordings import tare as fbgtare

SPLITS = ("all", "train", "val", "test")


def run_recording(engine: str, model_dir: str | Path | None, model: artifact.HierarchicalModel,
                  ds: Any, source: str | None = None) -> dict[str, np.ndarray]:
    """Tare one continuous recording on its own contact-free samples, then run ``engine``."""
    base, _ = fbgtare.tare(ds.wl_nm, ds.contact, ds.t_s, path=source)
    return engines.run_engine(engine, model_dir, model, ds.wl_nm, base)


def evaluate(model_dir: str | Path, data: Sequence[str | Path | Any], *, engine: str = "float",
             split: str = "all", seed: int | None = None, model: artifact.HierarchicalModel | None = None,
             extras: bool = True, predictions: Sequence[dict[str, np.ndarray]] | None = None,
             resample: bool = False) -> dict[str, Any]:
    """Metrics of ``engine`` over the recordings in ``data``.

    Each recording is run whole (the filter needs its continuous history), then the samples
    of the requested split (by press, with the model's training seed unless ``seed`` is given)
    are scored with :func:`fbgforce.evaluation.metrics.compute`; the presses of the split also give the
    onset and release delays (``contact_timing``), what the recordings' noise allows any
    decision on those presses (``noise_allows``, :func:`fbgforce.evaluation.onset_bound.bound`)
    and each recording's rests and holds (``at_rest``, ``holds``:
    :func:`fbgforce.evaluation.metrics.use_masks`). ``predictions``: the engine's
    output on each whole recording (:func:`run_recording`) when the caller has it already.

    A recording sampled at another rate than the model's is refused
    (:func:`fbgforce.samples.check_rate`), or with ``resample`` brought to the model's rate
    first (:func:`fbgforce.recordings.dataset.resample`). ``warnings`` in the result lists what makes the
    numbers weak (a split of fewer than ``MIN_SPLIT_PRESSES`` presses).
    """
    from fbgforce.recordings import dataset as fds
    from fbgforce import samples
    from fbgforce.trainer.data import load_datasets, split_rows
    from fbgforce.trainer.scoring import model_pad_mm

    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}")
    model = modeldir.load(model_dir) if model is None else model
    seed = int(model.metadata.get("seed", 0)) if seed is None else seed
    ds_list, described = load_datasets(data)
    trained_hz = samples.model_rate_hz(model)
    for i, (ds, d) in enumerate(zip(ds_list, described)):
        where = d.get("path") or d.get("source")
        if resample and trained_hz is not None:
            if abs(fbgtare.sample_rate_hz(ds.t_s) - trained_hz) > samples.RATE_TOLERANCE * trained_hz:
                ds_list[i] = fds.resample(ds, trained_hz)
        else:
            samples.check_rate(model, fbgtare.sample_rate_hz(ds.t_s), where)
    preds, truths, onsets, releases, uses, keeps = [], [], [], [], [], []
    n_presses = 0
    if predictions is None:
        predictions = [run_recording(engine, model_dir, model, ds, d.get("path"))
                       for ds, d in zip(ds_list, described)]
    for ds, pred in zip(ds_list, predictions):
        rows = np.arange(len(ds))
        keep = None
        if split != "all":
            keep = split_rows(ds, seed) == SPLITS.index(split) - 1
            rows = np.flatnonzero(keep)
        # Delays need the whole recording: a release may run into the next press's rest.
        onset, release = fmetrics.press_delays(pred["contact"], ds.contact, ds.t_s, ds.press_id,
                                               keep)
        onsets.append(onset)
        releases.append(release)
        keeps.append(keep)
        use = fmetrics.use_masks(pred["contact"], ds.contact, ds.force_N, ds.t_s)
        uses.append({k: v[rows] for k, v in use.items()})
        n_presses += int(np.unique(np.asarray(ds.press_id)[rows]).size)
        preds.append({k: np.asarray(pred[k])[rows] for k in ("contact", "force_N", "x_mm", "y_mm")})
        truths.append((np.asarray(ds.contact)[rows], np.asarray(ds.force_N)[rows],
                       np.asarray(ds.x_mm)[rows], np.asarray(ds.y_mm)[rows]))
    pred = {k: np.concatenate([p[k] for p in preds]) for k in preds[0]}
    truth = [np.concatenate([t[i] for t in truths]) for i in range(4)]
    out = fmetrics.compute(pred, *truth, extras=extras, pad_mm=model_pad_mm(model),
                           delays=(np.concatenate(onsets), np.concatenate(releases)),
                           use={k: np.concatenate([u[k] for u in uses]) for k in uses[0]})
    few = fmetrics.few_presses_warning(split, n_presses) if split in ("val", "test") else None
    if extras:
        out["noise_allows"] = onset_bound.bound(ds_list, keeps=keeps)
    out.update({"engine": engine, "model": str(model_dir), "split": split,
                "data": [d.get("path") or d.get("source") for d in described],
                "presses": n_presses, "warnings": [few] if few else []})
    return out
