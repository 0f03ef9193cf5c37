"""The one contract (fbgforce.contract): generated files are fresh, and the compiled library,
the blob codec and the numpy records agree with the spec field for field."""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce import contract
from fbgforce.contract import render
from fbgforce._runtime import ffi, lib


def test_generated_files_are_fresh():
    stale = render.stale_files()
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


@pytest.mark.parametrize("struct, fields", [("fbg_state", contract.STATE),
                                            ("fbgf_state", contract.FLOAT_STATE)])
def test_state_structs_are_the_spec_in_order(struct, fields):
    """The compiled states hold the spec's members in its order (the order is the layout),
    each of its type and dimensions, and nothing else: sizes add up to the struct."""
    c = ffi.new(f"{struct} *")
    offsets = [ffi.offsetof(struct, f.name) for f in fields]
    assert offsets == sorted(offsets)
    end = 0
    for f in fields:
        item = ffi.sizeof(f.ctype.replace("const ", "").replace(" *", "*") if f.ctype.endswith("*")
                          else f.ctype)
        size = ffi.sizeof(ffi.typeof(getattr(c[0], f.name))) if f.dims else item
        assert size == item * f.count(), f.name
        assert ffi.offsetof(struct, f.name) >= end, f.name
        end = ffi.offsetof(struct, f.name) + size
    assert ffi.sizeof(struct) - end < 8   # trailing padding only
    assert ffi.offsetof(struct, "act") % 8 == 0


def test_memory_kinds_size_the_limits_and_the_states():
    assert contract.LIMIT["MAX_INPUTS"] == contract.N_STRAIN + sum(k.limit for k in contract.MEMORY_KINDS)
    for kind in contract.MEMORY_KINDS:
        assert getattr(lib, f"FBG_MAX_{kind.name.upper()}") == kind.limit
        for struct in ("fbg_state", "fbgf_state"):
            assert ffi.sizeof(ffi.typeof(getattr(ffi.new(f"{struct} *")[0], kind.name))) == 4 * kind.limit
    assert contract.MEMORY_STATES == tuple(k.name for k in contract.MEMORY_KINDS) + ("loc",)


#: A third kind of memory state, as a newcomer would describe it in MEMORY_KINDS.
THIRD_KIND = contract.MemoryKind(
    "creep", 2, "creep memory states", "Q(z_frac)",
    (contract.MemoryParam("rate", "uint8_t", 1, 9, "creep rate", "uint8_t"),
     contract.MemoryParam("gain", "uint8_t", 0, contract.MAX_MEM_GAIN, "feature gain", "uint8_t",
                          optional=True),
     contract.MemoryParam("span", "int16_t", 0, contract.SAT16, "span, Q(z_frac)", "float")),
    noun="creep states", label="creep")


def test_a_memory_kind_is_described_once(monkeypatch):
    """A kind added to MEMORY_KINDS brings its parameter fields (both blocks: count, arrays
    of its limit, ranges, the entries past the count held at 0), the C dispatch over the kinds,
    the feature count and the float build's checks of its parameters."""
    monkeypatch.setattr(contract, "MEMORY_KINDS", contract.MEMORY_KINDS + (THIRD_KIND,))
    fixed = {f.name: f for f in contract.memory_params()}
    assert fixed["n_creep"] == contract.Field("n_creep", "uint8_t", 1, 0, 2, "ERR_SHAPE",
                                              doc="creep memory states")
    assert fixed["creep_rate"] == contract.Field("creep_rate", "uint8_t", 2, 1, 9, active="n_creep",
                                                 doc="creep rate")
    assert (fixed["creep_span"].ctype, fixed["creep_span"].hi) == ("int16_t", contract.SAT16)
    floats = {f.name: f for f in contract.float_memory_params()}
    assert (floats["creep_span"].ctype, floats["creep_span"].count) == ("float", 2)
    assert [f.name for f in contract.memory_params()] == [f.name for f in contract.float_memory_params()]
    header = render.contract_header_text()
    assert "#define FBG_MEMORY_KINDS(X) X(ema, EMA) X(play, PLAY) X(creep, CREEP)" in header
    assert "(m)->n_creep)" in header
    source = render.float_source_text()
    assert "m->n_creep > FBG_MAX_CREEP" in source
    assert "{ uint8_t v = m->creep_rate[k]; if (v < 1 || v > 9) return FBG_ERR_RANGE; }" in source
    assert "{ float v = m->creep_span[k]; if (!(v >= 0.0f) || v - v != 0.0f)" in source


def test_every_engine_has_each_kinds_update_rule():
    """The per-kind arithmetic the dispatch reaches by name exists in every engine: the float
    reference and the integer reference tables, and the C functions FBG_MEMORY_KINDS calls."""
    from fbgforce.model import artifact, floatref
    from fbgforce.export import intref

    names = [k.name for k in contract.MEMORY_KINDS]
    assert list(floatref.FLOAT_MEMORY) == names and list(intref.INT_MEMORY) == names
    src = render.ROOT / "runtime_c" / "src"
    for kind in contract.MEMORY_KINDS:
        assert f"static unsigned {kind.name}_features(" in (src / "fbg_stage_memory.c").read_text()
        assert f"static unsigned {kind.name}_features_f(" in (src / "fbgf_float.c").read_text()
        assert f"static unsigned {kind.name}_features_avx2(" in (src / "fbg_simd_x86_stages.c").read_text()
        assert kind.gain.optional and kind.counted_by.name != "gain"
        for param in kind.params:
            assert hasattr(artifact.Memory(), artifact.memory_attr(kind, param))


def test_params_codec_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(300):
        block = bytes(rng.integers(0, 256, contract.PARAMS_STRUCT.size, dtype=np.uint8))
        block += b"\0" * (contract.PARAMS_SIZE - len(block))
        assert contract.encode_params(contract.decode_params(block)) == block
