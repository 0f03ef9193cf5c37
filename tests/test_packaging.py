"""The package installs as one ``fbgforce`` namespace, regular or editable.

CI runs this file against a regular (non-editable) install from outside the repository root,
which is where a forgotten subpackage, scene file or C source shows up.
"""
from __future__ import annotations

import importlib
import importlib.resources
import importlib.util
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from conftest import missing_tool

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


def test_ros2_message_package_ships_as_package_data() -> None:
    package = importlib.resources.files("fbgforce.interrogator").joinpath("fbgforce_msgs")
    for name in ("package.xml", "CMakeLists.txt", "msg/Contact.msg", "msg/Peaks.msg",
                 "msg/Stage.msg"):
        assert package.joinpath(name).is_file(), name


def test_c_extension_loads_and_matches_header_version() -> None:
    from fbgforce import _runtime

    header = (REPO / "runtime_c" / "include" / "fbgforce.h").read_text()
    major, minor, patch = (int(header.split(f"#define FBG_VERSION_{part}")[1].split()[0])
                           for part in ("MAJOR", "MINOR", "PATCH"))
    assert _runtime.lib.fbg_version() == (major << 16) | (minor << 8) | patch
    import fbgforce

    assert fbgforce.__version__ == f"{major}.{minor}.{patch}"


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


def _runs_from_repository() -> bool:
    """True in an editable install (or with the repository on sys.path), False in a regular one."""
    import fbgforce

    return Path(fbgforce.__file__).resolve().is_relative_to(REPO)


def _repository_files(rel: str, ignored: tuple[str, ...]) -> set[str]:
    """Repository files under ``rel`` (a file or a directory), build products left out."""
    import fnmatch

    top = REPO / rel
    if top.is_file():
        return {rel}
    out = set()
    for p in top.rglob("*"):
        parts = p.relative_to(REPO).parts
        if p.is_file() and not any(fnmatch.fnmatch(part, pat) for part in parts for pat in ignored):
            out.add("/".join(parts))
    return out


def test_target_c_sources_ship_with_the_package() -> None:
    """What `fbgforce target-report` compiles is found wherever the package is installed: the
    header, the library sources, target.mk and the replay firmware with the QEMU plugin, the
    same bytes as the repository's."""
    from fbgforce.target import sources

    root = sources.source_root()
    if not _runs_from_repository():
        assert root == sources.PACKAGED, f"a regular install must use its own copy, not {root}"
    expected = set().union(*(_repository_files(rel, sources.IGNORED) for rel in sources.SHIPPED))
    for must in ("runtime_c/include/fbgforce.h", "runtime_c/src/fbg_fixed.c", "runtime_c/target.mk",
                 "examples/firmware/Makefile", "examples/firmware/insn_window_plugin.c",
                 "examples/firmware/mps2.ld"):
        assert must in expected, must
    for rel in sorted(expected):
        assert (root / rel).is_file(), f"{rel} missing from {root}"
        assert (root / rel).read_bytes() == (REPO / rel).read_bytes(), f"{rel} differs in {root}"
    assert sources.header_constants()["FBG_OK"] == 0


@pytest.mark.parametrize("command,option", [("target-report", "--model"), ("tradeoff", "--out")])
def test_tool_commands_explain_themselves(command: str, option: str, tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "fbgforce.cli", command, "--help"], cwd=tmp_path,
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert option in result.stdout


@pytest.mark.slow
def test_tradeoff_runs_from_the_installed_package(tmp_path: Path, small_dataset_path) -> None:
    """A tiny grid (two engines, one epoch, no target counts) end to end, outputs written."""
    out = tmp_path / "tradeoff"
    result = subprocess.run([sys.executable, "-m", "fbgforce.cli", "tradeoff", "--data",
                             str(small_dataset_path), "--out", str(out), "--quick", "--epochs", "1",
                             "--engines", "float", "fixed", "--no-target", "--json"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["measured"] >= 2 and not summary["missing"]
    for name in ("json", "csv", "md"):
        assert (out / f"tradeoff.{name}").stat().st_size > 0


def _tree(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.fixture(scope="module")
def tiny_model_dir(tmp_path_factory, small_dataset_path) -> Path:
    """A model trained for two epochs by the installed ``fbgforce train`` (bit-exactness on the
    target does not depend on how well it is trained)."""
    out = tmp_path_factory.mktemp("tiny_model") / "model"
    subprocess.run([sys.executable, "-m", "fbgforce.cli", "train", "--data", str(small_dataset_path),
                    "--out", str(out), "--epochs", "2", "--idle-pads", "0"], check=True,
                   capture_output=True)
    return out


@pytest.mark.target
def test_target_report_runs_from_the_installed_package(tmp_path: Path, tiny_model_dir: Path) -> None:
    """Bit-exact on the Cortex-M4 from wherever the package is installed, building in a staged
    copy (the installed package gains no build products)."""
    from fbgforce.target import sources, toolchain

    missing = toolchain.missing_tools()
    if missing:
        missing_tool(f"Cortex-M4 tools missing ({', '.join(missing)}); install: {toolchain.APT_LINE}")
    packaged = None if _runs_from_repository() else _tree(sources.PACKAGED)
    result = subprocess.run([sys.executable, "-m", "fbgforce.cli", "target-report", "--model",
                             str(tiny_model_dir), "--samples", "96", "--json"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["bit_exact"] is True and report["instructions_per_step"] > 0
    if packaged is not None:
        assert _tree(sources.PACKAGED) == packaged
