"""Scene-driven physics simulator of the FBG end-effector (stands in for the gripper).

Public API: :func:`simulate` (scene → :class:`fbgforce.recordings.dataset.Dataset`), :func:`load_scene`,
:class:`Scene`, :class:`EndEffector` (streaming, for closed-loop use), :data:`EFFECT_ORDER`.
Physics and effects: docs/simulator.md.
"""
from fbgforce.sim.effects import EFFECT_ORDER, EFFECTS, effect_rng
from fbgforce.sim.endeffector import EndEffector
from fbgforce.sim.scene import Scene, builtin_scenes, load_scene, scene_from_dict
from fbgforce.sim.schedule import Schedule, build_schedule
from fbgforce.sim.simulate import simulate

__all__ = ["EFFECT_ORDER", "EFFECTS", "EndEffector", "Scene", "Schedule", "build_schedule",
           "builtin_scenes", "effect_rng", "load_scene", "scene_from_dict", "simulate"]
