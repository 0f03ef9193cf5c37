"""The quantised model's numerical bounds and the blobs the loader refuses (the table in
docs/robustness.md; docs/fixed-point.md, "Worst cases driven to their bounds"): the exported
accumulator bounds recomputed and reached, the stress models at every bound, float overflow
inside the nets, corrupt blobs, and the committed fuzz corpus.

Every case runs three ways (cffi, the sanitizer-built driver, the integer reference) and must
give the same bits within the output contract (tests/hardcase_support.py).
"""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce.export import intref
from fbgforce.export.blob import to_bytes
from fbgforce.export.qmodel import SAT16, SAT32
from hardcase_support import (INT32_MAX, INT64_MAX, OVERLOAD, ROOT, SATURATED, SPECIAL, ffi, hc,
                              lib, record, run_case, with_crc)
# pytest fixtures, used by name
from hardcase_support import driver, models, write_report  # noqa: F401

#: Slow (pytest -m slow): sanitizer and valgrind builds of the driver, fuzzers, long runs.
pytestmark = pytest.mark.slow


# --------------------------------------------------------------------------------------------
# Accumulator bounds
# --------------------------------------------------------------------------------------------

def layer_bounds(q) -> dict[str, list[int]]:
    """Worst-case |acc| per layer, recomputed from the blob's integers (not the exporter's):
    sum_j |w[r][j]| * 32767 + |bias[r]|, maximised over rows; and the FIR's."""
    out = {}
    for name, net in zip(("contact", "force", "location"), q.nets):
        out[name] = [int(max(int(np.abs(ly.w[r]).sum()) * SAT16 + abs(int(ly.bias[r]))
                             for r in range(ly.n_out))) for ly in net]
    out["fir"] = [INT32_MAX * int(np.abs(q.taps).sum())]
    return out


def assert_int64_safe(q) -> None:
    """What fbg_model_check proves, recomputed: acc * mult + 2^(shift-1) fits int64 in every
    row; the FIR sum and every input-stage product fit too."""
    for net in q.nets:
        for ly in net:
            for r in range(ly.n_out):
                bound = int(np.abs(ly.w[r]).sum()) * SAT16 + abs(int(ly.bias[r]))
                assert bound * abs(int(ly.mult[r])) + (1 << (ly.shift - 1)) <= INT64_MAX
    assert INT32_MAX * int(np.abs(q.taps).sum()) + (1 << (q.tap_q - 1)) <= INT64_MAX
    assert INT32_MAX * max(abs(int(v)) for v in q.z_mult) + (1 << (q.z_shift - 1)) <= INT64_MAX
    assert INT32_MAX * abs(q.fq_mult) + (1 << (q.fq_shift - 1)) <= INT64_MAX
    assert INT32_MAX * max(abs(int(v)) for v in q.temp_coeff_q24) + (1 << 23) <= INT64_MAX


@pytest.mark.parametrize("key", ["small16", "small8"])
def test_exported_accumulator_bounds(models, driver, key):
    """The exporter's bounds equal the ones recomputed from the blob, are int64-safe, and are
    TIGHT for every first layer: inputs saturated with the signs of a row's weights reach them
    exactly (C and the reference agree there); deeper layers stay below their bounds."""
    m = models[key]
    q = m.q
    bounds = layer_bounds(q)
    for name in ("contact", "force", "location"):
        assert [info["acc_bound"] for info in m.report["nets"][name]] == bounds[name]
    assert m.report["fir"]["acc_bound"] == bounds["fir"][0]
    assert_int64_safe(q)

    # Drive each first-layer row of the contact and force nets to +bound and -bound: channel
    # c saturates to sign(w[r][c]) * 32767 with a 100 nm compensated shift held n_taps+2
    # samples (one jump fault at each change, then a full FIR window).
    # With memory states the first layers also read memory features, which a held input
    # drives to their rest values: there the bound is checked, not reached.
    tight = q.n_features == 4
    hold = q.taps.size + 2
    patterns = set()
    for net in q.nets[:2]:
        ly = net[0]
        for r in range(ly.n_out):
            s = np.sign(ly.w[r, :4]).astype(np.int64)
            s[s == 0] = 1
            d = 1 if ly.bias[r] >= 0 else -1
            patterns.add(tuple(d * s))
            patterns.add(tuple(-d * s))
    base = q.baseline_fm
    segs = []
    for p in sorted(patterns):
        row = base.copy()
        row[:4] = base[:4] + np.array(p) * 100_000_000
        segs.append(np.tile(row, (hold, 1)))
    wl = np.concatenate(segs)
    # A 1 pm dither keeps the stuck-peak rule quiet (it does not move a saturated z).
    wl += (np.arange(len(wl)) % 2)[:, None] * 1000
    out = run_case(m, wl, driver, baseline=base)
    trace: dict[str, int] = {}
    intref.run(q, wl, base, trace=trace)
    for i, name in enumerate(("contact", "force")):
        # Every row's bound is attained somewhere, so the layer maximum is too.
        if tight:
            assert trace[f"{name}.0"] == bounds[name][0], (name, trace[f"{name}.0"], bounds[name][0])
        assert trace[f"{name}.0"] <= bounds[name][0]
    assert ((out["status"] & SATURATED) != 0).any()

    # Deeper layers: search the input box for the largest accumulators (random corners and
    # interior points of z, evaluated on the integer reference's layers directly).
    rng = np.random.default_rng(3)
    f = q.n_features
    z = np.concatenate([rng.choice([-SAT16, SAT16], (4000, f)), rng.integers(-SAT16, SAT16 + 1, (20000, f))])
    reached = {}
    for name, net, zin in (("contact", q.nets[0], z), ("force", q.nets[1], z),
                           ("location", q.nets[2],
                            np.column_stack([z[:, :4], np.full(len(z), 1 << q.z_frac),
                                             rng.integers(-SAT16, SAT16 + 1, (len(z), 1 + q.n_loc))]))):
        x = zin.astype(np.int64)
        flag = np.zeros(len(x), dtype=bool)
        for i, ly in enumerate(net):
            acc = x @ ly.w.T + ly.bias
            reached[f"{name}.{i}"] = int(np.abs(acc).max())
            assert reached[f"{name}.{i}"] <= bounds[name][i]
            if i < len(net) - 1:
                x = intref._hidden(ly, x, flag)
    record(f"acc_bounds/{key}", bounds={k: [f"2^{np.log2(v):.1f}" for v in b] for k, b in bounds.items()},
           searched_over_bound={k: round(v / bounds[k.split('.')[0]][int(k.split('.')[1])], 3)
                                for k, v in reached.items()})


@pytest.mark.parametrize("key", ["stress", "stress8", "stress_bias"])
def test_stress_model_reaches_every_bound(models, driver, key):
    """The stress model (hardcases.stress_qmodel) is at the edge of fbg_model_check: with
    saturated inputs EVERY layer's accumulator equals its proven bound (both signs), the
    multipliers put acc * mult within one multiplier step of INT64_MAX, the FIR sum reaches
    its bound, and C (also under ASan/UBSan) still equals the reference bit for bit."""
    m = models[key]
    q = m.q
    assert_int64_safe(q)
    bounds = layer_bounds(q)
    for sign in (1, -1):
        wl = hc.stress_inputs(q, sign)
        out = run_case(m, wl, driver, baseline=q.baseline_fm)
        trace: dict[str, int] = {}
        intref.run(q, wl, q.baseline_fm, trace=trace)
        settled = out["status"][q.taps.size:]
        assert ((settled & SATURATED) != 0).all()
        if sign > 0:
            for name in ("contact", "force", "location"):
                for i, b in enumerate(bounds[name]):
                    assert trace[f"{name}.{i}"] == b, (name, i, trace[f"{name}.{i}"], b)
            assert trace["fir"] == bounds["fir"][0]
            n = q.taps.size
            assert (out["contact"][n:] == 1).all()
            assert ((settled & OVERLOAD) != 0).all()
            if q.w_bits == 16:
                # acc * mult ~ 2^63 >> 30: the outputs clamp symmetrically (never INT32_MIN).
                assert (out["force_mN"][n:] == SAT32).all()
                assert (out["x_um"][n:] == SAT32).all() and (out["y_um"][n:] == -SAT32).all()
            else:
                # int8 weights: the bound is ~2^28 and mult is capped at 2^31 - 1, so the
                # product stays ~2^59: large, correctly signed, not clamped.
                assert (out["force_mN"][n:] > 0).all()
                assert (out["x_um"][n:] > 0).all() and (out["y_um"][n:] < 0).all()
    # One multiplier step further and the C check refuses the model (the proof is tight):
    # the first row whose multiplier is not capped at the int32 limit.
    ly = next((ly for net in q.nets for ly in net if ly.mult[0] < 2**31 - 1), None)
    if ly is None:  # int8 weights: every multiplier is capped, the bound is far from int64
        return
    ly.mult = ly.mult.copy()
    ly.mult[0] += 1
    bad = to_bytes_unchecked(q)
    buf = ffi.new("uint64_t[]", (len(bad) + 7) // 8)
    ffi.memmove(buf, bad, len(bad))
    model = ffi.new("fbg_model *")
    assert lib.fbg_model_from_blob(model, ffi.cast("uint8_t *", buf), len(bad)) == lib.FBG_ERR_BOUND


def to_bytes_unchecked(q) -> bytes:
    """blob.to_bytes without the Python-side check (to hand the C loader a bad model)."""
    orig = type(q).check
    try:
        type(q).check = lambda self: None
        return to_bytes(q)
    finally:
        type(q).check = orig


# --------------------------------------------------------------------------------------------
# Float overflow inside the nets
# --------------------------------------------------------------------------------------------

def test_float_overflow_in_nets_gives_safe_output(models):
    """Finite but huge weights overflow float32 inside the nets (inf, then inf - inf = NaN):
    the C float build returns the safe output with SATURATED, never NaN/inf."""
    from fbgforce.model import modeldir as fm
    from fbgforce.pybind import FloatRuntime

    model = fm.load(models["small16"].path)
    for net in (model.contact, model.force):
        net.weights = [w * 1e18 for w in net.weights]
    fr = FloatRuntime(model)
    fr.set_baseline(models["small16"].q.baseline_fm)
    wl = np.concatenate([hc.stress_inputs(models["small16"].q, 1, 40),
                         hc.stress_inputs(models["small16"].q, -1, 40)]).astype(np.int32)
    o = fr.run(wl)
    for k in ("force_N", "p_contact", "margin"):
        assert np.isfinite(o[k]).all(), k
    sat = (o["status"] & SATURATED) != 0
    assert sat.any()
    assert not o["contact"][sat].any() and (o["force_N"][sat] == 0).all()
    record("float_overflow", samples=len(wl), saturated=int(sat.sum()))




# --------------------------------------------------------------------------------------------
# Corrupt blobs
# --------------------------------------------------------------------------------------------

ERR_CODES = {int(getattr(lib, n)) for n in dir(lib) if n.startswith("FBG_ERR_")}


def load_status(blob: bytes, offset: int = 0) -> int:
    """fbg_model_from_blob on a copy of ``blob`` at ``offset`` bytes past an 8-aligned address;
    an accepted model must also initialise and step within the contract."""
    buf = ffi.new("uint64_t[]", max(1, (len(blob) + offset + 7) // 8))
    base = ffi.cast("uint8_t *", buf) + offset
    ffi.memmove(base, blob, len(blob))
    model = ffi.new("fbg_model *")
    status = lib.fbg_model_from_blob(model, base, len(blob))
    if status == 0:
        state, out = ffi.new("fbg_state *"), ffi.new("fbg_output *")
        assert lib.fbg_init(state, model, 0) == 0
        for row in SPECIAL[:10].reshape(2, 5).tolist() + [[1_550_000_000] * 5]:
            assert lib.fbg_step(state, ffi.new("int32_t[5]", row), out) == 0
    return status


def test_corrupt_blobs_are_refused(models, driver):
    """Every truncation, every single-bit flip of the header/parameters/layer table and a
    sample of the arrays, and mutations with a REPAIRED CRC (so they reach the field checks)
    give a documented error code, never a crash or a read past the end (the driver loads each
    from an exact-size heap buffer under ASan)."""
    blob = models["small16"].blob
    n = len(blob)
    rng = np.random.default_rng(4)
    cases: list[tuple[str, bytes]] = []
    for cut in list(range(0, 130)) + sorted(rng.choice(np.arange(130, n), 120, replace=False).tolist()):
        cases.append(("truncated", blob[:cut]))
    from fbgforce.export.blob import PARAMS_END

    head = PARAMS_END + 8 * sum(len(net) for net in models["small16"].q.nets)
    flips = [(i, bit) for i in range(head) for bit in range(8)]
    flips = flips[::2] + [(int(i), int(rng.integers(0, 8))) for i in rng.integers(head, n, 120)]
    for i, bit in flips:
        b = bytearray(blob)
        b[i] ^= 1 << bit
        cases.append((f"flip@{i}", bytes(b)))
    for _ in range(250):
        b = bytearray(blob)
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.integers(8, head))
            b[i] = int(rng.integers(0, 256))
        cases.append(("mutated+crc", with_crc(b)))
    cases.append(("misaligned", blob))
    counts: dict[str, dict[str, int]] = {}
    statuses = []
    for kind, b in cases:
        st = load_status(b, offset=3 if kind == "misaligned" else 0)
        statuses.append(st)
        name = ffi.string(lib.fbg_status_str(st)).decode()
        counts.setdefault(kind.split("@")[0], {}).setdefault(name, 0)
        counts[kind.split("@")[0]][name] += 1
        assert st == 0 or st in ERR_CODES, (kind, st)
        if kind == "truncated":
            assert st == lib.FBG_ERR_TRUNCATED, (len(b), st)
        elif kind.startswith("flip@"):
            i = int(kind[5:])
            # The 2 flag bytes (offset 6-7) are neither CRC-protected nor interpreted.
            assert st != 0 or i in (6, 7), (kind, st)
            if i < 4:
                assert st == lib.FBG_ERR_BAD_MAGIC
            elif i in (4, 5):
                assert st == lib.FBG_ERR_VERSION
            elif 12 <= i < 16 or i >= 16:
                assert st in (lib.FBG_ERR_CRC,), (kind, st)
        elif kind == "misaligned":
            assert st == lib.FBG_ERR_ALIGN
    record("corrupt_blobs", blobs=len(cases), outcomes=counts)
    if driver is not None:
        # The same blobs (aligned ones) through the sanitizer driver: same codes, no reports.
        sel = [i for i, (k, _) in enumerate(cases) if k != "misaligned"]
        got = hc.driver_blob_status(driver, [cases[i][1] for i in sel])
        assert got == [statuses[i] for i in sel]


# --------------------------------------------------------------------------------------------
# The documented bounds (docs/fixed-point.md, "Worst cases driven to their bounds")
# --------------------------------------------------------------------------------------------

def bound_table(q) -> list[str]:
    """Markdown rows: per layer (consecutive identical layers of a net merged, "net.1-6") the
    proven |acc| bound, the largest requantisation value ``bound * |mult| + 2^(shift-1)`` and
    its distance to INT64_MAX."""
    rows: list[tuple[str, int, int, str]] = []
    for name, net in zip(("contact", "force", "location"), q.nets):
        for i, ly in enumerate(net):
            b = [int(np.abs(ly.w[r]).sum()) * SAT16 + abs(int(ly.bias[r])) for r in range(ly.n_out)]
            prod = max(bb * abs(int(m)) + (1 << (ly.shift - 1)) for bb, m in zip(b, ly.mult))
            body = (f"{ly.n_out}x{ly.n_in} int{ly.w_bits} | {max(b)} (2^{np.log2(max(b)):.2f}) | "
                    f"{prod} | {INT64_MAX - prod} |")
            if rows and rows[-1][0] == name and rows[-1][3] == body and rows[-1][2] == i - 1:
                rows[-1] = (name, rows[-1][1], i, body)
            else:
                rows.append((name, i, i, body))
    out = [f"| {n}.{a}{'' if a == b else f'-{b}'} | {body}" for n, a, b, body in rows]
    fir = INT32_MAX * int(np.abs(q.taps).sum())
    out.append(f"| fir | {q.taps.size} taps Q{q.tap_q} | {fir} (2^{np.log2(fir):.2f}) | "
               f"{fir + (1 << (q.tap_q - 1))} | {INT64_MAX - fir - (1 << (q.tap_q - 1))} |")
    return out


def test_documented_stress_bounds_match():
    """docs/fixed-point.md lists the stress model's bounds; they are recomputed here (and
    test_stress_model_reaches_every_bound shows the runtime reaching each one)."""
    doc = (ROOT / "docs" / "fixed-point.md").read_text()
    for w_bits in (16, 8):
        for row in bound_table(hc.stress_qmodel(w_bits=w_bits)):
            assert row in doc, f"docs/fixed-point.md lacks or disagrees with: {row}"


def test_committed_fuzz_corpus_is_current():
    """The fuzz models in runtime_c/fuzz/models must load with this library (a blob format
    change makes them stale: regenerate with `make -C runtime_c fuzz-corpus`), and the
    fuzz_blob seeds must cover a valid blob, truncations, a bad magic and a misalignment."""
    for name in ("small16", "small8", "stress", "stress_bias"):
        blob = (hc.MODELS_DIR / f"{name}.fbgm").read_bytes()
        assert load_status(blob) == 0, f"{name}.fbgm is stale: run make -C runtime_c fuzz-corpus"
    seeds = {p.name: p.read_bytes() for p in (hc.CORPUS_DIR / "fuzz_blob").iterdir()}
    assert load_status(seeds["valid16"][1:]) == 0
    assert load_status(seeds["truncated_body"][1:]) == lib.FBG_ERR_TRUNCATED
    assert load_status(seeds["bad_magic"][1:]) == lib.FBG_ERR_BAD_MAGIC
    assert len(list((hc.CORPUS_DIR / "fuzz_step").iterdir())) >= 4
