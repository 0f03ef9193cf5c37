"""Package list, the cffi extension and the C sources shipped for the target build; everything
else lives in pyproject.toml."""
import runpy
import tomllib
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
PACKAGE_DIR = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
# fbgforce.target.sources is standard-library only so it can be read before installation: it
# names the C files `fbgforce target-report` builds and copies them.
TARGET_SOURCES = runpy.run_path(str(ROOT / PACKAGE_DIR["fbgforce.target"] / "sources.py"))

packages = list(PACKAGE_DIR)
for name, directory in PACKAGE_DIR.items():
    packages += [f"{name}.{sub}" for sub in find_packages(directory)]


class BuildPyWithCSources(build_py):
    """Also copy the header, library sources, target.mk and the replay firmware into
    ``fbgforce/target/csrc`` so a regular install can cross-build them. An editable install
    reads them from the repository instead."""

    def run(self) -> None:
        super().run()
        if not getattr(self, "editable_mode", False):
            dest = Path(self.build_lib) / "fbgforce" / "target" / "csrc"
            TARGET_SOURCES["copy_tree"](ROOT, dest)


setup(packages=packages, cffi_modules=["runtime_c/build_runtime.py:ffibuilder"],
      cmdclass={"build_py": BuildPyWithCSources})
