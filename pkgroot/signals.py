"""SIGINT and SIGTERM as exceptions, so a command ends cleanly when it is stopped.

``systemd``, ``docker stop`` and ``kill`` send SIGTERM, a terminal's Ctrl-C sends SIGINT.
Python's default kills the process on SIGTERM without running ``finally`` blocks: files stay
unflushed, a summary unwritten. Within :func:`stop_on_signals` both signals raise
:class:`Stopped` (a :class:`KeyboardInterrupt`, so code that already ends a live loop on
Ctrl-C ends it on SIGTERM as well); the command writes what it has, and the CLI exits with
``128 + signal number`` (130 for SIGINT, 143 for SIGTERM), as shells and service managers
expect (docs/cli.md).
"""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Any, Iterator

#: The signals that stop a command cleanly.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stopped(KeyboardInterrupt):
    """The process received ``signum`` (SIGINT or SIGTERM) and should end cleanly."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """Within the block, the first SIGINT or SIGTERM raises :class:`Stopped`.

    Later ones are ignored until the block ends, so that the clean-up the first one started
    (flushing, writing the summary) is not itself interrupted. Outside the main thread, where
    Python cannot install handlers, this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def handler(signum: int, frame: Any) -> None:
        if received:
            return
        received.append(signum)
        raise Stopped(signum)

    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, old in previous.items():
            signal.signal(s, old)


def signal_name(exc: BaseException) -> str:
    """``"SIGTERM"`` or ``"SIGINT"``: what ended a loop that caught ``exc`` (a plain
    :class:`KeyboardInterrupt` is Ctrl-C)."""
    return signal.Signals(getattr(exc, "signum", signal.SIGINT)).name


def exit_status(name: str) -> int:
    """The exit status of a command stopped by the signal ``name``: 128 + its number."""
    return 128 + int(signal.Signals[name])
