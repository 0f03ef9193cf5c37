"""One verdict: the C loader and the Python reader accept and refuse the same blobs, with the
same code, on a seeded mutation campaign (fbgforce.export.mutate)."""
from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from fbgforce import contract
from fbgforce.model import artifact as fm
from fbgforce.export import blob, mutate
from fbgforce.export.quantize import calibrate, quantize

c_verdict, py_verdict = mutate.c_verdict, mutate.python_verdict


def small_blob(random_model_factory, random_walk_factory, bits: int = 16) -> bytes:
    """A small model with every kind of memory, quantised from a random walk."""
    mem = fm.Memory(ema_shifts=(3, 7), ema_gains=(2, 0), play_widths=(0.05,), play_gains=(3,),
                    loc_shift=4)
    model = random_model_factory(5, sizes=((6, 5), (7,), (5, 4)), n_taps=5, sigma=1.5, memory=mem)
    wl = random_walk_factory(model, 600, 1)
    q, _ = quantize(model, calibrate(model, [(wl, model.baseline_nm)]), bits=bits)
    return blob.to_bytes(q)


@pytest.mark.parametrize("bits", [16, 8])
def test_c_and_python_give_every_mutant_the_same_verdict(random_model_factory,
                                                         random_walk_factory, bits):
    data = small_blob(random_model_factory, random_walk_factory, bits)
    assert c_verdict(data) == py_verdict(data) == "FBG_OK"
    seen: Counter[str] = Counter()
    n = 6000
    for i, (kind, mutant) in enumerate(mutate.mutants(data, n, seed=bits)):
        c, py = c_verdict(mutant), py_verdict(mutant)
        assert c == py, f"mutant {i} ({kind}): C {c}, Python {py}"
        seen[c] += 1
    # The campaign reaches deep into the checks, not only the CRC.
    for code in ("FBG_OK", "FBG_ERR_TRUNCATED", "FBG_ERR_VERSION", "FBG_ERR_CRC",
                 "FBG_ERR_SHAPE", "FBG_ERR_RANGE", "FBG_ERR_SIZE", "FBG_ERR_BOUND"):
        assert seen[code] > 0, (code, seen)


def test_reader_returns_every_parameter_the_writer_wrote(random_model_factory, random_walk_factory):
    mem = fm.Memory(ema_shifts=(3, 7), play_widths=(0.05,), weights=(0.5, -0.25, 0.125, 1.0))
    model = random_model_factory(6, sizes=((6,), (5,), (4,)), n_taps=5, sigma=1.5, memory=mem)
    q, _ = quantize(model, calibrate(model, [(random_walk_factory(model, 400, 2), model.baseline_nm)]))
    back = blob.from_bytes(blob.to_bytes(q))
    assert back.params() == q.params()
    assert all(np.array_equal(a.w, b.w) and np.array_equal(a.bias, b.bias) and np.array_equal(a.mult, b.mult)
               for na, nb in zip(q.nets, back.nets) for a, b in zip(na, nb))


def test_documented_zero_fields_are_checked(random_model_factory, random_walk_factory):
    data = bytearray(small_blob(random_model_factory, random_walk_factory))
    flags = bytearray(data)
    flags[6] = 1
    assert c_verdict(mutate.fix_crc(flags)) == py_verdict(mutate.fix_crc(flags)) == "FBG_ERR_VERSION"
    # The parameter block's padding (none while the fields fill it to a multiple of 8).
    for pos in range(contract.HEADER.size + contract.PARAMS_STRUCT.size, contract.PARAMS_END):
        pad = bytearray(data)
        pad[pos] = 1
        assert c_verdict(mutate.fix_crc(pad)) == py_verdict(mutate.fix_crc(pad)) == "FBG_ERR_RANGE"
    # The last entry of the last field, just beyond its range.
    import struct

    f = contract.PARAMS[-1]
    fmt, _, size = contract.CTYPES[f.ctype]
    lo, _hi = contract.CTYPE_RANGE[f.ctype]
    value = f.lo - 1 if f.lo > lo else f.hi + 1
    last = bytearray(data)
    struct.pack_into("<" + fmt, last, contract.HEADER.size + contract.PARAMS_STRUCT.size - size, value)
    assert c_verdict(mutate.fix_crc(last)) == py_verdict(mutate.fix_crc(last)) == "FBG_ERR_RANGE"


def test_extreme_values_that_once_split_the_readers(random_model_factory, random_walk_factory):
    """A bias of INT64_MIN and a multiplier of INT32_MIN: both readers refuse both."""
    data = small_blob(random_model_factory, random_walk_factory)
    (taps, *layers) = mutate.array_slots(data)
    import struct

    w, bias, mult = layers[0], layers[1], layers[2]
    for off, fmt, value in ((bias[0], "<q", -2**63), (mult[0], "<i", -2**31)):
        buf = bytearray(data)
        struct.pack_into(fmt, buf, off, value)
        mutant = mutate.fix_crc(buf)
        assert c_verdict(mutant) == py_verdict(mutant) != "FBG_OK"
    del taps, w
