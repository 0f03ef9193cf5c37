"""The raw files a lab would have for a simulated session: the interrogator's log and the
x-y-z stage's log (load cell and position) on a clock of its own (docs/simulator.md "Lab
logs"). A logging option, not a physics effect: the dataset is the same with or without it,
and its random stream (``crc32("stage_log")``) touches no other.

The stage clock reads ``t_stage = t + offset_s + drift_ppm * 1e-6 * t`` at interrogator time
``t`` (the dataset's ``t_s``, from 0), its samples are taken every ``1 / rate_hz`` on its own
clock with Gaussian jitter (clipped to 0.4 periods) and time-stamped where they were taken,
and it logs from half a second before the interrogator's first sample to half a second after
its last.
"""
from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.recordings.dataset import Dataset
from fbgforce.errors import InputError
from fbgforce.recordings.labimport import FBG_KEYS, STAGE_KEYS

#: Column names of the written logs (deliberately not the dataset's).
FBG_LOG_COLUMNS = ("timestamp", "peak1", "peak2", "peak3", "peak4", "peak_ref")
STAGE_LOG_COLUMNS = ("time", "Fz", "X", "Y")
#: The stage logs this long before and after the interrogator, s.
STAGE_MARGIN_S = 0.5


def stage_rng(seed: int) -> np.random.Generator:
    """The stage log's stream: ``SeedSequence(seed, spawn_key=(crc32("stage_log"),))``."""
    key = zlib.crc32(b"stage_log")
    return np.random.default_rng(np.random.SeedSequence(entropy=int(seed), spawn_key=(key,)))


def press_locations(ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Where the stage stands at each sample: the location of the sample's press (from its
    contact samples) through the press's rest as well; a press without contact keeps the
    previous location."""
    ids, first = np.unique(ds.press_id, return_inverse=True)
    x = np.full(ids.size, np.nan)
    y = np.full(ids.size, np.nan)
    c = ds.contact
    x[first[c]] = ds.x_mm[c]            # one location per press: any of its samples
    y[first[c]] = ds.y_mm[c]
    for arr in (x, y):
        ok = np.isfinite(arr)
        if not ok.any():
            arr[:] = 0.0
            continue
        idx = np.where(ok, np.arange(arr.size), 0)
        np.maximum.accumulate(idx, out=idx)
        arr[:] = np.where(ok[idx], arr[idx], arr[ok][0])
    return x[first], y[first]


def write_lab_logs(ds: Dataset, directory: str | Path, *, rate_hz: float = 500.0,
                   offset_s: float = 0.1, drift_ppm: float = 80.0, jitter_s: float = 1e-4,
                   seed: int = 0) -> dict[str, Any]:
    """Write ``interrogator.csv``, ``stage.csv`` and ``import.toml`` (the ``--map`` that
    imports them) into ``directory``; returns what was written and the true clock."""
    if not (rate_hz > 0 and np.isfinite(rate_hz)):
        raise InputError(f"stage rate must be > 0 Hz, not {rate_hz}", column="--stage-rate-hz")
    if not 0 <= jitter_s < 0.25 / rate_hz:
        raise InputError(f"jitter must be in [0, a quarter of the stage period), not {jitter_s} s",
                         column="--stage-jitter-ms")
    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create: {exc.strerror}", path=str(out)) from None
    drift = drift_ppm * 1e-6
    # Interrogator log: the dataset's wavelengths on the interrogator's clock.
    fbg_path = out / "interrogator.csv"
    cols = np.column_stack([ds.t_s, ds.wl_nm])
    np.savetxt(fbg_path, cols, fmt=["%.9f"] + ["%.6f"] * 5, delimiter=",",
               header=",".join(FBG_LOG_COLUMNS), comments="")
    # Stage log: sampled on its own clock, jittered, the force interpolated from the load
    # cell's (the dataset's) samples and the position from the press table.
    t0 = ds.t_s[0] - STAGE_MARGIN_S
    t1 = ds.t_s[-1] + STAGE_MARGIN_S
    s0, s1 = (t0 + offset_s + drift * t0), (t1 + offset_s + drift * t1)
    k = np.arange(int(np.floor((s1 - s0) * rate_hz)) + 1)
    # Jitter clipped to 0.4 periods keeps the samples in order, as a logger's are.
    jitter = np.clip(stage_rng(seed).normal(0.0, 1.0, k.size) * jitter_s, -0.4 / rate_hz,
                     0.4 / rate_hz)
    t_stage = s0 + k / rate_hz + jitter
    t_true = (t_stage - offset_s) / (1.0 + drift)
    force = np.interp(t_true, ds.t_s, ds.force_N, left=0.0, right=0.0)
    px, py = press_locations(ds)
    j = np.clip(np.searchsorted(ds.t_s, t_true), 0, len(ds) - 1)
    stage_path = out / "stage.csv"
    np.savetxt(stage_path, np.column_stack([t_stage, force, px[j], py[j]]),
               fmt=["%.9f", "%.6f", "%.4f", "%.4f"], delimiter=",",
               header=",".join(STAGE_LOG_COLUMNS), comments="")
    map_path = out / "import.toml"
    fbg_map = ",".join(f"{k}={c}" for k, c in zip(FBG_KEYS, FBG_LOG_COLUMNS))
    stage_map = ",".join(f"{k}={c}" for k, c in zip(STAGE_KEYS, STAGE_LOG_COLUMNS))
    map_path.write_text(
        "# fbgforce import --map import.toml --out DATASET.csv\n"
        f'fbg = "{fbg_path.name}"\nfbg-columns = "{fbg_map}"\nfbg-unit = "nm"\n'
        f'stage = "{stage_path.name}"\nstage-columns = "{stage_map}"\n'
        'force-unit = "N"\nposition-unit = "mm"\n', encoding="utf-8")
    return {"interrogator": str(fbg_path), "stage": str(stage_path), "map": str(map_path),
            "stage_rate_hz": rate_hz, "offset_s": offset_s, "drift_ppm": drift_ppm,
            "jitter_ms": jitter_s * 1e3, "stage_samples": int(k.size)}
