"""Package list and the cffi extension; everything else lives in pyproject.toml."""
import tomllib
from pathlib import Path

from setuptools import find_packages, setup

ROOT = Path(__file__).resolve().parent
PACKAGE_DIR = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]

packages = list(PACKAGE_DIR)
for name, directory in PACKAGE_DIR.items():
    if name != "fbgforce":
        packages += [f"{name}.{sub}" for sub in find_packages(directory)]

setup(packages=packages, cffi_modules=["runtime_c/build_runtime.py:ffibuilder"])
