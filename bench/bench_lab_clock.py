"""The lab import's clock against the true one, on raw lab logs whose stage clock is known.

Usage::

    python tests/foreign.py --out lab --lab-logs --presses 40 --stage-rate-hz R \\
        --stage-offset-s O --stage-drift-ppm D [VARIANT ...]     # lab/VARIANT/ + clock.json
    fbgforce simulate --scene SCENE --out s.csv --lab-logs lab/SCENE --stage-rate-hz R \\
        --stage-offset-s O --stage-drift-ppm D                    # no clock.json: give it
    python bench/bench_lab_clock.py [--offset-s O --drift-ppm D] [--json OUT.json] DIR ...

Each ``DIR`` holds the ``import.toml`` that imports its logs (both writers put it there) and,
unless ``--offset-s`` and ``--drift-ppm`` give it, ``clock.json`` with the true stage clock
(``{"offset_s": O, "drift_ppm": D}``: ``t_stage = t + O + D 1e-6 (t - t[0])`` at interrogator
time ``t``). Each is imported as ``fbgforce import --map DIR/import.toml`` does (the dataset to
a temporary file) and the fitted stage clock's error at the interrogator log's first and last
sample is printed, ms, with the JSON's ``line_sd_ms``, ``lag_ms`` and ``seconds``.
docs/lab-import.md ("Measured") quotes it.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from fbgforce.recordings import labimport as li
from fbgforce.bench.bench_generalisation import fail
from fbgforce.errors import InputError

PROG = "bench_lab_clock"


def true_clock(directory: Path, offset_s: float | None, drift_ppm: float | None
               ) -> tuple[float, float]:
    """The true stage clock of ``directory``'s logs: the flags, else its ``clock.json``."""
    if offset_s is not None and drift_ppm is not None:
        return offset_s, drift_ppm
    path = directory / "clock.json"
    try:
        truth = json.loads(path.read_text())
        return float(truth["offset_s"]), float(truth["drift_ppm"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        fail(f"{path}: no true clock ({type(exc).__name__}: {exc}); give --offset-s and "
             "--drift-ppm", PROG)


def clock_errors(directory: Path, offset_s: float, drift_ppm: float) -> dict[str, Any]:
    """Import ``directory``'s logs; the clock's error at the log's ends (ms) and the JSON's
    alignment figures."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            values = li.load_map(directory / "import.toml") | {"out": str(Path(tmp) / "i.csv")}
            result = li.import_files(li.make_spec(values), progress=False)
        except InputError as exc:
            fail(f"{directory}: {exc}", PROG)
    duration = (result["fbg"]["rows"] - 1) / result["fbg"]["rate_hz"]
    start = result["offset_s"] - offset_s
    end = start + (result["drift_ppm"] - drift_ppm) * 1e-6 * duration
    alignment = result["alignment"]
    return {"log": str(directory), "error_start_ms": 1e3 * start, "error_end_ms": 1e3 * end,
            "line_sd_ms": alignment["line_sd_ms"], "lag_ms": alignment["lag_ms"],
            "presses_used": alignment["presses_used"], "seconds": result["seconds"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="+", type=Path, metavar="DIR",
                    help="directories holding import.toml (and clock.json)")
    ap.add_argument("--offset-s", type=float, help="true stage clock offset, s (all DIRs)")
    ap.add_argument("--drift-ppm", type=float, help="true stage clock drift, ppm (all DIRs)")
    ap.add_argument("--json", type=Path, metavar="OUT", help="also write the rows as JSON")
    args = ap.parse_args(argv)
    if (args.offset_s is None) != (args.drift_ppm is None):
        fail("give both --offset-s and --drift-ppm, or neither (then each DIR's clock.json)",
             PROG)
    for directory in args.logs:
        if not (directory / "import.toml").is_file():
            fail(f"{directory}: no import.toml (write the logs with tests/foreign.py "
                 "--lab-logs or fbgforce simulate --lab-logs)", PROG)
    truths = [true_clock(directory, args.offset_s, args.drift_ppm) for directory in args.logs]
    rows = []
    print(f"{'log':40s} {'start ms':>9s} {'end ms':>8s} {'line_sd':>8s} {'lag_ms':>7s} "
          f"{'s':>5s}")
    for directory, truth in zip(args.logs, truths):
        row = clock_errors(directory, *truth)
        rows.append(row)
        name = f"{directory.parent.name}/{directory.name}"
        print(f"{name:40s} {row['error_start_ms']:+9.2f} {row['error_end_ms']:+8.2f} "
              f"{row['line_sd_ms']:8.2f} {row['lag_ms']:+7.2f} {row['seconds']:5.1f}",
              flush=True)
    worst = max(max(abs(r["error_start_ms"]), abs(r["error_end_ms"])) for r in rows)
    print(f"worst error {worst:.2f} ms over {len(rows)} logs")
    if args.json:
        args.json.write_text(json.dumps({"logs": rows, "worst_ms": worst}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
