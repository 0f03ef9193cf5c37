"""The C runtime timed and counted from C, without Python: a small driver compiled with the
library sources under chosen compiler flags.

One build (:class:`CBuild`) is the library's ``runtime_c/src/*.c`` plus :data:`DRIVER`, compiled
with a flag set. The driver loads a model blob (``fbg_*``, so int16 and int8 blobs share a
build) or links a generated float model (``fbgf_*``, the export's ``c/<name>_model_f32.c``), reads
int32 femtometre samples (row 0 the tare baseline) and either

- ``time``: runs ``fbg_run`` over all samples and, separately, one ``fbg_step`` call per sample,
  each best of ``reps`` passes in the thread's CPU time, and writes the ``fbg_run`` outputs (so
  a caller can compare them byte for byte with the cffi extension), or
- ``count``: calls only ``*_step``, once per sample for the first ``k`` samples, so that
  ``valgrind --tool=callgrind --toggle-collect=fbg_step`` counts exactly the instructions of
  those steps (callgrind counts are deterministic: the same binary on the same samples gives
  the same figure, whatever the machine's load). Two counts, over ``w`` and ``w + n`` steps,
  give the ``n`` steps after a warm-up of ``w`` by difference: the first steps after a
  restart fill the filter and the memory states and may skip nets, so they are no measure of
  a running step.

A build's flags set what the compiler may use (``-O2``, ``-march=native``, ...) and its
``init_options`` what ``fbg_init`` is given (a dense-layer kernel choice) and ``packed``
whether the state then runs from weights ``fbg_pack`` packs for its kernel;
:func:`extension_flags` are the flags the cffi extension itself is built with.
"""
from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fbgforce.target.sources import REPOSITORY, CSourcesMissing, source_root


def runtime_c() -> Path:
    """``runtime_c/`` of the C sources the package ships or runs from
    (:func:`fbgforce.target.sources.source_root`)."""
    return source_root() / "runtime_c"

DRIVER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <stdint.h>
#include <time.h>
#include "fbgforce.h"
#ifdef FBG_BENCH_FLOAT_MODEL
#include FBG_BENCH_FLOAT_HEADER
#endif
#ifndef FBG_BENCH_INIT_OPTIONS
#define FBG_BENCH_INIT_OPTIONS 0u
#endif

static double cpu_ns(void) { struct timespec t; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
                             return (double)t.tv_sec * 1e9 + (double)t.tv_nsec; }

static void *slurp(const char *path, long *len) {
    FILE *f = fopen(path, "rb"); void *buf;
    if (!f) return NULL;
    fseek(f, 0, SEEK_END); *len = ftell(f); rewind(f);
    buf = malloc((size_t)(*len + 8));
    if (!buf || fread(buf, 1, (size_t)*len, f) != (size_t)*len) { fclose(f); return NULL; }
    fclose(f); return buf;
}

/* argv: MODE(time|count) KIND(fixed|float) BLOB(or -) SAMPLES.bin REPS OUT.bin(or -);
 * count mode: REPS steps from the first sample, no output file. */
int main(int argc, char **argv) {
    long blen = 0, wlen = 0; size_t n, i; int r, reps, count, fixed;
    double best_run = 1e300, best_step = 1e300;
    static fbg_model model; static fbg_state st; static fbgf_state fst;
    void *out; size_t rec; uint8_t *blob = NULL; int32_t *wl;
#ifdef FBG_BENCH_PACK
    unsigned char *pack_mem, *pack = NULL;
#endif
    if (argc != 7) return 2;
    count = strcmp(argv[1], "count") == 0;
    fixed = strcmp(argv[2], "fixed") == 0;
    reps = atoi(argv[5]);
    wl = slurp(argv[4], &wlen);
    if (!wl || wlen < 40 || reps < 1) return 3;
    n = (size_t)(wlen / 20 - 1);
    rec = fixed ? sizeof(fbg_output) : sizeof(fbgf_output);
    out = malloc(rec * n);
    if (!out) return 3;
    if (fixed) {
        blob = slurp(argv[3], &blen);
        if (!blob || fbg_model_from_blob(&model, blob, (size_t)blen) != FBG_OK) return 4;
    } else {
#ifndef FBG_BENCH_FLOAT_MODEL
        return 4;
#endif
    }
#ifdef FBG_BENCH_PACK /* the state runs from weights packed into a buffer of the driver's,
                       * when its kernel has a packed form (as fbgforce.Runtime does) */
    if (fixed && fbg_init(&st, &model, FBG_BENCH_INIT_OPTIONS) != FBG_OK) return 7;
    if (fixed && fbg_pack_bytes(&st) != 0u) {
        size_t bytes = fbg_pack_bytes(&st);
        pack_mem = malloc(bytes + FBG_PACK_ALIGN);
        if (!pack_mem) return 3;
        pack = pack_mem + (FBG_PACK_ALIGN - (uintptr_t)pack_mem % FBG_PACK_ALIGN) % FBG_PACK_ALIGN;
        if (fbg_pack(&st, pack, bytes) != FBG_OK) return 8;
    }
#define PACK_AGAIN() fbg_use_pack(&st, pack)
#else
#define PACK_AGAIN() FBG_OK
#endif
#define RESTART() (fixed ? (fbg_init(&st, &model, FBG_BENCH_INIT_OPTIONS) || fbg_set_baseline(&st, wl) \
                            || PACK_AGAIN()) \
                         : (FLOAT_INIT() || fbgf_set_baseline(&fst, wl)))
#ifdef FBG_BENCH_FLOAT_MODEL
#define FLOAT_INIT() fbgf_init(&fst, &FBG_BENCH_FLOAT_MODEL, 0)
#else
#define FLOAT_INIT() 1
#endif
#define STEP(k) (fixed ? fbg_step(&st, wl + 5 * ((k) + 1), (fbg_output *)out + (k)) \
                       : fbgf_step(&fst, wl + 5 * ((k) + 1), (fbgf_output *)out + (k)))
    if (count) { /* REPS is the number of steps here, from the first sample */
        if ((size_t)reps < n) n = (size_t)reps;
        if (RESTART()) return 7;
        for (i = 0; i < n; ++i)
            if (STEP(i) != FBG_OK) return 5;
        printf("%lu\n", (unsigned long)n);
        return 0;
    }
    for (r = 0; r < reps; ++r) {
        double t0, t;
        if (RESTART()) return 7;
        t0 = cpu_ns();
        for (i = 0; i < n; ++i)
            if (STEP(i) != FBG_OK) return 5;
        t = (cpu_ns() - t0) / (double)n;
        if (t < best_step) best_step = t;
        if (RESTART()) return 7;
        t0 = cpu_ns();
        if ((fixed ? fbg_run(&st, wl + 5, n, (fbg_output *)out)
                   : fbgf_run(&fst, wl + 5, n, (fbgf_output *)out)) != FBG_OK) return 5;
        t = (cpu_ns() - t0) / (double)n;
        if (t < best_run) best_run = t;
    }
    if (strcmp(argv[6], "-") != 0) { /* the outputs of the last fbg_run pass */
        FILE *f = fopen(argv[6], "wb");
        if (!f || fwrite(out, rec, n, f) != n) return 6;
        fclose(f);
    }
    printf("%.3f %.3f\n", best_run, best_step);
    return 0;
}
"""


@dataclass(frozen=True)
class CBuild:
    """A driver build: a name for the tables, the compiler flags (split on spaces) and the
    ``fbg_init`` options of its fixed-point runs (None: 0; a kernel choice where the header
    defines ``FBG_OPT_KERNEL_*`` values, so that every kernel path is timed and counted), and
    whether those runs use packed weights (``fbg_pack``, as :class:`fbgforce.Runtime` does)."""

    name: str
    flags: str
    init_options: int | None = None
    packed: bool = False


def extension_flags() -> str | None:
    """The compile flags of the cffi extension (``extra_compile_args`` in
    ``runtime_c/build_runtime.py``), so that the default driver build times the same code;
    None outside a source checkout (a regular install ships the sources, not the builder)."""
    path = REPOSITORY / "runtime_c" / "build_runtime.py"
    if not path.is_file():
        return None
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.keyword) and node.arg == "extra_compile_args":
            return " ".join(str(a) for a in ast.literal_eval(node.value))
    return ""


def parse_build(text: str) -> CBuild:
    """``NAME=FLAGS`` (or just ``FLAGS``, named after them) -> :class:`CBuild`, which runs
    as the extension does: the fastest kernel, from packed weights where it has them."""
    name, sep, flags = text.partition("=")
    if not sep:
        name, flags = text.strip(), text
    if not name.strip():
        raise ValueError(f"a build needs a name or flags: {text!r} (NAME=FLAGS)")
    return CBuild(name.strip(), flags.strip(), packed=True)


def compiler() -> str | None:
    """The C compiler (``$CC`` or gcc), or None when there is none."""
    cc = os.environ.get("CC", "gcc")
    return cc if shutil.which(cc.split()[0]) else None


def float_model_source(model_dir: Path) -> Path | None:
    """The generated float model ``c/<name>_model_f32.c`` of an exported model directory."""
    found = sorted((Path(model_dir) / "c").glob("*_model_f32.c"))
    return found[0] if found else None


def build(b: CBuild, work: Path, float_model: Path | None = None) -> Path:
    """Compile the driver for ``b`` in ``work``; returns the executable.

    Raises
    ------
    RuntimeError
        Without a compiler or the runtime's sources, or when the compiler fails (its last
        message line is in the text).
    """
    cc = compiler()
    if cc is None:
        raise RuntimeError(f"no C compiler ({os.environ.get('CC', 'gcc')}) found")
    try:
        root = runtime_c()
    except CSourcesMissing as exc:
        raise RuntimeError(str(exc)) from exc
    work.mkdir(parents=True, exist_ok=True)
    (work / "driver.c").write_text(DRIVER)
    exe = work / "driver"
    srcs = sorted(str(p) for p in (root / "src").glob("*.c"))
    extra: list[str] = []
    if float_model is not None:
        ident = float_model.stem
        extra = [f"-DFBG_BENCH_FLOAT_MODEL={ident}",
                 f'-DFBG_BENCH_FLOAT_HEADER="{float_model.with_suffix(".h").name}"',
                 f"-I{float_model.parent}", str(float_model)]
    if b.init_options is not None:
        extra.append(f"-DFBG_BENCH_INIT_OPTIONS={int(b.init_options)}u")
    if b.packed:
        extra.append("-DFBG_BENCH_PACK")
    cmd = [*cc.split(), "-std=c99", *b.flags.split(), f"-I{root / 'include'}", *srcs,
           *extra, str(work / "driver.c"), "-o", str(exe)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        lines = r.stderr.strip().splitlines()
        first = next((ln for ln in lines if "error" in ln), lines[-1] if lines else "(no message)")
        raise RuntimeError(f"compile with {b.flags!r} failed: {first.strip()}")
    return exe


def write_samples(path: Path, baseline_fm: np.ndarray, wl_fm: np.ndarray) -> None:
    """The driver's input: int32 rows of 5, the baseline first."""
    np.vstack([np.asarray(baseline_fm).reshape(1, 5), wl_fm]).astype("<i4").tofile(path)


def time_run(exe: Path, kind: str, blob: Path | None, samples: Path, reps: int,
             out: Path | None) -> tuple[float, float]:
    """CPU ns per sample of ``*_run`` over all samples and of one ``*_step`` call per sample,
    each the best of ``reps`` passes; ``out`` receives the ``*_run`` output records
    (``fbg_output`` or ``fbgf_output``)."""
    r = subprocess.run([str(exe), "time", kind, str(blob or "-"), str(samples), str(reps),
                        str(out or "-")], capture_output=True, text=True)
    if r.returncode == 7:
        raise RuntimeError("fbg_init refused the build's options (a kernel this CPU or build "
                           "does not run)")
    if r.returncode == 8:
        raise RuntimeError("fbg_pack refused the driver's buffer")
    if r.returncode != 0:
        raise RuntimeError(f"driver failed (exit {r.returncode}) on {kind} {blob or ''}")
    run_ns, step_ns = (float(v) for v in r.stdout.split())
    return run_ns, step_ns


def valgrind() -> str | None:
    """The valgrind executable, or None."""
    return shutil.which("valgrind")


def _callgrind_steps(exe: Path, kind: str, blob: Path | None, samples: Path,
                     steps: int) -> tuple[int, dict[str, int]]:
    """Instructions executed inside ``*_step`` over the first ``steps`` samples, in total and
    per function (self cost; empty when ``callgrind_annotate`` is missing)."""
    vg = valgrind()
    if vg is None:
        raise RuntimeError("valgrind not found")
    fn = "fbg_step" if kind == "fixed" else "fbgf_step"
    cg_out = samples.parent / f"callgrind.{kind}.out"
    try:
        r = subprocess.run([vg, "--tool=callgrind", f"--toggle-collect={fn}",
                            f"--callgrind-out-file={cg_out}", str(exe), "count", kind,
                            str(blob or "-"), str(samples), str(steps), "-"],
                           capture_output=True, text=True)
        m = re.search(r"Collected\s*:\s*(\d+)", r.stderr)
        if r.returncode != 0 or m is None or r.stdout.split() != [str(steps)]:
            raise RuntimeError(f"callgrind run failed (exit {r.returncode})")
        return int(m.group(1)), _self_costs(cg_out)
    finally:
        cg_out.unlink(missing_ok=True)


def _self_costs(cg_out: Path) -> dict[str, int]:
    """Per-function instruction counts of a callgrind output file (``callgrind_annotate``)."""
    annotate = shutil.which("callgrind_annotate")
    if annotate is None or not cg_out.is_file():
        return {}
    r = subprocess.run([annotate, "--threshold=100", str(cg_out)], capture_output=True,
                       text=True)
    costs: dict[str, int] = {}
    for line in r.stdout.splitlines():
        m = re.match(r"\s*([\d,]+)\s+\([\s\d.]+%\)\s+\S*?:(\w+)", line)
        if m:
            costs[m.group(2)] = costs.get(m.group(2), 0) + int(m.group(1).replace(",", ""))
    return costs


def count_instructions(exe: Path, kind: str, blob: Path | None, samples: Path, warmup: int,
                       n: int) -> tuple[float, dict[str, float]]:
    """Mean instructions per ``*_step`` call over the ``n`` steps after the first ``warmup``
    of a stream from a restart, from callgrind: every instruction executed inside the step
    function, callees included (``samples`` holds at least ``warmup + n`` samples); and the
    same per function (the functions the compiler kept; inlined code counts in its caller).
    """
    total, per_fn = _callgrind_steps(exe, kind, blob, samples, warmup + n)
    before, before_fn = _callgrind_steps(exe, kind, blob, samples, warmup) if warmup else (0, {})
    profile = {f: (c - before_fn.get(f, 0)) / n for f, c in per_fn.items()}
    return (total - before) / n, dict(sorted(profile.items(), key=lambda kv: -kv[1]))
