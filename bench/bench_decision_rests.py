"""Do the rests the contact decision's threshold was read on look like a pad's real long rests?

Usage::

    python -m fbgforce.bench.bench_decision_rests --model DIR --data long_rests.csv [...] [--json]

The trainer reads the CUSUM's threshold on the calibration's own rests (under a second each)
and on synthetic long rests it makes from the calibration (``fbgforce.trainer.synthetic.
decision_rests``), and records in ``model.json`` the contact net's margin quantiles on both
(``metadata.decision_rests``). Here the model's float pipeline
(:func:`fbgforce.model.floatref.predict`: the filter, the at-rest tracker, the nets; run by
:func:`fbgforce.bench.bench_onset_statistic.load`) runs on labelled recordings of the same pad
that hold long rests, each tared on its own contact-free samples, and the same quantiles are read on their long rests: every rest at least
``--min-rest-s`` long, from :data:`~fbgforce.trainer.synthetic.REST_AUGMENT_SETTLE_S` after the
release (where the synthetic rests are read from) to
:data:`~fbgforce.evaluation.metrics.REST_GAP_S` before the next press.

Synthetic rests that read lighter than the real ones set a threshold too low (false contact
events in use); heavier, one too high (onset lost). docs/tradeoff.md ("Each rest on its own,
the pad recovering") quotes it on the foreign family.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce.bench.bench_onset_statistic import load
from fbgforce.cliargs import fail
from fbgforce.errors import InputError
from fbgforce.evaluation.metrics import REST_GAP_S
from fbgforce.recordings.stagelog import runs
from fbgforce.trainer.synthetic import DECISION_REST_S, REST_AUGMENT_SETTLE_S

PROG = "bench_decision_rests"


def long_rest_margins(margin: np.ndarray, contact: np.ndarray, rate_hz: float,
                      min_rest_s: float) -> np.ndarray:
    """The margins on the long rests of one recording: every run out of labelled contact
    after a press (not the recording's start) at least ``min_rest_s`` long, from
    :data:`REST_AUGMENT_SETTLE_S` after the release to :data:`REST_GAP_S` before the next
    press (or the recording's end)."""
    settle = int(round(REST_AUGMENT_SETTLE_S * rate_hz))
    gap = int(round(REST_GAP_S * rate_hz))
    out = [np.empty(0)]
    for a, b in zip(*runs(~np.asarray(contact, dtype=bool))):
        if a == 0 or (b - a) < min_rest_s * rate_hz:
            continue
        end = b - gap if b < contact.size else b
        out.append(margin[a + settle:end])
    return np.concatenate(out)


def measure(model_dir: str | Path, data: Sequence[str | Path],
            min_rest_s: float = DECISION_REST_S[0]) -> dict[str, Any]:
    """The margin quantiles the model recorded for its decision's rests (``calibration``,
    ``long``) beside the same quantiles on the long rests of ``data`` (``recorded``)."""
    model, recordings = load(model_dir, data)
    rested = model.metadata.get("decision_rests")
    if not rested:
        raise InputError(f"{model_dir}: model.json records no decision_rests (trained by an "
                         "earlier release, or with a decision that reads no rests); train "
                         "it again")
    margins = [long_rest_margins(r["margin"], r["contact"], r["rate_hz"], min_rest_s)
               for r in recordings]
    minutes = sum(m.size / r["rate_hz"] / 60.0 for m, r in zip(margins, recordings))
    recorded = np.concatenate(margins)
    if not recorded.size:
        raise InputError(f"no rest of at least {min_rest_s:g} s after a press in "
                         f"{', '.join(map(str, data))}")
    quantiles = {key: float(np.quantile(recorded, float(key) / 100.0))
                 for key in rested["long"]["margin_quantiles"]}
    return {"model": str(model_dir), "data": list(map(str, data)), "min_rest_s": min_rest_s,
            "calibration": rested["calibration"], "long": rested["long"],
            "recorded": {"minutes": minutes,
                         "margin_quantiles": quantiles}}


def table(out: dict[str, Any]) -> str:
    """The quantiles side by side, one row each, with the minutes each was read on."""
    cols = (("the calibration's rests", out["calibration"]),
            ("synthetic long rests", out["long"]),
            ("the recordings' long rests", out["recorded"]))
    lines = [f"{'margin quantile':16s}" + "".join(f"{name:>29s}" for name, _ in cols)]
    for key in out["recorded"]["margin_quantiles"]:
        cells = []
        for _, col in cols:
            value = col["margin_quantiles"].get(key)
            cells.append(f"{'-' if value is None else f'{value:.2f}':>29s}")
        lines.append(f"{key + ' %':16s}" + "".join(cells))
    lines.append(f"{'minutes':16s}" + "".join(f"{col['minutes']:>29.1f}" for _, col in cols))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=f"python -m fbgforce.bench.{PROG}",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, metavar="DIR", help="a trained model directory")
    ap.add_argument("--data", required=True, nargs="+", metavar="FILE",
                    help="labelled recordings of the same pad with long rests (CSV/npz), e.g. "
                         "tests/foreign.py's long_rests logs")
    ap.add_argument("--min-rest-s", type=float, default=DECISION_REST_S[0], metavar="S",
                    help="the shortest rest read, seconds (default %(default)g, the synthetic "
                         "rests' shortest)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    if not args.min_rest_s > REST_AUGMENT_SETTLE_S + REST_GAP_S:
        return fail(f"{PROG}: --min-rest-s must be above "
                    f"{REST_AUGMENT_SETTLE_S + REST_GAP_S:g} s", args.json)
    try:
        out = measure(args.model, args.data, args.min_rest_s)
    except (InputError, OSError, ValueError) as exc:
        return fail(f"{PROG}: {exc}", args.json)
    print(json.dumps(out) if args.json else table(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
