"""``fbgforce bench-speed``: every engine side by side in one run (a small model, few samples).

Checks the table and the JSON (every engine, call and caller present, figures positive, ratios
consistent with the reference row, the C driver's outputs bit-exact with the extension's,
callgrind counts deterministic), not timings against thresholds. valgrind missing: the counts
are n/a and the callgrind checks skip, except under CI=true, where that fails.
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import require_tools
from fbgforce.cli import main
from fbgforce.tradeoff import cdriver, speed

# Small everything; the kernel builds (when the header offers kernels) have their own tests.
ARGS = ["--samples", "400", "--batch", "100", "--single-calls", "60", "--rounds", "1", "--reps", "2",
        "--count-samples", "30", "--count-warmup", "50", "--no-kernels"]


def _require(tool: str) -> None:
    require_tools(tool, install=tool)


@pytest.fixture(scope="module")
def result(small_exported_dir, small_dataset_path, tmp_path_factory):
    _require("gcc")
    out = tmp_path_factory.mktemp("bench_speed") / "speed.json"
    code = main(["bench-speed", "--model", str(small_exported_dir), "--data",
                 str(small_dataset_path), *ARGS, "--c-build", "O1=-O1", "--out", str(out)])
    assert code == 0
    return json.loads(out.read_text())


@pytest.mark.slow
def test_every_engine_call_and_caller(result):
    seen = {(r["engine"], r["call"], r["caller"], r["scope"], r["build"]) for r in result["rows"]}
    for engine in ("fixed", "fixed-int8", "cfloat"):
        for call in ("batch", "single"):
            assert (engine, call, "python", "pipeline", None) in seen
            for build in ("O1", "as-extension"):
                assert (engine, call, "c", "pipeline", build) in seen
    for engine in ("float", "onnx"):
        for call in ("batch", "single"):
            for scope in ("pipeline", "nets"):
                assert (engine, call, "python", scope, None) in seen
    assert len(seen) == len(result["rows"]), "a row appears twice"
    # Every batch from Python has the same length; from C one batch is all samples.
    assert {r["batch_size"] for r in result["rows"] if r["call"] == "batch"
            and r["caller"] == "python"} == {100}
    assert {r["batch_size"] for r in result["rows"] if r["call"] == "batch"
            and r["caller"] == "c"} == {400}
    assert [b["name"] for b in result["builds"]] == ["as-extension", "O1"]
    assert result["samples"] == 400 and result["count_samples"] == 30
    assert result["macs_per_step"] > 0 and result["platform"]["cpus"] >= 1


@pytest.mark.slow
def test_figures_positive_and_ratios_consistent(result):
    ref = [r for r in result["rows"] if (r["engine"], r["call"], r["scope"]) ==
           tuple(result["reference"][k] for k in ("engine", "call", "scope"))]
    assert len(ref) == 1 and ref[0]["ratio"] == pytest.approx(1.0)
    for r in result["rows"]:
        assert r["ns_per_sample"] is not None and r["ns_per_sample"] > 0, r
        assert r["ratio"] == pytest.approx(r["ns_per_sample"] / ref[0]["ns_per_sample"])
        if r["caller"] == "c" and r["engine"] != "cfloat" and r["call"] == "batch":
            assert r["bit_exact"] is True, r          # fbg_run from C == the extension's bits


@pytest.mark.slow
def test_callgrind_counts_deterministic(result, small_exported_dir, small_dataset_path, tmp_path):
    _require("valgrind")
    counted = {(r["engine"], r["build"]): r["instructions_per_step"] for r in result["rows"]
               if r["caller"] == "c" and r["call"] == "single"}
    assert all(v is not None and v > 1000 for v in counted.values()), counted
    # What holds for every build and kernel: every step runs all three nets, so it executes
    # at least one instruction per 16 MACs (the host SIMD kernels run at -O1 too, and the
    # widest, AVX2, does 16 MACs per VPMADDWD).
    assert counted[("fixed", "O1")] >= result["macs_per_step"] / 16
    # Counting again gives the same figure: the count is noise-free.
    from fbgforce.recordings import dataset as fds
    from fbgforce.pybind import to_fm
    from fbgforce.recordings.tare import tare
    from fbgforce.tradeoff.timers import timing_samples

    row = next(r for r in result["rows"] if (r["engine"], r["build"], r["call"], r["caller"]) ==
               ("fixed", "O1", "single", "c"))
    start, n = row["counted_steps"]["start"], row["counted_steps"]["n"]
    assert start >= result["count_warmup"] and 0 < n <= result["count_samples"]
    ds = fds.load(small_dataset_path)
    wl = timing_samples(ds)[:start + n]
    cdriver.write_samples(tmp_path / "s.bin", to_fm(tare(ds.wl_nm, ds.contact, ds.t_s)[0]),
                          to_fm(wl))
    exe = cdriver.build(cdriver.parse_build("O1=-O1"), tmp_path / "b",
                        cdriver.float_model_source(small_exported_dir))
    again, profile = cdriver.count_instructions(exe, "fixed", small_exported_dir / "model.fbgm",
                                                tmp_path / "s.bin", start, n)
    assert again == counted[("fixed", "O1")]
    # The per-function profile adds up to the step (every function, self costs).
    if shutil.which("callgrind_annotate"):
        assert sum(profile.values()) == pytest.approx(again)
        assert "fbg_step" in profile and row["profile_per_step"]


def test_contact_window():
    c = np.array([1, 1, 0, 1, 1, 1, 0, 1, 1, 1, 1, 1], dtype=bool)
    assert speed.contact_window(c, 2, 4) == (7, 4)      # the first full run after the warm-up
    assert speed.contact_window(c, 2, 9) == (7, 5)      # else the longest
    assert speed.contact_window(c, 0, 2) == (0, 2)
    assert speed.contact_window(np.zeros(5, bool), 0, 2) is None


@pytest.mark.slow
def test_table_lists_every_row(result):
    table = speed.markdown_table(result)
    lines = [ln for ln in table.splitlines() if ln.startswith("| ") and "---" not in ln]
    assert len(lines) == 1 + len(result["rows"])
    assert "bit-exact vs extension" in table and "DIFFERS" not in table
    assert np.isfinite([r["ns_per_sample"] for r in result["rows"]]).all()


def test_extension_flags_are_the_builders():
    text = (cdriver.REPOSITORY / "runtime_c" / "build_runtime.py").read_text()
    flags = cdriver.extension_flags()
    assert flags and all(f'"{f}"' in text for f in flags.split())


def test_parse_build():
    # A --c-build runs as the extension does: packed weights where the kernel has them.
    assert cdriver.parse_build("native=-O3 -march=native") == cdriver.CBuild("native", "-O3 -march=native",
                                                                             packed=True)
    assert cdriver.parse_build("-O2") == cdriver.CBuild("-O2", "-O2", packed=True)
    with pytest.raises(ValueError):
        cdriver.parse_build("=-O2")


def test_one_build_per_kernel_the_header_offers(monkeypatch):
    from fbgforce.target import sources

    monkeypatch.setattr(sources, "header_constants", lambda: {
        "FBG_OK": 0, "FBG_OPT_REQUIRE_TARE": 1, "FBG_OPT_KERNEL_MASK": 0xF0,
        "FBG_OPT_KERNEL_AUTO": 0, "FBG_OPT_KERNEL_SSE2": 0x20, "FBG_OPT_KERNEL_PORTABLE": 0x10})
    builds = speed.default_builds()
    flags = cdriver.extension_flags()
    # Every kernel on the model's weights, and once more packed where it has a packed form.
    assert builds == (cdriver.CBuild("as-extension", flags, packed=True),
                      cdriver.CBuild("kernel-portable", flags, 0x10),
                      cdriver.CBuild("kernel-sse2", flags, 0x20),
                      cdriver.CBuild("kernel-sse2-packed", flags, 0x20, packed=True))


@pytest.mark.slow
@pytest.mark.parametrize("kernel", ["sse2", "avx2"])
def test_packed_driver_builds_give_the_extensions_bits(kernel, small_exported_dir, small_dataset_path,
                                                       tmp_path):
    """The driver's packed runs (fbg_pack into its own buffer, fbg_use_pack after every
    restart) give the extension's fbg_run bits."""
    _require("gcc")
    from fbgforce.recordings import dataset as fds
    from fbgforce.pybind import KERNELS, ArgError, Runtime, to_fm
    from fbgforce.recordings.tare import tare
    from fbgforce.tradeoff.timers import timing_samples

    try:
        rt = Runtime(small_exported_dir, kernel=kernel)
    except ArgError:
        pytest.skip(f"this CPU or build does not run {kernel}")
    assert rt.packed
    ds = fds.load(small_dataset_path)
    base = to_fm(tare(ds.wl_nm, ds.contact, ds.t_s)[0])
    wl = to_fm(timing_samples(ds)[:300])
    cdriver.write_samples(tmp_path / "s.bin", base, wl)
    exe = cdriver.build(cdriver.CBuild(f"kernel-{kernel}-packed", cdriver.extension_flags() or "",
                                       KERNELS[kernel], packed=True), tmp_path / "b")
    cdriver.time_run(exe, "fixed", small_exported_dir / "model.fbgm", tmp_path / "s.bin", 1,
                     tmp_path / "out.bin")
    rt.set_baseline(base)
    assert (tmp_path / "out.bin").read_bytes() == rt.run_raw(wl).tobytes()
