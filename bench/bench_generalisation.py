"""The trainer on foreign calibration logs: train on one log of a device, score on another.

Usage::

    python tests/foreign.py --out DIR [--presses 60] [VARIANT ...]    # writes the logs
    python bench/bench_generalisation.py --data DIR [--epochs 200] [--json OUT.json] [VARIANT ...]

``--data`` is a directory holding ``foreign.json``, the manifest that tests/foreign.py writes
next to its logs: per variant a training log and another log of the same device
(``{"variants": {name: {"train": FILE, "other": FILE, "temp_coeff_true": [k1..k4]}}}``, files
relative to the manifest; ``temp_coeff_true`` is optional, so logs of a real device can be
listed the same way). The generator stays a test helper: this benchmark reads only its files.

For each variant (default all in the manifest): ``train`` with the default settings on the
training log, then the shared metrics on its held-out test presses and on the whole other log
(``evaluate``). Prints one table; docs/measurements/trainer.md ("Generalisation") quotes it.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import NoReturn

#: Manifest file name inside ``--data`` (tests/foreign.py writes it).
MANIFEST = "foreign.json"


def fail(msg: str, prog: str = "bench_generalisation") -> NoReturn:
    """Bad input: one line on stderr, exit status 2."""
    print(f"{prog}: {msg}", file=sys.stderr)
    sys.exit(2)


def load_manifest(data: Path, prog: str = "bench_generalisation") -> dict[str, dict]:
    """Variants of ``data/foreign.json`` with their log paths resolved; exits 2 with one line
    (starting with ``prog``) naming the file and the field when something is missing."""
    path = data / MANIFEST if data.is_dir() else data
    try:
        variants = json.loads(path.read_text())["variants"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        fail(f"{path}: not a foreign-log manifest ({type(exc).__name__}: "
             f"{exc}); write one with: python tests/foreign.py --out {data}", prog)
    out = {}
    for name, entry in variants.items():
        resolved = dict(entry)
        for key in ("train", "other"):
            if key not in entry:
                fail(f"{path}: variant {name!r} has no {key!r} log", prog)
            resolved[key] = path.parent / entry[key]
            if not resolved[key].is_file():
                fail(f"{path}: variant {name!r}: no such file {resolved[key]}", prog)
        out[name] = resolved
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("variants", nargs="*", help="variant names (default: all in the manifest)")
    ap.add_argument("--data", required=True, type=Path, metavar="DIR",
                    help="directory with foreign.json (python tests/foreign.py --out DIR)")
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args(argv)

    from fbgforce.trainer.evaluate import evaluate
    from fbgforce.trainer.train import train

    manifest = load_manifest(args.data)
    unknown = [v for v in args.variants if v not in manifest]
    if unknown:
        fail(f"{', '.join(unknown)} not in {args.data / MANIFEST} "
             f"(it lists {', '.join(manifest)})")
    names = args.variants or list(manifest)
    rows, out = [], {}
    for name in names:
        entry = manifest[name]
        a, b = entry["train"], entry["other"]
        true_k = entry.get("temp_coeff_true")
        t0 = time.perf_counter()
        model = train([a], epochs=args.epochs, seed=0, progress=False)
        seconds = time.perf_counter() - t0
        md = model.metadata
        other = evaluate(None, [b], model=model)
        out[name] = {"test": md["metrics"]["test"], "other": other, "train_s": seconds,
                     "temp_coeff": model.preprocess.temp_coeff.tolist(),
                     "temp_coeff_true": true_k,
                     "temp_coeff_identified": md["temperature"]["temp_coeff_identified"],
                     "group_delay_ms": md["filter"]["group_delay_ms"]}
        for where, m in (("test presses", md["metrics"]["test"]), ("other log", other)):
            rows.append((name, where, m))
        truth = f" (true {[round(float(k), 3) for k in true_k]})" if true_k else ""
        print(f"{name}: trained in {seconds:.0f} s, temp_coeff "
              f"{[round(float(k), 3) for k in model.preprocess.temp_coeff]}{truth}", file=sys.stderr)
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
