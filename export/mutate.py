"""Seeded mutations of a valid model blob, for the one-verdict campaign.

The C loader (``fbg_model_from_blob``) and the Python reader (:func:`fbgforce.export.blob.
from_bytes`) must accept and refuse exactly the same blobs with the same code.
:func:`mutants` yields corrupted copies of a valid blob: bit flips, truncations, length and
header edits, layer-table (shape) edits, extreme values in every parameter field and array,
non-zero padding, with the CRC fixed up in most cases (otherwise nearly every mutant would stop
at the CRC check). tests/test_blob_verdict.py runs 10^4 of them in CI,
``python -m fbgforce.bench.bench_blob_verdict`` 10^6.
"""
from __future__ import annotations

import struct
import zlib
from typing import Iterator

import numpy as np

from fbgforce import contract
from fbgforce.export import blob

_EXTREMES = {
    "int32_t": (0, 1, -1, -2**31, 2**31 - 1, -(2**31 - 1)),
    "uint32_t": (0, 1, 2**32 - 1, 2**31),
    "int16_t": (0, 1, -1, -2**15, 2**15 - 1),
    "uint16_t": (0, 1, 2**16 - 1, 2**15),
    "uint8_t": (0, 1, 255, 128),
}
_FMT = {"int32_t": "<i", "uint32_t": "<I", "int16_t": "<h", "uint16_t": "<H", "uint8_t": "<B",
        "int64_t": "<q", "int8_t": "<b"}


def fix_crc(buf: bytearray) -> bytes:
    """The blob with its header CRC recomputed over its declared (or whole) body."""
    total = struct.unpack_from("<I", buf, 8)[0] if len(buf) >= 16 else 0
    end = total if 16 <= total <= len(buf) else len(buf)
    if len(buf) >= 16:
        struct.pack_into("<I", buf, 12, zlib.crc32(bytes(buf[16:end])) & 0xFFFFFFFF)
    return bytes(buf)


def param_slots() -> list[tuple[int, str, contract.Field]]:
    """(byte offset, C type, field) of every parameter entry in the blob."""
    slots, off = [], contract.HEADER.size
    for f in contract.PARAMS:
        size = contract.CTYPES[f.ctype][2]
        for _ in range(f.count):
            slots.append((off, f.ctype, f))
            off += size
    return slots


def array_slots(blob: bytes) -> list[tuple[int, str, int]]:
    """(offset, C type, count) of every array of a valid blob, from its own layer table."""
    p = contract.decode_params(blob[contract.HEADER.size:contract.PARAMS_END])
    off, layers = contract.PARAMS_END, []
    for n in p["n_layers"]:  # type: ignore[union-attr]
        for _ in range(n):
            n_in, n_out, w_bits = struct.unpack_from("<HHB", blob, off)
            layers.append((n_in, n_out, w_bits))
            off += contract.LAYER_ENTRY.size
    off += -off % 8
    slots = [(off, "int16_t", int(p["n_taps"]))]  # type: ignore[arg-type]
    off += 2 * int(p["n_taps"]) + (-(2 * int(p["n_taps"])) % 8)  # type: ignore[arg-type]
    for n_in, n_out, w_bits in layers:
        for ctype, count, size in (("int16_t" if w_bits == 16 else "int8_t", n_in * n_out, w_bits // 8),
                                   ("int64_t", n_out, 8), ("int32_t", n_out, 4)):
            slots.append((off, ctype, count))
            off += count * size + (-(count * size) % 8)
    return slots


def mutants(blob: bytes, n: int, seed: int = 0) -> Iterator[tuple[str, bytes]]:
    """``n`` seeded mutants of a valid blob, as (kind, bytes)."""
    rng = np.random.default_rng(seed)
    params = param_slots()
    arrays = array_slots(blob)
    sizes = {"int8_t": 1, "int16_t": 2, "int32_t": 4, "int64_t": 8}
    array_gaps = [k for off, ctype, count in arrays
                  for k in range(off + count * sizes[ctype], off + count * sizes[ctype]
                                 + (-(count * sizes[ctype]) % 8))]
    n_layers = sum(contract.decode_params(blob[16:contract.PARAMS_END])["n_layers"])  # type: ignore[arg-type]
    kinds = ("flip", "truncate", "length", "header", "table", "param", "array", "padding")
    for _ in range(n):
        kind = kinds[int(rng.integers(len(kinds)))]
        buf = bytearray(blob)
        fix = rng.random() < 0.9
        if kind == "flip":
            for _ in range(int(rng.integers(1, 4))):
                pos = int(rng.integers(16, len(buf)))
                buf[pos] ^= 1 << int(rng.integers(8))
        elif kind == "truncate":
            buf = buf[:int(rng.integers(0, len(buf)))]
        elif kind == "length":
            total = len(buf) + int(rng.choice([-8, 8, -1, 1, -len(buf), 2**31, 16 - len(buf)]))
            if rng.random() < 0.5 and total - len(buf) <= 64:   # a longer blob to match
                buf += bytes(max(0, total - len(buf)))
            struct.pack_into("<I", buf, 8, max(0, min(total, 2**32 - 1)))
        elif kind == "header":
            pos = int(rng.choice([4, 5, 6, 7]))
            buf[pos] = int(rng.integers(256))
        elif kind == "table":
            entry = contract.PARAMS_END + 8 * int(rng.integers(n_layers))
            what = int(rng.integers(6))
            if what < 2:
                struct.pack_into("<H", buf, entry + 2 * what,
                                 int(rng.choice([0, 1, 2, 127, 128, 129, 65535, int(rng.integers(65536))])))
            else:
                buf[entry + 2 + what] = int(rng.choice([0, 1, 2, 8, 16, 32, 62, 63, 255]))
        elif kind == "param":
            off, ctype, f = params[int(rng.integers(len(params)))]
            values = list(_EXTREMES[ctype])
            if f.lo is not None:
                values += [f.lo, f.hi, f.lo - 1, f.hi + 1]
            v = int(rng.choice(values))
            lo, hi = contract.CTYPE_RANGE[ctype]
            struct.pack_into(_FMT[ctype], buf, off, min(max(v, lo), hi))
        elif kind == "array":
            off, ctype, count = arrays[int(rng.integers(len(arrays)))]
            bits = {"int8_t": 8, "int16_t": 16, "int32_t": 32, "int64_t": 64}[ctype]
            v = int(rng.choice([0, 1, -1, -2**(bits - 1), 2**(bits - 1) - 1, -(2**(bits - 1) - 1),
                                2**(bits - 2), -2**(bits - 2)]))
            struct.pack_into(_FMT[ctype], buf, off + int(rng.integers(count)) * (bits // 8), v)
        else:  # non-zero bytes where the format has zero padding or reserved fields
            gaps = [contract.HEADER.size + contract.PARAMS_STRUCT.size + k
                    for k in range(contract.PARAMS_SIZE - contract.PARAMS_STRUCT.size)]
            gaps += [contract.PARAMS_END + 8 * k + 7 for k in range(n_layers)] + array_gaps
            buf[int(rng.choice(gaps))] = int(rng.integers(1, 256))
        yield kind, fix_crc(buf) if fix else bytes(buf)


def python_verdict(data: bytes) -> str:
    """``FBG_OK`` or the ``FBG_ERR_*`` name :func:`fbgforce.export.blob.from_bytes` gives."""
    try:
        blob.from_bytes(data)
    except blob.BlobError as exc:
        return f"FBG_{exc.code}"
    return "FBG_OK"


def c_verdict(data: bytes) -> str:
    """The code name ``fbg_model_from_blob`` returns for ``data`` (from an aligned copy)."""
    from fbgforce.pybind import ffi, lib   # the C extension: only where a verdict is asked

    buf = ffi.new("uint64_t[]", max(1, (len(data) + 7) // 8))
    ffi.memmove(buf, data, len(data))
    model = ffi.new("fbg_model *")
    return contract.CODE_NAME[lib.fbg_model_from_blob(model, ffi.cast("uint8_t *", buf), len(data))]
