"""Transfer learning between devices (paper §VII-C): how much faster, with how much less data.

Usage::

    python bench/bench_transfer.py [--data-a FILE] [--data-b FILE] [--init-model DIR]
                                   [--fractions 0.05 0.1 0.25 0.5] [--json OUT.json]

Device A is the ``calibration`` scene (device 0), device B the ``two_devices`` scene (device 1,
another tolerance draw), unless files are given. A model is trained on A (or ``--init-model``
is used); then on B:

1. from scratch on all of B's training presses, and from A's weights (``init``) on the same;
   printed: epochs and seconds until early stopping, and the epochs and seconds each run needed
   to come within 5 % of the from-scratch run's best validation figures;
2. from scratch and from A's weights on a fraction of B's training presses; printed: test
   metrics per fraction, and the smallest fraction with which the transferred model is within
   10 % of the from-scratch, full-data model on force and location RMSE.

Every run uses the same seed, split and preprocessing of B (tare and temperature coefficients
are always fitted on B; with ``init`` the input standardisation and output scaling come from A).
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np

KEYS = ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm")
#: Validation figure per net and whether larger is better.
VAL_KEYS = {"contact": (("val_acc", True),), "force": (("val_rmse_N", False),),
            "location": (("val_x_mm", False), ("val_y_mm", False))}


def _reach(history: list[dict[str, Any]], targets: dict[str, tuple[float, bool]]) -> int | None:
    """First epoch at which every validation figure is within 5 % of its target."""
    for row in history:
        ok = True
        for key, (target, larger) in targets.items():
            v = row.get(key)
            if v is None:
                ok = False
            elif larger:
                ok &= v >= target - 0.05 * (1.0 - target)  # 5 % of the remaining error
            else:
                ok &= v <= 1.05 * target
        if ok:
            return int(row["epoch"])
    return None


def time_to_target(model: Any, reference: Any) -> dict[str, Any]:
    """Epochs and seconds (summed over nets) to come within 5 % of ``reference``'s best."""
    out: dict[str, Any] = {"epochs": {}, "seconds": 0.0, "reached": True}
    for net, keys in VAL_KEYS.items():
        ref_hist = reference.metadata["history"][net]
        best = reference.metadata["training"][net]["best_epoch"]
        targets = {k: (ref_hist[best - 1][k], larger) for k, larger in keys}
        hist = model.metadata["history"][net]
        ep = _reach(hist, targets)
        rep = model.metadata["training"][net]
        per_epoch = rep["seconds"] / max(rep["epochs_run"], 1)
        out["epochs"][net] = ep
        if ep is None:
            out["reached"] = False
        else:
            out["seconds"] += ep * per_epoch
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-a", help="device A recording (default: simulate 'calibration')")
    ap.add_argument("--data-b", help="device B recording (default: simulate 'two_devices')")
    ap.add_argument("--init-model", help="model of device A (default: train one)")
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.05, 0.1, 0.25, 0.5])
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="write the figures to this JSON file")
    args = ap.parse_args(argv)

    from fbgforce.recordings import dataset
    from fbgforce.model import modeldir as fm
    from fbgforce.sim import simulate
    from fbgforce.trainer.scoring import evaluate_rows
    from fbgforce.trainer.train import prepare, train

    ds_a = dataset.load(args.data_a) if args.data_a else simulate("calibration")
    ds_b = dataset.load(args.data_b) if args.data_b else simulate("two_devices")
    if args.init_model:
        model_a = fm.load(args.init_model)
    else:
        print("training device A ...", file=sys.stderr)
        model_a = train([ds_a], epochs=args.epochs, seed=args.seed)
    prep_b = prepare([ds_b], seed=args.seed)
    runs: dict[str, Any] = {}

    def run(label: str, fraction: float, init: Any) -> Any:
        print(f"device B: {label} ...", file=sys.stderr)
        m = train([ds_b], epochs=args.epochs, seed=args.seed, prepared=prep_b, init=init,
                  train_fraction=fraction)
        md = m.metadata
        runs[label] = {"fraction": fraction, "init": init is not None,
                       "train_s": md["times_s"]["train"],
                       "epochs": {k: v["epochs_run"] for k, v in md["training"].items()},
                       "test": {k: md["metrics"]["test"][k] for k in KEYS}}
        return m

    scratch = run("scratch 100%", 1.0, None)
    warm = run("init 100%", 1.0, model_a)
    ttt = {"scratch": time_to_target(scratch, scratch), "init": time_to_target(warm, scratch)}
    # Device A's model on device B as it is (B's own tare and filter, A's everything else).
    zero_shot = evaluate_rows(model_a, prep_b, prep_b.rows("test"), extras=False)
    for f in args.fractions:
        run(f"scratch {100 * f:g}%", f, None)
        run(f"init {100 * f:g}%", f, model_a)

    ref = runs["scratch 100%"]["test"]
    enough = None
    for f in sorted(args.fractions) + [1.0]:
        t = runs[f"init {100 * f:g}%"]["test"]
        if all(t[k] is not None and t[k] <= 1.10 * ref[k] for k in KEYS[1:]):
            enough = f
            break

    print(f"\nDevice A model on device B without retraining (test): "
          + ", ".join(f"{k} {zero_shot[k]:.3g}" for k in KEYS))
    print(f"\n{'run':<16} {'train s':>8} {'epochs c/f/l':>14}   " + "  ".join(f"{k:>16}" for k in KEYS))
    for label, r in runs.items():
        ep = "/".join(str(r["epochs"][n]) for n in ("contact", "force", "location"))
        print(f"{label:<16} {r['train_s']:8.1f} {ep:>14}   " +
              "  ".join(f"{r['test'][k]:16.3f}" for k in KEYS))
    print("\nTo within 5 % of the from-scratch best validation figures:")
    for label, t in ttt.items():
        eps = ", ".join(f"{n} {e}" for n, e in t["epochs"].items())
        print(f"  {label:<8} epochs {eps}; {t['seconds']:.1f} s"
              + ("" if t["reached"] else " (not reached by every net)"))
    if ttt["init"]["reached"] and ttt["init"]["seconds"] > 0:
        print(f"  speed-up: {ttt['scratch']['seconds'] / ttt['init']['seconds']:.1f}x")
    print(f"\nSmallest fraction of device B's training presses with which the transferred model "
          f"is within 10 % of the full from-scratch model on force, x and y RMSE: "
          f"{'none tried' if enough is None else f'{100 * enough:g} %'}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"runs": runs, "time_to_target": ttt, "zero_shot": zero_shot,
                       "smallest_fraction_within_10pct": enough}, fh, indent=2,
                      default=lambda v: v.item() if isinstance(v, np.generic) else str(v))
    return 0


if __name__ == "__main__":
    sys.exit(main())
