"""Nominal design of the fingertip and its analytic force/strain/wavelength model.

The trainer's model-based baseline and the simulator both use this module, so the forward
model the simulator runs and the inverse the baseline applies are the same mathematics
(the simulator perturbs a :class:`Design` for a real device; see ``fbgforce.sim``).

Mechanics (paper §II). A rigid pad rests on four elastic supports, the tips of four
cantilever beams. Pad frame: origin at the top-left corner of the sensing area, x right, y
down, mm. Beams / gratings are numbered clockwise from the top-left corner::

    FBG1 (top-left)      FBG2 (top-right)
    FBG4 (bottom-left)   FBG3 (bottom-right)

A normal force ``F`` at ``(x, y)`` loads support ``i`` with ``F_i``. Statics gives three
equations (sum of forces, moments about x and y) for four unknowns; a rigid pad on springs of
stiffness ``k_i`` settles on a plane, ``F_i = k_i (a + b x_i + c y_i)``, which with equal
stiffness is exactly the least-norm solution. The inverse needs no stiffness at all:
``F = sum F_i``, ``x = sum F_i x_i / F``, ``y = sum F_i y_i / F``.

Beam-root strain, eq. (5): ``eps = -F_i l h / (E I)`` with ``I = c (2h)^3 / 12`` (the sign:
the gratings sit on the compressed side, so wavelengths fall under load). Bragg shift,
eq. (6): ``d_lambda = lambda_0 (1 - p_e) eps``.

Sensitivity arithmetic (the issue's "1.5 N ≈ 10 µε ≈ 10 pm"): with l = 6 mm, c = 3 mm,
2h = 1.5 mm, E = 193 GPa (stainless steel), I = 3 * 1.5^3 / 12 = 0.84375 mm^4 and
l h / (E I) = 6 * 0.75 / (193000 * 0.84375) = 27.6 µε per newton on one beam. A centred
1.5 N load puts 0.375 N on each beam: 10.4 µε, and at 1546 nm with p_e = 0.22 a shift of
1546 * 0.78 * 10.4e-6 = 12.5 pm. At 70 N centred: 483 µε, 0.58 nm per grating; 70 N right
over one support: about 2 nm, well inside the 8 nm spacing of the base wavelengths.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

#: Sensing area of the pad, mm (x, y); the paper's percentage errors imply about 21 x 27 mm.
PAD_SIZE_MM = (21.0, 27.0)
#: Support (beam tip contact) centres in the pad frame, mm, rows = FBG1..4 (clockwise from
#: top-left). Inset from the pad edge: loads outside this rectangle tilt the pad and unload
#: the far supports (negative F_i), which is what makes the boundary hard.
SUPPORTS_MM = np.array([[2.5, 2.5], [18.5, 2.5], [18.5, 24.5], [2.5, 24.5]])
#: Cantilever dimensions, mm: free length l, width c, thickness 2h.
BEAM_LENGTH_MM = 6.0
BEAM_WIDTH_MM = 3.0
BEAM_THICKNESS_MM = 1.5
#: Young's modulus of stainless steel, N/mm^2 (MPa).
YOUNG_MODULUS_MPA = 193_000.0
#: Strain-optic coefficient p_e of silica fibre.
P_E = 0.22
#: Unloaded Bragg wavelengths of FBG1..4 and T at the reference temperature, nm.
BASE_WL_NM = np.array([1530.0, 1538.0, 1546.0, 1554.0, 1562.0])
#: Effective thermal coefficient of a grating bonded to steel, per K (thermo-optic plus
#: thermal expansion of fibre and substrate): about 18.6 pm/K at 1550 nm.
THERMAL_COEFF_PER_K = 1.2e-5
#: Number of strain gratings.
N_BEAMS = 4


def beam_inertia_mm4(width_mm: float = BEAM_WIDTH_MM, thickness_mm: float = BEAM_THICKNESS_MM) -> float:
    """Second moment of area ``I = c (2h)^3 / 12`` of the beam section, mm^4."""
    return width_mm * thickness_mm**3 / 12.0


def strain_per_newton(length_mm: float = BEAM_LENGTH_MM, width_mm: float = BEAM_WIDTH_MM,
                      thickness_mm: float = BEAM_THICKNESS_MM,
                      young_mpa: float = YOUNG_MODULUS_MPA) -> float:
    """Magnitude of the root surface strain per newton on one beam, eq. (5) at x = l, z = -h."""
    h = thickness_mm / 2.0
    return length_mm * h / (young_mpa * beam_inertia_mm4(width_mm, thickness_mm))


#: Root strain per newton on one beam (≈ 2.76e-5, i.e. 27.6 µε/N).
STRAIN_PER_N = strain_per_newton()


@dataclass(frozen=True)
class Design:
    """Parameters of one end-effector: the nominal design or a real (toleranced) device.

    Attributes
    ----------
    supports_mm
        (4, 2) support positions in the pad frame.
    stiffness
        (4,) relative support stiffness (only the ratios matter).
    gain
        (4,) strain actually seen by each grating per unit of nominal root strain (beam
        dimension errors times the strain transfer of the adhesive bond; 1 = nominal).
    base_wl_nm
        (5,) unloaded wavelengths of FBG1..4 and T.
    strain_per_N
        Nominal root strain per newton of beam force.
    p_e
        Strain-optic coefficient.
    """

    supports_mm: np.ndarray = field(default_factory=lambda: SUPPORTS_MM.copy())
    stiffness: np.ndarray = field(default_factory=lambda: np.ones(N_BEAMS))
    gain: np.ndarray = field(default_factory=lambda: np.ones(N_BEAMS))
    base_wl_nm: np.ndarray = field(default_factory=lambda: BASE_WL_NM.copy())
    strain_per_N: float = STRAIN_PER_N
    p_e: float = P_E

    def __post_init__(self) -> None:
        object.__setattr__(self, "supports_mm", np.asarray(self.supports_mm, float).reshape(N_BEAMS, 2))
        object.__setattr__(self, "stiffness", np.asarray(self.stiffness, float).reshape(N_BEAMS))
        object.__setattr__(self, "gain", np.asarray(self.gain, float).reshape(N_BEAMS))
        object.__setattr__(self, "base_wl_nm", np.asarray(self.base_wl_nm, float).reshape(N_BEAMS + 1))
        if np.any(self.stiffness <= 0):
            raise ValueError("support stiffness must be positive")

    def replace(self, **changes: object) -> "Design":
        """A copy with some fields changed."""
        return replace(self, **changes)

    # ---------------------------------------------------------------- forward
    @cached_property
    def _split(self) -> np.ndarray:
        # Cached: a closed loop calls beam_forces once per 1 kHz sample.
        a = np.vstack([np.ones(N_BEAMS), self.supports_mm[:, 0], self.supports_mm[:, 1]])
        k = np.diag(self.stiffness)
        return k @ a.T @ np.linalg.inv(a @ k @ a.T)

    def split_matrix(self) -> np.ndarray:
        """(4, 3) matrix ``C`` with beam forces ``F_i = F * (C[i,0] + C[i,1] x + C[i,2] y)``.

        From ``F_i = k_i (a + b x_i + c y_i)`` and the three equilibrium equations
        ``A F_vec = F [1, x, y]`` with ``A = [1; x_i; y_i]``: ``C = K A^T (A K A^T)^-1``.
        """
        return self._split.copy()

    def beam_forces(self, force_N: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """(n, 4) support forces for normal forces ``force_N`` at ``(x_mm, y_mm)``."""
        f = np.asarray(force_N, float).reshape(-1, 1)
        c = self._split
        x = np.asarray(x_mm, float).reshape(-1, 1)
        y = np.asarray(y_mm, float).reshape(-1, 1)
        return f * (c[:, 0] + c[:, 1] * x + c[:, 2] * y)

    def shift_per_newton_nm(self) -> np.ndarray:
        """(4,) wavelength shift per newton of beam force, nm (negative: compression)."""
        return -self.base_wl_nm[:N_BEAMS] * (1.0 - self.p_e) * self.strain_per_N * self.gain

    def wavelengths(self, beam_forces: np.ndarray) -> np.ndarray:
        """(n, 5) wavelengths for (n, 4) beam forces (T grating unstrained), eqs. (5)-(6)."""
        bf = np.asarray(beam_forces, float)
        wl = np.empty((bf.shape[0], N_BEAMS + 1))
        wl[:, :N_BEAMS] = self.base_wl_nm[:N_BEAMS] + bf * self.shift_per_newton_nm()
        wl[:, N_BEAMS] = self.base_wl_nm[N_BEAMS]
        return wl

    def forward(self, force_N: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """(n, 5) wavelengths for a normal force at a location (no noise, no temperature)."""
        return self.wavelengths(self.beam_forces(force_N, x_mm, y_mm))

    # ---------------------------------------------------------------- inverse
    def beam_forces_from_shift_pm(self, shift_pm: np.ndarray) -> np.ndarray:
        """(n, 4) beam forces from tared, temperature-compensated shifts of FBG1..4 in pm."""
        return np.asarray(shift_pm, float) / (1000.0 * self.shift_per_newton_nm())

    def locate(self, beam_forces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Total force and its location from (n, 4) beam forces by force/moment balance.

        Returns ``(force_N, x_mm, y_mm)``; x and y are NaN where the total force is 0.
        """
        bf = np.asarray(beam_forces, float)
        total = bf.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            x = (bf @ self.supports_mm[:, 0]) / total
            y = (bf @ self.supports_mm[:, 1]) / total
        zero = total == 0
        x[zero] = np.nan
        y[zero] = np.nan
        return total, x, y

    def inverse_shift(self, shift_pm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(force_N, x_mm, y_mm)`` from (n, 4) compensated shifts in pm."""
        return self.locate(self.beam_forces_from_shift_pm(shift_pm))

    def inverse(self, wl_nm: np.ndarray, baseline_nm: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(force_N, x_mm, y_mm)`` from (n, 5) wavelengths, tared against ``baseline_nm``
        (default: this design's base wavelengths). The T grating is not used (no temperature
        compensation here: see ``fbgforce.model.floatref.compensate`` for that step)."""
        wl = np.asarray(wl_nm, float)
        base = self.base_wl_nm if baseline_nm is None else np.asarray(baseline_nm, float)
        shift_pm = (wl[:, :N_BEAMS] - base[:N_BEAMS]) * 1000.0
        return self.inverse_shift(shift_pm)


#: The nominal design every device is a perturbation of.
NOMINAL = Design()


def forward_nominal(force_N: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """Wavelengths of the nominal design, see :meth:`Design.forward`."""
    return NOMINAL.forward(force_N, x_mm, y_mm)


def inverse_nominal(wl_nm: np.ndarray, baseline_nm: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Force and location through the nominal model, see :meth:`Design.inverse`."""
    return NOMINAL.inverse(wl_nm, baseline_nm)
