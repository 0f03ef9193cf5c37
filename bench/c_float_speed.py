"""How fast is the C float build (``fbgf_*``) on this host, per dense-layer kernel?

Times, in one run, CPU time per sample of

* ``fbgf_run`` batch through the installed cffi extension (``fbgforce.FloatRuntime``; the
  kernel the build and the CPU pick), and
* one ``fbgf_step`` called from C: ``runtime_c/src/*.c`` compiled with a small driver for each
  kernel (portable C, SSE2, and AVX2+FMA when this CPU has it; fbgf_dense.h) at ``-O2`` (what
  ``make -C runtime_c`` builds) and ``-O3`` (what the cffi extension builds),

best of 7 passes over the same samples, and the largest deviation of each build's force and
location from the float64 model (``fbgforce.model.predict``). Contact samples only, so all
three nets run (the worst case).

Usage::

    python -m fbgforce.bench.c_float_speed [--model MODEL_DIR --data FILE] [--samples 5000]

Without ``--model`` the model is a random one of the paper's size (contact and force nets
8-70-50-20-{2,1}, location net 6-70-50-40-2, 2 EMA + 2 play memory states, 16 taps) whose
contact net always says "contact". Needs ``gcc`` (or ``$CC``).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DRIVER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "fbgforce.h"
#include "fbgf_dense.h"
#include "bench_model_f32.h"
static double cpu_ns(void) { struct timespec t; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
                             return t.tv_sec * 1e9 + t.tv_nsec; }
int main(int argc, char **argv) {
    static const char *names[] = {"portable", "sse2", "avx2+fma", "neon"};
    static fbgf_state st; fbgf_output *out, *out_run; int32_t *wl; long len, n, i; int r;
    double best_step = 1e300, best_run = 1e300, t0, t;
    FILE *f;
    if (argc != 3 || !(f = fopen(argv[1], "rb"))) return 2;
    fseek(f, 0, SEEK_END); len = ftell(f); rewind(f);
    wl = malloc((size_t)len); n = len / 20 - 1;   /* row 0 is the baseline */
    out = malloc(sizeof *out * (size_t)n); out_run = malloc(sizeof *out * (size_t)n);
    if (!wl || !out || !out_run || fread(wl, 1, (size_t)len, f) != (size_t)len) return 3;
    fclose(f);
    for (r = 0; r < 7; ++r) {
        if (fbgf_init(&st, &bench_model_f32, 0) != FBG_OK || fbgf_set_baseline(&st, wl) != FBG_OK) return 4;
        t0 = cpu_ns();
        for (i = 0; i < n; ++i)
            if (fbgf_step(&st, wl + 5 * (i + 1), out + i) != FBG_OK) return 5;
        t = (cpu_ns() - t0) / (double)n;
        if (t < best_step) best_step = t;
        if (fbgf_init(&st, &bench_model_f32, 0) != FBG_OK || fbgf_set_baseline(&st, wl) != FBG_OK) return 4;
        t0 = cpu_ns();
        if (fbgf_run(&st, wl + 5, (size_t)n, out_run) != FBG_OK) return 5;
        t = (cpu_ns() - t0) / (double)n;
        if (t < best_run) best_run = t;
    }
    if (!(f = fopen(argv[2], "wb"))) return 6;
    fwrite(out, sizeof *out, (size_t)n, f); fclose(f);
    printf("%.1f %.1f %s %s\n", best_step, best_run, memcmp(out, out_run, sizeof *out * (size_t)n) ? "NO" : "yes",
           names[fbgf_dense_kernel()]);
    return 0;
}
"""

KERNELS = (("portable", ["-DFBGF_SIMD=0"]), ("sse2", ["-DFBGF_NO_AVX2=1"]), ("auto", []))
OPT_LEVELS = ("-O2", "-O3")


def paper_model(seed: int = 0):
    """A random model of the paper's size whose contact net always says "contact"."""
    from fbgforce import model as fm

    rng = np.random.default_rng(seed)

    def mlp(n_in: int, hidden: tuple[int, ...], n_out: int) -> fm.MLP:
        dims = [n_in, *hidden, n_out]
        return fm.MLP([rng.normal(0.0, np.sqrt(2.0 / a), (b, a)) for a, b in zip(dims[:-1], dims[1:])],
                      [rng.normal(0.0, 0.1, b) for b in dims[1:]])

    k = np.arange(16)
    taps = np.exp(-0.5 * (k / 4.0) ** 2)
    memory = fm.Memory(ema_shifts=(3, 6), ema_gains=(1, 0), play_widths=(0.05, 0.2), play_gains=(1, 0))
    pre = fm.Preprocess(temp_coeff=rng.uniform(0.9, 1.1, 4), filter_kind="causal", filter_sigma=4.0,
                        taps=taps / taps.sum(), input_mean=rng.normal(0.0, 50.0, 4),
                        input_std=rng.uniform(100.0, 400.0, 4), memory=memory)
    f = pre.n_features
    contact = mlp(f, (70, 50, 20), 2)
    contact.biases[-1] = contact.biases[-1] + np.array([-1e3, 1e3])
    return fm.HierarchicalModel(pre, contact, mlp(f, (70, 50, 20), 1), mlp(6, (70, 50, 40), 2),
                                force_offset=20.0, force_scale=15.0, xy_offset=[10.5, 13.5],
                                xy_scale=[6.0, 7.5], baseline_nm=[1530.0, 1535.0, 1540.0, 1545.0, 1550.0])


def _cffi_batch_ns(model, base: np.ndarray, wl: np.ndarray) -> float:
    from fbgforce.pybind import FloatRuntime, _C_FOUTPUT, ffi, lib, to_fm

    rt = FloatRuntime(model)
    rows = np.ascontiguousarray(to_fm(wl), dtype=np.int32)
    raw = np.zeros(rows.shape[0], dtype=_C_FOUTPUT)
    src = ffi.cast("int32_t *", ffi.from_buffer(rows))
    dst = ffi.cast("fbgf_output *", ffi.from_buffer(raw))
    best = float("inf")
    for _ in range(7):
        rt.set_baseline(base)
        t0 = time.thread_time_ns()
        if lib.fbgf_run(rt._state, src, rows.shape[0], dst) != 0:
            raise RuntimeError("fbgf_run failed")
        best = min(best, (time.thread_time_ns() - t0) / rows.shape[0])
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model directory (default: a random paper-size model)")
    ap.add_argument("--data", help="recording in the dataset contract (with --model): its contact "
                    "samples are timed")
    ap.add_argument("--samples", type=int, default=5000, help="samples per pass (default 5000)")
    args = ap.parse_args(argv)
    if (args.model is None) != (args.data is None):
        print("c_float_speed: give --model and --data together, or neither", file=sys.stderr)
        return 2

    from fbgforce import model as fm
    from fbgforce.export.codegen import float_source
    from fbgforce.pybind import to_fm

    cc = os.environ.get("CC", "gcc")
    if shutil.which(cc) is None:
        print(f"c_float_speed: {cc} not found", file=sys.stderr)
        return 2
    if args.model is None:
        model = paper_model()
        walk = np.cumsum(np.random.default_rng(1).normal(0.0, 0.004, (args.samples, 5)), axis=0)
        walk[:, 4] *= 0.2
        base, wl = np.asarray(model.baseline_nm, dtype=np.float64), model.baseline_nm + walk
    else:
        from fbgforce import dataset as fds
        from fbgforce.tare import tare
        from fbgforce.tradeoff.timers import timing_samples

        from fbgforce.errors import InputError

        try:
            model = fm.load(args.model)
            ds = fds.load(args.data)
        except InputError as exc:
            print(f"c_float_speed: {exc}", file=sys.stderr)
            return 2
        base = tare(ds.wl_nm, ds.contact, ds.t_s)[0]
        wl = timing_samples(ds)[:args.samples]
    ref = fm.predict(model, wl, base)
    root = Path(__file__).resolve().parent.parent / "runtime_c"
    print(f"C float build, {len(wl)} samples, {int(ref['contact'].sum())} with contact "
          f"(CPU ns per sample, best of 7)")
    print(f"fbgf_run batch via cffi (installed extension): {_cffi_batch_ns(model, base, wl):.0f}")
    hdr, src = float_source(model, "bench", 0x7FFFFFFF, 3.0e38)
    rows = np.vstack([to_fm(base[None, :]), to_fm(wl)]).astype("<i4")
    from fbgforce.pybind import _C_FOUTPUT

    print(f"{'from C: kernel, flags':24s} {'fbgf_step':>10s} {'fbgf_run':>10s}  run == steps  "
          "max |dev| from float64 model (force N, x mm)")
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        (t / "driver.c").write_text(DRIVER)
        (t / "bench_model_f32.h").write_text(hdr)
        (t / "bench_model_f32.c").write_text(src)
        rows.tofile(t / "wl.bin")
        srcs = sorted(str(p) for p in (root / "src").glob("*.c"))
        for label, defs in KERNELS:
            for opt in OPT_LEVELS:
                exe = t / "drv"
                cmd = [cc, "-std=c99", opt, *defs, f"-I{root / 'include'}", f"-I{root / 'src'}", f"-I{t}",
                       *srcs, str(t / "bench_model_f32.c"), str(t / "driver.c"), "-o", str(exe)]
                r = subprocess.run(cmd, capture_output=True, text=True)
                if r.returncode != 0:
                    print(f"{label} {opt}: compile failed: {r.stderr.strip().splitlines()[-1:]}")
                    continue
                r = subprocess.run([str(exe), str(t / "wl.bin"), str(t / "out.bin")],
                                   capture_output=True, text=True)
                if r.returncode != 0:
                    print(f"{label} {opt}: run failed (exit {r.returncode})")
                    continue
                step_ns, run_ns, same, kernel = r.stdout.split()
                out = np.fromfile(t / "out.bin", dtype=_C_FOUTPUT)
                both = out["contact"].astype(bool) & ref["contact"]
                dev_f = float(np.abs(out["force_N"][both] - ref["force_N"][both]).max(initial=0.0))
                dev_x = float(np.abs(out["x_mm"][both] - ref["x_mm"][both]).max(initial=0.0))
                print(f"{kernel + ' ' + opt:24s} {float(step_ns):10.0f} {float(run_ns):10.0f}  {same:12s}  "
                      f"{dev_f:.2e}  {dev_x:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
