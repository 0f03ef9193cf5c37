"""``fbgforce target-report``: the runtime on a real instruction set (Cortex-M4 under QEMU).

One call cross-compiles ``libfbgforce`` twice (portable C and the DSP-extension build,
``runtime_c/target.mk``), generates the model's C source and a file of golden vectors from the
numpy integer reference (:mod:`fbgforce.export.intref`), links the bare-metal replay program of
``examples/firmware/``, runs it on QEMU ``mps2-an386`` and reports:

- ``bit_exact``: every output bit of every golden record equal, in BOTH builds (the firmware
  compares the whole ``fbg_output`` struct and every return status; its exit status says so);
- exact executed-instruction counts per ``fbg_step`` from the TCG plugin
  ``examples/firmware/insn_window_plugin.c`` (one window per call, harness excluded);
- MACs per step (FIR ``4 * n_taps`` + every layer ``n_in * n_out`` of the nets that ran);
- flash and RAM from a minimal firmware (``main_size.c``): every linked section that does not
  come from the harness, i.e. library + model + the libc/libgcc helpers they pull in;
- the fraction of a 1 kHz period the worst step takes on a 168 MHz core, ASSUMING ONE
  INSTRUCTION PER CYCLE (QEMU has no timing model; on a real M4 loads not pipelined with a
  neighbouring load take 2 cycles and taken branches 2-4, so real cycles are somewhat higher).

The golden session (:func:`golden_session`) drives the whole API, not only ``fbg_step``: steps
before any tare, a tare through ``fbg_tare_begin/add/end`` (with rejected samples), a recording
replayed on that tare, ``fbg_set_baseline`` with edge-case samples (lost peaks, jumps, sentinels,
values that saturate), error returns, ``fbg_reset`` and a fresh ``fbg_init``.

Tools: ``apt-get install --no-install-recommends gcc-arm-none-eabi libnewlib-arm-none-eabi
qemu-system-arm`` (plus ``make`` and a host ``gcc`` for the plugin).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce.errors import InputError

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
#: Clock the budget fraction is quoted for, and the controller period.
CLOCK_HZ = 168_000_000
PERIOD_S = 1e-3

ROOT = Path(__file__).resolve().parent.parent
FIRMWARE_DIR = ROOT / "examples" / "firmware"
RUNTIME_DIR = ROOT / "runtime_c"
HEADER = RUNTIME_DIR / "include" / "fbgforce.h"

# Ops of examples/firmware/fw_golden.h.
OP_STEP, OP_TARE_BEGIN, OP_TARE_ADD, OP_TARE_END, OP_SET_BASELINE, OP_RESET, OP_INIT = range(7)
#: Output fields of ``fbg_output`` (fbgforce.h), as the integer reference names them.
OUTPUT_FIELDS = ("force_mN", "x_um", "y_um", "contact_margin_q8", "status", "contact_conf_q15",
                 "contact")
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1


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


def header_constants() -> dict[str, int]:
    """``FBG_*`` integer constants and ``fbg_status`` values from the public header."""
    text = HEADER.read_text()
    consts = {m.group(1): int(m.group(2), 0) for m in
              re.finditer(r"#define\s+(FBG_\w+)\s+\(?(-?(?:0x[0-9A-Fa-f]+|\d+))[uU]?\)?\s", text)}
    consts.update({m.group(1): int(m.group(2)) for m in
                   re.finditer(r"\b(FBG_(?:OK|ERR_\w+))\s*=\s*(-?\d+)", text)})
    return consts


# --------------------------------------------------------------------------------------------
# Golden vectors
# --------------------------------------------------------------------------------------------

@dataclass
class Record:
    """One API call of the golden session and what the integer reference says it returns."""

    op: int
    wl_fm: tuple[int, ...] = (0, 0, 0, 0, 0)
    status: int = 0
    accepted: int = 0
    out: dict[str, int] = field(default_factory=dict)


def _steps(q: Any, wl_fm: np.ndarray, baseline_fm: np.ndarray | None) -> list[Record]:
    """Step records of one stretch run from a fresh (or freshly tared / re-baselined) state."""
    from fbgforce.export import intref

    wl = np.asarray(wl_fm, dtype=np.int64).reshape(-1, 5)
    ref = intref.run(q, wl, baseline_fm)
    return [Record(OP_STEP, tuple(int(v) for v in wl[i]), 0, 0,
                   {k: int(ref[k][i]) for k in OUTPUT_FIELDS}) for i in range(wl.shape[0])]


def _tare_mean(samples: np.ndarray) -> np.ndarray:
    """Baseline fbg_tare_end sets: per channel floor((sum + count/2) / count) (fbgforce.h)."""
    s = samples.astype(np.int64)
    n = s.shape[0]
    return (s.sum(axis=0) + n // 2) // n


def edge_samples(baseline_fm: np.ndarray, jump_max_fm: int, seed: int = 0) -> np.ndarray:
    """Samples the recording never shows: lost peaks (0, -1, int32 sentinels, outside the
    1000-2000 nm window), one-sample jumps beyond the fault threshold, window edges, huge
    in-window shifts that saturate, and random in-window values."""
    c = header_constants()
    lo, hi = c["FBG_WL_MIN_FM"], c["FBG_WL_MAX_FM"]
    rng = np.random.default_rng(seed)
    b = np.asarray(baseline_fm, dtype=np.int64)
    rows: list[np.ndarray] = []
    for k in range(40):  # a quiet lead-in so that the FIR is warm and prev is valid
        rows.append(b + rng.integers(-3000, 3000, 5))
    for bad in (0, -1, INT32_MIN, INT32_MAX, lo - 1, hi + 1):
        for ch in (0, 2, 4):
            r = b.copy()
            r[ch] = bad
            rows.append(r)
            rows.append(b + rng.integers(-3000, 3000, 5))
    # A jump just above and just below the threshold on a strain and on the reference grating.
    for ch in (1, 4):
        for d in (jump_max_fm + 1, jump_max_fm, -(jump_max_fm + 1)):
            r = rows[-1].copy()
            r[ch] += d
            rows.append(r)
    # Window edges and the largest shifts: tare differences and compensation saturate.
    for v in (lo, hi):
        rows.append(np.full(5, v, dtype=np.int64))
        rows.append(np.full(5, v, dtype=np.int64))
    ramp = np.linspace(0, 1, 30)
    for t in ramp:  # a slow ramp to +-nanometres: drives hidden layers and outputs to saturation
        rows.append(np.clip(b + np.array([1, -1, 1, -1, 0]) * int(t * 0.9e9 * 0.05), lo, hi))
    for t in ramp:
        rows.append(np.clip(b + np.array([-1, 1, -1, 1, 1]) * int(t * 0.9e9 * 0.05), lo, hi))
    rows.extend(rng.integers(lo, hi + 1, (20, 5)))
    return np.clip(np.vstack(rows), INT32_MIN, INT32_MAX).astype(np.int64)


def golden_session(q: Any, wl_fm: np.ndarray, contact: np.ndarray | None = None, *,
                   n_untared: int = 16, n_tare: int = 24, seed: int = 0) -> list[Record]:
    """The replayed session: every API call with the integer reference's expected result.

    ``wl_fm`` (n, 5) is a recording in femtometres; its first ``n_tare`` samples without
    contact (or simply the first ones) are the tare window.
    """
    c = header_constants()
    ok, err_arg, err_tare = c["FBG_OK"], c["FBG_ERR_ARG"], c["FBG_ERR_TARE"]
    lo, hi = c["FBG_WL_MIN_FM"], c["FBG_WL_MAX_FM"]
    wl = np.asarray(wl_fm, dtype=np.int64).reshape(-1, 5)
    if wl.shape[0] < n_tare + 8:
        raise InputError(f"need at least {n_tare + 8} samples for the golden session, got {wl.shape[0]}")
    recs: list[Record] = []
    # 1. Untared: the model's nominal baseline.
    recs += _steps(q, wl[:n_untared], None)
    # 2. Tare through the API; two samples are refused (a lost peak, a peak above the window).
    quiet = np.flatnonzero(~np.asarray(contact, dtype=bool)) if contact is not None else np.arange(len(wl))
    tare_rows = wl[quiet[:n_tare]] if quiet.size >= n_tare else wl[:n_tare]
    recs.append(Record(OP_TARE_BEGIN, status=ok))
    for i, row in enumerate(tare_rows):
        recs.append(Record(OP_TARE_ADD, tuple(int(v) for v in row), ok, 1))
        if i == 3:
            bad = row.copy()
            bad[2] = 0
            recs.append(Record(OP_TARE_ADD, tuple(int(v) for v in bad), ok, 0))
        if i == 7:
            bad = row.copy()
            bad[4] = hi + 1
            recs.append(Record(OP_TARE_ADD, tuple(int(v) for v in bad), ok, 0))
    recs.append(Record(OP_TARE_END, status=ok))
    base = _tare_mean(tare_rows)
    # 3. The recording on that tare.
    recs += _steps(q, wl, base)
    # 4. Errors change nothing: a baseline outside the window, a tare_end without begin.
    recs.append(Record(OP_SET_BASELINE, (int(base[0]), int(base[1]), lo - 1, int(base[3]), int(base[4])),
                       err_arg))
    recs.append(Record(OP_TARE_END, status=err_tare))
    # 5. Edge cases on an explicit baseline.
    recs.append(Record(OP_SET_BASELINE, tuple(int(v) for v in base), ok))
    recs += _steps(q, edge_samples(base, q.jump_max_fm, seed), base)
    # 6. fbg_reset keeps the baseline and clears the FIR: the same as a fresh run on it.
    recs.append(Record(OP_RESET, status=ok))
    recs += _steps(q, wl[-32:], base)
    # 7. A fresh fbg_init: untared again.
    recs.append(Record(OP_INIT, status=ok))
    recs += _steps(q, wl[:8], None)
    return recs


def _c_int(v: int) -> str:
    return f"({v + 1} - 1)" if v == INT32_MIN else str(v)


def write_golden_c(records: Sequence[Record], path: Path, options: int = 0) -> None:
    """Write ``golden_vectors.c`` for examples/firmware/fw_golden.h."""
    lines = [
        "/* golden_vectors.c - generated by fbgforce.bench.target from the integer reference;",
        " * do not edit. Layout: examples/firmware/fw_golden.h. */",
        '#include "fw_golden.h"', "",
        f"const uint32_t fw_golden_options = {options}u;",
        f"const uint32_t fw_golden_count = {len(records)}u;",
        f"const fw_record fw_golden[{len(records)}] = {{",
    ]
    for r in records:
        wl = ", ".join(_c_int(v) for v in r.wl_fm)
        o = r.out or {k: 0 for k in OUTPUT_FIELDS}
        out = (f".force_mN = {_c_int(o['force_mN'])}, .x_um = {_c_int(o['x_um'])}, "
               f".y_um = {_c_int(o['y_um'])}, .contact_margin_q8 = {_c_int(o['contact_margin_q8'])}, "
               f".status = {o['status']}u, .contact_conf_q15 = {o['contact_conf_q15']}u, "
               f".contact = {o['contact']}u")
        lines.append(f"    {{.wl_fm = {{{wl}}}, .op = {r.op}, .status = {r.status}, "
                     f".accepted = {r.accepted}, .out = {{{out}}}}},")
    lines.append("};")
    path.write_text("\n".join(lines) + "\n")


def step_macs(q: Any, records: Sequence[Record]) -> list[int]:
    """MACs each step record performs in the C pipeline: the FIR (4 channels x taps) and every
    layer of the nets that run (contact always; force and location only on contact); a sensor
    fault runs neither."""
    fault = header_constants()["FBG_STATUS_SENSOR_FAULT"]
    fir = 4 * int(q.taps.size)
    net = [sum(ly.n_in * ly.n_out for ly in layers) for layers in q.nets]
    macs = []
    for r in records:
        if r.op != OP_STEP:
            continue
        if r.out["status"] & fault:
            macs.append(0)
        else:
            macs.append(fir + net[0] + (net[1] + net[2] if r.out["contact"] else 0))
    return macs


# --------------------------------------------------------------------------------------------
# Build and run
# --------------------------------------------------------------------------------------------

def _run(cmd: Sequence[str], cwd: Path | None = None, timeout: float = 300.0) -> subprocess.CompletedProcess:
    r = subprocess.run(list(cmd), cwd=cwd, capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-25:])
        raise RuntimeError(f"command failed ({r.returncode}): {' '.join(cmd)}\n{tail}")
    return r


def build_libraries() -> dict[str, Any]:
    """Cross-build the three libraries and run the no-float check (runtime_c/target.mk)."""
    r = _run(["make", "-s", "-C", str(RUNTIME_DIR), "-f", "target.mk", "target-libs"])
    warnings = [ln for ln in (r.stdout + r.stderr).splitlines() if "warning" in ln.lower()]
    return {"nofloat_ok": True, "warnings": warnings}


def build_firmware(build: Path, model_c: Path, model_sym: str, golden_c: Path, dsp: bool) -> Path:
    """``make -C examples/firmware`` for one library variant; returns the build directory."""
    out = build / ("dsp" if dsp else "portable")
    _run(["make", "-s", "-C", str(FIRMWARE_DIR), f"BUILD={out}", f"DSP={int(dsp)}",
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
    windows, total, by_lo = [], 0, {}
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
    profile = {name: by_lo.get(lo, 0) for name, (lo, _) in funcs.items()}
    return FirmwareRun(r.returncode, result, mism, windows, total, console,
                       {k: v for k, v in sorted(profile.items(), key=lambda kv: -kv[1]) if v})


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


# --------------------------------------------------------------------------------------------
# The report
# --------------------------------------------------------------------------------------------

def load_quantized(model_dir: Path, calib: Sequence[str] | None = None, bits: int | None = None
                   ) -> tuple[Any, str]:
    """The fixed-point model: ``model.fbgm`` if exported (and ``bits`` is None), else quantised
    in memory with ``bits``-bit weights (default 16; the model directory is not written).
    Returns ``(QModel, where it came from)``."""
    from fbgforce.export import blob

    if bits is None and (model_dir / blob.FILE_NAME).is_file():
        return blob.load_model_blob(model_dir), str(model_dir / blob.FILE_NAME)
    from fbgforce import model as fm
    from fbgforce.export import exporter
    from fbgforce.export import quantize as qz

    model = fm.load(model_dir)
    recs, forces, _ = exporter.calibration_recordings(model, calib)
    q, _ = qz.quantize(model, qz.calibrate(model, recs, forces), bits=bits or 16)
    return q, f"quantised in memory, int{bits or 16} weights"


def recording_fm(data: str | None, scene: str, seed: int, samples: int) -> tuple[np.ndarray, np.ndarray, str]:
    """``samples`` consecutive samples (int32 fm) and their contact flags: from ``data`` or a
    simulated ``scene``; the window starts shortly before the first contact."""
    from fbgforce import dataset as fds
    from fbgforce.export import intref

    if data:
        ds = fds.load(data)
        src = str(data)
    else:
        from fbgforce import sim

        ds = sim.simulate(scene, seed=seed)
        src = f"scene {scene} seed {seed}"
    contact = np.asarray(ds.contact, dtype=bool)
    first = int(np.argmax(contact)) if contact.any() else 0
    start = max(0, min(first - samples // 5, len(ds) - samples))
    sl = slice(start, start + samples)
    return intref.nm_to_fm(ds.wl_nm[sl]), contact[sl], f"{src}, samples {sl.start}..{sl.stop - 1}"


def _figures(run: FirmwareRun, macs: list[int], contact: list[bool]) -> dict[str, Any]:
    w = np.asarray(run.windows, dtype=np.int64)
    if w.size != len(macs):  # the run stopped early (fault, crash): no per-step figures
        return {"instructions_per_step": int(w.max()) if w.size else None,
                "instructions_per_step_mean": None, "instructions_per_step_no_contact_max": None,
                "instructions_per_mac": None, "budget_fraction_at_168MHz": None}
    m = np.asarray(macs, dtype=np.int64)
    c = np.asarray(contact, dtype=bool)
    full = c & (m > 0)
    worst = int(w.max()) if w.size else 0
    ipm = float(w[full].sum() / m[full].sum()) if full.any() else None
    return {
        "instructions_per_step": worst,
        "instructions_per_step_mean": round(float(w.mean()), 1) if w.size else None,
        "instructions_per_step_no_contact_max": int(w[~c & (m > 0)].max()) if (~c & (m > 0)).any() else None,
        "instructions_per_mac": round(ipm, 3) if ipm is not None else None,
        "budget_fraction_at_168MHz": round(worst / (CLOCK_HZ * PERIOD_S), 4),
    }


def target_report(model_dir: str | Path, *, data: str | None = None, scene: str = "smoke",
                  seed: int = 0, samples: int = 600, calib: Sequence[str] | None = None,
                  bits: int | None = None, build_dir: str | Path | None = None, log=None
                  ) -> dict[str, Any]:
    """Build, replay the golden vectors on QEMU (portable and DSP builds), count and measure.

    Returns the report dict (keys in docs/cli.md#target-report). Raises
    :class:`ToolchainMissing` without the tools and :class:`InputError` for a bad model/data.
    """
    from fbgforce.export import codegen

    t0 = time.perf_counter()
    log = log or (lambda msg: None)
    require_tools()
    root = Path(model_dir)
    if not root.exists():
        raise InputError("no such model directory", path=str(root))
    q, source = load_quantized(root, calib, bits)
    wl, contact, data_src = recording_fm(data, scene, seed, samples)
    records = golden_session(q, wl, contact, seed=seed)
    steps = [r for r in records if r.op == OP_STEP]
    macs = step_macs(q, records)
    step_contact = [bool(r.out["contact"]) for r in steps]

    tmp = None
    if build_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="fbg-target-")
        build = Path(tmp.name)
    else:
        build = Path(build_dir).resolve()
        build.mkdir(parents=True, exist_ok=True)
    try:
        ident = "target"
        hdr, src = codegen.fixed_source(q, ident)
        (build / f"{ident}_model.h").write_text(hdr)
        model_c = build / f"{ident}_model.c"
        model_c.write_text(src)
        golden_c = build / "golden_vectors.c"
        write_golden_c(records, golden_c)
        log(f"{len(records)} golden records ({len(steps)} steps) from {data_src}")
        log("cross-compiling libfbgforce (portable, DSP, float)")
        libs = build_libraries()
        builds: dict[str, Any] = {}
        exact = True
        for dsp in (False, True):
            name = "dsp" if dsp else "portable"
            log(f"firmware ({name}): build and run on QEMU mps2-an386")
            bdir = build_firmware(build, model_c, f"{ident}_model", golden_c, dsp)
            run = run_firmware(bdir)
            ok = (run.exit_code == 0 and run.result.get("mismatches") == 0
                  and run.result.get("steps") == len(steps) and len(run.windows) == len(steps))
            exact &= ok
            sizes = map_sizes(bdir / "fw_size.map", exclude=("startup.o", "semihost.o", "main_size.o"))
            entry = {"bit_exact": ok, "exit_code": run.exit_code,
                     "mismatches": run.result.get("mismatches"),
                     **_figures(run, macs, step_contact),
                     **{f"{k}_bytes": v for k, v in sizes.items()},
                     "stack_bytes": run.result.get("stack_bytes"),
                     "state_bytes": run.result.get("state_bytes")}
            # Instructions per replayed step by function (init and tare calls included: they
            # are a few hundred instructions in all), largest first.
            entry["profile_per_step"] = {k: round(v / max(len(steps), 1), 1)
                                         for k, v in list(run.profile.items())[:12]}
            if run.mismatch_lines:
                entry["first_mismatches"] = run.mismatch_lines[:3]
            if not run.result:
                entry["console"] = run.console[-2000:]
            builds[name] = entry
        best = builds["dsp"]
        full = [m for m, cc in zip(macs, step_contact) if cc and m > 0]
        report = {
            "bit_exact": exact,
            "samples": len(steps),
            "records": len(records),
            "instructions_per_step": best["instructions_per_step"],
            "macs_per_step": max(full) if full else max(macs, default=0),
            "instructions_per_mac": best["instructions_per_mac"],
            "text_bytes": best["text_bytes"],
            "rodata_bytes": best["rodata_bytes"],
            "data_bytes": best["data_bytes"],
            "bss_bytes": best["bss_bytes"],
            "flash_bytes": best["text_bytes"] + best["rodata_bytes"] + best["data_bytes"],
            "ram_bytes": best["data_bytes"] + best["bss_bytes"] + (best["state_bytes"] or 0)
                         + (best["stack_bytes"] or 0),
            "state_bytes": best["state_bytes"],
            "stack_bytes": best["stack_bytes"],
            "budget_fraction_at_168MHz": best["budget_fraction_at_168MHz"],
            "assumption": "one instruction per cycle (QEMU counts instructions, not cycles); "
                          "instructions_per_step is the worst step (contact: all three nets)",
            "builds": builds,
            "model": source,
            "weight_bits": int(q.w_bits),
            "data": data_src,
            "nofloat_ok": libs["nofloat_ok"],
            "seconds": round(time.perf_counter() - t0, 2),
        }
        return report
    finally:
        if tmp is not None:
            tmp.cleanup()


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------

def register(subparsers: Any) -> None:
    """Add the ``target-report`` subcommand."""
    from fbgforce.cli import add_json_flag

    p = subparsers.add_parser(
        "target-report", help="Cortex-M4 (QEMU): bit-exact golden vectors, instructions, size",
        description="Cross-compile libfbgforce for Cortex-M4 (portable and DSP-extension "
                    "builds), replay golden vectors from the integer reference on QEMU "
                    "mps2-an386 comparing every output bit, count the instructions of every "
                    "fbg_step exactly (TCG plugin) and measure flash/RAM. Needs: " + APT_LINE)
    p.add_argument("--model", required=True, metavar="DIR",
                   help="model directory (its model.fbgm if exported, else quantised in memory)")
    p.add_argument("--data", metavar="FILE", help="recording for the golden vectors "
                   "(default: the simulated --scene)")
    p.add_argument("--scene", default="smoke", help="scene simulated when --data is not given")
    p.add_argument("--samples", type=int, default=600, help="recording samples replayed (edge "
                   "cases and API calls are added)")
    p.add_argument("--calib", nargs="+", metavar="FILE", help="calibration data when the "
                   "model is not exported yet (default: its training files)")
    p.add_argument("--bits", type=int, choices=(16, 8), default=None,
                   help="quantise in memory with int16 or int8 weights instead of using model.fbgm")
    p.add_argument("--seed", type=int, default=0, help="simulation and edge-case seed")
    p.add_argument("--build-dir", metavar="DIR", help="keep the build here (default: a "
                   "temporary directory, removed afterwards)")
    add_json_flag(p)
    p.set_defaults(handler=_handler)


def _handler(args: argparse.Namespace) -> dict[str, Any]:
    if args.samples < 64:
        raise InputError("must be at least 64", column="--samples")
    try:
        rep = target_report(args.model, data=args.data, scene=args.scene, seed=args.seed,
                            samples=args.samples, calib=args.calib, bits=args.bits,
                            build_dir=args.build_dir,
                            log=lambda m: print(f"target-report: {m}", file=sys.stderr, flush=True))
    except ToolchainMissing as exc:
        raise InputError(str(exc)) from exc
    if not args.json:
        _print_summary(rep)
    return rep


def _print_summary(rep: dict[str, Any]) -> None:
    print(f"bit-exact on Cortex-M4 (portable and DSP): {rep['bit_exact']} over {rep['samples']} steps")
    for name, b in rep["builds"].items():
        frac = b["budget_fraction_at_168MHz"]
        share = f"{100 * frac:.1f} %" if frac is not None else "?"
        print(f"  {name:8s}: {b['instructions_per_step']} instructions worst step, "
              f"{b['instructions_per_mac']} per MAC, {share} of 1 ms at 168 MHz "
              f"(1 instruction/cycle assumed)" + ("" if b["bit_exact"] else
                                                  f"  MISMATCH: {b.get('first_mismatches')}"))
    print(f"  MACs per step {rep['macs_per_step']}; flash {rep['flash_bytes']} B "
          f"(text {rep['text_bytes']}, rodata {rep['rodata_bytes']}, data {rep['data_bytes']}); "
          f"RAM {rep['ram_bytes']} B (bss {rep['bss_bytes']}, state {rep['state_bytes']}, "
          f"stack {rep['stack_bytes']})")


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m fbgforce.bench.target`` (what ``make -C runtime_c target-test`` runs): the
    report for ``--model`` (default: a small model trained here on the ``smoke`` scene); exit
    status 1 unless bit-exact."""
    ap = argparse.ArgumentParser(prog="python -m fbgforce.bench.target")
    ap.add_argument("--model", help="model directory (default: train a small one)")
    ap.add_argument("--samples", type=int, default=600)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="fbg-target-model-") as tmp:
        model_dir = Path(args.model) if args.model else _train_small(Path(tmp))
        try:
            rep = target_report(model_dir, samples=args.samples,
                                log=lambda m: print(f"target-test: {m}", file=sys.stderr, flush=True))
        except (ToolchainMissing, InputError) as exc:
            print(f"target-test: {exc}", file=sys.stderr)
            return 2
    if args.json:
        print(json.dumps(rep))
    else:
        _print_summary(rep)
    return 0 if rep["bit_exact"] else 1


def _train_small(tmp: Path) -> Path:
    """A small model on the simulated ``smoke`` scene (what the test fixtures use)."""
    from fbgforce import dataset as fds
    from fbgforce import model as fm
    from fbgforce import sim
    from fbgforce.trainer.train import train

    data = tmp / "smoke.csv"
    fds.save(sim.simulate("smoke", seed=0), data)
    out = tmp / "model"
    print("target-test: training a small model on the smoke scene", file=sys.stderr, flush=True)
    fm.save(train([data], epochs=40, seed=0, filter="causal", progress=False), out)
    return out


if __name__ == "__main__":
    sys.exit(main())
