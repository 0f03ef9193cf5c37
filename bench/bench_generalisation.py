"""The trainer on foreign calibration logs (tests/foreign.py): train on one log, score on another.

Usage::

    python bench/bench_generalisation.py [--presses 60] [--epochs 200] [--out DIR]
                                         [--json OUT.json] [VARIANT ...]

For each variant of ``tests/foreign.py`` (default all): a device (seed 100 + its index in
``VARIANTS``), two logs of it (seeds 1 and 2) written as messy-but-valid CSVs, ``train`` with
the default settings on the first, then the shared metrics on the first log's held-out test
presses and on the whole second log (``evaluate``). Prints one table; docs/trainer.md
("Generalisation") quotes it.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("variants", nargs="*", help="variant names (default: all)")
    ap.add_argument("--presses", type=int, default=60, help="presses per log (default 60)")
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--out", default=None, help="keep the CSVs here (default: a temp dir)")
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args(argv)

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    import foreign as fg  # the independent generator is a test helper, not package code

    from fbgforce.trainer.evaluate import evaluate
    from fbgforce.trainer.train import train

    names = args.variants or list(fg.VARIANTS)
    root = Path(args.out or tempfile.mkdtemp(prefix="fbgf_foreign_"))
    root.mkdir(parents=True, exist_ok=True)
    rows, out = [], {}
    for name in names:
        spec = fg.VARIANTS[name]
        dev = fg.device(spec, 100 + list(fg.VARIANTS).index(name))
        a = fg.write_csv(fg.log(dev, 1, args.presses), root / f"{name}_A.csv", seed=1,
                         crlf=spec.crlf)
        b = fg.write_csv(fg.log(dev, 2, args.presses), root / f"{name}_B.csv", seed=2,
                         crlf=spec.crlf)
        t0 = time.perf_counter()
        model = train([a], epochs=args.epochs, seed=0, progress=False)
        seconds = time.perf_counter() - t0
        md = model.metadata
        other = evaluate(None, [b], model=model)
        out[name] = {"test": md["metrics"]["test"], "other": other, "train_s": seconds,
                     "temp_coeff": model.preprocess.temp_coeff.tolist(),
                     "temp_coeff_true": dev.temp_coeff.tolist(),
                     "temp_coeff_identified": md["temperature"]["temp_coeff_identified"],
                     "group_delay_ms": md["filter"]["group_delay_ms"]}
        for where, m in (("test presses", md["metrics"]["test"]), ("other log", other)):
            rows.append((name, where, m))
        print(f"{name}: trained in {seconds:.0f} s, temp_coeff "
              f"{[round(float(k), 3) for k in model.preprocess.temp_coeff]} (true "
              f"{[round(float(k), 3) for k in dev.temp_coeff]})", file=sys.stderr)
    print("| variant | scored on | contact | force RMSE | x RMSE | y RMSE | contact, true 0–5 N |")
    print("|---|---|---|---|---|---|---|")
    for name, where, m in rows:
        low = m["by_force"][0]["contact_accuracy"]
        print(f"| `{name}` | {where} | {100 * m['contact_accuracy']:.1f} % | "
              f"{m['rmse_force_N']:.2f} N | {m['rmse_x_mm']:.2f} mm | {m['rmse_y_mm']:.2f} mm | "
              f"{100 * low:.1f} % |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
