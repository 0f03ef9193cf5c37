"""Subcommands ``export`` and ``verify`` (docs/cli.md)."""
from __future__ import annotations

import argparse
from typing import Any

from fbgforce.cliargs import add_data, add_model, command, emit
from fbgforce.errors import InputError


def register(subparsers: Any) -> None:
    """Add ``export`` and ``verify``."""
    with command(subparsers, "export", _export,
                 help="write model.onnx, model.fbgm, generated C and an export report",
                 description="Quantise a trained model directory for the fixed-point C runtime "
                             "and write its artifacts into the directory: model.onnx (float "
                             "reference), model.fbgm (blob the runtime loads), "
                             "c/<name>_model.{c,h} and c/<name>_model_f32.{c,h} (const models "
                             "firmware links in) and export_report.json (scales and "
                             "accumulator bounds). Scales come from calibration data: --calib "
                             "files, or else the training recordings named in model.json."
                 ) as p:
        add_model(p, "model directory (fbgforce train)", metavar="DIR")
        p.add_argument("--bits", type=int, choices=(16, 8), default=16,
                       help="weight width of the nets (activations stay int16); default 16")
        p.add_argument("--calib", nargs="+", metavar="FILE",
                       help="calibration recording(s) (dataset CSV/npz); default: training files")
        p.add_argument("--name", default="fbgforce",
                       help="C symbol prefix: <name>_model (default fbgforce)")
        p.add_argument("--jump-nm", type=float, default=2.0,
                       help="sensor-fault threshold: largest plausible change per sample, nm "
                            "(default 2)")
        p.add_argument("--overload-N", type=float, default=None,
                       help="OVERLOAD flag threshold, N (default: largest calibration force)")
        p.add_argument("--stuck-samples", type=int, default=None, metavar="N",
                       help="sensor fault after N identical consecutive values of a channel "
                            "(0 = off; default: 4x the longest run in the calibration data, "
                            "at least 25)")
        p.add_argument("--acc32-max-drop", type=float, default=None, metavar="BITS",
                       help="int32 accumulators: bits of weight resolution a layer may give up "
                            "so that its proven worst case fits int32 (default 6; negative: "
                            "int64 everywhere, as blob version 2 did)")
        p.add_argument("--no-onnx", action="store_true", help="skip model.onnx")

    with command(subparsers, "verify", _verify,
                 help="C fixed point vs integer reference vs float on every sample",
                 description="Run the C fixed-point runtime, the numpy integer reference and "
                             "the float model on recordings (tared on their contact-free "
                             "samples) and compare: mismatches (C vs integer reference, any "
                             "output bit) must be 0, else the exit status is 1; fixed vs float "
                             "errors and contact disagreements measure the quantisation. A "
                             "model.fbgm exported from another model is refused (exit 2).") as v:
        add_model(v, "exported model directory", metavar="DIR")
        add_data(v, "recording(s)")
        v.add_argument("--fail-on-mismatch", action="store_true",
                       help="kept for old scripts: verify always exits with status 1 when any "
                            "sample mismatches")


def _export(args: argparse.Namespace) -> dict[str, Any]:
    import sys

    from fbgforce.export import quantize as qz
    from fbgforce.export.exporter import export_model

    if args.jump_nm <= 0:
        raise InputError("must be positive", column="--jump-nm")
    rep = export_model(args.model, bits=args.bits, calib=args.calib, name=args.name,
                       jump_nm=args.jump_nm, overload_N=args.overload_N,
                       stuck_samples=args.stuck_samples, onnx=not args.no_onnx,
                       acc32_max_drop=(qz.ACC32_MAX_DROP if args.acc32_max_drop is None
                                       else args.acc32_max_drop))
    if not args.json:
        chk = rep["calibration_check"]
        print(f"exported {args.model}: blob {rep['blob_bytes']} B, const data {rep['const_bytes']} B, "
              f"state {rep['state_bytes']} B; on calibration data max |fixed-float| force "
              f"{chk['max_abs_err_force_N']:.4f} N, x {chk['max_abs_err_x_mm']:.4f} mm, y "
              f"{chk['max_abs_err_y_mm']:.4f} mm, {chk['contact_disagreements']} contact "
              f"disagreements / {chk['samples']}", file=sys.stderr)
    return rep


def _verify(args: argparse.Namespace) -> dict[str, Any]:
    import sys

    from fbgforce.export.verify import verify
    from fbgforce.pybind import RuntimeCError

    try:
        res = verify(args.model, args.data)
    except RuntimeCError as exc:
        raise InputError(f"the runtime refused the model blob: {exc}", path=str(args.model)) from exc
    if not args.json:
        for k, v in res.items():
            print(f"{k}: {v}")
    if res["mismatches"]:
        print(f"fbgforce verify: {res['mismatches']} mismatching samples", file=sys.stderr)
        emit(res, args.json)
        sys.exit(1)
    return res
