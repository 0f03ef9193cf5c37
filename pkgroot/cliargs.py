"""What every subcommand's ``register`` and handler share: argument types, the options most
commands take (``--model``, ``--data``, ``--seed``, ``--json``), the shape of a subcommand and
the error exits of docs/cli.md.

It imports base modules only, so that a command module anywhere in the package can use it
without reaching up to :mod:`fbgforce.cli`, which imports every command module.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from typing import Any, Callable, Iterator

from fbgforce.errors import InputError
from fbgforce.jsonutil import json_default

Handler = Callable[[argparse.Namespace], "dict[str, Any] | None"]


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


# The shape of a subcommand and the options most of them take.

@contextlib.contextmanager
def command(subparsers: Any, name: str, handler: Handler, *, help: str,
            description: str) -> Iterator[argparse.ArgumentParser]:
    """Add subcommand ``name`` run by ``handler``; the ``with`` body adds its options and
    ``--json`` comes after them, last in its ``--help`` as in every command's."""
    parser = subparsers.add_parser(name, help=help, description=description)
    yield parser
    add_json_flag(parser)
    parser.set_defaults(handler=handler)


def add_json_flag(parser: argparse.ArgumentParser) -> None:
    """Give a subcommand the shared ``--json`` flag."""
    parser.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object on stdout (keys in docs/cli.md); progress stays on stderr",
    )


def add_model(parser: Any, help: str | None = None, *, metavar: str | None = "MODEL_DIR",
              required: bool = True) -> None:
    """``--model``: the model directory a command reads (required unless told)."""
    parser.add_argument("--model", required=required, metavar=metavar, help=help)


def add_data(parser: Any, help: str | None = None, *, metavar: str = "FILE",
             nargs: str | None = "+", required: bool = True) -> None:
    """``--data``: the recording(s) a command reads (one or more, required, unless told);
    ``parser`` may be a mutually exclusive group."""
    parser.add_argument("--data", nargs=nargs, required=required, metavar=metavar, help=help)


def add_seed(parser: Any, help: str | None = None, *, type: Callable[[str], int] = int,
             default: int | None = 0) -> None:
    """``--seed``: the seed of a command's randomness (default 0 unless told)."""
    parser.add_argument("--seed", type=type, default=default, help=help)


# Error exits (docs/cli.md): status 2 and one line on bad input, with --json also on stdout.

def at_least(value: float | None, low: float, flag: str) -> None:
    """Refuse ``value`` (when given) below ``low`` as a bad ``flag``."""
    if value is not None and value < low:
        raise InputError(f"must be >= {low}, got {value}", column=flag)


def emit(result: dict[str, Any] | None, as_json: bool) -> None:
    """Print a handler's result: JSON on stdout with ``--json``, else nothing more."""
    if as_json and result is not None:
        json.dump(result, sys.stdout, indent=None, sort_keys=False, default=json_default)
        sys.stdout.write("\n")


def fail(line: str, as_json: bool, code: int = 2) -> int:
    """Report a failure: ``line`` on stderr and, with ``--json``, ``{"error", "code"}`` on
    stdout (docs/cli.md); returns ``code``."""
    print(line, file=sys.stderr)
    if as_json:
        emit({"error": line, "code": code}, True)
    return code
