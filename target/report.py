"""The target report: golden vectors replayed bit-exactly on both builds, instructions per step,
MACs, flash, RAM and the share of a 1 kHz period."""
from __future__ import annotations

import bisect
import contextlib
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from fbgforce.errors import InputError
from fbgforce.target import cycles, firmware, golden, sources, toolchain
from fbgforce.units import estimate_shown

#: Clock the budget fraction is quoted for, and the controller period.
CLOCK_HZ = 168_000_000
PERIOD_S = 1e-3


def load_quantized(model_dir: Path, calib: Sequence[str] | None = None, bits: int | None = None
                   ) -> tuple[Any, str]:
    """The fixed-point model: ``model.fbgm`` if exported (and ``bits`` is None), else quantised
    in memory with ``bits``-bit weights (default 16; the model directory is not written).
    Returns ``(QModel, where it came from)``."""
    from fbgforce.export import blob

    if bits is None and (model_dir / blob.FILE_NAME).is_file():
        return blob.load_model_blob(model_dir), str(model_dir / blob.FILE_NAME)
    from fbgforce.model import modeldir as fm
    from fbgforce.export import exporter
    from fbgforce.export import quantize as qz

    model = fm.load(model_dir)
    kept = exporter.calibration_recordings(model_dir, model, calib)
    q, _ = qz.quantize(model, qz.calibrate(model, kept.recordings, kept.contact_force_N),
                       bits=bits or 16)
    return q, f"quantised in memory, int{bits or 16} weights"


def recording_fm(data: str | None, scene: str, seed: int, samples: int) -> tuple[np.ndarray, np.ndarray, str]:
    """``samples`` consecutive samples (int32 fm) and their contact flags: from ``data`` or a
    simulated ``scene``; the window starts shortly before the first contact."""
    from fbgforce.recordings import dataset as fds
    from fbgforce.export import intref

    if data:
        ds = fds.load(data)
        src = str(data)
    else:
        from fbgforce import sim

        ds = sim.simulate(scene, seed=seed)
        src = f"scene {scene} seed {seed}"
    contact = np.asarray(ds.contact, dtype=bool)
    first = int(np.argmax(contact)) if contact.any() else 0
    start = max(0, min(first - samples // 5, len(ds) - samples))
    sl = slice(start, start + samples)
    return intref.nm_to_fm(ds.wl_nm[sl]), contact[sl], f"{src}, samples {sl.start}..{sl.stop - 1}"


def _figures(run: firmware.FirmwareRun, macs: list[int], contact: list[bool]) -> dict[str, Any]:
    w = np.asarray(run.windows, dtype=np.int64)
    if w.size != len(macs):  # the run stopped early (fault, crash): no per-step figures
        return {"instructions_per_step": int(w.max()) if w.size else None,
                "instructions_per_step_mean": None, "instructions_per_step_no_contact_max": None,
                "instructions_per_mac": None, "budget_fraction_at_168MHz": None}
    m = np.asarray(macs, dtype=np.int64)
    c = np.asarray(contact, dtype=bool)
    full = c & (m > 0)
    worst = int(w.max()) if w.size else 0
    ipm = float(w[full].sum() / m[full].sum()) if full.any() else None
    return {
        "instructions_per_step": worst,
        "instructions_per_step_mean": round(float(w.mean()), 1) if w.size else None,
        "instructions_per_step_no_contact_max": int(w[~c & (m > 0)].max()) if (~c & (m > 0)).any() else None,
        "instructions_per_mac": round(ipm, 3) if ipm is not None else None,
        "budget_fraction_at_168MHz": round(worst / (CLOCK_HZ * PERIOD_S), 4),
    }


def _cycle_figures(run: firmware.FirmwareRun, elf: Path) -> dict[str, Any]:
    """Estimated Cortex-M4 cycles of the worst step from its instruction mix
    (:mod:`fbgforce.target.cycles`): P = 2 cycles of pipeline refill per transfer of control,
    and the range for P = 1 and 3; the mix by class as [instructions, cycles]; the worst step's
    instructions by function."""
    if not run.worst_pcs:
        return {"cycles_per_step_estimate": None}
    dis = cycles.disassemble(elf)
    est = {p: cycles.estimate(run.worst_pcs, dis, refill=p) for p in (1, 2, 3)}
    mid = est[2]
    funcs = sorted(firmware.function_ranges(elf).items(), key=lambda kv: kv[1][0])
    starts = [lo for _, (lo, _) in funcs]
    by_func: dict[str, int] = {}
    for pc, executed, _, _ in run.worst_pcs:
        i = bisect.bisect_right(starts, pc) - 1
        name = funcs[i][0] if i >= 0 and pc < funcs[i][1][0] + funcs[i][1][1] else "?"
        by_func[name] = by_func.get(name, 0) + executed
    return {
        "cycles_per_step_estimate": mid["cycles"],
        "cycles_per_step_range": [est[1]["cycles"], est[3]["cycles"]],
        "cycles_per_instruction": round(mid["cycles"] / max(mid["instructions"], 1), 3),
        "budget_fraction_cycles_at_168MHz": round(mid["cycles"] / (CLOCK_HZ * PERIOD_S), 4),
        "cycle_mix": {k: v for k, v in sorted(mid["by_class"].items(), key=lambda kv: -kv[1][1])},
        "taken_transfers": mid["taken_transfers"],
        "pipelined_loads": mid["pipelined_loads"],
        "worst_step_by_function": dict(sorted(by_func.items(), key=lambda kv: -kv[1])),
    }


def target_report(model_dir: str | Path, *, data: str | None = None, scene: str = "smoke",
                  seed: int = 0, samples: int = 600, calib: Sequence[str] | None = None,
                  bits: int | None = None, build_dir: str | Path | None = None, log=None
                  ) -> dict[str, Any]:
    """Build, replay the golden vectors on QEMU (portable and DSP builds), count and measure.

    Returns the report dict (keys in docs/cli.md#target-report). Raises
    :class:`~fbgforce.target.toolchain.ToolchainMissing` without the tools,
    :class:`~fbgforce.target.sources.CSourcesMissing` without the C sources and
    :class:`InputError` for a bad model/data.
    """
    from fbgforce.export import codegen

    t0 = time.perf_counter()
    log = log or (lambda msg: None)
    root = Path(model_dir)
    if not root.exists():
        raise InputError("no such model directory", path=str(root))
    # Model and data are read before the tools are looked for: a bad or stale model, or bad
    # data, is the same one-line error on any machine.
    q, source = load_quantized(root, calib, bits)
    wl, contact, data_src = recording_fm(data, scene, seed, samples)
    toolchain.require_tools()
    records = golden.golden_session(q, wl, contact, seed=seed)
    steps = [r for r in records if r.op == golden.OP_STEP]
    macs = golden.step_macs(q, records)
    # The steps that run the force and location nets: contact, and the release band after it.
    step_contact = [estimate_shown(r.out["contact"], r.out["status"]) for r in steps]

    with _build_directory(build_dir) as build:
        ident = "target"
        hdr, src = codegen.fixed_source(q, ident)
        (build / f"{ident}_model.h").write_text(hdr)
        model_c = build / f"{ident}_model.c"
        model_c.write_text(src)
        golden_c = build / "golden_vectors.c"
        golden.write_golden_c(records, golden_c)
        log(f"{len(records)} golden records ({len(steps)} steps) from {data_src}")
        log("cross-compiling libfbgforce (portable, DSP, float)")
        csrc = sources.stage(build / "src")
        libs = firmware.build_libraries(csrc)
        builds: dict[str, Any] = {}
        for dsp in (False, True):
            name = "dsp" if dsp else "portable"
            log(f"firmware ({name}): build and run on QEMU mps2-an386")
            bdir = firmware.build_firmware(csrc, build, model_c, f"{ident}_model", golden_c, dsp)
            builds[name] = _replay(bdir, macs, step_contact, len(steps))
        headline = _headline_figures(builds, macs, step_contact)
        return {
            "bit_exact": all(b["bit_exact"] for b in builds.values()),
            "samples": len(steps),
            "records": len(records),
            **headline,
            "builds": builds,
            "model": source,
            "weight_bits": int(q.w_bits),
            "data": data_src,
            "nofloat_ok": libs["nofloat_ok"],
            "seconds": round(time.perf_counter() - t0, 2),
        }


@contextlib.contextmanager
def _build_directory(build_dir: str | Path | None) -> Iterator[Path]:
    """``build_dir``, made if missing, or else a temporary directory removed afterwards."""
    if build_dir is None:
        with tempfile.TemporaryDirectory(prefix="fbg-target-") as tmp:
            yield Path(tmp)
        return
    build = Path(build_dir).resolve()
    build.mkdir(parents=True, exist_ok=True)
    yield build


def _replay(bdir: Path, macs: list[int], step_contact: list[bool], n_steps: int
            ) -> dict[str, Any]:
    """Run one firmware build on QEMU: whether it replayed every step bit-exactly, its
    instructions, cycles and sizes."""
    run = firmware.run_firmware(bdir)
    ok = (run.exit_code == 0 and run.result.get("mismatches") == 0
          and run.result.get("model_swap_refused") == 1
          and run.result.get("steps") == n_steps and len(run.windows) == n_steps)
    sizes = firmware.map_sizes(bdir / "fw_size.map", exclude=("startup.o", "semihost.o", "main_size.o"))
    entry = {"bit_exact": ok, "exit_code": run.exit_code,
             "mismatches": run.result.get("mismatches"),
             "model_swap_refused": run.result.get("model_swap_refused") == 1,
             **_figures(run, macs, step_contact),
             **{f"{k}_bytes": v for k, v in sizes.items()},
             "stack_bytes": run.result.get("stack_bytes"),
             "state_bytes": run.result.get("state_bytes")}
    entry.update(_cycle_figures(run, bdir / "fw.elf"))
    # Instructions per replayed step by function (init and tare calls included: they
    # are a few hundred instructions in all), largest first.
    entry["profile_per_step"] = {k: round(v / max(n_steps, 1), 1)
                                 for k, v in list(run.profile.items())[:12]}
    if run.mismatch_lines:
        entry["first_mismatches"] = run.mismatch_lines[:3]
    if not run.result:
        entry["console"] = run.console[-2000:]
    return entry


def _headline_figures(builds: dict[str, Any], macs: list[int], step_contact: list[bool]
                      ) -> dict[str, Any]:
    """The report's headline figures: the DSP build's, the one firmware ships."""
    best = builds["dsp"]
    full = [m for m, cc in zip(macs, step_contact) if cc and m > 0]
    return {
        "instructions_per_step": best["instructions_per_step"],
        "macs_per_step": max(full) if full else max(macs, default=0),
        "instructions_per_mac": best["instructions_per_mac"],
        "text_bytes": best["text_bytes"],
        "rodata_bytes": best["rodata_bytes"],
        "data_bytes": best["data_bytes"],
        "bss_bytes": best["bss_bytes"],
        "flash_bytes": best["text_bytes"] + best["rodata_bytes"] + best["data_bytes"],
        "ram_bytes": best["data_bytes"] + best["bss_bytes"] + (best["state_bytes"] or 0)
                     + (best["stack_bytes"] or 0),
        "state_bytes": best["state_bytes"],
        "stack_bytes": best["stack_bytes"],
        "budget_fraction_at_168MHz": best["budget_fraction_at_168MHz"],
        "cycles_per_step_estimate": best.get("cycles_per_step_estimate"),
        "budget_fraction_cycles_at_168MHz": best.get("budget_fraction_cycles_at_168MHz"),
        "assumption": "budget_fraction_at_168MHz: one instruction per cycle (QEMU counts "
                      "instructions, not cycles); budget_fraction_cycles_at_168MHz: cycles "
                      "estimated from the worst step's executed instruction mix with the "
                      "Cortex-M4 TRM timings, zero-wait-state memory (fbgforce.target.cycles); "
                      "instructions_per_step is the worst step (contact: all three nets)",
    }
