"""Where a model's contact and location errors come from, by true force: light touch or not.

Usage::

    python -m fbgforce.bench.bench_light_touch --model MODEL_DIR --data FILE [--json OUT]

Re-prepares ``--data`` (one recording of the model's device; the model's own seed gives the
same split by press as its training) and scores the float model on the held-out test presses:
per range of true force, the samples, the location RMSE and that range's share of the summed
squared location error; the contact errors split into missed contacts (by true force) and
false ones. docs/measurements/trainer.md ("With memory: where the remaining error is") quotes
it: a few per cent of the samples, the touches below 1 N where the four beams' signals are a
few noise deviations, carry most of the squared location error and most missed contacts.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

#: Upper edges (N) of the true-force ranges of the location table; the last range is open.
EDGES_N = (0.5, 1.0, 2.0, 5.0)


def analyse(model: Any, data: Any, edges_n: tuple[float, ...] = EDGES_N) -> dict[str, Any]:
    """Light-touch breakdown of ``model`` on the test presses of prepared ``data``.

    Returns
    -------
    dict
        ``location``: per range ``range_N``, ``n_samples``, ``rmse_x_mm``, ``rmse_y_mm``,
        ``share_sq_err_x``, ``share_sq_err_y`` (over samples where true and predicted contact
        agree, as the shared metrics score location); ``contact``: ``errors``, ``samples``,
        ``missed`` and ``missed_below_N`` (missed contacts per upper edge), ``false``.
    """
    from fbgforce.trainer.scoring import predict_prepared

    pred = predict_prepared(model, data)
    rows = data.rows("test")
    tc, tf, tx, ty = data.truth(rows)
    pc = pred["contact"][rows]
    both = pc & tc
    ex2 = np.where(both, (pred["x_mm"][rows] - tx) ** 2, 0.0)
    ey2 = np.where(both, (pred["y_mm"][rows] - ty) ** 2, 0.0)
    location = []
    bounds = [0.0, *edges_n, np.inf]
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        sel = both & (tf > lo) & (tf <= hi) if lo > 0 else both & (tf <= hi)
        n = int(sel.sum())
        location.append({
            "range_N": [lo, None if np.isinf(hi) else hi], "n_samples": n,
            "rmse_x_mm": float(np.sqrt(ex2[sel].mean())) if n else None,
            "rmse_y_mm": float(np.sqrt(ey2[sel].mean())) if n else None,
            "share_sq_err_x": float(ex2[sel].sum() / ex2.sum()) if ex2.sum() > 0 else None,
            "share_sq_err_y": float(ey2[sel].sum() / ey2.sum()) if ey2.sum() > 0 else None,
        })
    missed = tc & ~pc
    return {
        "location": location,
        "contact": {"samples": int(tc.size), "errors": int((pc != tc).sum()),
                    "missed": int(missed.sum()), "false": int((pc & ~tc).sum()),
                    "missed_below_N": {str(e): int((missed & (tf <= e)).sum()) for e in edges_n}},
    }


def table(result: dict[str, Any]) -> str:
    """The breakdown as Markdown."""
    lines = ["| true force (N) | samples | x RMSE (mm) | y RMSE (mm) | share of squared error x / y |",
             "|---|---|---|---|---|"]
    for r in result["location"]:
        lo, hi = r["range_N"]
        rng = f"{lo:g}–{hi:g}" if hi is not None else f"> {lo:g}"
        if not r["n_samples"]:
            lines.append(f"| {rng} | 0 | - | - | - |")
            continue
        lines.append(f"| {rng} | {r['n_samples']} | {r['rmse_x_mm']:.2f} | {r['rmse_y_mm']:.2f} | "
                     f"{100 * (r['share_sq_err_x'] or 0):.0f} % / {100 * (r['share_sq_err_y'] or 0):.0f} % |")
    c = result["contact"]
    below = ", ".join(f"{n} below {e} N" for e, n in c["missed_below_N"].items())
    lines.append("")
    lines.append(f"contact errors: {c['errors']} of {c['samples']} test samples "
                 f"({100 * c['errors'] / max(c['samples'], 1):.2f} %): {c['missed']} missed "
                 f"({below}), {c['false']} false")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbgforce.bench.bench_light_touch",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, metavar="MODEL_DIR", help="trained model directory")
    ap.add_argument("--data", required=True, metavar="FILE",
                    help="the recording the model was trained on (CSV/npz, dataset contract)")
    ap.add_argument("--json", metavar="OUT", help="also write the breakdown to this JSON file")
    args = ap.parse_args(argv)

    from fbgforce.recordings import dataset
    from fbgforce.model import modeldir as fm
    from fbgforce.errors import InputError
    from fbgforce.trainer import preprocess as pp, train as T

    try:
        model = fm.load(args.model)
        ds = dataset.load(args.data)
        data = T.prepare([ds], seed=int(model.metadata.get("seed", 0)),
                         filter=model.preprocess.filter_kind)
        # The model's own filter and temperature coefficients, not ones refitted here.
        for rec in data.recordings:
            rec.feats = pp.recording_features(model.preprocess, rec.ds.wl_nm, rec.baseline_nm)
        data = T.Prepared(data.recordings, model.preprocess, data.temp_info)
    except (InputError, OSError, ValueError, KeyError) as exc:
        print(f"bench_light_touch: {exc}", file=sys.stderr)
        return 2
    if not data.rows("test").size:
        print(f"bench_light_touch: {args.data}: no test presses after the split", file=sys.stderr)
        return 2
    result = analyse(model, data)
    print(table(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
