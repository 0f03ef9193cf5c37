"""How fast can the C fixed-point step run on this host, by compiler flags and dense-layer
kernel, and is it bit-exact?

Compiles ``runtime_c/src/fbg_*.c`` with a small driver (below) under several flag sets, runs
the same int32 samples (the contact samples of a recording, where all three nets run) with
every dense-layer kernel this CPU runs (``FBG_OPT_KERNEL_*``: portable C, SSE2, AVX2, NEON;
docs/runtime.md, "Host SIMD kernels"), and reports CPU ns per sample (best of 7 passes) of
``fbg_run`` (batch) and of one ``fbg_step`` call per sample from C, and whether every output
record is byte-identical to the installed cffi extension's (``fbgforce.Runtime.run_raw``).

Usage::

    python -m fbgforce.bench.c_speed --model MODEL_DIR --data FILE [--samples 5000]

Needs ``gcc`` (or ``$CC``). The cffi extension is built with ``-O3`` (runtime_c/build_runtime.py)
and ``make -C runtime_c`` too; this script shows what other flags would buy without touching
the library.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

DRIVER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <stdint.h>
#include <time.h>
#include "fbgforce.h"
static double cpu_ns(void) { struct timespec t; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
                             return t.tv_sec * 1e9 + t.tv_nsec; }
static void *slurp(const char *path, long *len) {
    FILE *f = fopen(path, "rb"); void *buf; if (!f) return NULL;
    fseek(f, 0, SEEK_END); *len = ftell(f); rewind(f);
    buf = malloc((size_t)(*len + 8)); if (fread(buf, 1, (size_t)*len, f) != (size_t)*len) return NULL;
    fclose(f); return buf; }
int main(int argc, char **argv) {
    long blen, wlen, n, i; int r; double best = 1e300, best_step = 1e300;
    static fbg_model model; static fbg_state st; fbg_output *out; FILE *f;
    uint8_t *blob; int32_t *wl; uint32_t options;
    if (argc != 5) return 2;
    blob = slurp(argv[1], &blen); wl = slurp(argv[2], &wlen);
    if (!blob || !wl) return 3;
    options = (uint32_t)strtoul(argv[4], NULL, 0);
    n = wlen / 20 - 1;   /* row 0 is the baseline */
    out = malloc(sizeof(fbg_output) * (size_t)n);
    if (fbg_model_from_blob(&model, blob, (size_t)blen) != FBG_OK) return 4;
    if (fbg_init(&st, &model, options) != FBG_OK) return 6;   /* kernel not on this CPU */
    for (r = 0; r < 7; ++r) {
        double t0, t;
        fbg_init(&st, &model, options); fbg_set_baseline(&st, wl);
        t0 = cpu_ns();
        if (fbg_run(&st, wl + 5, (size_t)n, out) != FBG_OK) return 5;
        t = (cpu_ns() - t0) / (double)n;
        if (t < best) best = t;
        fbg_init(&st, &model, options); fbg_set_baseline(&st, wl);
        t0 = cpu_ns();
        for (i = 0; i < n; ++i)
            if (fbg_step(&st, wl + 5 * (i + 1), out + i) != FBG_OK) return 5;
        t = (cpu_ns() - t0) / (double)n;
        if (t < best_step) best_step = t;
    }
    f = fopen(argv[3], "wb"); fwrite(out, sizeof(fbg_output), (size_t)n, f); fclose(f);
    printf("%.1f %.1f\n", best, best_step);
    return 0;
}
"""

FLAG_SETS = ("-O2", "-O3", "-O3 -march=native")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="model directory with model.fbgm")
    ap.add_argument("--data", required=True, help="recording in the dataset contract")
    ap.add_argument("--samples", type=int, default=5000)
    args = ap.parse_args(argv)

    from fbgforce import dataset as fds
    from fbgforce.tradeoff.timers import timing_samples
    from fbgforce.pybind import KERNELS, Runtime, to_fm
    from fbgforce.tare import tare

    cc = os.environ.get("CC", "gcc")
    if shutil.which(cc) is None:
        print(f"c_speed: {cc} not found", file=sys.stderr)
        return 2
    root = Path(__file__).resolve().parent.parent / "runtime_c"
    ds = fds.load(args.data)
    base = tare(ds.wl_nm, ds.contact, ds.t_s)[0]
    wl = timing_samples(ds)[:args.samples]
    rows = np.vstack([to_fm(base[None, :]), to_fm(wl)]).astype("<i4")
    rt = Runtime(args.model)
    rt.set_baseline(base)
    ref = rt.run_raw(to_fm(wl)).tobytes()
    blob = Path(args.model) / "model.fbgm"
    kernels = [k for k in KERNELS if k != "auto"]
    print(f"{'flags':20s} {'kernel':9s} {'fbg_run ns/sample':>17s} {'fbg_step ns':>11s}  "
          f"bit-exact vs extension ({len(wl)} contact samples)")
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        (t / "driver.c").write_text(DRIVER)
        rows.tofile(t / "wl.bin")
        for flags in FLAG_SETS:
            exe = t / "drv"
            cmd = [cc, "-std=c99", *flags.split(), f"-I{root / 'include'}",
                   *sorted(str(p) for p in (root / "src").glob("fbg_*.c")), str(t / "driver.c"),
                   "-o", str(exe)]
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode != 0:
                print(f"{flags:20s} compile failed: {r.stderr.strip().splitlines()[-1:]}")
                continue
            for kernel in kernels:
                r = subprocess.run([str(exe), str(blob), str(t / "wl.bin"), str(t / "out.bin"),
                                    str(KERNELS[kernel])], capture_output=True, text=True)
                if r.returncode == 6:
                    continue  # this CPU does not run the kernel
                if r.returncode != 0:
                    print(f"{flags:20s} {kernel:9s} run failed (exit {r.returncode})")
                    continue
                batch, step = (float(v) for v in r.stdout.split())
                same = (t / "out.bin").read_bytes() == ref
                print(f"{flags:20s} {kernel:9s} {batch:17.1f} {step:11.1f}  {'yes' if same else 'NO'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
