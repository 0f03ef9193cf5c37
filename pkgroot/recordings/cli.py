"""Subcommands for a lab's own calibration: ``import`` (its interrogator and stage logs into
a dataset) and ``protocol`` (the stage program to record); docs/cli.md, docs/lab-import.md."""
from __future__ import annotations

import argparse
import sys
from typing import Any

from fbgforce.cliargs import add_json_flag, non_negative_int, positive_float, positive_int


def register(subparsers: Any) -> None:
    """Add ``import`` and ``protocol`` to the ``fbgforce`` command."""
    from fbgforce.recordings.labimport import FBG_UNITS, FORCE_UNITS, POSITION_UNITS, TIME_UNITS
    from fbgforce.recordings.stagelog import MAX_OFFSET_S

    p = subparsers.add_parser(
        "import", help="a lab's interrogator log + stage/load-cell log -> one dataset",
        description="Align the stage clock to the interrogator's (offset and drift, from the "
                    "load against the gratings' strain), resample force and position onto the "
                    "interrogator's samples, label contact, number the presses and write a "
                    "dataset CSV (docs/lab-import.md).")
    p.add_argument("--map", metavar="FILE.toml",
                   help="a mapping file with the flags' keys (fbg, fbg-columns, ...); flags "
                        "given as well override it")
    p.add_argument("--fbg", metavar="FBG.csv", help="the interrogator log")
    p.add_argument("--fbg-columns", metavar="t=COL,wl1=COL,wl2=COL,wl3=COL,wl4=COL,wlT=COL",
                   help="its time column (seconds unless --fbg-time-unit) and the five "
                        "peak-wavelength columns")
    p.add_argument("--fbg-unit", choices=tuple(FBG_UNITS), default=None,
                   help="wavelength unit of the log (default nm)")
    p.add_argument("--fbg-time-unit", choices=tuple(TIME_UNITS), default=None,
                   help="unit of its time column (default s)")
    p.add_argument("--stage", metavar="STAGE.csv", help="the stage/load-cell log")
    p.add_argument("--stage-columns", metavar="t=COL,force=COL,x=COL,y=COL",
                   help="its time column (seconds unless --stage-time-unit), the load-cell "
                        "force and the position (pad frame)")
    p.add_argument("--stage-time-unit", choices=tuple(TIME_UNITS), default=None,
                   help="unit of its time column (default s)")
    p.add_argument("--force-unit", choices=tuple(FORCE_UNITS), default=None,
                   help="force unit of the stage log (default N)")
    p.add_argument("--position-unit", choices=tuple(POSITION_UNITS), default=None,
                   help="position unit of the stage log (default mm)")
    p.add_argument("--max-offset-s", type=positive_float, default=None,
                   help=f"largest clock offset searched (default {MAX_OFFSET_S:g} s)")
    p.add_argument("--out", metavar="DATASET.csv", help="the dataset to write")
    add_json_flag(p)
    p.set_defaults(handler=_import)

    p = subparsers.add_parser(
        "protocol", help="write the calibration stage program (CSV of moves)",
        description="Write the stage program a lab runs to calibrate a fingertip: presses over "
                    "the pad and the force range, slow ramps and fast taps, holds and long "
                    "rests (docs/lab-import.md).")
    p.add_argument("--out", required=True, metavar="PROGRAM.csv")
    p.add_argument("--presses", type=positive_int, default=300, help="presses (default 300)")
    p.add_argument("--force-max", type=positive_float, default=70.0,
                   help="largest target force, N (default 70)")
    p.add_argument("--groups", type=positive_int, default=6,
                   help="groups of presses, separated by long rests (default 6)")
    p.add_argument("--seed", type=non_negative_int, default=0)
    add_json_flag(p)
    p.set_defaults(handler=_protocol)


def _import(args: argparse.Namespace) -> dict[str, Any]:
    from fbgforce.recordings.labimport import import_files, load_map, make_spec, MAP_KEYS

    values: dict[str, Any] = load_map(args.map) if args.map else {}
    for key in MAP_KEYS:
        given = getattr(args, key.replace("-", "_"))
        if given is not None:
            values[key] = given
    spec = make_spec(values)
    result = import_files(spec, progress=None)
    if not args.json:
        al = result["alignment"]
        print(f"wrote {result['dataset']}: {result['samples']} samples, {result['presses']} "
              f"presses; stage clock offset {al['offset_s'] * 1e3:.2f} ms, drift "
              f"{al['drift_ppm']:.1f} ppm (correlation {al['correlation']:.3f}, residual "
              f"{al['residual_ms']:.2f} ms over {al['presses_used']} presses); dropped "
              + ", ".join(f"{k} {v}" for k, v in result["dropped"].items())
              + f"; stage rows without a reading {result['stage']['bad_rows']}", file=sys.stderr)
    return result


def _protocol(args: argparse.Namespace) -> dict[str, Any]:
    from fbgforce.recordings.protocol import default_program, write_program

    program = default_program(args.presses, force_max_N=args.force_max, groups=args.groups,
                              seed=args.seed)
    write_program(program, args.out)
    summary = program.summary()
    summary["file"] = args.out
    if not args.json:
        print(f"wrote {args.out}: {summary['presses']} presses in {summary['groups']} groups, "
              f"duration {summary['duration_s']:.1f} s ({summary['duration_s'] / 60:.1f} min)")
        print(summary["temperature_note"])
    return summary
