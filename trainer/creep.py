"""The pad's creep as the trainer models it: a standard linear solid (:class:`Creep`).

The fit that finds it on a calibration is :mod:`fbgforce.trainer.creep_fit`; whether the
calibration establishes it, :mod:`fbgforce.trainer.creep_evidence`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Creep:
    """The pad's viscoelastic creep as a standard linear solid: the beams carry
    ``F + magnitude * (lag(F) - F)``, ``lag`` a first-order lag of the load with
    ``time_constant_s`` (0, 0: none found)."""

    magnitude: float = 0.0
    time_constant_s: float = 0.0

    def lag(self, force_N: np.ndarray, rate_hz: float) -> np.ndarray:
        """The first-order lag of ``force_N`` (one recording) at ``rate_hz``."""
        a = 1.0 - np.exp(-1.0 / (rate_hz * self.time_constant_s))
        out = np.empty(len(force_N))
        state = 0.0
        for k, f in enumerate(np.asarray(force_N, float).tolist()):
            state += a * (f - state)
            out[k] = state
        return out

    def still_to_come(self, force_N: np.ndarray, at: np.ndarray, rate_hz: float) -> np.ndarray:
        """At samples ``at`` of a recording: how much more the beams would carry if the load
        stood still from there on, relative to what they carry (``m (F - lag) / (F + m (lag
        - F))``; 0 without creep)."""
        if self.magnitude <= 0:
            return np.zeros(len(at))
        f, lag = force_N[at], self.lag(force_N, rate_hz)[at]
        carried = f + self.magnitude * (lag - f)
        return self.magnitude * (f - lag) / np.maximum(carried, 1e-9)

    def settling(self, n: int, rate_hz: float) -> np.ndarray:
        """``1 - exp(-k / (tau rate))`` for ``k = 0 .. n-1``: how far the creep has run ``k``
        samples into a hold (1 without creep)."""
        if self.magnitude <= 0:
            return np.ones(n)
        return 1.0 - np.exp(-np.arange(n) / (self.time_constant_s * rate_hz))
