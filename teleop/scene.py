"""The teleoperation scene file: the fingertip's simulator scene plus a ``[teleop]`` table.

A teleoperation scene (``scenes/egg_grasp.toml`` is the built-in one) is a valid simulator
scene (:func:`fbgforce.sim.load_scene`: ``seed``, ``device``, ``sample_rate_hz``, a ``rest``
``[schedule]`` whose ``duration_s`` is the length of the scene, and the ``[effects.*]`` tables
of the fingertip, handed unchanged to :class:`fbgforce.sim.EndEffector`) with one more table,
``[teleop]``, that the simulator ignores: ``[teleop.loop]``, ``[teleop.master]``,
``[teleop.operator]``, ``[teleop.gripper]``, ``[teleop.egg]``, ``[teleop.arm]`` (with
``[[teleop.arm.moves]]``).

Every key of the teleop tables is required (the scene file is the one place the numbers live,
with their reasons in comments) and unknown keys are errors, so that a typo cannot silently
fall back to a default. A parameter that varies between seeded runs (operators differ, eggs
differ) is written ``[low, high]`` and drawn uniformly per run; a plain number is the same in
every run.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.errors import InputError

#: Allowed keys per table: key -> (lowest, highest, may it be a [low, high] range?).
SCHEMA: dict[str, dict[str, tuple[float, float, bool]]] = {
    "loop": {
        "preroll_s": (0.0, 5.0, False),
    },
    "master": {
        "peak_force_N": (0.1, 20.0, False),
        "base_stiffness_N_per_m": (0.0, 2000.0, False),
        "max_stiffness_N_per_m": (0.0, 2000.0, False),
        "full_stiffness_force_N": (0.1, 200.0, False),
        "damping_N_s_per_m": (0.0, 50.0, False),
        "travel_mm": (1.0, 300.0, False),
    },
    "operator": {
        "start_delay_s": (0.0, 10.0, True),
        "approach_speed_mm_s": (0.1, 500.0, True),
        "fine_speed_mm_s": (0.1, 100.0, True),
        "slow_down_margin_mm": (0.0, 100.0, True),
        "visual_delay_s": (0.0, 2.0, True),
        "haptic_delay_s": (0.0, 2.0, True),
        "feel_threshold_N": (0.0, 5.0, True),
        "target_felt_force_N": (0.0, 20.0, True),
        "force_gain_mm_s_per_N": (0.0, 200.0, True),
        "max_correction_speed_mm_s": (0.0, 500.0, True),
        "visual_squeeze_mm": (0.0, 50.0, True),
        "hand_mass_kg": (0.01, 5.0, True),
        "hand_stiffness_N_per_m": (1.0, 10_000.0, True),
        "hand_damping_ratio": (0.0, 5.0, True),
        "drift_mm": (0.0, 50.0, True),
        "drift_time_s": (0.01, 100.0, True),
        "tremor_mm": (0.0, 5.0, True),
        "tremor_hz": (0.1, 50.0, True),
    },
    "gripper": {
        "open_mm": (1.0, 200.0, False),
        "map_gain": (0.01, 20.0, False),
        "bandwidth_hz": (0.1, 1000.0, False),
        "max_speed_mm_s": (0.1, 5000.0, False),
        "servo_stiffness_N_per_mm": (0.01, 10_000.0, False),
        "pad_stiffness_N_per_mm": (0.01, 10_000.0, False),
    },
    "egg": {
        "width_mm": (1.0, 200.0, True),
        "mass_kg": (0.001, 10.0, True),
        "shell_stiffness_N_per_mm": (0.01, 100_000.0, True),
        "break_force_N": (0.1, 1000.0, True),
        "friction_static": (0.01, 5.0, True),
        "friction_kinetic_ratio": (0.01, 1.0, False),
        "drop_slip_mm": (0.1, 200.0, False),
        "contact_x_mm": (0.0, 21.0, True),
        "contact_y_mm": (0.0, 27.0, True),
        "safe_band_low_N": (0.0, 1000.0, False),
        "safe_band_high_N": (0.0, 1000.0, False),
    },
    "arm": {
        "gravity_m_s2": (0.0, 100.0, False),
    },
}
MOVE_KEYS: dict[str, tuple[float, float]] = {
    "start_s": (0.0, 1000.0),
    "duration_s": (0.01, 1000.0),
    "dx_m": (-10.0, 10.0),
    "dz_m": (-10.0, 10.0),
}


@dataclass
class Move:
    """One minimum-jerk move of the arm (the robot moves autonomously)."""

    start_s: float
    duration_s: float
    dx_m: float
    dz_m: float


@dataclass
class TeleopScene:
    """A loaded teleoperation scene.

    Attributes
    ----------
    name, path
        Scene name and the file it came from.
    sim_scene
        The fingertip's simulator scene (effects, seed, device, rate, duration).
    tables
        ``tables[table][key]`` is a float or a ``(low, high)`` tuple (drawn per run).
    moves
        The arm's moves, in time order.
    """

    name: str
    path: str
    sim_scene: Any
    tables: dict[str, dict[str, float | tuple[float, float]]]
    moves: list[Move] = field(default_factory=list)

    @property
    def rate_hz(self) -> float:
        """Loop rate = the fingertip's sample rate, Hz."""
        return float(self.sim_scene.sample_rate_hz)

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def duration_s(self) -> float:
        return float(self.sim_scene.schedule["duration_s"])

    @property
    def lift_s(self) -> float:
        """When the arm starts to move: from then on the grip alone holds the egg."""
        return min((m.start_s for m in self.moves), default=self.duration_s)

    def fixed(self, table: str, key: str) -> float:
        """A parameter that is the same in every run."""
        value = self.tables[table][key]
        if isinstance(value, tuple):
            raise ValueError(f"[teleop.{table}] {key} is a range, not a single value")
        return float(value)

    def draw(self, table: str, rngs: list[np.random.Generator]) -> dict[str, np.ndarray]:
        """Every parameter of ``table`` for each run: fixed values repeated, ranges drawn.

        Each run has its own generator, and keys are drawn in the schema's order, so a run's
        values depend only on its seed and not on how many runs are simulated with it.
        """
        out: dict[str, np.ndarray] = {k: np.empty(len(rngs)) for k in SCHEMA[table]}
        for i, rng in enumerate(rngs):
            for key in SCHEMA[table]:
                value = self.tables[table][key]
                out[key][i] = rng.uniform(*value) if isinstance(value, tuple) else value
        return out

    def with_values(self, **changes: float | tuple[float, float]) -> "TeleopScene":
        """A copy with some parameters replaced, keys as ``"table__key"`` (for ablations)."""
        tables = {t: dict(v) for t, v in self.tables.items()}
        for dotted, value in changes.items():
            table, key = dotted.split("__", 1)
            if key not in SCHEMA.get(table, {}):
                raise KeyError(f"no parameter teleop.{table}.{key}")
            tables[table][key] = value
        return TeleopScene(self.name, self.path, self.sim_scene, tables, list(self.moves))


def _number(value: Any, where: str, path: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"must be a number, not {value!r}", path=path, column=where)
    return float(value)


def _check_range(v: float, lo: float, hi: float, where: str, path: str) -> None:
    if not (lo <= v <= hi):
        raise InputError(f"{v:g} is outside the allowed range [{lo:g}, {hi:g}]",
                         path=path, column=where)


def parse_scene(doc: dict[str, Any], path: str, name: str) -> TeleopScene:
    """Validate a parsed TOML document into a :class:`TeleopScene`.

    Raises
    ------
    InputError
        Naming the file and the dotted key for a missing or unknown key, a value that is not a
        number, a range that is not ``[low, high]``, or a value out of its allowed range (the
        simulator part of the file is checked by :func:`fbgforce.sim.scene_from_dict`).
    """
    from fbgforce.sim import scene_from_dict

    sim_scene = scene_from_dict(doc, path=path, name=name)
    if sim_scene.schedule["kind"] != "rest":
        raise InputError("a teleoperation scene's fingertip schedule must be kind = \"rest\" "
                         "(the loop, not a schedule, loads it); its duration_s is the scene's",
                         path=path, column="schedule.kind")
    if sim_scene.schedule["duration_s"] * sim_scene.sample_rate_hz < 2:
        raise InputError("the scene needs at least two samples", path=path,
                         column="schedule.duration_s")
    tele = doc.get("teleop")
    if not isinstance(tele, dict):
        raise InputError("missing [teleop] tables (master, operator, gripper, egg, arm): not a "
                         "teleoperation scene", path=path, column="teleop")
    for top in tele:
        if top not in SCHEMA:
            raise InputError(f"unknown table; allowed: {', '.join(SCHEMA)}", path=path,
                             column=f"teleop.{top}")
    tables = {table: _parse_table(tele, table, keys, path) for table, keys in SCHEMA.items()}
    moves = _parse_moves(tele["arm"].get("moves", []), path)
    _check_between_keys(tables, path)
    return TeleopScene(name=name, path=path, sim_scene=sim_scene, tables=tables, moves=moves)


def _parse_table(tele: dict[str, Any], table: str, keys: dict[str, tuple[float, float, bool]],
                 path: str) -> dict[str, float | tuple[float, float]]:
    """One ``[teleop.<table>]``: every key of the schema present and nothing else (the arm may
    also hold its moves), each value a number or, where the schema lets it be drawn per run,
    a ``[low, high]`` range, within the schema's bounds."""
    given = tele.get(table)
    if not isinstance(given, dict):
        raise InputError("missing table", path=path, column=f"teleop.{table}")
    extra = set(given) - set(keys) - ({"moves"} if table == "arm" else set())
    if extra:
        raise InputError(f"unknown key; allowed: {', '.join(keys)}", path=path,
                         column=f"teleop.{table}.{sorted(extra)[0]}")
    out: dict[str, float | tuple[float, float]] = {}
    for key, (lo, hi, may_range) in keys.items():
        where = f"teleop.{table}.{key}"
        if key not in given:
            raise InputError("missing key", path=path, column=where)
        value = given[key]
        if isinstance(value, list):
            out[key] = _parse_range(value, lo, hi, may_range, where, path)
        else:
            v = _number(value, where, path)
            _check_range(v, lo, hi, where, path)
            out[key] = v
    return out


def _parse_range(value: list[Any], lo: float, hi: float, may_range: bool, where: str,
                 path: str) -> tuple[float, float]:
    """A ``[low, high]`` range of a key that may be drawn per run: two numbers, low not above
    high, both within ``[lo, hi]``."""
    if not may_range:
        raise InputError("must be a single number (it is not drawn per run)",
                         path=path, column=where)
    if len(value) != 2:
        raise InputError("a range must be [low, high]", path=path, column=where)
    low, high = (_number(v, where, path) for v in value)
    if low > high:
        raise InputError(f"range [{low:g}, {high:g}] has low > high",
                         path=path, column=where)
    for v in (low, high):
        _check_range(v, lo, hi, where, path)
    return (low, high)


def _parse_moves(given: list[Any], path: str) -> list[Move]:
    """The arm's moves: tables with every key of :data:`MOVE_KEYS` within its bounds, in
    order of start, none starting before the previous one ends."""
    moves = []
    for i, m in enumerate(given):
        where = f"teleop.arm.moves[{i}]"
        if not isinstance(m, dict):
            raise InputError("must be a table with " + ", ".join(MOVE_KEYS), path=path, column=where)
        extra = set(m) - set(MOVE_KEYS)
        if extra:
            raise InputError(f"unknown key {sorted(extra)[0]!r}; allowed: {', '.join(MOVE_KEYS)}",
                             path=path, column=where)
        vals = {}
        for key, (lo, hi) in MOVE_KEYS.items():
            if key not in m:
                raise InputError(f"missing key {key!r}", path=path, column=where)
            vals[key] = _number(m[key], f"{where}.{key}", path)
            _check_range(vals[key], lo, hi, f"{where}.{key}", path)
        moves.append(Move(**vals))
    moves.sort(key=lambda mv: mv.start_s)
    for a, b in zip(moves, moves[1:]):
        if b.start_s < a.start_s + a.duration_s:
            raise InputError(f"move at {b.start_s:g} s starts before the previous one ends",
                             path=path, column="teleop.arm.moves")
    return moves


def _check_between_keys(tables: dict[str, dict[str, float | tuple[float, float]]],
                        path: str) -> None:
    """The bounds one key sets another: the master's stiffest spring at least its base one,
    the egg's safe band not empty."""
    m = tables["master"]
    if m["max_stiffness_N_per_m"] < m["base_stiffness_N_per_m"]:  # type: ignore[operator]
        raise InputError("must be at least teleop.master.base_stiffness_N_per_m", path=path,
                         column="teleop.master.max_stiffness_N_per_m")
    e = tables["egg"]
    if e["safe_band_high_N"] <= e["safe_band_low_N"]:  # type: ignore[operator]
        raise InputError("must be above teleop.egg.safe_band_low_N", path=path,
                         column="teleop.egg.safe_band_high_N")


def load_teleop_scene(name_or_path: str | Path) -> TeleopScene:
    """Load a teleoperation scene by built-in name (``"egg_grasp"``) or by file path.

    Raises
    ------
    InputError
        If the file is missing, not valid TOML, or fails :func:`parse_scene`.
    """
    arg = str(name_or_path)
    p = Path(arg)
    if p.suffix == ".toml" or p.exists() or "/" in arg:
        if not p.is_file():
            raise InputError("no such scene file", path=arg)
        data = p.read_bytes()
        path, name = arg, p.stem
    else:
        res = resources.files("fbgforce.scenes").joinpath(f"{arg}.toml")
        if not res.is_file():
            raise InputError(f"no built-in scene {arg!r} (give a .toml path, or 'egg_grasp')",
                             column="--scene")
        data = res.read_bytes()
        path, name = f"<built-in scene {arg}>", arg
    try:
        doc = tomllib.loads(data.decode("utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"TOML syntax error: {exc}", path=path) from exc
    except UnicodeDecodeError as exc:
        raise InputError("not UTF-8 text", path=path) from exc
    return parse_scene(doc, path, name)
