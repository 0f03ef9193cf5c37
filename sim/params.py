"""Parameter schemas for scene sections, and their validation with located error messages."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from fbgforce.errors import InputError


@dataclass(frozen=True)
class Param:
    """One scene parameter: its type, default, allowed range or choices, and meaning.

    ``kind`` is ``"float"``, ``"int"``, ``"str"`` or ``"bool"``. ``lo``/``hi`` are inclusive
    bounds unless ``lo_open``/``hi_open`` says otherwise (a time constant must be > 0).
    """

    kind: str
    default: Any
    doc: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] = ()
    lo_open: bool = False
    hi_open: bool = False

    def allowed(self) -> str:
        """Human-readable description of the accepted values."""
        if self.choices:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        if self.kind == "bool":
            return "true or false"
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        left = "(" if self.lo_open or self.lo is None else "["
        right = ")" if self.hi_open or self.hi is None else "]"
        what = "an integer" if self.kind == "int" else "a number"
        return f"{what} in {left}{lo}, {hi}{right}"


def _type_name(value: Any) -> str:
    return {bool: "boolean", int: "integer", float: "number", str: "string", dict: "table",
            list: "array"}.get(type(value), type(value).__name__)


def check_params(values: Mapping[str, Any], schema: Mapping[str, Param], *, path: str | None,
                 key_path: str) -> dict[str, Any]:
    """Validate a TOML table against a schema and fill in defaults.

    Raises
    ------
    InputError
        Naming the file, the dotted key path, and the allowed keys or values.
    """
    out: dict[str, Any] = {}
    for key in values:
        if key not in schema:
            raise InputError(f"unknown key; allowed keys: {', '.join(schema)}", path=path,
                             column=f"{key_path}.{key}" if key_path else key)
    for key, p in schema.items():
        where = f"{key_path}.{key}" if key_path else key
        if key not in values:
            out[key] = p.default
            continue
        v = values[key]
        if p.kind == "bool":
            if not isinstance(v, bool):
                raise InputError(f"expected true or false, got {_type_name(v)} {v!r}", path=path,
                                 column=where)
        elif p.kind == "str":
            if not isinstance(v, str):
                raise InputError(f"expected a string ({p.allowed()}), got {_type_name(v)} {v!r}",
                                 path=path, column=where)
            if p.choices and v not in p.choices:
                raise InputError(f"{v!r} is not allowed; expected {p.allowed()}", path=path,
                                 column=where)
        else:
            ok_types = (int,) if p.kind == "int" else (int, float)
            if isinstance(v, bool) or not isinstance(v, ok_types):
                raise InputError(f"expected {p.allowed()}, got {_type_name(v)} {v!r}", path=path,
                                 column=where)
            if isinstance(v, float) and not math.isfinite(v):
                raise InputError(f"expected {p.allowed()}, got {v!r}", path=path, column=where)
            bad = ((p.lo is not None and (v < p.lo or (p.lo_open and v == p.lo)))
                   or (p.hi is not None and (v > p.hi or (p.hi_open and v == p.hi))))
            if bad:
                raise InputError(f"{v!r} is out of range; expected {p.allowed()}", path=path,
                                 column=where)
            v = int(v) if p.kind == "int" else float(v)
        out[key] = v
    return out
