"""The ``model.fbgm`` blob: the fixed-point model as the C runtime loads it (zero copy).

Layout (little-endian; docs/model-format.md is the normative description; the field list is
:data:`fbgforce.contract.PARAMS`)::

    0   "FBGM"                     magic
    4   u16 version                FBG_BLOB_VERSION
    6   u16 flags                  0 (a non-zero flag is a format this library does not know)
    8   u32 total_len              bytes of the whole blob, a multiple of 8
    12  u32 crc32                  zlib CRC-32 of bytes [16, total_len)
    16  parameter block            contract.PARAMS in order, zero-padded to a multiple of 8
    ..  layer table: 8 bytes per layer, nets in order contact, force, location:
        u16 n_in, u16 n_out, u8 w_bits, u8 shift, u8 acc32 (0: int64, 1: int32), u8 0
    then arrays, each starting at a multiple of 8 (zero padding):
        taps int16[n_taps]; per layer: weights int16|int8[n_out*n_in] (row-major),
        bias int64[n_out], mult int32[n_out]
    total_len = end of the last array rounded up to 8

:func:`from_bytes` applies the C loader's checks (runtime_c/src/fbg_blob.c) in the C loader's
order and reports the same ``FBG_ERR_*`` code, so both readers give every blob one verdict
(tests/test_blob_verdict.py).
"""
from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce import contract
from fbgforce.errors import InputError
from fbgforce.export.qmodel import NET_NAMES, ModelCheckError, QLayer, QModel

MAGIC = contract.MAGIC
VERSION = contract.LIMIT["BLOB_VERSION"]
HEADER = contract.HEADER
PARAMS_END = contract.PARAMS_END
LAYER_ENTRY = contract.LAYER_ENTRY
FILE_NAME = contract.BLOB_FILE
MAX_WIDTH = contract.LIMIT["MAX_WIDTH"]


class BlobError(InputError):
    """A blob the C loader refuses; ``code`` is the ``FBG_ERR_*`` name it returns."""

    def __init__(self, code: str, reason: str, path: str | None = None) -> None:
        self.code = code
        super().__init__(f"{reason} ({code})", path=path)


def _pad8(buf: bytearray) -> None:
    buf.extend(b"\0" * (-len(buf) % 8))


def to_bytes(q: QModel) -> bytes:
    """Serialise a quantised model (it is checked first)."""
    q.check()
    body = bytearray(contract.encode_params(q.params()))
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
    """Parse and check a blob into a :class:`QModel`, raising :class:`BlobError` with the code
    the C loader (``fbg_model_from_blob``) returns for the same bytes."""
    def bad(code: str, why: str) -> BlobError:
        return BlobError(code, why, path=path)

    if len(data) < HEADER.size:
        raise bad("ERR_TRUNCATED", "truncated: shorter than the 16-byte header")
    magic, version, flags, total, crc = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise bad("ERR_BAD_MAGIC", f"not an fbgforce model blob (magic {magic!r})")
    if version != VERSION or flags != 0:
        raise bad("ERR_VERSION", f"blob format version {version} flags {flags} is not supported "
                                 f"(this fbgforce reads version {VERSION}, flags 0)")
    if total > len(data):
        raise bad("ERR_TRUNCATED", f"truncated: declares {total} bytes, has {len(data)}")
    if total < PARAMS_END:
        raise bad("ERR_SIZE", "declared length smaller than the parameter block")
    if zlib.crc32(data[HEADER.size:total]) & 0xFFFFFFFF != crc:
        raise bad("ERR_CRC", "CRC-32 mismatch: the blob is corrupt")
    block = data[HEADER.size:PARAMS_END]
    p = contract.decode_params(block)
    if any(block[contract.PARAMS_STRUCT.size:]):
        raise bad("ERR_RANGE", "non-zero padding after the parameter block")
    problem = contract.check_params(p)
    if problem is not None:
        raise bad(*problem)

    off = PARAMS_END
    shapes = []
    for name, n_layers in zip(NET_NAMES, p["n_layers"]):  # type: ignore[arg-type]
        rows = []
        for _ in range(n_layers):
            if off + LAYER_ENTRY.size > total:
                raise bad("ERR_SIZE", f"{name}: layer table runs past the declared length")
            n_in, n_out, w_bits, shift, acc32, zero = LAYER_ENTRY.unpack_from(data, off)
            if zero != 0 or acc32 > 1:
                raise bad("ERR_RANGE", f"{name}: layer table acc32 {acc32} / reserved {zero}")
            off += LAYER_ENTRY.size
            if not (1 <= n_in <= MAX_WIDTH and 1 <= n_out <= MAX_WIDTH):
                raise bad("ERR_SHAPE", f"{name}: layer {n_in} x {n_out} beyond 1..{MAX_WIDTH}")
            if w_bits not in (8, 16):
                raise bad("ERR_RANGE", f"{name}: weight width {w_bits} is neither 8 nor 16")
            rows.append((n_in, n_out, w_bits, shift, acc32))
        shapes.append(rows)

    def take(nbytes: int) -> int:
        """Claim nbytes at off and the zero padding after them; returns their offset."""
        nonlocal off
        end = off + nbytes + (-(off + nbytes) % 8)
        if off + nbytes > total or end > total:
            raise bad("ERR_SIZE", "array runs past the declared length")
        if any(data[off + nbytes:end]):
            raise bad("ERR_RANGE", "non-zero padding between arrays")
        start, off = off, end
        return start

    def array(dtype: str, count: int) -> np.ndarray:
        start = take(np.dtype(dtype).itemsize * count)
        return np.frombuffer(data, dtype=dtype, count=count, offset=start).astype(np.int64)

    take(0)  # the layer table's padding
    taps = array("<i2", int(p["n_taps"]))  # type: ignore[arg-type]
    nets = []
    for rows in shapes:
        layers = []
        for n_in, n_out, w_bits, shift, acc32 in rows:
            w = array("<i2" if w_bits == 16 else "i1", n_in * n_out).reshape(n_out, n_in)
            layers.append(QLayer(w, w_bits, array("<i8", n_out), array("<i4", n_out), shift,
                                 acc32=bool(acc32)))
        nets.append(layers)
    if off != total:
        raise bad("ERR_SIZE", f"declared length {total} differs from the {off} bytes the shapes imply")
    q = QModel.from_params(p, taps, nets)
    try:
        q.check()
    except ModelCheckError as exc:
        raise bad(exc.code, str(exc)) from exc
    return q


def blob_path(model: str | Path) -> Path:
    """``model`` may be a model directory (its model.fbgm) or a blob file."""
    p = Path(model)
    return p / FILE_NAME if p.is_dir() else p


def load_model_blob(model: str | Path, float_model: Any = None) -> QModel:
    """Read and parse the blob of a model directory (or a blob file).

    A directory's blob must have been exported from its float model
    (:func:`fbgforce.model.modeldir.check_export`; ``float_model``: that model, if loaded already).
    """
    from fbgforce.model.modeldir import check_export

    p = blob_path(model)
    if not p.is_file():
        raise InputError("no fixed-point model blob; run 'fbgforce export --model DIR' first",
                         path=str(p))
    q = from_bytes(p.read_bytes(), path=str(p))
    if Path(model).is_dir():
        check_export(model, float_model)
    return q
