"""Errors shared by every part of fbgforce.

A user-facing problem with an input (a data file, a scene, a model directory, a command-line
value) is an :class:`InputError`. The CLI turns it into exit status 2 and one line on stderr,
so its message must say which file, where in it, and why.
"""
from __future__ import annotations


class InputError(ValueError):
    """Bad input from the user, located as precisely as we can.

    Parameters
    ----------
    message
        What is wrong and, where it helps, what would be accepted instead.
    path
        The file the problem is in, if any.
    line
        1-based line number in that file (CSV lines count the header and comments).
    column
        The column or key the problem is in (a CSV column name, a TOML key path).
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | None = None,
        line: int | None = None,
        column: str | None = None,
    ) -> None:
        self.reason = message
        self.path = path
        self.line = line
        self.column = column
        super().__init__(self._format())

    def _format(self) -> str:
        where = []
        if self.path is not None:
            where.append(str(self.path))
        if self.line is not None:
            where.append(f"line {self.line}")
        if self.column is not None:
            where.append(f"column {self.column!r}" if self.path else f"{self.column}")
        prefix = ", ".join(where)
        return f"{prefix}: {self.reason}" if prefix else self.reason
