"""How a model reads grips held longer than any calibration press: force bias and RMSE over
the held samples.

Usage::

    fbgforce simulate --scene long_holds --out holds.npz
    python -m fbgforce.bench.bench_held_grips --model MODEL_DIR --data holds.npz [--engine fixed] [--json]

Runs the model (any engine of ``fbgforce evaluate``) over each whole recording, tared on its
own start like the runtime, and scores the samples inside holds
(:func:`fbgforce.trainer.train.hold_mask`: at least 0.2 s in contact with the load within
max(0.2 N, 3 %)): the force bias (mean of estimate minus load cell) and RMSE there, with the
contact net's decision counted as 0 N where it says no contact, as every engine outputs it.
docs/measurements/trainer.md ("Held grips") quotes it for models trained with and without
synthetic holds.
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Sequence

import numpy as np


def held_grip_errors(pred_force_N: np.ndarray, pred_contact: np.ndarray, force_N: np.ndarray,
                     held: np.ndarray, rate_hz: float) -> dict[str, Any]:
    """Force bias and RMSE (N) of a prediction over the ``held`` samples.

    Returns
    -------
    dict
        ``held_samples``, ``held_s``, ``force_bias_N``, ``force_rmse_N``,
        ``contact_missed`` (share of held samples called no contact).
    """
    n = int(held.sum())
    if not n:
        return {"held_samples": 0, "held_s": 0.0, "force_bias_N": None, "force_rmse_N": None,
                "contact_missed": None}
    err = np.where(pred_contact, pred_force_N, 0.0)[held] - np.asarray(force_N, float)[held]
    return {"held_samples": n, "held_s": n / rate_hz, "force_bias_N": float(err.mean()),
            "force_rmse_N": float(np.sqrt(np.mean(err * err))),
            "contact_missed": float(np.mean(~np.asarray(pred_contact, bool)[held]))}


def measure(model_dir: str, data: Sequence[str], engine: str = "float") -> dict[str, Any]:
    """:func:`held_grip_errors` of ``engine`` over the holds of every recording in ``data``."""
    from fbgforce.model import modeldir as fm
    from fbgforce.recordings import tare as fbgtare
    from fbgforce.trainer.evaluate import run_recording
    from fbgforce.trainer.data import hold_mask, load_datasets

    model = fm.load(model_dir)
    ds_list, described = load_datasets(data)
    parts = []
    for ds, d in zip(ds_list, described):
        rate = fbgtare.sample_rate_hz(ds.t_s)
        pred = run_recording(engine, model_dir, model, ds, d.get("path"))
        held = hold_mask(ds.force_N, ds.contact, rate)
        parts.append((np.asarray(pred["force_N"]), np.asarray(pred["contact"], bool),
                      np.asarray(ds.force_N, float), held, rate))
    rate = float(np.median([p[4] for p in parts]))
    out = held_grip_errors(*(np.concatenate([p[i] for p in parts]) for i in range(4)), rate)
    out.update({"engine": engine, "model": str(model_dir), "data": list(map(str, data))})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbgforce.bench.bench_held_grips",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, metavar="MODEL_DIR", help="trained model directory")
    ap.add_argument("--data", required=True, nargs="+", metavar="FILE",
                    help="recordings of the model's device with holds (CSV/npz)")
    ap.add_argument("--engine", default="float", help="as fbgforce evaluate --engine (float)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    from fbgforce.cliargs import fail
    from fbgforce.errors import InputError

    try:
        out = measure(args.model, args.data, args.engine)
    except (InputError, OSError, ValueError, KeyError) as exc:
        return fail(f"bench_held_grips: {exc}", args.json)
    if args.json:
        print(json.dumps(out))
    elif not out["held_samples"]:
        print("no holds (0.2 s or more of steady load in contact) in the data")
    else:
        print(f"{out['held_s']:.1f} s held: force bias {out['force_bias_N']:+.3f} N, "
              f"RMSE {out['force_rmse_N']:.3f} N, contact missed on "
              f"{100 * out['contact_missed']:.2f} % ({args.engine})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
