"""The model directory's artifact: what the trainer writes and every later stage reads.

A model is its preprocessing (:class:`Preprocess`, with the load signal's :class:`Memory`),
three nets (:class:`MLP`, together :class:`HierarchicalModel`), what the runtimes do beyond
the nets when they run for hours (:class:`InUse`) and, for export, the recordings it was
trained on (:class:`CalibrationRecordings`). :mod:`fbgforce.model.modeldir` writes and reads
the directory; :mod:`fbgforce.model.floatref` runs the model in float64, the reference every
other engine (onnxruntime, C float, C fixed-point) is compared against.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from fbgforce import contract
from fbgforce.errors import InputError
from fbgforce.model.decision import (CUSUM_MAX, REST_MARGIN_FACTOR, REST_MARGIN_QUANTILE, RISE_S,
                                     cusum_parameters)

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

    def columns(self, name: str) -> range:
        """The net inputs' columns that the states of the kind ``name`` (``"ema"``,
        ``"play"``) feed: after the four channels, in ``contract.MEMORY_KINDS`` order."""
        start = N_STRAIN
        for kind in contract.MEMORY_KINDS:
            if kind.name == name:
                return range(start, start + self.count(kind))
            start += self.count(kind)
        raise KeyError(f"no memory kind {name!r}")

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
#: The band is at least this many times the nets' scatter on a load that stands still, as the
#: trainer measures it on its synthetic holds (``hold_noise_N``): a steady hold's sample then
#: passes it but for about one in 16,000 (Gaussian), so the settle and the ramp, 456 samples
#: of a scatter the filter correlates over a few, rarely restart; 0.5 N alone, on a pad whose
#: nets scatter 0.25 N, keeps the gain off on most holds below 15 N.
HOLD_BAND_NOISE = 4.0
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
        ``decision="cusum"`` sets it from the calibration's rests
        (:func:`~fbgforce.model.decision.cusum_parameters`).
    contact_cusum_k
        The CUSUM's drift: a sample adds its margin's excess over ``k`` (0 when off).
    contact_cusum_lo, contact_cusum_hi
        The CUSUM's clip of the margin, ``lo <= hi`` (0 when off): ``hi`` bounds what one
        sample adds, so no single spike raises contact; ``lo`` what one sample takes away.
        Every CUSUM value within ``+-MAX_CUSUM_Q8 / 256``
        (:data:`~fbgforce.model.decision.CUSUM_MAX`).
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
        """``(h, k, lo, hi)`` of the CUSUM rise (h 0: off), as
        :func:`~fbgforce.model.decision.decide_over_time` takes
        them."""
        return (self.contact_cusum_h, self.contact_cusum_k, self.contact_cusum_lo,
                self.contact_cusum_hi)

    @classmethod
    def recommended(cls, sample_rate_hz: float = 1000.0,
                    rest_margins: np.ndarray | None = None, *, creep_magnitude: float = 0.0,
                    creep_time_constant_samples: float = 0.0, hold_gain: float = 0.0,
                    hold_noise_N: float = 0.0, decision: str = "schmitt",
                    contact_margins: np.ndarray | None = None,
                    long_rests: np.ndarray | None = None,
                    presses: Sequence[tuple[np.ndarray, int]] | None = None,
                    idle: Sequence[np.ndarray] = ()) -> "InUse":
        """The trainer's default (docs/runtime.md, "In use", says how each value was chosen).

        ``rest_margins``: the contact net's margins on calibration samples at rest, in the
        order of the recording; contact
        rises only past :data:`~fbgforce.model.decision.REST_MARGIN_FACTOR` times their
        :data:`~fbgforce.model.decision.REST_MARGIN_QUANTILE`
        quantile, held for :data:`~fbgforce.model.decision.RISE_S`, and falls below minus half of
        it. None: the
        per-sample decision.

        ``decision``: ``"schmitt"`` for that rule, ``"cusum"`` for the CUSUM rise of
        :func:`~fbgforce.model.decision.cusum_parameters` on ``rest_margins`` (and
        ``contact_margins``, the margins on
        labelled contact samples, for its drift; ``long_rests``, its margins on synthetic long
        rests, every sample in time order, and ``idle``, its margins on idle pads, one array
        each, for its threshold; ``presses``, windows of its margins around the calibration's
        presses, for its drift), falling below minus its drift.

        ``creep_magnitude`` and ``creep_time_constant_samples``: the pad's creep as fitted,
        for the tracker's creep term (:func:`creep_parameters`); 0 leaves it off (as for a
        model that takes the creep out before the filter,
        :func:`~fbgforce.model.floatref.creep_inverse`, where the
        tracker never sees it).

        ``hold_gain``: the settled-hold gain's excess over 1 as the trainer measured it on its
        synthetic holds, clipped to :data:`HOLD_GAIN_MAX`; 0 leaves the stage off.
        ``hold_noise_N``: the nets' scatter on those holds (N); the steadiness band is
        :data:`HOLD_BAND_N` or :data:`HOLD_BAND_NOISE` times it, the larger.
        """
        creep, creep_shift = creep_parameters(creep_magnitude, creep_time_constant_samples)
        hold_gain = float(np.clip(hold_gain, -HOLD_GAIN_MAX, HOLD_GAIN_MAX))
        hold = {} if not hold_gain else {
            "hold_gain": hold_gain,
            "hold_settle": min(0xFFFF, int(round(HOLD_SETTLE_S * sample_rate_hz))),
            "hold_band_N": max(HOLD_BAND_N, HOLD_BAND_NOISE * float(hold_noise_N)),
            "hold_band_frac": HOLD_BAND_FRACTION,
            "hold_shift": min(contract.LIMIT["MAX_EMA_SHIFT"],
                              max(1, int(round(np.log2(HOLD_AVERAGE_S * sample_rate_hz))))),
            "hold_ramp_shift": min(contract.LIMIT["MAX_HOLD_RAMP_SHIFT"],
                                   max(0, int(round(np.log2(HOLD_RAMP_S * sample_rate_hz)))))}
        if decision not in ("schmitt", "cusum"):
            raise ValueError(f"decision must be 'schmitt' or 'cusum', not {decision!r}")
        on = 0.0
        rise: dict[str, float | int] = {}
        if decision == "cusum" and rest_margins is not None and np.size(rest_margins):
            cs = cusum_parameters(rest_margins, sample_rate_hz, contact_margins,
                                  long_rests=long_rests, presses=presses, idle=idle)
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
        (:func:`~fbgforce.model.floatref.reference_average`).
    creep
        The pad's creep magnitude ``m`` the creep inverse undoes
        (:func:`~fbgforce.model.floatref.creep_inverse`):
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
    #: (:class:`CalibrationRecordings`); written beside the weights by
    #: :func:`~fbgforce.model.modeldir.save`, read back
    #: by :func:`~fbgforce.model.modeldir.load_calibration` (not by
    #: :func:`~fbgforce.model.modeldir.load`: only export needs them).
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
        """Whether :func:`~fbgforce.model.floatref.predict` runs the decision over time, the
        tracker or the settled-hold
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
        (:func:`~fbgforce.model.modeldir.training_data_key`)."""
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
