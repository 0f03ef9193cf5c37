"""The C library as a product: the ways a firmware or host project consumes it.

A small consumer program is built outside the repository three ways (CMake ``find_package``
from an installed prefix, pkg-config over ``make install``, the single-file amalgamation),
linked with the C that ``fbgforce export`` generated for the shared small model, run on golden
vectors, and its outputs compared bit for bit with the Python integer reference. Also: the
amalgamation is fresh, the arm-none-eabi toolchain file cross-compiles, the header's "typical
use" compiles, and the sizes docs/runtime.md quotes are the sizes the code has.

cmake, pkg-config and a C compiler are needed; without them the tests SKIP, except under
CI=true, where a missing tool is a FAILURE.
"""
from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import require_tools
from fbgforce.export import blob, intref

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ROOT / "runtime_c"
STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic"]
#: Golden-vector samples per consumer run: contact and no-contact, a fraction of a second.
SAMPLES = 3000
OUTPUT_FIELDS = ("force_mN", "x_um", "y_um", "contact_margin_q8", "status", "contact_conf_q15",
                 "contact")


def _require(*tools: str) -> None:
    require_tools(*tools, install="cmake pkg-config gcc make")


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, **kw)
    assert r.returncode == 0, f"{' '.join(map(str, cmd))}\n{r.stdout}\n{r.stderr}"
    return r


def _amalgamate_module():
    spec = importlib.util.spec_from_file_location("fbg_amalgamate", RUNTIME / "amalgamate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# The consumer: generated model + library, golden vectors on stdin, fbg_output records out.
CONSUMER_C = r"""
#include <stdio.h>
#include "fbgforce.h"
#include "fbgforce_model.h"
/* stdin: 5 int32 baseline (fm), then n x 5 int32 samples (fm); stdout: one fbg_output each. */
int main(void) {
    static fbg_state st; int32_t base[FBG_N_CHANNELS], wl[FBG_N_CHANNELS]; fbg_output o;
    if (fbg_version() != (((uint32_t)FBG_VERSION_MAJOR << 16) | ((uint32_t)FBG_VERSION_MINOR << 8)
                          | FBG_VERSION_PATCH)) return 2;
    if (fbg_init(&st, &fbgforce_model, 0) != FBG_OK) return 3;
    if (fread(base, sizeof base, 1, stdin) != 1) return 4;
    if (fbg_set_baseline(&st, base) != FBG_OK) return 5;
    while (fread(wl, sizeof wl, 1, stdin) == 1) {
        if (fbg_step(&st, wl, &o) != FBG_OK) return 6;
        fwrite(&o, sizeof o, 1, stdout);
    }
    return 0;
}
"""

CONSUMER_CMAKE = """cmake_minimum_required(VERSION 3.13)
project(fbg_consumer C)
find_package(fbgforce ${FBG_VERSION} REQUIRED CONFIG)
file(GLOB MODEL_SOURCES "${MODEL_C_DIR}/*.c")
add_executable(consumer main.c ${MODEL_SOURCES})
target_include_directories(consumer PRIVATE "${MODEL_C_DIR}")
target_link_libraries(consumer PRIVATE fbgforce::fbgforce)
"""


@pytest.fixture(scope="module")
def golden(small_exported_dir, small_dataset_path):
    """(input bytes for the consumer, integer-reference outputs, generated C directory)."""
    from fbgforce.recordings import dataset
    from fbgforce.export.exporter import recording_baseline

    ds = dataset.load(small_dataset_path).subset(slice(0, SAMPLES))
    base = intref.nm_to_fm(recording_baseline(ds))
    wl = intref.nm_to_fm(ds.wl_nm)
    ref = intref.run(blob.load_model_blob(small_exported_dir), wl, base)
    assert ref["contact"].any() and not ref["contact"].all()
    stdin = base.astype("<i4").tobytes() + wl.astype("<i4").tobytes()
    return stdin, ref, small_exported_dir / "c"


def _check_consumer(exe: Path, golden) -> None:
    from fbgforce.pybind import _C_OUTPUT

    stdin, ref, _ = golden
    r = subprocess.run([str(exe)], input=stdin, capture_output=True)
    assert r.returncode == 0, f"consumer exit {r.returncode}"
    out = np.frombuffer(r.stdout, dtype=_C_OUTPUT)
    assert len(out) == SAMPLES
    for k in OUTPUT_FIELDS:
        assert np.array_equal(np.asarray(out[k], dtype=np.int64), ref[k]), k


def _library_version() -> str:
    """MAJOR.MINOR.PATCH as the built library reports it (fbg_version())."""
    from fbgforce.pybind import lib

    v = lib.fbg_version()
    return f"{v >> 16}.{(v >> 8) & 0xFF}.{v & 0xFF}"


def _model_sources(cdir: Path) -> list[Path]:
    return sorted(cdir.glob("*.c"))


@pytest.mark.slow
def test_consumer_cmake_find_package_from_installed_prefix(golden, tmp_path):
    _require("cmake", "cc")
    prefix = tmp_path / "prefix"
    _run(["cmake", "-S", RUNTIME, "-B", tmp_path / "lib-build", "-DCMAKE_BUILD_TYPE=Release"])
    _run(["cmake", "--build", tmp_path / "lib-build", "-j2"])
    _run(["cmake", "--install", tmp_path / "lib-build", "--prefix", prefix])
    assert (prefix / "lib/cmake/fbgforce/fbgforceConfig.cmake").is_file()
    assert (prefix / "include/fbgforce.h").is_file()
    app = tmp_path / "app"
    app.mkdir()
    (app / "main.c").write_text(CONSUMER_C)
    (app / "CMakeLists.txt").write_text(CONSUMER_CMAKE)
    _run(["cmake", "-S", app, "-B", app / "build", f"-DCMAKE_PREFIX_PATH={prefix}",
          f"-DFBG_VERSION={_library_version()}",
          f"-DMODEL_C_DIR={golden[2]}", f"-DCMAKE_C_FLAGS={' '.join(STRICT)}"])
    _run(["cmake", "--build", app / "build"])
    _check_consumer(app / "build" / "consumer", golden)
    # The same install also carries a relocatable pkg-config file.
    env = {**os.environ, "PKG_CONFIG_PATH": str(prefix / "lib/pkgconfig")}
    if shutil.which("pkg-config"):
        flags = _run(["pkg-config", "--cflags", "--libs", "fbgforce"], env=env).stdout.split()
        assert f"-I{prefix}/lib/pkgconfig/../../include" in flags


@pytest.mark.slow
def test_consumer_pkg_config_over_make_install(golden, tmp_path):
    _require("make", "pkg-config", "cc")
    prefix = tmp_path / "prefix"
    _run(["make", "-s", "-C", RUNTIME, f"BUILD={tmp_path / 'build'}", f"PREFIX={prefix}", "install"])
    pc = (prefix / "lib/pkgconfig/fbgforce.pc").read_text()
    assert f"prefix={prefix}" in pc and "@" not in pc
    env = {**os.environ, "PKG_CONFIG_PATH": str(prefix / "lib/pkgconfig")}
    version = _run(["pkg-config", "--modversion", "fbgforce"], env=env).stdout.strip()
    assert version == _library_version()
    flags = _run(["pkg-config", "--cflags", "--libs", "fbgforce"], env=env).stdout.split()
    (tmp_path / "main.c").write_text(CONSUMER_C)
    exe = tmp_path / "consumer"
    cdir = golden[2]
    _run(["cc", *STRICT, "-O2", f"-I{cdir}", tmp_path / "main.c", *_model_sources(cdir),
          *flags, "-o", exe])
    _check_consumer(exe, golden)


@pytest.mark.slow
def test_consumer_amalgamation(golden, tmp_path):
    _require("cc")
    amal = RUNTIME / "amalgamation"
    (tmp_path / "main.c").write_text(CONSUMER_C)
    exe = tmp_path / "consumer"
    cdir = golden[2]
    # Only the two files and the generated model, nothing else from the repository.
    inc = tmp_path / "fw"
    inc.mkdir()
    for name in ("fbgforce.c", "fbgforce.h"):
        shutil.copy(amal / name, inc / name)
    _run(["cc", *STRICT, "-O2", f"-I{inc}", f"-I{cdir}", inc / "fbgforce.c", tmp_path / "main.c",
          *_model_sources(cdir), "-o", exe])
    _check_consumer(exe, golden)


def test_amalgamation_is_fresh_and_covers_every_source():
    amalgamate = _amalgamate_module()
    stale = amalgamate.stale()
    assert not stale, (f"runtime_c/amalgamation/{', '.join(stale)} stale: run "
                       "`python runtime_c/amalgamate.py` and commit the result")
    text = (RUNTIME / "amalgamation" / "fbgforce.c").read_text()
    for src in sorted((RUNTIME / "src").glob("*.c")):
        assert f"/* ---- src/{src.name} ---- */" in text, src.name
    # The check can fail: a changed source makes the committed file stale.
    rendered = amalgamate.render()
    assert rendered["fbgforce.c"] == text


def test_amalgamation_refuses_header_without_guard(tmp_path, monkeypatch):
    amalgamate = _amalgamate_module()
    src, inc = tmp_path / "src", tmp_path / "include"
    src.mkdir()
    inc.mkdir()
    (inc / "fbgforce.h").write_text("#ifndef FBGFORCE_H\n#define FBGFORCE_H\n#endif\n")
    (src / "helper.h").write_text("int helper(void);\n")
    (src / "a.c").write_text('#include "helper.h"\nint helper(void) { return 1; }\n')
    monkeypatch.setattr(amalgamate, "HERE", tmp_path)
    monkeypatch.setattr(amalgamate, "SRC", src)
    monkeypatch.setattr(amalgamate, "INCLUDE", inc)
    with pytest.raises(SystemExit, match="no include guard"):
        amalgamate.render()
    (src / "helper.h").write_text("#ifndef HELPER_H\n#define HELPER_H\nint helper(void);\n#endif\n")
    assert "int helper(void) { return 1; }" in amalgamate.render()["fbgforce.c"]


def test_every_build_compiles_the_same_sources(tmp_path):
    """Makefile, CMake, the amalgamation and the Python extension all take every src/*.c, so
    a new source needs no edit anywhere."""
    _require("make", "cmake")
    expected = sorted(p.name for p in (RUNTIME / "src").glob("*.c"))
    r = _run(["make", "-s", "-n", "-C", RUNTIME, f"BUILD={tmp_path}", "lib"])
    assert sorted(re.findall(r"src/(\w+\.c)", r.stdout)) == expected
    _run(["cmake", "-S", RUNTIME, "-B", tmp_path / "cm"])
    listed = _run(["cmake", "--build", tmp_path / "cm", "--target", "help"]).stdout
    assert sorted(set(re.findall(r"src/(\w+)\.o", listed))) == [Path(n).stem for n in expected]
    assert [p.name for p in _amalgamate_module().sources()] == expected


@pytest.mark.target
def test_arm_none_eabi_toolchain_file_cross_compiles(tmp_path):
    _require("cmake")
    require_tools("arm-none-eabi-gcc", install="gcc-arm-none-eabi libnewlib-arm-none-eabi")
    build = tmp_path / "cm4"
    _run(["cmake", "-S", RUNTIME, "-B", build,
          f"-DCMAKE_TOOLCHAIN_FILE={RUNTIME / 'cmake' / 'arm-none-eabi.cmake'}",
          "-DFBG_USE_DSP=ON", "-DCMAKE_BUILD_TYPE=MinSizeRel"])
    _run(["cmake", "--build", build, "-j2"])
    lib = build / "libfbgforce.a"
    head = _run(["arm-none-eabi-objdump", "-f", lib]).stdout
    assert "elf32-littlearm" in head and "armv7e-m" in head
    # FBG_USE_DSP=ON reached the sources: the DSP kernels are in the archive.
    symbols = _run(["arm-none-eabi-nm", lib]).stdout
    assert "fbg_dsp_hidden" in symbols


def _typical_use_lines() -> list[str]:
    header = (RUNTIME / "include" / "fbgforce.h").read_text()
    block = header.split("Typical use (fixed point)", 1)[1].split("\n *\n", 1)[1]
    lines = []
    for line in block.splitlines():
        if not line.startswith(" *   "):
            break
        lines.append(line[len(" *   "):])
    return lines


def test_header_typical_use_compiles(tmp_path):
    _require("cc")
    lines = _typical_use_lines()
    assert any("fbg_step" in ln for ln in lines) and any("fbg_tare_add" in ln for ln in lines)
    (tmp_path / "use.c").write_text(
        '#include "fbgforce.h"\n'
        "const int32_t *read_peaks_fm(void);\n"
        "void control(int32_t force_mN, int32_t x_um, int32_t y_um);\n"
        "void typical_use(const uint8_t *blob, size_t blob_len);\n"
        "void typical_use(const uint8_t *blob, size_t blob_len) {\n"
        + "\n".join(lines) + "\n}\n")
    _run(["cc", *STRICT, f"-I{RUNTIME / 'include'}", "-c", tmp_path / "use.c",
          "-o", tmp_path / "use.o"])


@pytest.mark.slow
def test_runtime_md_call_sequence_compiles(golden, tmp_path):
    """The fixed-point call sequence docs/runtime.md shows, with the generated model header."""
    _require("cc")
    text = (ROOT / "docs" / "runtime.md").read_text()
    code = re.search(r"## Call sequence.*?```c\n(.*?)```", text, re.S).group(1)
    (tmp_path / "seq.c").write_text(
        "#include <stdint.h>\n"
        "const int32_t *read_peaks_fm(void);\n"
        "void control(int32_t force_mN, int32_t x_um, int32_t y_um);\n"
        "int setup(void);\nvoid isr_1khz(void);\n" + code)
    _run(["cc", *STRICT, f"-I{RUNTIME / 'include'}", f"-I{golden[2]}", "-c", tmp_path / "seq.c",
          "-o", tmp_path / "seq.o"])


# ---- docs/runtime.md quotes sizes; each must be what the code has -----------------------

def _paper_sized_quantized():
    """The int16 quantisation of a model with the paper's net sizes and the trainer's default
    causal filter (what docs/runtime.md quotes flash figures for)."""
    from conftest import make_random_model, make_random_walk

    from fbgforce.export import quantize as qz
    from fbgforce.trainer import preprocess as pp
    from fbgforce.trainer.params import PAPER_SIZES

    taps = pp.gaussian_taps("causal", pp.default_sigma(1000.0))
    model = make_random_model(0, sizes=(PAPER_SIZES["contact"], PAPER_SIZES["force"],
                                        PAPER_SIZES["location"]), n_taps=taps.size)
    model.preprocess.taps = taps
    wl = make_random_walk(model, 1000, seed=0)
    q, _ = qz.quantize(model, qz.calibrate(model, [(wl, model.baseline_nm)]), bits=16)
    return q


def _doc_figures() -> dict[str, tuple[int, str]]:
    """Name -> (number, the doc line it is on) for every size docs/runtime.md quotes."""
    text = (ROOT / "docs" / "runtime.md").read_text()
    found: dict[str, tuple[int, str]] = {}

    def number(s: str) -> int:
        return int(s.replace(",", ""))

    for line in text.splitlines():
        m = re.match(r"\|\s*`(fbgf?_\w+)`\s*\|\s*([\d,]+)\b", line)
        if m:
            found[m.group(1)] = (number(m.group(2)), line)
        m = re.match(r"\|\s*model arrays.*?\|\s*([\d,]+)\b", line)
        if m:
            found["const_bytes"] = (number(m.group(1)), line)
        m = re.match(r"\|\s*`model\.fbgm`.*?\|\s*([\d,]+)\b", line)
        if m:
            found["blob_bytes"] = (number(m.group(1)), line)
        m = re.search(r"static fbg_state st;\s*/\*\s*([\d,]+) bytes", line)
        if m:
            found["fbg_state (call sequence)"] = (number(m.group(1)), line)
    return found


def test_docs_runtime_sizes_match_the_code():
    import platform

    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip(f"docs/runtime.md quotes x86-64 sizes; this host is {platform.machine()}")
    from fbgforce.export.exporter import const_bytes
    from fbgforce.pybind import ffi, lib

    q = _paper_sized_quantized()
    actual = {
        "fbg_state": int(lib.fbg_state_size()),
        "fbg_state (call sequence)": int(lib.fbg_state_size()),
        "fbg_model": ffi.sizeof("fbg_model"),
        "fbgf_state": int(lib.fbgf_state_size()),
        "const_bytes": const_bytes(q),
        "blob_bytes": len(blob.to_bytes(q)),
    }
    documented = _doc_figures()
    # The compile-time limits the page quotes (`FBG_MAX_TAPS` 64, ...) are the header's.
    text = (ROOT / "docs" / "runtime.md").read_text()
    limits = re.findall(r"`(FBG_[A-Z_]+)` (\d+)", text)
    assert {name for name, _ in limits} >= {"FBG_MAX_TAPS", "FBG_MAX_WIDTH", "FBG_MAX_LAYERS"}
    for name, value in limits:
        actual[name] = int(getattr(lib, name))
        documented[name] = (int(value), f"`{name}` {value}")
    assert set(documented) >= set(actual), f"docs/runtime.md lost figures: {set(actual) - set(documented)}"
    wrong = [f"docs/runtime.md says {documented[k][0]} for {k}, the code has {v}: "
             f"update the line {documented[k][1].strip()!r}"
             for k, v in actual.items() if documented[k][0] != v]
    assert not wrong, "\n".join(wrong)
