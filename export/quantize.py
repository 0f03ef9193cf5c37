"""Post-training quantisation of a float model into the fixed-point model of the C runtime.

The arithmetic the runtime performs is fixed in docs/fixed-point.md; this module only CHOOSES
its integers (multipliers, shifts, Q formats, quantised weights) from the float model and a
calibration set. Float is allowed here because nothing the C code mirrors is computed in float:
once chosen, the integers are the model, and :mod:`fbgforce.export.intref` and the C runtime
evaluate exactly the same integer expressions.

Scales (all chosen from calibration data: the float pipeline run on recordings)
-----------------------------------------------------------------------------
- Net inputs ``z`` (standardised channels), the contact flag and the force net's output that
  feeds the location net share one power-of-two Q format ``Q(z_frac)``: the largest ``z_frac``
  (<= 14) with ``Z_HEADROOM * max|z or f| * 2^z_frac <= 32767``. A power of two makes the
  contact flag exact (``1 << z_frac``) and lets the location net's first layer treat its six
  inputs alike.
- Hidden activations: one scale per layer, ``ACT_HEADROOM * max(calibration activation) / 32767``.
- Weights: symmetric per output row, ``max|W[r]| / 32767`` (int16) or ``/ 127`` (int8).
- Biases: int64 at the accumulator scale ``in_scale * w_scale[r]``.
- Requantisation ``y = rshift_round(acc * mult[r], shift)``: one shift per layer, the largest for
  which every multiplier stays below 2^30 AND ``acc_bound[r] * |mult[r]| <= 2^62`` (so the
  product and the rounding constant cannot overflow int64: the accumulator proof).
"""
from __future__ import annotations

import math
from fractions import Fraction
from dataclasses import dataclass, field, make_dataclass
from functools import partial
from typing import Any, Sequence

import numpy as np

from fbgforce import contract, samples
from fbgforce.model import artifact, floatref
from fbgforce.errors import InputError
from fbgforce.units import nm_to_fm

SAT16 = contract.SAT16
SAT32 = contract.SAT32
TEMP_COEFF_SHIFT = contract.LIMIT["TEMP_COEFF_SHIFT"]
MAX_WIDTH = contract.LIMIT["MAX_WIDTH"]
WL_MIN_FM = contract.LIMIT["WL_MIN_FM"]
WL_MAX_FM = contract.LIMIT["WL_MAX_FM"]
NET_NAMES = contract.NET_NAMES
NET_OUTPUTS = {net.name: net.fixed_outputs for net in contract.NETS}

#: Calibration maximum of the net inputs times this must fit int16. 25 % above the
#: calibration range, like the activations: a press well beyond it (where the nets extrapolate
#: anyway) saturates and is flagged (SATURATED, and OVERLOAD above the calibrated force);
#: a spare bit (2.0) would cost the whole calibrated range one bit of resolution, which
#: doubled the location error on the test model (docs/fixed-point.md).
Z_HEADROOM = 1.25
#: The same for hidden activations.
ACT_HEADROOM = 1.25
#: Multipliers stay below 2^MULT_BITS (int32 with margin).
MULT_BITS = 30
#: |product| limit of ``acc * mult`` (the rounding constant adds at most 2^61).
PRODUCT_LIMIT = 2**62
#: Default of ``quantize(acc32_max_drop=)``: bits of weight resolution a layer may give up
#: for an int32 accumulator (docs/fixed-point.md, "int32 layers").
ACC32_MAX_DROP = 6.0
#: Largest change, in output integer units, that the weights of a row may make for any int16
#: input for the row to be quantised as zeros when it alone would need an int64 accumulator.
FAINT_ROW_LSB = 0.25
#: |load_coeff| limit (four int32 x int32 products must sum inside int64 with margin).
LOAD_COEFF_LIMIT = contract.LIMIT["LOAD_COEFF_LIMIT"]
#: |bias| limit of fbg_model_check, so that the accumulator bound cannot overflow int64 itself.
BIAS_LIMIT = 2**60


class ModelCheckError(ValueError):
    """A model the C runtime refuses: ``code`` is the ``FBG_ERR_*`` name it returns."""

    def __init__(self, code: str, reason: str) -> None:
        self.code = code
        super().__init__(reason)
#: Stuck-peak rule defaults: at least this many identical samples, and off when the
#: calibration data itself repeats values this long (noise-free data).
STUCK_MIN = 25
STUCK_OFF_RUN = 1000
#: Default for the sensor-fault jump rule, nm per sample.
DEFAULT_JUMP_NM = contract.DEFAULT_JUMP_NM
#: Default OVERLOAD threshold: this factor above the largest calibration force.
OVERLOAD_MARGIN = 1.02


@dataclass
class QLayer:
    """One quantised dense layer (``fbg_layer`` in C). Integer arrays are int64 numpy arrays
    holding values of the C types (int16/int8 weights, int64 bias, int32 multipliers)."""

    w: np.ndarray
    w_bits: int
    bias: np.ndarray
    mult: np.ndarray
    shift: int
    info: dict[str, Any] = field(default_factory=dict)
    #: Exporter-only float scales (not in the blob): w_scale (n_out,), in_scale, out_ratio
    #: (n_out,) = output integer units per real accumulator unit; used by error_bounds().
    scales: dict[str, Any] = field(default_factory=dict, repr=False)
    #: int32 accumulator (``fbg_layer.acc32``): allowed only when :meth:`acc_bound` fits int32,
    #: so the int32 sum equals the int64 one (docs/fixed-point.md, "int32 layers").
    acc32: bool = False

    def __post_init__(self) -> None:
        self.acc32 = bool(self.acc32)
        self.w = np.asarray(self.w, dtype=np.int64)
        self.bias = np.asarray(self.bias, dtype=np.int64).reshape(-1)
        self.mult = np.asarray(self.mult, dtype=np.int64).reshape(-1)

    @property
    def n_in(self) -> int:
        return int(self.w.shape[1])

    @property
    def n_out(self) -> int:
        return int(self.w.shape[0])

    def acc_bound(self) -> np.ndarray:
        """Worst-case ``|acc|`` per output row for any int16 inputs (|x| <= 32767)."""
        return np.abs(self.w).sum(axis=1) * SAT16 + np.abs(self.bias)

    def acc32_bound(self, relu_inputs: bool) -> np.ndarray:
        """Worst-case ``|acc|`` (and of every partial sum) per row for the inputs the runtime
        can produce: any int16 for a net's first layer, ReLU outputs in [0, 32767] for the
        others (``relu_inputs``), where the positive and negative weights cannot both act:
        ``max(sum of w > 0, sum of |w < 0|) * 32767 + |b|``. The proof of ``acc32``."""
        if not relu_inputs:
            return self.acc_bound()
        pos = np.where(self.w > 0, self.w, 0).sum(axis=1)
        neg = np.where(self.w < 0, -self.w, 0).sum(axis=1)
        return np.maximum(pos, neg) * SAT16 + np.abs(self.bias)


def check_layer(layer: QLayer, relu_inputs: bool, where: str) -> None:
    """``check_layer`` of runtime_c/src/fbg_model.c, rule for rule and in its order, in
    Python integers (numpy's int64 ``abs`` would wrap at INT64_MIN)."""
    def need(cond: bool, code: str, what: str) -> None:
        if not cond:
            raise ModelCheckError(code, f"{where}: {what}")

    need(1 <= layer.n_in <= MAX_WIDTH and 1 <= layer.n_out <= MAX_WIDTH, "ERR_SHAPE",
         f"width above {MAX_WIDTH}")
    need(layer.w_bits in (8, 16), "ERR_RANGE", f"weight width {layer.w_bits}")
    need(1 <= layer.shift <= 62 and layer.acc32 in (0, 1), "ERR_RANGE", "shift or acc32 out of range")
    qmax = 127 if layer.w_bits == 8 else 32767
    need(bool(np.all(np.abs(layer.w) <= qmax + 1)), "ERR_RANGE", f"weights exceed int{layer.w_bits}")
    mults = [int(m) for m in layer.mult]
    need(all(abs(m) <= SAT32 for m in mults), "ERR_RANGE", "multiplier out of int32 (or INT32_MIN)")
    half = 1 << (layer.shift - 1)
    for r in range(layer.n_out):
        row = [int(v) for v in layer.w[r]]
        b = int(layer.bias[r])
        need(abs(b) < BIAS_LIMIT, "ERR_BOUND", f"row {r}: |bias| >= 2^60")
        sumw = sum(abs(v) for v in row)
        bound = sumw * SAT16 + abs(b)
        if layer.acc32:
            pos = sum(v for v in row if v > 0)
            b32 = max(pos, sumw - pos) * SAT16 + abs(b) if relu_inputs else bound
            need(b32 <= SAT32, "ERR_BOUND", f"row {r}: int32 accumulator but the bound exceeds int32")
        need(bound * abs(mults[r]) + half <= 2**63 - 1, "ERR_BOUND",
             f"row {r}: accumulator bound exceeds int64")


#: Parameter-block fields a QModel does not hold: its taps and nets imply them.
_IMPLIED_PARAMS = ("n_taps", "n_layers")

#: The memory kinds' fields of the parameter block (``n_<kind>``, ``<kind>_<param>`` of
#: ``contract.MEMORY_KINDS``) as keyword-only dataclass fields, zero (no memory) by default:
#: the base of :class:`QModel`, derived from the contract so that a kind adds no field here.
QModelMemory = make_dataclass("QModelMemory", [
    (f.name, np.ndarray, field(default_factory=partial(np.zeros, f.count, dtype=np.int64), kw_only=True))
    if f.count > 1 else (f.name, int, field(default=0, kw_only=True))
    for f in contract.memory_params()])


@dataclass
class QModel(QModelMemory):
    """The fixed-point model (``fbg_model`` in C); see runtime_c/include/fbgforce.h."""

    baseline_fm: np.ndarray
    jump_max_fm: int
    temp_coeff_q24: np.ndarray
    taps: np.ndarray
    tap_q: int
    mean_fm: np.ndarray
    z_mult: np.ndarray
    z_shift: int
    z_frac: int
    fq_mult: int
    fq_shift: int
    force_offset_mN: int
    xy_offset_um: np.ndarray
    overload_mN: int
    nets: list[list[QLayer]]
    #: Input-side overload rule (fbg_model.load_*): defaults disable it.
    load_coeff: np.ndarray = field(default_factory=lambda: np.zeros(4, dtype=np.int64))
    load_shift: int = 1
    load_max_mN: int = SAT32
    #: Stuck-peak rule (fbg_model.stuck_max): 0 disables it.
    stuck_max: int = 0
    #: The memory's load signal (fbg_model.mem_mult, mem_shift); the kinds' fields (n_ema ...)
    #: are those of :class:`QModelMemory`.
    mem_mult: np.ndarray = field(default_factory=lambda: np.zeros(4, dtype=np.int64))
    mem_shift: int = 1
    #: Location averages (fbg_model.loc_shift): 0 is off.
    loc_shift: int = 0
    #: The temperature reference's average (fbg_model.ref_shift): 0 is the raw reference.
    ref_shift: int = 0
    #: The pad's creep inverse (fbg_model.creep_q15, creep_shift): 0 is off.
    creep_q15: int = 0
    creep_shift: int = 0
    #: The decision over time and the at-rest baseline tracker (fbg_model.contact_*,
    #: track_*): the defaults are the per-sample decision on a fixed tare.
    contact_on_q8: int = 0
    contact_off_q8: int = 0
    contact_rise_n: int = 1
    track_shift: int = 0
    track_settle: int = 0
    track_gain: np.ndarray = field(default_factory=lambda: np.zeros(4, dtype=np.int64))
    track_step_max_fm: int = 0
    track_limit_fm: int = 0
    #: The tracker's creep term (fbg_model.track_creep_q15, track_creep_shift): 0 is off.
    track_creep_q15: int = 0
    track_creep_shift: int = 0
    #: The settled-hold gain (fbg_model.hold_*): 0 is off.
    hold_gain_q15: int = 0
    hold_settle: int = 0
    hold_band_mN: int = 0
    hold_band_q15: int = 0
    hold_shift: int = 0
    hold_ramp_shift: int = 0
    #: The decision's CUSUM rise (fbg_model.contact_cusum_*): h 0 is off (the Schmitt trigger).
    contact_cusum_h_q8: int = 0
    contact_cusum_k_q8: int = 0
    contact_cusum_lo_q8: int = 0
    contact_cusum_hi_q8: int = 0
    #: OUT_OF_RANGE bounds of the net inputs (fbg_model.in_lo, in_hi): the defaults never flag.
    in_lo: np.ndarray = field(default_factory=lambda: np.full(contract.LIMIT["MAX_INPUTS"], -SAT16, dtype=np.int64))
    in_hi: np.ndarray = field(default_factory=lambda: np.full(contract.LIMIT["MAX_INPUTS"], SAT16, dtype=np.int64))
    #: Version of the library that wrote the blob (fbg_model.writer_version).
    writer_version: int = contract.VERSION_CODE

    def __post_init__(self) -> None:
        self.taps = np.asarray(self.taps, dtype=np.int64).reshape(-1)
        for f in contract.PARAMS:
            if f.name not in _IMPLIED_PARAMS:
                v = getattr(self, f.name)
                setattr(self, f.name, np.asarray(v, dtype=np.int64).reshape(-1) if f.count > 1 else int(v))

    @property
    def n_memory(self) -> int:
        """Memory states in use, every kind's ``n_<kind>`` together."""
        return sum(getattr(self, kind.count_field) for kind in contract.MEMORY_KINDS)

    @property
    def n_features(self) -> int:
        """Width of the contact and force nets' input (z and memory features)."""
        return contract.n_features(self.n_memory)

    @property
    def n_loc(self) -> int:
        """Location averages (4 when ``loc_shift`` is on, else 0)."""
        return contract.n_loc(self.loc_shift)

    def z_rest(self) -> tuple[np.ndarray, bool]:
        """(4,) ``z0``, the standardisation of a zero filtered shift as fbg_fixed.c computes it,
        and whether it saturated."""
        z0 = ((-self.mean_fm * self.z_mult) + (1 << (self.z_shift - 1))) >> self.z_shift
        return np.clip(z0, -SAT16, SAT16), bool(np.any(np.abs(z0) > SAT16))

    @classmethod
    def from_params(cls, values: dict[str, Any], taps: np.ndarray, nets: list[list[QLayer]]
                    ) -> "QModel":
        """The model of a decoded parameter block (:data:`fbgforce.contract.PARAMS` names)
        with its taps and nets; ``n_taps`` and ``n_layers`` are implied by those."""
        fields = {k: v for k, v in values.items() if k not in _IMPLIED_PARAMS}
        return cls(taps=taps, nets=nets, **fields)

    def params(self) -> dict[str, Any]:
        """The parameter block as :data:`fbgforce.contract.PARAMS` names it."""
        values: dict[str, Any] = {}
        for f in contract.PARAMS:
            if f.name == "n_taps":
                values[f.name] = int(self.taps.size)
            elif f.name == "n_layers":
                values[f.name] = tuple(len(net) for net in self.nets)
            else:
                v = getattr(self, f.name)
                values[f.name] = tuple(int(x) for x in v) if f.count > 1 else int(v)
        return values

    @property
    def w_bits(self) -> int:
        """Weight width of the nets (16, or 8 for an int8-weight export)."""
        return max(layer.w_bits for net in self.nets for layer in net)

    def check(self) -> None:
        """The checks of ``fbg_model_check`` (C), in its order: raises
        :class:`ModelCheckError` with the code C returns for the first violated rule."""
        def need(cond: bool, code: str, what: str) -> None:
            if not cond:
                raise ModelCheckError(code, what)

        bad = contract.check_params(self.params())
        if bad is not None:
            raise ModelCheckError(*bad)
        need(self.track_creep_q15 == 0 or self.track_creep_shift >= 1, "ERR_RANGE",
             "track_creep_shift must be at least 1 when track_creep_q15 is on")
        need(self.creep_q15 == 0 or self.creep_shift >= 1, "ERR_RANGE",
             "creep_shift must be at least 1 when creep_q15 is on")
        need(self.hold_gain_q15 == 0 or self.hold_shift >= 1, "ERR_RANGE",
             "hold_shift must be at least 1 when hold_gain_q15 is on")
        if self.contact_cusum_h_q8 == 0:
            need(self.contact_cusum_k_q8 == 0 and self.contact_cusum_lo_q8 == 0
                 and self.contact_cusum_hi_q8 == 0, "ERR_RANGE",
                 "contact_cusum_k_q8, _lo_q8 and _hi_q8 must be 0 when contact_cusum_h_q8 is off")
        else:
            need(self.contact_cusum_lo_q8 <= self.contact_cusum_hi_q8 and self.contact_on_q8 == 0
                 and self.contact_rise_n == 1, "ERR_RANGE",
                 "with contact_cusum_h_q8 on, contact_cusum_lo_q8 <= contact_cusum_hi_q8, "
                 "contact_on_q8 0 and contact_rise_n 1")
        need(self.taps.size >= 1 and bool(np.all(np.abs(self.taps) <= 32768)), "ERR_RANGE",
             "taps must be int16")
        for name, net in zip(NET_NAMES, self.nets):
            n_in = contract.net_inputs(name, self.n_memory, self.n_loc)
            need(net[0].n_in == n_in and net[-1].n_out == NET_OUTPUTS[name], "ERR_SHAPE",
                 f"{name}: input/output width {net[0].n_in}/{net[-1].n_out}, expected "
                 f"{n_in}/{NET_OUTPUTS[name]}")
            for i, layer in enumerate(net):
                where = f"{name} layer {i}"
                need(i == 0 or layer.n_in == net[i - 1].n_out, "ERR_SHAPE", f"{where}: shape chain")
                check_layer(layer, i > 0, where)

# --------------------------------------------------------------------------------------------
# Choosing integers
# --------------------------------------------------------------------------------------------

def choose_shift(ratios: Sequence[float], limits: Sequence[int] | int = 2**MULT_BITS,
                 max_shift: int = 62) -> tuple[int, np.ndarray]:
    """Largest shift ``s`` (1..max_shift) with ``|round(ratio * 2^s)| <= limit`` for all ratios.

    Returns ``(s, multipliers)``; ``rshift_round(x * mult, s)`` then approximates
    ``x * ratio`` with a relative error of at most ``2^-(bits of the smallest |mult|)``.
    """
    r = np.asarray(ratios, dtype=np.float64).reshape(-1)
    lim = np.broadcast_to(np.asarray(limits, dtype=np.float64), r.shape)
    if not np.all(np.isfinite(r)):
        raise ValueError("non-finite scale ratio")
    for s in range(max_shift, 0, -1):
        # Compared as Python ints before the int64 array: at large shifts a ratio above 2
        # would not fit int64 at all.
        m = [int(round(float(v) * 2.0**s)) for v in r]
        if all(abs(v) <= limit for v, limit in zip(m, lim)):
            return s, np.array(m, dtype=np.int64)
    raise ValueError(f"scale ratio too large to represent: max {np.abs(r).max():g}")


def quantize_taps(pre: artifact.Preprocess) -> tuple[np.ndarray, int]:
    """Causal FIR taps as int16 in Q15 (Q14 if a tap reaches 1), DC gain kept exactly."""
    taps = pre.runtime_taps()
    peak = float(np.abs(taps).max())
    if peak < 32767.5 / 32768:
        q = 15
    elif peak < 32767.5 / 16384:
        q = 14
    else:
        raise InputError(f"filter tap {peak:g} >= 2 cannot be represented", column="taps")
    t = np.round(taps * 2.0**q).astype(np.int64)
    # Put the rounding residue on the largest tap so a constant input passes exactly.
    target = int(round(float(taps.sum()) * 2.0**q))
    t[int(np.argmax(np.abs(t)))] += target - int(t.sum())
    if np.any(np.abs(t) > 32767):
        raise InputError("filter taps do not fit int16 after normalisation", column="taps")
    return t, q


@dataclass
class Calibration:
    """Float activations of the pipeline on calibration recordings (what scales come from)."""

    z: np.ndarray               # (n, 4) standardised inputs
    contact: np.ndarray         # (n,) float contact decision
    f: np.ndarray               # (n,) force net output
    force_N: np.ndarray         # (n,) float force (raw, before gating)
    true_force_N: np.ndarray | None
    max_step_fm: float          # largest per-sample change of any in-window channel
    max_same_run: int           # longest run of identical consecutive values (fm), any channel
    samples: int
    max_comp_pm: float = 0.0    # largest |compensated shift| the filter reads (after the creep inverse)
    #: (n, 4) per sample: |comp[n]| and max_k |comp[n-k] - comp[n]| over the filter window (pm)
    comp_abs_pm: np.ndarray | None = None
    comp_var_pm: np.ndarray | None = None


def _longest_same_run(wl_nm: np.ndarray) -> int:
    """Longest run of consecutive samples repeating the previous value (in fm), any channel:
    the count the runtime's stuck-peak rule keeps."""
    x = nm_to_fm(wl_nm).astype(np.int64)
    if x.shape[0] < 2:
        return 0
    same = np.vstack([np.zeros((1, x.shape[1]), dtype=bool), x[1:] == x[:-1]])
    n = np.arange(x.shape[0])[:, None]
    last_reset = np.maximum.accumulate(np.where(same, -1, n), axis=0)
    return int((n - last_reset).max())


def calibrate(model: artifact.HierarchicalModel, recordings: Sequence[tuple[np.ndarray, np.ndarray]],
              true_force_N: Sequence[np.ndarray] | None = None) -> Calibration:
    """Run the float pipeline on ``recordings`` = [(wl_nm (n,5), baseline_nm (5,)), ...]."""
    zs, steps, comp_max, c_abs, c_var, same_run = [], [0.0], 0.0, [], [], 0
    n_taps = model.preprocess.taps.size
    for wl, base in recordings:
        wl = np.asarray(wl, dtype=np.float64)
        zs.append(floatref.features(model, wl, base))
        # What the filter reads: the compensated shifts after the pad's creep inverse.
        comp = floatref.creep_inverse(model.preprocess, floatref.compensate(model, wl, base), None,
                                samples.sensor_fault_rows(wl))
        comp_max = max(comp_max, float(np.abs(comp[np.isfinite(comp)]).max(initial=0.0)))
        # Zero history before the first sample, as the causal filter sees it.
        padded = np.concatenate([np.zeros((n_taps - 1, 4)), comp])
        var = np.zeros_like(comp)
        for k in range(1, n_taps):
            var = np.maximum(var, np.abs(padded[n_taps - 1 - k:padded.shape[0] - k] - comp))
        c_abs.append(np.abs(comp))
        c_var.append(var)
        same_run = max(same_run, _longest_same_run(wl))
        if wl.shape[0] > 1:
            d = np.abs(np.diff(wl, axis=0)) * 1e6
            d = d[np.isfinite(d)]
            steps.append(float(d.max()) if d.size else 0.0)
    if not zs or sum(len(z) for z in zs) == 0:
        raise InputError("no calibration samples")
    z = np.concatenate(zs)
    finite = np.all(np.isfinite(z), axis=1)
    z = z[finite]
    pred = floatref.predict_from_features(model, z)
    f = model.force.forward(z[:, :model.preprocess.n_features])[:, 0]
    truth = None
    if true_force_N is not None:
        truth = np.concatenate([np.asarray(t, dtype=np.float64) for t in true_force_N])
    return Calibration(z=z, contact=pred["contact"], f=f, force_N=pred["force_raw_N"],
                       true_force_N=truth, max_step_fm=max(steps), max_same_run=same_run,
                       samples=int(z.shape[0]),
                       max_comp_pm=comp_max, comp_abs_pm=np.concatenate(c_abs)[finite],
                       comp_var_pm=np.concatenate(c_var)[finite])


def fit_load_proxy(model: artifact.HierarchicalModel, calib: Calibration
                   ) -> tuple[np.ndarray, int, int, dict[str, Any]]:
    """The input-side overload rule: a linear force proxy on the filtered shifts.

    Beyond the trained range the nets extrapolate (a 150 N press can read 60 N), so OVERLOAD
    cannot rest on their estimate alone. The four beams carry the pad, so the force is close to
    a fixed linear combination of the four filtered shifts whatever the location: least
    squares (no intercept) of the float model's force on ``filt`` (fm) over the calibration
    samples it calls contact. The threshold is the largest proxy value on the calibration
    data, so no calibration sample trips it.

    Returns ``(load_coeff (4,), load_shift, load_max_mN, info)``.
    """
    pre = model.preprocess
    filt_fm = (calib.z[:, :artifact.N_STRAIN] * pre.input_std + pre.input_mean) * 1000.0
    sel = calib.contact
    if sel.sum() < 8:
        return np.zeros(4, dtype=np.int64), 1, SAT32, {"fitted": False}
    coef, *_ = np.linalg.lstsq(filt_fm[sel], calib.force_N[sel] * 1000.0, rcond=None)
    shift, q = choose_shift(coef, LOAD_COEFF_LIMIT - 1)
    proxy = filt_fm @ (q / 2.0**shift)
    resid = proxy[sel] - calib.force_N[sel] * 1000.0
    load_max = int(min(SAT32, math.ceil(float(proxy.max())) + 1))
    return q, shift, load_max, {"fitted": True, "coeff": q.tolist(), "shift": shift,
                                "max_mN": load_max, "fit_rms_N": float(np.sqrt(np.mean(resid**2)) / 1000.0)}


def _int_weights(w: np.ndarray, b: np.ndarray, in_scale: float, w_scale: np.ndarray, qmax: int,
                 relu_inputs: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(wq, bq, bound, bound32): integer weights and biases at ``w_scale``, each row's
    worst-case ``|acc|`` for any int16 inputs, and for the inputs the runtime can produce
    (:meth:`QLayer.acc32_bound`)."""
    wq = np.clip(np.round(w / w_scale[:, None]), -qmax, qmax).astype(np.int64)
    bq = np.round(b / (in_scale * w_scale))
    if np.any(np.abs(bq) >= 2**60):
        raise InputError("a bias is too large for the accumulator scale (model weights out of range)")
    bq = bq.astype(np.int64)
    ly = QLayer(wq, 16, bq, np.zeros(wq.shape[0]), 1)
    return wq, bq, ly.acc_bound(), ly.acc32_bound(relu_inputs)


def _acc32_scale(w: np.ndarray, b: np.ndarray, in_scale: float, w_scale: np.ndarray,
                 relu_inputs: bool) -> np.ndarray:
    """Per row, the smallest weight scale (>= ``w_scale``) whose integer bound
    (:meth:`QLayer.acc32_bound`) provably fits int32: rounding adds at most 1/2 per weight and
    per bias, hence the slack in the limit."""
    if relu_inputs:
        sw = np.maximum(np.where(w > 0, w, 0.0).sum(axis=1), np.where(w < 0, -w, 0.0).sum(axis=1))
    else:
        sw = np.abs(w).sum(axis=1)
    need = sw * SAT16 + np.abs(b) / in_scale
    # Rounding moves each weight by at most 1/2; a column of zeros (a padding unit) not at all.
    room = SAT32 - (np.count_nonzero(np.any(w != 0.0, axis=0)) * SAT16) / 2.0 - 2.0
    return np.maximum(w_scale, need / room * (1.0 + 2.0**-20))


def _row_weight_scales(row_max: np.ndarray, zero_rows: np.ndarray, qmax: int) -> np.ndarray:
    """Per-row weight scales ``max|W[r]| / qmax``; a row quantised as zeros takes the largest
    of the other rows' (so its multiplier needs no smaller shift than theirs)."""
    live = row_max[~zero_rows] / qmax
    return np.where(zero_rows, live.max() if live.size else 1.0, row_max / qmax)


def _quantize_layer(w: np.ndarray, b: np.ndarray, in_scale: float, out_ratio: np.ndarray,
                    bits: int, acc32_max_drop: float = 0.0, relu_inputs: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, dict[str, Any]]:
    """Quantise one layer. ``out_ratio[r]`` is (real output unit) per (real accumulator unit):
    the multiplier implements ``acc * acc_scale[r] * out_ratio[r]``.

    The layer gets an int32 accumulator (``acc32``) when its proven bound fits int32, either
    as it is or after coarser weight scales on the rows that need it, as long as no row loses
    more than ``acc32_max_drop`` bits of weight resolution (negative: never int32).
    """
    qmax = 127 if bits == 8 else 32767
    row_max = np.abs(w).max(axis=1)
    # A row whose weights are negligible beside its bias is quantised as a row of zeros: weight
    # decay leaves the weights of a unit it has switched off at 1e-300 and below, where
    # row_max / qmax would underflow or put the bias beyond any accumulator, while what they
    # add is below 2^-30 of the bias. Its scale is then free: the largest of the other rows',
    # so its multiplier needs no smaller shift than theirs (int32 layers keep shift 32, the
    # Cortex-M4's one-instruction requantisation).
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        native = in_scale * row_max / qmax
        negligible = (native == 0) | (np.abs(b) / np.where(native > 0, native, 1.0) >= 2.0**60)
    w_scale = _row_weight_scales(row_max, negligible, qmax)
    wq, bq, bound, bound32 = _int_weights(w, b, in_scale, w_scale, qmax, relu_inputs)
    acc32_free = bool(bound32.max() <= SAT32)
    acc32, drop = False, 0.0
    if acc32_max_drop >= 0.0:
        if acc32_free:
            acc32 = True
        else:
            scale32 = _acc32_scale(w, b, in_scale, w_scale, relu_inputs)
            row_drop = np.log2(scale32 / w_scale)
            # A row that would cost more weight bits than allowed, but whose weights can move
            # its output by at most FAINT_ROW_LSB output units for any int16 input, is
            # quantised as a row of zeros (its bias stays) rather than taking the whole
            # layer to int64: weight decay leaves such units small but not switched off. The
            # change is within error_bounds, which compares with the float weights.
            reach = (np.abs(w).sum(axis=1) * SAT16 * in_scale
                     * np.abs(np.broadcast_to(out_ratio, row_drop.shape)))
            faint = (row_drop > acc32_max_drop) & (reach <= FAINT_ROW_LSB) & ~negligible
            if faint.any() and not np.all(negligible | faint):
                negligible = negligible | faint
                w = np.where(faint[:, None], 0.0, w)
                w_scale = _row_weight_scales(row_max, negligible, qmax)
                wq, bq, bound, bound32 = _int_weights(w, b, in_scale, w_scale, qmax, relu_inputs)
                scale32 = _acc32_scale(w, b, in_scale, w_scale, relu_inputs)
            drop = float(np.log2(scale32 / w_scale).max())
            if bound32.max() <= SAT32:
                acc32, drop = True, 0.0
            elif drop <= acc32_max_drop:
                wq, bq, bound, bound32 = _int_weights(w, b, in_scale, scale32, qmax, relu_inputs)
                if bound32.max() > SAT32:  # cannot happen by _acc32_scale's slack; never trust it
                    raise AssertionError("int32 weight scales do not meet the bound")
                w_scale, acc32 = scale32, True
            else:
                drop = 0.0
    acc_scale = in_scale * w_scale
    limits = np.minimum(2**MULT_BITS, PRODUCT_LIMIT // np.maximum(bound, 1))
    # int32 layers requantise with shift 32 when the multipliers allow it: the DSP build then
    # takes the rounded high word of acc * mult in one SMMULR (exactly rshift_round(., 32)).
    # Fewer multiplier bits cost at most |acc| / 2^33 <= 1/4 output LSB.
    shift, mult = choose_shift(acc_scale * out_ratio, limits, max_shift=32 if acc32 else 62)
    info = {"in_scale": in_scale, "w_scale_max": float(w_scale.max()),
            "acc_bound": int(bound.max()), "acc_bound_log2": round(math.log2(max(int(bound.max()), 1)), 2),
            "acc32_safe": acc32_free, "acc32": acc32, "acc32_weight_bits_dropped": round(drop, 3),
            "acc32_bound": int(bound32.max()),
            "product_bound_log2": round(math.log2(max(int(max(int(x) * abs(int(m)) for x, m in zip(bound, mult))), 1)), 2),
            "mult_min_abs": int(np.abs(mult).min()), "shift": shift}
    info["_scales"] = {"w_scale": w_scale, "in_scale": in_scale, "out_ratio": np.asarray(out_ratio, dtype=np.float64) * np.ones(w.shape[0])}
    return wq, bq, mult, shift, info


def even_hidden_widths(weights: Sequence[np.ndarray], biases: Sequence[np.ndarray]
                       ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The layers with every hidden width made even by a unit of zeros.

    The Cortex-M4 DSP kernels take rows and inputs in pairs of int16: an odd hidden width
    sends its layer and the layer it feeds to the unpaired path (a 35-25-10 net took more
    instructions than a 70-50-20 one). The added unit outputs ReLU(0) = 0 and is read with
    weight 0, so every output is the same number.
    """
    ws = [np.asarray(w, dtype=np.float64) for w in weights]
    bs = [np.asarray(b, dtype=np.float64) for b in biases]
    for i in range(len(ws) - 1):
        if ws[i].shape[0] % 2:
            ws[i] = np.vstack([ws[i], np.zeros((1, ws[i].shape[1]))])
            bs[i] = np.append(bs[i], 0.0)
            ws[i + 1] = np.hstack([ws[i + 1], np.zeros((ws[i + 1].shape[0], 1))])
    return ws, bs


def quantize_memory(memory: artifact.Memory, z_frac: int) -> dict[str, Any]:
    """The memory's integers: the load signal's weights as multipliers and a shift (u keeps
    the Q(z_frac) of z), every kind's parameters as they are, a value in standardised units
    (a play half-width) in Q(z_frac)."""
    mem_shift, mem_mult = choose_shift(memory.weights) if any(memory.weights) else (1, np.zeros(4))
    return {"mem_mult": mem_mult, "mem_shift": mem_shift, "loc_shift": memory.loc_shift,
            **memory.params(lambda v: min(SAT16, int(round(v * 2.0**z_frac))))}


def quantize_input_range(model: artifact.HierarchicalModel, z_frac: int) -> dict[str, np.ndarray]:
    """``in_lo``/``in_hi``: the float model's input range in Q(z_frac), rounded outwards (a
    value the float model accepts is never flagged), +-32767 where it has none."""
    n = contract.LIMIT["MAX_INPUTS"]
    lo, hi = np.full(n, -SAT16, dtype=np.int64), np.full(n, SAT16, dtype=np.int64)
    if model.input_range is not None:
        nf = model.preprocess.n_features
        scale = 2.0 ** z_frac
        lo[:nf] = np.clip(np.floor(model.input_range[0] * scale), -SAT16, SAT16)
        hi[:nf] = np.clip(np.ceil(model.input_range[1] * scale), -SAT16, SAT16)
    return {"in_lo": lo, "in_hi": hi}


def quantize_creep(pre: artifact.Preprocess) -> dict[str, int]:
    """The creep inverse's integers (fbg_model.creep_q15, creep_shift): ``creep_q15 =
    round(q * 2^15)`` of its gain :attr:`fbgforce.model.artifact.Preprocess.creep_gain`; a gain that
    rounds to 0 turns it off (shift 0 with it)."""
    q15 = int(round(pre.creep_gain * 2.0**15))
    return {"creep_q15": q15, "creep_shift": pre.creep_shift if q15 else 0}


def quantize_in_use(in_use: artifact.InUse, z_mult: np.ndarray, z_shift: int) -> dict[str, Any]:
    """The decision's and the tracker's integers (fbg_model.contact_*, track_*).

    The decision's CUSUM rise: :func:`quantize_cusum`.

    The creep magnitude becomes ``track_creep_q15 = round(track_creep * 2^15)``; a magnitude
    that rounds to 0 turns the creep term off (shift 0 with it). The settled-hold gain
    likewise becomes ``hold_gain_q15 = round(hold_gain * 2^15)`` (0 turns the stage off, its
    other fields 0 with it), its band ``hold_band_mN`` and ``hold_band_q15``.

    The tracker's gain turns a block's sum of ``z - z0`` (Q(z_frac) units, whose fm value is
    ``2^z_shift / z_mult``) into fm in Q(TRACK_FRAC), divided by its time constant
    ``2^track_shift``: ``round(2^(TRACK_FRAC + z_shift - track_shift) / z_mult)``, exact in
    Python integers.
    """
    gain = np.zeros(artifact.N_STRAIN, dtype=np.int64)
    if in_use.track_shift:
        for c, mult in enumerate(int(v) for v in z_mult):
            if mult == 0:
                continue
            g = round(Fraction(2) ** (contract.LIMIT["TRACK_FRAC"] + z_shift - in_use.track_shift)
                      / mult)
            if abs(g) > SAT32:
                raise InputError(f"tracker gain of channel {c + 1} does not fit int32 (a time "
                                 "constant this short for inputs this coarse)", column="track_shift")
            gain[c] = g
    creep_q15 = int(round(in_use.track_creep * 2.0**15))
    return {"contact_on_q8": int(round(in_use.contact_on_margin * 256.0)),
            "contact_off_q8": int(round(in_use.contact_off_margin * 256.0)),
            "contact_rise_n": in_use.contact_rise_samples, "track_shift": in_use.track_shift,
            "track_settle": in_use.track_settle, "track_gain": gain,
            "track_step_max_fm": min(SAT32, int(round(in_use.track_step_max_pm * 1000.0))),
            "track_limit_fm": int(round(in_use.track_limit_pm * 1000.0)),
            "track_creep_q15": creep_q15,
            "track_creep_shift": in_use.track_creep_shift if creep_q15 else 0,
            **quantize_hold(in_use), **quantize_cusum(in_use)}


def quantize_cusum(in_use: artifact.InUse) -> dict[str, int]:
    """The decision's CUSUM rise in Q8 margin units (fbg_model.contact_cusum_*): each value
    ``round(v * 256)``, clamped to the contract's ``MAX_CUSUM_Q8``; a threshold that would round
    to 0 stays on at 1 (the float model has it on). All 0 when the CUSUM is off."""
    if not in_use.contact_cusum_h:
        return {f.name: 0 for f in contract.PARAMS if f.name.startswith("contact_cusum_")}
    top = contract.LIMIT["MAX_CUSUM_Q8"]

    def q8(v: float) -> int:
        return int(np.clip(round(v * 256.0), -top, top))
    return {"contact_cusum_h_q8": max(1, q8(in_use.contact_cusum_h)),
            "contact_cusum_k_q8": q8(in_use.contact_cusum_k),
            "contact_cusum_lo_q8": q8(in_use.contact_cusum_lo),
            "contact_cusum_hi_q8": q8(in_use.contact_cusum_hi)}


def quantize_hold(in_use: artifact.InUse) -> dict[str, int]:
    """The settled-hold gain's integers (fbg_model.hold_*), all 0 when its gain rounds to 0."""
    gain_q15 = int(round(in_use.hold_gain * 2.0**15))
    if not gain_q15:
        return {f.name: 0 for f in contract.PARAMS if f.name.startswith("hold_")}
    return {"hold_gain_q15": gain_q15, "hold_settle": in_use.hold_settle,
            "hold_band_mN": min(SAT32, int(round(in_use.hold_band_N * 1000.0))),
            "hold_band_q15": int(round(in_use.hold_band_frac * 2.0**15)),
            "hold_shift": in_use.hold_shift, "hold_ramp_shift": in_use.hold_ramp_shift}


def quantize(model: artifact.HierarchicalModel, calib: Calibration, *, bits: int = 16,
             jump_nm: float = DEFAULT_JUMP_NM, overload_N: float | None = None,
             stuck_samples: int | None = None, acc32_max_drop: float = ACC32_MAX_DROP,
             even_widths: bool = True) -> tuple[QModel, dict[str, Any]]:
    """Quantise ``model`` with scales from ``calib``.

    Parameters
    ----------
    bits
        Weight width of the nets: 16 (default) or 8. Activations are always int16.
    jump_nm
        Sensor-fault jump threshold (raised to twice the largest per-sample step seen in the
        calibration recordings, so that normal data never trips it).
    overload_N
        FBG_STATUS_OVERLOAD threshold; default: the largest force of the calibration data,
        true (if known) or as the float model estimates it on its contact samples.
    stuck_samples
        Stuck-peak rule: SENSOR_FAULT after this many identical consecutive values of a
        channel (0 = off). Default: 4x the longest such run in the calibration data, at least
        25 (25 ms at 1 kHz); off if the calibration data repeats a value for 1000 samples or
        more (noise-free data, where repetition is normal).
    acc32_max_drop
        int32 accumulators: a layer whose proven worst case does not fit int32 as quantised
        gets coarser weight scales on the rows that need it if no row loses more than this
        many bits of weight resolution; otherwise it keeps int64. Negative: int64 everywhere.
    even_widths
        Pad odd hidden widths with a unit of zeros (:func:`even_hidden_widths`; the outputs
        are the same numbers). False keeps the model's widths, which the runtime also runs.

    Returns
    -------
    (QModel, report)
        The report holds the scales and the accumulator bounds (docs/fixed-point.md).
    """
    if bits not in (8, 16):
        raise InputError(f"--bits must be 16 or 8, not {bits}", column="--bits")
    pre = model.preprocess
    taps, tap_q = quantize_taps(pre)

    u = calib.z[:, :artifact.N_STRAIN] @ np.asarray(pre.memory.weights) if pre.memory.n_states else calib.f[:0]
    # The location averages' input r = z - z_rest (and so the averages, which stay within its
    # range) must fit too, but without the headroom of z: r differs from z by the rest value
    # |z_rest|, small beside the range of z, and taking it as is would cost every input a bit
    # whenever it crosses a power of two. Beyond the calibration range it saturates (SATURATED).
    r = calib.z[:, :artifact.N_STRAIN] - pre.z_rest if pre.memory.n_loc else calib.f[:0]
    zmax = float(max(np.abs(calib.z[:, :pre.n_features]).max(initial=0.0),
                     np.abs(calib.f).max(initial=0.0), np.abs(u).max(initial=0.0),
                     np.abs(r).max(initial=0.0) / Z_HEADROOM, 1e-6))
    z_frac = int(min(14, max(0, math.floor(math.log2(SAT16 / (Z_HEADROOM * zmax))))))
    zs = 2.0**-z_frac

    tc = np.round(pre.temp_coeff * 2.0**TEMP_COEFF_SHIFT)
    if np.any(np.abs(tc) > SAT32):
        raise InputError("temperature coefficient beyond +-128 cannot be represented",
                         column="temp_coeff")
    mean_fm = np.round(pre.input_mean * 1000.0)
    if np.any(np.abs(mean_fm) > SAT32):
        raise InputError("input_mean beyond +-2 ms of pm cannot be represented", column="input_mean")
    z_shift, z_mult = choose_shift(2.0**z_frac / (1000.0 * pre.input_std))
    fq_shift, fq_mult = choose_shift([2.0**z_frac / (1000.0 * model.force_scale)])

    nets: list[list[QLayer]] = []
    report_nets: dict[str, list[dict[str, Any]]] = {}
    loc_in = floatref.location_inputs(calib.z, calib.contact, calib.f, pre.memory.n_loc)
    zf = calib.z[:, :pre.n_features]
    inputs = {"contact": zf, "force": zf, "location": loc_in}
    for name in NET_NAMES:
        net = model.nets[name]
        x = inputs[name]
        in_scale = zs
        layers, infos = [], []
        weights, biases = (even_hidden_widths(net.weights, net.biases) if even_widths
                           else (net.weights, net.biases))
        for i, (w, b) in enumerate(zip(weights, biases)):
            last = i == len(weights) - 1
            if name == "contact" and last:
                # Two logits -> one margin row: contact iff margin > 0, exactly the float rule.
                w = (w[1] - w[0])[None, :]
                b = np.array([b[1] - b[0]])
            a = x @ w.T + b
            if not last:
                a = np.maximum(a, 0.0)
                amax = float(a.max(initial=0.0))
                out_scale = (ACT_HEADROOM * amax / SAT16) if amax > 0 else 1.0 / SAT16
                ratio = np.full(w.shape[0], 1.0 / out_scale)
            elif name == "contact":
                out_scale, ratio = 1.0 / 256.0, np.array([256.0])
            elif name == "force":
                out_scale, ratio = 1e-3, np.array([1000.0 * model.force_scale])
            else:
                out_scale, ratio = 1e-3, 1000.0 * model.xy_scale
            wq, bq, mult, shift, info = _quantize_layer(w, b, in_scale, ratio, bits, acc32_max_drop,
                                                        relu_inputs=i > 0)
            info.update({"shape": [int(w.shape[0]), int(w.shape[1])], "w_bits": bits,
                         "out_scale": out_scale, "calib_max_abs": float(np.abs(a).max(initial=0.0))})
            scales = info.pop("_scales")
            scales["w_float"], scales["b_float"] = w, b
            layers.append(QLayer(wq, bits, bq, mult, shift, info, scales, acc32=info["acc32"]))
            infos.append(info)
            x, in_scale = a, out_scale
        nets.append(layers)
        report_nets[name] = infos

    if overload_N is None:
        # The largest force of the calibration data, true or estimated, plus OVERLOAD_MARGIN,
        # so that (like the load proxy's threshold) no calibration sample trips OVERLOAD: a net
        # may read a little above the largest true force at the peak of the strongest press,
        # and the fixed-point estimate a little above the float one.
        est = calib.force_N[calib.contact] if calib.contact.any() else calib.force_N
        known = [] if calib.true_force_N is None else [calib.true_force_N]
        vals = np.concatenate([np.ravel(v) for v in [est, *known]]) if np.size(est) or known else []
        overload_N = float(np.nanmax(vals)) * OVERLOAD_MARGIN if np.size(vals) else 70.0
    jump_fm = int(round(max(jump_nm * 1e6, 2.0 * calib.max_step_fm)))
    load_coeff, load_shift, load_max_mN, load_info = fit_load_proxy(model, calib)
    if stuck_samples is None:
        stuck_samples = 0 if calib.max_same_run >= STUCK_OFF_RUN else max(STUCK_MIN, 4 * calib.max_same_run)
    if not 0 <= stuck_samples <= 0xFFFF:
        raise InputError("must be 0 (off) .. 65535", column="--stuck-samples")
    q = QModel(
        baseline_fm=np.round(model.baseline_nm * 1e6), jump_max_fm=min(jump_fm, SAT32),
        temp_coeff_q24=tc, taps=taps, tap_q=tap_q, mean_fm=mean_fm, z_mult=z_mult,
        z_shift=z_shift, z_frac=z_frac, fq_mult=int(fq_mult[0]), fq_shift=fq_shift,
        force_offset_mN=int(round(model.force_offset * 1000.0)),
        xy_offset_um=np.round(model.xy_offset * 1000.0), overload_mN=int(round(overload_N * 1000.0)),
        nets=nets, load_coeff=load_coeff, load_shift=load_shift, load_max_mN=load_max_mN,
        stuck_max=stuck_samples, ref_shift=pre.ref_shift, **quantize_creep(pre),
        **quantize_memory(pre.memory, z_frac),
        **quantize_in_use(model.in_use, z_mult, z_shift), **quantize_input_range(model, z_frac))
    try:
        q.check()
    except ValueError as exc:
        raise InputError(f"model cannot be quantised: {exc}") from exc
    fir_bound = (2**31 - 1) * int(np.abs(taps).sum())
    bounds = error_bounds(model, q, calib)
    report = {
        "bits": bits,
        "calibration": {"samples": calib.samples, "max_abs_input": zmax,
                        "max_step_nm": calib.max_step_fm * 1e-6},
        "input": {"z_frac": z_frac, "z_shift": z_shift, "z_mult": z_mult.tolist(),
                  "mean_fm": q.mean_fm.tolist(), "temp_coeff_q24": q.temp_coeff_q24.tolist(),
                  "fq_mult": q.fq_mult, "fq_shift": fq_shift,
                  "product_bound_log2": round(math.log2((2**31 - 1) * 2**MULT_BITS), 2)},
        "fir": {"n_taps": int(taps.size), "tap_q": tap_q, "taps_sum": int(taps.sum()),
                "acc_bound": fir_bound, "acc_bound_log2": round(math.log2(fir_bound), 2),
                "acc32_safe": fir_bound <= SAT32},
        "nets": report_nets,
        "error_bounds": bounds,
        "outputs": {"force_offset_mN": q.force_offset_mN, "xy_offset_um": q.xy_offset_um.tolist(),
                    "overload_mN": q.overload_mN, "jump_max_fm": q.jump_max_fm,
                    "stuck_max": q.stuck_max, "calib_longest_same_run": calib.max_same_run},
        "load_proxy": load_info,
    }
    return q, report


def _memory_errors(q: QModel, memory: artifact.Memory, z: np.ndarray, e_z: np.ndarray, zr: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The error bounds of :func:`error_bounds` carried into the memory: the contact and force
    nets' inputs (``e_z`` of the standardised channels ``z`` (n, 4), then one column per memory
    feature) and the location averages' (n, 4 or 0); ``zr`` is the ideal standardisation
    ratio in Q(z_frac) per fm."""
    # The load signal u = z . weights carries the inputs' errors through the weights, the
    # multipliers' residue and its rounding (half an LSB). A memory state is a weighted mean
    # (or a clamp) of past values of u, so its error is at most the largest error of u plus its
    # own rounding (one LSB, the average's rounding residues summing to less than that); a
    # feature is the difference of the two, times its gain; the float play width is rounded to
    # Q(z_frac) too (half an LSB).
    lsb = 2.0**-q.z_frac
    if q.n_memory:
        wts = np.asarray(memory.weights)
        wq = q.mem_mult / 2.0**q.mem_shift
        e_u = e_z @ np.abs(wts) + np.abs(z) @ np.abs(wq - wts) + 0.5 * lsb
        gains = np.concatenate([getattr(q, k.field(k.gain))[:getattr(q, k.count_field)]
                                for k in contract.MEMORY_KINDS])
        e_mem = [((e_u + e_u.max() + 1.5 * lsb) * 2.0**g)[:, None] for g in gains]
        e_z = np.concatenate([e_z, *e_mem], axis=1)
    # Location averages: r = z - z0 carries z's error and z0's (the rounded mean, the
    # multiplier's residue, the rounding to Q(z_frac)); an average is a weighted mean of past
    # r, so its error is at most the largest error of r plus its own rounding, as above.
    e_loc = np.zeros((e_z.shape[0], 0))
    if q.n_loc:
        mean_fm = q.mean_fm.astype(np.float64)
        e_z0 = (0.5 * zr + np.abs(mean_fm) * np.abs(q.z_mult / 2.0**q.z_shift - zr) + 0.5) / 2.0**q.z_frac
        e_r = e_z[:, :artifact.N_STRAIN] + e_z0
        e_loc = np.broadcast_to(e_r.max(axis=0, initial=0.0) + 1.5 * lsb, e_r.shape)
    return e_z, e_loc


def error_bounds(model: artifact.HierarchicalModel, q: QModel, calib: Calibration) -> dict[str, float]:
    """Error budget of fixed vs float on every calibration sample; the maxima.

    (docs/fixed-point.md, "Error bounds".) Each rounding of the integer pipeline injects a
    bounded error (``inj``); the nets are piecewise linear, so, at a sample whose ReLU pattern
    the quantised net shares, the output error is at most ``sum_l |g_l| . inj_l`` with ``g_l``
    the signed gradient of the output with respect to layer l's activations at that sample
    (a first-order bound, exact for the linear piece; it can fail only where a unit sits
    within its error of zero, i.e. near a kink). Per layer, row r::

        inj[r] = sum_j |W[r,j] - Wq[r,j]| |x[j]| + |b[r] - bq[r]|
                 + out_scale * (|acc[r]| * |mult[r] / 2^shift - R[r]| + 1/2)

    The input error (proven, per sample): conversion to fm (0.5 fm on wl and baseline), the
    temperature reference's average (1 fm), the Q24 coefficient, Q15 taps (their sum is
    exact to 2^-16, so the tap residue acts only on the variation of the signal within the
    filter window), the standardisation multiplier and the Q(z_frac) rounding.
    """
    pre = model.preprocess
    taps_f = np.array([1.0]) if pre.filter_kind == "none" else pre.taps
    dtaps = taps_f - q.taps / 2.0**q.tap_q
    comp_abs = calib.comp_abs_pm * 1000.0
    comp_var = calib.comp_var_pm * 1000.0
    tc_err = np.abs(pre.temp_coeff - q.temp_coeff_q24 / 2.0**TEMP_COEFF_SHIFT)
    # The reference's average adds at most 1 fm to the reference (its rounding, proven in
    # docs/fixed-point.md), which the coefficient scales.
    e_ref = 2.0 if q.ref_shift else 1.0
    e_comp = 1.0 + np.abs(pre.temp_coeff) * e_ref + 0.5 + tc_err * comp_abs.max(initial=0.0)
    if q.creep_q15:
        # The creep inverse (docs/fixed-point.md, "creep inverse"): an input error D becomes at
        # most (1 + 2q) D + 1.5 q + 1/2 fm, plus the Q15 gain's error times |c - L|, which is
        # at most |e - L| <= 2 max|e|, twice the largest shift the filter reads (comp_abs).
        gain = pre.creep_gain
        e_comp = ((1.0 + 2.0 * gain) * e_comp + 1.5 * gain + 0.5
                  + abs(gain - q.creep_q15 / 2.0**15) * 2.0 * comp_abs.max(initial=0.0))
    e_filt = (e_comp * np.abs(taps_f).sum() + np.abs(dtaps).sum() * comp_var
              + abs(dtaps.sum()) * comp_abs + 0.5)
    zr = 2.0**q.z_frac / (1000.0 * pre.input_std)
    d = np.abs(calib.z[:, :artifact.N_STRAIN]) * 1000.0 * pre.input_std + e_filt + 0.5
    e_z = ((e_filt + 0.5) * zr + d * np.abs(q.z_mult / 2.0**q.z_shift - zr) + 0.5) / 2.0**q.z_frac
    e_z, e_loc = _memory_errors(q, pre.memory, calib.z[:, :artifact.N_STRAIN], e_z, zr)
    def net_err(layers: list[QLayer], x: np.ndarray, e_in: np.ndarray, row: int) -> np.ndarray:
        """Per-sample bound of output ``row`` in output integer units."""
        acts, masks, injs = [x], [], []
        for i, layer in enumerate(layers):
            sc = layer.scales
            w, b = sc["w_float"], sc["b_float"]
            acc_scale = sc["in_scale"] * sc["w_scale"]
            dw = np.abs(w - layer.w * sc["w_scale"][:, None])
            a = acts[-1] @ w.T + b
            ratio_err = np.abs(layer.mult / 2.0**layer.shift - acc_scale * sc["out_ratio"])
            out_unit = 1.0 / np.abs(sc["out_ratio"])
            injs.append(np.abs(acts[-1]) @ dw.T + np.abs(b - layer.bias * acc_scale)
                        + out_unit * (np.abs(a) / acc_scale * ratio_err + 0.5))
            if i < len(layers) - 1:
                masks.append(a > 0.0)
                acts.append(np.maximum(a, 0.0))
        unit = 1.0 / abs(layers[-1].scales["out_ratio"][row])
        total = injs[-1][:, row] / unit
        g = np.broadcast_to(layers[-1].scales["w_float"][row], (x.shape[0], layers[-1].n_in))
        for i in range(len(layers) - 2, -1, -1):
            g = g * masks[i]                       # gradient w.r.t. layer i's pre-activation
            total = total + (np.abs(g) * injs[i]).sum(axis=1) / unit
            g = g @ layers[i].scales["w_float"]
        return total + (np.abs(g) * e_in).sum(axis=1) / unit

    z = calib.z[:, :q.n_features]
    e_margin = net_err(q.nets[0], z, e_z, 0) / 256.0
    out = {"contact_margin": float(e_margin.max(initial=0.0)), "input_z": float(e_z.max(initial=0.0))}
    c = calib.contact
    if c.any():
        zc, ezc, xc = z[c], e_z[c], calib.z[c]
        e_force_mN = net_err(q.nets[1], zc, ezc, 0)
        fq_ratio = 2.0**q.z_frac / (1000.0 * model.force_scale)
        force_out = np.abs(calib.f[c]) * 1000.0 * abs(model.force_scale) + e_force_mN
        e_fq = ((e_force_mN + 0.5) * abs(fq_ratio) + force_out * abs(q.fq_mult / 2.0**q.fq_shift - fq_ratio)
                + 0.5) / 2.0**q.z_frac
        loc_x = floatref.location_inputs(xc, np.ones(zc.shape[0]), calib.f[c], q.n_loc)
        loc_e = np.column_stack([ezc[:, :artifact.N_STRAIN], np.zeros(zc.shape[0]), e_fq, e_loc[c]])
        out.update({"force_N": float((e_force_mN.max() + 0.5) / 1000.0),
                    "x_mm": float((net_err(q.nets[2], loc_x, loc_e, 0).max() + 0.5) / 1000.0),
                    "y_mm": float((net_err(q.nets[2], loc_x, loc_e, 1).max() + 0.5) / 1000.0)})
    return out
