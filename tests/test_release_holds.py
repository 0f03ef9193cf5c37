"""Holds for a pad with friction: the trainer places synthetic holds on the presses' releases,
or wandering holds, only where the calibration shows a friction (a rise-fall gap that follows
the load, not its speed); a hold on the release keeps the release's strain, a wandering hold's
strain sticks at each turn and slides on the press's own branches (trainer.hysteresis,
trainer.synthetic)."""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import foreign as fg  # noqa: E402

from fbgforce.errors import InputError  # noqa: E402
from fbgforce.model import floatref  # noqa: E402
from fbgforce.trainer.hysteresis import (FRICTION_MIN_Z, LOOP_MIN_PRESSES, PressLoops,  # noqa: E402
                                         friction_evidence, friction_hold_choice)
from fbgforce.trainer.creep import Creep  # noqa: E402
from fbgforce.trainer.params import TrainParams  # noqa: E402
from fbgforce.trainer.synthetic import (RELEASE_HOLD_AT, WANDER_DEPTH,  # noqa: E402
                                        WANDER_LEAD_S, synthetic_holds)
from fbgforce.trainer import synthetic  # noqa: E402
from fbgforce.trainer.train import prepare  # noqa: E402


def _loops(friction: float, damper_s: float, presses: int = 80, noise_N: float = 0.05,
           seed: int = 0) -> PressLoops:
    """Loops of presses to 3-80 N at speeds that follow the peak loosely (as a stage's
    presses of a few durations do, correlation about 0.9): a gap of ``friction`` of the load
    plus ``damper_s`` times the speed, plus noise."""
    rng = np.random.default_rng(seed)
    peak = rng.uniform(3.0, 80.0, presses)
    speed = peak / rng.uniform(0.1, 0.35, presses)
    gap = friction * peak + damper_s * speed + rng.normal(0.0, noise_N, presses)
    return PressLoops(peak, speed, gap)


def test_a_friction_is_established_and_a_damper_is_not():
    friction = friction_evidence(_loops(0.03, 0.0))
    assert friction["established"], friction["why"]
    assert friction["friction"]["coefficient"] == pytest.approx(0.03, abs=0.003)
    assert friction["friction"]["z"] >= FRICTION_MIN_Z and friction["share"] > 0.9
    assert friction["why"].startswith("friction established: ")
    damper = friction_evidence(_loops(0.0, 0.008))
    assert not damper["established"], damper["why"]
    assert damper["damper"]["coefficient_s"] == pytest.approx(0.008, abs=0.001)
    assert damper["held_out"]["p"] > 0.05
    assert damper["why"].startswith("no friction established: ")


def test_a_friction_that_is_the_lesser_part_of_the_gap_is_not_enough():
    """A damper that holds back most of the gap would be kept by holds on the release; a
    friction of a fifth of the gap beside it is measurable but not enough."""
    mixed = friction_evidence(_loops(0.004, 0.008, noise_N=0.01))
    assert mixed["friction"]["z"] >= FRICTION_MIN_Z
    assert mixed["share"] < 0.5 and not mixed["established"], mixed["why"]


def test_noise_alone_and_too_few_presses_establish_nothing():
    for seed in range(3):
        assert not friction_evidence(_loops(0.0, 0.0, seed=seed))["established"]
    few = friction_evidence(_loops(0.03, 0.0, presses=LOOP_MIN_PRESSES - 1))
    assert not few["established"] and "needed" in few["why"]


def test_presses_at_one_duration_cannot_tell_a_friction_from_a_damper():
    rng = np.random.default_rng(0)
    peak = rng.uniform(3.0, 80.0, 60)
    one_speed = PressLoops(peak, peak / 0.29, 0.03 * peak + rng.normal(0, 0.05, 60))
    ev = friction_evidence(one_speed)
    assert not ev["established"] and "follow their peaks" in ev["why"]


@pytest.mark.parametrize("member, established", [("no_creep", True), ("viscous", False)])
def test_the_loops_of_a_foreign_pad(member, established):
    """On the calibration logs of two foreign pads (tests/foreign.py: a Dahl friction of 5 %,
    a Kelvin-Voigt damper of 4 ms; not the simulator's physics) the test tells which is which:
    the damper's gap grows 8 ms of the load's speed (twice its 4 ms, rise and fall)."""
    spec = replace(fg.IN_USE_VARIANTS["calib_3K"], **fg.FAMILY[member])
    data = prepare([fg.log(fg.device(spec, 200), 1, 40)], seed=0, creep="off")
    ev = friction_evidence(PressLoops.of(data, data.pre, data.rows("all")))
    assert ev["presses"] >= 35
    assert ev["established"] is established, ev["why"]
    if not established:
        assert ev["damper"]["coefficient_s"] == pytest.approx(0.008, rel=0.15)
    choice = friction_hold_choice(data, data.pre, data.rows("all"), "auto")
    assert choice["applied"] is established
    assert friction_hold_choice(data, data.pre, data.rows("all"), "on")["applied"]
    assert not friction_hold_choice(data, data.pre, data.rows("all"), "off")["applied"]


def test_friction_hold_modes():
    with pytest.raises(InputError, match="--release-holds"):
        TrainParams(release_holds="sometimes")
    with pytest.raises(InputError, match="--wander-holds"):
        TrainParams(wander_holds="always")
    assert TrainParams().release_holds == "off" and TrainParams().wander_holds == "auto"


def test_a_hold_on_the_release_keeps_the_releases_strain_and_labels():
    """Each hold starts at a release sample between 40 and 90 % of its press's peak, takes its
    labels, and holds the strain the release had there (not the peak's)."""
    spec = replace(fg.IN_USE_VARIANTS["calib_3K"], **fg.FAMILY["no_creep"])
    data = prepare([fg.log(fg.device(spec, 200), 1, 24)], seed=0, creep="off")
    rows = data.rows("all")
    x, src = synthetic_holds(data, data.pre, rows, 1.0, Creep(), np.random.default_rng(0),
                             on_release=True)
    ds = data.recordings[0].ds
    force, pid = np.asarray(ds.force_N), np.asarray(ds.press_id)
    points = [s for s in np.unique(src) if np.sum(src == s) > 300]     # 1.5-6 s held
    assert len(points) >= 20
    depth = {}
    for s in points:
        press = np.flatnonzero((pid == pid[s]) & np.asarray(ds.contact, bool))
        top = press[np.argmax(force[press])]
        assert s > top
        assert RELEASE_HOLD_AT[0] * force[top] - 1e-9 <= force[s] <= RELEASE_HOLD_AT[1] * force[top]
        # Its first sample of the release at or below the drawn share: the one before is above.
        assert force[s - 1] > force[s] or s - 1 == top
        depth[s] = force[s] / force[top]
    # Held at depths across the drawn range.
    assert min(depth.values()) < 0.55 and max(depth.values()) > 0.75
    # The held strain is the release's: the held rows' filtered strain inputs sit near the
    # release sample's, far from the peak's (on the deepest hold).
    s = min(depth, key=depth.get)
    feats = floatref.standardise(data.pre, data.feats)
    peak_row = np.flatnonzero(pid == pid[s])[np.argmax(force[pid == pid[s]])]
    held = x[src == s][-50:, :4].mean(axis=0)
    release, peak = feats[s, :4], feats[peak_row, :4]
    assert np.linalg.norm(held - release) < 0.25 * np.linalg.norm(peak - release)


def _no_creep_press(presses: int = 24) -> tuple[Any, np.ndarray, int]:
    """A foreign pad with friction alone (tests/foreign.py's Dahl law, not the simulator's),
    one recording; the loaded samples and the peak of its strongest press."""
    spec = replace(fg.IN_USE_VARIANTS["calib_3K"], **fg.FAMILY["no_creep"])
    ds = fg.log(fg.device(spec, 200), 1, presses)
    force, pid = np.nan_to_num(np.asarray(ds.force_N, float)), np.asarray(ds.press_id)
    loaded = np.asarray(ds.contact, bool)
    strongest = pid[loaded][np.argmax(force[loaded])]
    pressed = np.flatnonzero(loaded & (pid == strongest))
    return ds, pressed, int(pressed[np.argmax(force[pressed])])


def test_a_wandering_hold_sticks_at_each_turn_and_slides_on_the_press_branches():
    """The load stands through the lead, then dips and comes back through the press's own
    samples; the strain's load signal never leaves the band between the press's rise and its
    fall at the present load, stays put after each turn until the load has crossed that band,
    and then rides its edge (the fall on the way down, the rise on the way up)."""
    ds, pressed, peak = _no_creep_press()
    wl, force = np.asarray(ds.wl_nm, float), np.nan_to_num(np.asarray(ds.force_N, float))
    n = 6000
    moved, labels = synthetic._wandering(wl, force, pressed, peak, n, 1000.0,
                                         np.random.default_rng(3))
    assert moved.shape == (n, 4) and set(labels) <= set(pressed)
    load = force[labels]
    lead = int(np.argmax(labels != peak))
    assert WANDER_LEAD_S[0] * 1000 - 1 <= lead <= WANDER_LEAD_S[1] * 1000 + 1
    assert not moved[:lead].any()
    assert (1 - WANDER_DEPTH[1]) * force[peak] - 0.5 <= load.min() < force[peak]
    # It ends where it started, for the press's recorded release to go on from.
    assert abs(load[-1] - force[peak]) < 0.02 * force[peak]

    top = int(np.searchsorted(pressed, peak))
    up = synthetic._branch(wl, force, pressed[:top + 1])
    down = synthetic._branch(wl, force, pressed[top:])
    both = np.concatenate([pressed[:top + 1], pressed[top:]])
    signal = np.linalg.lstsq(np.column_stack([wl[both, :4], np.ones(both.size)]), force[both],
                             rcond=None)[0][:4]
    start = synthetic._shifts_at(up, force[peak:peak + 1])[0]
    now = moved @ signal                            # newtons, from the peak's
    rise = (synthetic._shifts_at(up, load) - start) @ signal
    fall = (synthetic._shifts_at(down, load) - start) @ signal
    below = load < 0.97 * force[peak]
    assert np.all(fall[below] > rise[below])        # a friction: the fall reads higher
    assert np.all(now >= np.minimum(rise, fall) - 1e-6)
    assert np.all(now <= np.maximum(rise, fall) + 1e-6)
    on_fall, on_rise = np.abs(now - fall) < 1e-6, np.abs(now - rise) < 1e-6
    # Near the top both branches meet, and their noise there outweighs the load's steps.
    inside = load < 0.98 * force[peak]
    falling = np.r_[False, np.diff(load) < 0] & inside
    rising = np.r_[False, np.diff(load) > 0] & inside
    # Where the load moves, the strain has either stuck or follows the branch of that way.
    assert not np.any(falling & on_rise & ~on_fall)
    assert not np.any(rising & on_fall & ~on_rise)
    assert falling[on_fall].sum() > 10 and rising[on_rise].sum() > 10     # steps of the load
    # At the first turn below, the load rises by about the loop's width while the strain stays,
    # then slides on the rise. (At the peak the press's own fall holds its stick.)
    bottom = int(np.argmin(load))
    first_slide = bottom + int(np.argmax(on_rise[bottom:] & rising[bottom:]))
    stuck = load[first_slide] - load[bottom]
    assert 0.01 * load[bottom] < stuck < 0.08 * load[bottom]
    assert np.all(moved[bottom:first_slide] == moved[bottom])
    assert abs(now[-1]) < 0.02 * force[peak]


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["release_holds", "wander_holds"])
def test_friction_holds_train_the_force_net_alone_and_are_recorded(kind):
    """Trained on a pad with friction, the model records the choice and its held samples; the
    contact net is the one trained without them, weight for weight (its decision's threshold
    and onset are set on it), the force net is not."""
    from fbgforce.trainer.train import train

    spec = replace(fg.IN_USE_VARIANTS["calib_3K"], **fg.FAMILY["no_creep"])
    ds = fg.log(fg.device(spec, 200), 1, 30)
    fast = dict(epochs=2, seed=0, restarts=1, idle_pads=0, track_calibration=False,
                progress=False, release_holds="off", wander_holds="off")
    on, off = (train([ds], **{**fast, kind: mode}) for mode in ("auto", "off"))
    key = kind.split("_")[0]
    made = on.metadata["synthetic_holds"][key]
    assert made["applied"] and made["established"] and made["samples"]["train"] > 0
    why = {c["name"]: c for c in on.metadata["corrections"]}[kind]
    assert why["applied"] and why["why"].startswith("friction established")
    assert not {c["name"]: c for c in off.metadata["corrections"]}[kind]["applied"]
    assert off.metadata["synthetic_holds"][key]["why"] == f"--{kind.replace('_', '-')} off"
    for w_on, w_off in zip(on.nets["contact"].weights, off.nets["contact"].weights):
        np.testing.assert_array_equal(w_on, w_off)
    assert not np.array_equal(on.nets["force"].weights[0], off.nets["force"].weights[0])


def test_coverage_names_presses_whose_speed_follows_their_peak():
    """The paper's protocol (every press as long as the next) cannot tell a friction from a
    damper, and `fbgforce coverage` says so; presses at several speeds can."""
    from fbgforce import sim
    from fbgforce.trainer.coverage import coverage

    one_speed = sim.simulate(sim.load_scene("calibration_paper").replace(schedule={"n_presses": 12}))
    assert any("friction or a damper" in u for u in coverage([one_speed])["cannot_establish"])
    spec = replace(fg.IN_USE_VARIANTS["calib_3K"], **fg.FAMILY["no_creep"])
    several = fg.log(fg.device(spec, 200), 1, 30)
    assert not any("friction or a damper" in u for u in coverage([several])["cannot_establish"])
