"""The numpy INTEGER reference of the fixed-point runtime: the C code, bit for bit.

Every operation of the C fixed-point step (runtime_c/src/fbg_fixed.c and its stages,
fbg_stage_*.c) is written here once more with the same rounding
rule, the same saturation rule and the same order, in int64 numpy arithmetic (vectorised over
samples; exact because every intermediate is proven to stay inside int64, see
docs/fixed-point.md). ``fbgforce verify`` and the tests compare the C output with this one
and require equality of every output bit.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from fbgforce import contract
from fbgforce.model import artifact, decision, floatref
from fbgforce.export.qmodel import SAT16, SAT32, QLayer, QModel
from fbgforce.units import nm_to_fm, to_engine_dict

STATUS_NOT_TARED = contract.STATUS_FLAG["NOT_TARED"]
STATUS_SATURATED = contract.STATUS_FLAG["SATURATED"]
STATUS_OVERLOAD = contract.STATUS_FLAG["OVERLOAD"]
STATUS_SENSOR_FAULT = contract.STATUS_FLAG["SENSOR_FAULT"]
STATUS_WARMUP = contract.STATUS_FLAG["WARMUP"]
STATUS_BASELINE_LIMIT = contract.STATUS_FLAG["BASELINE_LIMIT"]
STATUS_OUT_OF_RANGE = contract.STATUS_FLAG["OUT_OF_RANGE"]
STATUS_RELEASING = contract.STATUS_FLAG["RELEASING"]
EMA_FRAC = contract.LIMIT["EMA_FRAC"]
TEMP_COEFF_SHIFT = contract.LIMIT["TEMP_COEFF_SHIFT"]
WL_MIN_FM = contract.LIMIT["WL_MIN_FM"]
WL_MAX_FM = contract.LIMIT["WL_MAX_FM"]

__all__ = ["run", "run_recording", "memory_features", "rshift_round", "sat", "sigmoid_q15",
           "nm_to_fm", "to_engine_dict"]

#: round(32768 / (1 + exp(-x))) at x = -8, -7.875, ..., 8, clamped to 32767: the same literal
#: table as runtime_c/src/fbg_fixed.c (a test checks both against the formula and each other).
SIGMOID_Q15_TABLE = np.array([
    11, 12, 14, 16, 18, 21, 23, 26, 30, 34, 38, 43, 49, 56, 63, 72, 81, 92, 104, 118, 133,
    151, 171, 194, 219, 248, 281, 318, 360, 407, 461, 521, 589, 666, 753, 851, 961, 1084,
    1223, 1379, 1554, 1750, 1969, 2213, 2486, 2789, 3124, 3496, 3906, 4357, 4851, 5391,
    5978, 6613, 7297, 8031, 8813, 9641, 10513, 11424, 12371, 13348, 14347, 15361, 16384,
    17407, 18421, 19420, 20397, 21344, 22255, 23127, 23955, 24737, 25471, 26155, 26790,
    27377, 27917, 28411, 28862, 29272, 29644, 29979, 30282, 30555, 30799, 31018, 31214,
    31389, 31545, 31684, 31807, 31917, 32015, 32102, 32179, 32247, 32307, 32361, 32408,
    32450, 32487, 32520, 32549, 32574, 32597, 32617, 32635, 32650, 32664, 32676, 32687,
    32696, 32705, 32712, 32719, 32725, 32730, 32734, 32738, 32742, 32745, 32747, 32750,
    32752, 32754, 32756, 32757], dtype=np.int64)


# --------------------------------------------------------------------------------------------
# The two rules (docs/fixed-point.md)
# --------------------------------------------------------------------------------------------

def rshift_round(x: np.ndarray, s: int) -> np.ndarray:
    """``(x + 2^(s-1)) >> s`` with an arithmetic shift: round half up (s >= 1)."""
    return (np.asarray(x, dtype=np.int64) + np.int64(1 << (s - 1))) >> np.int64(s)


def sat(x: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric saturation to ``[-limit, limit]``; also returns where it clamped."""
    x = np.asarray(x, dtype=np.int64)
    return np.clip(x, -limit, limit), (x > limit) | (x < -limit)


def sigmoid_q15(x_q8: np.ndarray) -> np.ndarray:
    """``fbg_sigmoid_q15``: table lookup with linear interpolation (Q8 in, Q15 out)."""
    x = np.asarray(x_q8, dtype=np.int64)
    u = np.clip(x + 2048, 0, 4095)
    idx, frac = u >> 5, u & 31
    lo, hi = SIGMOID_Q15_TABLE[idx], SIGMOID_Q15_TABLE[np.minimum(idx + 1, 128)]
    out = lo + (((hi - lo) * frac + 16) >> 5)
    out = np.where(x <= -2048, SIGMOID_Q15_TABLE[0], out)
    return np.where(x >= 2048, SIGMOID_Q15_TABLE[128], out)


# --------------------------------------------------------------------------------------------
# The step: fbg_step's stages in its order (front end, filter, memory, nets with the
# decision and the rest tracker, hold), each below under its C name
# --------------------------------------------------------------------------------------------

def run(q: QModel, wl_fm: np.ndarray, baseline_fm: np.ndarray | None = None, *,
        trace: dict[str, int] | None = None, end: dict[str, Any] | None = None
        ) -> dict[str, np.ndarray]:
    """Run the fixed-point pipeline on one continuous recording from a fresh state.

    Equivalent to ``fbg_init`` then (if ``baseline_fm`` is given) ``fbg_set_baseline`` and
    ``fbg_step`` on every row. With the at-rest baseline tracker on (``q.track_shift``) the
    recording runs in blocks of TRACK_BLOCK samples, between which the tracker may move the
    baseline, as the C state does; otherwise in one block.

    Parameters
    ----------
    wl_fm
        (n, 5) int32 femtometres.
    baseline_fm
        (5,) tare baseline; None runs on the model's nominal baseline (status NOT_TARED).
    trace
        If a dict, receives the largest ``|accumulator|`` seen per layer (``"net.layer"``)
        and for the FIR (``"fir"``), for the export report.
    end
        If a dict, receives ``"baseline_fm"``: the (5,) baseline after the last sample, as
        ``fbg_get_baseline`` reads it (the tracker may have moved it), and ``"creep"``: the
        tracker's creep states (4,) as ``fbg_state.creep`` holds them (0 before any), and
        ``"creep_acc"``: the creep inverse's states as ``fbg_state.creep_acc`` (0 before any).

    Returns
    -------
    dict
        int arrays named as ``fbg_output``: force_mN, x_um, y_um, contact_margin_q8, status,
        contact_conf_q15, contact.
    """
    wl = np.asarray(wl_fm, dtype=np.int64).reshape(-1, 5)
    n = wl.shape[0]
    tared = baseline_fm is not None
    base = np.array(q.baseline_fm if baseline_fm is None else baseline_fm, dtype=np.int64).reshape(5)
    status = np.full(n, 0 if tared else STATUS_NOT_TARED, dtype=np.int64)
    flag = np.zeros(n, dtype=bool)
    # The front end's parts that read the wavelengths only, never the baseline the tracker
    # moves, run on the whole recording at once: the fault rule, the warm-up and the
    # temperature reference (the tracker moves only the strain gratings' baseline).
    fault = _sensor_faults(q, wl)
    status |= np.where(fault, STATUS_SENSOR_FAULT, 0)
    warm = np.arange(1, n + 1) < q.taps.size
    status |= np.where(warm, STATUS_WARMUP, 0)
    ref = reference_average(q, wl[:, 4] - base[4], fault)

    out = {k: np.zeros(n, dtype=np.int64) for k in
           ("force_mN", "x_um", "y_um", "contact_margin_q8", "contact_conf_q15", "contact")}
    state = _State(q, trace)
    block = contract.LIMIT["TRACK_BLOCK"] if (q.track_shift and tared) else max(n, 1)
    for a in range(0, n, block):
        b = min(n, a + block)
        if state.tracker.limited:
            status[a:b] |= STATUS_BASELINE_LIMIT
        rest, r_sum = _block(q, state, wl[a:b], ref[a:b], fault[a:b], warm[a:b], base,
                             status[a:b], flag[a:b], {k: v[a:b] for k, v in out.items()})
        if b - a == block:   # a block cut short by the recording's end moves nothing (C: track_pos)
            state.tracker.end_block(rest & tared, r_sum, base)
    status |= np.where(flag, STATUS_SATURATED, 0)
    out["status"] = status
    if end is not None:
        end["baseline_fm"] = base.copy()
        end["creep"] = np.array(state.tracker.creep or [0] * 4, dtype=np.int64)
        end["creep_acc"] = np.array(state.creep[0] or [0] * 4, dtype=np.int64)
    return out


class _State:
    """What ``fbg_state`` carries from one block of samples to the next: the FIR's held
    inputs and the last good sample's filtered shifts, the creep inverse's states, the
    memory, the rest tracker, the decision's and the hold's states; and the constant ``z0``
    the tracker measures from and the accumulator ``trace`` of :func:`run`."""

    def __init__(self, q: QModel, trace: dict[str, int] | None) -> None:
        self.trace = trace
        #: Held FIR inputs before the block, and the filtered shifts a faulty sample feeds it
        #: (zeros before any good sample).
        self.history = np.zeros((q.taps.size - 1, 4), dtype=np.int64)
        self.last_comp = np.zeros(4, dtype=np.int64)
        #: The creep inverse's acc (:func:`creep_inverse`), None until the first good sample.
        self.creep: list[list[int] | None] = [None]
        self.memory = _MemoryStage(q)
        self.tracker = _RestTracker(q)
        #: ``[decision, rise_run, cusum_q8, released, release_run]`` (:func:`_contact_decision`)
        #: and ``[hold_avg, hold_primed, hold_run]`` (:func:`_hold_stage`).
        self.decision = [0, 0, 0, 0, 0]
        self.hold = [0, 0, 0]
        self.z_rest, _ = q.z_rest()


def _block(q: QModel, state: _State, wl: np.ndarray, ref: np.ndarray, fault: np.ndarray,
           warm: np.ndarray, base: np.ndarray, status: np.ndarray, flag: np.ndarray,
           out: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The stages of ``fbg_step`` after the fault rule, on consecutive samples that share one
    baseline, in its order: front end, filter, memory, nets with the decision, hold. Writes
    ``status``, ``flag`` and ``out`` (views of the block) and carries ``state``; ``ref`` is
    the temperature reference of each sample (:func:`reference_average`). Returns which
    samples were at rest and their sum of the tracker's terms
    (:meth:`_RestTracker.rest_terms`), for the tracker's update at the block's end."""
    n = wl.shape[0]
    ok = ~fault
    comp = _front_stage(q, state, wl, ref, base, ok, flag)
    z = _filter_stage(q, state, comp, ok, status, flag)
    rows = np.flatnonzero(ok)
    terms = np.zeros((n, 4), dtype=np.int64)
    terms[rows] = state.tracker.rest_terms(z[rows], state.z_rest)
    feats = _memory_stage(q, state, z, rows, status, flag)
    rest = np.zeros(n, dtype=bool)
    if rows.size:
        held = _contact_outputs(q, state, feats, rows, status, flag, out)
        rest[rows] = ~held & ~warm[rows]
        if held.any():
            _force_location_outputs(q, state, feats, rows, held, status, flag, out)
        else:
            state.hold[1], state.hold[2] = 0, 0      # the settled-hold gain, cleared out of the hold
    return rest, terms[rest].sum(axis=0)


def run_recording(model_dir: str | Path, model: artifact.HierarchicalModel | None, wl_nm: np.ndarray,
                  baseline_nm: np.ndarray) -> dict[str, Any]:
    """Engine ``intref``: the integer reference on ``model_dir/model.fbgm``."""
    from fbgforce.export.blob import load_model_blob

    q = load_model_blob(model_dir, float_model=model)
    return to_engine_dict(run(q, nm_to_fm(wl_nm), nm_to_fm(np.asarray(baseline_nm).reshape(5))))


# --------------------------------------------------------------------------------------------
# Front end (front_stage): fault rule, tare, temperature compensation, creep inverse
# --------------------------------------------------------------------------------------------

def _sensor_faults(q: QModel, wl: np.ndarray) -> np.ndarray:
    """The front end's fault rule (``fbg_front_sample`` of fbg_front.h) on a whole recording
    (n, 5): per sample, whether a channel is outside the wavelength window, jumped more than
    ``jump_max_fm`` from its last in-window value, or repeated that value ``stuck_max`` times
    in a row (a uint16 count, saturating; 0 turns the stuck-peak rule off)."""
    n = wl.shape[0]
    inwin = (wl >= WL_MIN_FM) & (wl <= WL_MAX_FM)
    prev, has_prev = _prev_in_window(wl, inwin)
    jump = inwin & has_prev & (np.abs(wl - prev) > q.jump_max_fm)
    # The stuck-peak run: consecutive samples equal to the previous in-window value,
    # restarted by any change or out-of-window sample.
    same = inwin & has_prev & (wl == prev)
    steps = np.arange(n)[:, None]
    last_reset = np.maximum.accumulate(np.where(same, -1, steps), axis=0) if n else steps
    run_len = np.minimum(steps - last_reset, 0xFFFF)
    stuck = (run_len >= q.stuck_max) if q.stuck_max else np.zeros_like(inwin)
    return np.any(~inwin | jump | stuck, axis=1)


def _prev_in_window(wl: np.ndarray, inwin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per sample and channel: the last in-window value strictly before it, and whether any."""
    n = wl.shape[0]
    idx = np.where(inwin, np.arange(n)[:, None], -1)
    last = np.maximum.accumulate(idx, axis=0) if n else idx
    prev_idx = np.vstack([np.full((1, wl.shape[1]), -1), last[:-1]]) if n else idx
    prev = np.take_along_axis(wl, np.maximum(prev_idx, 0), axis=0)
    return prev, prev_idx >= 0


def _front_stage(q: QModel, state: _State, wl: np.ndarray, ref: np.ndarray, base: np.ndarray,
                 ok: np.ndarray, flag: np.ndarray) -> np.ndarray:
    """``fbg_front_stage`` of fbg_stage_front.c after the fault rule: tare, temperature compensation by
    the reference ``ref`` and the creep inverse, on the rows ``ok`` without a fault (the
    others' values are never read). Returns the compensated shifts (m, 4) fm; flags where a
    value saturated."""
    _, c1 = sat(wl[:, 4] - base[4], SAT32)    # the compensation reads ref
    shift, c2 = sat(wl[:, :4] - base[:4], SAT32)
    t = rshift_round(ref[:, None] * q.temp_coeff_q24[None, :], TEMP_COEFF_SHIFT)
    comp, c3 = sat(shift - t, SAT32)
    comp, c_creep = creep_inverse(q, comp, ok, state.creep)
    flag |= ok & (c1 | c2.any(axis=1) | c3.any(axis=1) | c_creep)
    return comp


def reference_average(q: QModel, shift_t: np.ndarray, fault: np.ndarray) -> np.ndarray:
    """``fbg_ref_update`` of fbg_internal.h on one recording from a fresh state: the
    temperature reference (n,) that the compensation of each sample without a fault reads.
    acc = r * 2^ref_shift in fm: the first good sample sets it to shift_T << ref_shift, the
    n-th adds (shift_T - rshift_round(acc, ref_shift)) << (ref_shift - s), s =
    :func:`fbgforce.model.floatref.reference_gain_shift` (n, ref_shift); r =
    rshift_round(acc, ref_shift); a faulty sample leaves acc alone (its row keeps its own
    shift_T, which nothing reads). ref_shift 0 is shift_T itself."""
    shift_t = np.asarray(shift_t, dtype=np.int64)
    k = q.ref_shift
    if k == 0:
        return shift_t
    ref = shift_t.copy()
    acc, half = 0, 1 << (k - 1)
    # Python integers, sample by sample, exactly the C recursion (as the memory's averages).
    for n, i in enumerate(np.flatnonzero(~np.asarray(fault, dtype=bool)).tolist(), start=1):
        x = int(shift_t[i])
        step = k - floatref.reference_gain_shift(n, k)
        acc = x << k if n == 1 else acc + ((x - ((acc + half) >> k)) << step)
        ref[i] = (acc + half) >> k
    return ref


def creep_inverse(q: QModel, comp: np.ndarray, ok: np.ndarray, acc: list[list[int] | None]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``creep_inverse`` of fbg_stage_front.c on consecutive samples: the compensated shifts ``comp``
    (n, 4) fm with the pad's creep taken out of the rows ``ok`` (the others, faulty, keep
    theirs and leave the state alone). Per grating, ``L = rshift_round(acc, creep_shift)``,
    ``e = sat32(c + rshift_round((c - L) * creep_q15, 15))``, ``acc += e - L``; ``acc[0]`` is
    the state (None: the first good sample primes it at ``c << creep_shift``, ``e = c``),
    updated in place. Returns ``e`` and which rows clamped. ``creep_q15`` 0: ``comp`` itself."""
    clamped = np.zeros(comp.shape[0], dtype=bool)
    if q.creep_q15 == 0:
        return comp, clamped
    k, g = q.creep_shift, q.creep_q15
    half = 1 << (k - 1)
    out = comp.copy()
    # Python integers, sample by sample, exactly the C recursion (as the memory's averages).
    for i in np.flatnonzero(ok).tolist():
        c = [int(v) for v in comp[i].tolist()]
        if acc[0] is None:
            acc[0] = [v << k for v in c]
            continue
        state = acc[0]
        for ch in range(4):
            lag = (state[ch] + half) >> k
            e = c[ch] + (((c[ch] - lag) * g + (1 << 14)) >> 15)
            if abs(e) > SAT32:
                e, clamped[i] = SAT32 if e > 0 else -SAT32, True
            state[ch] += e - lag
            out[i, ch] = e
    return out, clamped


# --------------------------------------------------------------------------------------------
# Filter (filter_stage): the causal FIR, the standardisation, the load proxy
# --------------------------------------------------------------------------------------------

def _fir(q: QModel, state: _State, comp: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """The causal FIR's accumulators (m, 4) over the carried history. A faulty sample feeds
    the FIR the last good sample's filtered shifts (``state.last_comp``), as the C ring does,
    so the block runs as alternating stretches of good and faulty samples."""
    n = comp.shape[0]
    k = q.taps.size - 1
    acc = np.zeros((n, 4), dtype=np.int64)
    edges = np.flatnonzero(np.diff(ok.astype(np.int8))) + 1 if n else np.zeros(0, dtype=np.int64)
    for a, b in zip(np.concatenate([[0], edges]), np.concatenate([edges, [n]])):
        part = comp[a:b] if ok[a] else np.repeat(state.last_comp[None, :], b - a, axis=0)
        seq = np.vstack([state.history, part])
        acc[a:b] = np.stack([np.convolve(seq[:, c], q.taps)[k:k + b - a] for c in range(4)],
                            axis=1)
        if k:
            state.history[:] = seq[-k:]
        if ok[a]:
            state.last_comp[:] = sat(rshift_round(acc[b - 1], q.tap_q), SAT32)[0]
    return acc


def _filter_stage(q: QModel, state: _State, comp: np.ndarray, ok: np.ndarray,
                  status: np.ndarray, flag: np.ndarray) -> np.ndarray:
    """``fbg_filter_stage`` of fbg_stage_filter.c: the FIR (:func:`_fir`), the standardisation into
    Q(z_frac) and the input-side overload of the linear load proxy (|coeff| < 2^28, so its
    sum stays < 2^61). Returns z (m, 4); flags saturation and OVERLOAD on the rows ``ok``."""
    acc = _fir(q, state, comp, ok)
    if state.trace is not None and comp.shape[0]:
        state.trace["fir"] = max(state.trace.get("fir", 0), int(np.abs(acc[ok]).max(initial=0)))
    filt, c4 = sat(rshift_round(acc, q.tap_q), SAT32)
    d, c5 = sat(filt - q.mean_fm, SAT32)
    z, c6 = sat(rshift_round(d * q.z_mult, q.z_shift), SAT16)
    flag |= ok & (c4 | c5 | c6).any(axis=1)
    load = rshift_round(filt @ q.load_coeff, q.load_shift)
    status |= np.where(ok & (load > q.load_max_mN), STATUS_OVERLOAD, 0)
    return z


# --------------------------------------------------------------------------------------------
# Memory (memory_stage): the memory features and the location averages
# --------------------------------------------------------------------------------------------

def _memory_stage(q: QModel, state: _State, z: np.ndarray, rows: np.ndarray,
                  status: np.ndarray, flag: np.ndarray) -> np.ndarray:
    """``fbg_memory_stage`` of fbg_stage_memory.c, then its OUT_OF_RANGE rule: the net inputs (m, F +
    location averages) of the fault-free ``rows`` in order (zeros on the others, which no
    net reads); flags saturation and inputs outside ``[in_lo, in_hi]``."""
    x, c_mem = state.memory.push(z[rows])
    flag[rows] |= c_mem
    nf = q.n_features
    outside = np.any((x[:, :nf] < q.in_lo[:nf]) | (x[:, :nf] > q.in_hi[:nf]), axis=1)
    status[rows] |= np.where(outside, STATUS_OUT_OF_RANGE, 0)
    feats = np.zeros((z.shape[0], nf + q.n_loc), dtype=np.int64)
    feats[rows] = x
    return feats


class _MemoryStage:
    """The memory states of fbg_stage_memory.c's ``memory_features`` (load-signal averages and play
    operators, location averages), carried from one block of fault-free samples to the next.
    The first sample primes them as at rest after a release; a faulty sample never reaches
    them, so a fault freezes them."""

    def __init__(self, q: QModel) -> None:
        self.q = q
        self.primed = False
        #: Every memory kind's states by kind name (contract.MEMORY_KINDS), once primed.
        self.states: dict[str, list[int]] = {}
        self.loc: list[int] = []

    def push(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Net inputs (m, F + location averages) of the next ``z`` (m, 4), and per sample
        whether a value saturated."""
        q = self.q
        z = np.asarray(z, dtype=np.int64).reshape(-1, 4)
        m = z.shape[0]
        nf = q.n_features
        feats = np.zeros((m, nf + q.n_loc), dtype=np.int64)
        feats[:, :4] = z
        clamped = np.zeros(m, dtype=bool)
        if m == 0:
            return feats, clamped
        if q.n_loc:
            feats[:, nf:], clamped = self._location_averages(z)
        if q.n_memory:
            feats[:, 4:nf], c_mem = self._load_features(z)
            clamped |= c_mem
        self.primed = True
        return feats, clamped

    def _load_features(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The load signal's features, every kind's in the order of ``contract.MEMORY_KINDS``
        (before sat16), and per sample whether u or a feature saturated."""
        q = self.q
        u, c_u = sat(rshift_round(z @ q.mem_mult, q.mem_shift), SAT16)
        columns = []
        for kind in contract.MEMORY_KINDS:
            prev = self.states[kind.name] if self.primed else None
            values, self.states[kind.name] = INT_MEMORY[kind.name](q, u, prev)
            columns.append(values)
        values, c2 = sat(np.concatenate(columns, axis=1), SAT16)
        return values, c_u | c2.any(axis=1)

    def _location_averages(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Q(z_frac) location inputs (m, 4) and where r or z0 saturated."""
        q = self.q
        z0, c0 = q.z_rest()
        r, c_r = sat(z - z0[None, :], SAT16)
        s = q.loc_shift
        if not self.primed:
            self.loc = [int(v) << EMA_FRAC for v in r[0].tolist()]
        out = _channel_averages(r, self.loc, s)
        # |state| <= 32767 << EMA_FRAC (docs/fixed-point.md): the rounded value needs no clamp.
        return rshift_round(out, EMA_FRAC), c_r.any(axis=1) | c0


def _channel_averages(x: np.ndarray, state: list[int], s: int) -> np.ndarray:
    """``state[c] += rshift_round((x[i, c] << EMA_FRAC) - state[c], s)`` for the samples of
    ``x`` (m, 4) in order, in Python integers, exactly the C recursion (as the load averages):
    the states after each sample (m, 4); ``state`` (4 values, Q(z_frac + EMA_FRAC)) is
    updated in place."""
    out = np.zeros(x.shape, dtype=np.int64)
    for i, xi in enumerate(x.tolist()):
        for c in range(4):
            state[c] += ((xi[c] << EMA_FRAC) - state[c] + (1 << (s - 1))) >> s
            out[i, c] = state[c]
    return out


# The memory kinds' update rules of fbg_stage_memory.c (``<kind>_features``) in Python integers,
# sample by sample: the recursions do not vectorise, and this keeps the rounding of every step
# exactly the C code's. Each takes the load signal ``u`` (m,) and the states (None: prime them
# as at rest after a release) and returns the features before sat16 (m, n) and the states.

def _ema_features(q: QModel, u: np.ndarray, states: list[int] | None
                  ) -> tuple[np.ndarray, list[int]]:
    """The exponential averages: e += rshift_round((u << EMA_FRAC) - e, shift), feature
    (u - rshift_round(e, EMA_FRAC)) << gain; primed at u << EMA_FRAC."""
    shifts = [int(v) for v in q.ema_shift[:q.n_ema]]
    ema = [int(u[0]) << EMA_FRAC for _ in shifts] if states is None else states
    mean = np.zeros((u.shape[0], q.n_ema), dtype=np.int64)
    if shifts:
        for i, ui in enumerate(u.tolist()):
            target = ui << EMA_FRAC
            for k, s in enumerate(shifts):
                ema[k] += (target - ema[k] + (1 << (s - 1))) >> s
                mean[i, k] = ema[k]
    return (u[:, None] - rshift_round(mean, EMA_FRAC)) << q.ema_gain[:q.n_ema][None, :], ema


def _play_features(q: QModel, u: np.ndarray, states: list[int] | None
                   ) -> tuple[np.ndarray, list[int]]:
    """The play operators: p = clamp(p, u - width, u + width), feature (u - p) << gain; primed
    at u + width (the load last went down)."""
    widths = [int(v) for v in q.play_width[:q.n_play]]
    play = [int(u[0]) + w for w in widths] if states is None else states
    state = np.zeros((u.shape[0], q.n_play), dtype=np.int64)
    if widths:
        for i, ui in enumerate(u.tolist()):
            for k, w in enumerate(widths):
                play[k] = min(max(play[k], ui - w), ui + w)
                state[i, k] = play[k]
    return (u[:, None] - state) << q.play_gain[:q.n_play][None, :], play


#: Every memory kind's update rule in the integer reference (``contract.MEMORY_KINDS`` by
#: name): ``(q, u, states) -> (features before sat16, states after)``.
INT_MEMORY: dict[str, Callable[[QModel, np.ndarray, list[int] | None], tuple[np.ndarray, list[int]]]] = {
    "ema": _ema_features,
    "play": _play_features,
}


def memory_features(q: QModel, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``memory_features`` of fbg_stage_memory.c on the consecutive fault-free samples ``z`` (m, 4)
    of one recording (the states are primed by the first as at rest after a release, and
    never see a faulty sample).

    Returns the net inputs (m, F + location averages) and, per sample, whether a value
    saturated.
    """
    return _MemoryStage(q).push(z)


def _location_averages(q: QModel, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The location averages of fbg_stage_memory.c's ``memory_features`` on consecutive fault-free
    ``z`` (m, 4), primed by the first: the Q(z_frac) inputs (m, 4) and where r or z0
    saturated."""
    return _MemoryStage(q)._location_averages(np.asarray(z, dtype=np.int64).reshape(-1, 4))


# --------------------------------------------------------------------------------------------
# Nets (contact_outputs, force_location_outputs): the three nets in integers
# --------------------------------------------------------------------------------------------

def _contact_outputs(q: QModel, state: _State, feats: np.ndarray, rows: np.ndarray,
                     status: np.ndarray, flag: np.ndarray, out: dict[str, np.ndarray]) -> np.ndarray:
    """``contact_outputs`` of fbg_fixed.c on the fault-free ``rows``: the contact net's margin
    (Q8), the decision over time (:func:`_contact_decision`) and the confidence; RELEASING in
    the release band. Returns where the decision holds, per row (contact and its release
    band: where the force and location run)."""
    f_ok = np.zeros(rows.size, dtype=bool)
    acc_c, margin = _net(q.nets[0], feats[rows, :q.n_features], f_ok, state.trace, "contact")
    contact, held = _contact_decision(q, acc_c[:, 0] > 0, margin[:, 0], state.decision)
    out["contact_margin_q8"][rows] = margin[:, 0]
    out["contact_conf_q15"][rows] = sigmoid_q15(margin[:, 0])
    out["contact"][rows] = contact
    status[rows] |= np.where(held & ~contact, STATUS_RELEASING, 0).astype(status.dtype)
    flag[rows] |= f_ok
    return held


def _force_location_outputs(q: QModel, state: _State, feats: np.ndarray, rows: np.ndarray,
                            contact: np.ndarray, status: np.ndarray, flag: np.ndarray,
                            out: dict[str, np.ndarray]) -> None:
    """``force_location_outputs`` of fbg_fixed.c on the ``rows`` where the decision holds
    (``contact``: contact and its release band): the
    force net, then the location net on [z, contact << z_frac, the force in Q(z_frac),
    location averages], then the settled-hold gain (:func:`_hold_stage`), which runs on every
    fault-free sample in order because one without contact clears it. Flags saturation and
    OVERLOAD above ``overload_mN``."""
    crow = rows[contact]
    nf = q.n_features
    f_c = np.zeros(crow.size, dtype=bool)
    _, force_out = _net(q.nets[1], feats[crow, :nf], f_c, state.trace, "force")
    force_out = force_out[:, 0]
    force_mN, c7 = sat(force_out + q.force_offset_mN, SAT32)
    fq, c8 = sat(rshift_round(force_out * q.fq_mult, q.fq_shift), SAT16)
    loc_in = np.column_stack([feats[crow, :4], np.full(crow.size, 1 << q.z_frac), fq,
                              feats[crow, nf:]])
    _, xy = _net(q.nets[2], loc_in, f_c, state.trace, "location")
    x_um, c9 = sat(xy[:, 0] + q.xy_offset_um[0], SAT32)
    y_um, c10 = sat(xy[:, 1] + q.xy_offset_um[1], SAT32)
    f_c |= c7 | c8 | c9 | c10
    if q.hold_gain_q15:
        seq = np.zeros(rows.size, dtype=np.int64)
        seq[contact] = force_mN
        held, c11 = _hold_stage(q, seq, contact, state.hold)
        force_mN = held[contact]
        f_c |= c11[contact]
    out["force_mN"][crow] = force_mN
    out["x_um"][crow] = x_um
    out["y_um"][crow] = y_um
    flag[crow] |= f_c
    status[crow] |= np.where(force_mN > q.overload_mN, STATUS_OVERLOAD, 0)


def _net(layers: list[QLayer], x: np.ndarray, flag: np.ndarray, trace: dict | None, name: str
         ) -> tuple[np.ndarray, np.ndarray]:
    """Hidden layers then the output layer's accumulator and sat32 output (per row)."""
    for i, layer in enumerate(layers[:-1]):
        if trace is not None and x.size:
            trace[f"{name}.{i}"] = max(trace.get(f"{name}.{i}", 0),
                                       int(np.abs(_acc(layer, x, i > 0)).max()))
        x = _hidden(layer, x, flag, i > 0)
    last = layers[-1]
    acc = _acc(last, x, len(layers) > 1)
    if trace is not None and x.size:
        key = f"{name}.{len(layers) - 1}"
        trace[key] = max(trace.get(key, 0), int(np.abs(acc).max()))
    y, clamped = sat(rshift_round(acc * last.mult, last.shift), SAT32)
    flag |= clamped.any(axis=1)
    return acc, y


def _hidden(layer: QLayer, x: np.ndarray, flag: np.ndarray, relu_inputs: bool = False
            ) -> np.ndarray:
    acc = _acc(layer, x, relu_inputs)
    y = rshift_round(acc * layer.mult, layer.shift)
    y, clamped = sat(np.maximum(y, 0), SAT16)
    flag |= clamped.any(axis=1)
    return y


def _acc(layer: QLayer, x: np.ndarray, relu_inputs: bool) -> np.ndarray:
    """The layer's accumulators. For an int32 layer (``acc32``) the sum is taken in int32, as
    the C code does. It equals the int64 sum because the bound below (the loader's proof,
    inputs are sat16 values, and ReLU outputs >= 0 after the first layer) keeps every partial
    sum inside int32; numpy would wrap silently otherwise, hence the check."""
    if not layer.acc32:
        return x @ layer.w.T + layer.bias
    # The proof that applies to these inputs: the ReLU-input bound needs x >= 0.
    nonneg = x.size == 0 or int(x.min()) >= 0
    if (relu_inputs and not nonneg) or (x.size and int(np.abs(x).max()) > SAT16) \
            or int(layer.acc32_bound(nonneg).max()) > SAT32:
        raise ValueError("int32 accumulator without the int32 bound proof")
    acc = x.astype(np.int32) @ layer.w.T.astype(np.int32) + layer.bias.astype(np.int32)
    return acc.astype(np.int64)


# --------------------------------------------------------------------------------------------
# Decision (contact_decision): contact over time
# --------------------------------------------------------------------------------------------

def _contact_decision(q: QModel, raw: np.ndarray, margin: np.ndarray, state: list[int]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``fbg_contact_decision`` of fbg_stage_decision.c on consecutive fault-free samples: the rule of
    :func:`fbgforce.model.decision.decide_over_time` on the Q8 margins, in Python integers (exact).
    ``raw`` is ``acc > 0`` and ``margin`` the output row as computed, whatever the sign of its
    multiplier: the rule reads both as C does, with no shortcut for the per-sample setting
    (which equals ``raw`` only when the multiplier is positive). ``state`` is ``[decision,
    rise_run, cusum_q8, released, release_run]``, carried and updated. Returns the contact shown
    and where the decision holds."""
    return decision.decide_over_time(raw, margin, q.contact_on_q8, q.contact_off_q8, q.contact_rise_n,
                               state, cusum=(q.contact_cusum_h_q8, q.contact_cusum_k_q8,
                                             q.contact_cusum_lo_q8, q.contact_cusum_hi_q8))


# --------------------------------------------------------------------------------------------
# Rest tracker (rest_track): the at-rest baseline tracker
# --------------------------------------------------------------------------------------------

class _RestTracker:
    """``fbg_rest_track`` of fbg_stage_tracker.c: the at-rest baseline tracker's state, and its update at
    the end of each TRACK_BLOCK block."""

    def __init__(self, q: QModel) -> None:
        self.q = q
        self.rest_run = 0
        self.drift = [0] * 4
        self.frac = [0] * 4
        self.limited = False
        #: ``fbg_creep_update`` of fbg_stage_tracker.c: the creep states, None until the first good sample.
        self.creep: list[int] | None = None

    def rest_terms(self, z: np.ndarray, z0: np.ndarray) -> np.ndarray:
        """What each of the consecutive fault-free samples ``z`` (m, 4) would add to the
        block's sum at rest: ``z - z0``, less ``rshift_round((creep - (z0 << EMA_FRAC)) *
        track_creep_q15, 30)`` with the creep term on, the creep states stepped by every
        sample first (primed at ``z << EMA_FRAC`` by the first)."""
        q = self.q
        terms = z - z0[None, :]
        if q.track_creep_q15 == 0 or z.shape[0] == 0:
            return terms
        if self.creep is None:
            self.creep = [int(v) << EMA_FRAC for v in z[0].tolist()]
        states = _channel_averages(z, self.creep, q.track_creep_shift)
        # |states - (z0 << EMA_FRAC)| < 2^31 times track_creep_q15 <= 2^14: int64.
        return terms - rshift_round((states - (z0[None, :] << EMA_FRAC)) * q.track_creep_q15, 30)

    def end_block(self, rest: np.ndarray, r_sum: np.ndarray, base: np.ndarray) -> None:
        """After a block: ``rest`` says which of its samples were at rest (in order),
        ``r_sum`` is their sum of :meth:`rest_terms`; moves ``base[:4]`` in place."""
        q = self.q
        self.rest_run = floatref.rest_run_after(self.rest_run, rest)
        if q.track_shift == 0 or self.rest_run < contract.LIMIT["TRACK_BLOCK"] + q.track_settle:
            return
        frac_bits = contract.LIMIT["TRACK_FRAC"]
        for c in range(4):
            frac = self.frac[c] + int(r_sum[c]) * int(q.track_gain[c])
            step = (frac + (1 << (frac_bits - 1))) >> frac_bits
            if abs(step) > q.track_step_max_fm:
                step = q.track_step_max_fm if step > 0 else -q.track_step_max_fm
                frac = 0
            else:
                frac -= step << frac_bits
            drift = self.drift[c] + step
            if abs(drift) > q.track_limit_fm:
                drift = q.track_limit_fm if drift > 0 else -q.track_limit_fm
                frac = 0
                self.limited = True
            base[c] += drift - self.drift[c]
            self.drift[c] = drift
            self.frac[c] = frac


# --------------------------------------------------------------------------------------------
# Hold (hold_stage): the settled-hold gain
# --------------------------------------------------------------------------------------------

def _hold_stage(q: QModel, force_mN: np.ndarray, contact: np.ndarray, state: list[int]
          ) -> tuple[np.ndarray, np.ndarray]:
    """``fbg_hold_stage`` of fbg_stage_hold.c (the settled-hold gain, the rule of
    :func:`fbgforce.model.floatref.hold_over_time` in integers) on consecutive fault-free samples: their
    force (mN, any value where there is no contact) and contact decisions. ``state`` is
    ``[hold_avg, hold_primed, hold_run]``, carried and updated. Returns the force and where it
    saturated."""
    out = np.asarray(force_mN, dtype=np.int64).copy()
    flag = np.zeros(out.size, dtype=bool)
    if q.hold_gain_q15 == 0:
        return out, flag
    avg, primed, run = state
    frac, settle, ramp = contract.LIMIT["EMA_FRAC"], q.hold_settle, 1 << q.hold_ramp_shift
    top = settle + ramp
    for i, (f, c) in enumerate(zip(out.tolist(), np.asarray(contact, dtype=bool).tolist())):
        if not c:
            primed, run = 0, 0
            continue
        if primed:
            avg += (((f << frac) - avg) + (1 << (q.hold_shift - 1))) >> q.hold_shift
        else:
            avg, primed = f << frac, 1
        dev = f - ((avg + (1 << (frac - 1))) >> frac)
        band = max(q.hold_band_mN, (abs(f) * q.hold_band_q15 + (1 << 14)) >> 15)
        if abs(dev) <= band:
            if run < top and run < 0xFFFF:
                run += 1
        else:
            run = 0
        w = min(max(run - settle, 0), ramp)
        shift = 15 + q.hold_ramp_shift
        v = f + ((f * q.hold_gain_q15 * w + (1 << (shift - 1))) >> shift)
        flag[i] = abs(v) > SAT32
        out[i] = max(-SAT32, min(SAT32, v))
    state[0], state[1], state[2] = avg, primed, run
    return out, flag
