"""cffi API-mode builder for ``fbgforce._runtime`` (run by ``pip install`` through setup.py).

The cdef is the public header with its preprocessor lines removed, so the header stays the
one place the C API is declared.
"""
from __future__ import annotations

import pathlib
import re

from cffi import FFI

HERE = pathlib.Path(__file__).resolve().parent
HEADER = HERE / "include" / "fbgforce.h"


def _cdef_text() -> str:
    lines = []
    in_cplusplus = False
    for line in HEADER.read_text().splitlines():
        stripped = line.lstrip()
        # The C++ linkage guard ('extern "C" {' ... '}') is not C; drop what it encloses.
        if re.match(r"#\s*ifdef\s+__cplusplus\b", stripped):
            in_cplusplus = True
            continue
        if in_cplusplus:
            if re.match(r"#\s*endif\b", stripped):
                in_cplusplus = False
            continue
        # cffi understands '#define NAME <integer>' but no other preprocessor lines.
        if stripped.startswith("#"):
            # A trailing /* comment */ on a constant is documentation, not part of the value.
            stripped = re.sub(r"/\*.*?\*/\s*$", "", stripped).rstrip()
            if re.match(r"#\s*define\s+FBG_\w+\s+\(?-?(0x)?[0-9A-Fa-f]+[uUlL]*\)?\s*$", stripped):
                lines.append(stripped)
            continue
        lines.append(line)
    return "\n".join(lines)


ffibuilder = FFI()
ffibuilder.cdef(_cdef_text())
ffibuilder.set_source(
    "fbgforce._runtime",
    '#include "fbgforce.h"',
    # Relative to the project root: setuptools rejects absolute source paths in some versions.
    sources=sorted(str(p.relative_to(HERE.parent)) for p in (HERE / "src").glob("*.c")),
    include_dirs=["runtime_c/include"],
    # Only optimisation here: cffi's generated wrapper is not -pedantic clean. The library's own
    # sources are held to -std=c99 -Wall -Wextra -Werror -pedantic by runtime_c/Makefile,
    # which the test suite runs. -O3 lets GCC vectorise the int16 x int16 -> int64 MAC loops
    # (exact integer arithmetic, so the bits do not change): 8.2 -> 3.4 us per sample on the
    # host for the paper-sized model (docs/measurements/runtime.md).
    extra_compile_args=["-O3"],
)

if __name__ == "__main__":
    ffibuilder.compile(verbose=True)
