"""What happens to the fingertip: a scene's schedule turned into per-sample ground truth.

The schedule's random draws (press locations, peak forces, impulses) come from a stream
derived from the scene seed and the name ``"schedule"`` only, not from the device: two
devices under the same seed see the same protocol (the same x-y-z stage program).
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field

import numpy as np

from fbgforce.geometry import PAD_SIZE_MM
from fbgforce.sim.scene import Scene


@dataclass
class Schedule:
    """Per-sample inputs to the end-effector and the ground truth that goes into the dataset.

    ``force_N``, ``x_mm``, ``y_mm``, ``impulse_Ns``, ``impulse_phase`` drive
    :class:`fbgforce.sim.EndEffector` (the location is known wherever a force acts, even
    below the contact threshold). ``truth_force_N`` is what the load cell reports (the mean
    force over the sample, impacts included); ``contact`` is ``truth_force_N > threshold``.
    """

    t_s: np.ndarray
    force_N: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    impulse_Ns: np.ndarray
    impulse_phase: np.ndarray
    press_id: np.ndarray
    truth_force_N: np.ndarray
    contact: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_s.size)


def schedule_rng(seed: int) -> np.random.Generator:
    """The schedule's stream: ``SeedSequence(seed, spawn_key=(crc32("schedule"),))``."""
    key = zlib.crc32(b"schedule")
    return np.random.default_rng(np.random.SeedSequence(entropy=int(seed), spawn_key=(key,)))


def sample_locations(rng: np.random.Generator, n: int, region: str, margin_mm: float,
                     band_mm: float) -> np.ndarray:
    """(n, 2) uniform random points on the pad: anywhere (``"pad"``, at least ``margin_mm``
    inside the edge), in the ``"interior"`` (at least ``band_mm`` inside) or in the
    ``"boundary"`` band (between ``margin_mm`` and ``band_mm`` from the nearest edge)."""
    w, h = PAD_SIZE_MM
    if region == "interior":
        lo = band_mm
        return np.column_stack([rng.uniform(lo, w - lo, n), rng.uniform(lo, h - lo, n)])
    if region == "pad":
        return np.column_stack([rng.uniform(margin_mm, w - margin_mm, n),
                                rng.uniform(margin_mm, h - margin_mm, n)])
    out = np.empty((0, 2))
    while out.shape[0] < n:  # rejection sampling from the margin-trimmed pad
        p = np.column_stack([rng.uniform(margin_mm, w - margin_mm, 4 * n),
                             rng.uniform(margin_mm, h - margin_mm, 4 * n)])
        edge = np.minimum.reduce([p[:, 0], w - p[:, 0], p[:, 1], h - p[:, 1]])
        out = np.vstack([out, p[edge < band_mm]])
    return out[:n]


def _shape(profile: str, s: np.ndarray) -> np.ndarray:
    if profile == "hertz":
        return s**1.5
    if profile == "cosine":
        return 0.5 - 0.5 * np.cos(np.pi * s)
    return s


def _samples(seconds: float, rate: float) -> int:
    return int(round(seconds * rate))


def _press_variety(s: dict, rng: np.random.Generator, n_p: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Per press: the hold (s) and the factor on the loading and unloading times.

    Drawn after the peaks and locations, and only for the keys a scene sets, so a scene with
    one hold and one speed for every press keeps its presses draw for draw."""
    hold = np.full(n_p, s["hold_s"])
    if s["hold_max_s"] > s["hold_s"]:
        hold = rng.uniform(s["hold_s"], s["hold_max_s"], n_p)
    if s["hold_fraction"] < 1.0:
        hold = np.where(rng.random(n_p) < s["hold_fraction"], hold, 0.0)
    speed = np.ones(n_p)
    if s["speed_spread"] > 1.0:
        spread = math.log(s["speed_spread"])
        speed = np.exp(rng.uniform(-spread, spread, n_p))
    return hold, speed


def _press_template(s: dict, rate: float, hold_s: float, time_factor: float) -> np.ndarray:
    """One press's force relative to its peak: rest, load, hold at the peak, unload."""
    n_rest = _samples(s["rest_s"], rate)
    n_load = max(1, _samples(s["load_s"] * time_factor, rate))
    n_unload = max(1, _samples(s["unload_s"] * time_factor, rate))
    ramp_up = _shape(s["profile"], np.arange(1, n_load + 1) / n_load)
    ramp_down = _shape(s["profile"], 1.0 - np.arange(1, n_unload + 1) / n_unload)
    return np.concatenate([np.zeros(n_rest), ramp_up, np.ones(_samples(hold_s, rate)), ramp_down])


def build_schedule(scene: Scene) -> Schedule:
    """Per-sample schedule of a scene (see the module and ``docs/simulator.md``)."""
    s = scene.schedule
    rate = scene.sample_rate_hz
    rng = schedule_rng(scene.seed)
    kind = s["kind"]
    extra: dict[str, np.ndarray] = {}
    if kind == "presses":
        n_p = s["n_presses"]
        if s["force_distribution"] == "loguniform":
            peaks = np.exp(rng.uniform(math.log(s["force_min_N"]), math.log(s["force_max_N"]), n_p))
        else:
            peaks = rng.uniform(s["force_min_N"], s["force_max_N"], n_p)
        loc = sample_locations(rng, n_p, s["region"], s["margin_mm"], s["band_mm"])
        templates = [_press_template(s, rate, hold, speed)
                     for hold, speed in zip(*_press_variety(s, rng, n_p))]
        per = np.array([t.size for t in templates])
        force = np.concatenate([p * t for p, t in zip(peaks, templates)])
        loaded = np.concatenate(templates) > 0
        x = np.where(loaded, np.repeat(loc[:, 0], per), np.nan)
        y = np.where(loaded, np.repeat(loc[:, 1], per), np.nan)
        press = np.repeat(np.arange(n_p, dtype=np.int64), per)
        impulse = np.zeros(force.size)
        phase = np.zeros(force.size)
    elif kind == "rest":
        n = max(1, _samples(s["duration_s"], rate))
        force, impulse, phase = np.zeros(n), np.zeros(n), np.zeros(n)
        x = np.full(n, np.nan)
        y = np.full(n, np.nan)
        press = np.zeros(n, dtype=np.int64)
    elif kind == "impacts":
        n_i = s["n_impacts"]
        per = max(2, _samples(s["interval_s"], rate))
        at = per // 3
        j = rng.uniform(s["impulse_min_Ns"], s["impulse_max_Ns"], n_i)
        ph = rng.random(n_i)
        loc = sample_locations(rng, n_i, s["region"], s["margin_mm"], s["band_mm"])
        n = n_i * per
        idx = np.arange(n_i) * per + at
        force = np.zeros(n)
        impulse = np.zeros(n)
        impulse[idx] = j
        phase = np.zeros(n)
        phase[idx] = ph
        x = np.full(n, np.nan)
        y = np.full(n, np.nan)
        x[idx], y[idx] = loc[:, 0], loc[:, 1]
        press = np.repeat(np.arange(n_i, dtype=np.int64), per)
        extra["impulse_Ns"] = impulse
    else:  # pragma: no cover - the scene validator only admits the kinds above
        raise ValueError(f"unknown schedule kind {kind!r}")

    n_lead, n_tail = _samples(s["lead_in_s"], rate), _samples(s["tail_s"], rate)
    if n_lead or n_tail:
        def pad(a: np.ndarray, fill: float) -> np.ndarray:
            return np.concatenate([np.full(n_lead, fill, dtype=a.dtype), a,
                                   np.full(n_tail, fill, dtype=a.dtype)])
        force, impulse, phase = pad(force, 0.0), pad(impulse, 0.0), pad(phase, 0.0)
        x, y = pad(x, np.nan), pad(y, np.nan)
        press = np.concatenate([np.full(n_lead, press[0]), press, np.full(n_tail, press[-1])])
        extra = {k: pad(v, 0.0) for k, v in extra.items()}
    n = force.size
    t = np.arange(n) / rate
    truth = force + impulse * rate
    contact = truth > s["contact_threshold_N"]
    return Schedule(t_s=t, force_N=force, x_mm=x, y_mm=y, impulse_Ns=impulse,
                    impulse_phase=phase, press_id=press, truth_force_N=truth, contact=contact,
                    extra=extra)
