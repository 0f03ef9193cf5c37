"""The Cortex-M4 cycle model of fbgforce.target.cycles on hand-made instruction mixes (no
tools needed): the timings it applies, branch refills, load pipelining."""
from __future__ import annotations

import pytest

from fbgforce.target import cycles


@pytest.mark.parametrize("mnemonic, operands, cls, cost", [
    ("smlad", "r9, r7, r3, r9", "multiply", 1),
    ("smmulr", "r9, r9, r7", "multiply", 1),
    ("mla", "r4, r5, r11, r4", "multiply_accumulate_2cycle", 2),
    ("ldr.w", "r4, [ip, #4]!", "load", 2),
    ("ldrsheq.w", "r3, [r7]", "load", 2),
    ("strh.w", "r3, [r6], #2", "store", 1),
    ("ldrd", "r7, r10, [r4], #8", "load_store_double", 3),
    ("ldmia.w", "lr!, {r3, r4, r5, r6}", "load_store_multiple", 5),
    ("ldm.w", "sp, {r3, r4, r5, r6, r8, lr}", "load_store_multiple", 7),
    ("stmdb", "sp!, {r4, r5, r6, r7, r8, r9, sl, fp, lr}", "load_store_multiple", 10),
    ("push", "{r4-r11, lr}", "load_store_multiple", 10),
    ("usat", "r9, #15, r9", "alu", 1),
    ("bic.w", "r9, r9, r9, asr #31", "alu", 1),
    ("bne.n", "8e6 <fbg_step+0xb2>", "branch", 1),
    ("udiv", "r0, r1, r2", "divide", 12),
])
def test_instruction_classes(mnemonic, operands, cls, cost):
    assert cycles.instruction_class(mnemonic, operands)[:2] == (cls, cost)


def test_unconditional_transfers_always_refill():
    assert cycles.instruction_class("bl", "3150 <f>")[2]
    assert cycles.instruction_class("bx", "lr")[2]
    assert cycles.instruction_class("ldr.w", "pc, [sp, #24]")[2]
    assert cycles.instruction_class("pop", "{r4, r5, pc}")[2]
    assert not cycles.instruction_class("bne.n", "10 <x>")[2]
    assert not cycles.instruction_class("pop", "{r4, r5}")[2]


def test_estimate_prices_refills_and_pipelined_loads():
    dis = {0: ("ldr", "r1, [r0]"), 2: ("ldr", "r2, [r0, #4]"), 4: ("smlad", "r3, r1, r2, r3"),
           8: ("subs", "r4, #1"), 10: ("bne.n", "0 <x>"), 12: ("bx", "lr")}
    # A 10-iteration loop: the branch is taken 9 times; the second load follows the first
    # every time (pipelined), the first is entered by the branch 9 times and from before once.
    pcs = [(0, 10, 0, 1), (2, 10, 0, 10), (4, 10, 0, 10), (8, 10, 0, 10), (10, 10, 9, 10),
           (12, 1, 0, 1)]
    est = cycles.estimate(pcs, dis, refill=2)
    assert est["instructions"] == 51
    # loads 2 x 10 + 2 x 10 - 10 pipelined, smlad 10, subs 10, bne 10 + 2 x 9, bx 1 + 2
    assert est["cycles"] == 20 + 10 + 10 + 10 + 28 + 3
    assert est["pipelined_loads"] == 10 and est["taken_transfers"] == 10
    assert cycles.estimate(pcs, dis, refill=3)["cycles"] == est["cycles"] + 10


def test_estimate_refuses_an_address_outside_the_disassembly():
    with pytest.raises(ValueError, match="0x64"):
        cycles.estimate([(100, 1, 0, 0)], {0: ("nop", "")})


def test_a_discontinuity_after_a_non_branch_is_not_a_refill():
    dis = {0: ("smlad", "r9, r7, r3, r9"), 4: ("ldmia.w", "r1!, {r7, r8}")}
    est = cycles.estimate([(0, 5, 5, 5), (4, 5, 0, 0)], dis, refill=2)
    assert est["cycles"] == 5 * 1 + 5 * 3 and est["taken_transfers"] == 0
