"""Host SIMD dense-layer kernels (SSE2, AVX2, NEON), on the weights as the model holds them
and packed by ``fbg_pack``: every output record equals the portable C's and the integer
reference's, on golden sessions and on random streams through random models (odd widths,
int8 weights, weights at +-32767 / -32768 within the int32 proof, multipliers at +-2^(shift-1),
saturating activations, int64-accumulator layers between int32 ones); ``fbg_pack`` /
``fbg_use_pack`` refuse bad buffers and states.

x86-64 kernels run in this process (``Runtime(kernel=...)``) and in a natively built replay
of golden vectors (tests/simd_replay.c); NEON runs the same replay cross-compiled with
``aarch64-linux-gnu-gcc`` under ``qemu-aarch64`` (skipped without them, a failure with CI=true).
"""
from __future__ import annotations

import os
import platform
import re
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import make_random_model, make_random_walk, require_tools
from fbgforce import contract
from fbgforce.model import artifact, floatref
from fbgforce.export import blob, codegen, intref
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import QLayer, QModel
from fbgforce.pybind import KERNEL_NAME, KERNELS, PACKED_KERNELS, ArgError, Runtime, ffi, lib
from fbgforce.target import golden
from fbgforce.target.report import load_quantized, recording_fm

ROOT = Path(__file__).resolve().parent.parent
RUNTIME = ROOT / "runtime_c"
FIELDS = contract.OUTPUT_FIELDS
INT32_MAX = 2**31 - 1
X86 = platform.machine() in ("x86_64", "AMD64")


def _cpu_has_avx2() -> bool:
    try:
        return " avx2" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def host_kernels() -> list[str]:
    """The SIMD kernels this CPU must run: SSE2 on every x86-64, AVX2 where the CPU has it."""
    if X86:
        return ["sse2"] + (["avx2"] if _cpu_has_avx2() else [])
    if platform.machine() in ("aarch64", "arm64"):
        return ["neon"]
    return []


def _require(*tools: str) -> None:
    require_tools(*tools, install="gcc qemu-user gcc-aarch64-linux-gnu libc6-dev-arm64-cross")


def _balance_contact(model: artifact.HierarchicalModel, wl: np.ndarray) -> None:
    """Shift the contact logit so that about half of ``wl`` is contact (every net runs)."""
    x = floatref.features(model, wl, model.baseline_nm)
    logits = model.contact.forward(x[:, :model.preprocess.n_features])
    model.contact.biases[-1][1] -= float(np.median(logits[:, 1] - logits[:, 0]))


def _extreme_layer(rng: np.random.Generator, layer: QLayer, relu_inputs: bool) -> QLayer:
    """A layer of the same shape whose rows sit at the edge of the int32 proof: int16 rows
    holding -32768 and 32767 (twice over after a ReLU, where the proof bounds the positive and
    the negative weights apart), random rows spending most of the budget, the extremes in
    random columns (the last and odd ones included); int8 rows of -128 / 127."""
    n_out, n_in = layer.w.shape
    lo, hi = (-32768, 32767) if layer.w_bits == 16 else (-128, 127)
    w = np.zeros((n_out, n_in), dtype=np.int64)
    for r in range(n_out):
        kind = rng.integers(3)
        if layer.w_bits == 8:
            w[r] = rng.choice([lo, hi, 0, 1, -1], n_in)
        elif kind == 0 or n_in < 2:
            # sum|w| = 65535 (any inputs) or max(sum w>0, sum|w<0|) = 65536 (ReLU inputs).
            cols = rng.permutation(n_in)
            w[r, cols[0]] = lo
            if n_in >= 2:
                w[r, cols[1]] = hi
            if relu_inputs and n_in >= 4:
                w[r, cols[2]], w[r, cols[3]] = lo, hi - 1
        else:
            # Random weights spending up to 65000 of sum|w|, 32767 in the last column (kind 2).
            v = rng.normal(0.0, 1.0, n_in)
            budget = rng.uniform(0.3, 0.98) * 65000
            if kind == 2:
                v[-1] = 0.0
                budget -= hi
            w[r] = np.clip(np.trunc(v / np.abs(v).sum() * budget), lo, hi)
            if kind == 2:
                w[r, -1] = hi
    probe = QLayer(w=w, w_bits=layer.w_bits, bias=np.zeros(n_out, dtype=np.int64),
                      mult=np.ones(n_out, dtype=np.int64), shift=30, acc32=True)
    room = INT32_MAX - probe.acc32_bound(relu_inputs)
    assert (room >= 0).all()
    bias = np.array([rng.integers(-min(r, 10**7), min(r, 10**7) + 1) for r in room], dtype=np.int64)
    mult = rng.integers(1 << 17, 1 << 21, n_out) * rng.choice([1, 1, 1, -1], n_out)
    # The same scales at shift 30 or 40: the packed AVX2 kernel requantises in int32 lanes
    # (shift <= 32, |mult| <= 2^(shift-1)) or in int64 ones.
    shift = int(rng.choice([30, 40]))
    mult = mult << (shift - 30)
    return QLayer(w=w, w_bits=layer.w_bits, bias=bias, mult=mult, shift=shift, acc32=True)


def _edge_multipliers(layer: QLayer, sign: int) -> QLayer:
    """``layer`` at shift 31 (the same scales) with row 0's multiplier at ``sign`` * 2^30, the
    edge of the packed AVX2 kernel's requantisation at shift 32: -2^30 * 2^(32-31) = -2^31 is
    an int32 (that layer requantises from the high dword), +2^31 is not (that layer takes the
    64-bit clamp)."""
    mult = np.array([int(m) << (31 - layer.shift) if layer.shift <= 31 else int(m) >> (layer.shift - 31)
                     for m in layer.mult], dtype=np.int64)
    mult[0] = sign << 30
    return QLayer(w=layer.w, w_bits=layer.w_bits, bias=layer.bias, mult=mult, shift=31, acc32=True)


def _extreme_model(seed: int, sizes, bits: int, memory: artifact.Memory,
                   edge: bool = False) -> tuple[QModel, np.ndarray]:
    """A quantised random model whose hidden layers are replaced by :func:`_extreme_layer`
    ones (``edge``: then given :func:`_edge_multipliers`, +2^30 and -2^30 in turn), and a
    stream for it: a random walk with strain excursions large enough to saturate the net
    inputs, and the golden session's edge samples."""
    rng = np.random.default_rng(seed)
    model = make_random_model(seed, sizes=sizes, memory=memory)
    wl = make_random_walk(model, 1200, seed=seed, step_nm=0.02)
    cal = qz.calibrate(model, [(wl, model.baseline_nm)])
    q, _ = qz.quantize(model, cal, bits=bits)
    for net in q.nets:
        for i in range(len(net) - 1):
            net[i] = _extreme_layer(rng, net[i], i > 0)
            if edge:
                net[i] = _edge_multipliers(net[i], 1 if i % 2 == 0 else -1)
    wl_fm = np.vstack([intref.nm_to_fm(wl), golden.edge_samples(q.baseline_fm, q.jump_max_fm, seed)])
    # Contact on about half of the stream, so that the force and location nets run: move the
    # contact row's bias by the median margin (in accumulator units), keeping the int32 proof.
    last = q.nets[0][-1]
    for _ in range(4):
        margin = np.median(intref.run(q, wl_fm, None)["contact_margin_q8"])
        last.bias = last.bias - int(round(margin * 2.0**last.shift / last.mult[0]))
        last.acc32 = bool((last.acc32_bound(True) <= INT32_MAX).all())
    return q, np.vstack([wl_fm, wl_fm[:200]])


def _edge_model(seed: int, sizes, bits: int, memory: artifact.Memory) -> tuple[QModel, np.ndarray]:
    return _extreme_model(seed, sizes, bits, memory, edge=True)


def _realistic_model(seed: int, sizes, bits: int, memory: artifact.Memory) -> tuple[QModel, np.ndarray]:
    """A quantised random model as the exporter makes it (acc32 where proven) and its stream."""
    model = make_random_model(seed, sizes=sizes, memory=memory)
    wl = make_random_walk(model, 1500, seed=seed)
    _balance_contact(model, wl)
    cal = qz.calibrate(model, [(wl, model.baseline_nm)])
    q, _ = qz.quantize(model, cal, bits=bits)
    return q, intref.nm_to_fm(wl)


def _dead_units_model(seed: int, sizes, bits: int, memory: artifact.Memory) -> tuple[QModel, np.ndarray]:
    """:func:`_realistic_model` with the units weight decay leaves in the force and location
    nets: a third of each hidden layer's outputs unread (the next layer's column all zero),
    half of those with all-zero weights too (a bias alone), the force net's first layer wholly
    so (every row unused: its next layer has no input left), and in the location net's first
    layer an unread bias-only unit that clamps on every step the net runs (the packed form must
    keep it for the saturation flag). The contact net stays as it is (contact on about half
    of the stream)."""
    q, wl_fm = _realistic_model(seed, sizes, bits, memory)
    rng = np.random.default_rng(seed)
    for n in (1, 2):
        net = q.nets[n]
        for i in range(len(net) - 1):
            layer, nxt = net[i], net[i + 1]
            n_out = layer.w.shape[0]
            unread = np.arange(n_out) if (n, i) == (1, 0) else rng.choice(n_out, max(1, n_out // 3), replace=False)
            nxt.w[:, unread] = 0
            layer.w[unread if (n, i) == (1, 0) else unread[::2]] = 0
    loc0, loc1 = q.nets[2][0], q.nets[2][1]
    r = int(np.flatnonzero((loc1.w == 0).all(axis=0))[0])
    loc0.w[r] = 0
    loc0.mult[r] = 1 << (loc0.shift - 2)
    loc0.bias[r] = 1 << 20  # requantises to 2^18: clamps
    return q, wl_fm


def _mixed_acc_model(seed: int, sizes, bits: int, memory: artifact.Memory) -> tuple[QModel, np.ndarray]:
    """:func:`_realistic_model` with every other layer (hidden and output ones, alternating
    between the nets) on int64 accumulators, which run the portable C between SIMD layers
    and are left out of the packed form."""
    q, wl_fm = _realistic_model(seed, sizes, bits, memory)
    for n, net in enumerate(q.nets):
        for i, layer in enumerate(net):
            if (i + n) % 2 == 0:
                layer.acc32 = False
    return q, wl_fm


PAPER = ((70, 50, 20), (70, 50, 20), (70, 50, 40))
ODD = ((13, 7, 3), (1, 9, 17), (33, 5, 2))
WIDE = ((128, 3, 127), (31, 128, 1), (9, 16, 24))
MEM8 = artifact.Memory(ema_shifts=(3, 6), ema_gains=(2, 1), play_widths=(0.2, 0.5), play_gains=(1, 2))
MEM5 = artifact.Memory(ema_shifts=(4,), ema_gains=(1,))
# With the location averages, which the AVX2 front end updates in vectors.
MEMLOC = artifact.Memory(ema_shifts=(3,), ema_gains=(2,), play_widths=(0.2,), play_gains=(1,), loc_shift=3)
CASES = {
    "paper-int16": (_realistic_model, 1, PAPER, 16, MEM8),
    "odd-int16": (_realistic_model, 2, ODD, 16, MEM5),
    "paper-int8": (_realistic_model, 3, PAPER, 8, MEM8),
    "extreme-paper-int16": (_extreme_model, 4, PAPER, 16, MEM8),
    "extreme-odd-int16": (_extreme_model, 5, ODD, 16, MEM5),
    "extreme-wide-int16": (_extreme_model, 6, WIDE, 16, artifact.Memory()),
    "extreme-odd-int8": (_extreme_model, 7, ODD, 8, MEM5),
    "extreme-edge-mult-odd-int16": (_edge_model, 10, ODD, 16, MEM5),
    "extreme-edge-mult-paper-int16": (_edge_model, 11, PAPER, 16, MEM8),
    "mixed-acc-odd-int16": (_mixed_acc_model, 2, ODD, 16, MEM5),
    "dead-units-paper-int16": (_dead_units_model, 12, PAPER, 16, MEM8),
    "dead-units-odd-int8": (_dead_units_model, 13, ODD, 8, MEM5),
    "loc-paper-int16": (_realistic_model, 14, PAPER, 16, MEMLOC),
    "extreme-loc-paper-int16": (_extreme_model, 15, PAPER, 16, MEMLOC),
}


@pytest.fixture(scope="module", params=sorted(CASES))
def case(request):
    make, seed, sizes, bits, memory = CASES[request.param]
    q, wl_fm = make(seed, sizes, bits, memory)
    return request.param, q, wl_fm


def test_every_host_kernel_matches_portable_and_the_reference(case):
    name, q, wl_fm = case
    data = blob.to_bytes(q)
    ref = intref.run(q, wl_fm, None)
    # The stream exercises what it should: both contact outcomes, clamping and clean samples.
    assert ref["contact"].any() and not ref["contact"].all(), name
    if name.startswith("extreme"):
        sat = (ref["status"] & contract.STATUS_FLAG["SATURATED"]) != 0
        assert sat.any() and not sat.all(), name
    portable = Runtime(data, kernel="portable").run_raw(wl_fm)
    for k in FIELDS:
        assert np.array_equal(np.asarray(portable[k], dtype=np.int64), ref[k]), (name, k)
    kernels = host_kernels()
    if not kernels:
        pytest.skip(f"no host SIMD kernel on {platform.machine()}")
    for kernel in kernels:
        for packed in (False, True):
            rt = Runtime(data, kernel=kernel, packed=packed)
            assert rt.kernel == kernel and rt.packed == (packed and kernel in PACKED_KERNELS)
            got = rt.run_raw(wl_fm)
            assert got.tobytes() == portable.tobytes(), (name, kernel, packed)


def test_location_average_clamp_alone_raises_saturated_on_every_kernel():
    """The location averages' r = z - z0 clamps while nothing else does: z0 at +-20000 (not
    saturated), z swinging from z0 to -0.8 z0 (never clamped), hidden layers that output 0
    (multipliers 0), a memory of the location averages only. SATURATED then comes from that
    clamp alone, on some steps and not on others, and every kernel, packed or not, equals the
    integer reference (the AVX2 front end updates the averages in vectors)."""
    import dataclasses

    model = make_random_model(21, sizes=PAPER, memory=artifact.Memory(loc_shift=3))
    wl = make_random_walk(model, 600, seed=21)
    q, _ = qz.quantize(model, qz.calibrate(model, [(wl, model.baseline_nm)]))
    for net in q.nets:
        for layer in net[:-1]:
            layer.mult = np.zeros_like(layer.mult)
    ratio = q.z_mult / 2.0**q.z_shift  # z per fm of filtered shift
    z0 = 20000 * np.array([1, -1, 1, -1])
    base = intref.nm_to_fm(np.array([1530.0, 1535.0, 1540.0, 1545.0, 1550.0]))
    q = dataclasses.replace(q, mean_fm=np.round(-z0 / ratio).astype(np.int64), baseline_fm=base,
                            jump_max_fm=2**31 - 1, stuck_max=0)
    assert not q.z_rest()[1]
    n = 1200
    swing = np.sin(np.linspace(0.0, 3.0 * np.pi, n))[:, None] ** 2 * (-1.8 * z0 / ratio)[None, :]
    wl_fm = np.column_stack([base[:4] + np.round(swing).astype(np.int64), np.full(n, base[4])])
    ref = intref.run(q, wl_fm, base)
    sat = (ref["status"][q.taps.size:] & contract.STATUS_FLAG["SATURATED"]) != 0
    assert sat.any() and not sat.all()
    data = blob.to_bytes(q)
    for kernel in ["portable"] + host_kernels():
        for packed in (False, True):
            rt = Runtime(data, kernel=kernel, packed=packed)
            rt.set_baseline(base.astype(np.int32))
            got = rt.run_raw(wl_fm)
            for k in FIELDS:
                assert np.array_equal(np.asarray(got[k], dtype=np.int64), ref[k]), (kernel, packed, k)


def test_front_end_clamps_on_every_kernel():
    """The AVX2 front end (filter, standardisation, load proxy in int64 lanes) where every
    clamp of it fires: taps of 32767 in Q15 (a gain of 16) on swings of +-0.45e9 fm held for
    20 samples drive the filtered shift past int32 both ways (a mean of 2^30 lets the
    difference show whether it was clamped), means at +-(2^31 - 1) drive the difference past it,
    and large multipliers the standardised value past int16; the load proxy flags overload
    on part of the stream. Every kernel gives the portable C's and the reference's records."""
    q, _ = _realistic_model(14, ODD, 16, MEM5)
    rng = np.random.default_rng(14)
    q.taps = np.full(16, 32767, dtype=np.int64)
    q.tap_q = 15
    q.jump_max_fm = 2**31 - 1
    q.mean_fm = np.array([2**31 - 1, -(2**31 - 1), 2**30, 123456], dtype=np.int64)
    q.z_mult = np.array([1 << 13, -(1 << 13), 1 << 13, 3 << 22], dtype=np.int64)
    q.z_shift = 30
    q.load_coeff = rng.integers(-(1 << 27), 1 << 27, 4)
    q.load_shift, q.load_max_mN = 24, 1 << 20
    base = np.asarray(q.baseline_fm, dtype=np.int64)
    swing = np.repeat(rng.integers(-450_000_000, 450_000_000, (75, 5)), 20, axis=0)  # held 20 steps
    walk = np.cumsum(rng.integers(-3_000_000, 3_000_001, (1500, 5)), axis=0)
    wl_fm = np.clip(base + np.where(np.arange(1500)[:, None] % 300 < 150, swing, walk),
                    1_000_000_000, 2_000_000_000)
    ref = intref.run(q, wl_fm, None)
    sat = (ref["status"] & contract.STATUS_FLAG["SATURATED"]) != 0
    over = (ref["status"] & contract.STATUS_FLAG["OVERLOAD"]) != 0
    assert sat.any() and over.any() and not over.all()
    data = blob.to_bytes(q)
    portable = Runtime(data, kernel="portable").run_raw(wl_fm)
    for k in FIELDS:
        assert np.array_equal(np.asarray(portable[k], dtype=np.int64), ref[k]), k
    for kernel in host_kernels():
        for packed in (False, True):
            got = Runtime(data, kernel=kernel, packed=packed).run_raw(wl_fm)
            assert got.tobytes() == portable.tobytes(), (kernel, packed)


def test_compensation_clamp_alone_raises_saturated_on_every_kernel():
    """The temperature compensation sat32(shift - rshift_round(shift_T * coeff, 24)) clamps
    while nothing after it does: coefficients of +-6 and +-5 (Q24) against a reference swing
    of +-0.4e9 fm, one small tap (gain 1/16), z = filt / 2^14, no memory features and hidden
    layers that output 0. SATURATED then comes from the compensation alone, on some steps
    and not on others, and every kernel, packed or not, equals the integer reference (the AVX2
    front end compensates in int64 lanes)."""
    q, _ = _realistic_model(16, ODD, 16, artifact.Memory())
    for net in q.nets:
        for layer in net[:-1]:
            layer.mult = np.zeros_like(layer.mult)
    q.taps = np.array([1 << 11], dtype=np.int64)
    q.tap_q = 15
    q.mean_fm = np.zeros(4, dtype=np.int64)
    q.z_mult = np.ones(4, dtype=np.int64)
    q.z_shift = 14
    q.temp_coeff_q24 = np.array([6 << 24, -(6 << 24), 5 << 24, -(5 << 24)], dtype=np.int64)
    q.jump_max_fm = 2**31 - 1
    base = np.asarray(q.baseline_fm, dtype=np.int64)
    n = 1200
    swing = np.round(4e8 * np.sin(np.linspace(0.0, 6.0 * np.pi, n))).astype(np.int64)
    walk = np.cumsum(np.random.default_rng(16).integers(-200_000, 200_001, (n, 4)), axis=0)
    wl_fm = np.column_stack([base[:4] + walk, base[4] + swing])
    ref = intref.run(q, wl_fm, None)
    sat = (ref["status"] & contract.STATUS_FLAG["SATURATED"]) != 0
    assert sat.any() and not sat.all()
    data = blob.to_bytes(q)
    for kernel in ["portable"] + host_kernels():
        for packed in (False, True):
            got = Runtime(data, kernel=kernel, packed=packed).run_raw(wl_fm)
            for k in FIELDS:
                assert np.array_equal(np.asarray(got[k], dtype=np.int64), ref[k]), (kernel, packed, k)


STATE_FIELDS = ("prev_fm", "same_run", "prev_valid", "hist", "last_comp", "pos", "since_reset",
                *contract.MEMORY_STATES, "mem_primed")


def test_load_signal_clamp_alone_raises_saturated_and_states_match_on_every_kernel():
    """The load signal u = sat16(rshift_round(sum z_c * mem_mult_c, mem_shift)) clamps while
    nothing else does: a mem_shift 3 below the exporter's (8 times the gain), one play operator of gain 0 (its
    feature |u - state| <= its width), no location averages, hidden layers that output 0.
    SATURATED then comes from u alone, on some steps and not on others; every kernel, packed
    or not, equals the integer reference, and its state after the stream equals the portable
    C's field by field (the AVX2 front end stores only the n_ema / n_play states it has)."""
    q, wl_fm = _realistic_model(17, ODD, 16, artifact.Memory(play_widths=(0.2,), play_gains=(0,)))
    for net in q.nets:
        for layer in net[:-1]:
            layer.mult = np.zeros_like(layer.mult)
    q.mem_shift -= 3
    ref = intref.run(q, wl_fm, None)
    sat = (ref["status"][q.taps.size:] & contract.STATUS_FLAG["SATURATED"]) != 0
    assert sat.any() and not sat.all()
    data = blob.to_bytes(q)
    portable = Runtime(data, kernel="portable")
    portable.run_raw(wl_fm)
    for kernel in host_kernels():
        for packed in (False, True):
            rt = Runtime(data, kernel=kernel, packed=packed)
            got = rt.run_raw(wl_fm)
            for k in FIELDS:
                assert np.array_equal(np.asarray(got[k], dtype=np.int64), ref[k]), (kernel, packed, k)
            for f in STATE_FIELDS:
                a, b = getattr(rt._state, f), getattr(portable._state, f)
                assert bytes(ffi.buffer(ffi.addressof(rt._state, f))) == \
                    bytes(ffi.buffer(ffi.addressof(portable._state, f))), (kernel, packed, f, a, b)


def test_packed_form_leaves_out_unused_units():
    """The dead units of :func:`_dead_units_model` are left out of the packed form (smaller
    than the same shapes without them), except the one that clamps, whose flag the stream
    shows on the steps the location net runs."""
    live, wl_fm = _realistic_model(12, PAPER, 16, MEM8)
    dead, _ = _dead_units_model(12, PAPER, 16, MEM8)
    ref = intref.run(dead, wl_fm, None)
    sat = (ref["status"] & contract.STATUS_FLAG["SATURATED"]) != 0
    assert np.array_equal(sat, ref["contact"] != 0)
    kernels = [k for k in host_kernels() if k in PACKED_KERNELS]
    if not kernels:
        pytest.skip(f"no kernel with a packed form on {platform.machine()}")
    for kernel in kernels:
        sizes = [lib.fbg_pack_bytes(Runtime(blob.to_bytes(q), kernel=kernel, packed=True)._state)
                 for q in (live, dead)]
        assert 0 < sizes[1] < sizes[0], (kernel, sizes)


def test_kernel_selection():
    q, _ = _realistic_model(8, ODD, 16, artifact.Memory())
    data = blob.to_bytes(q)
    assert Runtime(data, kernel="portable").kernel == "portable"
    best = host_kernels()
    assert Runtime(data).kernel == (best[-1] if best else "portable")
    for kernel in ("sse2", "avx2", "neon"):
        if kernel not in best:
            with pytest.raises(ArgError):
                Runtime(data, kernel=kernel)
    with pytest.raises(Exception, match="unknown kernel"):
        Runtime(data, kernel="mmx")
    # fbg_init refuses an unknown kernel value; fbg_kernel of an uninitialised state is 0.
    rt = Runtime(data)  # holds the model's memory while fbg_init reads it
    model = rt._model
    st = ffi.new("fbg_state *")
    assert lib.fbg_init(st, model, 0x70) == lib.FBG_ERR_ARG
    assert lib.fbg_kernel(st) == 0
    assert lib.fbg_init(st, model, lib.FBG_OPT_KERNEL_PORTABLE | lib.FBG_OPT_REQUIRE_TARE) == lib.FBG_OK
    assert lib.fbg_kernel(st) == lib.FBG_OPT_KERNEL_PORTABLE
    assert set(KERNELS) == {"auto", "portable", "sse2", "avx2", "neon"}


def _aligned(size: int, offset: int = 0) -> tuple[Any, Any]:
    """A cffi buffer of ``size`` bytes at ``offset`` past an FBG_PACK_ALIGN boundary (the
    memory, to be held, and the pointer)."""
    mem = ffi.new("uint8_t[]", size + 2 * lib.FBG_PACK_ALIGN)
    start = (-int(ffi.cast("uintptr_t", mem))) % lib.FBG_PACK_ALIGN + offset
    return mem, mem + start


def test_pack_refuses_bad_buffers_and_states():
    kernels = [k for k in host_kernels() if k in PACKED_KERNELS]
    if not kernels:
        pytest.skip(f"no kernel with a packed form on {platform.machine()}")
    q, wl_fm = _realistic_model(11, ODD, 16, MEM5)
    data = blob.to_bytes(q)
    rt = Runtime(data, kernel=kernels[0], packed=False)  # holds the model
    model, st = rt._model, ffi.new("fbg_state *")
    # Not initialised: no size, FBG_ERR_STATE; NULL pointers: FBG_ERR_NULL.
    assert lib.fbg_pack_bytes(ffi.NULL) == 0 and lib.fbg_pack_bytes(st) == 0
    mem, buf = _aligned(1 << 16)
    assert lib.fbg_pack(st, buf, 1 << 16) == lib.FBG_ERR_STATE
    assert lib.fbg_use_pack(st, ffi.NULL) == lib.FBG_ERR_STATE
    assert lib.fbg_pack(ffi.NULL, buf, 1 << 16) == lib.FBG_ERR_NULL
    assert lib.fbg_use_pack(ffi.NULL, buf) == lib.FBG_ERR_NULL
    # The portable kernel has no packed form.
    assert lib.fbg_init(st, model, lib.FBG_OPT_KERNEL_PORTABLE) == lib.FBG_OK
    assert lib.fbg_pack_bytes(st) == 0
    assert lib.fbg_pack(st, buf, 1 << 16) == lib.FBG_ERR_ARG and st.packed == ffi.NULL
    for kernel in kernels:
        assert lib.fbg_init(st, model, KERNELS[kernel]) == lib.FBG_OK
        size = lib.fbg_pack_bytes(st)
        assert 0 < size <= 1 << 16
        assert lib.fbg_pack(st, ffi.NULL, size) == lib.FBG_ERR_NULL
        # Too small, or not FBG_PACK_ALIGN-aligned: FBG_ERR_ARG, the state still unpacked.
        assert lib.fbg_pack(st, buf, size - 1) == lib.FBG_ERR_ARG
        for offset in (1, 2, 8, 16):
            _, off = _aligned(size, offset)
            assert lib.fbg_pack(st, off, size) == lib.FBG_ERR_ARG
        assert st.packed == ffi.NULL
        # Not a packed form (zeros), misaligned, another kernel's or another model's: refused.
        assert lib.fbg_use_pack(st, buf) == lib.FBG_ERR_ARG
        assert lib.fbg_pack(st, buf, size) == lib.FBG_OK and st.packed == buf
        assert lib.fbg_use_pack(st, buf + 1) == lib.FBG_ERR_ARG and st.packed == buf
        other = Runtime(data, kernel=[k for k in ("sse2", "avx2") if k != kernel][0]
                        if len(kernels) > 1 else "portable", packed=False)
        if other.kernel in PACKED_KERNELS:
            assert lib.fbg_use_pack(other._state, buf) == lib.FBG_ERR_ARG
        twin = Runtime(data, kernel=kernel, packed=False)  # the same blob, another model struct
        assert lib.fbg_use_pack(twin._state, buf) == lib.FBG_ERR_ARG
        # Two states share one packed form; NULL goes back to the unpacked kernels; fbg_init
        # forgets it, reset and tare keep it; every way, the bits of the portable C.
        ref = Runtime(data, kernel="portable").run_raw(wl_fm).tobytes()
        st2 = ffi.new("fbg_state *")
        assert lib.fbg_init(st2, model, KERNELS[kernel]) == lib.FBG_OK
        assert lib.fbg_use_pack(st2, buf) == lib.FBG_OK and st2.packed == buf
        for state in (st, st2):
            out = np.zeros(len(wl_fm), dtype=rt.run_raw(wl_fm[:0]).dtype)
            assert lib.fbg_reset(state) == lib.FBG_OK and state.packed == buf
            rows = np.ascontiguousarray(wl_fm, dtype=np.int32)
            assert lib.fbg_run(state, ffi.cast("int32_t *", ffi.from_buffer(rows)), len(rows),
                               ffi.cast("fbg_output *", ffi.from_buffer(out))) == lib.FBG_OK
            assert out.tobytes() == ref
        assert lib.fbg_use_pack(st2, ffi.NULL) == lib.FBG_OK and st2.packed == ffi.NULL
        assert lib.fbg_init(st, model, KERNELS[kernel]) == lib.FBG_OK and st.packed == ffi.NULL
    del mem


# ---- golden sessions replayed by a C driver, natively and on aarch64 ------------------------

def _golden_sources(out: Path, q: QModel, wl_fm: np.ndarray, contact: np.ndarray | None) -> list[Path]:
    """replay_model.{c,h} and golden_vectors.c for the session of ``q`` on ``wl_fm``."""
    hdr, src = codegen.fixed_source(q, "replay")
    (out / "replay_model.h").write_text(hdr)
    (out / "replay_model.c").write_text(src)
    golden.write_golden_c(golden.golden_session(q, wl_fm, contact), out / "golden_vectors.c")
    return [out / "replay_model.c", out / "golden_vectors.c"]


@pytest.fixture(scope="module")
def sessions(tmp_path_factory, small_model_dir):
    """Source directories of two golden sessions: the shared trained model on a simulated
    recording, and an extreme random model on its stream."""
    dirs = []
    q, _ = load_quantized(Path(small_model_dir))
    wl, contact, _ = recording_fm(None, "smoke", 0, 300)
    d = tmp_path_factory.mktemp("golden_trained")
    _golden_sources(d, q, wl, contact)
    dirs.append(d)
    q, wl = _extreme_model(9, ODD, 16, MEM5)
    d = tmp_path_factory.mktemp("golden_extreme")
    _golden_sources(d, q, wl[:600], None)
    dirs.append(d)
    return dirs


def _build_replay(cc: str, session: Path, exe: Path, extra: list[str]) -> None:
    cmd = [cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", *extra,
           f"-I{RUNTIME / 'include'}", f"-I{ROOT / 'examples' / 'firmware'}", f"-I{session}",
           *sorted(str(p) for p in (RUNTIME / "src").glob("*.c")),
           str(session / "replay_model.c"), str(session / "golden_vectors.c"),
           str(ROOT / "tests" / "simd_replay.c"), "-o", str(exe)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def _replay_args(kernels: list[int], packed: bool = True) -> list[str]:
    """simd_replay arguments: each kernel, and (``packed``) once more from packed weights
    where it has a packed form (a trailing "p")."""
    args = [hex(k) for k in kernels]
    if packed:
        args += [hex(k) + "p" for k in kernels if KERNEL_NAME.get(k) in PACKED_KERNELS]
    return args


def _check_replay(cmd: list[str], args: list[str]) -> None:
    r = subprocess.run(cmd + args, capture_output=True, text=True, timeout=300)
    lines = r.stdout.strip().splitlines()
    assert r.returncode == 0 and len(lines) == len(args), r.stdout + r.stderr
    for arg, line in zip(args, lines):
        k, packed = int(arg.rstrip("p"), 16), arg.endswith("p")
        assert line.startswith(f"kernel 0x{k:02x}{' packed' if packed else ''}: "), line
        assert line.endswith(", 0 differ"), line


@pytest.mark.slow
def test_golden_sessions_on_every_host_kernel(sessions, tmp_path):
    _require("cc")
    kernels = [lib.FBG_OPT_KERNEL_PORTABLE] + [KERNELS[k] for k in host_kernels()]
    for i, session in enumerate(sessions):
        exe = tmp_path / f"replay{i}"
        _build_replay("cc", session, exe, [])
        _check_replay([str(exe)], _replay_args(kernels))


@pytest.mark.slow
def test_kernels_read_nothing_outside_the_arrays(sessions, tmp_path):
    """AddressSanitizer (global redzones around every generated weight array) and UBSan on the
    extreme session: the whole-vector reads past a row's end stay inside the weight array."""
    _require("cc")
    exe = tmp_path / "replay_asan"
    try:
        _build_replay("cc", sessions[1], exe, ["-fsanitize=address,undefined", "-fno-sanitize-recover=all",
                                                "-fno-omit-frame-pointer"])
    except AssertionError as exc:
        if "asan" in str(exc).lower() or "sanitize" in str(exc).lower():
            pytest.skip(f"the compiler has no sanitizer runtime here: {exc}")
        raise
    env = dict(os.environ, ASAN_OPTIONS="detect_leaks=0")
    r = subprocess.run([str(exe)] + _replay_args([lib.FBG_OPT_KERNEL_PORTABLE] +
                                                 [KERNELS[k] for k in host_kernels()]),
                       capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0 and "ERROR" not in r.stderr, r.stdout + r.stderr


@pytest.mark.target
def test_golden_sessions_on_aarch64_neon_under_qemu(sessions, tmp_path):
    _require("aarch64-linux-gnu-gcc", "qemu-aarch64")
    for i, session in enumerate(sessions):
        exe = tmp_path / f"replay{i}.a64"
        _build_replay("aarch64-linux-gnu-gcc", session, exe, ["-static"])
        _check_replay(["qemu-aarch64", str(exe)], _replay_args([lib.FBG_OPT_KERNEL_PORTABLE,
                                                                lib.FBG_OPT_KERNEL_NEON]))
    # NEON keeps its row kernels: no packed form there.
    r = subprocess.run(["qemu-aarch64", str(exe), hex(lib.FBG_OPT_KERNEL_NEON) + "p"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "packed: cannot run here" in r.stdout, r.stdout + r.stderr


@pytest.mark.slow
def test_portable_only_build_refuses_simd_kernels(sessions, tmp_path):
    """-DFBG_HOST_SIMD=0 builds the portable C alone: it replays the session and refuses
    every SIMD kernel."""
    _require("cc")
    exe = tmp_path / "replay_portable"
    _build_replay("cc", sessions[1], exe, ["-DFBG_HOST_SIMD=0"])
    _check_replay([str(exe)], [hex(lib.FBG_OPT_KERNEL_PORTABLE)])
    r = subprocess.run([str(exe), hex(lib.FBG_OPT_KERNEL_SSE2)], capture_output=True, text=True)
    assert r.returncode == 1 and "cannot run here" in r.stdout
    # ... and has no packed form (fbg_pack_bytes 0).
    r = subprocess.run([str(exe), hex(lib.FBG_OPT_KERNEL_PORTABLE) + "p"], capture_output=True, text=True)
    assert r.returncode == 1 and "packed: cannot run here" in r.stdout


def _swap_blobs(work: Path) -> list[Path]:
    """The committed fuzz blobs: the four models and the fuzz_blob seeds without their mode
    byte (some load, some are refused early, some are copies of a model)."""
    seeds = []
    for p in sorted((RUNTIME / "fuzz" / "corpus" / "fuzz_blob").iterdir()):
        seeds.append(work / f"seed_{p.name}.fbgm")
        seeds[-1].write_bytes(p.read_bytes()[1:])
    return sorted((RUNTIME / "fuzz" / "models").glob("*.fbgm")) + seeds


def _model_swap(cc: str, exe: Path, extra: list[str], run: list[str], kernels: list[int]) -> None:
    """Build tests/model_swap.c and run it on ``kernels`` (and their packed forms) over the
    committed fuzz blobs: every reload under a running state is refused or harmless."""
    cmd = [cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O1", "-g", *extra,
           f"-I{RUNTIME / 'include'}", *sorted(str(p) for p in (RUNTIME / "src").glob("*.c")),
           str(ROOT / "tests" / "model_swap.c"), "-o", str(exe)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    args = _replay_args(kernels)
    r = subprocess.run(run + [str(exe), *args, "--", *map(str, _swap_blobs(exe.parent))], capture_output=True,
                       text=True, timeout=600, env=dict(os.environ, ASAN_OPTIONS="detect_leaks=1"))
    lines = r.stdout.strip().splitlines()
    assert r.returncode == 0 and len(lines) == len(args) and "ERROR" not in r.stderr, \
        r.stdout + r.stderr
    for line in lines:
        m = re.fullmatch(r"kernel 0x[0-9a-f]+(?: packed)?: (\d+) swaps, (\d+) refused, 0 wrong", line)
        assert m and int(m.group(1)) >= 200 and int(m.group(2)) >= 100, line


@pytest.mark.slow
def test_model_reloaded_under_a_state_is_refused_on_every_host_kernel(tmp_path):
    """fbg_model_from_blob into the model a running state uses, then fbg_step / fbg_run without
    fbg_init: FBG_ERR_MODEL_CHANGED and the safe output (or, when the model did not change,
    the same outputs as a state that saw no reload), under AddressSanitizer and UBSan, on the
    portable, SSE2, AVX2 and packed kernels; then fbg_init on the new model runs it."""
    _require("cc")
    kernels = [lib.FBG_OPT_KERNEL_PORTABLE] + [KERNELS[k] for k in host_kernels()]
    _model_swap("cc", tmp_path / "swap", ["-fsanitize=address,undefined", "-fno-sanitize-recover=all",
                                          "-fno-omit-frame-pointer"], [], kernels)


@pytest.mark.target
def test_model_reloaded_under_a_state_is_refused_on_aarch64_neon_under_qemu(tmp_path):
    _require("aarch64-linux-gnu-gcc", "qemu-aarch64")
    _model_swap("aarch64-linux-gnu-gcc", tmp_path / "swap.a64", ["-static"], ["qemu-aarch64"],
                [lib.FBG_OPT_KERNEL_PORTABLE, lib.FBG_OPT_KERNEL_NEON])
