"""The 1 kHz closed loop: master -> gripper -> egg -> fingertip -> estimator -> master.

One sample of the loop, in the order the hardware runs it:

1. the master renders its spring with the stiffness set by the last reported force;
2. the operator perceives (with delays), updates the intention and moves the stylus;
3. the gripper's servo follows the stylus; the fingers squeeze the egg (true force);
4. the egg breaks, sticks or slides under the grip while the arm moves;
5. the fingertip (simulator + runtime) reports the force, used by the master next sample.

:func:`simulate` runs ``B`` seeded runs at once and returns traces and per-run outcomes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbgforce.teleop.feedback import Feedback
from fbgforce.teleop.models import (Egg, Gripper, HapticMaster, Operator,
                                    arm_load_acceleration)
from fbgforce.teleop.scene import TeleopScene

#: Longest lag searched when measuring the estimator's delay, ms.
MAX_DELAY_SEARCH_MS = 200


@dataclass
class TeleopResult:
    """Traces and outcomes of ``B`` runs.

    Attributes
    ----------
    t_s
        (n,) time of each sample.
    traces
        (n, B) arrays: ``force_true_N``, ``force_reported_N``, ``opening_mm`` (gripper motor),
        ``command_mm`` (opening the master asks for), ``master_mm``, ``felt_N``,
        ``required_N`` (grip needed to hold the egg at that instant, once carried).
    outcomes
        Per-run arrays: ``egg_broken``, ``egg_dropped``, ``success``, ``max_force_N``,
        ``time_in_safe_band_fraction``, ``estimator_delay_ms``, ``force_rmse_N``,
        ``force_bias_N``, ``seed``.
    """

    t_s: np.ndarray
    traces: dict[str, np.ndarray]
    outcomes: dict[str, np.ndarray]
    feedback: str
    lift_s: float
    safe_band_N: tuple[float, float]
    extra: dict[str, Any] = field(default_factory=dict)

    def run_summary(self, k: int = 0) -> dict[str, Any]:
        """The documented JSON keys for run ``k``."""
        o = self.outcomes
        delay = float(o["estimator_delay_ms"][k])
        return {
            "egg_broken": bool(o["egg_broken"][k]),
            "egg_dropped": bool(o["egg_dropped"][k]),
            "max_force_N": round(float(o["max_force_N"][k]), 4),
            "time_in_safe_band_fraction": round(float(o["time_in_safe_band_fraction"][k]), 4),
            "estimator_delay_ms": None if np.isnan(delay) else round(delay, 2),
            "force_rmse_N": _rounded(o["force_rmse_N"][k]),
            "force_bias_N": _rounded(o["force_bias_N"][k]),
        }

    def rates(self) -> dict[str, float]:
        """Success, broken and dropped fractions over all runs."""
        o = self.outcomes
        return {"success_rate": float(np.mean(o["success"])),
                "broken_rate": float(np.mean(o["egg_broken"])),
                "dropped_rate": float(np.mean(o["egg_dropped"]))}


def _rounded(v: float) -> float | None:
    return None if np.isnan(v) else round(float(v), 4)


def force_error(true_N: np.ndarray, reported_N: np.ndarray, threshold_N: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per-run RMSE and bias (mean of reported - true), N, of the reported force against the
    truth over the samples in contact (true force above ``threshold_N``: the calibration's
    label rule, so the figures compare with the model's offline test RMSE); NaN for a run
    without contact."""
    inside = true_N > threshold_N
    count = inside.sum(axis=0)
    err = np.where(inside, reported_N - true_N, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rmse = np.sqrt((err ** 2).sum(axis=0) / count)
        bias = err.sum(axis=0) / count
    return np.where(count > 0, rmse, np.nan), np.where(count > 0, bias, np.nan)


def run_seeds(seed: int, n_runs: int) -> list[int]:
    """Seeds of ``n_runs`` runs starting at ``seed`` (run k uses seed + k)."""
    return [int(seed) + k for k in range(n_runs)]


def _streams(seed: int) -> dict[str, np.random.Generator]:
    # One independent stream per component, so e.g. a different egg never changes the operator.
    ss = np.random.SeedSequence(seed)
    names = ("operator", "motor_noise", "egg")
    return {n: np.random.default_rng(child) for n, child in zip(names, ss.spawn(len(names)))}


def measure_delay_ms(true_N: np.ndarray, reported_N: np.ndarray, dt: float) -> float:
    """Lag (ms) that best aligns the reported force with the true one (least squares).

    Returns NaN when there is too little force to tell (no contact in the run).
    """
    if np.max(true_N) < 0.5:
        return float("nan")
    max_lag = int(round(MAX_DELAY_SEARCH_MS * 1e-3 / dt))
    n = true_N.size
    errs = [np.mean((reported_N[lag:] - true_N[:n - lag]) ** 2) for lag in range(max_lag + 1)]
    return float(np.argmin(errs)) * dt * 1e3


@dataclass
class _Loop:
    """The loop's parts for ``B`` runs, built from one scene and one seed per run."""

    master: HapticMaster
    gripper: Gripper
    egg: Egg
    operator: Operator
    chain: Any
    load: np.ndarray
    egg_params: dict[str, np.ndarray]
    op_params: dict[str, np.ndarray]


def simulate(scene: TeleopScene, feedback: Feedback, seeds: list[int],
             progress: bool = False) -> TeleopResult:
    """Run the closed loop for one seeded run per entry of ``seeds``.

    Parameters
    ----------
    scene
        A loaded teleoperation scene.
    feedback
        Where the master's force comes from (:mod:`fbgforce.teleop.feedback`).
    seeds
        One seed per run: it fixes that run's operator, egg, motor noise and sensor device.
    progress
        Print a progress bar on stderr.
    """
    n_runs = len(seeds)
    n = int(round(scene.duration_s * scene.rate_hz))
    t_s = np.arange(n) * scene.dt
    lift_s = scene.lift_s
    loop = _build_loop(scene, feedback, seeds, t_s)
    feedback.start(scene, list(seeds))
    names = ("force_true_N", "force_reported_N", "opening_mm", "command_mm", "master_mm",
             "felt_N", "felt_excess_N")
    tr = {k: np.zeros((n, n_runs)) for k in names}
    tr["contact"] = np.zeros((n, n_runs), dtype=bool)
    reported = np.zeros(n_runs)
    bar = None
    if progress:
        from fbgforce import progress as fprogress

        bar = fprogress.bar(total=n, desc=f"teleop {feedback.name}", unit="sample")
    for i in range(n):
        reported = _loop_sample(i, t_s[i], n, lift_s, loop, feedback, reported, tr)
        if bar is not None and i % 100 == 99:
            bar.update(100)
    if bar is not None:
        bar.close()
    lo = scene.fixed("egg", "safe_band_low_N")
    hi = scene.fixed("egg", "safe_band_high_N")
    carried = t_s >= lift_s
    outcomes = _outcomes(scene, feedback, seeds, loop, tr, carried, (lo, hi))
    tr["required_N"] = np.where(carried[:, None], loop.egg.required_grip_N(loop.load[:, None]),
                                np.nan)
    return TeleopResult(t_s=t_s, traces=tr, outcomes=outcomes, feedback=feedback.name,
                        lift_s=lift_s, safe_band_N=(lo, hi),
                        extra={"break_force_N": loop.egg.break_N, "egg_params": loop.egg_params,
                               "operator_params": loop.op_params})


def _build_loop(scene: TeleopScene, feedback: Feedback, seeds: list[int], t_s: np.ndarray
                ) -> _Loop:
    """The loop's parts: each run's operator, egg and motor noise drawn from its own seed's
    streams, and the arm's load over the whole run."""
    n = t_s.size
    streams = [_streams(s) for s in seeds]
    op_params = scene.draw("operator", [s["operator"] for s in streams])
    egg_params = scene.draw("egg", [s["egg"] for s in streams])
    noise = np.stack([s["motor_noise"].standard_normal(n + 1) for s in streams], axis=1)
    master = HapticMaster(scene)
    gripper = Gripper(scene, len(seeds))
    egg = Egg(egg_params, scene)
    operator = Operator(op_params, scene, noise, feedback.renders_force)
    return _Loop(master=master, gripper=gripper, egg=egg, operator=operator,
                 chain=gripper.chain_stiffness(egg.k_shell), load=arm_load_acceleration(scene, t_s),
                 egg_params=egg_params, op_params=op_params)


def _loop_sample(i: int, t: float, n: int, lift_s: float, loop: _Loop, feedback: Feedback,
                 reported: np.ndarray, tr: dict[str, np.ndarray]) -> np.ndarray:
    """Sample ``i`` of the loop in the hardware's order (module docstring), its traces written
    into row ``i`` of ``tr``; returns the force the fingertip reports, which the master renders
    next sample."""
    master, gripper, egg, operator = loop.master, loop.gripper, loop.egg, loop.operator
    felt = master.force(reported, operator.y, operator.v)
    operator.step(i, t, tr, egg.width_mm, felt)
    # The stylus stops at the ends of the device's travel.
    travel = master.travel_mm
    hit = (operator.y < 0.0) | (operator.y > travel)
    operator.y = np.clip(operator.y, 0.0, travel)
    operator.v[hit] = 0.0
    opening = gripper.step(operator.y)
    force = egg.squeeze(opening, loop.chain)
    egg.step(force, loop.load[i], t >= lift_s)
    force = np.where(egg.present, force, 0.0)
    contact = force > 0.0
    # Samples after this one that cannot see contact: the gripper closes at most
    # max_step_mm per sample (one step of margin against rounding); a gone egg never does.
    reach = np.floor((opening - egg.width_mm) / gripper.max_step_mm) - 1.0
    free = np.where(egg.present, np.maximum(reach, 0.0), np.inf)
    free = np.minimum(free, n - 1 - i)
    reported = feedback.step(t, force, contact, loop.egg_params["contact_x_mm"],
                             loop.egg_params["contact_y_mm"], free)
    tr["force_true_N"][i] = force
    tr["force_reported_N"][i] = reported
    tr["opening_mm"][i] = opening
    tr["command_mm"][i] = gripper.command(operator.y)
    tr["master_mm"][i] = operator.y
    tr["felt_N"][i] = felt
    tr["felt_excess_N"][i] = felt - master.base_force(operator.y)
    tr["contact"][i] = contact
    return reported


def _outcomes(scene: TeleopScene, feedback: Feedback, seeds: list[int], loop: _Loop,
              tr: dict[str, np.ndarray], carried: np.ndarray, band: tuple[float, float]
              ) -> dict[str, np.ndarray]:
    """Each run's outcome: what became of the egg, how long the grip stayed in the safe band
    once carried, and (when the master renders the reported force) how late and how far off
    that force was; NaN where nothing was rendered."""
    n_runs = len(seeds)
    f = tr["force_true_N"]
    in_band = (f >= band[0]) & (f <= band[1])
    frac = in_band[carried].mean(axis=0) if carried.any() else np.zeros(n_runs)
    if feedback.renders_force:
        delays = np.array([measure_delay_ms(f[:, k], tr["force_reported_N"][:, k], scene.dt)
                           for k in range(n_runs)])
        rmse, bias = force_error(f, tr["force_reported_N"],
                                 float(scene.sim_scene.schedule["contact_threshold_N"]))
    else:
        delays = np.full(n_runs, np.nan)
        rmse = bias = np.full(n_runs, np.nan)
    egg = loop.egg
    return {
        "seed": np.asarray(seeds),
        "egg_broken": egg.broken.copy(),
        "egg_dropped": egg.dropped.copy(),
        "success": egg.present.copy(),
        "max_force_N": f.max(axis=0),
        "time_in_safe_band_fraction": frac,
        "estimator_delay_ms": delays,
        "force_rmse_N": rmse,
        "force_bias_N": bias,
        "contact_noticed_s": loop.operator.contact_time_s,
    }
