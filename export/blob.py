"""The ``model.fbgm`` blob: the fixed-point model as the C runtime loads it (zero copy).

Layout (little-endian; docs/model-format.md is the normative description)::

    0   "FBGM"                     magic
    4   u16 version (3)            FBG_BLOB_VERSION
    6   u16 flags (0)
    8   u32 total_len              bytes of the whole blob, a multiple of 8
    12  u32 crc32                  zlib CRC-32 of bytes [16, total_len)
    16  parameter block (128 bytes, see _PARAMS) -> offset 144
    144 layer table: 8 bytes per layer, nets in order contact, force, location:
        u16 n_in, u16 n_out, u8 w_bits, u8 shift, u8 acc32 (0: int64, 1: int32), u8 reserved (0)
    then arrays, each starting at a multiple of 8 (zero padding):
        taps int16[n_taps]; per layer: weights int16|int8[n_out*n_in] (row-major),
        bias int64[n_out], mult int32[n_out]
    total_len = end of the last array rounded up to 8
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from fbgforce.errors import InputError
from fbgforce.export.quantize import NET_NAMES, QLayer, QModel

MAGIC = b"FBGM"
VERSION = 3
HEADER = struct.Struct("<4sHHII")
#: baseline_fm[5], jump_max_fm, temp_coeff_q24[4], mean_fm[4], z_mult[4], fq_mult,
#: force_offset_mN, xy_offset_um[2], overload_mN, load_coeff[4], load_max_mN | n_taps, tap_q,
#: z_frac, z_shift, fq_shift, load_shift, n_layers[3], stuck_max, pad[4]
_PARAMS = struct.Struct("<5ii4i4i4iii2ii4ii" + "HBBBBB3BH4x")
PARAMS_END = HEADER.size + _PARAMS.size
LAYER_ENTRY = struct.Struct("<HHBBBB")
FILE_NAME = "model.fbgm"

assert PARAMS_END == 144


def _pad8(buf: bytearray) -> None:
    buf.extend(b"\0" * (-len(buf) % 8))


def to_bytes(q: QModel) -> bytes:
    """Serialise a quantised model (it is checked first)."""
    q.check()
    body = bytearray(_PARAMS.pack(
        *q.baseline_fm.tolist(), q.jump_max_fm, *q.temp_coeff_q24.tolist(), *q.mean_fm.tolist(),
        *q.z_mult.tolist(), q.fq_mult, q.force_offset_mN, *q.xy_offset_um.tolist(), q.overload_mN,
        *q.load_coeff.tolist(), q.load_max_mN,
        q.taps.size, q.tap_q, q.z_frac, q.z_shift, q.fq_shift, q.load_shift,
        *[len(net) for net in q.nets], q.stuck_max))
    for net in q.nets:
        for layer in net:
            body += LAYER_ENTRY.pack(layer.n_in, layer.n_out, layer.w_bits, layer.shift,
                                     int(layer.acc32), 0)
    buf = bytearray(HEADER.size) + body
    _pad8(buf)
    buf += q.taps.astype("<i2").tobytes()
    _pad8(buf)
    for net in q.nets:
        for layer in net:
            buf += layer.w.astype("<i2" if layer.w_bits == 16 else "i1").tobytes()
            _pad8(buf)
            buf += layer.bias.astype("<i8").tobytes()
            _pad8(buf)
            buf += layer.mult.astype("<i4").tobytes()
            _pad8(buf)
    crc = zlib.crc32(bytes(buf[HEADER.size:])) & 0xFFFFFFFF
    buf[:HEADER.size] = HEADER.pack(MAGIC, VERSION, 0, len(buf), crc)
    return bytes(buf)


def from_bytes(data: bytes, path: str | None = None) -> QModel:
    """Parse a blob into a :class:`QModel` (pure Python; same checks as the C loader, with
    InputError messages instead of codes)."""
    def bad(why: str) -> InputError:
        return InputError(why, path=path)

    if len(data) < HEADER.size:
        raise bad("truncated: shorter than the 16-byte header")
    magic, version, _flags, total, crc = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise bad(f"not an fbgforce model blob (magic {magic!r})")
    if version != VERSION:
        raise bad(f"blob format version {version} is not supported (this fbgforce reads {VERSION})")
    if total > len(data):
        raise bad(f"truncated: declares {total} bytes, has {len(data)}")
    if total < PARAMS_END:
        raise bad("declared length smaller than the parameter block")
    if zlib.crc32(data[HEADER.size:total]) & 0xFFFFFFFF != crc:
        raise bad("CRC-32 mismatch: the blob is corrupt")
    p = _PARAMS.unpack_from(data, HEADER.size)
    baseline, jump, tc, mean, zm = p[0:5], p[5], p[6:10], p[10:14], p[14:18]
    fq_mult, f_off, xy_off, overload = p[18], p[19], p[20:22], p[22]
    load_coeff, load_max = p[23:27], p[27]
    n_taps, tap_q, z_frac, z_shift, fq_shift, load_shift = p[28:34]
    n_layers, stuck_max = p[34:37], p[37]
    off = PARAMS_END
    shapes = []
    for name, nl in zip(NET_NAMES, n_layers):
        rows = []
        for _ in range(nl):
            if off + LAYER_ENTRY.size > total:
                raise bad(f"{name}: layer table runs past the end")
            entry = LAYER_ENTRY.unpack_from(data, off)
            if entry[4] not in (0, 1) or entry[5] != 0:
                raise bad(f"{name}: layer table flags {entry[4]}/{entry[5]} (acc32 must be 0 or 1)")
            rows.append(entry[:5])
            off += LAYER_ENTRY.size
        shapes.append(rows)

    def take(dtype: str, count: int) -> np.ndarray:
        nonlocal off
        off += -off % 8
        size = np.dtype(dtype).itemsize * count
        if off + size > total:
            raise bad("array runs past the declared length")
        arr = np.frombuffer(data, dtype=dtype, count=count, offset=off).astype(np.int64)
        off += size
        return arr

    taps = take("<i2", n_taps)
    nets = []
    for rows in shapes:
        layers = []
        for n_in, n_out, w_bits, shift, acc32 in rows:
            if w_bits not in (8, 16):
                raise bad(f"weight width {w_bits} is neither 8 nor 16")
            w = take("<i2" if w_bits == 16 else "i1", n_in * n_out).reshape(n_out, n_in)
            layers.append(QLayer(w, w_bits, take("<i8", n_out), take("<i4", n_out), shift,
                                 acc32=bool(acc32)))
        nets.append(layers)
    off += -off % 8
    if off != total:
        raise bad(f"declared length {total} differs from the {off} bytes the shapes imply")
    q = QModel(baseline_fm=baseline, jump_max_fm=jump, temp_coeff_q24=tc, taps=taps, tap_q=tap_q,
               mean_fm=mean, z_mult=zm, z_shift=z_shift, z_frac=z_frac, fq_mult=fq_mult,
               fq_shift=fq_shift, force_offset_mN=f_off, xy_offset_um=xy_off,
               overload_mN=overload, nets=nets, load_coeff=load_coeff, load_shift=load_shift,
               load_max_mN=load_max, stuck_max=stuck_max)
    try:
        q.check()
    except ValueError as exc:
        raise bad(str(exc)) from exc
    return q


def blob_path(model: str | Path) -> Path:
    """``model`` may be a model directory (its model.fbgm) or a blob file."""
    p = Path(model)
    return p / FILE_NAME if p.is_dir() else p


def load_model_blob(model: str | Path) -> QModel:
    """Read and parse the blob of a model directory (or a blob file)."""
    p = blob_path(model)
    if not p.is_file():
        raise InputError("no fixed-point model blob; run 'fbgforce export --model DIR' first",
                         path=str(p))
    return from_bytes(p.read_bytes(), path=str(p))
