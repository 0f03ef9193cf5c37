"""The pieces of the bilateral teleoperation loop, each a small physical model.

All models are vectorised over ``B`` independent runs (seeded operators and eggs): every state
is an array of shape ``(B,)``, so that many operators are simulated in one pass. Units: mm,
mm/s, N, s (stiffnesses in N/m where the haptics literature quotes them so). The scene file
(``scenes/egg_grasp.toml``) holds every number and docs/teleop.md explains each choice.

Sign convention: the master's vertical position ``y_mm`` is 0 at its home (gripper open) and
grows as the operator pushes the stylus down, which closes the gripper. The master's force on
the hand is positive when it pushes back towards home.
"""
from __future__ import annotations

import math

import numpy as np

from fbgforce.teleop.scene import TeleopScene


# --------------------------------------------------------------------------------------------
# The robot arm: moves autonomously; the grip must hold the egg against gravity + acceleration
# --------------------------------------------------------------------------------------------

def arm_load_acceleration(scene: TeleopScene, t_s: np.ndarray) -> np.ndarray:
    """Magnitude of gravity plus the arm's acceleration that the grip must resist, m/s^2.

    Each move is a minimum-jerk profile (how a robot controller moves smoothly between two
    points): displacement ``D (10 s^3 - 15 s^4 + 6 s^5)`` with ``s = (t - t0) / T``, so its
    acceleration is ``D / T^2 (60 s - 180 s^2 + 120 s^3)`` (peak ``5.77 D / T^2``). The
    tangential load on the two friction contacts is ``m |g + a|`` whatever its direction.
    """
    g = scene.fixed("arm", "gravity_m_s2")
    ax = np.zeros_like(t_s, dtype=np.float64)
    az = np.zeros_like(t_s, dtype=np.float64)
    for mv in scene.moves:
        s = (t_s - mv.start_s) / mv.duration_s
        inside = (s >= 0.0) & (s <= 1.0)
        shape = np.where(inside, 60.0 * s - 180.0 * s**2 + 120.0 * s**3, 0.0) / mv.duration_s**2
        ax += mv.dx_m * shape
        az += mv.dz_m * shape
    return np.hypot(ax, g + az)


# --------------------------------------------------------------------------------------------
# Haptic master (3D Systems Touch)
# --------------------------------------------------------------------------------------------

class HapticMaster:
    """A Touch-like device rendering a spring towards home whose stiffness rises with force.

    As in the paper, the device's stiffness follows the fingertip force reported to it:
    ``K = K0 + (Kmax - K0) * clip(F_reported / F_full, 0, 1)``, force on the hand
    ``clip(K * y + b * v, -F_peak, F_peak)``. ``K0`` is the light spring that holds the stylus
    at home (felt all the time, carries no information about the grip); ``Kmax`` ≈ 400 N/m is
    what a Touch renders without chatter; ``F_peak`` = 3.3 N is its peak force; ``b`` is a
    small rendered damping that haptic loops use for stability.
    """

    def __init__(self, scene: TeleopScene) -> None:
        self.k0 = scene.fixed("master", "base_stiffness_N_per_m")
        self.kmax = scene.fixed("master", "max_stiffness_N_per_m")
        self.f_full = scene.fixed("master", "full_stiffness_force_N")
        self.f_peak = scene.fixed("master", "peak_force_N")
        self.b = scene.fixed("master", "damping_N_s_per_m")
        self.travel_mm = scene.fixed("master", "travel_mm")

    def stiffness(self, reported_force_N: np.ndarray) -> np.ndarray:
        """Rendered stiffness, N/m, for the force the fingertip reports."""
        frac = np.clip(reported_force_N / self.f_full, 0.0, 1.0)
        return self.k0 + (self.kmax - self.k0) * frac

    def force(self, reported_force_N: np.ndarray, y_mm: np.ndarray, v_mm_s: np.ndarray
              ) -> np.ndarray:
        """Force on the operator's hand, N (positive pushes towards home)."""
        raw = self.stiffness(reported_force_N) * y_mm * 1e-3 + self.b * v_mm_s * 1e-3
        return np.clip(raw, -self.f_peak, self.f_peak)

    def base_force(self, y_mm: np.ndarray) -> np.ndarray:
        """What the home spring alone renders: the operator's learned 'free space' feel."""
        return self.k0 * y_mm * 1e-3


# --------------------------------------------------------------------------------------------
# Two-finger gripper with the egg between the fingers
# --------------------------------------------------------------------------------------------

class Gripper:
    """Position-controlled two-finger gripper whose opening follows the master.

    Command: ``open - map_gain * y_master`` (mm between fingertips). The actuator follows it
    as a first-order lag of the given bandwidth with a speed limit (servo + gearbox). The
    fingers squeeze the egg through a chain of springs in series: servo stiffness (position
    loop and gear compliance), the two fingertip rubber pads, and the egg shell. The egg's
    resistance does not slow the servo's set-point: a position-controlled gripper presses as
    hard as its position error demands, which is exactly why the operator must not overshoot.
    """

    def __init__(self, scene: TeleopScene, n_runs: int) -> None:
        self.open_mm = scene.fixed("gripper", "open_mm")
        self.gain = scene.fixed("gripper", "map_gain")
        self.alpha = 1.0 - math.exp(-2.0 * math.pi * scene.fixed("gripper", "bandwidth_hz")
                                    * scene.dt)
        self.max_step_mm = scene.fixed("gripper", "max_speed_mm_s") * scene.dt
        self.k_servo = scene.fixed("gripper", "servo_stiffness_N_per_mm")
        self.k_pad = scene.fixed("gripper", "pad_stiffness_N_per_mm")
        self.opening_mm = np.full(n_runs, self.open_mm)

    def command(self, y_master_mm: np.ndarray) -> np.ndarray:
        """Opening the master asks for, mm (what Fig. 7 shows dotted)."""
        return np.maximum(self.open_mm - self.gain * y_master_mm, 0.0)

    def step(self, y_master_mm: np.ndarray) -> np.ndarray:
        """Advance the actuator one sample; returns the motor opening, mm."""
        move = np.clip(self.alpha * (self.command(y_master_mm) - self.opening_mm),
                       -self.max_step_mm, self.max_step_mm)
        self.opening_mm = np.maximum(self.opening_mm + move, 0.0)
        return self.opening_mm

    def chain_stiffness(self, shell_N_per_mm: np.ndarray) -> np.ndarray:
        """Series stiffness servo + two pads + shell, N/mm."""
        return 1.0 / (1.0 / self.k_servo + 2.0 / self.k_pad + 1.0 / shell_N_per_mm)


class Egg:
    """A hen's egg: width, mass, shell stiffness, breaking force, friction on the pads.

    Breaks the first time the true squeeze exceeds its breaking force. Once the arm moves, the
    two friction contacts must carry ``m |g + a|``: while ``2 mu_s F`` covers it the egg sticks;
    otherwise it slides with kinetic friction ``2 mu_k F`` until it sticks again, and it is
    dropped once it has slid ``drop_slip_mm`` (off the fingertip pads). A broken or dropped
    egg no longer pushes back on the fingers.
    """

    def __init__(self, params: dict[str, np.ndarray], scene: TeleopScene) -> None:
        self.width_mm = params["width_mm"]
        self.mass_kg = params["mass_kg"]
        self.k_shell = params["shell_stiffness_N_per_mm"]
        self.break_N = params["break_force_N"]
        self.mu_s = params["friction_static"]
        self.mu_k = params["friction_static"] * scene.fixed("egg", "friction_kinetic_ratio")
        self.drop_mm = scene.fixed("egg", "drop_slip_mm")
        self.dt = scene.dt
        n = self.width_mm.size
        self.broken = np.zeros(n, dtype=bool)
        self.dropped = np.zeros(n, dtype=bool)
        self.slip_mm = np.zeros(n)
        self.slip_v_mm_s = np.zeros(n)

    @property
    def present(self) -> np.ndarray:
        """Runs whose egg is still whole and between the fingers."""
        return ~(self.broken | self.dropped)

    def required_grip_N(self, load_m_s2: float | np.ndarray) -> np.ndarray:
        """Smallest squeeze that holds the egg against ``load_m_s2`` by static friction."""
        return self.mass_kg * load_m_s2 / (2.0 * self.mu_s)

    def squeeze(self, opening_mm: np.ndarray, chain_N_per_mm: np.ndarray) -> np.ndarray:
        """True grip force for the motor opening (0 where the egg is gone or untouched)."""
        force = chain_N_per_mm * np.maximum(self.width_mm - opening_mm, 0.0)
        return np.where(self.present, force, 0.0)

    def step(self, force_N: np.ndarray, load_m_s2: float, carried: bool) -> None:
        """Update breakage and slip for one sample under the grip ``force_N``."""
        self.broken |= self.present & (force_N > self.break_N)
        if not carried:
            return  # still resting on the table: the table carries the weight
        demand = self.mass_kg * load_m_s2
        sliding = (self.slip_v_mm_s > 0.0) | (demand > 2.0 * self.mu_s * force_N)
        accel_mm_s2 = 1000.0 * (demand - 2.0 * self.mu_k * force_N) / self.mass_kg
        v = np.maximum(self.slip_v_mm_s + accel_mm_s2 * self.dt, 0.0)
        self.slip_v_mm_s = np.where(sliding & self.present, v, 0.0)
        self.slip_mm += self.slip_v_mm_s * self.dt
        self.dropped |= ~self.broken & (self.slip_mm > self.drop_mm)


# --------------------------------------------------------------------------------------------
# Operator: intention, perception with delays, and the hand's mechanics
# --------------------------------------------------------------------------------------------

WAIT, APPROACH, FINE, SQUEEZE, HOLD, REGULATE = range(6)
PHASE_NAMES = ("wait", "approach", "fine", "squeeze", "hold", "regulate")


class Operator:
    """A human holding the stylus: an intention, delayed perception, and an arm's impedance.

    Intention ``y_d`` (mm of stylus travel the operator means), per phase:

    - wait for ``start_delay_s``, then approach at ``approach_speed_mm_s`` until the gap they
      see on the camera (``visual_delay_s`` old) is within ``slow_down_margin_mm`` of the egg;
    - close slowly at ``fine_speed_mm_s`` until contact is noticed: seen on the camera
      (``visual_delay_s`` after it happened) or felt (the device pushes back more than its
      home spring by ``feel_threshold_N``, ``haptic_delay_s`` after it happened);
    - with force feedback, regulate: move the intention at ``force_gain * (target_felt -
      felt(t - haptic_delay))`` mm/s (capped), i.e. push until the stylus feels as firm as
      intended; without it, squeeze on by ``visual_squeeze_mm`` of finger travel (what they
      judge a safe grip from the picture) and hold the stylus there.

    The hand is a mass-spring-damper pulled towards ``y_d`` plus motor noise: slow postural
    drift (an Ornstein-Uhlenbeck process, ``drift_mm`` standard deviation, ``drift_time_s``
    correlation time: an unsupported hand wanders by millimetres over seconds) and
    physiological tremor (``tremor_mm`` at ``tremor_hz``). The device's force acts on that
    mass, so a stiffening device pushes the hand back at once, before any reaction.
    """

    def __init__(self, params: dict[str, np.ndarray], scene: TeleopScene,
                 noise: np.ndarray, feels_force: bool) -> None:
        self.p = params
        self.dt = scene.dt
        self.feels_force = feels_force
        self.map_gain = scene.fixed("gripper", "map_gain")
        n = params["hand_mass_kg"].size
        self.phase = np.full(n, WAIT)
        self.y_d = np.zeros(n)
        self.squeeze_to = np.full(n, np.inf)
        self.y = np.zeros(n)
        self.v = np.zeros(n)
        self.vis_steps = np.rint(params["visual_delay_s"] / self.dt).astype(np.int64)
        self.hap_steps = np.rint(params["haptic_delay_s"] / self.dt).astype(np.int64)
        self.contact_time_s = np.full(n, np.nan)
        self.b_hand = 2.0 * params["hand_damping_ratio"] * np.sqrt(
            params["hand_stiffness_N_per_m"] * params["hand_mass_kg"])
        self.motor_noise_mm = self._motor_noise(noise, scene)

    def _motor_noise(self, noise: np.ndarray, scene: TeleopScene) -> np.ndarray:
        """Drift + tremor for every run and sample, (n_steps, B) mm, from white noise."""
        n_steps = noise.shape[0] - 1
        tau = self.p["drift_time_s"]
        a = np.exp(-self.dt / tau)
        scale = self.p["drift_mm"] * np.sqrt(1.0 - a * a)
        drift = np.empty((n_steps, tau.size))
        state = np.zeros(tau.size)  # the hand starts where it means to be
        for i in range(n_steps):
            state = a * state + scale * noise[i]
            drift[i] = state
        t = np.arange(n_steps)[:, None] * self.dt
        phase0 = 2.0 * np.pi * np.mod(noise[-1], 1.0)  # seeded phase from the run's stream
        tremor = self.p["tremor_mm"] * np.sin(2.0 * np.pi * self.p["tremor_hz"] * t + phase0)
        return drift + tremor

    def step(self, i: int, t_s: float, hist: dict[str, np.ndarray], egg_width_mm: np.ndarray,
             master_force_N: np.ndarray) -> None:
        """Update the intention from what the operator perceives, then move the hand.

        ``hist`` holds the loop's past samples, shape ``(n_steps, B)``, valid up to ``i - 1``:
        ``opening_mm``, ``contact``, ``felt_N``, ``felt_excess_N``.
        """
        p, dt = self.p, self.dt
        runs = np.arange(self.y.size)
        vi = i - self.vis_steps
        hi = i - self.hap_steps
        seen_gap = np.where(vi >= 0, hist["opening_mm"][np.maximum(vi, 0), runs], np.inf)
        seen_contact = (vi >= 0) & hist["contact"][np.maximum(vi, 0), runs]
        felt_ok = hi >= 0
        felt = np.where(felt_ok, hist["felt_N"][np.maximum(hi, 0), runs], 0.0)
        felt_excess = np.where(felt_ok, hist["felt_excess_N"][np.maximum(hi, 0), runs], 0.0)

        ph = self.phase
        start = (ph == WAIT) & (t_s >= p["start_delay_s"])
        ph[start] = APPROACH
        near = (ph == APPROACH) & (seen_gap <= egg_width_mm + p["slow_down_margin_mm"])
        ph[near] = FINE
        noticed = np.isin(ph, (APPROACH, FINE)) & (
            seen_contact | (felt_excess > p["feel_threshold_N"]))
        self.contact_time_s[noticed] = t_s
        if self.feels_force:
            ph[noticed] = REGULATE
        else:
            ph[noticed] = SQUEEZE
            self.squeeze_to[noticed] = self.y_d[noticed] + p["visual_squeeze_mm"][noticed] \
                / self.map_gain
        rate = np.zeros_like(self.y_d)
        rate = np.where(ph == APPROACH, p["approach_speed_mm_s"], rate)
        rate = np.where((ph == FINE) | (ph == SQUEEZE), p["fine_speed_mm_s"], rate)
        correction = np.clip(p["force_gain_mm_s_per_N"] * (p["target_felt_force_N"] - felt),
                             -p["max_correction_speed_mm_s"], p["max_correction_speed_mm_s"])
        rate = np.where(ph == REGULATE, correction, rate)
        self.y_d = self.y_d + rate * dt
        done = (ph == SQUEEZE) & (self.y_d >= self.squeeze_to)
        self.y_d[done] = self.squeeze_to[done]
        ph[done] = HOLD

        # Hand mechanics (semi-implicit Euler, exact enough at 1 kHz for a ~15 Hz hand mode).
        target = self.y_d + self.motor_noise_mm[i]
        force_N = (p["hand_stiffness_N_per_m"] * (target - self.y) * 1e-3
                   - self.b_hand * self.v * 1e-3 - master_force_N)
        self.v = self.v + 1000.0 * force_N / p["hand_mass_kg"] * dt
        self.y = self.y + self.v * dt
