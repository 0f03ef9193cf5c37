"""Cortex-M4 cycles of the worst ``fbg_step``, estimated from its executed instruction mix.

QEMU counts instructions, not cycles. The instruction-window plugin keeps the worst window
instruction by instruction (how often each instruction ran, how often control left it for
anything but the next instruction in memory, how often it was entered by falling through from
the instruction before it), and this module prices every instruction with the timings of the
Cortex-M4 technical reference manual (ARM DDI 0439, "Processor instruction timings"):

- data processing, shifts, saturation (USAT/SSAT), packing (PKHBT), extension (SXTB16, UXTH),
  bit-field, MRS/MSR, IT, compares: 1 cycle;
- every multiply of the M4's single-cycle MAC unit (MUL, SMULL/UMULL, SMLAL, SMLAD, SMLALD,
  SMMULR, SMULxy, ...): 1; MLA, MLS, SMMLA(R), SMMLS(R): 2; SDIV/UDIV: 12 (the TRM gives 2-12,
  data-dependent: this is the upper bound, and no division runs in the DSP build's step);
- single loads (LDR, LDRH, LDRSH, LDRB, ...): 2, but 1 when entered straight from the
  previous instruction in memory and that one is a single load or store (the TRM's
  pipelining of neighbouring loads and stores; a dependency of the address on the load before
  would add a cycle back, which is not modelled);
- single stores: 1 (the store retires through the write buffer);
- LDRD/STRD: 3; LDM/STM/PUSH/POP of N registers: 1 + N;
- every transfer of control (a taken branch, BX, BL, a load or POP into the PC, falling
  anywhere but to the next instruction): + P cycles of pipeline refill, P = 1 to 3 by the TRM
  (alignment and width of the target, early speculation); the estimate uses P = 2 and also
  gives P = 1 and P = 3. A conditional branch that falls through costs 1. Only branches and
  writes to the PC are priced a refill (QEMU reports a discontinuity after an instruction that
  precedes one crossing a page boundary; that is translation, not the core).

Not modelled (so the figure is for zero-wait-state memory: SRAM, or flash behind a cache that
hits): flash wait states, bus contention between instruction fetch and data, and interrupts.
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path
from typing import Any, Iterable

#: Condition-code suffixes of conditional (IT-block or branch) instructions.
_CONDS = ("eq", "ne", "cs", "hs", "cc", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt",
          "gt", "le", "al")
_LOADS = {"ldr", "ldrb", "ldrh", "ldrsb", "ldrsh", "ldrex", "ldrexb", "ldrexh", "ldrt", "ldrbt",
          "ldrht", "ldrsbt", "ldrsht"}
_STORES = {"str", "strb", "strh", "strex", "strexb", "strexh", "strt", "strbt", "strht"}
_DOUBLE = {"ldrd", "strd"}
_MULTIPLE = {"ldm", "ldmia", "ldmfd", "ldmdb", "ldmea", "stm", "stmia", "stmea", "stmdb", "stmfd",
             "push", "pop"}
_MUL2 = {"mla", "mls", "smmla", "smmlar", "smmls", "smmlsr"}
_DIV = {"sdiv", "udiv"}
_BRANCHES = {"b", "bl", "bx", "blx", "cbz", "cbnz", "tbb", "tbh"}
_MULS = {"mul", "smull", "umull", "smlal", "umlal", "umaal", "smlad", "smladx", "smlald",
         "smlaldx", "smlsd", "smlsld", "smuad", "smusd", "smmul", "smmulr", "smulbb", "smulbt",
         "smultb", "smultt", "smulwb", "smulwt", "smlabb", "smlabt", "smlatb", "smlatt",
         "smlawb", "smlawt", "smlalbb", "smlalbt", "smlaltb", "smlaltt"}
_KNOWN = _LOADS | _STORES | _DOUBLE | _MULTIPLE | _MUL2 | _DIV | _BRANCHES | _MULS

_LINE = re.compile(r"^\s*([0-9a-f]+):\s+(?:[0-9a-f]{4}\s?){1,2}\s*\t(\S+)\s*(.*)$")


def base_mnemonic(mnemonic: str) -> tuple[str, bool]:
    """``(mnemonic without width, condition and flag-setting suffixes, conditional?)``."""
    m = mnemonic.lower().split(".")[0]
    if m in _KNOWN:
        return m, False
    for cond in _CONDS:
        if m.endswith(cond) and m[:-2] in _KNOWN:
            return m[:-2], cond != "al"
    if m.endswith("s") and m[:-1] in _KNOWN:
        return m[:-1], False
    return m, False  # everything else costs one cycle, conditional or not


def disassemble(elf: Path) -> dict[int, tuple[str, str]]:
    """``{address: (mnemonic, operands)}`` of every instruction in ``elf`` (objdump -d)."""
    out = subprocess.run(["arm-none-eabi-objdump", "-d", str(elf)], capture_output=True, text=True,
                         check=True).stdout
    dis = {}
    for line in out.splitlines():
        m = _LINE.match(line)
        if m and not m.group(2).startswith("."):
            dis[int(m.group(1), 16)] = (m.group(2), m.group(3).split(";")[0].split("@")[0].strip())
    return dis


def _n_regs(operands: str) -> int:
    inside = operands[operands.find("{") + 1:operands.find("}")]
    n = 0
    for part in inside.split(","):
        part = part.strip()
        if "-" in part:
            a, b = (int(re.sub(r"\D", "", p) or 0) for p in part.split("-"))
            n += b - a + 1
        elif part:
            n += 1
    return max(n, 1)


def _writes_pc(base: str, operands: str) -> bool:
    ops = operands.replace(" ", "")
    if base in _MULTIPLE:
        return "pc" in ops[ops.find("{"):]
    return ops.startswith("pc,")


def instruction_class(mnemonic: str, operands: str) -> tuple[str, int, bool]:
    """``(class, base cycles, always transfers control?)`` of one instruction."""
    base, conditional = base_mnemonic(mnemonic)
    transfers = _writes_pc(base, operands)
    if base in _BRANCHES:
        uncond = base in ("bl", "blx", "bx", "tbb", "tbh") or (base == "b" and not conditional)
        return "branch", 2 if base in ("tbb", "tbh") else 1, uncond
    if base in _LOADS:
        return "load", 2, transfers
    if base in _STORES:
        return "store", 1, False
    if base in _DOUBLE:
        return "load_store_double", 3, False
    if base in _MULTIPLE:
        return "load_store_multiple", 1 + _n_regs(operands), transfers
    if base in _MUL2:
        return "multiply_accumulate_2cycle", 2, False
    if base in _DIV:
        return "divide", 12, False
    if base in _MULS:
        return "multiply", 1, False
    return "alu", 1, transfers


def estimate(pcs: Iterable[tuple[int, int, int, int]], dis: dict[int, tuple[str, str]],
             refill: int = 2) -> dict[str, Any]:
    """Cycles of one window from ``(address, executed, taken, sequential_in)`` records.

    Returns ``{"cycles", "instructions", "by_class": {class: [instructions, cycles]},
    "taken_transfers", "pipelined_loads"}``.
    """
    recs = sorted(pcs)
    addrs = sorted(dis)
    prev_of = {a: b for b, a in zip(addrs, addrs[1:])}
    by_class: dict[str, list[int]] = {}
    cycles = instructions = transfers = pipelined = 0
    for pc, executed, taken, seq_in in recs:
        if pc not in dis:
            raise ValueError(f"no instruction at 0x{pc:x} in the disassembly")
        mnem, ops = dis[pc]
        cls, cost, always = instruction_class(mnem, ops)
        # Only a branch or a write to the PC can transfer control; QEMU may still report a
        # discontinuity after another instruction (at an instruction that crosses a page
        # boundary, translated on its own), which is not a pipeline refill.
        taken_n = executed if always else (taken if cls == "branch" or _writes_pc(
            base_mnemonic(mnem)[0], ops) else 0)
        c = cost * executed + refill * taken_n
        if cls == "load" and seq_in and pc in prev_of:
            pcls = instruction_class(*dis[prev_of[pc]])[0]
            if pcls in ("load", "store"):
                c -= seq_in
                pipelined += seq_in
        transfers += taken_n
        instructions += executed
        cycles += c
        acc = by_class.setdefault(cls, [0, 0])
        acc[0] += executed
        acc[1] += c
    return {"cycles": cycles, "instructions": instructions, "by_class": by_class,
            "taken_transfers": transfers, "pipelined_loads": pipelined}
