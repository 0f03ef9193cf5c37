"""Scenes: TOML files that say what happens to the end-effector and which effects apply.

A scene file has top-level keys ``description``, ``seed``, ``device``, ``sample_rate_hz``, a
``[schedule]`` table (``kind`` = ``presses`` | ``rest`` | ``impacts`` and that kind's keys, see
:data:`SCHEDULES`) and an ``[effects]`` table with one sub-table per effect to apply
(``[effects.noise]``; keys omitted take their defaults; see ``fbgforce.sim.effects``).
Built-in scenes live in the ``fbgforce.scenes`` package and load by name; anything else
loads by path. Every problem raises :class:`InputError` naming the file, the dotted key and
the allowed keys or values.
"""
from __future__ import annotations

import copy
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

from fbgforce.recordings.dataset import CONTACT_THRESHOLD_N
from fbgforce.errors import InputError
from fbgforce.sim.effects import EFFECT_ORDER, EFFECTS, RENAMED_EFFECTS, canonical_effect_name
from fbgforce.sim.params import Param, check_params

_REGIONS = ("pad", "interior", "boundary")

#: Keys shared by every schedule kind.
_COMMON = {
    "contact_threshold_N": Param("float", CONTACT_THRESHOLD_N,
                                 "ground-truth contact is force > this, N", 0, 10),
    "lead_in_s": Param("float", 0.0, "extra rest (no contact) at the start, s", 0, 3600),
    "tail_s": Param("float", 0.0, "rest (no contact) at the end, s", 0, 3600),
}

#: Schedule kinds and their keys.
SCHEDULES: dict[str, dict[str, Param]] = {
    "presses": {
        "n_presses": Param("int", 300, "number of presses", 1, 1_000_000),
        "rest_s": Param("float", 0.201, "rest before each press (no contact), s; the first one "
                        "is the taring time", 0.0, 3600),
        "load_s": Param("float", 0.29, "loading time, s", 0.001, 3600),
        "hold_s": Param("float", 0.0, "hold at peak force, s", 0, 3600),
        "hold_max_s": Param("float", 0.0, "when above hold_s, each holding press holds for a "
                            "time drawn uniformly in [hold_s, hold_max_s], s", 0, 3600),
        "hold_fraction": Param("float", 1.0, "share of the presses that hold (each press "
                               "drawn at random); the others turn round at the peak", 0, 1),
        "unload_s": Param("float", 0.29, "unloading time, s", 0.001, 3600),
        "speed_spread": Param("float", 1.0, "each press loads and unloads in load_s and "
                              "unload_s times a factor drawn log-uniformly in "
                              "[1/speed_spread, speed_spread] (1: every press at one speed)",
                              1, 100),
        "force_min_N": Param("float", 1.0, "smallest peak force, N", 0, 1000),
        "force_max_N": Param("float", 70.0, "largest peak force, N", 0, 1000, lo_open=True),
        "force_distribution": Param("str", "uniform", "distribution of peak forces",
                                    choices=("uniform", "loguniform")),
        "profile": Param("str", "hertz", "force curve of a press: 'hertz' (F ~ s^1.5, a stage "
                         "at constant speed into a rubber pad), 'linear' or 'cosine'",
                         choices=("hertz", "linear", "cosine")),
        "region": Param("str", "pad", "where presses land: the whole pad (minus margin), its "
                        "interior, or the boundary band", choices=_REGIONS),
        "margin_mm": Param("float", 0.5, "keep presses this far inside the pad edge, mm", 0, 10),
        "band_mm": Param("float", 2.5, "width of the boundary band for region "
                         "'interior'/'boundary', mm", 0, 10, lo_open=True),
        **_COMMON,
    },
    "rest": {
        "duration_s": Param("float", 60.0, "length of the recording, s", 0.001, 1e6),
        **_COMMON,
    },
    "impacts": {
        "n_impacts": Param("int", 10, "number of impacts (taps)", 1, 100_000),
        "interval_s": Param("float", 0.3, "time between impacts, s", 0.002, 3600),
        "impulse_min_Ns": Param("float", 0.002, "smallest impulse, N s", 0, 10),
        "impulse_max_Ns": Param("float", 0.02, "largest impulse, N s", 0, 10, lo_open=True),
        "region": Param("str", "pad", "where impacts land", choices=_REGIONS),
        "margin_mm": Param("float", 0.5, "keep impacts this far inside the pad edge, mm", 0, 10),
        "band_mm": Param("float", 2.5, "boundary band width, mm", 0, 10, lo_open=True),
        **_COMMON,
    },
}

_TOP = {
    "description": Param("str", "", "what the scene is for"),
    "seed": Param("int", 0, "seed of the scene's random streams", 0, 2**63 - 1),
    "device": Param("int", 0, "device number (seeds the tolerance of a physical device)", 0, 2**31 - 1),
    "sample_rate_hz": Param("float", 1000.0, "interrogator sample rate, Hz", 1, 1e6),
}


@dataclass(frozen=True)
class Scene:
    """A validated scene. Build with :func:`load_scene` or :func:`scene_from_dict`."""

    name: str
    description: str
    seed: int
    device: int
    sample_rate_hz: float
    schedule: dict[str, Any]
    effects: dict[str, dict[str, Any]] = field(default_factory=dict)
    path: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The scene as a TOML-shaped dict (all defaults filled in)."""
        return {"description": self.description, "seed": self.seed, "device": self.device,
                "sample_rate_hz": self.sample_rate_hz, "schedule": copy.deepcopy(self.schedule),
                "effects": copy.deepcopy(self.effects)}

    def replace(self, *, seed: int | None = None, device: int | None = None,
                schedule: Mapping[str, Any] | None = None,
                effects: Mapping[str, Mapping[str, Any]] | None = None,
                name: str | None = None) -> "Scene":
        """A validated copy: ``schedule`` keys are merged into the schedule, ``effects``
        replaces the effect table entirely (``{}`` = no effects)."""
        d = self.to_dict()
        if seed is not None:
            d["seed"] = seed
        if device is not None:
            d["device"] = device
        if schedule:
            if "kind" in schedule and schedule["kind"] != d["schedule"]["kind"]:
                d["schedule"] = {}
            d["schedule"].update(schedule)
        if effects is not None:
            d["effects"] = {k: dict(v) for k, v in effects.items()}
        return scene_from_dict(d, path=self.path, name=name or self.name)


def scene_from_dict(data: Mapping[str, Any], *, path: str | None = None,
                    name: str = "<scene>") -> Scene:
    """Validate a TOML-shaped dict (as :mod:`tomllib` returns it) into a :class:`Scene`.

    A ``base = "NAME"`` (built-in scene) or ``base = "other.toml"`` (relative to this file)
    key inherits everything from that scene; this dict's values override it: top-level keys
    replace, ``[schedule]`` keys merge (a different ``kind`` starts a fresh schedule),
    ``[effects.NAME]`` tables merge key by key, and ``NAME = false`` under ``[effects]``
    removes an inherited effect.
    """
    if "base" in data:
        data = _inherit(data, path, ())
    if "schedule" not in data:
        raise InputError("not a simulator scene: missing [schedule] table (kind = "
                         + " | ".join(SCHEDULES) + ")", path=path, column="schedule")
    # A [teleop] table belongs to fbgforce.teleop (closed-loop scenes such as egg_grasp, whose
    # fingertip is this simulator): the simulator ignores it, the teleop loader validates it.
    top = {k: v for k, v in data.items() if k not in ("schedule", "effects", "teleop")}
    for key in top:
        if key not in _TOP:
            raise InputError(f"unknown key; allowed top-level keys: "
                             f"{', '.join(list(_TOP) + ['base', 'schedule', 'effects'])}",
                             path=path, column=key)
    values = check_params(top, _TOP, path=path, key_path="")

    sched = data["schedule"]
    if not isinstance(sched, Mapping):
        raise InputError("must be a table", path=path, column="schedule")
    kind = sched.get("kind")
    if kind not in SCHEDULES:
        raise InputError(f"unknown schedule kind {kind!r}; allowed: {', '.join(SCHEDULES)}",
                         path=path, column="schedule.kind")
    sched_vals = check_params({k: v for k, v in sched.items() if k != "kind"}, SCHEDULES[kind],
                              path=path, key_path="schedule")
    sched_vals = {"kind": kind, **sched_vals}
    _check_schedule(sched_vals, path)

    eff = data.get("effects", {})
    if not isinstance(eff, Mapping):
        raise InputError("must be a table of [effects.NAME] tables", path=path, column="effects")
    eff = _canonical_effects(eff, path)
    effects: dict[str, dict[str, Any]] = {}
    for ename, params in eff.items():
        if ename not in EFFECTS:
            raise InputError(f"unknown effect; allowed effects: {', '.join(EFFECT_ORDER)}",
                             path=path, column=f"effects.{ename}")
        if not isinstance(params, Mapping):
            raise InputError(f"must be a table ([effects.{ename}]), got {params!r}", path=path,
                             column=f"effects.{ename}")
    for ename in EFFECT_ORDER:
        if ename in eff:
            effects[ename] = check_params(eff[ename], EFFECTS[ename].params, path=path,
                                          key_path=f"effects.{ename}")
    if "dynamics" in effects:
        ratio = effects["dynamics"]["internal_rate_hz"] / values["sample_rate_hz"]
        if ratio < 10 or abs(ratio - round(ratio)) > 1e-9 * ratio:
            raise InputError(f"must be an integer multiple (>= 10x) of sample_rate_hz "
                             f"({values['sample_rate_hz']:g})", path=path,
                             column="effects.dynamics.internal_rate_hz")
    return Scene(name=name, description=values["description"], seed=values["seed"],
                 device=values["device"], sample_rate_hz=values["sample_rate_hz"],
                 schedule=sched_vals, effects=effects, path=path)


def _canonical_effects(eff: Mapping[str, Any], path: str | None) -> dict[str, Any]:
    """``eff`` with former effect names (:data:`RENAMED_EFFECTS`) replaced by current ones;
    a table naming one effect under both names is ambiguous and refused."""
    out: dict[str, Any] = {}
    for given, params in eff.items():
        name = canonical_effect_name(given)
        if name in out:
            old = [k for k, v in RENAMED_EFFECTS.items() if v == name]
            raise InputError(f"effect {name!r} given twice (also as its former name "
                             f"{', '.join(old)!s})", path=path, column=f"effects.{given}")
        out[name] = params
    return out


def _check_schedule(s: dict[str, Any], path: str | None) -> None:
    """Cross-key checks that a per-key range cannot express."""
    if s["kind"] == "presses" and s["force_min_N"] > s["force_max_N"]:
        raise InputError(f"force_min_N ({s['force_min_N']:g}) must not exceed force_max_N "
                         f"({s['force_max_N']:g})", path=path, column="schedule.force_min_N")
    if s["kind"] == "presses" and s["force_distribution"] == "loguniform" and s["force_min_N"] <= 0:
        raise InputError("must be > 0 for force_distribution = 'loguniform'", path=path,
                         column="schedule.force_min_N")
    if s["kind"] == "presses" and 0 < s["hold_max_s"] < s["hold_s"]:
        raise InputError(f"hold_max_s ({s['hold_max_s']:g}) must be 0 or at least hold_s "
                         f"({s['hold_s']:g})", path=path, column="schedule.hold_max_s")
    if s["kind"] == "impacts" and s["impulse_min_Ns"] > s["impulse_max_Ns"]:
        raise InputError("impulse_min_Ns must not exceed impulse_max_Ns", path=path,
                         column="schedule.impulse_min_Ns")
    if s.get("region", "pad") != "pad":
        if s["margin_mm"] >= s["band_mm"] and s["region"] == "boundary":
            raise InputError(f"margin_mm ({s['margin_mm']:g}) must be smaller than band_mm "
                             f"({s['band_mm']:g}) for region 'boundary'", path=path,
                             column="schedule.margin_mm")


def _read_raw(ref: str, including: str | None) -> tuple[dict[str, Any], str]:
    """The parsed TOML of a scene reference (built-in name, or a path relative to the
    including file) and its display path."""
    p = Path(ref)
    if p.suffix == ".toml" or "/" in ref or "\\" in ref:
        if not p.is_absolute() and including is not None and Path(including).is_file():
            p = Path(including).parent / p
        try:
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read base scene {ref!r}: {exc}", path=including,
                             column="base") from None
        where = str(p)
    else:
        res = resources.files("fbgforce.scenes") / f"{ref}.toml"
        if not res.is_file():
            raise InputError(f"unknown base scene {ref!r}; built-in scenes: "
                             f"{', '.join(builtin_scenes())}", path=including, column="base")
        text = res.read_text(encoding="utf-8")
        where = f"<built-in scene {ref}>"
    try:
        return tomllib.loads(text), where
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"TOML syntax error: {exc}", path=where) from None


def _inherit(data: Mapping[str, Any], path: str | None, chain: tuple[str, ...]) -> dict[str, Any]:
    """``data`` with its ``base`` scene (recursively) merged underneath (see scene_from_dict)."""
    ref = data["base"]
    if not isinstance(ref, str) or not ref:
        raise InputError(f"expected a scene name or path, got {ref!r}", path=path, column="base")
    base, where = _read_raw(ref, path)
    if where in chain:
        raise InputError(f"circular base: {' -> '.join(chain + (where,))}", path=path,
                         column="base")
    if "base" in base:
        base = _inherit(base, where, chain + (where,))
    scene_from_dict(base, path=where, name=ref)  # errors in the base name the base's file
    merged = copy.deepcopy(base)
    for key, value in data.items():
        if key == "base":
            continue
        if key == "schedule" and isinstance(value, Mapping):
            sched = merged.get("schedule", {})
            if "kind" in value and value["kind"] != sched.get("kind"):
                sched = {}
            merged["schedule"] = {**sched, **value}
        elif key == "effects" and isinstance(value, Mapping):
            effects = merged.get("effects", {})
            if isinstance(effects, Mapping):
                effects = _canonical_effects(effects, where)
            for ename, params in _canonical_effects(value, path).items():
                if params is False:
                    effects.pop(ename, None)
                elif isinstance(params, Mapping) and isinstance(effects.get(ename), Mapping):
                    effects[ename] = {**effects[ename], **params}
                else:
                    effects[ename] = params
            merged["effects"] = effects
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def builtin_scenes() -> list[str]:
    """Names of the simulator scenes shipped in ``fbgforce.scenes`` (files with a
    ``[schedule]`` table or a ``base``)."""
    root = resources.files("fbgforce.scenes")
    names = []
    for p in root.iterdir():
        if p.name.endswith(".toml"):
            try:
                raw = tomllib.loads(p.read_text(encoding="utf-8"))
                if "schedule" in raw or "base" in raw:
                    names.append(p.name[:-5])
            except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
                names.append(p.name[:-5])  # broken: listed, so that loading it reports why
    return sorted(names)


def load_scene(name_or_path: str | Path | Scene) -> Scene:
    """A scene by built-in name (``"calibration"``), by path to a TOML file, or as given.

    Raises
    ------
    InputError
        Unknown name, unreadable file, TOML syntax error, or an invalid key or value.
    """
    if isinstance(name_or_path, Scene):
        return name_or_path
    arg = str(name_or_path)
    p = Path(arg)
    if p.suffix == ".toml" or p.exists() or "/" in arg or "\\" in arg:
        try:
            text = p.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise InputError("no such scene file", path=arg) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read scene file: {exc}", path=arg) from None
        return _parse(text, path=arg, name=p.stem)
    res = resources.files("fbgforce.scenes") / f"{arg}.toml"
    if not res.is_file():
        raise InputError(f"unknown scene {arg!r}; built-in scenes: {', '.join(builtin_scenes())} "
                         "(or give a path to a .toml file)", column="--scene")
    return _parse(res.read_text(encoding="utf-8"), path=f"<built-in scene {arg}>", name=arg)


def _parse(text: str, *, path: str, name: str) -> Scene:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"TOML syntax error: {exc}", path=path) from None
    return scene_from_dict(data, path=path, name=name)
