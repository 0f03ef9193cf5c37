"""The fingertip in the loop: the simulator's streaming end-effector and a runtime engine.

Each run gets its own :class:`fbgforce.sim.EndEffector` (the scene's device and effects, the
run's seed for the random streams: interrogator noise, temperature walk) and its own runtime
state, stepped one sample per loop tick as the firmware would.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.errors import InputError
from fbgforce.teleop.scene import TeleopScene

#: Engine names accepted by :func:`make_engine`.
ENGINE_NAMES = ("fixed", "cfloat")


def make_end_effector(scene: TeleopScene, seed: int) -> Any:
    """The scene's fingertip device with the run's random streams."""
    from fbgforce.sim import EndEffector

    return EndEffector(scene.sim_scene, seed=seed, device=scene.sim_scene.device)


class _Engine:
    """One runtime instance: ``tare(wl (n, 5))``, then ``run(wl (n, 5)) -> force_N (n,)``."""

    def __init__(self, runtime: Any, raw_mN: bool) -> None:
        self.rt = runtime
        self.raw_mN = raw_mN

    def tare(self, wl_nm: np.ndarray) -> None:
        self.rt.tare(wl_nm)

    def run(self, wl_nm: np.ndarray) -> np.ndarray:
        """Reported force (n,), N, for the next ``n`` samples (n, 5), in order."""
        if self.raw_mN:
            # The raw C record skips building the SI-unit record: cheaper per 1 kHz tick.
            return self.rt.run_raw(wl_nm)["force_mN"] * 1e-3
        return np.asarray(self.rt.run(wl_nm)["force_N"], dtype=np.float64)


def make_engine(model: Any, model_dir: str | Path, engine: str) -> _Engine:
    """A runtime for one run: ``"fixed"`` (C fixed point, ``model.fbgm``) or ``"cfloat"``.

    Raises
    ------
    InputError
        If the C extension is not built, or the model has no exported blob for ``fixed``.
    """
    if engine not in ENGINE_NAMES:
        raise InputError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINE_NAMES)}",
                         column="--engine")
    try:
        from fbgforce.pybind import FloatRuntime, Runtime, RuntimeCError
    except ImportError as exc:
        raise InputError(f"the C runtime is not available ({exc})", column="--engine") from exc
    try:
        if engine == "fixed":
            return _Engine(Runtime(model_dir), raw_mN=True)
        return _Engine(FloatRuntime(model), raw_mN=False)
    except RuntimeCError as exc:
        # A blob from another export format version, or a corrupt one: the user's file.
        raise InputError(f"the runtime refuses this model ({exc}); re-run 'fbgforce export "
                         f"--model {model_dir}'", path=str(model_dir)) from exc
