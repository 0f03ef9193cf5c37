"""fbgforce: contact, force and contact location from fibre Bragg gratings.

Subpackages live in sibling top-level directories of the repository and are mapped onto this
namespace by ``pyproject.toml``: ``fbgforce.sim`` (simulator), ``fbgforce.trainer`` (numpy
training), ``fbgforce.export`` (ONNX and fixed-point export), ``fbgforce.pybind`` (the cffi
binding of the C runtime), ``fbgforce.interrogator`` (serial I/O), ``fbgforce.teleop``.
"""
from __future__ import annotations

from typing import Any

from fbgforce.contract import VERSION_STR as __version__

__all__ = ["Runtime", "__version__"]


def __getattr__(name: str) -> Any:
    # The C extension is imported lazily so that simulation and training work even where the
    # extension could not be built, and so that `import fbgforce` stays cheap for the CLI.
    if name == "Runtime":
        from fbgforce.pybind import Runtime

        return Runtime
    raise AttributeError(f"module 'fbgforce' has no attribute {name!r}")
