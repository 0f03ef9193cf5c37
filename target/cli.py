"""``fbgforce target-report``, and ``python -m fbgforce.target`` (what ``make -C runtime_c
target-test`` runs)."""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any, Sequence

from fbgforce.cliargs import add_data, add_model, add_seed, command
from fbgforce.errors import InputError
from fbgforce.target import toolchain
from fbgforce.target.report import target_report
from fbgforce.target.sources import CSourcesMissing


def register(subparsers: Any) -> None:
    """Add the ``target-report`` subcommand."""
    with command(subparsers, "target-report", _handler,
                 help="Cortex-M4 (QEMU): bit-exact golden vectors, instructions, size",
                 description="Cross-compile libfbgforce for Cortex-M4 (portable and DSP-extension "
                             "builds), replay golden vectors from the integer reference on QEMU "
                             "mps2-an386 comparing every output bit, count the instructions of "
                             "every fbg_step exactly (TCG plugin) and measure flash/RAM. Needs: "
                             + toolchain.APT_LINE) as p:
        add_model(p, "model directory (its model.fbgm if exported, else quantised in memory)",
                  metavar="DIR")
        add_data(p, "recording for the golden vectors (default: the simulated --scene)",
                 nargs=None, required=False)
        p.add_argument("--scene", default="smoke", help="scene simulated when --data is not given")
        p.add_argument("--samples", type=int, default=600, help="recording samples replayed (edge "
                       "cases and API calls are added)")
        p.add_argument("--calib", nargs="+", metavar="FILE", help="calibration data when the "
                       "model is not exported yet (default: its training files)")
        p.add_argument("--bits", type=int, choices=(16, 8), default=None,
                       help="quantise in memory with int16 or int8 weights instead of using "
                            "model.fbgm")
        add_seed(p, "simulation and edge-case seed")
        p.add_argument("--build-dir", metavar="DIR", help="keep the build here (default: a "
                       "temporary directory, removed afterwards)")


def _handler(args: argparse.Namespace) -> dict[str, Any]:
    if args.samples < 64:
        raise InputError("must be at least 64", column="--samples")
    try:
        rep = target_report(args.model, data=args.data, scene=args.scene, seed=args.seed,
                            samples=args.samples, calib=args.calib, bits=args.bits,
                            build_dir=args.build_dir,
                            log=lambda m: print(f"target-report: {m}", file=sys.stderr, flush=True))
    except (toolchain.ToolchainMissing, CSourcesMissing) as exc:
        raise InputError(str(exc)) from exc
    if not args.json:
        _print_summary(rep)
    return rep


def _print_summary(rep: dict[str, Any]) -> None:
    print(f"bit-exact on Cortex-M4 (portable and DSP): {rep['bit_exact']} over {rep['samples']} steps")
    for name, b in rep["builds"].items():
        frac = b["budget_fraction_at_168MHz"]
        share = f"{100 * frac:.1f} %" if frac is not None else "?"
        print(f"  {name:8s}: {b['instructions_per_step']} instructions worst step, "
              f"{b['instructions_per_mac']} per MAC, {share} of 1 ms at 168 MHz "
              f"(1 instruction/cycle assumed)" + ("" if b["bit_exact"] else
                                                  f"  MISMATCH: {b.get('first_mismatches')}"))
    print(f"  MACs per step {rep['macs_per_step']}; flash {rep['flash_bytes']} B "
          f"(text {rep['text_bytes']}, rodata {rep['rodata_bytes']}, data {rep['data_bytes']}); "
          f"RAM {rep['ram_bytes']} B (bss {rep['bss_bytes']}, state {rep['state_bytes']}, "
          f"stack {rep['stack_bytes']})")


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m fbgforce.target`` (what ``make -C runtime_c target-test`` runs): the
    report for ``--model`` (default: a small model trained here on the ``smoke`` scene); exit
    status 1 unless bit-exact."""
    ap = argparse.ArgumentParser(prog="python -m fbgforce.target")
    ap.add_argument("--model", help="model directory (default: train a small one)")
    ap.add_argument("--samples", type=int, default=600)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="fbg-target-model-") as tmp:
        model_dir = Path(args.model) if args.model else _train_small(Path(tmp))
        try:
            rep = target_report(model_dir, samples=args.samples,
                                log=lambda m: print(f"target-test: {m}", file=sys.stderr, flush=True))
        except (toolchain.ToolchainMissing, CSourcesMissing, InputError) as exc:
            print(f"target-test: {exc}", file=sys.stderr)
            return 2
    if args.json:
        print(json.dumps(rep))
    else:
        _print_summary(rep)
    return 0 if rep["bit_exact"] else 1


def _train_small(tmp: Path) -> Path:
    """A small model on the simulated ``smoke`` scene (what the test fixtures use)."""
    from fbgforce.recordings import dataset as fds
    from fbgforce.model import modeldir as fm
    from fbgforce import sim
    from fbgforce.trainer.train import train

    data = tmp / "smoke.csv"
    fds.save(sim.simulate("smoke", seed=0), data)
    out = tmp / "model"
    print("target-test: training a small model on the smoke scene", file=sys.stderr, flush=True)
    fm.save(train([data], epochs=40, seed=0, filter="causal", progress=False), out)
    return out
