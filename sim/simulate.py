"""Scene → ground-truth schedule → :class:`EndEffector` → :class:`fbgforce.recordings.dataset.Dataset`."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fbgforce.recordings.dataset import Dataset
from fbgforce.sim.endeffector import EndEffector
from fbgforce.sim.scene import Scene, load_scene
from fbgforce.sim.schedule import build_schedule

#: Samples per EndEffector call; also the progress-bar granularity.
CHUNK = 25_000


def simulate(scene: str | Path | Scene, seed: int | None = None, device: int | None = None,
             *, progress: bool | None = False) -> Dataset:
    """Simulate a scene.

    Parameters
    ----------
    scene
        Built-in scene name (``"calibration"``, ``"ideal"``, ...), path to a TOML file, or a
        :class:`Scene`.
    seed, device
        Override the scene's seed / device number.
    progress
        Show progress on stderr (:func:`fbgforce.progress.bar`; False: none).

    Returns
    -------
    Dataset
        ``source`` is ``"sim:NAME seed=S device=D"``; extras: ``temperature_K`` (with the
        ``temperature`` effect), ``dropout`` (with ``dropout``), ``impulse_Ns`` (impacts).
    """
    sc = load_scene(scene)
    if seed is not None or device is not None:
        sc = sc.replace(seed=seed, device=device)
    sched = build_schedule(sc)
    ee = EndEffector(sc)
    n = len(sched)
    wl = np.empty((n, 5))
    extras: dict[str, list[np.ndarray]] = {}
    bar = None
    if progress is not False:
        from fbgforce import progress as fprogress

        bar = fprogress.bar(total=n, unit="sample", unit_scale=True, desc=f"simulate {sc.name}",
                            enabled=progress)
    for start in range(0, n, CHUNK):
        sl = slice(start, min(start + CHUNK, n))
        out, ex = ee.process_with_extras(sched.t_s[sl], sched.force_N[sl], sched.x_mm[sl],
                                         sched.y_mm[sl], None, sched.impulse_Ns[sl],
                                         sched.impulse_phase[sl])
        wl[sl] = out
        for k, v in ex.items():
            extras.setdefault(k, []).append(v)
        if bar is not None:
            bar.update(sl.stop - sl.start)
    if bar is not None:
        bar.close()
    extra = {k: np.concatenate(v) for k, v in extras.items()}
    extra.update(sched.extra)
    contact = sched.contact
    return Dataset(
        t_s=sched.t_s, wl_nm=wl, contact=contact,
        x_mm=np.where(contact, sched.x_mm, np.nan), y_mm=np.where(contact, sched.y_mm, np.nan),
        force_N=sched.truth_force_N, press_id=sched.press_id, extra=extra,
        source=f"sim:{sc.name} seed={sc.seed} device={sc.device}",
    )
