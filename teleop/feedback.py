"""Where the master's force information comes from: the pluggable force estimators.

A feedback source sees the loop's true fingertip contact every sample and returns the force
it reports to the haptic master, for ``B`` runs at once:

- :class:`NoFeedback`: the master never stiffens (the operator has only the camera);
- :class:`TrueForce`: the true squeeze, optionally delayed and low-passed (an ideal sensor,
  and what a given delay costs with nothing else changed);
- :class:`SensorFeedback`: the real chain: the end-effector simulator turns the contact into
  five FBG wavelengths with the scene's effects, and the runtime (C fixed point, or its C
  float build) estimates the force from them at the loop rate, tared before contact.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import numpy as np

from fbgforce.errors import InputError
from fbgforce.teleop.scene import TeleopScene


#: Smallest and largest contact-free stretch computed in one block by :class:`SensorFeedback`.
MIN_BLOCK = 8
MAX_BLOCK = 4096


class Feedback(Protocol):
    """A force estimator feeding the master, vectorised over runs."""

    #: Short label for tables and plots.
    name: str
    #: Does the master's stiffness follow this source (False only for :class:`NoFeedback`)?
    renders_force: bool

    def start(self, scene: TeleopScene, seeds: list[int]) -> None:
        """Reset for one batch of runs (one seed each), before the first :meth:`step`."""

    def step(self, t_s: float, force_N: np.ndarray, contact: np.ndarray, x_mm: np.ndarray,
             y_mm: np.ndarray, free_samples: np.ndarray | None = None) -> np.ndarray:
        """Reported force per run, N, given this sample's true contact (arrays of shape (B,)).

        ``free_samples`` (B,), when given, is how many samples after this one the loop
        guarantees to be contact-free (the gripper cannot reach the egg sooner, or the egg is
        gone): a source may compute them ahead, as long as its output stays identical.
        """


class DelayLine:
    """A whole-sample delay of a (B,) signal (transport delay of a link or a filter)."""

    def __init__(self, delay_samples: int, n_runs: int) -> None:
        self.buf = np.zeros((max(int(delay_samples), 0) + 1, n_runs))
        self.pos = 0

    def push(self, x: np.ndarray) -> np.ndarray:
        """Store this sample and return the one ``delay_samples`` old."""
        self.buf[self.pos] = x
        self.pos = (self.pos + 1) % self.buf.shape[0]
        return self.buf[self.pos].copy()


class NoFeedback:
    """No force information: the master keeps its home spring only."""

    name = "none"
    renders_force = False

    def start(self, scene: TeleopScene, seeds: list[int]) -> None:
        self.n = len(seeds)

    def step(self, t_s: float, force_N: np.ndarray, contact: np.ndarray, x_mm: np.ndarray,
             y_mm: np.ndarray, free_samples: np.ndarray | None = None) -> np.ndarray:
        return np.zeros(self.n)


class TrueForce:
    """The true squeeze, after a transport delay and an optional first-order low-pass.

    Parameters
    ----------
    delay_ms
        Pure delay (rounded to whole samples).
    lowpass_ms
        Time constant of a first-order low-pass (0: none); its delay for slow signals equals
        the time constant.
    """

    renders_force = True

    def __init__(self, delay_ms: float = 0.0, lowpass_ms: float = 0.0) -> None:
        self.delay_ms = float(delay_ms)
        self.lowpass_ms = float(lowpass_ms)
        self.name = "true" if not (delay_ms or lowpass_ms) else (
            f"true+{delay_ms:g}ms" + (f" lp{lowpass_ms:g}ms" if lowpass_ms else ""))

    def start(self, scene: TeleopScene, seeds: list[int]) -> None:
        self.line = DelayLine(round(self.delay_ms * 1e-3 * scene.rate_hz), len(seeds))
        self.alpha = 1.0 if self.lowpass_ms <= 0 else 1.0 - np.exp(
            -scene.dt / (self.lowpass_ms * 1e-3))
        self.state = np.zeros(len(seeds))

    def step(self, t_s: float, force_N: np.ndarray, contact: np.ndarray, x_mm: np.ndarray,
             y_mm: np.ndarray, free_samples: np.ndarray | None = None) -> np.ndarray:
        self.state = self.state + self.alpha * (force_N - self.state)
        return self.line.push(self.state)


class SensorFeedback:
    """End-effector simulator + runtime estimator, one instance of each per run.

    Parameters
    ----------
    model_dir
        A model directory from ``fbgforce train`` (``fbgforce export`` adds ``model.fbgm``
        for the C engine).
    engine
        ``"fixed"``: the C fixed-point runtime (:class:`fbgforce.Runtime`), what ships;
        ``"cfloat"``: the runtime's float build on the float weights (for comparison).
    extra_delay_ms
        Added transport delay after the estimator (network link, slower interrogator).
    label
        Name in tables; defaults to ``"estimator"`` plus the options.
    prefetch
        Compute contact-free stretches the loop announces in one block (identical output;
        about 15 % less CPU on the egg scene); False steps every sample singly.
    allow_other_device
        Run even when the scene's fingertip is not the device the model was calibrated on
        (:func:`fbgforce.teleop.sensor.check_device`; to measure what that costs). By default
        such a mismatch is an :class:`InputError`.

    Attributes
    ----------
    device_check
        The result of the device check, after :meth:`start`.
    """

    renders_force = True

    def __init__(self, model_dir: str | Path, engine: str = "fixed", extra_delay_ms: float = 0.0,
                 label: str | None = None, prefetch: bool = True,
                 allow_other_device: bool = False) -> None:
        from fbgforce.model import modeldir as model_mod
        from fbgforce.teleop.sensor import ENGINE_NAMES

        if engine not in ENGINE_NAMES:
            raise InputError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINE_NAMES)}",
                             column="--engine")
        self.model_dir = Path(model_dir)
        self.engine = engine
        self.prefetch = prefetch
        self.allow_other_device = allow_other_device
        self.device_check: dict[str, Any] | None = None
        self.extra_delay_ms = float(extra_delay_ms)
        self.name = label or ("estimator" + ("" if engine == "fixed" else f"[{engine}]")
                              + (f"+{extra_delay_ms:g}ms" if extra_delay_ms else ""))
        self.model = model_mod.load(self.model_dir)
        if engine == "fixed" and not (self.model_dir / "model.fbgm").is_file():
            raise InputError("no model.fbgm: run 'fbgforce export --model DIR' first (or use the "
                             "cfloat engine)", path=str(self.model_dir))

    @property
    def filter_delay_ms(self) -> float:
        """The model's FIR group delay at the loop rate, ms (1 kHz: one sample = 1 ms)."""
        return self.model.preprocess.group_delay_samples

    def start(self, scene: TeleopScene, seeds: list[int]) -> None:
        from fbgforce.teleop.sensor import check_device, make_end_effector, make_engine

        self.device_check = check_device(self.model, scene.sim_scene)
        if self.device_check["status"] == "mismatch" and not self.allow_other_device:
            raise InputError(self.device_check["detail"] + " (use the calibration scene's device, "
                             "or --allow-other-device to measure what the mismatch costs)",
                             path=scene.path, column="effects")
        self.dt = scene.dt
        self.line = DelayLine(round(self.extra_delay_ms * 1e-3 * scene.rate_hz), len(seeds))
        self.sensors = [make_end_effector(scene, seed) for seed in seeds]
        self.engines = [make_engine(self.model, self.model_dir, self.engine) for _ in seeds]
        self.ahead = [np.empty(0) for _ in seeds]
        # Tare on a short unloaded stretch before the scene starts, as an operator would
        # before a grasp: it removes the device's offsets and the current temperature.
        n_pre = max(int(round(scene.fixed("loop", "preroll_s") * scene.rate_hz)), 1)
        t_pre = (np.arange(n_pre) - n_pre) * scene.dt
        zeros = np.zeros(n_pre)
        nan = np.full(n_pre, np.nan)
        for sensor, engine in zip(self.sensors, self.engines):
            wl = sensor.process(t_pre, zeros, nan, nan, np.zeros(n_pre, dtype=bool))
            engine.tare(wl)

    def step(self, t_s: float, force_N: np.ndarray, contact: np.ndarray, x_mm: np.ndarray,
             y_mm: np.ndarray, free_samples: np.ndarray | None = None) -> np.ndarray:
        out = np.empty(force_N.size)
        t = np.array([t_s])
        if not self.prefetch:
            free_samples = None
        for i, (sensor, engine) in enumerate(zip(self.sensors, self.engines)):
            ahead = self.ahead[i]
            if ahead.size:
                # Computed earlier for a stretch the loop guaranteed contact-free.
                out[i], self.ahead[i] = ahead[0], ahead[1:]
                continue
            c = bool(contact[i])
            n_free = 0 if free_samples is None or c or force_N[i] != 0.0 else int(
                min(free_samples[i], MAX_BLOCK - 1))
            if n_free >= MIN_BLOCK:
                # The simulator and the runtime give bit-identical results in blocks of any
                # size, and one call costs about as much as one sample: compute the unloaded
                # stretch at once (approach, or after the egg is gone).
                n = n_free + 1
                wl = sensor.process(t_s + np.arange(n) * self.dt, np.zeros(n), np.full(n, np.nan),
                                    np.full(n, np.nan), np.zeros(n, dtype=bool))
                forces = engine.run(wl)
                out[i], self.ahead[i] = forces[0], forces[1:]
                continue
            wl = sensor.process(t, force_N[i:i + 1], np.array([x_mm[i] if c else np.nan]),
                                np.array([y_mm[i] if c else np.nan]), np.array([c]))
            out[i] = engine.run(wl)[0]
        return self.line.push(np.maximum(out, 0.0))


def describe(fb: Any) -> dict[str, Any]:
    """JSON-friendly description of a feedback source."""
    d: dict[str, Any] = {"name": fb.name, "renders_force": fb.renders_force}
    if isinstance(fb, TrueForce):
        d.update(delay_ms=fb.delay_ms, lowpass_ms=fb.lowpass_ms)
    if isinstance(fb, SensorFeedback):
        d.update(model=str(fb.model_dir), engine=fb.engine, extra_delay_ms=fb.extra_delay_ms,
                 filter=fb.model.preprocess.filter_kind,
                 filter_sigma=fb.model.preprocess.filter_sigma,
                 filter_group_delay_ms=fb.filter_delay_ms, device_check=fb.device_check)
    return d
