"""The ``fbgforce`` command.

Each part of the package contributes its own subcommands through a ``cli`` module with a
``register(subparsers)`` function (see :data:`COMMAND_MODULES`), so that the parts stay
independent and this file never grows. A subcommand's handler takes the parsed arguments and
returns a dict (printed as one JSON object with ``--json``) or ``None``.

Conventions (docs/cli.md): progress goes to stderr, ``--json`` prints exactly one JSON object
on stdout, exit status 0 on success and 2 on bad input with a one-line reason.
"""
from __future__ import annotations

import argparse
import importlib
import json
import math
import sys
from typing import Any, Callable, Sequence

from fbgforce.jsonutil import json_default
from fbgforce import __version__
from fbgforce.errors import InputError

#: Modules that define subcommands, in the order their commands appear in ``--help``.
COMMAND_MODULES = (
    "fbgforce.sim.cli",
    "fbgforce.labcli",
    "fbgforce.trainer.cli",
    "fbgforce.export.cli",
    "fbgforce.tradeoff.cli",
    "fbgforce.target.cli",
    "fbgforce.interrogator.cli",
    "fbgforce.teleop.cli",
    "fbgforce.demo",
)

Handler = Callable[[argparse.Namespace], "dict[str, Any] | None"]


def add_json_flag(parser: argparse.ArgumentParser) -> None:
    """Give a subcommand the shared ``--json`` flag."""
    parser.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object on stdout (keys in docs/cli.md); progress stays on stderr",
    )


# Argument types shared by every subcommand, so a bad number reads the same everywhere.

def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {text}")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, not {text}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, not {text}")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    value = float(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, not {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """Assemble the top-level parser from every module in :data:`COMMAND_MODULES`."""
    parser = argparse.ArgumentParser(
        prog="fbgforce",
        description=(
            "Contact, force and contact location from the fibre Bragg gratings of a gripper "
            "fingertip: simulate, train, export to ONNX and fixed-point C, verify, stream."
        ),
        epilog="Run 'fbgforce COMMAND --help' for the options of one command. Docs: docs/cli.md",
    )
    parser.add_argument("--version", action="version", version=f"fbgforce {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_name in COMMAND_MODULES:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            # Only tolerate the command module itself being absent (a part not built yet);
            # a missing dependency inside it is a real error and must surface.
            if exc.name == module_name:
                continue
            raise
        module.register(subparsers)
    return parser


def emit(result: dict[str, Any] | None, as_json: bool) -> None:
    """Print a handler's result: JSON on stdout with ``--json``, else nothing more."""
    if as_json and result is not None:
        json.dump(result, sys.stdout, indent=None, sort_keys=False, default=json_default)
        sys.stdout.write("\n")



def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``fbgforce`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Handler | None = getattr(args, "handler", None)
    if handler is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        result = handler(args)
    except InputError as exc:
        print(f"fbgforce {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fbgforce {args.command}: interrupted", file=sys.stderr)
        return 130
    emit(result, getattr(args, "json", False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
