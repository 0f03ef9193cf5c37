"""The C library itself: Makefile targets, no-float proof, blob validation error codes, the
generated C model, the float build, the Python wrapper and the 1 kHz latency budget."""
from __future__ import annotations

import shutil
import statistics
import struct
import subprocess
import time
import zlib
import os
from pathlib import Path

import numpy as np
import pytest

from fbgforce import contract

from fbgforce.export import blob, intref
from fbgforce.pybind import (ERRORS, AlignError, BadMagicError, CrcError, FloatRuntime, Runtime,
                             RuntimeCError, ShapeError, SizeError, TruncatedError, VersionError,
                             ffi, lib)

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ROOT / "runtime_c"
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2"]


def _make(*args: str, cwd: Path = RUNTIME) -> subprocess.CompletedProcess:
    return subprocess.run(["make", "-s", "-C", str(cwd), *args], capture_output=True, text=True)


@pytest.fixture(scope="module")
def blob_bytes(small_exported_dir) -> bytes:
    return (small_exported_dir / "model.fbgm").read_bytes()


def _load(data: bytes, offset: int = 0, length: int | None = None) -> int:
    """fbg_model_from_blob on ``data`` placed ``offset`` bytes into an aligned buffer."""
    buf = ffi.new("uint64_t[]", (len(data) + offset + 15) // 8)
    base = ffi.cast("uint8_t *", buf) + offset
    ffi.memmove(base, data, len(data))
    m = ffi.new("fbg_model *")
    return lib.fbg_model_from_blob(m, base, len(data) if length is None else length)


def _recrc(data: bytearray) -> bytes:
    total = struct.unpack_from("<I", data, 8)[0]
    struct.pack_into("<I", data, 12, zlib.crc32(bytes(data[16:total])) & 0xFFFFFFFF)
    return bytes(data)


@pytest.mark.slow
def test_make_library_install_and_check_nofloat(tmp_path):
    build = tmp_path / "build"
    r = _make(f"BUILD={build}", "all")
    assert r.returncode == 0, r.stderr
    assert (build / "libfbgforce.a").is_file()
    r = _make(f"BUILD={build}", f"PREFIX={tmp_path / 'inst'}", "install")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "inst/include/fbgforce.h").is_file()
    assert (tmp_path / "inst/lib/libfbgforce.a").is_file()
    r = _make(f"BUILD={build}", "check-nofloat")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "check-nofloat: OK" in r.stdout
    # The check can fail: a fixed-point source that uses a double is caught.
    bad = tmp_path / "fbg_bad.c"
    bad.write_text('#include "fbgforce.h"\nint32_t fbg_bad(int32_t x);\n'
                   "int32_t fbg_bad(int32_t x) { return (int32_t)(x * 0.5); }\n")
    r = _make(f"BUILD={build}", f"FIXED_SRCS={bad}", "check-nofloat")
    assert r.returncode != 0 and "FAIL" in (r.stdout + r.stderr)


def test_blob_loads_and_error_codes(blob_bytes):
    assert _load(blob_bytes) == lib.FBG_OK
    # Every truncation is refused as TRUNCATED, never read past the end.
    for cut in list(range(0, 40)) + list(range(40, len(blob_bytes), 997)) + [len(blob_bytes) - 1]:
        assert _load(blob_bytes[:cut]) == lib.FBG_ERR_TRUNCATED, cut
    bad = bytearray(blob_bytes)
    bad[0:4] = b"XXXX"
    assert _load(bytes(bad)) == lib.FBG_ERR_BAD_MAGIC
    bad = bytearray(blob_bytes)
    bad[4] = 1                                   # an older format version
    assert _load(bytes(bad)) == lib.FBG_ERR_VERSION
    for pos in (16, 200, len(blob_bytes) // 2, len(blob_bytes) - 1):
        bad = bytearray(blob_bytes)
        bad[pos] ^= 0x10
        assert _load(bytes(bad)) == lib.FBG_ERR_CRC, pos
    assert _load(blob_bytes, offset=4) == lib.FBG_ERR_ALIGN
    # Consistent CRC but inconsistent content: layer widths, sizes, shifts.
    bad = bytearray(blob_bytes)
    table = contract.PARAMS_END                  # first layer-table entry
    struct.pack_into("<H", bad, table, 5)        # contact layer 0 n_in -> 5
    # (the arrays then shift: a size, shape or non-zero-padding refusal, whichever comes first)
    assert _load(_recrc(bad)) in (lib.FBG_ERR_SHAPE, lib.FBG_ERR_SIZE, lib.FBG_ERR_RANGE)
    bad = bytearray(blob_bytes)
    struct.pack_into("<H", bad, table + 2, 200)  # n_out above FBG_MAX_WIDTH
    assert _load(_recrc(bad)) == lib.FBG_ERR_SHAPE
    bad = bytearray(blob_bytes)
    bad[table + 5] = 63                          # shift out of range
    assert _load(_recrc(bad)) == lib.FBG_ERR_RANGE
    bad = bytearray(blob_bytes) + bytearray(8)
    struct.pack_into("<I", bad, 8, len(bad))     # declared longer than the shapes imply
    assert _load(_recrc(bad)) == lib.FBG_ERR_SIZE
    bad = bytearray(blob_bytes)
    struct.pack_into("<i", bad, 20, 5)           # baseline outside the 1000-2000 nm window
    assert _load(_recrc(bad)) == lib.FBG_ERR_RANGE
    m = ffi.new("fbg_model *")
    assert lib.fbg_model_from_blob(ffi.NULL, ffi.new("uint8_t[]", 16), 16) == lib.FBG_ERR_NULL
    assert lib.fbg_model_from_blob(m, ffi.NULL, 0) == lib.FBG_ERR_NULL
    assert lib.fbg_crc32(b"123456789", 9) == 0xCBF43926


def test_python_exceptions_per_code(blob_bytes, tmp_path):
    codes = {cls.code for cls in ERRORS.values()}
    assert len(codes) == len(ERRORS) == 16
    assert all(issubclass(cls, RuntimeCError) for cls in ERRORS.values())
    cases = [(blob_bytes[:10], TruncatedError), (b"XXXX" + blob_bytes[4:], BadMagicError),
             (blob_bytes[:4] + bytes([contract.LIMIT["BLOB_VERSION"] + 1]) + blob_bytes[5:], VersionError),
             (blob_bytes[:-1] + bytes([blob_bytes[-1] ^ 1]), CrcError)]
    for data, exc in cases:
        with pytest.raises(exc):
            Runtime(data)
    bad = bytearray(blob_bytes)
    struct.pack_into("<H", bad, contract.PARAMS_END + 2, 200)
    with pytest.raises(ShapeError):
        Runtime(_recrc(bad))
    bad = bytearray(blob_bytes) + bytearray(8)
    struct.pack_into("<I", bad, 8, len(bad))
    with pytest.raises(SizeError):
        Runtime(_recrc(bad))
    assert AlignError.code == lib.FBG_ERR_ALIGN
    # The pure-Python reader refuses the same files with a located InputError.
    from fbgforce.errors import InputError

    p = tmp_path / "bad.fbgm"
    p.write_bytes(blob_bytes[:-1] + bytes([blob_bytes[-1] ^ 1]))
    with pytest.raises(InputError, match="CRC"):
        blob.load_model_blob(p)


def test_blob_roundtrip(blob_bytes):
    q = blob.from_bytes(blob_bytes)
    assert blob.to_bytes(q) == blob_bytes


_DRIVER = r"""
#include <stdio.h>
#include "fbgforce.h"
#include "fbgforce_model.h"
#include "fbgforce_model_f32.h"
/* stdin: n x 5 int32 (fm), 5 int32 baseline first; stdout: fbg_output and fbgf_output per sample */
int main(void) {
    static fbg_state st; static fbgf_state fs; int32_t base[5], wl[5]; fbg_output o; fbgf_output fo;
    if (fbg_init(&st, &fbgforce_model, 0) != FBG_OK) return 3;
    if (fbgf_init(&fs, &fbgforce_model_f32, 0) != FBG_OK) return 4;
    if (fread(base, sizeof base, 1, stdin) != 1) return 5;
    if (fbg_set_baseline(&st, base) != FBG_OK || fbgf_set_baseline(&fs, base) != FBG_OK) return 6;
    while (fread(wl, sizeof wl, 1, stdin) == 1) {
        if (fbg_step(&st, wl, &o) != FBG_OK || fbgf_step(&fs, wl, &fo) != FBG_OK) return 7;
        fwrite(&o, sizeof o, 1, stdout); fwrite(&fo, sizeof fo, 1, stdout);
    }
    return 0;
}
"""


@pytest.mark.slow
def test_generated_c_model_matches_blob_and_float(small_exported_dir, small_dataset_path, tmp_path):
    """Firmware path: generated const model + libfbgforce, compiled with the strict flags,
    gives the same bits as the blob through the integer reference; the generated float model
    gives what the float build gives through the wrapper."""
    from fbgforce.recordings import dataset
    from fbgforce.export.exporter import recording_baseline

    cdir = small_exported_dir / "c"
    (tmp_path / "main.c").write_text(_DRIVER)
    exe = tmp_path / "golden"
    srcs = sorted(str(p) for p in (RUNTIME / "src").glob("*.c"))
    cmd = ["gcc", *CFLAGS, f"-I{RUNTIME / 'include'}", f"-I{cdir}", str(cdir / "fbgforce_model.c"),
           str(cdir / "fbgforce_model_f32.c"), *srcs, str(tmp_path / "main.c"), "-o", str(exe)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    ds = dataset.load(small_dataset_path).subset(slice(0, 4000))
    base = intref.nm_to_fm(recording_baseline(ds))
    wl = intref.nm_to_fm(ds.wl_nm)
    r = subprocess.run([str(exe)], input=base.astype("<i4").tobytes() + wl.astype("<i4").tobytes(),
                       capture_output=True)
    assert r.returncode == 0
    osz, fsz = ffi.sizeof("fbg_output"), ffi.sizeof("fbgf_output")
    rec = np.frombuffer(r.stdout, dtype=np.dtype([("o", "V%d" % osz), ("f", "V%d" % fsz)]))
    from fbgforce.pybind import _C_FOUTPUT, _C_OUTPUT

    c_fixed = np.frombuffer(rec["o"].tobytes(), dtype=_C_OUTPUT)
    c_float = np.frombuffer(rec["f"].tobytes(), dtype=_C_FOUTPUT)
    ref = intref.run(blob.load_model_blob(small_exported_dir), wl, base)
    for k in contract.OUTPUT_FIELDS:
        assert np.array_equal(np.asarray(c_fixed[k], dtype=np.int64), ref[k]), k
    fr = FloatRuntime(small_exported_dir)
    fr.set_baseline(base)
    py_float = fr.run(wl)
    assert np.array_equal(c_float["contact"].astype(bool), py_float["contact"])
    assert np.allclose(c_float["force_N"], np.nan_to_num(py_float["force_N"]), atol=1e-4)


def test_cfloat_matches_float_model(small_exported_dir, small_dataset_path):
    from fbgforce.recordings import dataset
    from fbgforce.model import floatref, modeldir
    from fbgforce.export.exporter import recording_baseline

    ds = dataset.load(small_dataset_path)
    base = recording_baseline(ds)
    model = modeldir.load(small_exported_dir)
    ref = floatref.predict(model, ds.wl_nm, base)
    fr = FloatRuntime(model)
    fr.set_baseline(base)
    out = fr.run(ds.wl_nm)
    assert (out["contact"] != ref["contact"]).mean() < 1e-3
    both = out["contact"] & ref["contact"]
    assert np.abs(out["force_N"][both] - ref["force_N"][both]).max() < 1e-3
    assert np.abs(out["x_mm"][both] - ref["x_mm"][both]).max() < 1e-3
    assert np.allclose(out["p_contact"], ref["p_contact"], atol=1e-4)


def test_float_params_fill_the_float_model_for_codegen_and_binding(small_exported_dir):
    """One assembly of the fbgf_model parameters (HierarchicalModel.float_params): every
    contract field, at its length, and the binding's struct holds exactly those values."""
    from fbgforce.model import modeldir as fm

    model = fm.load(small_exported_dir)
    params = model.float_params(123456, 70.0, 3)
    assert list(params) == [f.name for f in contract.FLOAT_PARAMS]
    rt = FloatRuntime(model, jump_nm=0.123456, overload_N=70.0, stuck_samples=3)
    for f in contract.FLOAT_PARAMS:
        value = getattr(rt._model, f.name)
        got = list(value) if f.count > 1 else [value]
        want = params[f.name] if f.count > 1 else [params[f.name]]
        assert len(want) == f.count, f.name
        assert np.allclose(np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64),
                           rtol=1e-6, atol=0), f.name


def test_wrapper_units_and_step(small_exported_dir, small_dataset_path):
    from fbgforce.recordings import dataset

    ds = dataset.load(small_dataset_path).subset(slice(0, 1500))
    rt = Runtime(small_exported_dir)
    rt.tare(ds.wl_nm[:200])
    batch = rt.run(ds.wl_nm)
    rt2 = Runtime(small_exported_dir / "model.fbgm")
    rt2.tare(intref.nm_to_fm(ds.wl_nm[:200]))          # int input is fm
    steps = np.array([rt2.step(w) for w in ds.wl_nm], dtype=batch.dtype)
    for k in batch.dtype.names:
        assert np.array_equal(steps[k], batch[k], equal_nan=k.endswith("_mm")), k
    c = batch["contact"]
    assert np.all(np.isnan(batch["x_mm"][~c])) and np.all(batch["force_N"][~c] == 0)
    assert np.allclose(batch["force_N"][c], batch["force_mN"][c] / 1000.0)
    # NaN (a lost peak) is a sensor fault, not an exception.
    wl = ds.wl_nm[:30].copy()
    wl[10, 0] = np.nan
    out = rt.run(wl)
    assert out["status"][10] & lib.FBG_STATUS_SENSOR_FAULT


@pytest.mark.parametrize("engine", ["float", "onnx", "fixed", "cfloat", "intref"])
def test_every_engine_gates_outputs_by_the_one_rule(engine, small_exported_dir, small_dataset_path):
    """No contact -> force 0 and location NaN, contact -> a finite location, on every engine
    (fbgforce.units.gate_outputs, the one place the rule is written)."""
    from fbgforce.recordings import dataset
    from fbgforce.evaluation.engines import run_engine
    from fbgforce.export.exporter import recording_baseline
    from fbgforce.units import gate_outputs

    ds = dataset.load(small_dataset_path).subset(slice(0, 3000))
    out = run_engine(engine, small_exported_dir, None, ds.wl_nm, recording_baseline(ds))
    c = out["contact"]
    assert c.any() and (~c).any()
    assert np.all(out["force_N"][~c] == 0.0)
    assert np.all(np.isnan(out["x_mm"][~c])) and np.all(np.isnan(out["y_mm"][~c]))
    assert np.all(np.isfinite(out["x_mm"][c])) and np.all(np.isfinite(out["y_mm"][c]))
    assert gate_outputs(False, 3.0, 1.0, 2.0)[0] == 0.0
    assert gate_outputs(True, 3.0, 1.0, 2.0) == (3.0, 1.0, 2.0)


def test_latency_inside_1khz_budget(small_exported_dir, small_dataset_path):
    """Median step time over 10,000 samples, through Python and in C (batch). The figures are
    printed (pytest -s); only the 1 kHz budget (1000 us) is asserted."""
    from fbgforce.recordings import dataset

    ds = dataset.load(small_dataset_path)
    wl = intref.nm_to_fm(ds.wl_nm[:10_000])
    rt = Runtime(small_exported_dir)
    rt.set_baseline(wl[0])
    times = []
    for row in wl:
        t0 = time.perf_counter()
        rt.step(row)
        times.append(time.perf_counter() - t0)
    py_us = statistics.median(times) * 1e6
    batch = []
    for _ in range(5):
        rt.reset()
        t0 = time.perf_counter()
        rt.run_raw(wl)
        batch.append((time.perf_counter() - t0) / len(wl))
    c_us = statistics.median(batch) * 1e6
    print(f"\nlatency: Runtime.step median {py_us:.1f} us/sample (Python wrapper), "
          f"fbg_run batch median {c_us:.2f} us/sample (C), budget 1000 us")
    assert py_us < 1000.0 and c_us < 1000.0


def test_float_build_has_its_own_objects():
    """The Makefile keeps the float build out of check-nofloat by name: fbgf_*.c only."""
    fixed = sorted(p.name for p in (RUNTIME / "src").glob("fbg_*.c"))
    floats = sorted(p.name for p in (RUNTIME / "src").glob("fbgf_*.c"))
    assert floats and fixed and not set(fixed) & set(floats)
    assert shutil.which("make")


@pytest.mark.slow
def test_generated_c_int8_random_model(random_model_factory, random_walk_factory, tmp_path):
    """int8 weights and odd shapes through the generated-C path, bit-exact."""
    from fbgforce.export import codegen
    from fbgforce.export import quantize as qz

    model = random_model_factory(11, sizes=((17,), (128, 3), (5, 9, 2)), n_taps=7, sigma=2.0)
    wl = random_walk_factory(model, 1500, seed=11)
    q, _ = qz.quantize(model, qz.calibrate(model, [(wl, model.baseline_nm)]), bits=8)
    cdir = tmp_path / "c"
    codegen.write_c(q, model, cdir, "fbgforce")
    (tmp_path / "main.c").write_text(_DRIVER)
    exe = tmp_path / "golden8"
    srcs = sorted(str(p) for p in (RUNTIME / "src").glob("*.c"))
    r = subprocess.run(["gcc", *CFLAGS, f"-I{RUNTIME / 'include'}", f"-I{cdir}",
                        str(cdir / "fbgforce_model.c"), str(cdir / "fbgforce_model_f32.c"), *srcs,
                        str(tmp_path / "main.c"), "-o", str(exe)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    base = intref.nm_to_fm(model.baseline_nm)
    wl_fm = intref.nm_to_fm(wl)
    r = subprocess.run([str(exe)], input=base.astype("<i4").tobytes() + wl_fm.astype("<i4").tobytes(),
                       capture_output=True)
    assert r.returncode == 0
    from fbgforce.pybind import _C_OUTPUT

    osz, fsz = ffi.sizeof("fbg_output"), ffi.sizeof("fbgf_output")
    rec = np.frombuffer(r.stdout, dtype=np.dtype([("o", "V%d" % osz), ("f", "V%d" % fsz)]))
    c_fixed = np.frombuffer(rec["o"].tobytes(), dtype=_C_OUTPUT)
    ref = intref.run(q, wl_fm, base)
    for k in contract.OUTPUT_FIELDS:
        assert np.array_equal(np.asarray(c_fixed[k], dtype=np.int64), ref[k]), k


def test_generated_model_c_carries_its_blob_crc(small_exported_dir):
    """The generated const model has model.fbgm's CRC in blob_crc, the identity fbg_step checks
    (FBG_ERR_MODEL_CHANGED), as fbg_model_from_blob gives a loaded one."""
    crc = int.from_bytes((small_exported_dir / "model.fbgm").read_bytes()[12:16], "little")
    text = (small_exported_dir / "c" / "fbgforce_model.c").read_text()
    assert f"/* blob_crc: model.fbgm's */ 0x{crc:08X}u\n}};" in text
    m = ffi.new("fbg_model *")
    data = (small_exported_dir / "model.fbgm").read_bytes()
    buf = ffi.new("uint64_t[]", (len(data) + 7) // 8)
    ffi.memmove(buf, data, len(data))
    assert lib.fbg_model_from_blob(m, ffi.cast("uint8_t *", buf), len(data)) == lib.FBG_OK
    assert m.blob_crc == crc


def test_generated_model_c_compiles_as_cxx_and_c99(small_exported_dir):
    """The generated model sources are plain positional initialisers in declaration order, so a
    C++ firmware (which has no C99 designated initialisers before C++20) can compile them."""
    import shutil
    import subprocess

    cxx, cc = shutil.which("g++") or shutil.which("clang++"), shutil.which("cc")
    if cxx is None or cc is None:
        pytest.skip("needs a C and a C++ compiler")
    cdir = small_exported_dir / "c"
    inc = str(ROOT / "runtime_c" / "include")
    for src in sorted(cdir.glob("*.c")):
        for cmd in ([cxx, "-std=c++11", "-x", "c++"], [cc, "-std=c99"]):
            r = subprocess.run([*cmd, "-Wall", "-Wextra", "-Werror", "-pedantic", "-I", inc,
                                "-I", str(cdir), "-c", str(src), "-o", os.devnull],
                               capture_output=True, text=True)
            assert r.returncode == 0, (cmd, src.name, r.stderr)
