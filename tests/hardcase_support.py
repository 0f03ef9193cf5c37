"""What the hard-case tests share (tests/test_hardcases_inputs.py: hard inputs to the
runtime; tests/test_hardcases_bounds.py: the quantised model's numerical bounds and the blobs
the loader refuses; the table in docs/robustness.md).

Every case runs the fixed-point runtime three ways and demands the same bits:

1. the cffi module (``fbgforce._runtime``) through ``fbg_init/tare/set_baseline/step/run``;
2. ``hardcase_driver`` (runtime_c/fuzz/hardcase_driver.c), a plain C program built by default
   with AddressSanitizer + UndefinedBehaviorSanitizer (``make -C runtime_c asan-driver``), or
   the binary named by ``FBGFORCE_HARDCASE_DRIVER`` (``make valgrind-check`` points it at the
   plain build and sets ``FBGFORCE_HARDCASE_WRAPPER`` to valgrind); ``=off`` disables it;
3. the numpy integer reference ``fbgforce.export.intref``.

and checks every output against the contract of fbgforce.h (:func:`assert_contract`, the same
rules as ``hc_check_output`` in runtime_c/fuzz/fuzz_common.h) and the sensor-fault flag
against an independent evaluation of the fault rule. Figures quoted in docs/robustness.md are
printed with ``-s`` and written to ``$FBGFORCE_HARDCASE_REPORT`` (JSON) when that is set: the
figures of every hard-case file run in the session, in one report.
"""
from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce import contract
import pytest

from fbgforce.export import intref
from fbgforce.export.blob import from_bytes, to_bytes
from fbgforce.export.intref import WL_MAX_FM, WL_MIN_FM
from fbgforce.export.qmodel import SAT32

ROOT = Path(__file__).resolve().parents[1]
RUNTIME_C = ROOT / "runtime_c"
INT32_MIN, INT32_MAX = -2**31, 2**31 - 1
INT64_MAX = 2**63 - 1
FIELDS = contract.OUTPUT_FIELDS
FAULT, SATURATED, OVERLOAD = (intref.STATUS_SENSOR_FAULT, intref.STATUS_SATURATED,
                              intref.STATUS_OVERLOAD)
NOT_TARED, WARMUP = intref.STATUS_NOT_TARED, intref.STATUS_WARMUP
RELEASING = intref.STATUS_RELEASING
ALL_FLAGS = contract.STATUS_ALL
TARE_ROWS = 150  # every scene below starts with >= 0.2 s at rest


def _load_support():
    spec = importlib.util.spec_from_file_location("fbg_hardcases", RUNTIME_C / "fuzz" / "hardcases.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


hc = _load_support()
RESULTS: dict[str, dict[str, Any]] = {}


def record(case: str, **figures: Any) -> None:
    """Keep figures for docs/robustness.md (printed; JSON via FBGFORCE_HARDCASE_REPORT)."""
    RESULTS.setdefault(case, {}).update(figures)
    print(f"[hardcase] {case}: " + ", ".join(f"{k}={v}" for k, v in figures.items()))


@pytest.fixture(scope="module", autouse=True)
def write_report():
    yield
    path = os.environ.get("FBGFORCE_HARDCASE_REPORT")
    if path:
        Path(path).write_text(json.dumps(RESULTS, indent=2, default=str) + "\n")


# --------------------------------------------------------------------------------------------
# Engines: cffi, driver, integer reference
# --------------------------------------------------------------------------------------------

_lib_mod = pytest.importorskip("fbgforce.pybind")
ffi, lib = _lib_mod.ffi, _lib_mod.lib
C_OUTPUT = np.dtype(contract.numpy_dtype(contract.OUTPUT))
assert C_OUTPUT.itemsize == ffi.sizeof("fbg_output")


class CModel:
    """A blob loaded by the C loader from an 8-aligned copy, plus one state."""

    def __init__(self, blob: bytes) -> None:
        self.buf = ffi.new("uint64_t[]", max(1, (len(blob) + 7) // 8))
        ffi.memmove(self.buf, blob, len(blob))
        self.model = ffi.new("fbg_model *")
        status = lib.fbg_model_from_blob(self.model, ffi.cast("uint8_t *", self.buf), len(blob))
        assert status == 0, ffi.string(lib.fbg_status_str(status))
        self.state = ffi.new("fbg_state *")

    def init(self, options: int = 0) -> int:
        return lib.fbg_init(self.state, self.model, options)

    def run(self, wl: np.ndarray, mode: str = "run") -> tuple[int, np.ndarray]:
        rows = np.ascontiguousarray(np.asarray(wl, dtype=np.int64).reshape(-1, 5).astype(np.int32))
        out = np.zeros(rows.shape[0], dtype=C_OUTPUT)
        if rows.shape[0] == 0:
            return 0, out
        wp = ffi.cast("int32_t *", ffi.from_buffer(rows))
        op = ffi.cast("fbg_output *", ffi.from_buffer(out))
        if mode == "run":
            return lib.fbg_run(self.state, wp, rows.shape[0], op), out
        status = 0
        for i in range(rows.shape[0]):
            s = lib.fbg_step(self.state, wp + 5 * i, op + i)
            status = status or s
        return status, out


def _as_fields(out: np.ndarray) -> dict[str, np.ndarray]:
    return {k: np.asarray(out[k], dtype=np.int64) for k in FIELDS}


def exec_cffi(blob: bytes, ops: list[tuple]) -> list[dict[str, Any]]:
    """The driver's protocol (hardcases.encode_ops) executed through the cffi module."""
    c = CModel(blob)
    res = []
    for op in ops:
        kind = op[0]
        if kind == "init":
            res.append({"op": hc.OP_INIT, "status": c.init(int(op[1]))})
        elif kind == "tare":
            rows = np.ascontiguousarray(np.asarray(op[1], dtype=np.int64).reshape(-1, 5).astype(np.int32))
            acc, accepted = ffi.new("int *"), 0
            status = lib.fbg_tare_begin(c.state)
            wp = ffi.cast("int32_t *", ffi.from_buffer(rows))
            for i in range(rows.shape[0]):
                if status:
                    break
                acc[0] = 0
                status = lib.fbg_tare_add(c.state, wp + 5 * i, acc)
                accepted += acc[0]
            if status == 0:
                status = lib.fbg_tare_end(c.state)
            base = ffi.new("int32_t[5]")
            lib.fbg_get_baseline(c.state, base)
            res.append({"op": hc.OP_TARE, "status": status, "accepted": accepted,
                        "baseline_fm": np.array(list(base), dtype=np.int64)})
        elif kind == "base":
            b = np.ascontiguousarray(np.asarray(op[1], dtype=np.int64).reshape(5).astype(np.int32))
            res.append({"op": hc.OP_BASE,
                        "status": lib.fbg_set_baseline(c.state, ffi.cast("int32_t *", ffi.from_buffer(b)))})
        elif kind in ("run", "step"):
            status, out = c.run(op[1], kind)
            res.append({"op": hc.OP_RUN if kind == "run" else hc.OP_STEP, "status": status,
                        "out": _as_fields(out)})
        elif kind == "reset":
            res.append({"op": hc.OP_RESET, "status": lib.fbg_reset(c.state)})
    return res


def assert_same_results(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b)
    for i, (x, y) in enumerate(zip(a, b)):
        assert x.keys() == y.keys(), i
        for k in x:
            if k == "out":
                for f in FIELDS:
                    np.testing.assert_array_equal(x[k][f], y[k][f], err_msg=f"op {i} field {f}")
            elif isinstance(x[k], np.ndarray):
                np.testing.assert_array_equal(x[k], y[k], err_msg=f"op {i} {k}")
            else:
                assert x[k] == y[k], (i, k, x[k], y[k])


_DRIVER: dict[str, Path | None] = {}


@pytest.fixture(scope="session")
def driver(tmp_path_factory) -> Path | None:
    """The external driver, found or built once for every hard-case file of the session."""
    if "path" not in _DRIVER:
        _DRIVER["path"] = _find_or_build_driver(tmp_path_factory)
    return _DRIVER["path"]


def _find_or_build_driver(tmp_path_factory) -> Path | None:
    """The external driver: $FBGFORCE_HARDCASE_DRIVER, else the ASan+UBSan build (if gcc)."""
    env = os.environ.get("FBGFORCE_HARDCASE_DRIVER", "")
    if env.lower() in ("0", "off", "no", "none"):
        return None
    if env:
        return Path(env)
    if shutil.which("gcc") is None or shutil.which("make") is None:
        return None  # cffi and the integer reference still run every case
    build = tmp_path_factory.mktemp("hardening")
    p = subprocess.run(["make", "-s", "-C", str(RUNTIME_C), "asan-driver", f"HARD_BUILD={build}"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr
    return build / "asan" / "hardcase_driver"


def execute(blob: bytes, ops: list[tuple], driver: Path | None) -> list[dict[str, Any]]:
    """cffi result; the driver (sanitizers/valgrind) must give exactly the same."""
    res = exec_cffi(blob, ops)
    if driver is not None:
        assert_same_results(res, hc.run_driver(driver, blob, ops))
    return res


# --------------------------------------------------------------------------------------------
# Oracles
# --------------------------------------------------------------------------------------------

def fault_oracle(wl: np.ndarray, jump_max_fm: int, stuck_max: int = 0) -> np.ndarray:
    """The sensor-fault rule of fbgforce.h, evaluated independently of intref and C (a plain
    loop per channel): a channel outside [WL_MIN, WL_MAX]; or jumping more than jump_max from
    its previous in-window value; or (stuck_max > 0) repeating that value for stuck_max
    consecutive samples (the run restarts on any change or out-of-window sample)."""
    wl = np.asarray(wl, dtype=np.int64).reshape(-1, 5)
    inwin = (wl >= WL_MIN_FM) & (wl <= WL_MAX_FM)
    fault = ~inwin.all(axis=1)
    for c in range(5):
        idx = np.flatnonzero(inwin[:, c])
        if idx.size > 1:
            jumped = np.abs(np.diff(wl[idx, c])) > jump_max_fm
            fault[idx[1:][jumped]] = True
        if stuck_max:
            run, prev = 0, None
            col, win = wl[:, c].tolist(), inwin[:, c].tolist()
            for t in range(len(col)):
                if not win[t]:
                    run = 0
                    continue
                run = min(run + 1, 0xFFFF) if prev is not None and col[t] == prev else 0
                prev = col[t]
                if run >= stuck_max:
                    fault[t] = True
    return fault


def assert_contract(out: dict[str, np.ndarray], q, wl: np.ndarray, tared: bool) -> None:
    """fbgforce.h's output contract on every sample (= hc_check_output, vectorised)."""
    st = out["status"]
    assert not np.any(st & ~ALL_FLAGS), "undefined status bit"
    assert np.isin(out["contact"], (0, 1)).all()
    assert ((out["contact_conf_q15"] >= 0) & (out["contact_conf_q15"] <= 32767)).all()
    for k in ("force_mN", "x_um", "y_um", "contact_margin_q8"):
        assert (np.abs(out[k]) <= SAT32).all(), f"{k} outside +-(2^31-1)"
    assert (((st & NOT_TARED) != 0) == (not tared)).all()
    fault = (st & FAULT) != 0
    np.testing.assert_array_equal(fault, fault_oracle(wl, q.jump_max_fm, q.stuck_max),
                                  "SENSOR_FAULT vs the rule")
    for k in ("force_mN", "x_um", "y_um", "contact_margin_q8", "contact", "contact_conf_q15"):
        assert not np.any(out[k][fault]), f"faulty samples must give the safe output ({k})"
    # Force and location where the decision holds: contact, or the release band after it
    # (contact 0 with RELEASING, which never comes with contact).
    releasing = (st & RELEASING) != 0
    assert not np.any(releasing & (out["contact"] == 1)), "RELEASING with contact"
    none = (out["contact"] == 0) & ~releasing
    for k in ("force_mN", "x_um", "y_um"):
        assert not np.any(out[k][none]), f"{k} without contact or RELEASING"
    # OVERLOAD: the estimate above overload_mN, or the input-side load rule (contact or not).
    over = ((out["contact"] == 1) | releasing) & (out["force_mN"] > q.overload_mN)
    assert ((st[over] & OVERLOAD) != 0).all(), "force above overload_mN without OVERLOAD"
    assert not np.any(st[fault] & OVERLOAD), "OVERLOAD on a faulty sample"
    ok = ~fault
    np.testing.assert_array_equal(out["contact_conf_q15"][ok],
                                  intref.sigmoid_q15(out["contact_margin_q8"][ok]))


def expected_tare(rows: np.ndarray) -> np.ndarray:
    """The tare rule: mean of the in-window samples, rounded half up."""
    rows = np.asarray(rows, dtype=np.int64).reshape(-1, 5)
    ok = ((rows >= WL_MIN_FM) & (rows <= WL_MAX_FM)).all(axis=1)
    n = int(ok.sum())
    return (rows[ok].sum(axis=0) + n // 2) // n


def with_crc(b: bytearray) -> bytes:
    """A blob's bytes with its header CRC made right again after an edit (so the loader reaches
    the check the edit aims at); a header whose length field is out of range is left as it is."""
    import struct
    import zlib

    total = struct.unpack_from("<I", b, 8)[0]
    if 16 <= total <= len(b):
        struct.pack_into("<I", b, 12, zlib.crc32(bytes(b[16:total])) & 0xFFFFFFFF)
    return bytes(b)


#: int32 wavelengths at every edge: the type's limits, 0 and +-1, the window's edges.
SPECIAL = np.array([INT32_MIN, INT32_MIN + 1, -1, 0, 1, WL_MIN_FM - 1, WL_MIN_FM, WL_MIN_FM + 1,
                    1_550_000_000, WL_MAX_FM - 1, WL_MAX_FM, WL_MAX_FM + 1, INT32_MAX - 1, INT32_MAX],
                   dtype=np.int64)


@dataclass
class Model:
    blob: bytes
    q: Any
    report: dict | None
    path: Path | None


def run_case(model: Model, wl: np.ndarray, driver: Path | None, *, tare: np.ndarray | None = None,
             baseline: np.ndarray | None = None, mode: str = "run") -> dict[str, np.ndarray]:
    """init -> [tare | set_baseline] -> run/step ``wl``: C == driver == intref, contract holds."""
    wl = np.asarray(wl, dtype=np.int64).reshape(-1, 5)
    ops: list[tuple] = [("init", 0)]
    if tare is not None:
        ops.append(("tare", tare))
    if baseline is not None:
        ops.append(("base", baseline))
    ops.append((mode, wl))
    res = execute(model.blob, ops, driver)
    assert res[0]["status"] == 0
    base = None
    if tare is not None:
        assert res[1]["status"] == 0
        base = res[1]["baseline_fm"]
        np.testing.assert_array_equal(base, expected_tare(tare))
    if baseline is not None:
        assert res[1]["status"] == 0
        base = np.asarray(baseline, dtype=np.int64)
    assert res[-1]["status"] == 0
    out = res[-1]["out"]
    ref = intref.run(model.q, wl, base)
    for k in FIELDS:
        np.testing.assert_array_equal(out[k], np.asarray(ref[k], dtype=np.int64),
                                      err_msg=f"C != integer reference: {k}")
    assert_contract(out, model.q, wl, tared=base is not None)
    return out


# --------------------------------------------------------------------------------------------
# Models and data
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def models(small_model_dir, small_dataset_path, tmp_path_factory) -> dict[str, Model]:
    """The small trained model exported with int16 and int8 weights (in private copies of
    the shared model directory) and the stress models of hardcases.py."""
    from fbgforce.export.exporter import export_model

    out: dict[str, Model] = {}
    for bits in (16, 8):
        d = tmp_path_factory.mktemp(f"hardcase_model{bits}") / "model"
        shutil.copytree(small_model_dir, d)
        report = export_model(d, bits=bits, calib=[small_dataset_path], onnx=False)
        blob = (d / "model.fbgm").read_bytes()
        out[f"small{bits}"] = Model(blob, from_bytes(blob), report, d)
    for name, q in {"stress": hc.stress_qmodel(), "stress8": hc.stress_qmodel(w_bits=8),
                    "stress_bias": hc.stress_qmodel(bias=(1 << 60) - 1)}.items():
        blob = to_bytes(q)
        out[name] = Model(blob, from_bytes(blob), None, None)
    return out


def scene_fm(name: str, **schedule: Any) -> tuple[np.ndarray, Any]:
    """A built-in scene, shortened through its schedule, as int32 fm (the one nm->fm rule)."""
    from fbgforce import sim

    sc = sim.load_scene(name)
    if schedule:
        sc = sc.replace(schedule=schedule)
    ds = sim.simulate(sc)
    return intref.nm_to_fm(ds.wl_nm).astype(np.int64), ds


@pytest.fixture(scope="module")
def press_fm():
    """A short recording with presses (smoke scene, 6 presses) as int32 fm."""
    wl, ds = scene_fm("smoke", n_presses=6)
    return wl, ds
