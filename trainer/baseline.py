"""Model-based estimator (paper §II-C): beam strains -> beam forces -> force and torque balance.

Each strain grating ``j`` sits at the root of a beam that carries the share ``F_j`` of the
normal force the rigid pad passes to support ``j`` at ``(x_j, y_j)``; eq. (5) makes the root
strain linear in ``F_j`` and eq. (6) the Bragg shift linear in the strain, so the compensated
shift is ``s_j = g_j F_j`` with a per-beam sensitivity ``g_j`` (pm/N). Inverting::

    F_j = s_j / g_j                     (beam forces)
    F   = sum_j F_j                     (force equilibrium)
    x   = sum_j F_j x_j / F,  y likewise  (torque equilibrium about the origin)

Two parameter sets:

- **nominal**: ``g_j`` and ``(x_j, y_j)`` from the design constants in :mod:`fbgforce.geometry`
  (what the paper did);
- **fitted**: the same model with ``a_j = 1/g_j`` and ``a_j x_j``, ``a_j y_j`` found by linear
  least squares on calibration data (``F ~ a.s``, ``F x ~ b.s``, ``F y ~ c.s``).

Contact is declared when the estimated force exceeds a threshold set from contact-free
training samples (99.5th percentile of the estimate there).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbgforce.errors import InputError
from fbgforce.units import gate_outputs

CONTACT_QUANTILE = 99.5


@dataclass
class BeamModel:
    """Linear beam model: per-beam sensitivity and support positions.

    Attributes
    ----------
    sensitivity_pm_per_N
        (4,) compensated shift of grating ``j`` per newton carried by beam ``j``.
    support_xy_mm
        (4, 2) support (beam) positions in the pad frame.
    pad_mm
        (x, y) size of the sensing area, to clip location estimates.
    contact_threshold_N
        Estimated force above which the model declares contact.
    kind
        ``"nominal"`` or ``"fitted"``.
    clip
        Clip locations to the pad. Off by default: the paper's model-based estimate is the
        plain equilibrium solution, and clipping would hide how wrong it can be.
    """

    sensitivity_pm_per_N: np.ndarray
    support_xy_mm: np.ndarray
    pad_mm: tuple[float, float]
    contact_threshold_N: float = 0.5
    kind: str = "nominal"
    clip: bool = False
    info: dict[str, Any] = field(default_factory=dict)

    def beam_forces(self, shift_pm: np.ndarray) -> np.ndarray:
        """(n, 4) beam forces from compensated shifts (n, 4) in pm."""
        return np.asarray(shift_pm, dtype=np.float64) / self.sensitivity_pm_per_N

    def predict(self, shift_pm: np.ndarray) -> dict[str, np.ndarray]:
        """Contact, force and location from compensated (and optionally filtered) shifts.

        Returns the keys of :func:`fbgforce.model.floatref.predict_from_features` that the metrics
        read: ``contact``, ``force_N`` (0 where no contact), ``x_mm``/``y_mm`` (NaN there),
        plus ``force_raw_N``.
        """
        fj = self.beam_forces(shift_pm)
        force = fj.sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = fj @ self.support_xy_mm[:, 0] / force
            y = fj @ self.support_xy_mm[:, 1] / force
        x = np.nan_to_num(x, nan=self.pad_mm[0] / 2, posinf=self.pad_mm[0], neginf=0.0)
        y = np.nan_to_num(y, nan=self.pad_mm[1] / 2, posinf=self.pad_mm[1], neginf=0.0)
        if self.clip:
            x = np.clip(x, 0.0, self.pad_mm[0])
            y = np.clip(y, 0.0, self.pad_mm[1])
        contact = force > self.contact_threshold_N
        force_N, x_mm, y_mm = gate_outputs(contact, force, x, y)
        return {"contact": contact, "p_contact": contact.astype(np.float64),
                "force_N": force_N, "x_mm": x_mm, "y_mm": y_mm, "force_raw_N": force}

    def set_threshold(self, shift_pm_free: np.ndarray) -> None:
        """Contact threshold from contact-free samples' force estimates."""
        if shift_pm_free.shape[0]:
            est = self.beam_forces(shift_pm_free).sum(axis=1)
            self.contact_threshold_N = float(max(np.percentile(est, CONTACT_QUANTILE), 1e-3))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "sensitivity_pm_per_N": self.sensitivity_pm_per_N.tolist(),
                "support_xy_mm": self.support_xy_mm.tolist(), "pad_mm": list(self.pad_mm),
                "contact_threshold_N": self.contact_threshold_N, **self.info}


def nominal(base_wl_nm: np.ndarray | None = None) -> BeamModel:
    """The beam model from the nominal design constants of :mod:`fbgforce.geometry`.

    Parameters
    ----------
    base_wl_nm
        (5,) the device's unloaded wavelengths (its tare), if known: eq. (6) scales each
        grating's shift with its own Bragg wavelength, which a design sheet would also give.
        Default: the nominal design's.
    """
    from fbgforce import geometry as g

    design = g.NOMINAL if base_wl_nm is None else g.NOMINAL.replace(base_wl_nm=base_wl_nm)
    sens = 1000.0 * design.shift_per_newton_nm()
    pad = (float(g.PAD_SIZE_MM[0]), float(g.PAD_SIZE_MM[1]))
    return BeamModel(sens, design.supports_mm.copy(), pad, kind="nominal")


def fit(shift_pm: np.ndarray, force_N: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray,
        pad_mm: tuple[float, float] | None = None) -> BeamModel:
    """Fit per-beam sensitivity and support positions by linear least squares.

    Parameters
    ----------
    shift_pm
        (n, 4) compensated shifts of true-contact calibration samples.
    force_N, x_mm, y_mm
        Their ground truth.
    """
    s = np.asarray(shift_pm, dtype=np.float64)
    f = np.asarray(force_N, dtype=np.float64)
    ok = np.isfinite(x_mm) & np.isfinite(y_mm) & np.isfinite(f)
    s, f, x, y = s[ok], f[ok], np.asarray(x_mm)[ok], np.asarray(y_mm)[ok]
    if s.shape[0] < 8:
        raise InputError("too few contact samples to fit the model-based baseline")
    targets = np.column_stack([f, f * x, f * y])
    coef, *_ = np.linalg.lstsq(s, targets, rcond=None)
    a, b, c = coef[:, 0], coef[:, 1], coef[:, 2]
    # A beam whose fitted compliance is ~0 carries no information; keep it finite.
    a_safe = np.where(np.abs(a) < 1e-9, 1e-9, a)
    supports = np.column_stack([b / a_safe, c / a_safe])
    if pad_mm is None:
        from fbgforce import geometry as g

        pad_mm = (float(g.PAD_SIZE_MM[0]), float(g.PAD_SIZE_MM[1]))
    return BeamModel(1.0 / a_safe, supports, pad_mm, kind="fitted")
