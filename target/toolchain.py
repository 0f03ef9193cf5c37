"""The Cortex-M4 tools target-report needs, and the apt line that installs them."""
from __future__ import annotations

import os
import shutil
import subprocess


#: apt packages that provide the tools (the message of a skipped test names them).
APT_PACKAGES = ("gcc-arm-none-eabi", "libnewlib-arm-none-eabi", "qemu-system-arm")
APT_LINE = "apt-get install --no-install-recommends " + " ".join(APT_PACKAGES) + " make gcc"
#: Executables needed, with the package that provides each.
TOOLS = {
    "arm-none-eabi-gcc": "gcc-arm-none-eabi",
    "arm-none-eabi-nm": "gcc-arm-none-eabi",
    "qemu-system-arm": "qemu-system-arm",
    "make": "make",
    "gcc": "gcc",
}


class ToolchainMissing(RuntimeError):
    """The cross toolchain or QEMU is not installed; the message says what to install."""


def missing_tools() -> list[str]:
    """Executables of :data:`TOOLS` not on PATH, plus newlib if the cross libc is absent."""
    missing = [t for t in TOOLS if shutil.which(t) is None]
    if "arm-none-eabi-gcc" not in missing and not _newlib_present():
        missing.append("libc_nano.a (newlib)")
    return missing


def _newlib_present() -> bool:
    r = subprocess.run(["arm-none-eabi-gcc", "-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=soft",
                        "-print-file-name=libc_nano.a"], capture_output=True, text=True)
    return r.returncode == 0 and os.path.isabs(r.stdout.strip())


def require_tools() -> None:
    """Raise :class:`ToolchainMissing` naming the apt packages when a tool is missing."""
    missing = missing_tools()
    if missing:
        raise ToolchainMissing(f"Cortex-M4 target tools missing ({', '.join(missing)}); "
                               f"install them with: {APT_LINE}")
