"""Python side of the hardening tools (docs/robustness.md).

- The operation-stream protocol of ``hardcase_driver`` (:func:`encode_ops`, :func:`decode_out`,
  :func:`run_driver`), used by tests/test_hardcases_*.py to run every hard case through the
  driver built with sanitizers or under valgrind.
- :func:`stress_qmodel`: a fixed-point model at the edge of what ``fbg_model_check`` accepts,
  built so that a saturated input drives EVERY layer's accumulator exactly to its proven
  worst-case bound (both signs) and ``acc * mult + 2^(shift-1)`` to within one multiplier step
  of INT64_MAX.
- ``python runtime_c/fuzz/hardcases.py`` (``make -C runtime_c fuzz-corpus``) regenerates the
  committed fuzz models and seed corpus in runtime_c/fuzz/.

Test code only; not part of the installed package.
"""
from __future__ import annotations

import os
import shlex
import struct
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce import contract

HERE = Path(__file__).resolve().parent
INT64_MAX = 2**63 - 1
SAT16 = 32767

# Driver op codes (hardcase_driver.c).
OP_INIT, OP_TARE, OP_BASE, OP_STEP, OP_RUN, OP_RESET = 1, 2, 3, 4, 5, 6
#: Output fields per sample, in the driver's order (= fbg_output's integer fields).
OUT_FIELDS = contract.OUTPUT_FIELDS


# --------------------------------------------------------------------------------------------
# Driver protocol
# --------------------------------------------------------------------------------------------

def _samples(wl: Any) -> np.ndarray:
    a = np.asarray(wl, dtype=np.int64).reshape(-1, 5)
    if a.size and (a.min() < -2**31 or a.max() > 2**31 - 1):
        raise ValueError("wavelengths must be int32 femtometres")
    return a.astype("<i4")


def encode_ops(ops: Sequence[tuple]) -> bytes:
    """``[("init", options), ("tare", wl), ("base", wl5), ("step", wl), ("run", wl), ("reset",)]``
    -> the driver's little-endian int32 stream."""
    out = bytearray()
    for op in ops:
        kind = op[0]
        if kind == "init":
            out += struct.pack("<ii", OP_INIT, int(op[1]))
        elif kind in ("tare", "step", "run"):
            wl = _samples(op[1])
            code = {"tare": OP_TARE, "step": OP_STEP, "run": OP_RUN}[kind]
            out += struct.pack("<ii", code, wl.shape[0]) + wl.tobytes()
        elif kind == "base":
            out += struct.pack("<i", OP_BASE) + _samples(op[1]).reshape(5).tobytes()
        elif kind == "reset":
            out += struct.pack("<i", OP_RESET)
        else:
            raise ValueError(f"unknown op {kind!r}")
    return bytes(out)


def decode_out(data: bytes) -> list[dict[str, Any]]:
    """The driver's OUT stream -> one dict per op (``op``, ``status`` and, for step/run,
    ``out``: a dict of int64 arrays named like :data:`OUT_FIELDS`; for tare ``accepted``,
    ``baseline_fm``)."""
    v = np.frombuffer(data, dtype="<i4").astype(np.int64)
    i, res = 0, []
    while i < v.size:
        op, status = int(v[i]), int(v[i + 1])
        i += 2
        rec: dict[str, Any] = {"op": op, "status": status}
        if op == OP_TARE:
            rec["accepted"] = int(v[i])
            rec["baseline_fm"] = v[i + 1:i + 6].copy()
            i += 6
        elif op in (OP_STEP, OP_RUN):
            n = int(v[i])
            block = v[i + 1:i + 1 + n * len(OUT_FIELDS)].reshape(n, len(OUT_FIELDS))
            rec["out"] = {k: block[:, j].copy() for j, k in enumerate(OUT_FIELDS)}
            i += 1 + n * len(OUT_FIELDS)
        res.append(rec)
    return res


def driver_wrapper() -> list[str]:
    """``FBGFORCE_HARDCASE_WRAPPER`` (e.g. a valgrind command line) as an argv prefix."""
    return shlex.split(os.environ.get("FBGFORCE_HARDCASE_WRAPPER", ""))


def run_driver(driver: str | Path, blob: bytes, ops: Sequence[tuple], timeout: float = 600.0
               ) -> list[dict[str, Any]]:
    """Run ``ops`` through the driver binary on a model blob; raises AssertionError with the
    driver's stderr if it fails (sanitizer report, valgrind error, contract violation)."""
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        (t / "model.fbgm").write_bytes(blob)
        (t / "ops.bin").write_bytes(encode_ops(ops))
        cmd = driver_wrapper() + [str(driver), "run", str(t / "model.fbgm"), str(t / "ops.bin"),
                                  str(t / "out.bin")]
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if p.returncode != 0:
            raise AssertionError(f"{' '.join(cmd[:3])}... exit {p.returncode}:\n{p.stderr[-4000:]}")
        return decode_out((t / "out.bin").read_bytes())


def driver_blob_status(driver: str | Path, blobs: Sequence[bytes], timeout: float = 600.0) -> list[int]:
    """Load each blob through ``hardcase_driver blob`` (exact-size heap copies); status codes."""
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i, b in enumerate(blobs):
            p = Path(tmp) / f"b{i}.fbgm"
            p.write_bytes(b)
            paths.append(str(p))
        cmd = driver_wrapper() + [str(driver), "blob", *paths]
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if p.returncode != 0:
            raise AssertionError(f"hardcase_driver blob: exit {p.returncode}:\n{p.stderr[-4000:]}")
        return [int(line.split()[0]) for line in p.stdout.splitlines()]


# --------------------------------------------------------------------------------------------
# The stress model
# --------------------------------------------------------------------------------------------

def stress_qmodel(width: int = 128, n_layers: int = 8, w_bits: int = 16, bias: int = 0,
                  n_taps: int = 64):
    """A valid fixed-point model whose accumulators reach their proven bounds exactly.

    Every hidden layer has ``width`` rows: rows ``[0, width/2)`` weigh the "hot" inputs with
    +qmax and carry ``+bias``, rows ``[width/2, width)`` weigh them with -qmax and ``-bias``;
    other weights are 0. The hot inputs of layer 0 are the four standardised channels (and, in
    the location net, the quantised force; the contact input, which can never reach 32767,
    gets weight 0); of later layers the outputs of the positive rows. When all four channels
    saturate high (a compensated shift of +2^31 - 1, reached with temperature coefficient 4),
    every positive row's accumulator is ``+bound`` (output clamps to 32767, keeping the next
    layer hot) and every negative row's ``-bound``, where ``bound = sum|w| * 32767 + |bias|``.
    Multipliers are the largest ``fbg_model_check`` accepts: ``floor((INT64_MAX -
    2^(shift-1)) / bound)``. The FIR has ``n_taps`` taps of 32767 (Q15), the largest FIR bound.

    Output layers: contact margin row positive (contact), force row positive (force clamps to
    INT32_MAX -> OVERLOAD), location x row positive, y row negative (x, y clamp to +-INT32_MAX).
    The load proxy (input-side overload rule) has the largest coefficients the loader accepts.
    """
    from fbgforce.export.qmodel import QLayer, QModel

    qmax = 127 if w_bits == 8 else SAT16
    half = width // 2
    # acc * mult is close to 2^63 by construction; >> 30 leaves ~2^33, so every output clamps
    # (hidden rows to 32767, keeping the next layer's inputs hot).
    shift = 30

    def mult_for(bound: np.ndarray, sh: int) -> np.ndarray:
        return np.array([min((INT64_MAX - (1 << (sh - 1))) // max(int(b), 1), 2**31 - 1)
                         for b in bound], dtype=np.int64)

    def layer(n_in: int, hot: Sequence[int], signs: Sequence[int]) -> QLayer:
        w = np.zeros((len(signs), n_in), dtype=np.int64)
        w[:, list(hot)] = qmax
        w *= np.asarray(signs, dtype=np.int64)[:, None]
        b = np.asarray(signs, dtype=np.int64) * bias
        bound = np.abs(w).sum(axis=1) * SAT16 + np.abs(b)
        return QLayer(w, w_bits, b, mult_for(bound, shift), shift)

    def net(n_in: int, hot0: Sequence[int], out_signs: Sequence[int]):
        layers, hot = [], list(hot0)
        signs = [1] * half + [-1] * (width - half)
        for _ in range(n_layers - 1):
            layers.append(layer(n_in, hot, signs))
            n_in, hot = width, list(range(half))
        layers.append(layer(n_in, hot, out_signs))
        return layers

    nets = [net(4, range(4), [1]), net(4, range(4), [1]), net(6, [0, 1, 2, 3, 5], [1, -1])]
    return QModel(
        baseline_fm=[1_530_000_000, 1_538_000_000, 1_546_000_000, 1_554_000_000, 1_562_000_000],
        jump_max_fm=2_000_000, temp_coeff_q24=[4 << 24] * 4, taps=[SAT16] * n_taps, tap_q=15,
        mean_fm=[0] * 4, z_mult=[1] * 4, z_shift=1, z_frac=14, fq_mult=1 << 30, fq_shift=1,
        force_offset_mN=1000, xy_offset_um=[0, 0], overload_mN=70_000, nets=nets,
        # The input-side load proxy at its limits too: |coeff| just below 2^28, so the sum of
        # four products of saturated filter outputs is ~2^61.
        load_coeff=[(1 << 28) - 1] * 4, load_shift=30, load_max_mN=1000,
        # The temperature reference's average at its longest: its accumulator at its largest
        # (the reference's shift at +-1e9 fm times 2^8).
        ref_shift=8)


def stress_inputs(q, sign: int = 1, n: int | None = None) -> np.ndarray:
    """Constant samples that saturate the stress model's compensated shifts with ``sign``:
    strain gratings at the window edge, the reference grating at the other (no jump faults
    after the first sample, which has no predecessor)."""
    from fbgforce.contract import LIMIT

    lo, hi = LIMIT["WL_MIN_FM"], LIMIT["WL_MAX_FM"]
    n = q.taps.size + 8 if n is None else n
    row = np.array([hi] * 4 + [lo] if sign > 0 else [lo] * 4 + [hi])
    return np.tile(row, (n, 1)).astype(np.int64)


# --------------------------------------------------------------------------------------------
# Fuzz models and seed corpus
# --------------------------------------------------------------------------------------------

MODELS_DIR = HERE / "models"
CORPUS_DIR = HERE / "corpus"


def trained_blobs(tmp: Path) -> dict[str, bytes]:
    """Blobs of a small model trained on the ``smoke`` scene (as tests/conftest.py's
    ``small_model_dir``), exported with 16- and 8-bit weights."""
    from fbgforce import sim
    from fbgforce.recordings import dataset
    from fbgforce.model import modeldir as fm
    from fbgforce.export.exporter import export_model
    from fbgforce.trainer.train import train

    data = tmp / "smoke.csv"
    dataset.save(sim.simulate("smoke", seed=0), data)
    mdir = tmp / "model"
    fm.save(train([data], epochs=40, seed=0, filter="causal", progress=False), mdir)
    out = {}
    for bits in (16, 8):
        export_model(mdir, bits=bits, calib=[data], onnx=False)
        out[f"small{bits}"] = (mdir / "model.fbgm").read_bytes()
    return out


def write_corpus() -> list[Path]:
    """Regenerate runtime_c/fuzz/models/*.fbgm and the seed corpus of both fuzzers."""
    from fbgforce.export.blob import to_bytes

    written: list[Path] = []
    MODELS_DIR.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        blobs = trained_blobs(Path(tmp))
    # The fuzzer's stress model is narrow (fast to step); the tests use the full 128 x 8 one.
    blobs["stress"] = to_bytes(stress_qmodel(width=16, n_layers=4, n_taps=8))
    blobs["stress_bias"] = to_bytes(stress_qmodel(width=16, n_layers=3, bias=(1 << 60) - 1, n_taps=4))
    for name, b in blobs.items():
        p = MODELS_DIR / f"{name}.fbgm"
        p.write_bytes(b)
        written.append(p)

    # fuzz_blob seeds: byte 0 = mode (bit 0: repair the CRC, bit 1: misalign), rest = blob.
    cb = CORPUS_DIR / "fuzz_blob"
    cb.mkdir(parents=True, exist_ok=True)
    small = blobs["small16"]
    seeds = {
        "valid16": b"\x00" + small, "valid8": b"\x00" + blobs["small8"],
        "stress": b"\x00" + blobs["stress"], "stress_bias": b"\x01" + blobs["stress_bias"],
        "truncated_header": b"\x00" + small[:10], "truncated_body": b"\x01" + small[:len(small) // 2],
        "bad_magic": b"\x00" + b"FBGX" + small[4:], "misaligned": b"\x02" + small,
        "layer_table": b"\x01" + small[:200],
    }
    for name, data in seeds.items():
        p = cb / name
        p.write_bytes(data)
        written.append(p)

    # fuzz_step seeds: byte 0 selects the model, then the op stream of fuzz_step.c.
    cs = CORPUS_DIR / "fuzz_step"
    cs.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for m in range(4):
        for k in range(3):
            p = cs / f"model{m}_{k}"
            p.write_bytes(bytes([m]) + rng.integers(0, 256, 160, dtype=np.uint8).tobytes())
            written.append(p)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    for p in write_corpus():
        print(p.relative_to(HERE.parent.parent))
    return 0


if __name__ == "__main__":
    sys.exit(main())
