"""The float model: the artifact the trainer writes and every later stage reads.

This module is the contract between training (``fbgforce.trainer``) and export / runtime
(``fbgforce.export``, ``fbgforce.pybind``): it defines what a model directory holds and the one
float64 implementation of the shipped pipeline, which is the reference every other engine
(onnxruntime, C float, C fixed-point) is compared against.

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
import json
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fbgforce import contract, samples
from fbgforce.units import gate_outputs
from fbgforce.jsonutil import json_default
from fbgforce.errors import InputError

FORMAT_NAME = "fbgforce-model"
FORMAT_VERSION = 2
N_STRAIN = contract.N_STRAIN
FILTER_KINDS = ("causal", "centred", "none")
NET_NAMES = contract.NET_NAMES


@dataclass
class Memory:
    """Recursive states of one load signal whose features give the nets a sense of history.

    The states follow ``u = z @ weights``, a fixed linear combination of the standardised
    channels that tracks the load (the trainer fits it to the force): a pad's hysteresis lives
    in its force path, which all four beams share, so one signal carries it, and its
    direction of motion is the load's (a single channel may go either way at a release,
    depending on where the press was).

    ``loc_shift`` (0: off) gives the location net four more inputs: exponential averages
    (factor 2^-loc_shift) of the rest-referenced channels ``r = z - z_rest``, where ``z_rest``
    is the standardised value of a zero filtered shift, so r is 0 at rest. The direction of
    the four-beam vector says where a press is; at a light touch sensor noise makes it noisy
    and the average steadies it, and because r is 0 at rest, averaging rest samples in at a
    press onset only shrinks the average, keeping its direction. Updated on every sample,
    contact or not, like the load signal's states.

    ``ema_shifts[k]``: an exponential average with factor 2^-shift (time constant about 2^shift
    samples); its feature is ``(u - average) * 2^ema_gains[k]``, the recent change. Rate
    dependent: what a viscoelastic pad's creep needs. ``play_widths[k]``: a play (backlash)
    operator of half-width w; its feature ``(u - play) * 2^play_gains[k]`` says which way the
    load last moved and how far, whatever the speed: the building block of Prandtl-Ishlinskii
    hysteresis models, what a pad's rate-independent (frictional) hysteresis needs. Constant
    work and memory per sample (docs/trainer.md, "memory").

    The tuples are the parameters of ``contract.MEMORY_KINDS``, ``<kind>_<param>s`` each
    (:func:`memory_attr`), checked against their ranges there; an optional one (the gains)
    left empty is all 0.
    """

    ema_shifts: tuple[int, ...] = ()
    ema_gains: tuple[int, ...] = ()
    play_widths: tuple[float, ...] = ()
    play_gains: tuple[int, ...] = ()
    weights: tuple[float, ...] = (0.25, 0.25, 0.25, 0.25)
    loc_shift: int = 0

    def __post_init__(self) -> None:
        self.loc_shift = int(self.loc_shift)
        for kind in contract.MEMORY_KINDS:
            n = len(getattr(self, memory_attr(kind, kind.counted_by)))
            if n > kind.limit:
                raise ValueError(f"at most {kind.limit} {kind.noun}")
            for param in kind.params:
                name = memory_attr(kind, param)
                values = tuple((float if param.standardised else int)(v) for v in getattr(self, name))
                values = values or ((0,) * n if param.optional else ())
                if len(values) != n:
                    raise ValueError(f"{name}: one per {kind.noun} ({n}), got {len(values)}")
                if param.standardised and not all(np.isfinite(v) and v >= param.lo for v in values):
                    raise ValueError(f"{name} must be finite and >= {param.lo}")
                if not param.standardised and not all(param.lo <= v <= param.hi for v in values):
                    raise ValueError(f"{name} must be {param.lo}..{param.hi}")
                setattr(self, name, values)
        self.weights = tuple(float(v) for v in self.weights)
        if len(self.weights) != N_STRAIN or not all(np.isfinite(self.weights)):
            raise ValueError(f"{N_STRAIN} finite memory weights")
        if not 0 <= self.loc_shift <= contract.MAX_EMA_SHIFT:
            raise ValueError(f"location average shift must be 0 (off)..{contract.MAX_EMA_SHIFT}")

    def count(self, kind: contract.MemoryKind) -> int:
        """States of ``kind`` in use (``n_<kind>`` of the parameter blocks)."""
        return len(getattr(self, memory_attr(kind, kind.counted_by)))

    @property
    def n_states(self) -> int:
        """Memory states of every kind (averages and play operators)."""
        return sum(self.count(kind) for kind in contract.MEMORY_KINDS)

    @property
    def n_loc(self) -> int:
        """Location averages (one per channel, or none)."""
        return contract.n_loc(self.loc_shift)

    @property
    def state_words(self) -> int:
        """int32 words of state the memory uses in ``fbg_state``: one per average, play
        operator and location average."""
        return self.n_states + self.n_loc

    def params(self, standardised: Callable[[float], Any]) -> dict[str, Any]:
        """The memory kinds' fields of a parameter block (``contract.PARAMS`` and
        ``FLOAT_PARAMS`` names): every kind's count, and its parameters padded with zeros to
        the kind's limit, a value in standardised units through ``standardised``."""
        out: dict[str, Any] = {kind.count_field: self.count(kind) for kind in contract.MEMORY_KINDS}
        for kind in contract.MEMORY_KINDS:
            for param in kind.params:
                values = getattr(self, memory_attr(kind, param))
                values = [standardised(v) for v in values] if param.standardised else list(values)
                out[kind.field(param)] = values + [0] * (kind.limit - len(values))
        return out

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for kind in contract.MEMORY_KINDS:   # the counting parameter first: model.json key order
            for param in sorted(kind.params, key=lambda p: p is not kind.counted_by):
                out[memory_attr(kind, param)] = list(getattr(self, memory_attr(kind, param)))
        return {**out, "weights": list(self.weights), "loc_shift": self.loc_shift}


def memory_attr(kind: contract.MemoryKind, param: contract.MemoryParam) -> str:
    """The :class:`Memory` tuple of a memory kind's parameter: ``<kind>_<param>s``."""
    return f"{kind.field(param)}s"


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


class MemoryStream:
    """The memory states of one continuous recording, fed in pieces: ``push(z)`` on
    consecutive pieces gives what :func:`memory_features` gives on the whole.

    ``z_rest`` (4,): the standardised channels at rest (:attr:`Preprocess.z_rest`), needed by
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
        p = np.empty_like(u)
        lo, hi = (u - width).tolist(), (u + width).tolist()
        for i in range(u.shape[0]):
            state = min(max(state, lo[i]), hi[i])
            p[i] = state
        after.append(state)
        feats.append(((u - p) * 2.0 ** gain)[:, None])
    return feats, after


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


#: The decision's rise threshold: :data:`REST_MARGIN_FACTOR` times this quantile of the contact
#: net's margin at rest in the calibration data, its synthetic long rests included
#: (docs/runtime.md, "In use").
REST_MARGIN_QUANTILE = 0.9999
#: A calibration's rests end within half a second of a release, where the margin is still
#: rising out of the release; in use rests last seconds, and 0.2-1.5 s after a release, as the
#: load signal's averages settle, it comes higher than any calibration rest shows (on the
#: hours-of-use run, docs/robustness.md: 3.8 false events per minute at the quantile itself,
#: 1.2 at 1.5 times it, 0.5 at twice it).
REST_MARGIN_FACTOR = 2.0
#: How long the rise condition must hold, s: 3 samples at 1 kHz. On fault-free logs one
#: sample past a threshold set on settled rests is nearly as quiet and 3 ms faster, but the
#: count also rides out the few samples a burst of lost peaks disturbs (docs/tradeoff.md).
RISE_S = 0.003
#: Largest magnitude of every CUSUM value of :class:`InUse` (margin units): the contract's
#: ``MAX_CUSUM_Q8`` in Q8.
CUSUM_MAX = contract.LIMIT["MAX_CUSUM_Q8"] / 256.0
#: The CUSUM rise's false events per minute at rest that :func:`cusum_parameters` aims at: an
#: average run length at rest of 10 minutes, ten times below the goal of 1 per minute, for what
#: a calibration's rests cannot show (the margin rising 0.2-1.5 s after a release in use).
CUSUM_FALSE_PER_MIN = 0.1
#: Fewest excursion peaks for the tail fit above their 90th percentile (fewer: all of them).
CUSUM_TAIL_MIN = 20
#: The exponential fit of the excursion peaks' tail reads correlated rests too light: on
#: two minutes of AR(1) rest margins (correlation 0.5 to 0.98 per sample) the rate observed
#: over 30 minutes at the fitted threshold was up to 5 times the fit. The threshold is set
#: where the fit gives the target divided by this.
CUSUM_FIT_MARGIN = 5.0
#: The at-rest tracker: time constant, the rest after a release before it learns, the
#: fastest drift it follows and its bound from the tare.
TRACK_TIME_CONSTANT_S = 1.0
TRACK_SETTLE_S = 0.2
TRACK_RATE_MAX_PM_PER_S = 4.0
TRACK_LIMIT_PM = 200.0
#: The settled-hold gain (docs/runtime.md, "In use"): a contact sample is steady when the
#: force lies within HOLD_BAND_N or HOLD_BAND_FRACTION of it (the larger) of its own average
#: over HOLD_AVERAGE_S; after HOLD_SETTLE_S of steady samples (longer than a calibration
#: press stands at its peak, 0.15 s, and than the 10-130 ms after a turn that a causal
#: estimator cannot tell from a hold) the gain ramps in over HOLD_RAMP_S. The band lets a
#: held grip's creep and the nets' noise through and stops at a press's slopes.
HOLD_SETTLE_S = 0.2
HOLD_AVERAGE_S = 0.128
HOLD_BAND_N = 0.5
HOLD_BAND_FRACTION = 0.03
HOLD_RAMP_S = 0.256
#: The largest |hold_gain| (the fixed-point stage's bound, docs/fixed-point.md).
HOLD_GAIN_MAX = contract.LIMIT["MAX_HOLD_GAIN_Q15"] / 2.0**15
#: The largest creep magnitude the tracker's creep term and the creep inverse take (the
#: term's fixed-point bound, docs/fixed-point.md): a pad that gives back half a press after
#: the release is no longer one a first-order lag describes.
CREEP_MAX = contract.LIMIT["MAX_TRACK_CREEP_Q15"] / 2.0**15


def _check_creep(magnitude_name: str, magnitude: float, shift_name: str, shift: int) -> None:
    """The one rule of a creep's parameters (the tracker's creep term, the creep inverse):
    the magnitude 0..:data:`CREEP_MAX`, 0 being off; the time constant's shift 1..15 when on
    (the rounding rule needs at least 1), 0 when off."""
    if not 0.0 <= magnitude <= CREEP_MAX:
        raise ValueError(f"{magnitude_name} must be 0 .. {CREEP_MAX:g}, not {magnitude}")
    top = contract.LIMIT["MAX_EMA_SHIFT"]
    if magnitude and not 1 <= shift <= top:
        raise ValueError(f"{shift_name} must be 1 .. {top} when {magnitude_name} is on, not {shift}")
    if not magnitude and shift:
        raise ValueError(f"{shift_name} must be 0 when {magnitude_name} is 0, not {shift}")


def creep_parameters(magnitude: float, time_constant_samples: float) -> tuple[float, int]:
    """A fitted creep (magnitude, first-order time constant in samples) as the model's
    parameters ``(m, k)`` (:attr:`Preprocess.creep` / ``creep_shift`` and
    :attr:`InUse.track_creep` / ``track_creep_shift``): the magnitude clipped to
    0..:data:`CREEP_MAX`, the time constant as the nearest power of two ``2**k``, k clipped
    to 1..15. ``(0.0, 0)`` (off) for a magnitude of 0 or a time constant below one sample."""
    if not (magnitude > 0.0 and time_constant_samples >= 1.0):
        return 0.0, 0
    return (min(float(magnitude), CREEP_MAX),
            int(np.clip(round(np.log2(time_constant_samples)), 1, contract.LIMIT["MAX_EMA_SHIFT"])))


@dataclass
class InUse:
    """What the runtimes do beyond the nets when they run for hours: the contact decision over
    time and the at-rest baseline tracker (docs/runtime.md, "In use").

    The defaults (all off) are the nets' own per-sample decision on a fixed tare; the trainer
    writes :meth:`recommended`.

    Attributes
    ----------
    contact_on_margin
        Contact rises when the contact net's margin (logit difference) is positive and at
        least this (>= 0) ...
    contact_off_margin
        ... and stays while the margin is positive or above this (<= 0): a Schmitt trigger.
    contact_rise_samples
        Consecutive samples of the rise condition before contact rises (>= 1).
    track_shift
        At-rest baseline tracker: time constant ``2**track_shift`` samples (0: off). While the
        decision says no contact (and the state is tared, without fault or warm-up), every
        ``contract.LIMIT['TRACK_BLOCK']`` samples move each strain grating's tare baseline
        towards the value that makes its filtered shift zero.
    track_settle
        Samples of rest before the tracker's blocks count (the pad relaxes after a release).
    track_step_max_pm
        Largest baseline step of one block, pm.
    track_limit_pm
        Largest total correction per grating since the tare, pm (then the status flag
        BASELINE_LIMIT asks for a new tare).
    track_creep
        The pad's creep magnitude m, 0..0.5 (0: off, what a model saved without the field
        reads). A viscoelastic pad gives a press's load back for a second or more after the
        release, and the gratings read ``m`` times a first-order lag of the load meanwhile;
        the tracker would learn that as drift. With ``m`` > 0 each grating's creep state
        ``L += (f - L) / 2**track_creep_shift`` follows its filtered shift ``f`` on every
        sample without a sensor fault (contact, rest and the filter's warm-up alike), primed
        ``L = f`` by the first one after a tare, reset or new baseline and held through a
        fault, and the tracker sums ``f - m * L`` at rest instead of ``f``.
    track_creep_shift
        The creep's time constant, ``2**track_creep_shift`` samples: 1..15 when
        ``track_creep`` > 0, 0 when it is 0.
    hold_gain
        The settled-hold gain's excess over 1, ``|hold_gain| <=`` :data:`HOLD_GAIN_MAX` (0:
        off, what a model saved without the field reads). On each contact sample the force's
        average ``a += (f - a) / 2**hold_shift`` (primed ``a = f`` by the first contact sample
        after none) gives the sample as steady when ``|f - a| <= max(hold_band_N,
        hold_band_frac * |f|)``; ``hold_run`` counts steady samples (any other sets it to 0)
        and the force becomes ``f * (1 + hold_gain * w / 2**hold_ramp_shift)``, ``w =
        clamp(hold_run - hold_settle, 0, 2**hold_ramp_shift)``. A sample without contact, a
        reset, tare or new baseline clears the stage; a sensor fault leaves it as it was.
    hold_settle
        Steady contact samples before the gain ramps in.
    hold_band_N, hold_band_frac
        The steadiness band, N and a fraction of the force (0..1).
    hold_shift
        The force average's time constant, ``2**hold_shift`` samples: 1..15 when
        ``hold_gain`` is on.
    hold_ramp_shift
        The gain ramps in over ``2**hold_ramp_shift`` samples (0..12).
    contact_cusum_h
        The decision's quickest-detection rise (0: off, the Schmitt trigger above; what a
        model saved without the field reads): a one-sided CUSUM on the margin, ``S = max(0, S
        + clip(margin, contact_cusum_lo, contact_cusum_hi) - contact_cusum_k)`` out of
        contact, contact rising when ``S >= contact_cusum_h`` (margin x samples) and ``S``
        restarting at 0; contact stays as above (margin positive or above
        ``contact_off_margin``). On, it replaces the Schmitt trigger's rise:
        ``contact_on_margin`` 0 and ``contact_rise_samples`` 1. :meth:`recommended` with
        ``decision="cusum"`` sets it from the calibration's rests (:func:`cusum_parameters`).
    contact_cusum_k
        The CUSUM's drift: a sample adds its margin's excess over ``k`` (0 when off).
    contact_cusum_lo, contact_cusum_hi
        The CUSUM's clip of the margin, ``lo <= hi`` (0 when off): ``hi`` bounds what one
        sample adds, so no single spike raises contact; ``lo`` what one sample takes away.
        Every CUSUM value within ``+-MAX_CUSUM_Q8 / 256`` (:data:`CUSUM_MAX`).
    """

    contact_on_margin: float = 0.0
    contact_off_margin: float = 0.0
    contact_rise_samples: int = 1
    track_shift: int = 0
    track_settle: int = 0
    track_step_max_pm: float = 0.0
    track_limit_pm: float = 0.0
    track_creep: float = 0.0
    track_creep_shift: int = 0
    hold_gain: float = 0.0
    hold_settle: int = 0
    hold_band_N: float = 0.0
    hold_band_frac: float = 0.0
    hold_shift: int = 0
    hold_ramp_shift: int = 0
    contact_cusum_h: float = 0.0
    contact_cusum_k: float = 0.0
    contact_cusum_lo: float = 0.0
    contact_cusum_hi: float = 0.0

    def __post_init__(self) -> None:
        self.contact_on_margin = float(self.contact_on_margin)
        self.contact_off_margin = float(self.contact_off_margin)
        self.contact_rise_samples = int(self.contact_rise_samples)
        self.track_shift = int(self.track_shift)
        self.track_settle = int(self.track_settle)
        self.track_step_max_pm = float(self.track_step_max_pm)
        self.track_limit_pm = float(self.track_limit_pm)
        self.track_creep = float(self.track_creep)
        self.track_creep_shift = int(self.track_creep_shift)
        if self.contact_on_margin < 0 or self.contact_off_margin > 0:
            raise ValueError("contact_on_margin must be >= 0 and contact_off_margin <= 0")
        if not 1 <= self.contact_rise_samples <= 255:
            raise ValueError("contact_rise_samples must be in [1, 255]")
        if not 0 <= self.track_shift <= 20:
            raise ValueError("track_shift must be in [0, 20]")
        if not 0 <= self.track_settle <= 0xFFFF:
            raise ValueError("track_settle must be in [0, 65535]")
        limit_pm = contract.LIMIT["TRACK_LIMIT_MAX_FM"] / 1000.0
        if self.track_step_max_pm < 0 or not 0 <= self.track_limit_pm <= limit_pm:
            raise ValueError(f"track_step_max_pm must be >= 0 and track_limit_pm in [0, {limit_pm}]")
        _check_creep("track_creep", self.track_creep, "track_creep_shift", self.track_creep_shift)
        self.hold_gain = float(self.hold_gain)
        self.hold_settle = int(self.hold_settle)
        self.hold_band_N = float(self.hold_band_N)
        self.hold_band_frac = float(self.hold_band_frac)
        self.hold_shift = int(self.hold_shift)
        self.hold_ramp_shift = int(self.hold_ramp_shift)
        if not abs(self.hold_gain) <= HOLD_GAIN_MAX:
            raise ValueError(f"hold_gain must be within +-{HOLD_GAIN_MAX:g}, not {self.hold_gain}")
        if not 0 <= self.hold_settle <= 0xFFFF:
            raise ValueError("hold_settle must be in [0, 65535]")
        if not (np.isfinite(self.hold_band_N) and self.hold_band_N >= 0
                and 0 <= self.hold_band_frac <= 1):
            raise ValueError("hold_band_N must be >= 0 and hold_band_frac in [0, 1]")
        top = contract.LIMIT["MAX_EMA_SHIFT"]
        if not 0 <= self.hold_shift <= top or (self.hold_gain and not self.hold_shift):
            raise ValueError(f"hold_shift must be 1 .. {top} when hold_gain is on, not "
                             f"{self.hold_shift}")
        if not 0 <= self.hold_ramp_shift <= contract.LIMIT["MAX_HOLD_RAMP_SHIFT"]:
            raise ValueError(f"hold_ramp_shift must be in [0, {contract.LIMIT['MAX_HOLD_RAMP_SHIFT']}]")
        self._check_cusum()

    def _check_cusum(self) -> None:
        names = ("contact_cusum_h", "contact_cusum_k", "contact_cusum_lo", "contact_cusum_hi")
        for name in names:
            setattr(self, name, float(getattr(self, name)))
            if not abs(getattr(self, name)) <= CUSUM_MAX:
                raise ValueError(f"{name} must be within +-{CUSUM_MAX:g}, not {getattr(self, name)}")
        h, k, lo, hi = self.cusum
        if h < 0:
            raise ValueError(f"contact_cusum_h must be >= 0 (0: off), not {h}")
        if not h and (k or lo or hi):
            raise ValueError("contact_cusum_k, _lo and _hi must be 0 while contact_cusum_h is 0 (off)")
        if h and not lo <= hi:
            raise ValueError(f"contact_cusum_lo ({lo}) must be <= contact_cusum_hi ({hi})")
        if h and (self.contact_on_margin or self.contact_rise_samples != 1):
            raise ValueError("with contact_cusum_h on, contact_on_margin must be 0 and "
                             "contact_rise_samples 1 (the CUSUM is the rise rule)")

    @property
    def cusum(self) -> tuple[float, float, float, float]:
        """``(h, k, lo, hi)`` of the CUSUM rise (h 0: off), as :func:`decide_over_time` takes
        them."""
        return (self.contact_cusum_h, self.contact_cusum_k, self.contact_cusum_lo,
                self.contact_cusum_hi)

    @classmethod
    def recommended(cls, sample_rate_hz: float = 1000.0,
                    rest_margins: np.ndarray | None = None, *, creep_magnitude: float = 0.0,
                    creep_time_constant_samples: float = 0.0, hold_gain: float = 0.0,
                    decision: str = "schmitt", contact_margins: np.ndarray | None = None
                    ) -> "InUse":
        """The trainer's default (docs/runtime.md, "In use", says how each value was chosen).

        ``rest_margins``: the contact net's margins on calibration samples at rest, in the
        order of the recording; contact
        rises only past :data:`REST_MARGIN_FACTOR` times their :data:`REST_MARGIN_QUANTILE`
        quantile, held for :data:`RISE_S`, and falls below minus half of it. None: the
        per-sample decision.

        ``decision``: ``"schmitt"`` for that rule, ``"cusum"`` for the CUSUM rise of
        :func:`cusum_parameters` on ``rest_margins`` (and ``contact_margins``, the margins on
        labelled contact samples, for its drift), falling below minus its drift.

        ``creep_magnitude`` and ``creep_time_constant_samples``: the pad's creep as fitted,
        for the tracker's creep term (:func:`creep_parameters`); 0 leaves it off (as for a
        model that takes the creep out before the filter, :func:`creep_inverse`, where the
        tracker never sees it).

        ``hold_gain``: the settled-hold gain's excess over 1 as the trainer measured it on its
        synthetic holds, clipped to :data:`HOLD_GAIN_MAX`; 0 leaves the stage off.
        """
        creep, creep_shift = creep_parameters(creep_magnitude, creep_time_constant_samples)
        hold_gain = float(np.clip(hold_gain, -HOLD_GAIN_MAX, HOLD_GAIN_MAX))
        hold = {} if not hold_gain else {
            "hold_gain": hold_gain,
            "hold_settle": min(0xFFFF, int(round(HOLD_SETTLE_S * sample_rate_hz))),
            "hold_band_N": HOLD_BAND_N, "hold_band_frac": HOLD_BAND_FRACTION,
            "hold_shift": min(contract.LIMIT["MAX_EMA_SHIFT"],
                              max(1, int(round(np.log2(HOLD_AVERAGE_S * sample_rate_hz))))),
            "hold_ramp_shift": min(contract.LIMIT["MAX_HOLD_RAMP_SHIFT"],
                                   max(0, int(round(np.log2(HOLD_RAMP_S * sample_rate_hz)))))}
        if decision not in ("schmitt", "cusum"):
            raise ValueError(f"decision must be 'schmitt' or 'cusum', not {decision!r}")
        on = 0.0
        rise: dict[str, float | int] = {}
        if decision == "cusum" and rest_margins is not None and np.size(rest_margins):
            cs = cusum_parameters(rest_margins, sample_rate_hz, contact_margins)
            rise = {"contact_off_margin": -cs["k"], "contact_cusum_h": cs["h"],
                    "contact_cusum_k": cs["k"], "contact_cusum_lo": cs["lo"],
                    "contact_cusum_hi": cs["hi"]}
        elif rest_margins is not None and np.size(rest_margins):
            on = REST_MARGIN_FACTOR * max(0.0, float(np.quantile(rest_margins,
                                                                 REST_MARGIN_QUANTILE)))
        return cls(contact_on_margin=on, **{"contact_off_margin": -0.5 * on, **rise},
                   contact_rise_samples=max(1, min(255, int(round(RISE_S * sample_rate_hz))))
                   if on > 0 else 1,
                   track_shift=max(1, int(round(np.log2(TRACK_TIME_CONSTANT_S * sample_rate_hz)))),
                   track_settle=min(0xFFFF, int(round(TRACK_SETTLE_S * sample_rate_hz))),
                   track_step_max_pm=TRACK_RATE_MAX_PM_PER_S * contract.LIMIT["TRACK_BLOCK"]
                   / sample_rate_hz,
                   track_limit_pm=TRACK_LIMIT_PM, track_creep=creep,
                   track_creep_shift=creep_shift, **hold)

    def to_json(self) -> dict[str, float | int]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    def float_params(self) -> dict[str, float | int]:
        """The ``fbgf_model`` fields (:data:`fbgforce.contract.FLOAT_PARAMS`) of these values."""
        return {"contact_on": self.contact_on_margin, "contact_off": self.contact_off_margin,
                "contact_rise_n": self.contact_rise_samples, "track_shift": self.track_shift,
                "track_settle": self.track_settle, "track_step_max_pm": self.track_step_max_pm,
                "track_limit_pm": self.track_limit_pm, "track_creep": self.track_creep,
                "track_creep_shift": self.track_creep_shift, "hold_gain": self.hold_gain,
                "hold_settle": self.hold_settle, "hold_band_N": self.hold_band_N,
                "hold_band_frac": self.hold_band_frac, "hold_shift": self.hold_shift,
                "hold_ramp_shift": self.hold_ramp_shift, "contact_cusum_h": self.contact_cusum_h,
                "contact_cusum_k": self.contact_cusum_k, "contact_cusum_lo": self.contact_cusum_lo,
                "contact_cusum_hi": self.contact_cusum_hi}

    @property
    def per_sample(self) -> bool:
        """True when the decision is the contact net's own, sample by sample."""
        return (self.contact_on_margin == 0.0 and self.contact_off_margin == 0.0
                and self.contact_rise_samples == 1 and self.contact_cusum_h == 0.0)


#: Beyond each input's calibrated range, the share of that range still accepted without
#: OUT_OF_RANGE: a press a little beyond the strongest calibration press, a little more
#: temperature drift than the log had, is not yet an extrapolation worth flagging.
INPUT_RANGE_MARGIN = 0.1
#: A float bound no input reaches (the float runtime's "never out of range").
FLOAT_NEVER = 1e30


def input_range_of(x: np.ndarray, margin: float = INPUT_RANGE_MARGIN) -> np.ndarray:
    """(2, F) the accepted range of each column of the calibration inputs ``x`` (n, F): its
    smallest and largest value, widened by ``margin`` times its span on either side."""
    x = np.asarray(x, dtype=np.float64)
    lo, hi = np.nanmin(x, axis=0), np.nanmax(x, axis=0)
    span = hi - lo
    return np.vstack([lo - margin * span, hi + margin * span])


def rest_run_after(run: int, rest: np.ndarray) -> int:
    """The runtimes' count of consecutive samples at rest (saturating at 0xFFFF), ``run``
    before the samples whose rest flags are ``rest`` (in order), after them."""
    rest = np.asarray(rest, dtype=bool)
    if rest.all():
        return min(0xFFFF, run + rest.size)
    return min(0xFFFF, rest.size - int(np.flatnonzero(~rest)[-1]) - 1)


def decide_over_time(raw: np.ndarray, margin: np.ndarray, on: float, off: float, rise_n: int,
                     state: list[Any], cusum: tuple[float, float, float, float] | None = None
                     ) -> np.ndarray:
    """The contact decision over time on consecutive samples, in any units of the margin.

    Contact stays while ``raw`` (the net's own decision) or ``margin > off``. It rises by one
    of two rules. With ``cusum`` None or its threshold ``h`` 0: after ``rise_n`` consecutive
    samples with ``raw`` and ``margin >= on`` (a Schmitt trigger with a count). Else
    ``cusum = (h, k, lo, hi)``, a one-sided CUSUM: out of contact ``S = max(0, S +
    clip(margin, lo, hi) - k)``, contact rises when ``S >= h`` and ``S`` restarts at 0 (it
    stays 0 in contact). ``state`` is ``[decision, rise_run, S]`` of the previous sample,
    carried and updated. Integer arguments give the integer rule exactly (Python integers);
    the C runtimes run this rule (``contact_decision`` in fbg_fixed.c, ``fcontact_decision``
    in fbgf_float.c).
    """
    raw = np.asarray(raw, dtype=bool)
    out = np.zeros(raw.size, dtype=bool)
    decision, rise, s = state
    h, k, lo, hi = cusum if cusum is not None else (0, 0, 0, 0)
    for i, (r, mg) in enumerate(zip(raw.tolist(), np.asarray(margin).tolist())):
        if decision:
            decision = int(r or mg > off)
        elif h:
            s = max(s + (min(max(mg, lo), hi) - k), 0)
            if s >= h:
                decision, s = 1, 0
        else:
            rise = min(rise + 1, 255) if (r and mg >= on) else 0
            if rise >= rise_n:
                decision, rise = 1, 0
        out[i] = decision
    state[0], state[1], state[2] = decision, rise, s
    return out


def cusum_path(margins: np.ndarray, k: float, lo: float = -CUSUM_MAX, hi: float = CUSUM_MAX
               ) -> np.ndarray:
    """S of the CUSUM rise over consecutive margins, never rising (no threshold): ``S_t =
    max(0, S_{t-1} + clip(m_t, lo, hi) - k)``, from ``S = 0``, in closed form (Lindley: the
    walk of the increments less its running minimum, 0 included)."""
    d = np.clip(np.asarray(margins, dtype=np.float64).ravel(), lo, hi) - k
    walk = np.cumsum(d)
    return walk - np.minimum(np.minimum.accumulate(walk), 0.0) if walk.size else walk


def cusum_peaks(margins: np.ndarray, k: float, lo: float = -CUSUM_MAX, hi: float = CUSUM_MAX
                ) -> np.ndarray:
    """The highest S of each excursion of :func:`cusum_path` above 0: a CUSUM with threshold
    ``h`` raises one false event per excursion whose peak reaches ``h``."""
    s = cusum_path(margins, k, lo, hi)
    up = s > 0
    if not up.any():
        return np.empty(0)
    starts = np.flatnonzero(up & ~np.concatenate([[False], up[:-1]]))
    return np.maximum.reduceat(np.where(up, s, 0.0), starts)


def cusum_false_rate(peaks: np.ndarray, minutes: float, h: float) -> float:
    """False events per minute at rest of a CUSUM with threshold ``h``, estimated from the
    excursion peaks (:func:`cusum_peaks`) of ``minutes`` of rest: the peaks' upper tail as an
    exponential, ``rate(h) = r_u exp(-(h - u) / beta)`` (a random walk with a negative drift
    has excursion maxima with such a tail), ``u`` the peaks' 90th percentile (0 with fewer than
    :data:`CUSUM_TAIL_MIN` peaks), ``r_u`` the rate of the peaks above it, ``beta`` their mean
    excess. Past the highest observed peak only the fit counts; below it, the larger of the
    fit and the observed rate."""
    p = np.asarray(peaks, dtype=np.float64)
    if not p.size or minutes <= 0:
        return 0.0
    u = float(np.quantile(p, 0.9)) if p.size >= CUSUM_TAIL_MIN else 0.0
    tail = p[p > u]
    if not tail.size:
        return 0.0
    rate_u, beta = tail.size / minutes, max(float(np.mean(tail - u)), 1e-12)
    fit = rate_u * float(np.exp(-(h - u) / beta)) if h > u else rate_u
    return max(fit, float(np.sum(p >= h)) / minutes)


def cusum_parameters(rest_margins: np.ndarray, sample_rate_hz: float = 1000.0,
                     contact_margins: np.ndarray | None = None,
                     false_per_min: float | None = None, k: float | None = None
                     ) -> dict[str, float]:
    """The CUSUM rise the trainer sets from the calibration's rests (docs/runtime.md, "In
    use").

    ``k``, the drift, unless given: the rests' :data:`REST_MARGIN_QUANTILE` quantile (the level
    rest noise almost never passes; at least 0), or, given ``contact_margins`` whose 10th
    percentile lies above it, the midpoint of the two. ``h``: the smallest threshold at which the false events
    at rest estimated from the rests' excursion peaks (:func:`cusum_false_rate`, ``rest_margins``
    in recording order) stay at ``false_per_min`` (:data:`CUSUM_FALSE_PER_MIN`, an average run
    length at rest of 10 minutes) divided by :data:`CUSUM_FIT_MARGIN`, above every observed peak (no false event on the calibration
    itself), and at least what today's rule asks of a rise (:data:`RISE_S` of samples at
    ``max(k, 0.5)`` above ``k``). ``hi = k + h / 2``: no single sample raises contact, and the
    clip only lowers the peaks the estimate counted; ``lo`` the contract's lowest (no clip).

    Returns ``h``, ``k``, ``lo``, ``hi`` (margin units), the fitted ``false_per_min`` at ``h``
    and the ``rest_minutes`` it rests on.
    """
    rest = np.asarray(rest_margins, dtype=np.float64).ravel()
    rest = rest[np.isfinite(rest)]
    target = (CUSUM_FALSE_PER_MIN if false_per_min is None else float(false_per_min)) \
        / CUSUM_FIT_MARGIN
    q = max(0.0, float(np.quantile(rest, REST_MARGIN_QUANTILE))) if rest.size else 0.0
    given = k is not None
    k = float(k) if k is not None else q
    if not given and contact_margins is not None and np.size(contact_margins):
        c10 = float(np.quantile(np.asarray(contact_margins, dtype=np.float64), 0.1))
        if c10 > q:
            k = 0.5 * (q + c10)
    minutes = rest.size / sample_rate_hz / 60.0
    peaks = cusum_peaks(rest, k)
    h = max(1.0, RISE_S * sample_rate_hz) * max(k, 0.5)
    if peaks.size:
        h = max(h, float(np.nextafter(peaks.max(), np.inf)))
        u = float(np.quantile(peaks, 0.9)) if peaks.size >= CUSUM_TAIL_MIN else 0.0
        tail = peaks[peaks > u]
        if tail.size and tail.size / minutes > target:
            beta = max(float(np.mean(tail - u)), 1e-12)
            h = max(h, u + beta * float(np.log(tail.size / minutes / target)))
    h = min(h, CUSUM_MAX)
    k = float(np.clip(k, -CUSUM_MAX, CUSUM_MAX))
    return {"h": h, "k": k, "lo": -CUSUM_MAX, "hi": min(k + 0.5 * h, CUSUM_MAX),
            "false_per_min": cusum_false_rate(peaks, minutes, h), "rest_minutes": minutes}


def hold_over_time(force: np.ndarray, contact: np.ndarray, iu: InUse,
                   state: list[Any]) -> np.ndarray:
    """The settled-hold gain of ``iu`` on consecutive fault-free samples, in float.

    ``force`` and ``contact`` are the samples' outputs; ``state`` is ``[average, primed,
    hold_run]`` of the previous sample, carried and updated. Returns the force with the gain.
    The C float runtime runs this rule (``fhold_stage`` in fbgf_float.c); the fixed-point
    one its integer form (``hold_stage`` in fbg_fixed.c, ``fbgforce.export.intref``).
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


@dataclass
class Preprocess:
    """Temperature compensation, causal smoothing and input standardisation.

    Attributes
    ----------
    temp_coeff
        (4,) factor applied to the reference grating's shift before it is subtracted from each
        strain grating's shift (fitted per channel; 1.0 would mean identical thermal response).
    filter_kind
        ``"causal"`` (shipped), ``"centred"`` (offline, the paper's) or ``"none"``.
    filter_sigma
        Gaussian sigma in samples (informative; ``taps`` is what is applied).
    taps
        FIR taps, summing to 1. Causal: ``taps[k]`` weights sample ``n - k``. Centred: odd
        length, ``taps[k]`` weights sample ``n + k - len(taps)//2``.
    input_mean, input_std
        (4,) standardisation of the filtered compensated shifts (pm).
    memory
        The memory states after standardisation (:class:`Memory`; none by default).
    ref_shift
        The temperature reference's average (0: off, the raw reference): time constant
        about 2^ref_shift samples, 0 .. ``contract.LIMIT["MAX_REF_SHIFT"]``
        (:func:`reference_average`).
    creep
        The pad's creep magnitude ``m`` the creep inverse undoes (:func:`creep_inverse`):
        0 .. 0.5, 0 is off (what a model saved before the field reads).
    creep_shift
        The pad's creep time constant as ``2^creep_shift`` samples: 1 .. 15 when ``creep`` is
        on, 0 when it is off.
    """

    temp_coeff: np.ndarray
    filter_kind: str
    filter_sigma: float
    taps: np.ndarray
    input_mean: np.ndarray
    input_std: np.ndarray
    memory: Memory = field(default_factory=Memory)
    ref_shift: int = 0
    creep: float = 0.0
    creep_shift: int = 0

    def __post_init__(self) -> None:
        self.temp_coeff = np.asarray(self.temp_coeff, dtype=np.float64).reshape(N_STRAIN)
        if not 0 <= int(self.ref_shift) <= contract.LIMIT["MAX_REF_SHIFT"]:
            raise ValueError(f"ref_shift must be 0 .. {contract.LIMIT['MAX_REF_SHIFT']}, "
                             f"not {self.ref_shift}")
        self.ref_shift = int(self.ref_shift)
        self.creep, self.creep_shift = float(self.creep), int(self.creep_shift)
        _check_creep("creep", self.creep, "creep_shift", self.creep_shift)
        self.taps = np.asarray(self.taps, dtype=np.float64).reshape(-1)
        self.input_mean = np.asarray(self.input_mean, dtype=np.float64).reshape(N_STRAIN)
        self.input_std = np.asarray(self.input_std, dtype=np.float64).reshape(N_STRAIN)
        if self.filter_kind not in FILTER_KINDS:
            raise ValueError(f"filter_kind must be one of {FILTER_KINDS}, not {self.filter_kind!r}")
        if self.taps.size == 0:
            raise ValueError("taps must not be empty (use [1.0] for no filter)")
        if self.filter_kind == "centred" and self.taps.size % 2 == 0:
            raise ValueError("a centred filter needs an odd number of taps")
        if np.any(self.input_std <= 0):
            raise ValueError("input_std must be positive")

    @property
    def n_features(self) -> int:
        """Width of the feature vector the contact and force nets read (its first columns)."""
        return contract.n_features(self.memory.n_states)

    @property
    def n_inputs(self) -> int:
        """Width of the whole feature vector: the contact and force nets' inputs, then the
        location averages."""
        return self.n_features + self.memory.n_loc

    @property
    def creep_gain(self) -> float:
        """The creep inverse's gain ``q = kappa / (1 - kappa)``, ``kappa = creep * (1 -
        2^-creep_shift)`` (0 when off; below 1 for ``creep`` up to 0.5)."""
        if not self.creep:
            return 0.0
        kappa = self.creep * (1.0 - 2.0 ** -self.creep_shift)
        return kappa / (1.0 - kappa)

    @property
    def z_rest(self) -> np.ndarray:
        """(4,) the standardised value of a zero filtered shift: the channels at rest."""
        return -self.input_mean / self.input_std

    def runtime_taps(self) -> np.ndarray:
        """The causal FIR the runtimes run (``[1]`` for no filter).

        Raises
        ------
        InputError
            For the centred (offline) filter, or more taps than the runtime holds.
        """
        if self.filter_kind == "centred":
            raise InputError("the model uses the centred (offline) filter, which needs future "
                             "samples; retrain with the causal filter to export", column="filter_kind")
        taps = np.array([1.0]) if self.filter_kind == "none" else self.taps.copy()
        if taps.size > contract.LIMIT["MAX_TAPS"]:
            raise InputError(f"{taps.size} filter taps; the runtime holds at most "
                             f"{contract.LIMIT['MAX_TAPS']} (use a smaller sigma)", column="taps")
        return taps

    @property
    def group_delay_samples(self) -> float:
        """Delay the filter adds to a slowly varying signal, in samples (0 for centred)."""
        if self.filter_kind == "centred":
            return 0.0
        return float(np.dot(np.arange(self.taps.size), self.taps) / self.taps.sum())


@dataclass
class MLP:
    """A ReLU multilayer perceptron with a linear output layer.

    ``weights[l]`` has shape ``(n_out, n_in)`` (ONNX Gemm with ``transB=1`` and the C runtime
    use the same row-major layout), ``biases[l]`` shape ``(n_out,)``.
    """

    weights: list[np.ndarray]
    biases: list[np.ndarray]

    def __post_init__(self) -> None:
        self.weights = [np.asarray(w, dtype=np.float64) for w in self.weights]
        self.biases = [np.asarray(b, dtype=np.float64).reshape(-1) for b in self.biases]
        if len(self.weights) != len(self.biases) or not self.weights:
            raise ValueError("an MLP needs as many bias vectors as weight matrices, at least one")
        for layer, (w, b) in enumerate(zip(self.weights, self.biases)):
            if w.ndim != 2 or w.shape[0] != b.size:
                raise ValueError(f"layer {layer}: weight {w.shape} does not match bias {b.shape}")
            if layer and w.shape[1] != self.weights[layer - 1].shape[0]:
                raise ValueError(f"layer {layer}: expects {w.shape[1]} inputs, previous layer gives "
                                 f"{self.weights[layer - 1].shape[0]}")

    @property
    def sizes(self) -> list[int]:
        """Layer widths from input to output, e.g. ``[4, 70, 50, 20, 2]``."""
        return [self.weights[0].shape[1]] + [w.shape[0] for w in self.weights]

    @property
    def macs(self) -> int:
        """Multiply-accumulates per sample."""
        return int(sum(w.size for w in self.weights))

    def forward(self, x: np.ndarray) -> np.ndarray:
        """Evaluate on a batch ``x`` of shape ``(n, n_in)``; returns ``(n, n_out)``."""
        a = np.asarray(x, dtype=np.float64)
        last = len(self.weights) - 1
        for layer, (w, b) in enumerate(zip(self.weights, self.biases)):
            a = a @ w.T + b
            if layer != last:
                a = np.maximum(a, 0.0)
        return a


@dataclass
class HierarchicalModel:
    """Preprocessing plus the three nets of the paper's Fig. 4, with output scaling.

    Attributes
    ----------
    preprocess
        See :class:`Preprocess`.
    contact, force, location
        The nets. Contact: F -> ... -> 2 logits (index 1 is "contact"). Force: F -> ... -> 1.
        Location: 6 (10 with location averages) -> ... -> 2 (the four standardised channels,
        the contact flag, the force net's output, the location averages);
        F = ``preprocess.n_features`` (4 + memory states).
    force_offset, force_scale
        ``force_N = force_offset + force_scale * force_net_output``.
    xy_offset, xy_scale
        (2,) the same for x and y in millimetres.
    baseline_nm
        (5,) nominal unloaded wavelengths of gratings 1..4 and T seen in training; the runtime
        tares on live data, this is the fallback before a tare and the reference for fault checks.
    metadata
        JSON-serialisable facts: data files, seed, metrics, training time, versions.
    """

    preprocess: Preprocess
    contact: MLP
    force: MLP
    location: MLP
    force_offset: float
    force_scale: float
    xy_offset: np.ndarray
    xy_scale: np.ndarray
    baseline_nm: np.ndarray
    metadata: dict[str, Any] = field(default_factory=dict)
    in_use: InUse = field(default_factory=InUse)
    #: (2, F) lowest and highest value of each input of the contact and force nets that the
    #: runtimes accept without the status flag OUT_OF_RANGE (:func:`input_range_of`); None:
    #: no such flag.
    input_range: np.ndarray | None = None
    #: The recordings the model was trained on, as export quantises and checks against them
    #: (:class:`CalibrationRecordings`); written beside the weights by :func:`save`, read back
    #: by :func:`load_calibration` (not by :func:`load`: only export needs them).
    calibration: "CalibrationRecordings | None" = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.xy_offset = np.asarray(self.xy_offset, dtype=np.float64).reshape(2)
        self.xy_scale = np.asarray(self.xy_scale, dtype=np.float64).reshape(2)
        self.baseline_nm = np.asarray(self.baseline_nm, dtype=np.float64).reshape(N_STRAIN + 1)
        self.force_offset = float(self.force_offset)
        self.force_scale = float(self.force_scale)
        if self.input_range is not None:
            self.input_range = np.asarray(self.input_range, dtype=np.float64)
            if self.input_range.shape != (2, self.preprocess.n_features):
                raise ValueError(f"input_range must have shape (2, {self.preprocess.n_features})")
        mem = self.preprocess.memory
        for net in contract.NETS:
            name, n_out = net.name, net.float_outputs
            n_in = contract.net_inputs(name, mem.n_states, mem.n_loc)
            sizes = getattr(self, name).sizes
            if sizes[0] != n_in or sizes[-1] != n_out:
                raise ValueError(f"{name} net must map {n_in} inputs to {n_out} outputs, has {sizes}")

    @property
    def runs_in_use(self) -> bool:
        """Whether :func:`predict` runs the decision over time, the tracker or the settled-hold
        gain, which carry state along a recording (a centred filter's offline model never
        does)."""
        iu = self.in_use
        return (not (iu.per_sample and not iu.track_shift and not iu.hold_gain)
                and self.preprocess.filter_kind != "centred")

    def out_of_range(self, x: np.ndarray) -> np.ndarray:
        """(n,) True where a contact/force net input of ``x`` (n, >= F) lies outside
        :attr:`input_range`."""
        x = np.asarray(x)
        if self.input_range is None:
            return np.zeros(x.shape[0], dtype=bool)
        z = x[:, :self.preprocess.n_features]
        return np.any((z < self.input_range[0]) | (z > self.input_range[1]), axis=1)

    def float_params(self, jump_max_fm: int, overload_N: float, stuck_max: int = 0
                     ) -> dict[str, Any]:
        """Every parameter field of the float runtime's model (``fbgf_model``,
        :data:`fbgforce.contract.FLOAT_PARAMS`) by name, as Python numbers and lists (array
        fields padded with zeros to their length): what the generated float C
        (:mod:`fbgforce.export.codegen`) and the Python binding (:class:`fbgforce.pybind.FloatRuntime`)
        both fill it with. The taps and the nets are the struct's arrays, not parameters.

        Parameters
        ----------
        jump_max_fm
            Sensor-fault jump threshold, fm per sample.
        overload_N
            OVERLOAD above this force (``inf``: never).
        stuck_max
            Sensor fault after this many identical samples on a channel (0: off).
        """
        pre, mem = self.preprocess, self.preprocess.memory
        n, nf = contract.LIMIT["MAX_INPUTS"], pre.n_features
        lo, hi = np.full(n, -FLOAT_NEVER), np.full(n, FLOAT_NEVER)
        if self.input_range is not None:
            lo[:nf], hi[:nf] = self.input_range

        def floats(values: Any) -> list[float]:
            return [float(v) for v in np.asarray(values, dtype=np.float64).ravel()]

        return {
            "baseline_fm": [int(v) for v in np.rint(self.baseline_nm * 1e6)],
            "jump_max_fm": int(jump_max_fm), "stuck_max": int(stuck_max),
            "n_taps": int(pre.runtime_taps().size), "temp_coeff": floats(pre.temp_coeff),
            "input_mean_pm": floats(pre.input_mean), "input_std_pm": floats(pre.input_std),
            "force_offset_N": float(self.force_offset), "force_scale": float(self.force_scale),
            "xy_offset_mm": floats(self.xy_offset), "xy_scale": floats(self.xy_scale),
            "overload_N": float(overload_N), "mem_weight": floats(mem.weights),
            **mem.params(float), "loc_shift": int(mem.loc_shift),
            **self.in_use.float_params(), "in_lo": lo.tolist(), "in_hi": hi.tolist(),
            "ref_shift": pre.ref_shift, "creep_q": pre.creep_gain, "creep_shift": pre.creep_shift}

    @property
    def nets(self) -> dict[str, MLP]:
        """The three nets by name, in evaluation order."""
        return {"contact": self.contact, "force": self.force, "location": self.location}

    @property
    def macs(self) -> int:
        """Multiply-accumulates per sample in the three nets (the filter adds 4 * len(taps))."""
        return sum(net.macs for net in self.nets.values())


# --------------------------------------------------------------------------------------------
# The float64 reference pipeline
# --------------------------------------------------------------------------------------------

def reference_average(shift_t: np.ndarray, ref_shift: int, fault: np.ndarray,
                      prev: float | None = None) -> tuple[np.ndarray, float | None]:
    """The temperature reference the compensation subtracts: ``r[n] = r[n-1] + (shift_T[n] -
    r[n-1]) / 2^ref_shift`` over the samples without a fault, in order.

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
        The average before the first sample; None primes it with the first good sample.

    Returns
    -------
    tuple
        ``r`` (n,) and the average after the samples (``prev`` when none was good), to carry
        into the next call.
    """
    shift_t = np.asarray(shift_t, dtype=np.float64)
    good = np.flatnonzero(~np.asarray(fault, dtype=bool))
    if not ref_shift or good.size == 0:
        return shift_t, prev
    x = shift_t[good]
    start = np.array([x[0] if prev is None else prev])
    r = shift_t.copy()
    r[good] = _exp_average(x[:, None], ref_shift, start)[:, 0]
    return r, float(r[good[-1]])


def compensate(model: HierarchicalModel, wl_nm: np.ndarray, baseline_nm: np.ndarray,
               reference: list[float | None] | None = None,
               fault: np.ndarray | None = None) -> np.ndarray:
    """Tare and temperature-compensate raw wavelengths.

    Parameters
    ----------
    wl_nm
        (n, 5) peak wavelengths of gratings 1..4 and T, nm.
    baseline_nm
        (5,) unloaded wavelengths to tare against, nm.
    reference
        ``[r]``: the temperature reference's average before the samples (None: the first good
        sample primes it), updated in place; None: a recording of its own. Read only when
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


def creep_inverse(pre: Preprocess, comp: np.ndarray, lag: list[np.ndarray | None] | None = None,
                  fault: np.ndarray | None = None) -> np.ndarray:
    """The pad's creep taken out of the compensated shifts of one continuous recording, per
    strain grating: ``e = c + q (c - L)``, then ``L += (e - L) / 2^creep_shift``
    (``q`` :attr:`Preprocess.creep_gain`; the module's docstring derives it), i.e. ``L``
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
    lags = _first_order(c, (1.0 + q) * 2.0 ** -pre.creep_shift, prev)   # L after each sample
    before = np.vstack([prev[None, :], lags[:-1]])
    out = comp.copy()
    out[good] = c + q * (c - before)
    state[0] = lags[-1].copy()
    return out


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


def standardise(pre: Preprocess, filt: np.ndarray) -> np.ndarray:
    """Net inputs (n, F) of one continuous recording from its filtered shifts (n, 4), pm:
    standardisation, then the memory features."""
    return memory_features(pre.memory, (np.asarray(filt, dtype=np.float64) - pre.input_mean)
                           / pre.input_std, pre.z_rest)


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
        self._reference: list[float | None] = [None]   # primed by the first good sample
        self._creep_lag: list[np.ndarray | None] = [None]   # the creep inverse's, likewise
        self._memory = MemoryStream(pre.memory, pre.z_rest)
        self._decision: list[Any] = [0, 0, 0.0]
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
        model, pre, iu = self.model, self.model.preprocess, self.model.in_use
        n = wl.shape[0]
        fault = samples.sensor_fault_rows(wl) if n else np.zeros(0, dtype=bool)
        good = np.flatnonzero(~fault)
        comp = creep_inverse(pre, compensate(model, wl, self.baseline_nm, self._reference, fault),
                             self._creep_lag, fault)
        filt, self._history, self._last_comp = filter_through_faults(
            self.taps, comp, fault, self._history, self._last_comp)

        def decide(raw: np.ndarray, margin: np.ndarray) -> np.ndarray:
            return decide_over_time(raw, margin, iu.contact_on_margin, iu.contact_off_margin,
                                    iu.contact_rise_samples, self._decision, iu.cusum)

        z = (filt - pre.input_mean) / pre.input_std
        x = np.zeros((n, pre.n_inputs))
        x[:, :N_STRAIN] = z
        x[good] = self._memory.push(z[good])
        ran = predict_from_features(model, x[good], decide, self.nets)
        ran["force_N"] = hold_over_time(ran["force_N"], ran["contact"], iu, self._hold)
        out = {key: np.zeros(n, dtype=v.dtype) for key, v in ran.items()}
        for key, v in ran.items():
            out[key][good] = v
        out = safe_output(out, fault)
        if iu.track_shift and n:
            # At rest: no contact, no fault, past the filter's warm-up (the runtimes' WARMUP).
            warm = self.taps.size - 1
            rest = ~out["contact"] & ~fault & (np.arange(self.samples, self.samples + n) >= warm)
            self._track_sum += (filt - self._creep_term(filt, good))[rest].sum(axis=0)
            self._rest_run = rest_run_after(self._rest_run, rest)
        self.samples += n
        block = contract.LIMIT["TRACK_BLOCK"]
        if iu.track_shift and n and self.samples % block == 0:
            if self._rest_run >= block + iu.track_settle:
                # A first-order follower of the filtered shift at rest (time constant
                # 2^track_shift samples), each step and the whole correction bounded.
                step = np.clip(self._track_sum / 2.0 ** iu.track_shift,
                               -iu.track_step_max_pm, iu.track_step_max_pm)
                new = np.clip(self._drift + step, -iu.track_limit_pm, iu.track_limit_pm)
                self.baseline_nm[:N_STRAIN] += (new - self._drift) / 1000.0
                self._drift = new
            self._track_sum[:] = 0.0
        return out

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


# --------------------------------------------------------------------------------------------
# Model directory I/O
# --------------------------------------------------------------------------------------------

MODEL_JSON = "model.json"
WEIGHTS_NPZ = "weights.npz"
CALIBRATION_NPZ = "calibration.npz"


@dataclass
class CalibrationRecordings:
    """The calibration data export needs, kept in the model directory so that export never
    reopens the training files (which may have moved): each training recording's raw
    wavelengths, its tare baseline and the true force of its contact samples.

    Attributes
    ----------
    recordings
        ``[(wl_nm (n, 5), baseline_nm (5,)), ...]`` one continuous recording each.
    contact_force_N
        True force (N) of each recording's samples in contact.
    sources
        Where each recording came from (a path, or a dataset's source).
    """

    recordings: list[tuple[np.ndarray, np.ndarray]]
    contact_force_N: list[np.ndarray]
    sources: list[str]

    def to_arrays(self, data_key: str) -> dict[str, np.ndarray]:
        """The ``calibration.npz`` arrays; ``data_key`` names the training data they belong to
        (:func:`training_data_key`)."""
        return {
            "wl_nm": np.concatenate([np.asarray(wl, dtype=np.float64) for wl, _ in self.recordings]),
            "baseline_nm": np.array([np.asarray(b, dtype=np.float64) for _, b in self.recordings]),
            "lengths": np.array([len(wl) for wl, _ in self.recordings], dtype=np.int64),
            "contact_force_N": np.concatenate([np.asarray(f, dtype=np.float64)
                                               for f in self.contact_force_N]),
            "force_lengths": np.array([len(f) for f in self.contact_force_N], dtype=np.int64),
            "sources": np.array(self.sources, dtype=str), "data_key": np.array(data_key)}

    @classmethod
    def from_arrays(cls, a: Any) -> "CalibrationRecordings":
        """Inverse of :meth:`to_arrays`."""
        wl = np.split(a["wl_nm"], np.cumsum(a["lengths"])[:-1])
        forces = np.split(a["contact_force_N"], np.cumsum(a["force_lengths"])[:-1])
        return cls(list(zip(wl, list(a["baseline_nm"]))), forces, [str(x) for x in a["sources"]])


def training_data_key(model: HierarchicalModel) -> str:
    """What identifies a model's training data: a digest of ``metadata["data"]`` (paths, file
    digests, sample counts, tare baselines). A ``calibration.npz`` under another key belongs
    to another model."""
    import hashlib

    text = json.dumps(model.metadata.get("data"), sort_keys=True, default=json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def load_calibration(directory: str | Path, model: HierarchicalModel) -> CalibrationRecordings | None:
    """The calibration recordings :func:`save` kept for ``model`` in ``directory``; None when
    there are none, or they belong to other training data (:func:`training_data_key`).

    Raises
    ------
    InputError
        If ``calibration.npz`` cannot be read (naming the file).
    """
    path = Path(directory) / CALIBRATION_NPZ
    if not path.is_file():
        return None
    try:
        with np.load(path) as npz:
            if str(npz["data_key"]) != training_data_key(model):
                return None
            return CalibrationRecordings.from_arrays(npz)
    except CALIBRATION_READ_ERRORS as exc:
        raise InputError(f"cannot read calibration recordings (truncated or corrupt?): {exc}",
                         path=str(path)) from exc


#: What reading a damaged ``calibration.npz`` raises.
CALIBRATION_READ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error)


def _stored_data_key(path: Path) -> str | None:
    """The training-data key a ``calibration.npz`` was written under (None: unreadable)."""
    try:
        with np.load(path) as npz:
            return str(npz["data_key"])
    except CALIBRATION_READ_ERRORS:
        return None


def save(model: HierarchicalModel, directory: str | Path, flag: str | None = None) -> Path:
    """Write ``model.json`` (readable parameters and metadata), ``weights.npz`` and, when the
    model carries them, its calibration recordings (``calibration.npz``,
    :class:`CalibrationRecordings`).

    The files are written atomically as a set (:class:`fbgforce.fileio.Outputs`): a failed
    write leaves the directory as it was. A ``calibration.npz`` of other training data is
    removed. An export in the directory made from another model
    is removed (:func:`fbgforce.freshness.remove_stale_export`). ``flag`` names the
    command-line option of ``directory`` in errors.
    """
    from fbgforce import fileio, freshness

    out = Path(directory)
    pre = model.preprocess
    doc = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "preprocess": {
            "temp_coeff": pre.temp_coeff.tolist(),
            "filter_kind": pre.filter_kind,
            "filter_sigma": pre.filter_sigma,
            "taps": pre.taps.tolist(),
            "input_mean": pre.input_mean.tolist(),
            "input_std": pre.input_std.tolist(),
            "memory": pre.memory.to_json(),
            "ref_shift": pre.ref_shift,
            "creep": pre.creep,
            "creep_shift": pre.creep_shift,
            "group_delay_ms_at_1kHz": pre.group_delay_samples,
        },
        "nets": {name: {"sizes": net.sizes} for name, net in model.nets.items()},
        "force_offset": model.force_offset,
        "force_scale": model.force_scale,
        "xy_offset": model.xy_offset.tolist(),
        "xy_scale": model.xy_scale.tolist(),
        "baseline_nm": model.baseline_nm.tolist(),
        "in_use": model.in_use.to_json(),
        "input_range": None if model.input_range is None else model.input_range.tolist(),
        "metadata": model.metadata,
    }
    arrays = {}
    for name, net in model.nets.items():
        for layer, (w, b) in enumerate(zip(net.weights, net.biases)):
            arrays[f"{name}.W{layer}"] = w
            arrays[f"{name}.b{layer}"] = b
    key = training_data_key(model)
    with fileio.Outputs(flag) as files:
        files.write_with(out / WEIGHTS_NPZ, lambda fh: np.savez(fh, **arrays))
        if model.calibration is not None:
            cal = model.calibration.to_arrays(key)
            files.write_with(out / CALIBRATION_NPZ, lambda fh: np.savez_compressed(fh, **cal))
        files.write_text(out / MODEL_JSON, json.dumps(doc, indent=2, default=json_default) + "\n")
    stale = out / CALIBRATION_NPZ
    if model.calibration is None and stale.is_file() and _stored_data_key(stale) != key:
        try:
            stale.unlink()          # another model's training data: export must not use it
        except OSError as exc:
            raise fileio.write_error(exc, stale, flag) from None
    try:
        freshness.remove_stale_export(out, model)
    except OSError as exc:
        raise fileio.write_error(exc, exc.filename or out, flag) from None
    return out



def load(directory: str | Path) -> HierarchicalModel:
    """Read a model directory written by :func:`save`.

    Raises
    ------
    InputError
        If the directory or its files are missing, of another format or version, or
        inconsistent (naming the file and the key).
    """
    root = Path(directory)
    json_path = root / MODEL_JSON
    npz_path = root / WEIGHTS_NPZ
    if not root.is_dir():
        raise InputError("not a model directory (train one with 'fbgforce train')", path=str(root))
    for p in (json_path, npz_path):
        if not p.is_file():
            raise InputError("missing; is this a model directory written by 'fbgforce train'?",
                             path=str(p))
    try:
        doc = json.loads(json_path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg}", path=str(json_path), line=exc.lineno) from exc
    if doc.get("format") != FORMAT_NAME:
        raise InputError(f"format is {doc.get('format')!r}, expected {FORMAT_NAME!r}",
                         path=str(json_path), column="format")
    if doc.get("version") not in (1, FORMAT_VERSION):   # version 1: no memory
        raise InputError(f"format version {doc.get('version')!r} is not supported "
                         f"(this fbgforce reads version {FORMAT_VERSION})",
                         path=str(json_path), column="version")
    try:
        with np.load(npz_path) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"cannot read weights (truncated or corrupt?): {exc}",
                         path=str(npz_path)) from exc
    try:
        nets = {}
        for name in NET_NAMES:
            n_layers = len(doc["nets"][name]["sizes"]) - 1
            nets[name] = MLP([arrays[f"{name}.W{i}"] for i in range(n_layers)],
                             [arrays[f"{name}.b{i}"] for i in range(n_layers)])
        p = doc["preprocess"]
        pre = Preprocess(p["temp_coeff"], p["filter_kind"], p["filter_sigma"], p["taps"],
                         p["input_mean"], p["input_std"], Memory(**p.get("memory", {})),
                         p.get("ref_shift", 0),   # models trained before it: the raw reference
                         p.get("creep", 0.0), p.get("creep_shift", 0))   # ... and no creep inverse
        return HierarchicalModel(
            preprocess=pre, force_offset=doc["force_offset"], force_scale=doc["force_scale"],
            xy_offset=doc["xy_offset"], xy_scale=doc["xy_scale"], baseline_nm=doc["baseline_nm"],
            metadata=doc.get("metadata", {}), in_use=InUse(**doc.get("in_use", {})),
            input_range=doc.get("input_range"), **nets)
    except KeyError as exc:
        raise InputError(f"missing entry {exc.args[0]!r}", path=str(root)) from exc
    except ValueError as exc:
        raise InputError(str(exc), path=str(root)) from exc
