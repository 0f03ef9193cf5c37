"""Build and run on the target: the cross-built libraries (``runtime_c/target.mk``), the replay
firmware (``examples/firmware/``), QEMU with the instruction-window plugin, and flash/RAM from
the linker map. Every build runs in a staged copy of the C sources
(:func:`fbgforce.target.sources.stage`), never in the installed package."""
from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence


def _run(cmd: Sequence[str], cwd: Path | None = None, timeout: float = 300.0) -> subprocess.CompletedProcess:
    r = subprocess.run(list(cmd), cwd=cwd, capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-25:])
        raise RuntimeError(f"command failed ({r.returncode}): {' '.join(cmd)}\n{tail}")
    return r


def build_libraries(root: Path) -> dict[str, Any]:
    """Cross-build the three libraries and run the no-float check (``runtime_c/target.mk``)
    in the staged C tree ``root``."""
    r = _run(["make", "-s", "-C", str(root / "runtime_c"), "-f", "target.mk", "target-libs"])
    warnings = [ln for ln in (r.stdout + r.stderr).splitlines() if "warning" in ln.lower()]
    return {"nofloat_ok": True, "warnings": warnings}


def build_firmware(root: Path, build: Path, model_c: Path, model_sym: str, golden_c: Path,
                   dsp: bool) -> Path:
    """``make -C examples/firmware`` of the staged C tree ``root`` for one library variant;
    returns the build directory."""
    out = build / ("dsp" if dsp else "portable")
    _run(["make", "-s", "-C", str(root / "examples" / "firmware"), f"BUILD={out}", f"DSP={int(dsp)}",
          f"MODEL_C={model_c}", f"MODEL_SYM={model_sym}", f"GOLDEN_C={golden_c}",
          "all", f"{out}/insn_window.so"])
    return out


def _symbols(elf: Path, functions_only: bool = False) -> dict[str, tuple[int, int]]:
    """``{name: (address without the Thumb bit, size)}`` from ``nm -S``."""
    r = _run(["arm-none-eabi-nm", "-S", str(elf)])
    syms = {}
    for line in r.stdout.splitlines():
        parts = line.split()
        if len(parts) == 4 and (not functions_only or parts[2] in "tT"):
            syms[parts[3]] = (int(parts[0], 16) & ~1, int(parts[1], 16))
    return syms


def function_ranges(elf: Path) -> dict[str, tuple[int, int]]:
    """``{function: (address, size)}`` of every sized function symbol of ``elf``."""
    return {k: v for k, v in _symbols(elf, functions_only=True).items() if v[1] > 0}


#: Functions of the replay harness itself, left out of the per-function profile.
HARNESS_FUNCTIONS = {"main", "paint_stack", "report_mismatch", "current_sp", "stack_used_below",
                     "Reset_Handler", "Fault_Handler", "sh_exit", "sh_puts", "sh_putu", "sh_puti",
                     "sh_kv", "utoa10", "itoa10", "fbg_mark_begin", "fbg_mark_end", "fw_timed_step",
                     "memcmp"}


@dataclass
class FirmwareRun:
    exit_code: int
    result: dict[str, int]
    mismatch_lines: list[str]
    windows: list[int]
    insns_total: int
    console: str
    profile: dict[str, int] = field(default_factory=dict)
    #: The worst window instruction by instruction: (address, executed, taken, sequential in).
    worst_pcs: list[tuple[int, int, int, int]] = field(default_factory=list)


def run_firmware(build: Path, timeout: float = 300.0) -> FirmwareRun:
    """Run fw.elf under QEMU with the instruction-window plugin; parse its result line."""
    elf = build / "fw.elf"
    syms = _symbols(elf)
    for s in ("fbg_mark_begin", "fbg_mark_end", "fw_timed_step"):
        if s not in syms:
            raise RuntimeError(f"{elf}: symbol {s} missing")
    out = build / "insns.txt"
    args = [f"begin={syms['fbg_mark_begin'][0]}", f"end={syms['fbg_mark_end'][0]}"]
    args += [f"ex={syms[s][0]}:{syms[s][0] + syms[s][1]}"
             for s in ("fbg_mark_begin", "fbg_mark_end", "fw_timed_step")]
    funcs = {k: v for k, v in _symbols(elf, functions_only=True).items()
             if v[1] > 0 and k not in HARNESS_FUNCTIONS}
    args += [f"r={lo}:{lo + size}" for lo, size in funcs.values()]
    args.append(f"out={out}")
    cmd = ["qemu-system-arm", "-M", "mps2-an386", "-nographic", "-semihosting", "-kernel", str(elf),
           "-plugin", f"{build / 'insn_window.so'}," + ",".join(args)]
    r = subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=timeout)
    # QEMU 7.2 writes the semihosting console to stderr.
    console = r.stdout + r.stderr
    result: dict[str, int] = {}
    for line in console.splitlines():
        if line.startswith("FBG_RESULT"):
            result = {k: int(v) for k, v in re.findall(r"(\w+)=(-?\d+)", line)}
    mism = [ln for ln in console.splitlines() if ln.startswith("FBG_MISMATCH")]
    windows, total, by_lo, pcs = [], 0, {}, []
    if out.is_file():
        for line in out.read_text().splitlines():
            key, _, val = line.partition(" ")
            if key == "w":
                windows.append(int(val))
            elif key == "insns_total":
                total = int(val)
            elif key == "range":
                lo, _, cnt = val.split()
                by_lo[int(lo)] = int(cnt)
            elif key == "pc":
                a, e, t, q = (int(v) for v in val.split())
                pcs.append((a, e, t, q))
    profile = {name: by_lo.get(lo, 0) for name, (lo, _) in funcs.items()}
    return FirmwareRun(r.returncode, result, mism, windows, total, console,
                       {k: v for k, v in sorted(profile.items(), key=lambda kv: -kv[1]) if v}, pcs)


_MAP_LINE = re.compile(r"^\s+0x[0-9a-fA-F]+\s+0x([0-9a-fA-F]+)\s+(\S.*)$")
_MAP_FULL = re.compile(r"^ (\.\S+|COMMON)\s+0x[0-9a-fA-F]+\s+0x([0-9a-fA-F]+)\s+(\S.*)$")


def map_sizes(map_path: Path, exclude: Sequence[str]) -> dict[str, int]:
    """Bytes per kind (text, rodata, data, bss) of every input section in the final link
    (after --gc-sections) except those from object files whose name ends with one of
    ``exclude``; parsed from a GNU ld map file."""
    sizes = {"text": 0, "rodata": 0, "data": 0, "bss": 0}
    text = map_path.read_text()
    start = text.find("Linker script and memory map")
    lines = text[start:].splitlines() if start >= 0 else []
    pending: str | None = None
    for line in lines:
        sect = size = origin = None
        m = _MAP_FULL.match(line)
        if m:
            sect, size, origin = m.group(1), int(m.group(2), 16), m.group(3)
        elif pending is not None:
            m2 = _MAP_LINE.match(line)
            if m2:
                sect, size, origin = pending, int(m2.group(1), 16), m2.group(2)
        pending = None
        if sect is None:
            s = line.strip()
            if line.startswith(" .") and len(s.split()) == 1:
                pending = s
            continue
        origin = origin.strip()
        if any(origin.endswith(e) for e in exclude) or size == 0:
            continue
        kind = _kind(sect)
        if kind:
            sizes[kind] += size
    return sizes


def _kind(section: str) -> str | None:
    if section.startswith((".text", ".ARM.exidx")):
        return "text"
    if section.startswith(".rodata"):
        return "rodata"
    if section.startswith(".data"):
        return "data"
    if section.startswith((".bss", "COMMON")):
        return "bss"
    return None
