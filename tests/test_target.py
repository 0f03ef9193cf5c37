"""Cortex-M4 target: cross builds, golden vectors on QEMU, instruction counts, sizes.

Needs arm-none-eabi-gcc, newlib and qemu-system-arm; without them every test here SKIPS with
the apt line to install, except under CI=true, where a missing tool is a FAILURE.
"""
from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import pytest

from conftest import missing_tool
from fbgforce import contract
from fbgforce.model import artifact, modeldir
from fbgforce.target import firmware, golden, sources, toolchain
from fbgforce.target.report import load_quantized, recording_fm, target_report

ROOT = Path(__file__).resolve().parent.parent
#: Recording samples replayed per report (edge cases and API calls come on top): enough for
#: contact and no-contact steps, small enough to keep each QEMU run around a second.
SAMPLES = 300


def _require_tools() -> None:
    missing = toolchain.missing_tools()
    if missing:
        missing_tool(f"Cortex-M4 tools missing ({', '.join(missing)}); install: {toolchain.APT_LINE}")


@pytest.fixture(scope="module")
def tools() -> None:
    _require_tools()


@pytest.fixture(scope="module")
def report(tools, small_model_dir, tmp_path_factory):
    """The report of the shared small model (int16), build kept for the other tests."""
    build = tmp_path_factory.mktemp("target_build")
    rep = target_report(small_model_dir, samples=SAMPLES, build_dir=build)
    rep["_build"] = build
    return rep


def test_missing_tools_message_names_apt_packages(monkeypatch):
    monkeypatch.setattr(toolchain.shutil, "which", lambda name: None)
    with pytest.raises(toolchain.ToolchainMissing) as exc:
        toolchain.require_tools()
    for pkg in toolchain.APT_PACKAGES:
        assert pkg in str(exc.value)


def test_golden_session_covers_every_status_and_api_call(small_model_dir):
    """The replayed session is not just a recording: every status flag, contact and no
    contact, refused tare samples, error returns and every API call occur (no tools needed)."""
    q, _ = load_quantized(Path(small_model_dir))
    wl, contact, _ = recording_fm(None, "smoke", 0, SAMPLES)
    recs = golden.golden_session(q, wl, contact)
    c = sources.header_constants()
    steps = [r for r in recs if r.op == golden.OP_STEP]
    for flag in ("NOT_TARED", "SATURATED", "OVERLOAD", "SENSOR_FAULT", "WARMUP"):
        assert any(r.out["status"] & c[f"FBG_STATUS_{flag}"] for r in steps), flag
    assert any(r.out["contact"] for r in steps) and not all(r.out["contact"] for r in steps)
    assert {r.op for r in recs} == set(range(7))
    assert any(r.op == golden.OP_TARE_ADD and r.accepted == 0 for r in recs)
    assert {c["FBG_ERR_ARG"], c["FBG_ERR_TARE"]} <= {r.status for r in recs}


def test_step_macs_count_the_nets_of_the_release_band(small_model_dir):
    """The force and location nets run in contact and in the release band after it (contact 0,
    RELEASING): both count their MACs; a rest runs the contact net alone, a fault nothing."""
    q, _ = load_quantized(Path(small_model_dir))
    flag = contract.STATUS_FLAG
    outs = [{"contact": 1, "status": 0}, {"contact": 0, "status": flag["RELEASING"]},
            {"contact": 0, "status": 0}, {"contact": 0, "status": flag["SENSOR_FAULT"]}]
    macs = golden.step_macs(q, [golden.Record(golden.OP_STEP, out=o) for o in outs])
    fir, nets = 4 * int(q.taps.size), [sum(ly.n_in * ly.n_out for ly in n) for n in q.nets]
    assert macs == [fir + sum(nets), fir + sum(nets), fir + nets[0], 0]


@pytest.mark.target
def test_cross_libraries_build_clean_and_without_float(tools):
    """-Werror builds of the three libraries, and the soft-float symbol scan passes."""
    r = subprocess.run(["make", "-s", "-C", str(ROOT / "runtime_c"), "-f", "target.mk", "target-libs"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "warning" not in (r.stdout + r.stderr).lower()
    for lib in ("build/cm4/libfbgforce.a", "build/cm4-dsp/libfbgforce.a", "build/cm4f/libfbgforce_float.a"):
        assert (ROOT / "runtime_c" / lib).is_file()
    # The DSP build really contains the dual 16-bit MAC.
    dis = subprocess.run(["arm-none-eabi-objdump", "-d", str(ROOT / "runtime_c/build/cm4-dsp/libfbgforce.a")],
                         capture_output=True, text=True).stdout
    assert "smlald" in dis


@pytest.mark.target
def test_nofloat_check_catches_a_float_helper(tools, tmp_path):
    """The check is not vacuous: a library with one float multiply fails it."""
    src = tmp_path / "f.c"
    src.write_text("float scale(float a, int b) { return a * (float)b; }\n")
    obj, lib = tmp_path / "f.o", tmp_path / "libbad.a"
    subprocess.run(["arm-none-eabi-gcc", "-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=soft", "-O2",
                    "-c", str(src), "-o", str(obj)], check=True)
    subprocess.run(["arm-none-eabi-ar", "rcs", str(lib), str(obj)], check=True)
    r = subprocess.run(["make", "-s", "-C", str(ROOT / "runtime_c"), "-f", "target.mk",
                        "target-check-nofloat", f"TARGET_LIB={lib}", f"TARGET_LIB_DSP={lib}"],
                       capture_output=True, text=True)
    assert r.returncode != 0
    assert "__aeabi_fmul" in r.stderr


@pytest.mark.target
@pytest.mark.parametrize("dsp_asm", ["1", "0"], ids=["assembly", "acle-c"])
def test_dsp_kernels_equal_the_rules_on_random_layers(tools, tmp_path, dsp_asm):
    """fbg_dsp*.c against docs/fixed-point.md on QEMU: odd widths, unaligned rows, all shifts,
    extreme multipliers, rounding ties, saturation, random FIR ring positions, the hidden-layer
    loop, the output rows' rounded product and the standardisation; the assembly kernels and
    (FBG_DSP_ASM=0) their ACLE C versions."""
    r = subprocess.run(["make", "-s", "-C", str(ROOT / "examples" / "firmware"), f"BUILD={tmp_path}",
                        f"DSP_ASM={dsp_asm}", "kernel-test"],
                       capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=120)
    line = next((ln for ln in (r.stdout + r.stderr).splitlines() if ln.startswith("KERNEL_TEST")), "")
    fields = dict(kv.split("=") for kv in line.split()[1:])
    assert r.returncode == 0 and fields.get("mismatches") == "0", r.stdout + r.stderr
    # Both three-row paths (assembly: rows3_asm and rows3d_asm), the first-layer path and
    # saturation were exercised.
    assert int(fields["fast"]) > 300 and int(fields["first"]) > 100 and int(fields["int8"]) > 300
    assert 100 < int(fields["aligned"]) < int(fields["fast"]) - 100  # both rows3 variants
    assert int(fields["saturated"]) > 100
    # int32 layers (acc32): SMLAD/SMMULR pair kernels (first2d32_asm, rows2d32_asm) and the C
    # rows, with half the cases driving row 0's accumulator exactly to the loader's int32 bound;
    # int8 weights through rows2b32_asm / first2b32_asm and the C rows.
    assert int(fields["acc32"]) > 500 and int(fields["acc32_fast"]) > 40
    assert int(fields["acc32_first"]) > 30 and int(fields["acc32_at_bound"]) > 400
    assert int(fields["acc32_first_wide"]) > 20  # first layers of 10 and 12 inputs
    # and every entry of the first-layer kernel: 2-12 inputs, every pair count modulo 4
    assert int(fields["first_sweep"]) == 96
    assert int(fields["acc32_saturated"]) > 100
    assert int(fields["acc32_int8"]) > 300 and int(fields["acc32_int8_saturated"]) > 100
    assert int(fields["acc32_int8_fast"]) > 50
    # The DSP standardisation on random parameters: clamping and exact cases, and the load
    # proxy on both sides of its limit.
    assert int(fields["standardise_clamped"]) > 300 and int(fields["standardise_exact"]) > 300
    assert 300 < int(fields["standardise_overload"]) < 1200


@pytest.mark.target
def test_golden_vectors_bit_exact_on_target_both_builds(report):
    assert report["bit_exact"] is True
    for name in ("portable", "dsp"):
        b = report["builds"][name]
        assert b["bit_exact"] and b["exit_code"] == 0 and b["mismatches"] == 0, b
        assert b["model_swap_refused"] is True, b  # FBG_ERR_MODEL_CHANGED on the target
    assert report["samples"] >= SAMPLES and report["records"] > report["samples"]


@pytest.mark.target
def test_instruction_counts_and_figures(report, small_model_dir):
    port, dsp = report["builds"]["portable"], report["builds"]["dsp"]
    assert report["macs_per_step"] > 1000
    assert 0 < dsp["instructions_per_step"] < port["instructions_per_step"]
    # The DSP path must at least halve the cost per MAC of the portable C.
    assert dsp["instructions_per_mac"] < 0.5 * port["instructions_per_mac"]
    assert report["instructions_per_mac"] == dsp["instructions_per_mac"]
    assert report["budget_fraction_at_168MHz"] == pytest.approx(
        report["instructions_per_step"] / 168_000, abs=1e-4)
    # Generated weights are 8-byte aligned (codegen) and so are the activation buffers of
    # fbg_state, so every hidden layer of an even width takes an LDRD kernel, never the
    # unaligned fallback, and no input is copied. The exporter proves int32 accumulators for
    # this model's layers, so the SMLAD/SMMULR kernels run (docs/fixed-point.md).
    prof = dsp["profile_per_step"]
    assert "fbg_dsp_rows2d32_asm" in prof and "fbg_dsp_rows3_asm" not in prof
    assert "fbg_dsp_first2d32_asm" in prof  # first layers (<= 12 inputs): inputs held in registers
    assert "memcpy" not in prof
    # A step without contact runs only the contact net: far cheaper than the worst step.
    assert dsp["instructions_per_step_no_contact_max"] < 0.6 * dsp["instructions_per_step"]
    for key in ("text_bytes", "rodata_bytes", "data_bytes", "bss_bytes", "state_bytes", "stack_bytes"):
        assert isinstance(report[key], int) and report[key] >= 0, key
    assert report["text_bytes"] > 1000 and report["rodata_bytes"] > 1000
    # Budgets that are exact, deterministic figures: flash and static RAM.
    # 48 KB held until the parameter checks became generated (every field of the contract is
    # range-checked at fbg_init: +1.2 KB of code) and the nets gained memory inputs (+1.7 KB
    # of weights and code at the default memory): 52 KB; the location averages of the default
    # memory add 0.56 KB of location-net weights and 0.4 KB of code: 54 KB; the decision over
    # time, the at-rest tracker and the input range check add 1.4 KB of code and parameters:
    # 56 KB; the CUSUM rise of the contact decision and the generated checks of its four
    # parameters took it to 57,566 B: 58 KB (docs/firmware.md).
    assert report["flash_bytes"] < 58 * 1024
    assert report["ram_bytes"] < 4 * 1024


@pytest.mark.target
def test_cycle_estimate_of_the_worst_step(report):
    """Cycles from the worst step's instruction mix: every executed instruction priced (the
    mix adds up to the worst step's count), more cycles than instructions (loads, LDM, taken
    branches), the range ordered by pipeline-refill cost."""
    dsp = report["builds"]["dsp"]
    mix = dsp["cycle_mix"]
    assert sum(n for n, _ in mix.values()) == dsp["instructions_per_step"]
    assert sum(c for _, c in mix.values()) == dsp["cycles_per_step_estimate"]
    lo, hi = dsp["cycles_per_step_range"]
    assert lo < dsp["cycles_per_step_estimate"] < hi
    assert 1.0 < dsp["cycles_per_instruction"] < 3.0
    assert mix["multiply"][0] > 0 and mix["load_store_multiple"][0] > 0
    assert sum(dsp["worst_step_by_function"].values()) == dsp["instructions_per_step"]
    assert report["budget_fraction_cycles_at_168MHz"] == pytest.approx(
        dsp["cycles_per_step_estimate"] / 168_000, abs=1e-4)


@pytest.mark.target
def test_counts_are_deterministic(report):
    """Two QEMU runs of the same firmware give identical per-step counts."""
    build = report["_build"] / "dsp"
    a, b = firmware.run_firmware(build), firmware.run_firmware(build)
    assert a.exit_code == 0 and a.windows == b.windows and len(a.windows) == report["samples"]


@pytest.mark.target
def test_firmware_reports_a_single_flipped_bit(report, small_model_dir):
    """The on-target comparison can fail: expected outputs off by one LSB in one record."""
    q, _ = load_quantized(Path(small_model_dir))
    wl, contact, _ = recording_fm(None, "smoke", 0, 96)
    recs = golden.golden_session(q, wl, contact)
    idx = next(i for i, r in enumerate(recs) if r.op == golden.OP_STEP and r.out["contact"])
    recs[idx].out["x_um"] += 1
    from fbgforce.export import codegen

    bdir = report["_build"] / "bad"
    bdir.mkdir()
    hdr, src = codegen.fixed_source(q, "bad")
    (bdir / "bad_model.h").write_text(hdr)
    (bdir / "bad_model.c").write_text(src)
    golden_c = bdir / "golden_bad.c"
    golden.write_golden_c(recs, golden_c)
    # The C tree the report staged (and already built the libraries in).
    firmware_dir = report["_build"] / "src" / "examples" / "firmware"
    subprocess.run(["make", "-s", "-C", str(firmware_dir), f"BUILD={bdir}", "DSP=1",
                    f"MODEL_C={bdir / 'bad_model.c'}", "MODEL_SYM=bad_model",
                    f"GOLDEN_C={golden_c}", "all", f"{bdir}/insn_window.so"], check=True,
                   capture_output=True)
    run = firmware.run_firmware(bdir)
    assert run.exit_code == 1
    assert run.result["mismatches"] == 1 and run.result["first_mismatch"] == idx
    assert f"record={idx}" in run.mismatch_lines[0]


@pytest.mark.target
def test_int8_weights_bit_exact(tools, small_model_dir):
    rep = target_report(small_model_dir, samples=128, bits=8)
    assert rep["bit_exact"] and rep["weight_bits"] == 8


@pytest.mark.target
def test_temperature_reference_average_bit_exact_on_target(tools, small_model_dir, tmp_path):
    """The temperature reference's average at its longest (ref_shift 8: the largest
    accumulator) on both Cortex-M4 builds, through the golden session's faults, tares, resets
    and new baselines."""
    d = tmp_path / "model"
    shutil.copytree(small_model_dir, d)
    model = modeldir.load(d)
    model.preprocess = replace(model.preprocess, ref_shift=contract.LIMIT["MAX_REF_SHIFT"])
    modeldir.save(model, d)
    rep = target_report(d, samples=128)
    assert rep["bit_exact"] is True
    for name in ("portable", "dsp"):
        assert rep["builds"][name]["bit_exact"] and rep["builds"][name]["mismatches"] == 0


@pytest.mark.target
def test_tracker_creep_term_bit_exact_on_target(tools, small_model_dir, tmp_path):
    """The at-rest tracker's creep term at its largest magnitude (0.5) on both Cortex-M4
    builds, with a tracker quick enough to move the baseline within the golden session
    (which it does differently without the term), through its faults, tares, resets and new
    baselines."""
    d = tmp_path / "model"
    shutil.copytree(small_model_dir, d)
    model = modeldir.load(d)
    model.in_use = replace(model.in_use, track_shift=4, track_settle=0, track_step_max_pm=50.0,
                           track_creep=0.5, track_creep_shift=3)
    modeldir.save(model, d)
    q, _ = load_quantized(d)
    assert q.track_creep_q15 == contract.LIMIT["MAX_TRACK_CREEP_Q15"]
    # The recording's first rest long enough for tracker blocks.
    _changes_the_session_and_is_bit_exact(d, q, replace(q, track_creep_q15=0, track_creep_shift=0),
                                          2 * SAMPLES)


def _changes_the_session_and_is_bit_exact(d, q, off, samples: int) -> None:
    """The model in ``d`` (quantised ``q``) answers the golden session otherwise than ``off``
    (the same without the stage under test) and both Cortex-M4 builds run it bit-exact."""
    wl, contact, _ = recording_fm(None, "smoke", 0, samples)

    def steps(qm) -> list[dict[str, int]]:
        return [r.out for r in golden.golden_session(qm, wl, contact) if r.op == golden.OP_STEP]

    assert steps(q) != steps(off)
    rep = target_report(d, samples=samples)
    assert rep["bit_exact"] is True
    for name in ("portable", "dsp"):
        assert rep["builds"][name]["bit_exact"] and rep["builds"][name]["mismatches"] == 0


@pytest.mark.target
def test_creep_inverse_bit_exact_on_target(tools, small_model_dir, tmp_path):
    """The pad's creep inverse at its largest gain (magnitude 0.5, time constant 2^15) on both
    Cortex-M4 builds through the golden session (which it changes), its faults, tares, resets
    and new baselines re-priming it."""
    d = tmp_path / "model"
    shutil.copytree(small_model_dir, d)
    model = modeldir.load(d)
    model.preprocess = replace(model.preprocess, creep=0.5, creep_shift=15)
    modeldir.save(model, d)
    q, _ = load_quantized(d)
    assert q.creep_q15 == round(model.preprocess.creep_gain * 2**15) > 32000
    _changes_the_session_and_is_bit_exact(d, q, replace(q, creep_q15=0, creep_shift=0), SAMPLES)


@pytest.mark.target
def test_settled_hold_gain_bit_exact_on_target(tools, small_model_dir, tmp_path):
    """The settled-hold gain at its largest (12.5 %), quick to settle and with the whole band,
    on both Cortex-M4 builds through the golden session (which it changes), its faults,
    tares and resets clearing it."""
    d = tmp_path / "model"
    shutil.copytree(small_model_dir, d)
    model = modeldir.load(d)
    model.in_use = replace(model.in_use, hold_gain=artifact.HOLD_GAIN_MAX, hold_settle=2,
                           hold_band_N=1000.0, hold_band_frac=1.0, hold_shift=3, hold_ramp_shift=2)
    modeldir.save(model, d)
    q, _ = load_quantized(d)
    assert q.hold_gain_q15 == contract.LIMIT["MAX_HOLD_GAIN_Q15"]
    _changes_the_session_and_is_bit_exact(d, q, replace(q, hold_gain_q15=0), SAMPLES)


@pytest.mark.target
def test_cusum_decision_bit_exact_on_target(tools, small_model_dir, tmp_path):
    """The decision's CUSUM rise with a low threshold and a narrow clip on both Cortex-M4
    builds through the golden session (which it changes), its faults holding S and its tares
    and resets clearing it."""
    d = tmp_path / "model"
    shutil.copytree(small_model_dir, d)
    model = modeldir.load(d)
    own = model.in_use
    model.in_use = replace(own, contact_on_margin=0.0, contact_rise_samples=1,
                           contact_cusum_h=4.0, contact_cusum_k=0.5, contact_cusum_lo=-2.0,
                           contact_cusum_hi=2.5)
    modeldir.save(model, d)
    q, _ = load_quantized(d)
    assert (q.contact_cusum_h_q8, q.contact_cusum_k_q8) == (1024, 128)
    off = replace(q, contact_cusum_h_q8=0, contact_cusum_k_q8=0, contact_cusum_lo_q8=0,
                  contact_cusum_hi_q8=0)
    _changes_the_session_and_is_bit_exact(d, q, off, SAMPLES)


@pytest.mark.target
def test_cli_json(tools, small_model_dir, capsys):
    from fbgforce.cli import main

    assert main(["target-report", "--model", str(small_model_dir), "--samples", "96", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("bit_exact", "samples", "instructions_per_step", "macs_per_step",
                "instructions_per_mac", "text_bytes", "rodata_bytes", "data_bytes", "bss_bytes",
                "budget_fraction_at_168MHz"):
        assert key in out, key
    assert out["bit_exact"] is True
    assert "one instruction per cycle" in out["assumption"]


@pytest.mark.target
def test_cli_bad_model_dir_exits_2(tools, tmp_path, capsys):
    from fbgforce.cli import main

    assert main(["target-report", "--model", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err
