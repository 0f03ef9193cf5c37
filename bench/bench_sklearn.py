"""fbgforce's trainer against scikit-learn's MLPs on identical inputs and split.

Usage::

    python -m fbgforce.bench.bench_sklearn [--data FILE [FILE ...] | --scene NAME [--presses N]]
                                           [--seed N] [--epochs N] [--max-iter N] [--json OUT]

Needs the optional ``bench`` extra (``pip install "fbgforce[bench]"``: scikit-learn).

One preparation (:func:`fbgforce.trainer.train.prepare`: tare, temperature fit, filter, and
whatever features the model's preprocessing computes) and one split by press feed three
estimators, all scored with :func:`fbgforce.evaluation.metrics.compute` on the same held-out test presses:

- **fbgforce**: :func:`fbgforce.trainer.train.train` with its defaults;
- **scikit-learn**: ``MLPClassifier`` (contact) -> ``MLPRegressor`` (force) -> ``MLPRegressor``
  (location) in the paper's hierarchy with the paper's hidden sizes, trained on the training
  presses with scikit-learn's defaults (Adam, lr 1e-3, batch 200, L2 1e-4, stop when the
  training loss improves by less than 1e-4 for 10 epochs, at most ``--max-iter`` epochs). Its
  inputs are the trainer's own net inputs ``z`` (the fbgforce model's standardisation and
  memory features, ``Prepared.inputs``); the force and location nets are fitted on the true-contact
  training samples, with targets scaled like the trainer's (``force_offset``/``force_scale``,
  ``xy_offset``/``xy_scale``); the location net gets the same inputs as the fbgforce location net
  (``fbgforce.model.floatref.location_inputs``: channels, contact decision, force output), from its own
  contact and force nets;
- **linear (fitted)**: the fitted beam model of :mod:`fbgforce.trainer.baseline` on the
  filtered, compensated shifts (the first four feature columns).

Prints a table (contact accuracy overall and above 1 N, force, x, y RMSE, median onset and
release delay, training time), then x and y of all three on the test samples that all three
and the truth call contact (:func:`fbgforce.evaluation.metrics.common_location`: like for like, since each
estimator's own x/y leave out the touches it misses), and optionally writes it as JSON. Foreign data: write CSVs with
``tests/foreign.py`` (docs/measurements/trainer.md, "Against scikit-learn") and pass them with
``--data``.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

#: Columns of the printed table: (key in the metrics, header, format, scale).
COLUMNS = (
    ("contact_accuracy", "contact", "{:.2f} %", 100.0),
    ("contact_accuracy_above_1N", ">1 N", "{:.2f} %", 100.0),
    ("rmse_force_N", "force N", "{:.3f}", 1.0),
    ("rmse_x_mm", "x mm", "{:.3f}", 1.0),
    ("rmse_y_mm", "y mm", "{:.3f}", 1.0),
)
SUMMARY_KEYS = ("contact_accuracy", "contact_accuracy_above_1N", "contact_accuracy_above_5N",
                "rmse_force_N", "rmse_x_mm", "rmse_y_mm", "n_samples", "contact_by_force",
                "contact_timing")


def load_data(args: argparse.Namespace) -> tuple[list[Any], list[str]]:
    """The recordings to compare on: ``--data`` files or a simulated scene."""
    from fbgforce.recordings import dataset

    if args.data:
        return [dataset.load(p) for p in args.data], list(args.data)
    from fbgforce.sim import simulate

    scene = args.scene
    if args.presses is not None:
        # A derived scene inherits everything but the number of presses.
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"{args.scene}_{args.presses}.toml"
            path.write_text(f'base = "{args.scene}"\n\n[schedule]\nn_presses = {args.presses}\n')
            ds = simulate(path, progress=None)
        return [ds], [f"scene {scene} ({args.presses} presses)"]
    return [simulate(scene, progress=None)], [f"scene {scene}"]


def sklearn_hierarchy(z: np.ndarray, data: Any, tr: np.ndarray, model: Any, *, seed: int,
                      max_iter: int) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Fit scikit-learn's MLPs in the paper's hierarchy on ``z[tr]``; predict every row.

    Returns the predictions in the engines' format and the seconds per net.
    """
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPClassifier, MLPRegressor

    from fbgforce.model import floatref as fm
    from fbgforce.trainer.params import DEFAULT_SIZES

    common = dict(max_iter=max_iter, random_state=seed)
    seconds = {}
    x, z = z, z[:, :model.preprocess.n_features]  # contact and force read the first columns
    ctr = tr[data.contact[tr]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        t0 = time.perf_counter()
        clf = MLPClassifier(hidden_layer_sizes=DEFAULT_SIZES["contact"], **common)
        clf.fit(z[tr], data.contact[tr])
        seconds["contact"] = time.perf_counter() - t0
        contact = clf.predict(z).astype(bool)
        print(f"  scikit-learn contact: {clf.n_iter_} epochs, {seconds['contact']:.1f} s",
              file=sys.stderr)

        t0 = time.perf_counter()
        freg = MLPRegressor(hidden_layer_sizes=DEFAULT_SIZES["force"], **common)
        freg.fit(z[ctr], (data.force_N[ctr] - model.force_offset) / model.force_scale)
        seconds["force"] = time.perf_counter() - t0
        f = freg.predict(z)
        print(f"  scikit-learn force: {freg.n_iter_} epochs, {seconds['force']:.1f} s",
              file=sys.stderr)

        # what the fbgforce location net reads
        loc_in = fm.location_inputs(x, contact, f, model.preprocess.memory.n_loc)
        xy = (np.column_stack([data.x_mm, data.y_mm]) - model.xy_offset) / model.xy_scale
        t0 = time.perf_counter()
        lreg = MLPRegressor(hidden_layer_sizes=DEFAULT_SIZES["location"], **common)
        lreg.fit(loc_in[ctr], xy[ctr])
        seconds["location"] = time.perf_counter() - t0
        uv = lreg.predict(loc_in)
        print(f"  scikit-learn location: {lreg.n_iter_} epochs, {seconds['location']:.1f} s",
              file=sys.stderr)
    force = model.force_offset + model.force_scale * f
    xy_mm = model.xy_offset + model.xy_scale * uv
    pred = {"contact": contact, "force_N": np.where(contact, force, 0.0),
            "x_mm": np.where(contact, xy_mm[:, 0], np.nan),
            "y_mm": np.where(contact, xy_mm[:, 1], np.nan)}
    return pred, seconds


def linear_baseline(data: Any, tr: np.ndarray) -> tuple[dict[str, np.ndarray], float]:
    """The fitted beam model on the filtered, compensated shifts; predictions for every row."""
    from fbgforce.model import artifact as fm
    from fbgforce.trainer import baseline as bl

    t0 = time.perf_counter()
    shifts = data.feats[:, :fm.N_STRAIN]
    ctr, free = tr[data.contact[tr]], tr[~data.contact[tr]]
    lin = bl.fit(shifts[ctr], data.force_N[ctr], data.x_mm[ctr], data.y_mm[ctr])
    lin.set_threshold(shifts[free])
    return lin.predict(shifts), time.perf_counter() - t0


def score(data: Any, pred: dict[str, np.ndarray], rows: np.ndarray) -> dict[str, Any]:
    """Shared metrics of whole-data predictions on ``rows`` (with contact timing)."""
    from fbgforce.evaluation import metrics as fmetrics
    from fbgforce.trainer.scoring import press_delays

    full = fmetrics.compute({k: np.asarray(v)[rows] for k, v in pred.items()}, *data.truth(rows),
                            delays=press_delays(data, np.asarray(pred["contact"]), rows))
    return {k: full[k] for k in SUMMARY_KEYS if k in full}


def table(results: dict[str, dict[str, Any]]) -> str:
    """The comparison as aligned text."""
    head = (f"{'estimator':<18}" + "".join(f"{h:>11}" for _, h, _, _ in COLUMNS)
            + f"{'onset ms':>10}{'release ms':>11}{'train s':>9}")
    lines = [head, "-" * len(head)]
    for name, r in results.items():
        m = r["metrics"]
        cells = []
        for key, _, fmt, scale in COLUMNS:
            v = m.get(key)
            cells.append(f"{'-' if v is None else fmt.format(v * scale):>11}")
        timing = m.get("contact_timing", {})
        on = timing.get("onset_delay_ms", {}).get("median")
        off = timing.get("release_delay_ms", {}).get("median")
        lines.append(f"{name:<18}" + "".join(cells)
                     + f"{'-' if on is None else f'{on:.1f}':>10}"
                     + f"{'-' if off is None else f'{off:.1f}':>11}"
                     + f"{r['train_s']:9.1f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        import sklearn
    except ImportError:
        print("bench_sklearn: scikit-learn is not installed; pip install 'fbgforce[bench]'",
              file=sys.stderr)
        return 2
    if args.presses is not None and args.presses < 10:
        print("bench_sklearn: --presses must be at least 10 (the split is 8:1:1 by press)",
              file=sys.stderr)
        return 2

    from fbgforce.errors import InputError
    from fbgforce.trainer.train import prepare

    try:
        ds_list, names = load_data(args)
        data = prepare(ds_list, seed=args.seed, sources=names)
    except InputError as exc:
        print(f"bench_sklearn: {exc}", file=sys.stderr)
        return 2
    tr, te = data.rows("train"), data.rows("test")
    print(f"data: {', '.join(names)}: {data.split.size} samples; "
          f"train {tr.size}, test {te.size} samples", file=sys.stderr)
    results, preds, model, z = _fit_and_score(ds_list, data, tr, te, args, sklearn.__version__)
    from fbgforce.evaluation import metrics as fmetrics

    # Each estimator's own x/y are scored where it detects contact; these are like for like.
    common_xy = fmetrics.common_location({k: {c: np.asarray(v)[te] for c, v in p.items()}
                                       for k, p in preds.items()},
                                      data.contact[te], data.x_mm[te], data.y_mm[te])
    print(f"{z.shape[1]} net inputs (memory: {model.metadata.get('memory')})")
    print(table(results))
    f, s = results["fbgforce"]["metrics"], results["scikit-learn"]["metrics"]
    ratios = {k: (f[k] / s[k] if f.get(k) and s.get(k) else None)
              for k in ("rmse_force_N", "rmse_x_mm", "rmse_y_mm")}
    if common_xy["n_samples"]:
        print(f"x / y mm on the {common_xy['n_samples']} test samples all three call contact: "
              + ", ".join(f"{k} {common_xy[k]['rmse_x_mm']:.3f} / {common_xy[k]['rmse_y_mm']:.3f}"
                          for k in preds))
    print("fbgforce / scikit-learn RMSE: " + ", ".join(
        f"{k} {v:.2f}" for k, v in ratios.items() if v is not None))
    if args.json:
        doc = {"data": names, "seed": args.seed, "features": int(z.shape[1]),
               "samples": {"train": int(tr.size), "test": int(te.size)},
               "sklearn_version": sklearn.__version__, "max_iter": args.max_iter,
               "epochs": args.epochs, "results": results, "ratios_fbgforce_over_sklearn": ratios,
               "location_on_common_contacts": common_xy}
        from fbgforce.jsonutil import json_default

        Path(args.json).write_text(json.dumps(doc, indent=2, default=json_default) + "\n")
    return 0


def _parser() -> argparse.ArgumentParser:
    """The bench's options (module docstring)."""
    ap = argparse.ArgumentParser(
        prog="python -m fbgforce.bench.bench_sklearn",
        description="Compare fbgforce's trainer with scikit-learn's MLPs and the fitted linear "
                    "baseline on identical inputs and the same split by press.")
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--data", nargs="+", metavar="FILE",
                     help="recordings of one device (CSV/npz, dataset contract)")
    src.add_argument("--scene", default="calibration",
                     help="scene to simulate when no --data is given (default calibration)")
    ap.add_argument("--presses", type=int, default=None,
                    help="simulate only this many presses of the scene (default: the scene's)")
    ap.add_argument("--seed", type=int, default=0, help="split, initialisation, shuffling")
    ap.add_argument("--epochs", type=int, default=200, help="fbgforce: maximum epochs per net")
    ap.add_argument("--max-iter", type=int, default=200,
                    help="scikit-learn: maximum epochs per net (its default 200)")
    ap.add_argument("--json", metavar="OUT", help="also write the results to this JSON file")
    return ap


def _fit_and_score(ds_list: list[Any], data: Any, tr: np.ndarray, te: np.ndarray,
                   args: argparse.Namespace, sklearn_version: str
                   ) -> tuple[dict[str, dict[str, Any]], dict[str, dict[str, np.ndarray]], Any,
                              np.ndarray]:
    """The three estimators trained on the training presses and scored on the test presses,
    in this order: fbgforce's trainer, scikit-learn's hierarchy on the trainer's own net
    inputs, the fitted linear baseline. Returns their results and whole-data predictions,
    the fbgforce model and its net inputs."""
    from fbgforce.model import floatref as fm
    from fbgforce.trainer.train import train

    results: dict[str, dict[str, Any]] = {}
    print("fbgforce trainer ...", file=sys.stderr)
    t0 = time.perf_counter()
    model = train(ds_list, seed=args.seed, epochs=args.epochs, prepared=data)
    t_fbg = time.perf_counter() - t0
    z = data.inputs(model.preprocess)  # the fbgforce nets' own inputs (standardised, memory)
    preds = {"fbgforce": fm.predict_from_features(model, z)}
    results["fbgforce"] = {"metrics": score(data, preds["fbgforce"], te),
                           "train_s": t_fbg,
                           "epochs": {k: v["epochs_run"] for k, v in
                                      model.metadata["training"].items()}}
    print(f"scikit-learn {sklearn_version} ...", file=sys.stderr)
    t0 = time.perf_counter()
    preds["scikit-learn"], seconds = sklearn_hierarchy(z, data, tr, model, seed=args.seed,
                                                       max_iter=args.max_iter)
    results["scikit-learn"] = {"metrics": score(data, preds["scikit-learn"], te),
                               "train_s": time.perf_counter() - t0, "seconds": seconds}
    preds["linear (fitted)"], t_lin = linear_baseline(data, tr)
    results["linear (fitted)"] = {"metrics": score(data, preds["linear (fitted)"], te),
                                  "train_s": t_lin}
    return results, preds, model, z


if __name__ == "__main__":
    sys.exit(main())
