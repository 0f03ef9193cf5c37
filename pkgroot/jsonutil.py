"""JSON encoding of the values our results hold (numpy scalars and arrays, paths)."""
from __future__ import annotations

from pathlib import PurePath
from typing import Any

import numpy as np


def json_default(value: Any) -> Any:
    """``default=`` hook for :func:`json.dumps`: numpy scalars, arrays and paths as plain JSON."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, PurePath):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
