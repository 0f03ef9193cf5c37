"""The ``fbgforce`` command.

Each part of the package contributes its own subcommands through a ``cli`` module with a
``register(subparsers)`` function (see :data:`COMMAND_MODULES`), so that the parts stay
independent and this file never grows. A subcommand's handler takes the parsed arguments and
returns a dict (printed as one JSON object with ``--json``) or ``None``.

Conventions (docs/cli.md): progress goes to stderr, ``--json`` prints exactly one JSON object
on stdout, exit status 0 on success and 2 on bad input with a one-line reason (with ``--json``
also ``{"error": ..., "code": 2}`` on stdout). SIGINT and SIGTERM end a command cleanly
(:mod:`fbgforce.signals`): exit status 130 or 143, after the command's summary if it has one.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Any, Sequence

from fbgforce import __version__, signals
from fbgforce.cliargs import Handler, emit, fail
from fbgforce.errors import InputError

#: Modules that define subcommands, in the order their commands appear in ``--help``.
COMMAND_MODULES = (
    "fbgforce.sim.cli",
    "fbgforce.recordings.cli",
    "fbgforce.trainer.cli",
    "fbgforce.export.cli",
    "fbgforce.tradeoff.cli",
    "fbgforce.target.cli",
    "fbgforce.interrogator.cli",
    "fbgforce.teleop.cli",
    "fbgforce.demo.cli",
)


class UsageError(Exception):
    """A command line argparse refuses (its message is argparse's one line)."""


class _Parser(argparse.ArgumentParser):
    """argparse, but a bad command line raises :class:`UsageError` instead of exiting, so that
    :func:`main` reports it like any other input error (JSON with ``--json``). Subparsers
    inherit the class."""

    def error(self, message: str) -> Any:
        self.print_usage(sys.stderr)
        raise UsageError(f"{self.prog}: error: {message}")


def build_parser() -> argparse.ArgumentParser:
    """Assemble the top-level parser from every module in :data:`COMMAND_MODULES`."""
    parser = _Parser(
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


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``fbgforce`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        return fail(str(exc), "--json" in argv)
    handler: Handler | None = getattr(args, "handler", None)
    if handler is None:
        parser.print_help(sys.stderr)
        return 2
    as_json = getattr(args, "json", False)
    try:
        with signals.stop_on_signals():
            result = handler(args)
            emit(result, as_json)
    except InputError as exc:
        return fail(f"fbgforce {args.command}: error: {exc}", as_json)
    except OSError as exc:
        # A file problem outside the paths that name their option.
        where = f"{exc.filename}: " if exc.filename else ""
        return fail(f"fbgforce {args.command}: error: {where}{exc.strerror or exc}", as_json)
    except KeyboardInterrupt as exc:
        name = signals.signal_name(exc)
        return fail(f"fbgforce {args.command}: stopped by {name}", as_json,
                    signals.exit_status(name))
    if isinstance(result, dict) and result.get("interrupted"):
        # A live command stopped by a signal has written its summary; the exit status still
        # says it was stopped (130 SIGINT, 143 SIGTERM).
        return signals.exit_status(result.get("signal") or "SIGINT")
    return 0


if __name__ == "__main__":
    sys.exit(main())
