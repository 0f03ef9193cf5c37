"""Golden vectors: a session of API calls with what the integer reference says each returns,
written as C for the replay firmware (``examples/firmware/fw_golden.h``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce import contract
from fbgforce.errors import InputError
from fbgforce.target.sources import header_constants
from fbgforce.units import estimate_shown


# Ops of examples/firmware/fw_golden.h.
OP_STEP, OP_TARE_BEGIN, OP_TARE_ADD, OP_TARE_END, OP_SET_BASELINE, OP_RESET, OP_INIT = range(7)
#: Output fields of ``fbg_output`` (fbgforce.h), as the integer reference names them.
OUTPUT_FIELDS = contract.OUTPUT_FIELDS
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1


@dataclass
class Record:
    """One API call of the golden session and what the integer reference says it returns."""

    op: int
    wl_fm: tuple[int, ...] = (0, 0, 0, 0, 0)
    status: int = 0
    accepted: int = 0
    out: dict[str, int] = field(default_factory=dict)


def _steps(q: Any, wl_fm: np.ndarray, baseline_fm: np.ndarray | None,
           end: dict[str, Any] | None = None) -> list[Record]:
    """Step records of one stretch run from a fresh (or freshly tared / re-baselined) state;
    ``end`` receives the baseline after it (:func:`fbgforce.export.intref.run`)."""
    from fbgforce.export import intref

    wl = np.asarray(wl_fm, dtype=np.int64).reshape(-1, 5)
    ref = intref.run(q, wl, baseline_fm, end=end)
    return [Record(OP_STEP, tuple(int(v) for v in wl[i]), 0, 0,
                   {k: int(ref[k][i]) for k in OUTPUT_FIELDS}) for i in range(wl.shape[0])]


def _tare_mean(samples: np.ndarray) -> np.ndarray:
    """Baseline fbg_tare_end sets: per channel floor((sum + count/2) / count) (fbgforce.h)."""
    s = samples.astype(np.int64)
    n = s.shape[0]
    return (s.sum(axis=0) + n // 2) // n


def edge_samples(baseline_fm: np.ndarray, jump_max_fm: int, seed: int = 0) -> np.ndarray:
    """Samples the recording never shows: lost peaks (0, -1, int32 sentinels, outside the
    1000-2000 nm window), one-sample jumps beyond the fault threshold, window edges, huge
    in-window shifts that saturate, and random in-window values."""
    c = header_constants()
    lo, hi = c["FBG_WL_MIN_FM"], c["FBG_WL_MAX_FM"]
    rng = np.random.default_rng(seed)
    b = np.asarray(baseline_fm, dtype=np.int64)
    rows: list[np.ndarray] = []
    for k in range(40):  # a quiet lead-in so that the FIR is warm and prev is valid
        rows.append(b + rng.integers(-3000, 3000, 5))
    for bad in (0, -1, INT32_MIN, INT32_MAX, lo - 1, hi + 1):
        for ch in (0, 2, 4):
            r = b.copy()
            r[ch] = bad
            rows.append(r)
            rows.append(b + rng.integers(-3000, 3000, 5))
    # A jump just above and just below the threshold on a strain and on the reference grating.
    for ch in (1, 4):
        for d in (jump_max_fm + 1, jump_max_fm, -(jump_max_fm + 1)):
            r = rows[-1].copy()
            r[ch] += d
            rows.append(r)
    # Window edges and the largest shifts: tare differences and compensation saturate.
    for v in (lo, hi):
        rows.append(np.full(5, v, dtype=np.int64))
        rows.append(np.full(5, v, dtype=np.int64))
    ramp = np.linspace(0, 1, 30)
    for t in ramp:  # a slow ramp to +-nanometres: drives hidden layers and outputs to saturation
        rows.append(np.clip(b + np.array([1, -1, 1, -1, 0]) * int(t * 0.9e9 * 0.05), lo, hi))
    for t in ramp:
        rows.append(np.clip(b + np.array([-1, 1, -1, 1, 1]) * int(t * 0.9e9 * 0.05), lo, hi))
    rows.extend(rng.integers(lo, hi + 1, (20, 5)))
    return np.clip(np.vstack(rows), INT32_MIN, INT32_MAX).astype(np.int64)


def golden_session(q: Any, wl_fm: np.ndarray, contact: np.ndarray | None = None, *,
                   n_untared: int = 16, n_tare: int = 24, seed: int = 0) -> list[Record]:
    """The replayed session: every API call with the integer reference's expected result.

    ``wl_fm`` (n, 5) is a recording in femtometres; its first ``n_tare`` samples without
    contact (or simply the first ones) are the tare window.
    """
    c = header_constants()
    ok, err_arg, err_tare = c["FBG_OK"], c["FBG_ERR_ARG"], c["FBG_ERR_TARE"]
    lo, hi = c["FBG_WL_MIN_FM"], c["FBG_WL_MAX_FM"]
    wl = np.asarray(wl_fm, dtype=np.int64).reshape(-1, 5)
    if wl.shape[0] < n_tare + 8:
        raise InputError(f"need at least {n_tare + 8} samples for the golden session, got {wl.shape[0]}")
    recs: list[Record] = []
    # 1. Untared: the model's nominal baseline.
    recs += _steps(q, wl[:n_untared], None)
    # 2. Tare through the API; two samples are refused (a lost peak, a peak above the window).
    quiet = np.flatnonzero(~np.asarray(contact, dtype=bool)) if contact is not None else np.arange(len(wl))
    tare_rows = wl[quiet[:n_tare]] if quiet.size >= n_tare else wl[:n_tare]
    recs.append(Record(OP_TARE_BEGIN, status=ok))
    for i, row in enumerate(tare_rows):
        recs.append(Record(OP_TARE_ADD, tuple(int(v) for v in row), ok, 1))
        if i == 3:
            bad = row.copy()
            bad[2] = 0
            recs.append(Record(OP_TARE_ADD, tuple(int(v) for v in bad), ok, 0))
        if i == 7:
            bad = row.copy()
            bad[4] = hi + 1
            recs.append(Record(OP_TARE_ADD, tuple(int(v) for v in bad), ok, 0))
    recs.append(Record(OP_TARE_END, status=ok))
    base = _tare_mean(tare_rows)
    # 3. The recording on that tare.
    recs += _steps(q, wl, base)
    # 4. Errors change nothing: a baseline outside the window, a tare_end without begin.
    recs.append(Record(OP_SET_BASELINE, (int(base[0]), int(base[1]), lo - 1, int(base[3]), int(base[4])),
                       err_arg))
    recs.append(Record(OP_TARE_END, status=err_tare))
    # 5. Edge cases on an explicit baseline.
    recs.append(Record(OP_SET_BASELINE, tuple(int(v) for v in base), ok))
    end: dict[str, Any] = {}
    recs += _steps(q, edge_samples(base, q.jump_max_fm, seed), base, end)
    # 6. fbg_reset keeps the baseline (as the at-rest tracker left it) and clears the rest:
    #    the same as a fresh run on it.
    recs.append(Record(OP_RESET, status=ok))
    recs += _steps(q, wl[-32:], end["baseline_fm"])
    # 7. A fresh fbg_init: untared again.
    recs.append(Record(OP_INIT, status=ok))
    recs += _steps(q, wl[:8], None)
    return recs


def _c_int(v: int) -> str:
    return f"({v + 1} - 1)" if v == INT32_MIN else str(v)


def write_golden_c(records: Sequence[Record], path: Path, options: int = 0) -> None:
    """Write ``golden_vectors.c`` for examples/firmware/fw_golden.h."""
    lines = [
        "/* golden_vectors.c - generated by fbgforce.target.golden from the integer reference;",
        " * do not edit. Layout: examples/firmware/fw_golden.h. */",
        '#include "fw_golden.h"', "",
        f"const uint32_t fw_golden_options = {options}u;",
        f"const uint32_t fw_golden_count = {len(records)}u;",
        f"const fw_record fw_golden[{len(records)}] = {{",
    ]
    for r in records:
        wl = ", ".join(_c_int(v) for v in r.wl_fm)
        o = r.out or {k: 0 for k in OUTPUT_FIELDS}
        out = (f".force_mN = {_c_int(o['force_mN'])}, .x_um = {_c_int(o['x_um'])}, "
               f".y_um = {_c_int(o['y_um'])}, .contact_margin_q8 = {_c_int(o['contact_margin_q8'])}, "
               f".status = {o['status']}u, .contact_conf_q15 = {o['contact_conf_q15']}u, "
               f".contact = {o['contact']}u")
        lines.append(f"    {{.wl_fm = {{{wl}}}, .op = {r.op}, .status = {r.status}, "
                     f".accepted = {r.accepted}, .out = {{{out}}}}},")
    lines.append("};")
    path.write_text("\n".join(lines) + "\n")


def step_macs(q: Any, records: Sequence[Record]) -> list[int]:
    """MACs each step record performs in the C pipeline: the FIR (4 channels x taps) and every
    layer of the nets that run (contact always; force and location where the decision holds:
    contact, or RELEASING, :func:`fbgforce.units.estimate_shown`); a sensor fault runs neither."""
    fault = header_constants()["FBG_STATUS_SENSOR_FAULT"]
    fir = 4 * int(q.taps.size)
    net = [sum(ly.n_in * ly.n_out for ly in layers) for layers in q.nets]
    macs = []
    for r in records:
        if r.op != OP_STEP:
            continue
        if r.out["status"] & fault:
            macs.append(0)
        else:
            shown = estimate_shown(r.out["contact"], r.out["status"])
            macs.append(fir + net[0] + (net[1] + net[2] if shown else 0))
    return macs
