"""False contact events on an idle pad: minutes of nothing but the interrogator's white noise
at the tare, through a model's whole pipeline, for several noise draws.

Usage::

    python -m fbgforce.bench.bench_idle --model DIR [--noise-pm 5] [--minutes 1] [--draws 20] [--engine fixed] [--json]

The simplest scene a gripper meets is rest: tared, then left alone. Every grating, the
temperature reference included, reads its tare plus independent Gaussian noise of
``--noise-pm`` (the interrogator's; ``fbgforce train`` prints a calibration's as its rest
noise), and the engine runs from a fresh state set to that baseline, as after a tare. Each
draw of the noise is a pad left idle once; the false events a minute differ from draw to draw
because what the first samples leave in the pipeline's states stays there for as long as the
pad rests (docs/fixed-point.md, "Temperature reference"). The rests of a recording never
last this long: the presses between them put the states back. A first second (the filter's
and the averages' start) runs before the minutes counted. The trainer reads the CUSUM's
threshold on idle pads of its own too (two minutes each of the calibration's rest noise,
docs/runtime.md, "In use"); these are other draws, at the noise given here.
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np


def idle_events(model_dir: str, noise_pm: float = 5.0, minutes: float = 1.0, draws: int = 20,
                engine: str = "fixed", seed: int = 0) -> dict[str, Any]:
    """False contact events a minute of ``engine`` on ``draws`` idle pads (module docstring),
    and the share of samples in contact."""
    from fbgforce import samples
    from fbgforce.evaluation import engines
    from fbgforce.model import modeldir
    from fbgforce.trainer.synthetic import IDLE_WARMUP_S

    model = modeldir.load(model_dir)
    rate = samples.model_rate_hz(model) or 1000.0
    # Not counted, as the trainer's idle pads are not: the filter's warm-up, the averages' start.
    skip = int(round(IDLE_WARMUP_S * rate))
    n = skip + int(round(minutes * 60.0 * rate))
    base = np.asarray(model.baseline_nm, dtype=np.float64)
    rng = np.random.default_rng(seed)
    per_draw = []
    for _ in range(draws):
        wl = base + rng.normal(0.0, noise_pm / 1000.0, (n, base.size))
        out = engines.run_engine(engine, model_dir, model, wl, base)
        contact = np.asarray(out["contact"], dtype=bool)[skip:]
        events = int(np.sum(contact[1:] & ~contact[:-1])) + int(contact[0])
        per_draw.append({"false_events_per_min": events / ((n - skip) / rate / 60.0),
                         "contact_share": float(contact.mean())})
    rates = np.array([d["false_events_per_min"] for d in per_draw])
    return {"model": str(model_dir), "engine": engine, "noise_pm": noise_pm, "minutes": minutes,
            "seed": seed, "draws": per_draw,
            "worst_per_min": float(rates.max()) if rates.size else None,
            "median_per_min": float(np.median(rates)) if rates.size else None}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbgforce.bench.bench_idle",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, metavar="DIR", help="a trained model directory "
                    "(exported, for the C engines)")
    ap.add_argument("--noise-pm", type=float, default=5.0, metavar="PM",
                    help="the interrogator's white noise per grating (5 pm)")
    ap.add_argument("--minutes", type=float, default=1.0, metavar="MIN",
                    help="how long each pad is left idle (1)")
    ap.add_argument("--draws", type=int, default=20, metavar="N", help="noise draws (20)")
    ap.add_argument("--engine", default="fixed", choices=("float", "onnx", "cfloat", "fixed",
                                                          "intref"),
                    help="the engine (fixed: the C fixed point, the default)")
    ap.add_argument("--seed", type=int, default=0, help="the noise draws' seed (0)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    from fbgforce.cliargs import fail
    from fbgforce.errors import InputError

    if not args.noise_pm > 0 or not args.minutes > 0 or args.draws < 1:
        return fail("bench_idle: --noise-pm and --minutes must be above 0 and --draws at "
                    "least 1", args.json)
    try:
        out = idle_events(args.model, args.noise_pm, args.minutes, args.draws, args.engine,
                          args.seed)
    except (InputError, OSError, ValueError) as exc:
        return fail(f"bench_idle: {exc}", args.json)
    if args.json:
        print(json.dumps(out))
        return 0
    rates = ", ".join(f"{d['false_events_per_min']:.1f}" for d in out["draws"])
    print(f"idle pad, {args.noise_pm:g} pm, {args.minutes:g} min x {args.draws} draws "
          f"({args.engine}): false contact events a minute {rates}; worst "
          f"{out['worst_per_min']:.1f}, median {out['median_per_min']:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
