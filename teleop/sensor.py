"""The fingertip in the loop: the simulator's streaming end-effector and a runtime engine.

Each run gets its own :class:`fbgforce.sim.EndEffector` (the scene's device and effects, the
run's seed for the random streams: interrogator noise, temperature walk) and its own runtime
state, stepped one sample per loop tick as the firmware would.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.errors import InputError
from fbgforce.teleop.scene import TeleopScene

#: Engine names accepted by :func:`make_engine`.
ENGINE_NAMES = ("fixed", "cfloat")
#: Effect tables that make the fingertip what it is (device, pad), as opposed to its
#: surroundings (temperature history, interrogator noise): a model is only valid on a fingertip
#: whose tables match those of the scene it was calibrated on.
DEVICE_EFFECTS = ("tolerance", "edge_contact", "friction_hysteresis", "viscoelastic")
#: Device properties inside the temperature effect (the gratings' thermal response).
DEVICE_TEMPERATURE_KEYS = ("sensitivity_pm_per_K", "mismatch_sd")
#: How ``fbgforce simulate`` names a recording's origin (``Dataset.source``).
_SIM_SOURCE = re.compile(r"^sim:(?P<scene>\S+) seed=\d+ device=(?P<device>\d+)$")


def _recorded_source(entry: dict[str, Any]) -> str:
    """The ``source`` of one training recording named in a model's metadata: given directly
    (trained from a Dataset object) or read from the recording file (the ``# source:`` header
    line of a CSV, the ``source`` field of an npz); '' when unknown."""
    if entry.get("source"):
        return str(entry["source"])
    path = entry.get("path")
    if not path or not Path(path).is_file():
        return ""
    p = Path(path)
    try:
        if p.suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                return str(z["source"]) if "source" in z.files else ""
        with p.open(encoding="utf-8", errors="replace") as fh:
            for line in fh:
                if not line.startswith("#"):
                    break
                if line.startswith("# source:"):
                    return line[len("# source:"):].strip()
    except (OSError, ValueError, KeyError):
        return ""
    return ""


def _device_tables(sim_scene: Any) -> dict[str, Any]:
    eff = sim_scene.effects
    tables: dict[str, Any] = {name: eff.get(name) for name in DEVICE_EFFECTS}
    temp = eff.get("temperature")
    tables["temperature"] = (None if temp is None
                             else {k: temp[k] for k in DEVICE_TEMPERATURE_KEYS})
    return tables


def check_device(model: Any, sim_scene: Any) -> dict[str, Any]:
    """Is the loop's fingertip the device ``model`` was calibrated on?

    The model's metadata names its training recordings; a simulated one says which scene and
    device made it (``sim:NAME seed=S device=D``). That scene's device tables
    (:data:`DEVICE_EFFECTS`, the thermal keys of ``temperature``) and device number are
    compared with ``sim_scene``'s.

    Returns
    -------
    dict
        ``status``: ``"verified"`` (every recording is from this device), ``"mismatch"`` (a
        recording is from another device; ``detail`` names the first difference) or
        ``"unverified"`` (a recording's origin is unknown: real data, a moved file, a scene
        that is not built in); ``sources``: the recordings' origins.
    """
    from fbgforce.sim import load_scene

    entries = (model.metadata or {}).get("data") or []
    sources = [_recorded_source(e) for e in entries]
    if not sources:
        return {"status": "unverified", "detail": "the model names no training data",
                "sources": []}
    mine = _device_tables(sim_scene)
    unverified = []
    for src in sources:
        m = _SIM_SOURCE.match(src)
        if not m:
            unverified.append(src or "an unknown recording")
            continue
        try:
            trained = load_scene(m["scene"])
        except InputError:
            unverified.append(src)
            continue
        if int(m["device"]) != int(sim_scene.device):
            return {"status": "mismatch", "sources": sources,
                    "detail": f"the model was calibrated on device {m['device']} ({src}), the "
                              f"fingertip is device {sim_scene.device}"}
        theirs = _device_tables(trained)
        for name in mine:
            if mine[name] != theirs[name]:
                mk, tk = mine[name] or {}, theirs[name] or {}
                keys = sorted(k for k in set(mk) | set(tk) if mk.get(k) != tk.get(k))
                what = (f"effects.{name} present in only one of them" if not (mk and tk)
                        else f"effects.{name}.{keys[0]} = {mk[keys[0]]!r}, calibrated "
                             f"{tk[keys[0]]!r}")
                return {"status": "mismatch", "sources": sources,
                        "detail": f"the fingertip is not the device the model was calibrated "
                                  f"on ({src}): {what}"}
    if unverified:
        return {"status": "unverified", "sources": sources,
                "detail": "cannot tell which device made " + ", ".join(unverified)}
    return {"status": "verified", "sources": sources,
            "detail": f"the fingertip is the device of {', '.join(sorted(set(sources)))}"}


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
