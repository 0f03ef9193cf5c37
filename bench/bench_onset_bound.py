"""How early any contact decision could find the presses of a recording: the information
bound on onset delay, from the interrogator's noise and the pad's sensitivity
(:mod:`fbgforce.evaluation.onset_bound`, which ``fbgforce coverage`` also reports on a
calibration).

Usage::

    python -m fbgforce.bench.bench_onset_bound --data const_temp.csv rests.csv [--per-min 1] [--json]

docs/tradeoff.md ("How quick the decision can be") quotes the bound beside the frontier of
``fbgforce tradeoff --decision`` on the foreign family.
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Sequence


def measure(data: Sequence[str], per_min: float = 1.0) -> dict[str, Any]:
    """:func:`fbgforce.evaluation.onset_bound.bound` over the recordings of ``data``, with
    their paths; stops with an InputError when none has rests to measure the noise on."""
    from fbgforce.errors import InputError
    from fbgforce.evaluation.onset_bound import MIN_REST_PAIRS, bound
    from fbgforce.recordings import dataset

    out = bound([dataset.load(p) for p in data], per_min)
    if out is None:
        raise InputError(f"no {MIN_REST_PAIRS} samples of rest clear of contact to measure "
                         "the noise on", path=", ".join(map(str, data)))
    return {"data": list(map(str, data)), **out}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbgforce.bench.bench_onset_bound",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, nargs="+", metavar="FILE",
                    help="labelled recordings with presses and rests (CSV/npz)")
    ap.add_argument("--per-min", type=float, default=1.0, metavar="N",
                    help="false contact events per minute at rest the detector may raise (1)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    from fbgforce.cliargs import fail
    from fbgforce.errors import InputError
    from fbgforce.evaluation.onset_bound import (SENSITIVITY_MIN_N, ZERO_SAMPLES, delay_text,
                                                 lag_text)

    if not args.per_min > 0:
        return fail("bench_onset_bound: --per-min must be above 0", args.json)
    try:
        out = measure(args.data, args.per_min)
    except (InputError, OSError, ValueError) as exc:
        return fail(f"bench_onset_bound: {exc}", args.json)
    if args.json:
        print(json.dumps(out))
    elif not out["presses"]:
        print(f"no press with {ZERO_SAMPLES} unloaded samples before it and 5 above "
              f"{SENSITIVITY_MIN_N:g} N")
    else:
        b = out["onset_bound_ms"]
        noise = out["force_noise_N"]
        print(f"{out['presses']} presses, noise {out['noise_pm']:.1f} pm per grating, force "
              f"noise of the matched filter "
              f"{'unbounded' if noise is None else f'{noise:.3f} N'} per sample"
              f"{lag_text(out)}: "
              f"no decision within {args.per_min:g} false event"
              f"{'' if args.per_min == 1 else 's'} a minute finds them sooner "
              f"than {delay_text(b['median'])} median ({delay_text(b['p90'])} p90) after the "
              f"label, "
              f"nor more than {100 * out['detected_above_1N']:.2f} % of their samples above "
              f"{SENSITIVITY_MIN_N:g} N")
    return 0


if __name__ == "__main__":
    sys.exit(main())
