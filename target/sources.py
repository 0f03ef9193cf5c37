"""The C sources the target build needs, where they are, and a private copy to build in.

A regular install ships them as package data under ``fbgforce/target/csrc/`` (setup.py copies
:data:`SHIPPED` there when it builds the wheel); an editable install, or a run from the
repository, uses the repository's own files. Paths below either root are the repository's, so
``examples/firmware/Makefile`` finds ``../../runtime_c`` in both.

Builds never run in the installed package (it may be read-only, and several runs may build at
once): :func:`stage` copies the tree into the build directory first. Copies keep modification
times, so a kept build directory rebuilds only what changed.

This module uses the standard library only: setup.py reads :data:`SHIPPED` and
:func:`copy_tree` from it before the package is installed.
"""
from __future__ import annotations

import re
import shutil
from pathlib import Path

#: Files and directories (repository-relative) the cross build and the replay firmware use:
#: the public header, the library sources, the cross-build rules, and the firmware with its
#: linker script, startup code and the QEMU instruction-window plugin.
SHIPPED = ("runtime_c/include", "runtime_c/src", "runtime_c/target.mk", "examples/firmware")
#: Build products and caches that a developer's tree may hold next to the sources.
IGNORED = ("build", "__pycache__", "*.o", "*.a", "*.so", "*.elf", "*.map", "*.su", "*.pyc")
#: Where a regular install keeps its copy.
PACKAGED = Path(__file__).resolve().parent / "csrc"
#: The repository root when the package runs from a checkout (editable install).
REPOSITORY = Path(__file__).resolve().parent.parent
HEADER = "runtime_c/include/fbgforce.h"


class CSourcesMissing(RuntimeError):
    """Neither the installed package nor a repository checkout holds the C sources."""


def copy_tree(src_root: Path, dest_root: Path) -> None:
    """Copy every :data:`SHIPPED` path from ``src_root`` to the same place under ``dest_root``
    (modification times kept, build products left out)."""
    ignore = shutil.ignore_patterns(*IGNORED)
    for rel in SHIPPED:
        src, dest = Path(src_root) / rel, Path(dest_root) / rel
        if src.is_dir():
            shutil.copytree(src, dest, ignore=ignore, dirs_exist_ok=True)
        else:
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest)


def source_root() -> Path:
    """The directory holding every :data:`SHIPPED` path: the repository checkout the package
    runs from, else the installed copy. Raises :class:`CSourcesMissing` naming both places."""
    for root in (REPOSITORY, PACKAGED):
        if all((root / rel).exists() for rel in SHIPPED):
            return root
    raise CSourcesMissing(f"C sources for the target build not found (looked for "
                          f"{', '.join(SHIPPED)} in {REPOSITORY} and {PACKAGED}); reinstall "
                          f"fbgforce: pip install fbgforce")


def stage(dest: Path) -> Path:
    """Copy the C sources into ``dest`` and return it (the root to run ``make`` below)."""
    dest = Path(dest)
    copy_tree(source_root(), dest)
    return dest


def header_constants() -> dict[str, int]:
    """``FBG_*`` integer constants and ``fbg_status`` values from the public header."""
    text = (source_root() / HEADER).read_text()
    consts = {m.group(1): int(m.group(2), 0) for m in
              re.finditer(r"#define\s+(FBG_\w+)\s+\(?(-?(?:0x[0-9A-Fa-f]+|\d+))[uU]?\)?\s", text)}
    consts.update({m.group(1): int(m.group(2)) for m in
                   re.finditer(r"\b(FBG_(?:OK|ERR_\w+))\s*=\s*(-?\d+)", text)})
    return consts
