"""The package installs as one ``fbgforce`` namespace, regular or editable.

CI runs this file against a regular (non-editable) install from outside the repository root,
which is where a forgotten subpackage, scene file or C source shows up.
"""
from __future__ import annotations

import importlib
import importlib.resources
import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]


@pytest.mark.parametrize("name", sorted(PACKAGES))
def test_every_mapped_package_imports(name: str) -> None:
    module = importlib.import_module(name)
    assert module.__file__ is not None


def test_no_top_level_modules_named_after_directories() -> None:
    # Only the fbgforce namespace is installed: `import trainer` must not work from elsewhere.
    for directory in PACKAGES.values():
        if directory == "pkgroot":
            continue
        found = importlib.util.find_spec(directory)
        if found is not None and found.origin is not None:
            assert Path(found.origin).resolve().parent.parent == REPO, (
                f"a top-level module {directory!r} is installed: {found.origin}")


def test_scene_files_ship_as_package_data() -> None:
    scenes = importlib.resources.files("fbgforce.scenes")
    names = {p.name for p in scenes.iterdir() if p.name.endswith(".toml")}
    assert {"calibration.toml", "ideal.toml"} <= names


def test_c_extension_loads_and_matches_header_version() -> None:
    from fbgforce import _runtime

    header = (REPO / "runtime_c" / "include" / "fbgforce.h").read_text()
    major = int(header.split("#define FBG_VERSION_MAJOR")[1].split()[0])
    minor = int(header.split("#define FBG_VERSION_MINOR")[1].split()[0])
    assert _runtime.lib.fbg_version() == (major << 16) | minor


def test_console_command_lists_every_part() -> None:
    out = subprocess.run([sys.executable, "-m", "fbgforce.cli", "--help"], capture_output=True,
                         text=True, check=True).stdout
    for command in ("simulate", "train", "evaluate", "export", "verify", "demo"):
        assert command in out


def test_bad_input_exits_2_with_one_line() -> None:
    result = subprocess.run([sys.executable, "-m", "fbgforce.cli", "evaluate", "--model",
                             "/nonexistent/model", "--data", "/nonexistent.csv"],
                            capture_output=True, text=True)
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1
    assert "nonexistent" in result.stderr
