"""The simulated end-effector: applied load in, five peak wavelengths out, sample by sample.

:class:`EndEffector` keeps every effect's state (pad friction and lag, vibration, temperature
walk, random streams, dropout bursts) between calls, so a controller can drive it in blocks of
any size and get exactly (bit for bit) what one call over the whole recording would give.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from fbgforce.errors import InputError
from fbgforce.geometry import NOMINAL, PAD_SIZE_MM, Design
from fbgforce.sim.effects import EFFECT_ORDER, EFFECTS, Context, Effect, canonical_effect_name
from fbgforce.sim.params import check_params
from fbgforce.sim.scene import Scene, load_scene


class EndEffector:
    """A (possibly imperfect) fingertip under a chosen set of effects.

    Parameters
    ----------
    scene_or_effects
        A :class:`Scene`, a scene name or path (its effects, seed, device and rate are used
        unless overridden), a mapping ``{effect name: {param: value}}`` (defaults filled in),
        or None for the ideal device.
    seed, device
        Random-stream seed and device number (default: the scene's, else 0).
    rate_hz
        Sample rate of the calls to :meth:`process` (default: the scene's, else 1000 Hz).

    Attributes
    ----------
    design
        The device's :class:`fbgforce.geometry.Design` (nominal unless ``tolerance`` applies).
    effects
        The active effect components by name, in :data:`EFFECT_ORDER`.
    """

    def __init__(self, scene_or_effects: Scene | str | Path | Mapping[str, Mapping[str, Any]] | None = None,
                 seed: int | None = None, device: int | None = None,
                 rate_hz: float | None = None) -> None:
        if isinstance(scene_or_effects, (Scene, str, Path)):
            scene = load_scene(scene_or_effects)
            effects = scene.effects
            seed = scene.seed if seed is None else seed
            device = scene.device if device is None else device
            rate_hz = scene.sample_rate_hz if rate_hz is None else rate_hz
        else:
            effects = {}
            for given, params in dict(scene_or_effects or {}).items():
                name = canonical_effect_name(given)
                if name not in EFFECTS or name in effects:
                    raise InputError(f"unknown or repeated effect; allowed effects: "
                                     f"{', '.join(EFFECT_ORDER)}", column=f"effects.{given}")
                effects[name] = check_params(params, EFFECTS[name].params, path=None,
                                             key_path=f"effects.{name}")
        self.ctx = Context(seed=int(seed or 0), device=int(device or 0),
                           rate_hz=float(rate_hz or 1000.0))
        self.effects: dict[str, Effect] = {
            name: EFFECTS[name](effects[name], self.ctx) for name in EFFECT_ORDER if name in effects}
        design = NOMINAL
        if "tolerance" in self.effects:
            design = self.effects["tolerance"].apply(design)  # type: ignore[attr-defined]
        self.design: Design = design
        self.n_processed = 0

    def _pad(self, beam_forces: np.ndarray) -> np.ndarray:
        """Beam forces after the rubber pad (friction loop, then viscoelastic lag)."""
        for name in ("friction_hysteresis", "viscoelastic"):
            if name in self.effects:
                beam_forces = self.effects[name].process(beam_forces)  # type: ignore[attr-defined]
        return beam_forces

    @property
    def rate_hz(self) -> float:
        return self.ctx.rate_hz

    def process(self, t_s: np.ndarray, force_N: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray,
                contact: np.ndarray | None = None, impulse_Ns: np.ndarray | None = None,
                impulse_phase: np.ndarray | None = None) -> np.ndarray:
        """Wavelengths (n, 5), nm, for the next ``n`` samples. See :meth:`process_with_extras`."""
        return self.process_with_extras(t_s, force_N, x_mm, y_mm, contact, impulse_Ns,
                                        impulse_phase)[0]

    def process_with_extras(self, t_s: np.ndarray, force_N: np.ndarray, x_mm: np.ndarray,
                            y_mm: np.ndarray, contact: np.ndarray | None = None,
                            impulse_Ns: np.ndarray | None = None,
                            impulse_phase: np.ndarray | None = None
                            ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Advance by ``n`` samples (at :attr:`rate_hz`, consecutive with earlier calls).

        Parameters
        ----------
        t_s
            (n,) sample times, s (used by the temperature history).
        force_N
            (n,) normal force on the pad, N (the quasi-static load).
        x_mm, y_mm
            (n,) load location in the pad frame; may be NaN only where no force acts.
        contact
            Accepted for symmetry with the dataset and ignored: the physics follows the force.
        impulse_Ns
            (n,) impacts: impulse delivered during each sample interval, N s (a tap shorter
            than a sample). Without the ``dynamics`` effect it acts as its mean force
            ``impulse * rate`` over that sample.
        impulse_phase
            (n,) when within the interval before the sample the impulse arrives, as a fraction
            of the interval from its end (default 0.5).

        Returns
        -------
        (wl_nm, extras)
            ``wl_nm`` (n, 5); ``extras`` holds ``temperature_K`` (with ``temperature``) and
            ``dropout`` flags (with ``dropout``).
        """
        t, f, x, y, j = _checked_inputs(t_s, force_N, x_mm, y_mm, contact, impulse_Ns)
        wl, extras = self._readout(self._beam_forces(f, x, y, j, impulse_phase), t)
        self.n_processed += t.size
        return wl, extras

    def _beam_forces(self, f: np.ndarray, x: np.ndarray, y: np.ndarray, j: np.ndarray,
                     impulse_phase: np.ndarray | None) -> np.ndarray:
        """The beams' forces (n, 5) under the load as the pad passes it on: where an edge
        contact moves the load, then the pad's friction and lag, then (with ``dynamics``) the
        mass-spring response with the impulses kicked in at their phase; without ``dynamics``
        an impulse acts as its mean force over its sample."""
        fx = self.effects
        if "edge_contact" in fx:
            x, y = fx["edge_contact"].location(x, y)  # type: ignore[attr-defined]
        design = self.design
        if "dynamics" not in fx:
            load = f + j * self.ctx.rate_hz if np.any(j) else f
            return self._pad(design.beam_forces(load, x, y))
        bf = self._pad(design.beam_forces(f, x, y))
        dyn = fx["dynamics"]
        kicks = design.beam_forces(j, x, y) if np.any(j) else None
        steps = None
        if kicks is not None:
            ph = (np.full(j.size, 0.5) if impulse_phase is None
                  else np.asarray(impulse_phase, float).reshape(-1))
            steps = np.minimum((dyn.substeps * (1.0 - ph)).astype(int),  # type: ignore[attr-defined]
                               dyn.substeps - 1)  # type: ignore[attr-defined]
        return dyn.process(bf, kicks, steps)  # type: ignore[attr-defined]

    def _readout(self, bf: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The wavelengths the interrogator reports for the beams' forces: the gratings'
        response, then temperature, noise (scaled by the strain signal), quantisation and
        dropout, in that order, and the extras the temperature and dropout effects report."""
        fx = self.effects
        design = self.design
        extras: dict[str, np.ndarray] = {}
        wl = design.wavelengths(bf)
        signal = wl - design.base_wl_nm
        if "temperature" in fx:
            temp = fx["temperature"]
            dT = temp.delta_T(t)  # type: ignore[attr-defined]
            wl = wl + temp.shift_nm(design, dT)  # type: ignore[attr-defined]
            extras["temperature_K"] = dT
        if "noise" in fx:
            wl = fx["noise"].process(wl, signal)  # type: ignore[attr-defined]
        if "quantization" in fx:
            wl = fx["quantization"].process(wl)  # type: ignore[attr-defined]
        if "dropout" in fx:
            extras["dropout"] = fx["dropout"].process(t.size)  # type: ignore[attr-defined]
        return wl, extras


def _checked_inputs(t_s: np.ndarray, force_N: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray,
                    contact: np.ndarray | None, impulse_Ns: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The inputs of :meth:`EndEffector.process_with_extras` as flat float arrays (no impulse:
    zeros): refuses arrays of different lengths, a force or impulse that is not finite, and a
    load without a location; an unloaded sample's missing location becomes the pad's centre."""
    t = np.asarray(t_s, float).reshape(-1)
    n = t.size
    f = np.asarray(force_N, float).reshape(-1)
    x = np.asarray(x_mm, float).reshape(-1)
    y = np.asarray(y_mm, float).reshape(-1)
    j = np.zeros(n) if impulse_Ns is None else np.asarray(impulse_Ns, float).reshape(-1)
    for name, a in (("force_N", f), ("x_mm", x), ("y_mm", y), ("impulse_Ns", j)):
        if a.size != n:
            raise ValueError(f"{name} has {a.size} samples, t_s has {n}")
    if contact is not None and np.asarray(contact).size != n:
        raise ValueError(f"contact has {np.asarray(contact).size} samples, t_s has {n}")
    if not np.all(np.isfinite(f)) or not np.all(np.isfinite(j)):
        raise ValueError("force_N and impulse_Ns must be finite")
    located = np.isfinite(x) & np.isfinite(y)
    if np.any(((f != 0) | (j != 0)) & ~located):
        raise ValueError("x_mm/y_mm must be finite wherever a force or impulse acts")
    # Unloaded samples have no location; any point gives zero beam forces.
    x = np.where(located, x, PAD_SIZE_MM[0] / 2)
    y = np.where(located, y, PAD_SIZE_MM[1] / 2)
    return t, f, x, y, j
