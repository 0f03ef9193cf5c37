"""The float build's dense-layer kernels (runtime_c/src/fbgf_dense.c): portable C, SSE2,
AVX2+FMA (x86-64, picked at run time) and NEON (aarch64, under qemu-aarch64).

Each kernel is compiled into a small C driver with the strict flags and run on a random model
with memory features over a random walk (contact and no contact). For every build:

* ``fbgf_run`` gives byte for byte what ``fbgf_step`` gives sample by sample (``fbgf_run``
  batches the nets of up to 16 samples);
* the bits do not depend on where the weights sit in memory (the same model copied to
  addresses off by one float gives the same bytes), nor on the run (two runs agree);
* the outputs follow the float64 model (``fbgforce.model.floatref.predict``) within the tolerance the
  float build is held to (docs/runtime.md, "Float build: speed"): contact decisions agree on
  all but 0.1 % of samples, force and location within 1e-3 of the output's scale, p_contact
  within 1e-4;
* the SIMD kernels differ from the portable one by float32 rounding only (within 1e-4 of the
  output's scale), and the cffi extension gives the bits of the build that picks the same
  kernel;
* on AVX2+FMA, the batch kernel with the samples in lanes (``fbgf_dense_lanes``, which
  ``fbgf_run`` uses) gives every sample of every layer shape (narrow and wide, rows not a
  multiple of the block) the bytes that ``fbgf_dense`` gives it alone, in whichever lane and
  with whatever the other lanes hold.

Tools: gcc (x86-64 builds), aarch64-linux-gnu-gcc and qemu-aarch64 (NEON); a missing tool
SKIPS, except under CI=true, where it FAILS.
"""
from __future__ import annotations

import platform
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import require_tools
from fbgforce import contract
from fbgforce.model import artifact, floatref
from fbgforce.export.codegen import float_source
from fbgforce.pybind import _C_FOUTPUT, FloatRuntime, to_fm

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ROOT / "runtime_c"
STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2"]
SAMPLES = 2500
#: Samples replayed under qemu-aarch64 (about 0.1 ms each, emulated).
QEMU_SAMPLES = 1000

DRIVER = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "fbgforce.h"
#include "fbgf_dense.h"
#include "simd_model_f32.h"

/* The model again, every array at an address one float past where a 32-byte aligned copy
 * would put it. */
static float pool[1 << 16];
static size_t used = 1;
static const float *moved(const float *src, size_t n)
{
    float *dst = pool + used;
    memcpy(dst, src, n * sizeof *src);
    used = (used + n + 7u) / 8u * 8u + 1u;
    return dst;
}

static int replay(const fbgf_model *m, const int32_t *wl, long n, fbgf_output *steps, fbgf_output *run)
{
    static fbgf_state st;
    long i;
    if (fbgf_init(&st, m, 0) != FBG_OK || fbgf_set_baseline(&st, wl) != FBG_OK) return 1;
    for (i = 0; i < n; ++i)
        if (fbgf_step(&st, wl + 5 * (i + 1), steps + i) != FBG_OK) return 1;
    if (fbgf_init(&st, m, 0) != FBG_OK || fbgf_set_baseline(&st, wl) != FBG_OK) return 1;
    return fbgf_run(&st, wl + 5, (size_t)n, run) != FBG_OK;
}

/* argv: wl.bin (baseline row, then samples), out.bin. stdout: kernel, run==steps, moved==same */
int main(int argc, char **argv)
{
    static const char *names[] = {"portable", "sse2", "avx2+fma", "neon"};
    static fbgf_model m2;
    fbgf_output *steps, *run, *steps2, *run2;
    int32_t *wl;
    long len, n;
    unsigned k, l;
    size_t bytes;
    FILE *f;
    if (argc != 3 || !(f = fopen(argv[1], "rb"))) return 2;
    fseek(f, 0, SEEK_END);
    len = ftell(f);
    rewind(f);
    wl = malloc((size_t)len);
    n = len / 20 - 1;
    bytes = sizeof *steps * (size_t)n;
    steps = malloc(bytes); run = malloc(bytes); steps2 = malloc(bytes); run2 = malloc(bytes);
    if (!wl || !steps || !run || !steps2 || !run2 || fread(wl, 1, (size_t)len, f) != (size_t)len) return 3;
    fclose(f);
    m2 = simd_model_f32;
    m2.taps = moved(m2.taps, m2.n_taps);
    for (k = 0; k < FBG_N_NETS; ++k)
        for (l = 0; l < m2.nets[k].n_layers; ++l) {
            fbgf_layer *ly = &m2.nets[k].layers[l];
            ly->w = moved(ly->w, (size_t)ly->n_in * ly->n_out);
            ly->b = moved(ly->b, ly->n_out);
        }
    if (replay(&simd_model_f32, wl, n, steps, run) || replay(&m2, wl, n, steps2, run2)) return 4;
    if (!(f = fopen(argv[2], "wb"))) return 5;
    fwrite(steps, sizeof *steps, (size_t)n, f);
    fclose(f);
    printf("%s %d %d\n", names[fbgf_dense_kernel()], !memcmp(steps, run, bytes),
           !memcmp(steps, steps2, bytes) && !memcmp(run, run2, bytes));
    return 0;
}
"""

LANES_DRIVER = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "fbgforce.h"
#include "fbgf_dense.h"

static unsigned long long rng = 88172645463325252ull;
static float uniform(void)   /* [-1, 1) with zeros and signed zeros now and then */
{
    rng ^= rng << 13; rng ^= rng >> 7; rng ^= rng << 17;
    switch (rng % 16u) {
    case 0: return 0.0f;
    case 1: return -0.0f;
    default: return (float)((rng >> 11) % 2000001u) / 1000000.0f - 1.0f;
    }
}

/* Every sample of random layers of each shape through fbgf_dense_lanes (in either vector,
 * with the other lanes random) and alone through fbgf_dense. stdout: shapes checked and bytes
 * that differ, or "skip" when this CPU does not run the AVX2 kernel. */
int main(void)
{
    static const unsigned ins[] = {1, 3, 8, 10, 16, 17, 23, 40, 50, 64, 70, 127, 128};
    static const unsigned outs[] = {1, 2, 5, 6, 7, 13, 20, 50, 128};
    static float w[128 * 128], b[128], x[128 * FBGF_RUN_CHUNK], y[128 * FBGF_RUN_CHUNK];
    static float xs[FBGF_RUN_CHUNK][128], ys[FBGF_RUN_CHUNK][128];
    unsigned a, c, i, j, n, relu, n_vec, shapes = 0, bad = 0;
    fbgf_layer ly;
    if (fbgf_dense_kernel() != FBGF_KERNEL_AVX2_FMA) {
        puts("skip");
        return 0;
    }
    for (a = 0; a < sizeof ins / sizeof *ins; ++a)
        for (c = 0; c < sizeof outs / sizeof *outs; ++c)
            for (relu = 0; relu < 2u; ++relu)
                for (n_vec = 1; n_vec <= FBGF_RUN_CHUNK / 8u; ++n_vec) {
                    ly.n_in = (uint16_t)ins[a];
                    ly.n_out = (uint16_t)outs[c];
                    ly.w = w;
                    ly.b = b;
                    for (i = 0; i < 128u * 128u; ++i) w[i] = uniform();
                    for (i = 0; i < 128u; ++i) b[i] = uniform();
                    for (i = 0; i < 128u * FBGF_RUN_CHUNK; ++i) x[i] = 4.0f * uniform();
                    n = 8u * n_vec;
                    for (i = 0; i < n; ++i)
                        for (j = 0; j < ly.n_in; ++j)
                            xs[i][j] = x[j * FBGF_RUN_CHUNK + i];
                    memset(y, 0, sizeof y);
                    fbgf_dense_lanes(&ly, x, y, n_vec, (int)relu);
                    for (i = 0; i < n; ++i) {
                        fbgf_dense(FBGF_KERNEL_AVX2_FMA, &ly, xs[i], 128, ys[i], 128, 1, (int)relu);
                        for (j = 0; j < ly.n_out; ++j)
                            bad += memcmp(&ys[i][j], &y[j * FBGF_RUN_CHUNK + i], sizeof(float)) != 0;
                    }
                    ++shapes;
                }
    printf("%u %u\n", shapes, bad);
    return 0;
}
"""

#: label -> (extra C flags, kernel the driver must report on this host)
X86_BUILDS = {"portable": (["-DFBGF_SIMD=0"], "portable"), "sse2": (["-DFBGF_NO_AVX2=1"], "sse2"),
              "auto": ([], None), "rows": (["-DFBGF_RUN_LANES=0"], None)}


def _need(*tools: str) -> None:
    require_tools(*tools, install="gcc gcc-aarch64-linux-gnu qemu-user")


def _float32_parameters(model: artifact.HierarchicalModel) -> None:
    """Round every float parameter to a float32 value, so that the generated C (decimal
    literals) and the cffi wrapper (binary conversion) hold the same float32 numbers."""
    def f32(a):
        return np.asarray(a, dtype=np.float32).astype(np.float64)

    for net in model.nets.values():
        net.weights = [f32(w) for w in net.weights]
        net.biases = [f32(b) for b in net.biases]
    pre = model.preprocess
    pre.temp_coeff, pre.input_mean, pre.input_std = f32(pre.temp_coeff), f32(pre.input_mean), f32(pre.input_std)
    pre.taps = f32(pre.taps)
    pre.memory.weights = tuple(float(v) for v in f32(pre.memory.weights))
    pre.memory.play_widths = tuple(float(v) for v in f32(pre.memory.play_widths))
    model.force_offset, model.force_scale = float(f32(model.force_offset)), float(f32(model.force_scale))
    model.xy_offset, model.xy_scale = f32(model.xy_offset), f32(model.xy_scale)


@pytest.fixture(scope="module")
def case(random_model_factory, random_walk_factory, tmp_path_factory):
    """A random model with every kind of memory state and the location averages, its C source, a random
    walk and the float64 model's outputs on it."""
    # 10 net inputs (and 10 for the location net, with the location averages): the AVX2
    # kernel for first layers takes them as one full and one partial block of eight.
    memory = artifact.Memory(ema_shifts=(2, 4, 7), ema_gains=(1, 1, 0), play_widths=(0.03, 0.1, 0.3),
                       play_gains=(2, 1, 0), loc_shift=3)
    model = random_model_factory(seed=3, memory=memory)
    wl = random_walk_factory(model, SAMPLES, seed=4)
    base = np.asarray(model.baseline_nm, dtype=np.float64)
    # Contact on about half of the samples: both branches of the step run.
    x = floatref.features(model, wl, base)
    logits = model.contact.forward(x[:, :model.preprocess.n_features])
    model.contact.biases[-1][1] -= float(np.median(logits[:, 1] - logits[:, 0]))
    _float32_parameters(model)
    d = tmp_path_factory.mktemp("float_simd")
    hdr, src = float_source(model, "simd", int(round(contract.DEFAULT_JUMP_NM * 1e6)), 3.0e38)
    (d / "simd_model_f32.h").write_text(hdr)
    (d / "simd_model_f32.c").write_text(src)
    (d / "driver.c").write_text(DRIVER)
    rows = np.vstack([to_fm(base[None, :]), to_fm(wl)]).astype("<i4")
    rows.tofile(d / "wl.bin")
    rows[:QEMU_SAMPLES + 1].tofile(d / "wl_qemu.bin")
    ref = floatref.predict(model, wl, base)
    assert 0.1 < ref["contact"].mean() < 0.9, "the walk should give contact and no contact"
    return {"model": model, "wl": wl, "base": base, "dir": d, "ref": ref}


def _build_and_run(case: dict, name: str, cc: str, flags: list[str], runner: list[str] = (),
                   wl_file: str = "wl.bin") -> tuple[str, np.ndarray]:
    d = case["dir"]
    exe = d / f"drv_{name}"
    cmd = [cc, *STRICT, *flags, f"-I{RUNTIME / 'include'}", f"-I{RUNTIME / 'src'}", f"-I{d}",
           *sorted(str(p) for p in (RUNTIME / "src").glob("fbgf_*.c")), str(d / "simd_model_f32.c"),
           str(d / "driver.c"), "-o", str(exe)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    out = d / f"out_{name}.bin"
    r = subprocess.run([*runner, str(exe), str(d / wl_file), str(out)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    kernel, run_same, moved_same = r.stdout.split()
    assert run_same == "1", f"{name}: fbgf_run differs from fbgf_step"
    assert moved_same == "1", f"{name}: the bits depend on where the weights are"
    return kernel, np.fromfile(out, dtype=_C_FOUTPUT)


def _scale(ref: np.ndarray, both: np.ndarray, key: str) -> float:
    return max(1.0, float(np.abs(ref[key][both]).max()))


def _assert_follows(out: np.ndarray, ref: dict, name: str, rel: float) -> None:
    """out (fbgf_output records) against ref within rel of each output's scale."""
    contact = out["contact"].astype(bool)
    assert (contact != ref["contact"]).mean() < 1e-3, name
    both = contact & ref["contact"]
    assert both.sum() > 100
    for key in ("force_N", "x_mm", "y_mm"):
        dev = np.abs(out[key][both] - ref[key][both]).max()
        assert dev <= rel * _scale(ref, both, key), f"{name} {key}: {dev}"
    assert np.abs(out["p_contact"] - ref["p_contact"]).max() <= 1e-4, name


@pytest.fixture(scope="module")
def x86_outputs(case):
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("x86-64 kernels need an x86-64 host")
    _need("gcc")
    outs = {}
    for name, (flags, want) in X86_BUILDS.items():
        kernel, out = _build_and_run(case, name, "gcc", flags)
        assert want is None or kernel == want, (name, kernel)
        outs[name] = (kernel, out)
    return outs


@pytest.mark.slow
def test_x86_kernels_follow_the_float64_model(case, x86_outputs):
    for name, (_, out) in x86_outputs.items():
        _assert_follows(out, case["ref"], name, 1e-3)


@pytest.mark.slow
def test_x86_simd_differs_from_portable_by_rounding_only(case, x86_outputs):
    portable = x86_outputs["portable"][1]
    for name in ("sse2", "auto"):
        _assert_follows(x86_outputs[name][1], {k: portable[k] for k in portable.dtype.names}
                        | {"contact": portable["contact"].astype(bool)}, name, 1e-4)
    # They are different code: a test that could not tell them apart would prove nothing.
    assert not np.array_equal(x86_outputs["sse2"][1]["force_N"], portable["force_N"])


@pytest.mark.slow
def test_batches_in_lanes_give_the_bits_of_batches_in_rows(x86_outputs):
    """fbgf_run with the samples in lanes (AVX2+FMA, the default) and in rows
    (-DFBGF_RUN_LANES=0) runs the same kernel order: the same bytes."""
    assert x86_outputs["rows"][0] == x86_outputs["auto"][0]
    assert x86_outputs["rows"][1].tobytes() == x86_outputs["auto"][1].tobytes()


@pytest.mark.slow
def test_auto_build_picks_avx2_where_the_cpu_has_it(x86_outputs):
    flags = Path("/proc/cpuinfo").read_text().split() if Path("/proc/cpuinfo").is_file() else []
    expected = "avx2+fma" if {"avx2", "fma"} <= set(flags) else "sse2"
    assert x86_outputs["auto"][0] == expected


@pytest.mark.slow
def test_extension_gives_the_bits_of_the_matching_build(case, x86_outputs):
    """The cffi extension (other flags: -O3, the wrapper) runs the kernel its CPU picks and
    gives the same bytes as the driver build that reports that kernel."""
    rt = FloatRuntime(case["model"])
    rt.set_baseline(case["base"])
    rows = np.ascontiguousarray(to_fm(case["wl"]), dtype=np.int32)
    raw = np.zeros(rows.shape[0], dtype=_C_FOUTPUT)
    from fbgforce.pybind import ffi, lib

    assert lib.fbgf_run(rt._state, ffi.cast("int32_t *", ffi.from_buffer(rows)), rows.shape[0],
                        ffi.cast("fbgf_output *", ffi.from_buffer(raw))) == 0
    assert raw.tobytes() == x86_outputs["auto"][1].tobytes()


def test_avx2_lanes_kernel_gives_each_sample_its_single_bits(tmp_path):
    """fbgf_dense_lanes against fbgf_dense one sample at a time: the same bytes for every
    sample, layer shape, lane and ReLU setting (the rule that lets fbgf_run give the bits of
    fbgf_step)."""
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("the AVX2 kernels need an x86-64 host")
    _need("gcc")
    (tmp_path / "lanes.c").write_text(LANES_DRIVER)
    exe = tmp_path / "lanes"
    r = subprocess.run(["gcc", *STRICT, f"-I{RUNTIME / 'include'}", f"-I{RUNTIME / 'src'}",
                        str(RUNTIME / "src" / "fbgf_dense.c"), str(tmp_path / "lanes.c"), "-o", str(exe)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    if r.stdout.split() == ["skip"]:
        pytest.skip("this CPU lacks AVX2 or FMA")
    shapes, bad = (int(v) for v in r.stdout.split())
    assert shapes == 13 * 9 * 2 * 2
    assert bad == 0, f"{bad} outputs of fbgf_dense_lanes differ from fbgf_dense"


@pytest.mark.target
def test_neon_kernel_under_qemu(case):
    _need("aarch64-linux-gnu-gcc", "qemu-aarch64")
    qemu = dict(runner=["qemu-aarch64"], wl_file="wl_qemu.bin")
    kernel, out = _build_and_run(case, "neon", "aarch64-linux-gnu-gcc", ["-static"], **qemu)
    assert kernel == "neon"
    ref = {k: v[:QEMU_SAMPLES] for k, v in case["ref"].items()}
    _assert_follows(out, ref, "neon", 1e-3)
    kernel, portable = _build_and_run(case, "neon_portable", "aarch64-linux-gnu-gcc",
                                      ["-static", "-DFBGF_SIMD=0"], **qemu)
    assert kernel == "portable"
    _assert_follows(out, {k: portable[k] for k in portable.dtype.names}
                    | {"contact": portable["contact"].astype(bool)}, "neon vs portable", 1e-4)
    assert not np.array_equal(out["force_N"], portable["force_N"])
