"""The float reference engine: the one float64 implementation of the shipped pipeline, the
reference every other engine (onnxruntime, C float, C fixed-point) is compared against.

Its stages carry the names of the C runtimes' (runtime_c/src/fbg_fixed.c, fbgf_float.c), in
the order a sample meets them: the front stage (tare, temperature compensation, creep
inverse: :func:`compensate`, :func:`creep_inverse`), the filter stage (:func:`apply_filter`,
:func:`filter_through_faults`), the memory stage (:func:`memory_features`), the nets
(:func:`numpy_nets`, :func:`predict_from_features`), the contact decision
(:func:`fbgforce.model.decision.decide_over_time`), the hold stage (:func:`hold_over_time`)
and the rest tracker (:class:`FloatPipeline`); :func:`predict` runs them all on a recording.

The pipeline, per sample ``n`` and strain channel ``i`` = 1..4 (docs/trainer.md)::

    shift_i[n]  = 1000 * (wl_i[n] - baseline_i)                      # tare, pm
    shift_T[n]  = 1000 * (wl_T[n] - baseline_T)
    r[n]        = r[n-1] + (shift_T[n] - r[n-1]) / 2^ref_shift         # the reference, averaged
    comp_i[n]   = shift_i[n] - temp_coeff_i * r[n]                     # temperature compensation
    e_i[n]      = comp_i[n] + q * (comp_i[n] - L_i[n-1])                # the pad's creep inverse
    L_i[n]      = L_i[n-1] + (e_i[n] - L_i[n-1]) / 2^creep_shift
    filt_i[n]   = sum_k taps[k] * e_i[n - k]                           # causal FIR, zero history
    z_i[n]      = (filt_i[n] - input_mean_i) / input_std_i            # standardisation
    u[n]        = sum_i weight_i * z_i[n]                              # memory: a load signal,
    e_k[n]      = e_k[n-1] + (u[n] - e_k[n-1]) / 2^ema_shift[k]       # its averages ...
    p_k[n]      = clamp(p_k[n-1], u[n] - w_k, u[n] + w_k)             # ... and play operators
    x           = [z, (u - e_k) * 2^ema_gain[k] for each k, (u - p_k) * 2^play_gain[k] for each k]
    logits      = contact_net(x)            -> contact = logits[1] > logits[0]
    f           = force_net(x)[0]           -> force_N = force_offset + force_scale * f
    r_i[n]      = z_i[n] - z0_i,  z0_i = -input_mean_i / input_std_i  # rest-referenced z
    a_i[n]      = a_i[n-1] + (r_i[n] - a_i[n-1]) / 2^loc_shift         # location averages
    (u, v)      = location_net([z, contact, f, a if loc_shift])        # not the load memory
    x_mm        = xy_offset[0] + xy_scale[0] * u,   y_mm likewise
    outputs: force_N is 0 and x/y are NaN where contact is False.

The reference average ``r`` is primed by the first good sample (``r = shift_T``) of a
recording, as the runtimes' after init, tare, reset or a new baseline; a sensor-fault sample
does not update it (held), and ``ref_shift`` 0 gives ``r = shift_T``. Temperature moves
slowly, so averaging the reference grating over tens of milliseconds costs no lag worth
having and keeps its own noise out of every compensated channel (docs/trainer.md,
"Temperature reference").

The creep inverse undoes a viscoelastic pad (a standard linear solid): its gratings read
``s = (1 - m) e + m lag(e)`` of the elastic strain ``e``, ``lag`` first order with step
``2^-creep_shift`` (``lag[n] = lag[n-1] + (e[n] - lag[n-1]) / 2^creep_shift``), so
``s[n] = (1 - kappa) e[n] + kappa lag[n-1]`` with ``kappa = m (1 - 2^-creep_shift)``, and
``e[n] = s[n] + q (s[n] - lag[n-1])`` with ``q = kappa / (1 - kappa)`` is its exact causal
inverse (``L`` above is ``lag``). ``m`` is ``creep`` (0 .. 0.5; 0: off, ``e = comp``). ``L`` is
primed ``L = comp`` (so ``e = comp``) by the first good sample of a recording, as the runtimes'
after init, tare, reset or a new baseline; a sensor-fault sample leaves it untouched (the
filter is fed the last good filtered shifts instead). It runs wherever a continuous
recording's compensated shifts feed the filter (:func:`apply_filter`, :func:`features`,
:class:`FloatPipeline`), never on rows compensated one by one.

The memory states are primed by the recording's first sample as a pad at rest after a release
leaves them (averages at u, play operators at u + width: the load last moved down), as the
runtime's after a tare or reset, so the features read at the start what they read at every
rest of the calibration data. The centred filter (``filter_kind == "centred"``) is the paper's offline smoothing, for
reproducing its figures; it uses future samples and cannot be exported to the runtime.
"""
from __future__ import annotations

import functools
from typing import Any, Callable

import numpy as np

from fbgforce import contract, samples
from fbgforce.errors import InputError
from fbgforce.model.artifact import N_STRAIN, HierarchicalModel, InUse, Memory, Preprocess
from fbgforce.model.decision import decide_over_time
from fbgforce.units import gate_outputs

#: The status bit of the release band (:func:`fbgforce.units.estimate_shown`).
RELEASING = contract.STATUS_FLAG["RELEASING"]


# --------------------------------------------------------------------------------------------
# First-order recursions in closed form
# --------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=64)
def _first_order_weights(alpha: float, block: int) -> tuple[np.ndarray, np.ndarray]:
    """The closed form's weights for blocks of ``block`` samples (read-only): made once per
    step and block length, since a stream fed sample by sample asks for the same ones at
    every sample."""
    i = np.arange(block)
    w_full = np.tril((1.0 - alpha) ** (i[:, None] - i[None, :])) * alpha
    decay = (1.0 - alpha) ** (i + 1)
    w_full.setflags(write=False)
    decay.setflags(write=False)
    return w_full, decay


def _exp_average(x: np.ndarray, shift: int, prev: np.ndarray) -> np.ndarray:
    """e[n] = e[n-1] + (x[n] - e[n-1]) / 2^shift along axis 0 of ``x`` (n, k) from ``prev``
    (k,): a first-order IIR (:func:`_first_order` with step ``2^-shift``)."""
    return _first_order(x, 2.0 ** -shift, prev)


def _first_order(x: np.ndarray, alpha: float, prev: np.ndarray) -> np.ndarray:
    """e[n] = e[n-1] + alpha * (x[n] - e[n-1]) along axis 0 of ``x`` (n, k) from ``prev``
    (k,), 0 < alpha <= 1. A blocked closed form keeps it exact to rounding and fast in numpy:
    within a block of 256 the powers of (1 - alpha) cannot underflow for the steps used here
    (2^-15 .. 1, :func:`_exp_average` and :func:`creep_inverse`)."""
    n = x.shape[0]
    e = np.empty_like(x)
    block = min(n, 256)
    w_full, decay = _first_order_weights(float(alpha), block)
    for start in range(0, n, block):
        seg = x[start:start + block]
        m = seg.shape[0]
        out = decay[:m, None] * prev[None, :] + w_full[:m, :m] @ seg
        e[start:start + m] = out
        prev = out[-1]
    return e


# --------------------------------------------------------------------------------------------
# Front stage: tare, temperature compensation, creep inverse
# --------------------------------------------------------------------------------------------

#: Good samples after which the temperature reference's gain no longer falls: its count
#: saturates there (``fbg_state.ref_count``, uint8; 2^MAX_REF_SHIFT = 256 needs no more).
REFERENCE_COUNT_MAX = 255


def reference_gain_shift(n: int, ref_shift: int) -> int:
    """``s`` of the n-th good sample's step ``(shift_T - r) / 2^s`` of the temperature
    reference's average: ``min(ref_shift, floor(log2 n))``, n >= 1. Over the first 2^ref_shift
    samples the average is (nearly) their running mean. A gain of 2^-ref_shift from the second
    sample on would keep the first sample's noise for about 2^ref_shift samples: a step on all
    four compensated gratings at once, which the memory's play operators hold while the pad
    rests (docs/fixed-point.md, "Temperature reference")."""
    return min(ref_shift, int(n).bit_length() - 1)


def reference_average(shift_t: np.ndarray, ref_shift: int, fault: np.ndarray,
                      prev: tuple[float, int] | None = None
                      ) -> tuple[np.ndarray, tuple[float, int] | None]:
    """The temperature reference the compensation subtracts: the n-th sample without a fault
    (in order since the state was fresh) moves ``r`` by ``(shift_T[n] - r) / 2^s``, ``s =``
    :func:`reference_gain_shift` ``(n, ref_shift)`` (the first sets ``r = shift_T``).

    Parameters
    ----------
    shift_t
        (n,) the reference grating's shift, pm.
    ref_shift
        The average's shift (0: ``r = shift_T``).
    fault
        (n,) True for a sensor-fault sample: it leaves the average as it was (its own row
        gets its raw shift, which no engine reads).
    prev
        ``(r, count)``: the average and the good samples it holds (counted up to
        :data:`REFERENCE_COUNT_MAX`) before the first sample; None: a fresh state.

    Returns
    -------
    tuple
        ``r`` (n,) and the state after the samples (``prev`` when none was good), to carry
        into the next call.
    """
    shift_t = np.asarray(shift_t, dtype=np.float64)
    good = np.flatnonzero(~np.asarray(fault, dtype=bool))
    if not ref_shift or good.size == 0:
        return shift_t, prev
    x = shift_t[good]
    avg, count = (0.0, 0) if prev is None else prev
    out = np.empty_like(x)
    # While the gain still falls, sample by sample (at most 2^ref_shift of them); then the
    # plain exponential average.
    ramp = min(x.size, max(0, (1 << ref_shift) - 1 - count))
    for i in range(ramp):
        n = count + 1 + i
        avg = x[i] if n == 1 else avg + (x[i] - avg) / 2.0 ** reference_gain_shift(n, ref_shift)
        out[i] = avg
    if ramp < x.size:
        out[ramp:] = _exp_average(x[ramp:, None], ref_shift, np.array([avg]))[:, 0]
    r = shift_t.copy()
    r[good] = out
    return r, (float(out[-1]), min(count + x.size, REFERENCE_COUNT_MAX))


def compensate(model: HierarchicalModel, wl_nm: np.ndarray, baseline_nm: np.ndarray,
               reference: list[tuple[float, int] | None] | None = None,
               fault: np.ndarray | None = None) -> np.ndarray:
    """Tare and temperature-compensate raw wavelengths.

    Parameters
    ----------
    wl_nm
        (n, 5) peak wavelengths of gratings 1..4 and T, nm.
    baseline_nm
        (5,) unloaded wavelengths to tare against, nm.
    reference
        ``[state]``: the temperature reference's average before the samples
        (:func:`reference_average`'s ``prev``; None: a fresh one), updated in place; None: a
        recording of its own. Read only when
        ``preprocess.ref_shift`` is on (:func:`reference_average`).
    fault
        (n,) the samples' sensor faults, :func:`fbgforce.samples.sensor_fault_rows` of
        ``wl_nm`` (None: found here), which the reference's average skips.

    Returns
    -------
    numpy.ndarray
        (n, 4) compensated strain-grating shifts in pm.
    """
    wl = np.asarray(wl_nm, dtype=np.float64)
    pre = model.preprocess
    shift_pm = (wl - np.asarray(baseline_nm, dtype=np.float64)) * 1000.0
    ref = shift_pm[:, N_STRAIN]
    if pre.ref_shift:
        state = [None] if reference is None else reference
        if fault is None:
            fault = samples.sensor_fault_rows(wl)
        ref, state[0] = reference_average(ref, pre.ref_shift, fault, state[0])
    return shift_pm[:, :N_STRAIN] - ref[:, None] * pre.temp_coeff


def creep_lags(pre: Preprocess, comp: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """The creep inverse's lag ``L`` (n, 4) after each of the compensated shifts ``comp``
    (n, 4), pm, of one continuous recording from ``prev`` (4,) before them: ``L`` follows
    ``c`` with step ``(1 + q) / 2^creep_shift`` (:func:`creep_inverse`). ``pre.creep`` > 0."""
    return _first_order(np.asarray(comp, dtype=np.float64),
                        (1.0 + pre.creep_gain) * 2.0 ** -pre.creep_shift, prev)


def creep_inverse(pre: Preprocess, comp: np.ndarray, lag: list[np.ndarray | None] | None = None,
                  fault: np.ndarray | None = None) -> np.ndarray:
    """The pad's creep taken out of the compensated shifts of one continuous recording, per
    strain grating: ``e = c + q (c - L)``, then ``L += (e - L) / 2^creep_shift``
    (``q`` :attr:`~fbgforce.model.artifact.Preprocess.creep_gain`; the module's docstring derives
    it), i.e. ``L``
    follows ``c`` with step ``(1 + q) / 2^creep_shift``.

    Parameters
    ----------
    pre
        The preprocessing (``creep`` 0: ``comp`` is returned as it is).
    comp
        (n, 4) compensated shifts, pm, in order.
    lag
        ``[L]``: the lags (4,) before the samples (None: the first good sample primes them,
        ``L = c``, so ``e = c`` there), updated in place; None: a recording of its own.
    fault
        (n,) True for a sensor-fault sample: it leaves ``L`` as it was and keeps its own row
        (which no engine filters: the filter is fed the last good filtered shifts). None: no
        fault.

    Returns
    -------
    numpy.ndarray
        (n, 4) the elastic shifts ``e`` that replace ``comp`` before the filter.
    """
    comp = np.asarray(comp, dtype=np.float64)
    if not pre.creep:
        return comp
    good = np.arange(comp.shape[0]) if fault is None else np.flatnonzero(~np.asarray(fault, dtype=bool))
    state = [None] if lag is None else lag
    if good.size == 0:
        return comp
    c = comp[good]
    prev = c[0].copy() if state[0] is None else np.asarray(state[0], dtype=np.float64)
    q = pre.creep_gain
    lags = creep_lags(pre, c, prev)
    before = np.vstack([prev[None, :], lags[:-1]])
    out = comp.copy()
    out[good] = c + q * (c - before)
    state[0] = lags[-1].copy()
    return out


# --------------------------------------------------------------------------------------------
# Filter stage: the causal FIR and standardisation
# --------------------------------------------------------------------------------------------

def apply_filter(pre: Preprocess, x: np.ndarray) -> np.ndarray:
    """The pad's creep inverse (:func:`creep_inverse`, primed by the first sample), then the
    model's FIR, along axis 0 of the compensated shifts ``x`` of one continuous recording.

    Causal: zero history before the first sample, as the runtime after a tare. Centred: edges
    padded with the nearest sample (offline only).
    """
    return _fir(pre, creep_inverse(pre, x))


def _fir(pre: Preprocess, x: np.ndarray) -> np.ndarray:
    """The model's FIR alone along axis 0 of ``x`` (:func:`apply_filter`)."""
    x = np.asarray(x, dtype=np.float64)
    taps = pre.taps
    if pre.filter_kind == "none" or taps.size == 1:
        return x * taps.sum() if taps.size == 1 else x.copy()
    n = x.shape[0]
    out = np.empty_like(x)
    if pre.filter_kind == "causal":
        padded = np.concatenate([np.zeros((taps.size - 1,) + x.shape[1:]), x])
        for c in range(x.shape[1]):
            out[:, c] = np.convolve(padded[:, c], taps, mode="valid")[:n]
        return out
    half = taps.size // 2
    padded = np.concatenate([np.repeat(x[:1], half, axis=0), x, np.repeat(x[-1:], half, axis=0)])
    for c in range(x.shape[1]):
        # np.convolve flips its kernel; taps[::-1] makes taps[k] weight sample n + k - half.
        out[:, c] = np.convolve(padded[:, c], taps[::-1], mode="valid")
    return out


def filter_through_faults(taps: np.ndarray, comp: np.ndarray, fault: np.ndarray,
                          history: np.ndarray, last: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The causal FIR ``taps`` over compensated shifts ``comp`` (n, 4) of one recording, as
    the runtimes run it through sensor faults: a faulty sample feeds the filter ``last``, the
    last good sample's filtered shifts (the runtimes' ``last_comp``), so a burst of faults
    holds the output where it was instead of holding one raw sample's noise.

    Returns the filtered shifts (n, 4), the filter's history (its ``len(taps) - 1`` last
    inputs) and ``last`` after the samples, to carry into the next call.
    """
    n, k = comp.shape[0], taps.size - 1
    filt = np.zeros((n, N_STRAIN))
    history, last = np.array(history, dtype=np.float64), np.array(last, dtype=np.float64)
    edges = np.flatnonzero(np.diff(fault.astype(np.int8))) + 1 if n else np.zeros(0, int)
    for a, b in zip(np.concatenate([[0], edges]), np.concatenate([edges, [n]])):
        part = np.repeat(last[None, :], b - a, axis=0) if fault[a] else comp[a:b]
        seq = np.vstack([history, part])
        filt[a:b] = np.stack([np.convolve(seq[:, c], taps)[k:k + b - a]
                              for c in range(N_STRAIN)], axis=1)
        if k:
            history = seq[-k:]
        if not fault[a]:
            last = filt[b - 1].copy()
    return filt, history, last


def standardise(pre: Preprocess, filt: np.ndarray) -> np.ndarray:
    """Net inputs (n, F) of one continuous recording from its filtered shifts (n, 4), pm:
    standardisation, then the memory features."""
    return memory_features(pre.memory, (np.asarray(filt, dtype=np.float64) - pre.input_mean)
                           / pre.input_std, pre.z_rest)


# --------------------------------------------------------------------------------------------
# Memory stage: the load signal's states and the location averages
# --------------------------------------------------------------------------------------------

class MemoryStream:
    """The memory states of one continuous recording, fed in pieces: ``push(z)`` on
    consecutive pieces gives what :func:`memory_features` gives on the whole.

    ``z_rest`` (4,): the standardised channels at rest
    (:attr:`~fbgforce.model.artifact.Preprocess.z_rest`), needed by
    the location averages (``memory.loc_shift``)."""

    def __init__(self, memory: Memory, z_rest: np.ndarray | None = None) -> None:
        self.memory = memory
        #: Every kind's states by kind name; None until the first sample primes them.
        self.states: dict[str, list[float]] | None = None
        self.loc: np.ndarray | None = None
        if memory.loc_shift and z_rest is None:
            raise ValueError("the location averages need z_rest (Preprocess.z_rest)")
        self.z_rest = None if z_rest is None else np.asarray(z_rest, dtype=np.float64).reshape(N_STRAIN)

    def push(self, z: np.ndarray) -> np.ndarray:
        """Net inputs (n, 4 + states + location averages) of the next ``z`` (n, 4) of the
        recording."""
        memory = self.memory
        z = np.asarray(z, dtype=np.float64).reshape(-1, N_STRAIN)
        n = z.shape[0]
        if n == 0:
            return np.zeros((0, N_STRAIN + memory.n_states + memory.n_loc))
        feats = [z]
        if memory.n_states:
            feats += self._load_features(z)
        if memory.n_loc:
            r = z - self.z_rest
            if self.loc is None:    # primed by the first sample, as the load averages
                self.loc = r[0].copy()
            a = _exp_average(r, memory.loc_shift, self.loc)
            self.loc = a[-1].copy()
            feats.append(a)
        return np.concatenate(feats, axis=1) if len(feats) > 1 else z.copy()

    def _load_features(self, z: np.ndarray) -> list[np.ndarray]:
        """The load signal's features, every kind's in the order of ``contract.MEMORY_KINDS``,
        one column each."""
        u = z @ np.asarray(self.memory.weights)
        feats: list[np.ndarray] = []
        states: dict[str, list[float]] = {}
        for kind in contract.MEMORY_KINDS:
            prev = None if self.states is None else self.states[kind.name]
            columns, states[kind.name] = FLOAT_MEMORY[kind.name](self.memory, u, prev)
            feats += columns
        self.states = states
        return feats


def _ema_features(memory: Memory, u: np.ndarray, states: list[float] | None
                  ) -> tuple[list[np.ndarray], list[float]]:
    """The exponential averages of ``u``: features ``(u - e_k) * 2^gain``, one column each,
    and the states after the last sample (``states`` None: primed at u[0])."""
    states = [float(u[0])] * len(memory.ema_shifts) if states is None else states
    feats, after = [], []
    for state, shift, gain in zip(states, memory.ema_shifts, memory.ema_gains):
        e = _exp_average(u[:, None], shift, np.array([state]))[:, 0]
        after.append(float(e[-1]))
        feats.append(((u - e) * 2.0 ** gain)[:, None])
    return feats, after


def _play_features(memory: Memory, u: np.ndarray, states: list[float] | None
                   ) -> tuple[list[np.ndarray], list[float]]:
    """The play operators of ``u``: features ``(u - p_k) * 2^gain``, one column each, and the
    states after the last sample (``states`` None: primed at u[0] + width, the load last went
    down)."""
    states = [float(u[0]) + w for w in memory.play_widths] if states is None else states
    feats, after = [], []
    for state, width, gain in zip(states, memory.play_widths, memory.play_gains):
        p = play_path(float(state), u - width, u + width)
        after.append(float(p[-1]) if p.size else float(state))
        feats.append(((u - p) * 2.0 ** gain)[:, None])
    return feats, after


def play_path(state: float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``p_i = min(max(p_{i-1}, lo_i), hi_i)`` from ``p_{-1} = state`` (``lo <= hi``), bit for
    bit what that loop gives, without it.

    Clamps compose into clamps: clamping into ``[a, b]`` after ``[A, B]`` is clamping into
    ``[min(max(A, a), b), min(max(B, a), b)]``. So the clamps of every prefix come from a scan
    that doubles its span each step (log2 n passes over the arrays), and each ``p_i`` is
    ``state`` clamped by its prefix's. Only ``min`` and ``max`` are taken, which round
    nothing: every ``p_i`` is the loop's."""
    a = np.array(lo, dtype=np.float64)
    b = np.array(hi, dtype=np.float64)
    span = 1
    while span < a.size:
        # The clamp of samples (i - 2 span, i]: those of (i - span, i] after those before.
        later_a, later_b = a[span:], b[span:]
        first_a = np.minimum(np.maximum(a[:-span], later_a), later_b)
        first_b = np.minimum(np.maximum(b[:-span], later_a), later_b)
        a[span:], b[span:] = first_a, first_b
        span *= 2
    return np.minimum(np.maximum(state, a), b)


#: Every memory kind's update rule in the float reference (``contract.MEMORY_KINDS`` by name):
#: ``(memory, u, states) -> (feature columns, states after)``.
FLOAT_MEMORY: dict[str, Callable[[Memory, np.ndarray, list[float] | None],
                                 tuple[list[np.ndarray], list[float]]]] = {
    "ema": _ema_features,
    "play": _play_features,
}


def memory_features(memory: Memory, z: np.ndarray, z_rest: np.ndarray | None = None
                    ) -> np.ndarray:
    """The net inputs of one continuous recording: ``z`` (n, 4) and its memory features.

    Returns (n, 4 + states + location averages) in the order of :mod:`fbgforce.contract`: z,
    then one feature per average, then one per play operator, all of the load signal
    ``u = z @ weights``, then the location averages of ``z - z_rest`` (if
    ``memory.loc_shift``); the states are primed by the first sample as a pad at rest after a
    release leaves them.
    """
    return MemoryStream(memory, z_rest).push(z)


def features(model: HierarchicalModel, wl_nm: np.ndarray, baseline_nm: np.ndarray) -> np.ndarray:
    """Net inputs (n, F) for one continuous recording: standardised channels and memory.

    Samples with a lost peak (:func:`fbgforce.samples.sensor_fault_rows`) are handled as the
    C runtime handles a sensor fault: the filter is fed the last good sample's filtered
    shifts (:func:`filter_through_faults`; zeros before any), the creep inverse
    (:func:`creep_inverse`) and the memory states skip the
    sample (they are frozen), and the sample's own row holds zeros in place of memory
    features (its outputs are the safe output). The centred (offline) filter, which no
    runtime runs, is fed the last good input instead.
    """
    pre = model.preprocess
    fault = samples.sensor_fault_rows(wl_nm)
    comp = compensate(model, wl_nm, baseline_nm, fault=fault)
    if not fault.any():
        return standardise(pre, apply_filter(pre, comp))
    good = np.flatnonzero(~fault)
    comp = creep_inverse(pre, comp, fault=fault)
    if pre.filter_kind == "centred":
        last_good = np.maximum.accumulate(np.where(fault, -1, np.arange(fault.size)))
        held = np.where((last_good >= 0)[:, None], comp[np.maximum(last_good, 0)], 0.0)
        filt = _fir(pre, held)
    else:
        taps = pre.runtime_taps()
        filt, _, _ = filter_through_faults(taps, comp, fault, np.zeros((taps.size - 1, N_STRAIN)),
                                           np.zeros(N_STRAIN))
    z = (filt - pre.input_mean) / pre.input_std
    out = np.zeros((z.shape[0], pre.n_inputs))
    out[:, :N_STRAIN] = z
    out[good] = memory_features(pre.memory, z[good], pre.z_rest)
    return out


# --------------------------------------------------------------------------------------------
# The nets
# --------------------------------------------------------------------------------------------

def location_inputs(x: np.ndarray, contact: np.ndarray, f: np.ndarray, n_loc: int = 0
                    ) -> np.ndarray:
    """The location net's input: the standardised channels (not the load signal's memory
    features), the contact decision (0/1), the force net's own (unscaled) output and, with
    ``n_loc`` location averages, the last ``n_loc`` columns of ``x``, as every engine builds
    it (:data:`fbgforce.contract.MEMORY_NETS`)."""
    x = np.asarray(x)
    cols = [x[:, :N_STRAIN], np.asarray(contact, dtype=np.float64), f]
    if n_loc:
        cols.append(x[:, x.shape[1] - n_loc:])
    return np.column_stack(cols)


#: ``nets(x, decide) -> raw outputs``: the three nets on net inputs x (n, F + location
#: averages), returning ``margin``, ``contact = decide(margin)`` (called once: the decision over
#: time carries its state from call to call), ``p_contact``, ``force_raw_N``, ``x_raw_mm``,
#: ``y_raw_mm``. The location net reads ``contact``, the decision the outputs are gated on, on
#: every row (:func:`location_inputs`): an engine that fed it another decision would report
#: another location wherever the two differ.
Nets = Callable[[np.ndarray, Callable[[np.ndarray], np.ndarray]], dict[str, np.ndarray]]


def gated_outputs(raw: dict[str, np.ndarray], contact: np.ndarray, out_of_range: np.ndarray
                  ) -> dict[str, np.ndarray]:
    """The outputs every float engine reports, gated by :func:`fbgforce.units.gate_outputs`;
    the raw net outputs kept as ``*_raw_*``."""
    force_N, x_mm, y_mm = gate_outputs(contact, raw["force_raw_N"], raw["x_raw_mm"], raw["y_raw_mm"])
    return {"contact": contact, "out_of_range": out_of_range, "margin": raw["margin"],
            "p_contact": raw["p_contact"], "force_N": force_N, "x_mm": x_mm, "y_mm": y_mm,
            "force_raw_N": raw["force_raw_N"], "x_raw_mm": raw["x_raw_mm"],
            "y_raw_mm": raw["y_raw_mm"]}


def numpy_nets(model: HierarchicalModel) -> Nets:
    """The model's nets in float64 numpy (:data:`Nets`)."""
    def nets(x: np.ndarray, decide: Callable[[np.ndarray], np.ndarray]) -> dict[str, np.ndarray]:
        z = x[:, :model.preprocess.n_features]
        logits = model.contact.forward(z)
        margin = logits[:, 1] - logits[:, 0]
        contact = decide(margin)
        f = model.force.forward(z)[:, 0]
        uv = model.location.forward(location_inputs(x, contact, f, model.preprocess.memory.n_loc))
        xy = model.xy_offset + model.xy_scale * uv
        return {"contact": contact, "margin": margin,
                "p_contact": 1.0 / (1.0 + np.exp(-np.clip(margin, -500.0, 500.0))),
                "force_raw_N": model.force_offset + model.force_scale * f,
                "x_raw_mm": xy[:, 0], "y_raw_mm": xy[:, 1]}
    return nets


def predict_from_features(model: HierarchicalModel, z: np.ndarray,
                          decide: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                          nets: Nets | None = None) -> dict[str, np.ndarray]:
    """Run the three nets on standardised inputs.

    ``decide(raw, margin)`` turns the contact net's own decision (``margin > 0``) and margin
    into the decision the outputs are gated on (the decision over time of
    :func:`predict`); None takes the net's own. ``nets``: who runs the nets (default
    :func:`numpy_nets`; the onnx engine passes onnxruntime's).

    Returns
    -------
    dict
        ``contact`` (bool), ``p_contact`` (softmax probability of contact), ``margin`` (the
        contact net's logit difference), ``out_of_range`` (bool), ``force_N``
        (0 where no contact), ``x_mm``/``y_mm`` (NaN where no contact), and the raw net
        outputs ``force_raw_N``, ``x_raw_mm``, ``y_raw_mm`` (before gating on contact).
    """
    x = np.asarray(z, dtype=np.float64)

    def decision(margin: np.ndarray) -> np.ndarray:
        return margin > 0.0 if decide is None else decide(margin > 0.0, margin)

    raw = (nets or numpy_nets(model))(x, decision)
    return gated_outputs(raw, raw["contact"], model.out_of_range(x))


def safe_output(out: dict[str, np.ndarray], fault: np.ndarray) -> dict[str, np.ndarray]:
    """Give the samples where ``fault`` (n,) is True the runtime's safe output with the
    ``SENSOR_FAULT`` status bit: no contact, probability 0, 0 N, no location. Adds ``status``
    (uint32, the C runtime's bits) to ``out`` (in place) and returns it."""
    fault = np.asarray(fault, dtype=bool)
    out["contact"] = np.asarray(out["contact"], dtype=bool) & ~fault
    for key, value in (("p_contact", 0.0), ("force_N", 0.0), ("x_mm", np.nan), ("y_mm", np.nan),
                       ("force_raw_N", np.nan), ("x_raw_mm", np.nan), ("y_raw_mm", np.nan)):
        if key in out:
            out[key] = np.where(fault, value, np.asarray(out[key], dtype=np.float64))
    out["status"] = np.where(fault, np.uint32(contract.STATUS_FLAG["SENSOR_FAULT"]),
                             np.uint32(0)).astype(np.uint32)
    return out


# --------------------------------------------------------------------------------------------
# Hold stage and rest tracker
# --------------------------------------------------------------------------------------------

def hold_over_time(force: np.ndarray, contact: np.ndarray, iu: InUse,
                   state: list[Any]) -> np.ndarray:
    """The settled-hold gain of ``iu`` on consecutive fault-free samples, in float.

    ``force`` and ``contact`` are the samples' outputs; ``state`` is ``[average, primed,
    hold_run]`` of the previous sample, carried and updated. Returns the force with the gain.
    The C float runtime runs this rule (``fbgf_hold_stage`` in fbgf_float.c); the fixed-point
    one its integer form (``fbg_hold_stage`` in fbg_stage_hold.c, ``fbgforce.export.intref``).
    """
    out = np.asarray(force, dtype=np.float64).copy()
    if not iu.hold_gain:
        return out
    avg, primed, run = state
    settle, ramp, alpha = iu.hold_settle, 1 << iu.hold_ramp_shift, 1.0 / (1 << iu.hold_shift)
    for i, (f, c) in enumerate(zip(out.tolist(), np.asarray(contact, dtype=bool).tolist())):
        if not c:
            primed, run = 0, 0
            continue
        if primed:
            avg += (f - avg) * alpha
        else:
            avg, primed = f, 1
        steady = abs(f - avg) <= max(iu.hold_band_N, iu.hold_band_frac * abs(f))
        run = min(run + 1, settle + ramp, 0xFFFF) if steady else 0
        w = min(max(run - settle, 0), ramp)
        out[i] = f + f * iu.hold_gain * (w / ramp)
    state[0], state[1], state[2] = avg, primed, run
    return out


def rest_run_after(run: int, rest: np.ndarray) -> int:
    """The runtimes' count of consecutive samples at rest (saturating at 0xFFFF), ``run``
    before the samples whose rest flags are ``rest`` (in order), after them."""
    rest = np.asarray(rest, dtype=bool)
    if rest.all():
        return min(0xFFFF, run + rest.size)
    return min(0xFFFF, rest.size - int(np.flatnonzero(~rest)[-1]) - 1)


# --------------------------------------------------------------------------------------------
# The whole pipeline
# --------------------------------------------------------------------------------------------

def predict(model: HierarchicalModel, wl_nm: Any, baseline_nm: Any = None, *,
            rate_hz: float | None = None) -> dict[str, np.ndarray]:
    """Full float pipeline on one continuous recording of raw wavelengths.

    With ``model.in_use`` on, the decision over time gates the outputs, the settled-hold gain
    scales a force that has stood still, and the at-rest
    baseline tracker moves the strain gratings' baseline between blocks of
    ``contract.LIMIT["TRACK_BLOCK"]`` samples, as the runtimes do (docs/runtime.md, "In
    use"); the first ``len(taps) - 1`` samples (the runtimes' warm-up) are never at rest.

    Parameters
    ----------
    model
        The float model.
    wl_nm
        (n, 5) peak wavelengths of gratings 1..4 and T in nm, real numbers; validated by
        :func:`fbgforce.samples.wavelength_array` (wrong shape, dtype or unit: InputError).
        A sample with a non-finite value or a peak outside 1000-2000 nm is a sensor fault.
    baseline_nm
        (5,) unloaded wavelengths to tare against, nm; default the model's training baseline.
    rate_hz
        The data's sample rate, if known: refused when it differs from the model's
        (:func:`fbgforce.samples.check_rate`).

    Returns
    -------
    dict
        :func:`predict_from_features`'s keys, plus ``status`` (uint32): ``SENSOR_FAULT``
        (0x08) on faulty samples, whose outputs are the safe output (:func:`safe_output`).
    """
    wl = samples.wavelength_array(wl_nm, name="wl_nm")
    if rate_hz is not None:
        samples.check_rate(model, rate_hz)
    if baseline_nm is None:
        base = model.baseline_nm
    else:
        base = samples.wavelength_array(baseline_nm, name="baseline_nm", single=True)
        if base.shape[0] != 1 or samples.sensor_fault_rows(base).any():
            raise InputError("baseline_nm must be 5 finite wavelengths within 1000-2000 nm")
        base = base[0]
    if model.runs_in_use:
        return FloatPipeline(model, base).push(wl)
    out = predict_from_features(model, features(model, wl, base))
    return safe_output(out, samples.sensor_fault_rows(wl))


class FloatPipeline:
    """The float pipeline of ONE continuous recording, fed in pieces of any length: what
    :func:`predict` computes on the whole, sample for sample (the temperature reference's
    average, the creep inverse's lags, the filter's history, the memory states, the decision
    over time, the settled-hold gain and the at-rest tracker carry over from piece to piece).
    It starts as the
    runtimes after a tare: the first good sample primes the reference's average, the creep
    inverse's lags and the memory states.
    A sensor fault (:func:`fbgforce.samples.sensor_fault_rows`) is handled as the runtimes
    handle it: the filter is fed the last good sample's filtered shifts, the reference's
    average, the creep inverse's lags, the memory states, the decision, the settled-hold gain
    and the tracker skip the sample (the tracker restarts its rest count), and the sample gets
    the safe output.

    Parameters
    ----------
    model
        The float model (a causal or unfiltered one: the centred filter needs the future).
    baseline_nm
        (5,) the tare; the tracker moves the strain gratings' entries (:attr:`baseline_nm`).
    nets
        Who runs the nets (:data:`Nets`; default numpy float64).
    """

    def __init__(self, model: HierarchicalModel, baseline_nm: np.ndarray,
                 nets: Nets | None = None) -> None:
        pre = model.preprocess
        self.model = model
        self.nets = nets
        self.baseline_nm = np.array(baseline_nm, dtype=np.float64).reshape(N_STRAIN + 1)
        self.taps = pre.runtime_taps()
        self.samples = 0
        self._history = np.zeros((self.taps.size - 1, N_STRAIN))
        self._last_comp = np.zeros(N_STRAIN)
        self._reference: list[tuple[float, int] | None] = [None]   # fresh: no good sample yet
        self._creep_lag: list[np.ndarray | None] = [None]   # the creep inverse's, likewise
        self._memory = MemoryStream(pre.memory, pre.z_rest)
        self._decision: list[Any] = [0, 0, 0.0, 0, 0]
        self._shown = np.zeros(0, dtype=bool)   # the contact the last decision showed
        self._hold: list[Any] = [0.0, 0, 0]
        self._drift = np.zeros(N_STRAIN)
        self._track_sum = np.zeros(N_STRAIN)
        self._rest_run = 0
        self._track_creep: np.ndarray | None = None   # the tracker's creep states, likewise

    def push(self, wl_nm: np.ndarray) -> dict[str, np.ndarray]:
        """Outputs of :func:`predict` for the next samples (n, 5) nm."""
        wl = np.asarray(wl_nm, dtype=np.float64).reshape(-1, N_STRAIN + 1)
        block = contract.LIMIT["TRACK_BLOCK"] if self.model.in_use.track_shift else 0
        parts, i = [], 0
        while i < wl.shape[0] or not parts:
            # Up to the tracker's next block boundary: the baseline moves only there.
            m = wl.shape[0] - i if not block else min(wl.shape[0] - i, block - self.samples % block)
            parts.append(self._run(wl[i:i + m]))
            i += m
            if m == 0:
                break
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _run(self, wl: np.ndarray) -> dict[str, np.ndarray]:
        """Outputs of the samples ``wl`` (n, 5), none of them past a tracker block's end."""
        n = wl.shape[0]
        fault = samples.sensor_fault_rows(wl) if n else np.zeros(0, dtype=bool)
        good = np.flatnonzero(~fault)
        filt = self._filter_stage(self._front_stage(wl, fault), fault)
        x = self._memory_stage(filt, good)
        # The nets' outputs are gated on where the decision holds; the contact shown is the
        # decision's other output.
        self._shown = np.zeros(0, dtype=bool)
        ran = predict_from_features(self.model, x[good], self._contact_decision, self.nets)
        held = np.zeros(n, dtype=bool)
        held[good] = ran["contact"]
        ran["force_N"] = self._hold_stage(ran["force_N"], ran["contact"])
        ran["contact"] = self._shown
        out = {key: np.zeros(n, dtype=v.dtype) for key, v in ran.items()}
        for key, v in ran.items():
            out[key][good] = v
        out = safe_output(out, fault)
        out["status"] |= np.where(held & ~out["contact"], np.uint32(RELEASING), np.uint32(0))
        track = self.model.in_use.track_shift and n
        if track:
            self._rest_track(filt, held, fault, good)
        self.samples += n
        if track and self.samples % contract.LIMIT["TRACK_BLOCK"] == 0:
            self._rest_track_block()
        return out

    def _front_stage(self, wl: np.ndarray, fault: np.ndarray) -> np.ndarray:
        """Tare, temperature compensation and the creep inverse: the strain gratings'
        elastic shifts (n, 4), pm."""
        comp = compensate(self.model, wl, self.baseline_nm, self._reference, fault)
        return creep_inverse(self.model.preprocess, comp, self._creep_lag, fault)

    def _filter_stage(self, comp: np.ndarray, fault: np.ndarray) -> np.ndarray:
        """The causal FIR through sensor faults: the filtered shifts (n, 4), pm."""
        filt, self._history, self._last_comp = filter_through_faults(
            self.taps, comp, fault, self._history, self._last_comp)
        return filt

    def _memory_stage(self, filt: np.ndarray, good: np.ndarray) -> np.ndarray:
        """Net inputs (n, F + location averages): the standardised channels, and the memory
        features on the samples ``good`` (a faulty sample's stay 0)."""
        pre = self.model.preprocess
        z = (filt - pre.input_mean) / pre.input_std
        x = np.zeros((filt.shape[0], pre.n_inputs))
        x[:, :N_STRAIN] = z
        x[good] = self._memory.push(z[good])
        return x

    def _contact_decision(self, raw: np.ndarray, margin: np.ndarray) -> np.ndarray:
        """The decision over time (:func:`fbgforce.model.decision.decide_over_time`): returns
        where it holds (what the nets' outputs are gated on), keeps the contact shown."""
        iu = self.model.in_use
        self._shown, held = decide_over_time(raw, margin, iu.contact_on_margin,
                                             iu.contact_off_margin, iu.contact_rise_samples,
                                             self._decision, iu.cusum)
        return held

    def _hold_stage(self, force: np.ndarray, contact: np.ndarray) -> np.ndarray:
        """The settled-hold gain (:func:`hold_over_time`)."""
        return hold_over_time(force, contact, self.model.in_use, self._hold)

    def _rest_track(self, filt: np.ndarray, contact: np.ndarray, fault: np.ndarray,
                    good: np.ndarray) -> None:
        """Sum the filtered shifts at rest (no contact, no fault, past the filter's warm-up:
        the runtimes' WARMUP), less the creep term, for the block's step."""
        n = filt.shape[0]
        warm = self.taps.size - 1
        rest = ~contact & ~fault & (np.arange(self.samples, self.samples + n) >= warm)
        self._track_sum += (filt - self._creep_term(filt, good))[rest].sum(axis=0)
        self._rest_run = rest_run_after(self._rest_run, rest)

    def _rest_track_block(self) -> None:
        """At a block's end, after a long enough rest, move the strain gratings' baseline: a
        first-order follower of the filtered shift at rest (time constant 2^track_shift
        samples), each step and the whole correction bounded."""
        iu = self.model.in_use
        if self._rest_run >= contract.LIMIT["TRACK_BLOCK"] + iu.track_settle:
            step = np.clip(self._track_sum / 2.0 ** iu.track_shift,
                           -iu.track_step_max_pm, iu.track_step_max_pm)
            new = np.clip(self._drift + step, -iu.track_limit_pm, iu.track_limit_pm)
            self.baseline_nm[:N_STRAIN] += (new - self._drift) / 1000.0
            self._drift = new
        self._track_sum[:] = 0.0

    def _creep_term(self, filt: np.ndarray, good: np.ndarray) -> np.ndarray | float:
        """``track_creep`` times the creep states (n, 4) of the rows ``good`` of ``filt``
        (the states follow every good sample; the other rows are 0), or 0 when the term is off."""
        iu = self.model.in_use
        if not iu.track_creep or not good.size:
            return 0.0
        if self._track_creep is None:
            self._track_creep = filt[good[0]].copy()
        states = np.zeros_like(filt)
        states[good] = _exp_average(filt[good], iu.track_creep_shift, self._track_creep)
        self._track_creep = states[good[-1]].copy()
        return iu.track_creep * states


def tracked_baselines(model: HierarchicalModel, wl_nm: np.ndarray, baseline_nm: np.ndarray
                      ) -> np.ndarray:
    """(n, 5) the baseline the float pipeline holds at each sample of one continuous
    recording tared at ``baseline_nm``: the tare, with the at-rest tracker's correction of
    the strain gratings' entries as it stands when the sample arrives (it moves only at the
    tracker's block boundaries)."""
    wl = np.asarray(wl_nm, dtype=np.float64).reshape(-1, N_STRAIN + 1)
    pipe = FloatPipeline(model, baseline_nm)
    block = contract.LIMIT["TRACK_BLOCK"]
    out = np.empty_like(wl)
    for start in range(0, wl.shape[0], block):
        out[start:start + block] = pipe.baseline_nm
        pipe.push(wl[start:start + block])
    return out
