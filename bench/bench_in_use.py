"""Robust in use: a model on recordings of the conditions it is used in, goal by goal.

Usage::

    python tests/foreign.py --out DIR --presses 100 calib_1K const_temp ramp20K ramp40K \\
        ramp40K_fast long_rests held_grips ramp_hold               # writes the logs
    fbgforce train --data DIR/calib_1K_A.csv --out MODEL && fbgforce export --model MODEL
    python -m fbgforce.bench.bench_in_use --model MODEL --logs DIR [--engine fixed|float] [--json]

    python tests/foreign.py --out FAM --family                      # the family of fingertips
    python -m fbgforce.bench.bench_in_use --family FAM --work WORK [--without STAGE ...] \
        [--calibration calib_1K|calib_3K]

``--logs`` is a directory holding ``foreign.json``, the manifest tests/foreign.py writes (read
with :func:`fbgforce.bench.bench_generalisation.load_manifest`; the generator stays a test
helper). Each variant's ``role`` says what its "other" log (seed 2, never trained on) measures:
``constant`` (presses at constant temperature), ``ramp`` (the same presses through a
temperature ramp), ``rest`` (long rests), ``hold`` (held grips), ``ramp_hold`` (a grip held
through a ramp); ``calibration`` logs are not scored. Every log is run whole by ``--engine`` (default ``fixed``: the C fixed-point runtime),
tared at start-up on its own contact-free samples, through :func:`fbgforce.trainer.evaluate.
evaluate`, the code path of ``fbgforce evaluate --engine fixed``; the metrics are those of
``fbgforce evaluate --json`` (docs/cli.md).

Prints one table, every goal of "Robust in use" beside its target (docs/robustness.md, "Use in
the field"), with the logs it was scored on:

- per ramp: contact on rest samples, force at rest (99th percentile), force RMSE under contact
  against the constant-temperature logs of the same device;
- constant temperature (``constant`` and ``rest`` logs together): false contact events per
  minute of rest, median onset delay, detection of contact samples above 1 N;
- an idle pad at those logs' interrogator noise (:mod:`fbgforce.bench.bench_idle`): false
  contact events per minute, the worst of 20 one-minute draws;
- held grips: force bias over the holds, force RMSE over them against the model's own
  calibration test RMSE (its training logs, test split, same engine); beside them, no goal,
  the same over the held samples away from the load's turns
  (:data:`fbgforce.evaluation.metrics.AFTER_TURN_S`);
- a grip held through a ramp: force bias over the hold (the holds' bound);
- light presses (0.2-3 N): contact accuracy;
- the calibration's own test presses: contact errors.

With ``--family`` it does this for every member of a family of fingertips
(``tests/foreign.py --family``: pads that differ in one piece of in-use physics each), each
member's model trained by the default ``fbgforce train`` on its calibration log
(``--calibration``: which, when the member has several) and exported
(into ``--work``, reused when there), and prints the goals by member with the worst member
beside each target (:func:`family`); ``--without STAGE`` scores beside each model a copy with
one in-use stage off, or the contact decision's other rule (docs/robustness.md, "The family
of fingertips").
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

from fbgforce.bench.bench_generalisation import fail, load_manifest
from fbgforce.errors import InputError
from fbgforce.jsonutil import json_default

PROG = "bench_in_use"
#: Roles of manifest entries that are scored, in the order of the table.
SCORED_ROLES = ("ramp", "constant", "rest", "hold", "ramp_hold", "light")


@dataclass(frozen=True)
class Goal:
    """One goal: what it reads, its target and how the measured value is compared."""

    key: str
    label: str
    target: float
    compare: str              # "<=", ">=", or "abs<=" (|value| <= target)
    unit: str                 # "%" (value is a fraction), "N", "ms", "/min", "x"

    def passes(self, value: float | None) -> bool | None:
        """True or False, or None when nothing was measured."""
        if value is None:
            return None
        if self.compare == "<=":
            return value <= self.target
        if self.compare == ">=":
            return value >= self.target
        return abs(value) <= self.target

    def show(self, value: float | None) -> str:
        """The value in the goal's unit."""
        if value is None:
            return "–"
        if self.unit == "%":
            return f"{100 * value:.2f} %"
        if self.unit == "x":
            return f"{value:.2f}×"
        return f"{value:.3g} {self.unit}"

    def show_target(self) -> str:
        """The target, e.g. ``≤ 0.1 %``."""
        sign = {"<=": "≤ ", ">=": "≥ ", "abs<=": "within ±"}[self.compare]
        return sign + self.show(self.target)


#: The goals of "Robust in use" this benchmark scores (the issue's "Goals" section).
RAMP_GOALS = (
    Goal("rest_contact", "contact on samples at rest", 0.001, "<=", "%"),
    Goal("rest_force_p99", "force at rest, 99th percentile", 0.15, "<=", "N"),
    Goal("rmse_ratio", "force RMSE under contact / constant temperature", 1.2, "<=", "x"),
)
CONSTANT_GOALS = (
    Goal("false_events", "false contact events per minute at rest", 1.0, "<=", "/min"),
    Goal("onset_median", "onset delay, median", 10.0, "<=", "ms"),
    Goal("detected_above_1N", "contact samples above 1 N detected", 0.999, ">=", "%"),
)
HOLD_GOALS = (
    Goal("hold_bias", "force bias over the holds", 0.1, "abs<=", "N"),
    Goal("hold_rmse_ratio", "force RMSE over the holds / calibration test RMSE", 1.4, "<=", "x"),
)
#: Light presses (0.2-3 N): the decision where the contact net's margin is thin.
LIGHT_GOALS = (
    Goal("light_accuracy", "contact accuracy on light presses (0.2–3 N)", 0.87, ">=", "%"),
)
#: The calibration's own test presses (its training logs, the test split of its seed).
CALIBRATION_GOALS = (
    Goal("test_contact_errors", "contact errors on the calibration's test presses", 0.019, "<=",
         "%"),
)
#: An idle pad: tared, then left alone, nothing but the interrogator's noise at the tare
#: (:mod:`fbgforce.bench.bench_idle`, the worst of its draws).
IDLE_GOALS = (
    Goal("idle_false_events", "false contact events per minute on an idle pad (worst of 20 "
         "one-minute draws)", 1.0, "<=", "/min"),
)
#: A grip held through a ramp stays where it belongs: the holds' bound.
RAMP_HOLD_GOALS = (
    Goal("ramp_hold_bias", "force bias over a grip held through a ramp", 0.1, "abs<=", "N"),
)


#: Every goal by key, in the order of the tables.
GOALS: dict[str, Goal] = {g.key: g for g in (*RAMP_GOALS, *CONSTANT_GOALS, *IDLE_GOALS,
                                             *HOLD_GOALS, *RAMP_HOLD_GOALS, *LIGHT_GOALS,
                                             *CALIBRATION_GOALS)}


def _ratio(num: float | None, den: float | None) -> float | None:
    return num / den if num is not None and den else None


def _row(goal: Goal, scored_on: list[str], value: float | None) -> dict[str, Any]:
    return {**asdict(goal), "scored_on": scored_on, "value": value, "pass": goal.passes(value)}


def calibration_test(model_dir: Path, model: Any, engine: str) -> dict[str, Any] | None:
    """The ``fbgforce evaluate --json`` metrics of ``engine`` on the model's own test presses
    (its training logs, the test split of its seed); None when a training log named in
    ``model.json`` is gone."""
    from fbgforce.trainer.evaluate import evaluate

    paths = [d.get("path") for d in model.metadata.get("data", [])]
    if not paths or any(p is None or not Path(p).is_file() for p in paths):
        return None
    return evaluate(model_dir, paths, engine=engine, split="test", model=model)


def score(model_dir: Path, logs: Path, engine: str = "fixed",
          loaded: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every goal on the logs of ``logs/foreign.json``; see the module docstring.
    ``loaded``: logs already read, by path (filled in as they are read).

    Returns
    -------
    dict
        ``model``, ``engine``, ``logs``, ``calibration_test_rmse_force_N``, ``scored``
        (variant -> ``role``, ``data`` and the ``fbgforce evaluate --json`` metrics of its other
        log, and ``constant+rest`` for the constant-temperature group), ``goals`` (list of
        rows: ``key``, ``label``, ``target``, ``compare``, ``unit``, ``scored_on``, ``value``,
        ``pass``; every goal has a row, ``value`` and ``pass`` null where the logs of its role
        are missing), ``passed``, ``failed``, ``not_measured``.
    """
    from fbgforce.model import modeldir as fm

    model = fm.load(model_dir)
    manifest = load_manifest(logs, PROG)
    by_role = _logs_by_role(manifest, logs)
    run = _LogRuns(model_dir, model, engine, manifest, loaded)
    scored: dict[str, Any] = {}
    for role in SCORED_ROLES:
        for name in by_role[role]:
            scored[name] = {"role": role, **run([name]),
                            "data": [str(manifest[name]["other"])]}
    rows = _ramp_rows(by_role, manifest, scored, run)
    rows += _constant_rows(by_role, manifest, scored, run)
    rows += _idle_rows(scored.get("constant+rest", {}).get("noise_allows"), model_dir, engine)
    cal = calibration_test(model_dir, model, engine)
    cal_rmse = cal["rmse_force_N"] if cal is not None else None
    rows += _hold_rows(by_role["hold"], cal, cal_rmse, model_dir, run)
    if by_role["ramp_hold"]:
        m = run(by_role["ramp_hold"])
        rows += [_row(g, by_role["ramp_hold"], m["holds"]["force_bias_N"]) for g in RAMP_HOLD_GOALS]
    else:
        rows += [_row(g, [], None) for g in RAMP_HOLD_GOALS]
    if by_role["light"]:
        m = run(by_role["light"])
        rows += [_row(g, by_role["light"], m["contact_accuracy"]) for g in LIGHT_GOALS]
    else:
        rows += [_row(g, [], None) for g in LIGHT_GOALS]
    # A few presses of a short calibration fall in its test split (6 of 60): the count says
    # how far one training's figure can be read.
    cal_on = [f"calibration test, {cal['contact_timing']['presses']} presses"] if cal else []
    rows += [_row(g, cal_on, 1.0 - cal["contact_accuracy"] if cal else None)
             for g in CALIBRATION_GOALS]
    verdicts = [r["pass"] for r in rows]
    return {"model": str(model_dir), "engine": engine, "logs": str(logs),
            "calibration_test_rmse_force_N": cal_rmse, "scored": scored, "goals": rows,
            "passed": verdicts.count(True), "failed": verdicts.count(False),
            "not_measured": verdicts.count(None)}


def _logs_by_role(manifest: dict[str, Any], logs: Path) -> dict[str, list[str]]:
    """The manifest's variants grouped by the role they are scored in (other roles, such as
    ``calibration``, left out); stops the bench when no variant has a scored role."""
    by_role: dict[str, list[str]] = {role: [] for role in SCORED_ROLES}
    for name, entry in manifest.items():
        if entry.get("role") in by_role:
            by_role[entry["role"]].append(name)
    if not any(by_role.values()):
        fail(f"{logs}: no variant with a role among {', '.join(SCORED_ROLES)}; write them with "
             "python tests/foreign.py --out DIR const_temp ramp40K long_rests held_grips ...",
             PROG)
    return by_role


class _LogRuns:
    """The engine's runs of the variants' other logs, each log loaded and run only once;
    calling it with variant names gives the ``fbgforce evaluate --json`` metrics over their
    logs together."""

    def __init__(self, model_dir: Path, model: Any, engine: str, manifest: dict[str, Any],
                 loaded: dict[str, Any] | None) -> None:
        self.model_dir, self.model, self.engine = model_dir, model, engine
        self.manifest, self.loaded = manifest, loaded
        self.runs: dict[str, tuple[Any, dict[str, Any]]] = {}

    def __call__(self, names: list[str]) -> dict[str, Any]:
        """Metrics over the other logs of ``names``, each log loaded and run only once."""
        from fbgforce.recordings import dataset
        from fbgforce.trainer.evaluate import evaluate, run_recording

        for n in names:
            if n not in self.runs:
                path = self.manifest[n]["other"]
                print(f"{PROG}: {self.engine} on {path}", file=sys.stderr)
                cache = {} if self.loaded is None else self.loaded
                if str(path) not in cache:
                    cache[str(path)] = dataset.load(path)
                ds = cache[str(path)]
                self.runs[n] = (ds, run_recording(self.engine, self.model_dir, self.model, ds,
                                                  str(path)))
        return evaluate(self.model_dir, [self.runs[n][0] for n in names], engine=self.engine,
                        model=self.model, predictions=[self.runs[n][1] for n in names])


def _ramp_rows(by_role: dict[str, list[str]], manifest: dict[str, Any], scored: dict[str, Any],
               run: _LogRuns) -> list[dict[str, Any]]:
    """The ramp goals of every ramp log: its rest contact and rest force, and its force RMSE
    over the constant-temperature logs of the same device (none there: no ratio)."""
    rows = []
    for name in by_role["ramp"]:
        seed = manifest[name].get("device_seed")
        twins = [n for n in by_role["constant"] if manifest[n].get("device_seed") == seed]
        const = run(twins)["rmse_force_N"] if twins else None
        m = scored[name]
        values = {"rest_contact": m["at_rest"]["contact_fraction"],
                  "rest_force_p99": m["at_rest"]["force_p99_N"],
                  "rmse_ratio": _ratio(m["rmse_force_N"], const)}
        rows += [_row(g, [name] + (twins if g.key == "rmse_ratio" else []), values[g.key])
                 for g in RAMP_GOALS]
    if not by_role["ramp"]:
        rows += [_row(g, [], None) for g in RAMP_GOALS]
    return rows


def _constant_rows(by_role: dict[str, list[str]], manifest: dict[str, Any],
                   scored: dict[str, Any], run: _LogRuns) -> list[dict[str, Any]]:
    """The constant-temperature goals, scored on the ``constant`` and ``rest`` logs together
    (added to ``scored`` as ``constant+rest``)."""
    constant = by_role["constant"] + by_role["rest"]
    if not constant:
        return [_row(g, [], None) for g in CONSTANT_GOALS]
    m = run(constant)
    scored["constant+rest"] = {"role": "constant+rest", **m,
                               "data": [str(manifest[n]["other"]) for n in constant]}
    values = {"false_events": m["at_rest"]["false_events_per_min"],
              "onset_median": m["contact_timing"]["onset_delay_ms"]["median"],
              "detected_above_1N": m["contact_accuracy_above_1N"]}
    return [_row(g, constant, values[g.key]) for g in CONSTANT_GOALS]


def _idle_rows(noise_allows: dict[str, Any] | None, model_dir: Path, engine: str
               ) -> list[dict[str, Any]]:
    """The idle pad's goal at the interrogator noise of the constant-temperature logs' rests
    (the median grating's, which their ``evaluate`` run measured in ``noise_allows``:
    :func:`fbgforce.evaluation.onset_bound.bound`); not measured without those logs or
    their rests."""
    from fbgforce.bench.bench_idle import idle_events

    if noise_allows is None:
        return [_row(g, [], None) for g in IDLE_GOALS]
    noise_pm = noise_allows["noise_pm"]
    idle = idle_events(str(model_dir), noise_pm=noise_pm, engine=engine)
    return [_row(g, [f"idle at {noise_pm:.1f} pm"], idle["worst_per_min"]) for g in IDLE_GOALS]


def _hold_rows(holds: list[str], cal: dict[str, Any] | None, cal_rmse: float | None,
               model_dir: Path, run: _LogRuns) -> list[dict[str, Any]]:
    """The held-grip goals: the bias over the holds, and their RMSE over the calibration's
    test RMSE, which needs the model's training logs (without them the bench stops)."""
    if not holds:
        return [_row(g, [], None) for g in HOLD_GOALS]
    if cal is None:
        fail(f"{model_dir}: the model's training logs are not all readable; the held-grip "
             "goal compares with their test presses", PROG)
    m = run(holds)
    values = {"hold_bias": m["holds"]["force_bias_N"],
              "hold_rmse_ratio": _ratio(m["holds"]["rmse_force_N"], cal_rmse)}
    return [_row(g, holds, values[g.key]) for g in HOLD_GOALS]


def table(result: dict[str, Any]) -> str:
    """The goals as a markdown table, then one line per scored log with its context."""
    goals = GOALS
    lines = ["| goal | scored on | measured | target | |", "|---|---|---|---|---|"]
    for r in result["goals"]:
        g = goals[r["key"]]
        verdict = {True: "pass", False: "FAIL", None: "not measured"}[r["pass"]]
        lines.append(f"| {g.label} | {', '.join(r['scored_on']) or '–'} | {g.show(r['value'])} | "
                     f"{g.show_target()} | {verdict} |")
    lines.append("")
    for name, m in result["scored"].items():
        rest, holds, timing = m["at_rest"], m["holds"], m["contact_timing"]
        p90 = timing["onset_delay_ms"]["p90"]
        lines.append(
            f"- {name} ({m['role']}): contact {100 * m['contact_accuracy']:.1f} %, force RMSE "
            f"{m['rmse_force_N']:.3f} N; rest {rest['seconds']:.0f} s, {rest['false_events']} "
            f"false events, force at rest max {rest['force_max_N']:.3f} N; onset p90 "
            + ("–" if p90 is None else f"{p90:.1f} ms")
            + f", {timing['missed_presses']}/{timing['presses']} presses missed; "
            f"{holds['holds']} holds ({holds['seconds']:.0f} s)")
    if result["calibration_test_rmse_force_N"] is not None:
        lines.append(f"- calibration test presses: force RMSE "
                     f"{result['calibration_test_rmse_force_N']:.3f} N")
    allows = _noise_allows(result)
    if allows:
        lines.append(f"- the noise allows on the constant-temperature presses: onset "
                     f"{allows[0]}, {allows[1]} of the samples above 1 N "
                     "(fbgforce.evaluation.onset_bound)")
    away = _away_from_turns(result)
    if away:
        lines.append(f"- held grips away from the load's turns (the held samples more than "
                     f"{away[2]} after one): force bias {away[0]}, RMSE {away[1]} of the "
                     "calibration test RMSE")
    direction = _by_direction(result)
    if direction:
        lines.append(f"- held grips by the load's direction: force bias {direction} (a "
                     "friction reads the falls high and the rises low, a level error both alike)")
    return "\n".join(lines)


def _held_grips(result: dict[str, Any]) -> dict[str, Any] | None:
    """``holds`` of the one held-grip log's ``evaluate`` run; None without exactly one."""
    holds = [m["holds"] for m in result["scored"].values() if m.get("role") == "hold"]
    return holds[0] if len(holds) == 1 else None


def _away_from_turns(result: dict[str, Any]) -> tuple[str, str, str] | None:
    """The held grips' force bias and RMSE ratio over the held samples away from the load's
    turns (``holds.away_from_turns`` of their ``evaluate`` run), as text, and how long after a
    turn counts as near it; None without held grips or samples away from turns."""
    holds = _held_grips(result)
    away = holds.get("away_from_turns") if holds else None
    if not away or away["force_bias_N"] is None:
        return None
    ratio = _ratio(away["rmse_force_N"], result["calibration_test_rmse_force_N"])
    return (f"{away['force_bias_N']:+.3f} N", "–" if ratio is None else f"{ratio:.2f}×",
            f"{away['after_turn_s']:g} s")


def _by_direction(result: dict[str, Any]) -> str | None:
    """The held grips' force bias over the held samples whose load rises, then falls
    (``holds.by_direction`` of their ``evaluate`` run), as text; None without held grips."""
    holds = _held_grips(result)
    parts = holds.get("by_direction") if holds else None
    if not parts:
        return None
    return " / ".join("–" if parts[d]["force_bias_N"] is None else
                      f"{parts[d]['force_bias_N']:+.3f} N" for d in ("rising", "falling"))


def _noise_allows(result: dict[str, Any]) -> tuple[str, str] | None:
    """The median onset and the share of the samples above 1 N that the constant-temperature
    logs' noise allows any decision (``noise_allows`` of their ``evaluate`` run), as text; None
    where those logs or their rests are missing."""
    from fbgforce.evaluation.onset_bound import delay_text, median_onset_ms

    allows = result["scored"].get("constant+rest", {}).get("noise_allows")
    if not allows or not allows.get("onset_bound_ms"):
        return None
    found = allows["detected_above_1N"]
    return (delay_text(median_onset_ms(allows)),
            "–" if found is None else f"{100 * found:.2f} %")


#: What ``--without STAGE`` sets in a copy of each member's model: the in-use stage off, the
#: rest of the model as trained.
WITHOUT: dict[str, dict[str, Any]] = {
    "hold_gain": {"hold_gain": 0.0, "hold_settle": 0, "hold_band_N": 0.0, "hold_band_frac": 0.0,
                  "hold_shift": 0, "hold_ramp_shift": 0},
    "creep_term": {"track_creep": 0.0, "track_creep_shift": 0},
    "tracker": {"track_shift": 0, "track_settle": 0, "track_step_max_pm": 0.0,
                "track_limit_pm": 0.0, "track_creep": 0.0, "track_creep_shift": 0},
    "decision": {"contact_on_margin": 0.0, "contact_off_margin": 0.0, "contact_rise_samples": 1,
                 "contact_cusum_h": 0.0, "contact_cusum_k": 0.0, "contact_cusum_lo": 0.0,
                 "contact_cusum_hi": 0.0},
}
#: The decision's rules ``--without`` may also name: the model's own fields for that rule
#: (``metadata.decision_rules``), scored beside the default.
RULES = ("schmitt", "cusum")
#: The file ``family.json`` that ``python tests/foreign.py --family`` writes.
FAMILY_MANIFEST = "family.json"


def worst(goal: Goal, values: dict[str, float | None]) -> tuple[str | None, float | None]:
    """The member whose value is furthest on the failing side of ``goal`` (largest for ``<=``,
    smallest for ``>=``, largest magnitude for ``abs<=``), and that value."""
    measured = {m: v for m, v in values.items() if v is not None}
    if not measured:
        return None, None
    key = {"<=": lambda m: measured[m], ">=": lambda m: -measured[m],
           "abs<=": lambda m: abs(measured[m])}[goal.compare]
    member = max(measured, key=key)
    return member, measured[member]


def _cli(args: list[str]) -> None:
    """Run an ``fbgforce`` command in this process; exits 2 with its message when it fails."""
    from fbgforce.cli import main as fbgforce_main

    code = fbgforce_main(args)
    if code:
        fail(f"fbgforce {' '.join(args)} exited {code}", PROG)


#: The calibration a family member is trained on unless ``--calibration`` names another:
#: tests/foreign.py's ``calib_1K``, about a kelvin.
DEFAULT_CALIBRATION = "calib_1K"


def member_model(logs: Path, model_dir: Path, seed: int, train_options: list[str],
                 calibration: str = DEFAULT_CALIBRATION) -> Path:
    """``model_dir`` trained (``fbgforce train`` with ``train_options`` on the member's
    ``calibration`` log, a variant with that role) and exported, unless it already holds a
    model."""
    if not (model_dir / "model.json").is_file():
        manifest = load_manifest(logs, PROG)
        calib = {name: e["train"] for name, e in manifest.items()
                 if e.get("role") == "calibration"}
        if calibration not in calib:
            fail(f"{logs}: no calibration {calibration!r} to train on; it has "
                 f"{', '.join(calib) or 'none'}", PROG)
        print(f"{PROG}: training {model_dir} on {calib[calibration]}", file=sys.stderr)
        _cli(["train", "--data", str(calib[calibration]), "--out", str(model_dir), "--seed",
              str(seed), *train_options])
    if not (model_dir / "model.fbgm").is_file():
        _cli(["export", "--model", str(model_dir)])
    return model_dir


def without(model_dir: Path, stage: str, out: Path) -> Path:
    """A copy of ``model_dir`` in ``out`` with the in-use ``stage`` off (:data:`WITHOUT`), or
    with the decision's rule ``stage`` of ``metadata.decision_rules`` (``fbgforce train
    --decision``) when ``stage`` is one of those, exported."""
    import shutil
    from dataclasses import replace

    from fbgforce.model import modeldir as fm

    out.mkdir(parents=True, exist_ok=True)
    for f in model_dir.iterdir():
        if f.is_file():
            shutil.copy2(f, out / f.name)
    model = fm.load(out)
    if stage in WITHOUT:
        fields = WITHOUT[stage]
    else:
        fields = model.metadata.get("decision_rules", {}).get(stage)
        if fields is None:
            fail(f"{model_dir}: the model records no decision rule {stage!r} "
                 "(metadata.decision_rules; train it again)", PROG)
    model.in_use = replace(model.in_use, **fields)
    fm.save(model, out)
    _cli(["export", "--model", str(out)])
    return out


def family(root: Path, work: Path, engine: str = "fixed", seed: int = 0,
           train_options: list[str] | None = None, stages: list[str] | None = None,
           members: list[str] | None = None,
           calibration: str = DEFAULT_CALIBRATION) -> dict[str, Any]:
    """Every goal on every member of ``root/family.json``, and the worst member of each.

    Each member's model is ``work/MEMBER/model`` (trained on its ``calibration`` log and
    exported by :func:`member_model` when missing), scored by :func:`score` on the member's
    logs; for
    each of ``stages`` a copy of it (:func:`without`) is scored beside it on the same logs.

    Returns
    -------
    dict
        ``members`` (member -> its :func:`score` result, with ``without`` -> {stage: the
        copy's result}), ``goals`` (rows: ``key``, ``label``, ``target``, ``values`` by member,
        ``worst_member``, ``worst``, ``pass``, and ``without`` -> {stage: ``values``,
        ``worst_member``, ``worst``, ``pass``}), ``stages``, ``engine``, ``passed``,
        ``failed``, ``not_measured`` (of the worst members' values, default model).
    """
    path = root / FAMILY_MANIFEST
    try:
        listed = json.loads(path.read_text())["members"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        fail(f"{path}: not a family manifest ({type(exc).__name__}: {exc}); write one with: "
             f"python tests/foreign.py --family --out {root}", PROG)
    chosen = members or list(listed)
    unknown = [m for m in chosen if m not in listed]
    if unknown:
        fail(f"{path}: no member {', '.join(unknown)}; it has {', '.join(listed)}", PROG)
    stages = list(stages or [])
    results: dict[str, Any] = {}
    for member in chosen:
        logs = (path.parent / listed[member]["manifest"]).parent
        model_dir = member_model(logs, work / member / "model", seed, train_options or [],
                                 calibration)
        loaded: dict[str, Any] = {}      # each log read once for the model and its copies
        results[member] = score(model_dir, logs, engine, loaded)
        results[member]["without"] = {
            stage: score(without(model_dir, stage, work / member / f"without_{stage}"), logs,
                         engine, loaded) for stage in stages}
    return summarise(results, stages, str(path), engine)


def summarise(results: dict[str, Any], stages: list[str], family_path: str = "",
              engine: str = "fixed") -> dict[str, Any]:
    """:func:`family`'s result from its members' :func:`score` results (each with ``without``
    -> {stage: result} for every stage of ``stages``)."""
    def summary(goal: Goal, pick: Callable[[dict[str, Any]], dict[str, Any]]) -> dict[str, Any]:
        values = {m: next(g["value"] for g in pick(r)["goals"] if g["key"] == goal.key)
                  for m, r in results.items()}
        member, value = worst(goal, values)
        return {"values": values, "worst_member": member, "worst": value,
                "pass": goal.passes(value)}

    rows = []
    for key, goal in GOALS.items():
        row = {"key": key, "label": goal.label, "target": goal.target,
               **summary(goal, lambda r: r)}
        row["without"] = {stage: summary(goal, lambda r, st=stage: r["without"][st])
                          for stage in stages}
        rows.append(row)
    verdicts = [r["pass"] for r in rows]
    return {"family": family_path, "engine": engine, "stages": stages, "members": results,
            "goals": rows, "passed": verdicts.count(True), "failed": verdicts.count(False),
            "not_measured": verdicts.count(None)}


def family_table(result: dict[str, Any], stage: str | None = None) -> str:
    """The goals by member as a markdown table, the worst member last; with ``stage`` (one of
    ``result["stages"]``) each cell reads ``default / the copy``."""
    members = list(result["members"])
    head = "| goal | target | " + " | ".join(members) + " | worst | |"
    lines = [head, "|" + "---|" * (len(members) + 4)]
    for r in result["goals"]:
        g = GOALS[r["key"]]
        other = r["without"][stage] if stage else None

        def cell(member: str) -> str:
            text = g.show(r["values"][member])
            return text + (f" / {g.show(other['values'][member])}" if other else "")
        worst_text = (f"{g.show(r['worst'])} ({r['worst_member']})" if r["worst_member"]
                      else "–")
        if other:
            worst_text += (f" / {g.show(other['worst'])} ({other['worst_member']})"
                           if other["worst_member"] else " / –")
        words = {True: "pass", False: "FAIL", None: "not measured"}
        verdict = words[r["pass"]] + (f" / {words[other['pass']]}" if other else "")
        lines.append(f"| {g.label} | {g.show_target()} | " + " | ".join(map(cell, members))
                     + f" | {worst_text} | {verdict} |")
    if not stage:
        # Beside the onset and detection goals: how far any decision could get on these pads.
        allows = {m: _noise_allows(result["members"][m]) for m in members}
        for i, label in enumerate(("onset the noise allows, median",
                                   "samples above 1 N the noise allows")):
            lines.append(f"| {label} | | "
                         + " | ".join(a[i] if a else "–" for a in allows.values()) + " | | |")
        # Beside the held-grip goals: the same grips away from the load's turns.
        away = {m: _away_from_turns(result["members"][m]) for m in members}
        after = next((a[2] for a in away.values() if a), None)
        if after:
            for i, label in enumerate(("force bias over the holds",
                                       "force RMSE over the holds / calibration test RMSE")):
                lines.append(f"| {label}, more than {after} after a turn of the load | | "
                             + " | ".join(a[i] if a else "–" for a in away.values()) + " | | |")
        direction = {m: _by_direction(result["members"][m]) for m in members}
        if any(direction.values()):
            lines.append("| force bias over the holds, load rising / falling | | "
                         + " | ".join(d or "–" for d in direction.values()) + " | | |")
    if stage:
        what = (f"with the {stage} decision rule" if stage in RULES else f"without {stage}")
        lines += ["", f"Each cell: the default / the same model {what}."]
    return "\n".join(lines)


def family_tables(result: dict[str, Any]) -> str:
    """:func:`family_table` of the defaults, then one per stage of ``result["stages"]``."""
    return "\n\n".join([family_table(result)]
                        + [family_table(result, stage) for stage in result["stages"]])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, metavar="MODEL_DIR",
                    help="model directory (exported for --engine fixed)")
    ap.add_argument("--logs", type=Path, metavar="DIR",
                    help="directory with foreign.json (python tests/foreign.py --out DIR ...)")
    ap.add_argument("--family", type=Path, metavar="DIR",
                    help="instead of --model and --logs: every member of DIR/family.json "
                         "(python tests/foreign.py --family --out DIR), each trained with the "
                         "default fbgforce train on its calibration log into --work, a table "
                         "of goals by member with the worst member beside the target")
    ap.add_argument("--work", type=Path, metavar="DIR",
                    help="with --family: where each member's model goes (DIR/MEMBER/model; "
                         "a model already there is scored as it is)")
    ap.add_argument("--member", action="append", metavar="NAME",
                    help="with --family: score only this member (repeatable)")
    ap.add_argument("--seed", type=int, default=0, help="with --family: the training seed")
    ap.add_argument("--calibration", default=DEFAULT_CALIBRATION, metavar="VARIANT",
                    help="with --family: the calibration log each member trains on "
                         "(default %(default)s, about a kelvin; calib_3K: a few kelvin; use a "
                         "--work of its own)")
    ap.add_argument("--train-option", action="append", default=[], metavar="OPT",
                    help="with --family: an option for fbgforce train, e.g. "
                         "--train-option=--hold-augment=0 (repeatable; use a --work of its own)")
    ap.add_argument("--without", action="append", choices=sorted(WITHOUT) + list(RULES),
                    metavar="STAGE",
                    help="with --family: also score a copy of each model with this in-use "
                         f"stage off ({', '.join(sorted(WITHOUT))}), or with the contact "
                         f"decision's other rule ({', '.join(RULES)}: the fields the trainer "
                         "recorded for it), side by side (repeatable: a table each)")
    ap.add_argument("--engine", choices=("fixed", "float"), default="fixed",
                    help="fixed (the C fixed-point runtime, default) or float (numpy)")
    ap.add_argument("--combine", nargs="+", type=Path, metavar="JSON",
                    help="instead: the tables of several --family --json outputs (members "
                         "scored in separate runs, with the same --without stages) as one")
    ap.add_argument("--json", action="store_true",
                    help="print one JSON object on stdout instead of the table")
    args = ap.parse_args(argv)
    if args.combine:
        members: dict[str, Any] = {}
        stages: list[str] | None = None
        for f in args.combine:
            try:
                part = json.loads(f.read_text())
                members.update(part["members"])
                stages = part.get("stages", []) if stages is None else stages
                if part.get("stages", []) != stages:
                    fail(f"{f}: scored with --without {part.get('stages')}, not {stages}", PROG)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                fail(f"{f}: not a bench_in_use --family --json output "
                     f"({type(exc).__name__}: {exc})", PROG)
        result = summarise(members, stages or [])
        print(json.dumps(result, default=json_default) if args.json else family_tables(result))
        return 0
    if args.family is not None:
        if args.work is None:
            fail("--family needs --work DIR (where the members' models go)", PROG)
        try:
            result = family(args.family, args.work, args.engine, args.seed, args.train_option,
                            args.without, args.member, args.calibration)
        except InputError as exc:
            fail(str(exc), PROG)
        print(json.dumps(result, default=json_default) if args.json else family_tables(result))
        return 0
    if args.model is None or args.logs is None:
        fail("give --model and --logs, or --family and --work", PROG)
    if not (args.model / "model.json").is_file():
        fail(f"{args.model}: not a model directory (no model.json)", PROG)
    try:
        result = score(args.model, args.logs, args.engine)
    except InputError as exc:
        fail(str(exc), PROG)
    if args.json:
        print(json.dumps(result, default=json_default))
    else:
        print(table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
