"""Robust in use: a model on recordings of the conditions it is used in, goal by goal.

Usage::

    python tests/foreign.py --out DIR --presses 100 calib_1K const_temp ramp20K ramp40K \\
        ramp40K_fast long_rests held_grips ramp_hold               # writes the logs
    fbgforce train --data DIR/calib_1K_A.csv --out MODEL && fbgforce export --model MODEL
    python -m fbgforce.bench.bench_in_use --model MODEL --logs DIR [--engine fixed|float] [--json]

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
- held grips: force bias over the holds, force RMSE over them against the model's own
  calibration test RMSE (its training logs, test split, same engine);
- a grip held through a ramp: force bias over the hold (the holds' bound).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from fbgforce.bench.bench_generalisation import fail, load_manifest
from fbgforce.errors import InputError
from fbgforce.jsonutil import json_default

PROG = "bench_in_use"
#: Roles of manifest entries that are scored, in the order of the table.
SCORED_ROLES = ("ramp", "constant", "rest", "hold", "ramp_hold")


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
    Goal("onset_median", "onset delay, median", 12.0, "<=", "ms"),
    Goal("detected_above_1N", "contact samples above 1 N detected", 0.999, ">=", "%"),
)
HOLD_GOALS = (
    Goal("hold_bias", "force bias over the holds", 0.1, "abs<=", "N"),
    Goal("hold_rmse_ratio", "force RMSE over the holds / calibration test RMSE", 1.2, "<=", "x"),
)
#: A grip held through a ramp stays where it belongs: the holds' bound.
RAMP_HOLD_GOALS = (
    Goal("ramp_hold_bias", "force bias over a grip held through a ramp", 0.1, "abs<=", "N"),
)


def _ratio(num: float | None, den: float | None) -> float | None:
    return num / den if num is not None and den else None


def _row(goal: Goal, scored_on: list[str], value: float | None) -> dict[str, Any]:
    return {**asdict(goal), "scored_on": scored_on, "value": value, "pass": goal.passes(value)}


def calibration_test_rmse(model_dir: Path, model: Any, engine: str) -> float | None:
    """Force RMSE of ``engine`` on the model's own test presses (its training logs, the test
    split of its seed); exits 2 when a training log named in ``model.json`` is gone."""
    from fbgforce.trainer.evaluate import evaluate

    paths = [d.get("path") for d in model.metadata.get("data", [])]
    if not paths or any(p is None or not Path(p).is_file() for p in paths):
        fail(f"{model_dir}: the model's training logs {paths} are not all readable; the held-"
             "grip goal compares with their test presses", PROG)
    return evaluate(model_dir, paths, engine=engine, split="test", model=model)["rmse_force_N"]


def score(model_dir: Path, logs: Path, engine: str = "fixed") -> dict[str, Any]:
    """Every goal on the logs of ``logs/foreign.json``; see the module docstring.

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
    from fbgforce import dataset
    from fbgforce import model as fm
    from fbgforce.trainer.evaluate import evaluate, run_recording

    model = fm.load(model_dir)
    manifest = load_manifest(logs, PROG)
    by_role: dict[str, list[str]] = {role: [] for role in SCORED_ROLES}
    for name, entry in manifest.items():
        if entry.get("role") in by_role:
            by_role[entry["role"]].append(name)
    if not any(by_role.values()):
        fail(f"{logs}: no variant with a role among {', '.join(SCORED_ROLES)}; write them with "
             "python tests/foreign.py --out DIR const_temp ramp40K long_rests held_grips ...",
             PROG)

    runs: dict[str, tuple[Any, dict[str, Any]]] = {}

    def run(names: list[str]) -> dict[str, Any]:
        """Metrics over the other logs of ``names``, each log loaded and run only once."""
        for n in names:
            if n not in runs:
                path = manifest[n]["other"]
                print(f"{PROG}: {engine} on {path}", file=sys.stderr)
                ds = dataset.load(path)
                runs[n] = (ds, run_recording(engine, model_dir, model, ds, str(path)))
        return evaluate(model_dir, [runs[n][0] for n in names], engine=engine, model=model,
                        predictions=[runs[n][1] for n in names])

    scored: dict[str, Any] = {}
    for role in SCORED_ROLES:
        for name in by_role[role]:
            scored[name] = {"role": role, **run([name]),
                            "data": [str(manifest[name]["other"])]}
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
    constant = by_role["constant"] + by_role["rest"]
    if constant:
        m = run(constant)
        scored["constant+rest"] = {"role": "constant+rest", **m,
                                   "data": [str(manifest[n]["other"]) for n in constant]}
        values = {"false_events": m["at_rest"]["false_events_per_min"],
                  "onset_median": m["contact_timing"]["onset_delay_ms"]["median"],
                  "detected_above_1N": m["contact_accuracy_above_1N"]}
        rows += [_row(g, constant, values[g.key]) for g in CONSTANT_GOALS]
    else:
        rows += [_row(g, [], None) for g in CONSTANT_GOALS]
    cal_rmse = None
    if by_role["hold"]:
        cal_rmse = calibration_test_rmse(model_dir, model, engine)
        m = run(by_role["hold"])
        values = {"hold_bias": m["holds"]["force_bias_N"],
                  "hold_rmse_ratio": _ratio(m["holds"]["rmse_force_N"], cal_rmse)}
        rows += [_row(g, by_role["hold"], values[g.key]) for g in HOLD_GOALS]
    else:
        rows += [_row(g, [], None) for g in HOLD_GOALS]
    if by_role["ramp_hold"]:
        m = run(by_role["ramp_hold"])
        rows += [_row(g, by_role["ramp_hold"], m["holds"]["force_bias_N"]) for g in RAMP_HOLD_GOALS]
    else:
        rows += [_row(g, [], None) for g in RAMP_HOLD_GOALS]
    verdicts = [r["pass"] for r in rows]
    return {"model": str(model_dir), "engine": engine, "logs": str(logs),
            "calibration_test_rmse_force_N": cal_rmse, "scored": scored, "goals": rows,
            "passed": verdicts.count(True), "failed": verdicts.count(False),
            "not_measured": verdicts.count(None)}


def table(result: dict[str, Any]) -> str:
    """The goals as a markdown table, then one line per scored log with its context."""
    goals = {g.key: g for g in (*RAMP_GOALS, *CONSTANT_GOALS, *HOLD_GOALS, *RAMP_HOLD_GOALS)}
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
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, type=Path, metavar="MODEL_DIR",
                    help="model directory (exported for --engine fixed)")
    ap.add_argument("--logs", required=True, type=Path, metavar="DIR",
                    help="directory with foreign.json (python tests/foreign.py --out DIR ...)")
    ap.add_argument("--engine", choices=("fixed", "float"), default="fixed",
                    help="fixed (the C fixed-point runtime, default) or float (numpy)")
    ap.add_argument("--json", action="store_true",
                    help="print one JSON object on stdout instead of the table")
    args = ap.parse_args(argv)
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
