"""The calibration protocol a lab runs on its x-y-z stage: a CSV of moves (docs/lab-import.md
"Protocol").

Each row is one press: the stage rests ``rest_s`` off the pad, moves to (``x_mm``,
``y_mm``), loads to ``force_N`` in ``ramp_s``, holds ``hold_s``, and unloads in ``ramp_s``.
The default program covers what a model needs to be robust in use (docs/trainer.md and
docs/teleop.md measured what it lacks otherwise): the whole pad, light touches and the force
range up to 70 N, loading speeds from slow ramps to fast taps, holds of 1.5-6 s beside short
presses, and long rests between groups of presses.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.errors import InputError
from fbgforce.geometry import PAD_SIZE_MM

#: Columns of the program CSV, in order.
COLUMNS = ("move", "group", "x_mm", "y_mm", "force_N", "ramp_s", "hold_s", "rest_s")
#: Loading-time classes: (share of presses, shortest, longest ramp s). Fast taps, the paper's
#: speed and slow ramps.
RAMPS = ((0.25, 0.05, 0.1), (0.45, 0.2, 0.5), (0.30, 1.0, 3.0))
#: Hold classes: (share, shortest, longest s): none, short, long (a grip holds its load).
HOLDS = ((0.45, 0.0, 0.0), (0.25, 0.2, 1.0), (0.30, 1.5, 6.0))
#: Share of light touches, drawn log-uniform in LIGHT_N; the rest uniform up to force_max.
LIGHT_SHARE = 0.15
LIGHT_N = (0.2, 1.0)
#: Rest before each press (>= 0.2 s: the tare window), s; the first press of each group
#: after the first rests GROUP_REST_S.
REST_S = (0.3, 1.0)
GROUP_REST_S = 10.0
#: Distance kept from the pad's edge, mm.
MARGIN_MM = 0.5
#: Printed at the top of the program.
TEMPERATURE_NOTE = ("temperature: if the lab can, let the room or a climate chamber move "
                    "the fingertip's temperature by several kelvin (3-5 K) during the session; "
                    "a model calibrated at one temperature knows only that one")


@dataclass
class Program:
    """A protocol: one row per press (arrays of :data:`COLUMNS`)."""

    group: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    force_N: np.ndarray
    ramp_s: np.ndarray
    hold_s: np.ndarray
    rest_s: np.ndarray

    @property
    def duration_s(self) -> float:
        """The program's length: every rest, ramp (load and unload) and hold."""
        return float(np.sum(self.rest_s + 2 * self.ramp_s + self.hold_s))

    def summary(self) -> dict[str, Any]:
        """What the program covers (the ``--json`` keys of ``fbgforce protocol``)."""
        speed = self.force_N / self.ramp_s
        return {
            "presses": int(self.force_N.size), "groups": int(np.unique(self.group).size),
            "duration_s": self.duration_s,
            "force_N": [float(self.force_N.min()), float(self.force_N.max())],
            "loading_N_per_s": [float(speed.min()), float(speed.max())],
            "holds_1_5_to_6_s": int(((self.hold_s >= 1.5) & (self.hold_s <= 6.0)).sum()),
            "rest_s": float(self.rest_s.sum()),
            "long_rest_s": float(self.rest_s[self.rest_s >= GROUP_REST_S].sum()),
            "temperature_note": TEMPERATURE_NOTE,
        }


def _classes(rng: np.random.Generator, n: int, classes: tuple[tuple[float, float, float], ...]
             ) -> np.ndarray:
    """``n`` values, each class taking its share of the presses (shuffled), uniform within."""
    counts = np.floor(np.array([c[0] for c in classes]) * n).astype(int)
    counts[np.argmax(counts)] += n - counts.sum()
    values = np.concatenate([rng.uniform(lo, hi, k) for (_, lo, hi), k in zip(classes, counts)])
    return rng.permutation(values)


def default_program(n_presses: int = 300, *, force_max_N: float = 70.0, groups: int = 6,
                    seed: int = 0) -> Program:
    """The default protocol (module docstring): locations spread over the pad by a jittered
    grid, peak forces stratified over the range, ramps and holds in the shares of
    :data:`RAMPS` and :data:`HOLDS`, all drawn independently of one another."""
    if n_presses < groups:
        raise InputError(f"need at least {groups} presses, one per group", column="--presses")
    if not 1.0 < force_max_N <= 1000.0:
        raise InputError(f"must be in (1, 1000] N, not {force_max_N}", column="--force-max")
    rng = np.random.default_rng(seed)
    w, h = PAD_SIZE_MM
    nx = max(1, int(round(np.sqrt(n_presses * w / h))))
    ny = max(1, int(np.ceil(n_presses / nx)))
    cells = rng.permutation(nx * ny)[:n_presses]
    span_x, span_y = w - 2 * MARGIN_MM, h - 2 * MARGIN_MM
    x = MARGIN_MM + (cells % nx + rng.random(n_presses)) * span_x / nx
    y = MARGIN_MM + (cells // nx + rng.random(n_presses)) * span_y / ny
    n_light = int(round(LIGHT_SHARE * n_presses))
    light = np.exp(rng.uniform(*np.log(LIGHT_N), n_light))
    # Stratified: one draw in each of n equal slices of the range.
    n_main = n_presses - n_light
    step = (force_max_N - LIGHT_N[1]) / n_main
    main = LIGHT_N[1] + (np.arange(n_main) + rng.random(n_main)) * step
    force = rng.permutation(np.concatenate([light, main]))
    ramp = _classes(rng, n_presses, RAMPS)
    hold = _classes(rng, n_presses, HOLDS)
    rest = rng.uniform(*REST_S, n_presses)
    group = np.minimum(np.arange(n_presses) * groups // n_presses, groups - 1)
    starts = np.flatnonzero(np.diff(group)) + 1
    rest[starts] = GROUP_REST_S
    return Program(group=group, x_mm=x, y_mm=y, force_N=force, ramp_s=ramp, hold_s=hold,
                   rest_s=rest)


def write_program(program: Program, path: str | Path) -> None:
    """The program as CSV, with comments saying what the columns mean and how long it runs."""
    lines = [
        "# fbgforce calibration protocol: one press per row; the stage rests rest_s off the "
        "pad, moves to x_mm,y_mm (pad frame: origin top-left, x right, y down), loads to "
        "force_N in ramp_s, holds hold_s, unloads in ramp_s",
        f"# duration: {program.duration_s:.1f} s ({program.duration_s / 60:.1f} min), "
        f"{program.force_N.size} presses",
        f"# {TEMPERATURE_NOTE}",
        "# log the interrogator and the stage/load cell throughout; import them with "
        "fbgforce import (docs/lab-import.md)",
        ",".join(COLUMNS),
    ]
    for k in range(program.force_N.size):
        lines.append(f"{k},{program.group[k]},{program.x_mm[k]:.2f},{program.y_mm[k]:.2f},"
                     f"{program.force_N[k]:.3f},{program.ramp_s[k]:.3f},{program.hold_s[k]:.3f},"
                     f"{program.rest_s[k]:.3f}")
    try:
        Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot write: {exc.strerror}", path=str(path), column="--out") from None
