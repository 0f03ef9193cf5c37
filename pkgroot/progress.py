"""Progress bars that show wherever the user looks: a terminal, a notebook, or a log file.

Plain ``tqdm`` with ``disable=None`` draws only on a terminal: a command piped into a log, run
by CI or by ``fbgforce demo`` under a service manager printed nothing for minutes, and a
notebook (whose stderr is no terminal) got no bar at all. :func:`bar` picks:

- a terminal: the usual bar on stderr, redrawn in place;
- a notebook (an IPython kernel is running): ``tqdm.auto``, a widget where ipywidgets is
  installed;
- anything else (a pipe, a file): one plain line on stderr at most every
  :data:`PIPE_PERIOD_S` seconds (and at the start), so a log shows that work goes on.
"""
from __future__ import annotations

import sys
from typing import Any, Iterable, TextIO

#: Seconds between two progress lines when stderr is not a terminal.
PIPE_PERIOD_S = 10.0


class _Lines:
    """A text stream for tqdm that turns its in-place redraws into whole lines."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        line = text.replace("\r", "").strip()
        if line:
            self.stream.write(line + "\n")
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


def _in_notebook() -> bool:
    return "ipykernel" in sys.modules


def bar(iterable: Iterable[Any] | None = None, *, enabled: bool | None = None,
        **kwargs: Any) -> Any:
    """A ``tqdm`` progress bar on stderr (``kwargs`` as for ``tqdm``).

    Parameters
    ----------
    iterable
        What to iterate over, if anything (else call ``update``).
    enabled
        False: no output at all. True or None: a bar on a terminal or in a notebook, periodic
        lines elsewhere (see the module docstring).
    """
    from tqdm import tqdm

    if enabled is False:
        return tqdm(iterable, disable=True, **kwargs)
    stderr = sys.stderr
    if getattr(stderr, "isatty", lambda: False)():
        return tqdm(iterable, file=stderr, dynamic_ncols=True, **kwargs)
    if _in_notebook():
        from tqdm.auto import tqdm as auto_tqdm

        return auto_tqdm(iterable, **kwargs)
    kwargs.pop("leave", None)
    return tqdm(iterable, file=_Lines(stderr), mininterval=PIPE_PERIOD_S,
                maxinterval=PIPE_PERIOD_S, ncols=100, ascii=True, leave=False, **kwargs)
