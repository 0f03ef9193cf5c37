"""Physical effects of the simulated end-effector, one small component each.

An effect is applied only when a scene lists it (``[effects.NAME]``); an unlisted effect has no
influence at all, down to the random numbers: every effect draws from its own stream derived
from ``(scene seed, device, effect name)`` (:func:`effect_rng`), and draws a fixed number of
values per sample, so adding, removing or re-parameterising one effect never changes another
effect's numbers, and processing a recording in chunks draws exactly what one call would.

Properties of the physical device (manufacturing tolerances, the thermal mismatch of the
bonded gratings) come from a stream derived from ``(device, effect name)`` only: the same
device keeps the same imperfections in every scene and under every scene seed.

Effects run in a fixed physical order, whatever the order in the scene file
(:data:`EFFECT_ORDER`): tolerance (device) → edge_contact (where the load enters the
beams) → friction_hysteresis, viscoelastic (rubber pad) → dynamics (pad/beam vibration) →
Bragg shift → temperature → noise → quantization (interrogator) → dropout (link).
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from fbgforce.geometry import BASE_WL_NM, N_BEAMS, PAD_SIZE_MM, THERMAL_COEFF_PER_K, Design
from fbgforce.sim.params import Param

#: Entropy of the device-property streams (fixed: a device is a physical object, its
#: tolerances must not change with the scene seed).
DEVICE_ENTROPY = 0x0F0B_6DE5
#: Dropout flag values in the ``dropout`` extra column.
DROPOUT_OK, DROPOUT_LOST, DROPOUT_GARBLED = 0, 1, 2


def effect_rng(name: str, seed: int, device: int, *, device_property: bool = False
               ) -> np.random.Generator:
    """The random stream of one effect.

    ``numpy.random.SeedSequence(entropy=seed, spawn_key=(device, crc32(name)))``; for device
    properties the entropy is :data:`DEVICE_ENTROPY` instead of the scene seed. CRC-32 (not
    Python's salted ``hash``) keeps streams identical across processes and machines.
    """
    key = zlib.crc32(name.encode("utf-8"))
    entropy = DEVICE_ENTROPY if device_property else int(seed)
    return np.random.default_rng(np.random.SeedSequence(entropy=entropy,
                                                        spawn_key=(int(device), key)))


@dataclass(frozen=True)
class Context:
    """What every effect may know: the scene seed, the device number and the sample rate."""

    seed: int
    device: int
    rate_hz: float


class Effect:
    """Base class: holds validated parameters and the context."""

    name: ClassVar[str]
    summary: ClassVar[str]
    params: ClassVar[dict[str, Param]]

    def __init__(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.p = dict(params)
        self.ctx = ctx

    def rng(self, *, device_property: bool = False) -> np.random.Generator:
        """This effect's own random stream (see :func:`effect_rng`)."""
        return effect_rng(self.name, self.ctx.seed, self.ctx.device,
                          device_property=device_property)


# ------------------------------------------------------------------------------------ device

class Tolerance(Effect):
    """A manufactured device differs from the nominal design.

    Per-beam gain ``(1 + gain_sd z) * (strain_transfer + strain_transfer_sd z')`` (beam
    dimensions; strain transferred through the adhesive bond to the fibre), support positions
    scaled about the pad centre (spacing error) and offset systematically and randomly (worse
    in y: the pad is longer and the beams are clamped along x), support stiffness spread, and
    base wavelength spread. Random parts are drawn once per device from the device stream.
    """

    name = "tolerance"
    summary = "seeded device: beam gains, bond strain transfer, support positions and stiffness"
    params = {
        "gain_sd": Param("float", 0.04, "relative sd of the beam strain gain (dimensions)", 0, 0.5),
        "strain_transfer": Param("float", 0.90, "mean bond strain-transfer factor (1 = perfect)",
                                 0.3, 1.0, lo_open=True),
        "strain_transfer_sd": Param("float", 0.04, "sd of the strain-transfer factor per beam", 0, 0.3),
        "support_offset_x_mm": Param("float", 0.0, "systematic x offset of all supports, mm", -10, 10),
        "support_offset_y_mm": Param("float", 0.0, "systematic y offset of all supports, mm", -10, 10),
        "support_scale_x": Param("float", 1.0, "support spacing in x relative to the design "
                                 "(about the pad centre)", 0.2, 3.0),
        "support_scale_y": Param("float", 1.0, "support spacing in y relative to the design", 0.2, 3.0),
        "support_sd_x_mm": Param("float", 0.2, "sd of each support's x position error, mm", 0, 5),
        "support_sd_y_mm": Param("float", 0.6, "sd of each support's y position error, mm", 0, 5),
        "stiffness_sd": Param("float", 0.08, "relative sd of support stiffness", 0, 0.5),
        "base_wl_sd_nm": Param("float", 0.2, "sd of the unloaded wavelength of each grating, nm", 0, 2),
    }

    def __init__(self, params: Mapping[str, Any], ctx: Context) -> None:
        super().__init__(params, ctx)
        g = self.rng(device_property=True)
        # Fixed draw order and count: the device is the same whatever the parameter values.
        z_gain = g.standard_normal(N_BEAMS)
        z_transfer = g.standard_normal(N_BEAMS)
        z_support = g.standard_normal((N_BEAMS, 2))
        z_stiff = g.standard_normal(N_BEAMS)
        z_base = g.standard_normal(N_BEAMS + 1)
        p = self.p
        self.gain_factor = (1.0 + p["gain_sd"] * z_gain) * np.clip(
            p["strain_transfer"] + p["strain_transfer_sd"] * z_transfer, 0.05, 1.0)
        self.support_offset_mm = (np.array([p["support_offset_x_mm"], p["support_offset_y_mm"]])
                                  + z_support * np.array([p["support_sd_x_mm"], p["support_sd_y_mm"]]))
        self.support_scale = np.array([p["support_scale_x"], p["support_scale_y"]])
        self.stiffness_factor = np.clip(1.0 + p["stiffness_sd"] * z_stiff, 0.05, None)
        self.base_offset_nm = p["base_wl_sd_nm"] * z_base

    def apply(self, design: Design) -> Design:
        """The device: ``design`` with this device's errors."""
        centre = np.asarray(PAD_SIZE_MM) / 2.0
        # Written as a correction so that a scale of exactly 1 leaves the design untouched.
        supports = design.supports_mm + (design.supports_mm - centre) * (self.support_scale - 1.0)
        return design.replace(
            supports_mm=supports + self.support_offset_mm,
            stiffness=design.stiffness * self.stiffness_factor,
            gain=design.gain * self.gain_factor,
            base_wl_nm=design.base_wl_nm + self.base_offset_nm,
        )


# ------------------------------------------------------------------------------- mechanics

class EdgeContact(Effect):
    """Planar pad–beam contact (paper §VII-B): near the pad boundary the pad pivots on the edge
    of the flat contact patch, so loads across a boundary band of width ``width_mm`` produce
    nearly the same beam forces. Modelled as a compression of the load's effective position:
    within the band the slope d(effective)/d(true) falls linearly from 1 to
    ``1 - strength`` at the pad edge (a strength of 1 makes the outermost loads identical).
    """

    name = "edge_contact"
    summary = "boundary loads look alike (planar contact between pad and beams)"
    params = {
        "width_mm": Param("float", 3.0, "width of the boundary band, mm", 0, 10.5, lo_open=True),
        "strength_x": Param("float", 0.6, "slope loss at the left/right edges (0 = none, 1 = flat)", 0, 1),
        "strength_y": Param("float", 0.8, "slope loss at the top/bottom edges", 0, 1),
    }

    def location(self, x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Effective load position for the beam-force split."""
        return (self._squeeze(x_mm, PAD_SIZE_MM[0], self.p["strength_x"]),
                self._squeeze(y_mm, PAD_SIZE_MM[1], self.p["strength_y"]))

    def _squeeze(self, v: np.ndarray, size: float, strength: float) -> np.ndarray:
        half = size / 2.0
        w = self.p["width_mm"]
        u = v - half
        depth = np.abs(u) - (half - w)  # how far into the band (negative: interior)
        # Integral of the slope loss: strength * d^2 / (2w) inside the band, linear beyond.
        loss = np.where(depth <= 0, 0.0,
                        np.where(depth <= w, strength * depth**2 / (2 * w),
                                 strength * (w / 2 + (depth - w))))
        return v - np.sign(u) * loss


class FrictionHysteresis(Effect):
    """Rate-independent (frictional) hysteresis of the rubber pad: a Prandtl–Ishlinskii model,
    a weighted sum of play operators, per beam.

    Where the pad bears on a support it sticks until the load change overcomes friction, and
    Coulomb friction grows with the normal load, so each play operator's half-width is
    proportional to the load it carries: operator ``i`` of beam ``b`` follows
    ``y = clip(y, F - r_i |F|, F + r_i |F|)`` with ``F`` the beam force, and the beam receives
    ``F + mean_i(y_i - F)``. Thresholds ``r_i = g_b (2 i - 1) / (2 n)`` (``i = 1..n``,
    ``n = n_operators``) spread evenly so that their mean is ``g_b / 2``: on branches where
    every operator has slipped, loading delivers ``(1 - g_b / 2) F`` and unloading
    ``(1 + g_b / 2) F``, a gap of ``g_b F`` at equal force; right after a reversal the
    operators release one by one (the rounded corner of a rubber loop). The loop closes at zero
    load, so the pad carries nothing when nothing presses on it. The output depends on the
    sequence of loads only, not on their timing (the rate-dependent part is
    :class:`Viscoelastic`). ``g_b = gap * max(0, 1 + gap_sd * z_b)`` with ``z_b`` drawn once
    per device from this effect's device stream (the friction of each support differs).
    """

    name = "friction_hysteresis"
    summary = "rubber pad friction: rate-independent loading/unloading loop (play operators)"
    params = {
        "gap": Param("float", 0.06, "loading-unloading gap at equal force on developed branches, "
                     "as a fraction of that force (0 = none)", 0, 0.5),
        "gap_sd": Param("float", 0.2, "relative sd of the gap between beams (supports)", 0, 1),
        "n_operators": Param("int", 8, "play operators per beam (smoothness of the reversal)",
                             1, 64),
    }

    def __init__(self, params: Mapping[str, Any], ctx: Context) -> None:
        super().__init__(params, ctx)
        z = self.rng(device_property=True).standard_normal(N_BEAMS)
        n = self.p["n_operators"]
        self.beam_gap = self.p["gap"] * np.clip(1.0 + self.p["gap_sd"] * z, 0.0, None)
        # (beam, operator) half-widths relative to the load.
        self.ratio = self.beam_gap[:, None] * ((2 * np.arange(1, n + 1) - 1) / (2.0 * n))[None, :]
        self.state = np.zeros((N_BEAMS, n))

    def process(self, beam_forces: np.ndarray) -> np.ndarray:
        """Pass (n, 4) beam forces through the pad; keeps the operator states between calls."""
        f = np.asarray(beam_forces, float)
        out = np.empty_like(f)
        n_ops = self.ratio.shape[1]
        for b in range(N_BEAMS):
            col = f[:, b].tolist()
            mag = np.abs(f[:, b])
            dev_sum = np.zeros(f.shape[0])
            for i in range(n_ops):
                r = float(self.ratio[b, i])
                lo = (f[:, b] - r * mag).tolist()
                hi = (f[:, b] + r * mag).tolist()
                y = float(self.state[b, i])
                ys = [0.0] * len(col)
                # A plain float loop: min/max are exact, so any chunking gives the same bits.
                for k in range(len(col)):
                    if y < lo[k]:
                        y = lo[k]
                    elif y > hi[k]:
                        y = hi[k]
                    ys[k] = y
                self.state[b, i] = y
                dev_sum += np.asarray(ys) - f[:, b]
            out[:, b] = f[:, b] + dev_sum / n_ops
        return out


class Viscoelastic(Effect):
    """Viscoelastic rubber pad (paper Fig. 8): the force reaching the beams lags the applied
    force, a standard-linear-solid response per beam,
    ``out = F + magnitude * (F_lag - F)`` with ``F_lag`` a first-order lag of ``F`` with time
    constant ``time_constant_s``: lower strain while loading, higher while unloading (a loop
    that narrows as the press slows down), and a small creep recovery after release. Scene
    files may still call it ``hysteresis`` (its former name, see :data:`RENAMED_EFFECTS`).
    """

    name = "viscoelastic"
    summary = "viscoelastic pad: rate-dependent lag and creep"
    params = {
        "magnitude": Param("float", 0.06, "fraction of the force that relaxes (0 = elastic)", 0, 0.9),
        "time_constant_s": Param("float", 0.25, "relaxation time constant, s", 0, 100, lo_open=True),
    }

    def __init__(self, params: Mapping[str, Any], ctx: Context) -> None:
        super().__init__(params, ctx)
        self.alpha = 1.0 - math.exp(-1.0 / (ctx.rate_hz * self.p["time_constant_s"]))
        self.state = [0.0] * N_BEAMS

    def process(self, beam_forces: np.ndarray) -> np.ndarray:
        """Pass (n, 4) beam forces through the pad; keeps the lag state between calls."""
        lag = np.empty_like(beam_forces)
        a = self.alpha
        for b in range(N_BEAMS):
            s = self.state[b]
            col = beam_forces[:, b].tolist()
            out = [0.0] * len(col)
            # A plain float loop: bit-identical however the recording is chunked, and fast
            # enough (about 0.1 s per 234k samples and beam); numpy has no IIR filter.
            for k, u in enumerate(col):
                s += a * (u - s)
                out[k] = s
            self.state[b] = s
            lag[:, b] = out
        return beam_forces + self.p["magnitude"] * (lag - beam_forces)


def _expm(m: np.ndarray) -> np.ndarray:
    """Matrix exponential of a small matrix (scaling and squaring with a Taylor series)."""
    norm = np.abs(m).sum(axis=1).max()
    squarings = max(0, int(math.ceil(math.log2(norm / 0.25))) if norm > 0.25 else 0)
    a = m / 2.0**squarings
    result = np.eye(m.shape[0])
    term = np.eye(m.shape[0])
    for k in range(1, 25):
        term = term @ a / k
        result = result + term
    for _ in range(squarings):
        result = result @ result
    return result


class Dynamics(Effect):
    """Structural vibration (paper Fig. 9): each beam force follows the quasi-static force
    through a lightly damped mode, ``f'' + 2 zeta w f' + w^2 f = w^2 u``, and an impact of
    impulse ``J`` kicks the mode (``df'/dt += w^2 J_i``). The mode (> 500 Hz) is integrated on
    an internal grid of ``internal_rate_hz`` (input interpolated linearly between samples,
    impacts placed on the internal grid) and sampled at the output rate, so it aliases as it
    does in the real 1 kHz interrogator. The internal steps are composed exactly into one
    transition per output sample (matrix powers), which keeps a recording of any length cheap.
    """

    name = "dynamics"
    summary = "impacts excite a >500 Hz mode decaying in ~0.04 s"
    params = {
        "frequency_hz": Param("float", 720.0, "natural frequency of the pad mode, Hz", 1, 20000),
        "time_constant_s": Param("float", 0.010, "amplitude decay time constant, s "
                                 "(0.04 s from a tap to the noise floor is about 4 time constants)",
                                 0, 10, lo_open=True),
        "internal_rate_hz": Param("float", 20000.0, "internal simulation rate, Hz (>= 10 kHz, "
                                  "an integer multiple of the sample rate)", 10000, 1e7),
    }

    def __init__(self, params: Mapping[str, Any], ctx: Context) -> None:
        super().__init__(params, ctx)
        ratio = self.p["internal_rate_hz"] / ctx.rate_hz
        self.substeps = int(round(ratio))
        if self.substeps < 1 or abs(ratio - self.substeps) > 1e-9 * ratio:
            raise ValueError(f"dynamics.internal_rate_hz ({self.p['internal_rate_hz']:g}) must be "
                             f"an integer multiple of the sample rate ({ctx.rate_hz:g} Hz)")
        w = 2 * math.pi * self.p["frequency_hz"]
        zeta = 1.0 / (w * self.p["time_constant_s"])
        self.omega = w
        T = 1.0 / ctx.rate_hz
        h = T / self.substeps
        # State [f, f'/w, u, r] with u the input force and r = du/dt * T, constant within a
        # sample interval (linear interpolation). Scaled so all entries are O(1).
        m = np.zeros((4, 4))
        m[0, 1] = w
        m[1, 0] = -w
        m[1, 1] = -2 * zeta * w
        m[1, 2] = w
        m[2, 3] = 1.0 / T
        step = _expm(m * h)  # one internal step
        powers = [np.eye(4)]
        for _ in range(self.substeps):
            powers.append(powers[-1] @ step)
        whole = powers[self.substeps]  # the internal grid composed over one output sample
        self.g = whole[:2, :2]
        self.b_u = whole[:2, 2]  # weight of u at the start of the interval
        self.b_r = whole[:2, 3]
        # An impact at internal step j of the interval is propagated over the remaining steps.
        self.kick_prop = [powers[self.substeps - j][:2, 1] for j in range(self.substeps)]
        self.state = np.zeros((2, N_BEAMS))
        self.prev_u = np.zeros(N_BEAMS)

    def process(self, beam_forces: np.ndarray, kicks_Ns: np.ndarray | None = None,
                kick_step: np.ndarray | None = None) -> np.ndarray:
        """Beam forces (n, 4) after the mode; ``kicks_Ns`` (n, 4) impulses per beam delivered
        at internal step ``kick_step`` (n,) of each sample interval (default: its middle)."""
        u = np.asarray(beam_forces, float)
        n = u.shape[0]
        prev = np.vstack([self.prev_u, u[:-1]]) if n else u
        # Drive of each interval, vectorised: d_k = b_u u_{k-1} + b_r (u_k - u_{k-1}) [+ kick].
        drive = (self.b_u[:, None, None] * prev[None] + self.b_r[:, None, None] * (u - prev)[None])
        if kicks_Ns is not None and np.any(kicks_Ns):
            steps = (np.full(n, self.substeps // 2) if kick_step is None
                     else np.clip(np.asarray(kick_step, int), 0, self.substeps - 1))
            for k in np.flatnonzero(np.any(kicks_Ns != 0, axis=1)):
                prop = self.kick_prop[steps[k]]
                drive[:, k, :] += prop[:, None] * (self.omega * kicks_Ns[k])[None, :]
        out = np.empty_like(u)
        g00, g01, g10, g11 = self.g.ravel().tolist()
        for b in range(N_BEAMS):
            f, v = self.state[:, b].tolist()
            d0 = drive[0, :, b].tolist()
            d1 = drive[1, :, b].tolist()
            col = [0.0] * n
            for k in range(n):
                f, v = g00 * f + g01 * v + d0[k], g10 * f + g11 * v + d1[k]
                col[k] = f
            self.state[:, b] = (f, v)
            out[:, b] = col
        if n:
            self.prev_u = u[-1].copy()
        return out


# ------------------------------------------------------------------------------ wavelengths

class Temperature(Effect):
    """Temperature history and the gratings' thermal response, eq. (6).

    ``dT(t) = offset_K + ramp_K * clip((t - ramp_start_s) / ramp_duration_s, 0, 1) + walk(t)``
    with ``walk`` a random walk of ``drift_K_per_sqrt_s``. Each grating shifts by
    ``S * lambda_i / lambda_T * (1 + m_i) * dT`` pm with ``S = sensitivity_pm_per_K`` at the
    reference grating; ``m_i`` (sd ``mismatch_sd``, 0 for the reference itself) is the
    device's per-grating mismatch (bond, substrate strain), so compensation is imperfect.
    """

    name = "temperature"
    summary = "temperature drift/ramp with per-grating thermal mismatch"
    params = {
        "offset_K": Param("float", 0.0, "constant temperature offset from the tare, K", -100, 100),
        "ramp_K": Param("float", 0.0, "ramp amplitude, K", -200, 200),
        "ramp_start_s": Param("float", 0.0, "ramp start time, s", 0, None),
        "ramp_duration_s": Param("float", 60.0, "ramp duration, s", 0, None, lo_open=True),
        "drift_K_per_sqrt_s": Param("float", 0.02, "random-walk drift, K per sqrt(s)", 0, 10),
        "sensitivity_pm_per_K": Param("float", round(BASE_WL_NM[-1] * THERMAL_COEFF_PER_K * 1000, 2),
                                      "thermal sensitivity of the reference grating, pm/K "
                                      "(bonded gratings: 10-25)", 0, 100),
        "mismatch_sd": Param("float", 0.03, "relative sd of each strain grating's thermal "
                             "sensitivity against the reference", 0, 0.5),
    }

    def __init__(self, params: Mapping[str, Any], ctx: Context) -> None:
        super().__init__(params, ctx)
        m = self.rng(device_property=True).standard_normal(N_BEAMS) * self.p["mismatch_sd"]
        self.mismatch = np.append(m, 0.0)
        self.walk_rng = self.rng()
        self.walk = 0.0

    def delta_T(self, t_s: np.ndarray) -> np.ndarray:
        """Temperature change (n,) at times ``t_s``; advances the random walk."""
        p = self.p
        t = np.asarray(t_s, float)
        steps = self.walk_rng.standard_normal(t.size) * (p["drift_K_per_sqrt_s"]
                                                         / math.sqrt(self.ctx.rate_hz))
        walk = np.cumsum(np.concatenate([[self.walk], steps]))[1:]
        if t.size:
            self.walk = float(walk[-1])
        ramp = p["ramp_K"] * np.clip((t - p["ramp_start_s"]) / p["ramp_duration_s"], 0.0, 1.0)
        return p["offset_K"] + ramp + walk

    def shift_nm(self, design: Design, dT: np.ndarray) -> np.ndarray:
        """(n, 5) thermal wavelength shifts, nm."""
        base = design.base_wl_nm
        sens_nm = self.p["sensitivity_pm_per_K"] * 1e-3 * base / base[-1] * (1.0 + self.mismatch)
        return dT[:, None] * sens_nm[None, :]


class Noise(Effect):
    """Interrogator peak-detection noise: white, Gaussian, sd ``sigma_pm + relative * |s|``
    with ``s`` the strain-induced shift (the paper: 3-10 pm, growing with the force level)."""

    name = "noise"
    summary = "interrogator noise, 3-10 pm with a part proportional to the signal"
    params = {
        "sigma_pm": Param("float", 4.0, "noise sd at rest, pm", 0, 1000),
        "relative": Param("float", 0.005, "extra sd per unit of strain shift (0.005 = 0.5 %)", 0, 1),
    }

    def __init__(self, params: Mapping[str, Any], ctx: Context) -> None:
        super().__init__(params, ctx)
        self.stream = self.rng()

    def process(self, wl_nm: np.ndarray, signal_nm: np.ndarray) -> np.ndarray:
        """Add noise to (n, 5) wavelengths; ``signal_nm`` (n, 5) is the strain shift."""
        z = self.stream.standard_normal(wl_nm.shape)
        sd_nm = self.p["sigma_pm"] * 1e-3 + self.p["relative"] * np.abs(signal_nm)
        return wl_nm + sd_nm * z


class Quantization(Effect):
    """Interrogator resolution: reported peaks are multiples of ``step_pm``."""

    name = "quantization"
    summary = "interrogator resolution"
    params = {
        "step_pm": Param("float", 1.0, "wavelength resolution, pm", 0, 1000, lo_open=True),
    }

    def process(self, wl_nm: np.ndarray) -> np.ndarray:
        step = self.p["step_pm"]
        return np.round(wl_nm * (1000.0 / step)) * (step / 1000.0)


class Dropout(Effect):
    """Lost or garbled samples on the interrogator link, in bursts. Wavelengths are left as
    they are; the ``dropout`` extra column marks each sample (0 ok, 1 lost, 2 garbled) so a
    serial emulator can produce the real line faults."""

    name = "dropout"
    summary = "lost or garbled samples, flagged in the 'dropout' column"
    params = {
        "rate": Param("float", 2e-4, "probability that a fault burst starts at a sample", 0, 0.5),
        "burst_mean_samples": Param("float", 2.0, "mean burst length, samples", 1, 1000),
        "garbled_fraction": Param("float", 0.3, "fraction of bursts that are garbled (not lost)", 0, 1),
    }

    def __init__(self, params: Mapping[str, Any], ctx: Context) -> None:
        super().__init__(params, ctx)
        self.stream = self.rng()
        self.remaining = 0
        self.kind = DROPOUT_OK

    def process(self, n: int) -> np.ndarray:
        """Flags (n,) int8 for the next ``n`` samples; bursts continue across calls."""
        u = self.stream.random((n, 3))  # start?, burst length, kind: always 3 draws per sample
        flags = np.zeros(n, dtype=np.int8)
        p_continue = 1.0 - 1.0 / self.p["burst_mean_samples"]
        starts = np.flatnonzero(u[:, 0] < self.p["rate"])
        k = 0
        while k < n:
            if self.remaining > 0:
                take = min(self.remaining, n - k)
                flags[k:k + take] = self.kind
                self.remaining -= take
                k += take
                continue
            i = int(np.searchsorted(starts, k))  # a start inside a burst is part of that burst
            if i == starts.size:
                break
            nxt = int(starts[i])
            length = 1 if p_continue <= 0 else 1 + int(math.log(max(u[nxt, 1], 1e-300))
                                                        / math.log(p_continue))
            self.kind = DROPOUT_GARBLED if u[nxt, 2] < self.p["garbled_fraction"] else DROPOUT_LOST
            self.remaining = length
            k = nxt
        return flags


#: Every effect by name, in the order they act.
EFFECT_ORDER = ("tolerance", "edge_contact", "friction_hysteresis", "viscoelastic", "dynamics",
                "temperature", "noise", "quantization", "dropout")
EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in (
    Tolerance, EdgeContact, FrictionHysteresis, Viscoelastic, Dynamics, Temperature, Noise,
    Quantization, Dropout)}
assert tuple(EFFECTS) == EFFECT_ORDER
#: Former effect names still accepted in scene files and effect mappings: ``hysteresis`` was
#: the viscoelastic lag before the rate-independent loop got its own effect.
RENAMED_EFFECTS = {"hysteresis": "viscoelastic"}


def canonical_effect_name(name: str) -> str:
    """The current name of an effect (a former name maps to its successor)."""
    return RENAMED_EFFECTS.get(name, name)
