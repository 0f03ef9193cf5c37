"""The one contract (fbgforce.contract): generated files are fresh, and the compiled library,
the blob codec and the numpy records agree with the spec field for field."""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce import contract
from fbgforce._runtime import ffi, lib


def test_generated_files_are_fresh():
    stale = contract.stale_files()
    assert not stale, f"regenerate with `python -m fbgforce.contract --write`: {stale}"


def test_limits_codes_and_flags_match_the_library():
    for name, (value, _doc) in contract.LIMITS.items():
        assert getattr(lib, f"FBG_{name}") == value, name
    for code in contract.ERRORS:
        assert getattr(lib, f"FBG_{code.name}") == code.value
        assert ffi.string(lib.fbg_status_str(code.value)).decode() == f"FBG_{code.name}"
    for flag in contract.STATUS:
        assert getattr(lib, f"FBG_STATUS_{flag.name}") == flag.value
    assert lib.fbg_version() == contract.VERSION_CODE


def test_python_package_reports_the_library_version():
    import fbgforce

    assert fbgforce.__version__ == contract.VERSION_STR


@pytest.mark.parametrize("struct, fields", [("fbg_output", contract.OUTPUT),
                                            ("fbgf_output", contract.FLOAT_OUTPUT)])
def test_output_records_match_the_c_structs(struct, fields):
    dt = np.dtype(contract.numpy_dtype(fields))
    assert dt.itemsize == ffi.sizeof(struct)
    for f in fields:
        assert dt.fields[f.name][1] == ffi.offsetof(struct, f.name), f.name


@pytest.mark.parametrize("struct, fields", [("fbg_model", contract.PARAMS),
                                            ("fbgf_model", contract.FLOAT_PARAMS)])
def test_parameter_structs_hold_every_field(struct, fields):
    c = ffi.new(f"{struct} *")
    for f in fields:
        if f.c_member:
            continue
        size = ffi.sizeof(ffi.typeof(getattr(c[0], f.name))) if f.count > 1 else None
        if f.count > 1:
            assert size == contract.CTYPES[f.ctype][2] * f.count, f.name


def test_params_codec_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(300):
        block = bytes(rng.integers(0, 256, contract.PARAMS_STRUCT.size, dtype=np.uint8))
        block += b"\0" * (contract.PARAMS_SIZE - len(block))
        assert contract.encode_params(contract.decode_params(block)) == block
