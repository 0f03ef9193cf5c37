"""Post-training quantisation of a float model into the fixed-point model of the C runtime
(:class:`fbgforce.export.qmodel.QModel`).

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
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from fbgforce import contract, samples
from fbgforce.model import artifact, floatref
from fbgforce.errors import InputError
from fbgforce.export.qmodel import NET_NAMES, SAT16, SAT32, QLayer, QModel
from fbgforce.units import nm_to_fm

TEMP_COEFF_SHIFT = contract.LIMIT["TEMP_COEFF_SHIFT"]

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
#: Stuck-peak rule defaults: at least this many identical samples, and off when the
#: calibration data itself repeats values this long (noise-free data).
STUCK_MIN = 25
STUCK_OFF_RUN = 1000
#: Default for the sensor-fault jump rule, nm per sample.
DEFAULT_JUMP_NM = contract.DEFAULT_JUMP_NM
#: Default OVERLOAD threshold: this factor above the largest calibration force.
OVERLOAD_MARGIN = 1.02


# --------------------------------------------------------------------------------------------
# Calibration: the float pipeline on recordings, what every scale is chosen from
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# Quantisation: quantize() and its steps, in the order it takes them
# --------------------------------------------------------------------------------------------

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
    z_frac, zmax = choose_input_format(pre, calib)
    front = quantize_front(model, z_frac)
    nets, report_nets = quantize_nets(model, calib, z_frac, bits, acc32_max_drop, even_widths)
    overload_mN = choose_overload_mN(calib, overload_N)
    load_coeff, load_shift, load_max_mN, load_info = fit_load_proxy(model, calib)
    faults = choose_fault_rules(calib, jump_nm, stuck_samples)
    q = QModel(
        baseline_fm=np.round(model.baseline_nm * 1e6), taps=taps, tap_q=tap_q, z_frac=z_frac,
        force_offset_mN=int(round(model.force_offset * 1000.0)),
        xy_offset_um=np.round(model.xy_offset * 1000.0), overload_mN=overload_mN,
        nets=nets, load_coeff=load_coeff, load_shift=load_shift, load_max_mN=load_max_mN,
        ref_shift=pre.ref_shift, **front, **faults, **quantize_creep(pre),
        **quantize_memory(pre.memory, z_frac),
        **quantize_in_use(model.in_use, front["z_mult"], front["z_shift"]),
        **quantize_input_range(model, z_frac))
    try:
        q.check()
    except ValueError as exc:
        raise InputError(f"model cannot be quantised: {exc}") from exc
    return q, quantize_report(q, calib, bits, zmax, report_nets, error_bounds(model, q, calib),
                              load_info)


def choose_input_format(pre: artifact.Preprocess, calib: Calibration) -> tuple[int, float]:
    """``z_frac``, the one Q format of every net input, and the largest calibration input it
    was chosen from.

    The standardised channels z, the memory features, the load signal u, the location
    averages' input and the force net's output that feeds the location net share Q(z_frac):
    a power of two makes the contact flag exact (``1 << z_frac``) and lets the location net's
    first layer treat its inputs alike. It is the finest format (at most 14 fractional bits)
    in which Z_HEADROOM times the largest of them fits int16.
    """
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
    return z_frac, zmax


def quantize_front(model: artifact.HierarchicalModel, z_frac: int) -> dict[str, Any]:
    """The integers of the front end and of the standardisation (``QModel`` fields):
    ``temp_coeff_q24``, ``mean_fm``, ``z_mult``/``z_shift`` (filtered fm to Q(z_frac)) and
    ``fq_mult``/``fq_shift`` (the force net's output to Q(z_frac), for the location net).

    Each is its float value at the fixed scale the runtime reads it with. A coefficient or
    mean that does not fit int32 is refused (InputError) rather than clamped: the runtime
    would compute another model.
    """
    pre = model.preprocess
    tc = np.round(pre.temp_coeff * 2.0**TEMP_COEFF_SHIFT)
    if np.any(np.abs(tc) > SAT32):
        raise InputError("temperature coefficient beyond +-128 cannot be represented",
                         column="temp_coeff")
    mean_fm = np.round(pre.input_mean * 1000.0)
    if np.any(np.abs(mean_fm) > SAT32):
        raise InputError("input_mean beyond +-2 ms of pm cannot be represented", column="input_mean")
    z_shift, z_mult = choose_shift(2.0**z_frac / (1000.0 * pre.input_std))
    fq_shift, fq_mult = choose_shift([2.0**z_frac / (1000.0 * model.force_scale)])
    return {"temp_coeff_q24": tc, "mean_fm": mean_fm, "z_mult": z_mult, "z_shift": z_shift,
            "fq_mult": int(fq_mult[0]), "fq_shift": fq_shift}


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


def quantize_nets(model: artifact.HierarchicalModel, calib: Calibration, z_frac: int, bits: int,
                  acc32_max_drop: float, even_widths: bool
                  ) -> tuple[list[list[QLayer]], dict[str, list[dict[str, Any]]]]:
    """The three nets' layers in the runtime's order (contact, force, location) and each
    net's report of its layers.

    Every net reads its inputs in Q(z_frac), so its first layer's input scale is
    ``2^-z_frac``; the calibration activations each layer is scaled on are the float nets' on
    the calibration samples: z and the memory features for the contact and force nets, the
    location net's own input (:func:`fbgforce.model.floatref.location_inputs`) for the location net.
    """
    pre = model.preprocess
    zf = calib.z[:, :pre.n_features]
    inputs = {"contact": zf, "force": zf,
              "location": floatref.location_inputs(calib.z, calib.contact, calib.f, pre.memory.n_loc)}
    nets: list[list[QLayer]] = []
    report: dict[str, list[dict[str, Any]]] = {}
    for name in NET_NAMES:
        layers, report[name] = quantize_net(model, name, inputs[name], 2.0**-z_frac, bits,
                                            acc32_max_drop, even_widths)
        nets.append(layers)
    return nets, report


def quantize_net(model: artifact.HierarchicalModel, name: str, x: np.ndarray, in_scale: float,
                 bits: int, acc32_max_drop: float, even_widths: bool
                 ) -> tuple[list[QLayer], list[dict[str, Any]]]:
    """One net's quantised layers and their reports, layer by layer: each layer's output
    scale (:func:`layer_output_scale`) is the next one's input scale, and its float
    activations on ``x`` the next one's calibration input.

    The contact net's two logits become one margin row (logit 1 - logit 0): the runtime
    decides contact iff the margin is positive, exactly the float rule, with one row fewer.
    """
    layers, infos = [], []
    net = model.nets[name]
    weights, biases = (even_hidden_widths(net.weights, net.biases) if even_widths
                       else (net.weights, net.biases))
    for i, (w, b) in enumerate(zip(weights, biases)):
        last = i == len(weights) - 1
        if name == "contact" and last:
            w = (w[1] - w[0])[None, :]
            b = np.array([b[1] - b[0]])
        a = x @ w.T + b
        if not last:
            a = np.maximum(a, 0.0)
        out_scale, ratio = layer_output_scale(model, name, last, a, w.shape[0])
        wq, bq, mult, shift, info = _quantize_layer(w, b, in_scale, ratio, bits, acc32_max_drop,
                                                    relu_inputs=i > 0)
        info.update({"shape": [int(w.shape[0]), int(w.shape[1])], "w_bits": bits,
                     "out_scale": out_scale, "calib_max_abs": float(np.abs(a).max(initial=0.0))})
        scales = info.pop("_scales")
        scales["w_float"], scales["b_float"] = w, b
        layers.append(QLayer(wq, bits, bq, mult, shift, info, scales, acc32=info["acc32"]))
        infos.append(info)
        x, in_scale = a, out_scale
    return layers, infos


def layer_output_scale(model: artifact.HierarchicalModel, name: str, last: bool, a: np.ndarray,
                       n_rows: int) -> tuple[float, np.ndarray]:
    """A layer's output scale (real units per output integer) and ``out_ratio`` per row
    (output integer units per real unit), from its calibration activations ``a``.

    A hidden layer maps ACT_HEADROOM times its largest calibration activation to 32767: int16
    at full resolution over the calibrated range, with room for a press a little beyond it.
    An output layer's integer is fixed by the runtime's outputs: the contact margin in Q8,
    the force in mN, the location in um (the scales of the float model's outputs included).
    """
    if not last:
        amax = float(a.max(initial=0.0))
        out_scale = (ACT_HEADROOM * amax / SAT16) if amax > 0 else 1.0 / SAT16
        return out_scale, np.full(n_rows, 1.0 / out_scale)
    if name == "contact":
        return 1.0 / 256.0, np.array([256.0])
    if name == "force":
        return 1e-3, np.array([1000.0 * model.force_scale])
    return 1e-3, 1000.0 * model.xy_scale


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


def _row_weight_scales(row_max: np.ndarray, zero_rows: np.ndarray, qmax: int) -> np.ndarray:
    """Per-row weight scales ``max|W[r]| / qmax``; a row quantised as zeros takes the largest
    of the other rows' (so its multiplier needs no smaller shift than theirs)."""
    live = row_max[~zero_rows] / qmax
    return np.where(zero_rows, live.max() if live.size else 1.0, row_max / qmax)


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


def choose_overload_mN(calib: Calibration, overload_N: float | None) -> int:
    """``overload_mN``, the FBG_STATUS_OVERLOAD threshold: ``overload_N`` if given, else the
    largest force of the calibration data, true or estimated, plus OVERLOAD_MARGIN.

    The default is chosen so that (like the load proxy's threshold) no calibration sample
    trips OVERLOAD: a net may read a little above the largest true force at the peak of the
    strongest press, and the fixed-point estimate a little above the float one.
    """
    if overload_N is None:
        est = calib.force_N[calib.contact] if calib.contact.any() else calib.force_N
        known = [] if calib.true_force_N is None else [calib.true_force_N]
        vals = np.concatenate([np.ravel(v) for v in [est, *known]]) if np.size(est) or known else []
        overload_N = float(np.nanmax(vals)) * OVERLOAD_MARGIN if np.size(vals) else 70.0
    return int(round(overload_N * 1000.0))


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


def choose_fault_rules(calib: Calibration, jump_nm: float, stuck_samples: int | None
                       ) -> dict[str, int]:
    """The sensor-fault rules' integers (``jump_max_fm``, ``stuck_max``), chosen so that the
    calibration recordings, which are normal data, never trip them.

    The jump threshold is ``jump_nm`` raised to twice the largest per-sample step of the
    calibration recordings. The stuck-peak count defaults to 4x their longest run of
    identical values (at least STUCK_MIN), and to off when they repeat a value STUCK_OFF_RUN
    times (noise-free data, where repetition is normal); it is a uint16 in the runtime.
    """
    jump_fm = int(round(max(jump_nm * 1e6, 2.0 * calib.max_step_fm)))
    if stuck_samples is None:
        stuck_samples = 0 if calib.max_same_run >= STUCK_OFF_RUN else max(STUCK_MIN, 4 * calib.max_same_run)
    if not 0 <= stuck_samples <= 0xFFFF:
        raise InputError("must be 0 (off) .. 65535", column="--stuck-samples")
    return {"jump_max_fm": min(jump_fm, SAT32), "stuck_max": stuck_samples}


def quantize_creep(pre: artifact.Preprocess) -> dict[str, int]:
    """The creep inverse's integers (fbg_model.creep_q15, creep_shift): ``creep_q15 =
    round(q * 2^15)`` of its gain :attr:`fbgforce.model.artifact.Preprocess.creep_gain`; a gain that
    rounds to 0 turns it off (shift 0 with it)."""
    q15 = int(round(pre.creep_gain * 2.0**15))
    return {"creep_q15": q15, "creep_shift": pre.creep_shift if q15 else 0}


def quantize_memory(memory: artifact.Memory, z_frac: int) -> dict[str, Any]:
    """The memory's integers: the load signal's weights as multipliers and a shift (u keeps
    the Q(z_frac) of z), every kind's parameters as they are, a value in standardised units
    (a play half-width) in Q(z_frac)."""
    mem_shift, mem_mult = choose_shift(memory.weights) if any(memory.weights) else (1, np.zeros(4))
    return {"mem_mult": mem_mult, "mem_shift": mem_shift, "loc_shift": memory.loc_shift,
            **memory.params(lambda v: min(SAT16, int(round(v * 2.0**z_frac))))}


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


def quantize_report(q: QModel, calib: Calibration, bits: int, zmax: float,
                    nets: dict[str, list[dict[str, Any]]], bounds: dict[str, float],
                    load_info: dict[str, Any]) -> dict[str, Any]:
    """The export report of a quantised model: the scales it was given, its accumulator
    bounds (the FIR's here, each layer's in ``nets``), its error bounds against the float
    model and the thresholds chosen from the calibration data (docs/fixed-point.md)."""
    fir_bound = (2**31 - 1) * int(np.abs(q.taps).sum())
    return {
        "bits": bits,
        "calibration": {"samples": calib.samples, "max_abs_input": zmax,
                        "max_step_nm": calib.max_step_fm * 1e-6},
        "input": {"z_frac": q.z_frac, "z_shift": q.z_shift, "z_mult": q.z_mult.tolist(),
                  "mean_fm": q.mean_fm.tolist(), "temp_coeff_q24": q.temp_coeff_q24.tolist(),
                  "fq_mult": q.fq_mult, "fq_shift": q.fq_shift,
                  "product_bound_log2": round(math.log2((2**31 - 1) * 2**MULT_BITS), 2)},
        "fir": {"n_taps": int(q.taps.size), "tap_q": q.tap_q, "taps_sum": int(q.taps.sum()),
                "acc_bound": fir_bound, "acc_bound_log2": round(math.log2(fir_bound), 2),
                "acc32_safe": fir_bound <= SAT32},
        "nets": nets,
        "error_bounds": bounds,
        "outputs": {"force_offset_mN": q.force_offset_mN, "xy_offset_um": q.xy_offset_um.tolist(),
                    "overload_mN": q.overload_mN, "jump_max_fm": q.jump_max_fm,
                    "stuck_max": q.stuck_max, "calib_longest_same_run": calib.max_same_run},
        "load_proxy": load_info,
    }


# --------------------------------------------------------------------------------------------
# Error bounds: how far the integers can take an output from the float model
# --------------------------------------------------------------------------------------------

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
    e_z, zr = _standardised_errors(model, q, calib)
    e_z, e_loc = _memory_errors(q, model.preprocess.memory, calib.z[:, :artifact.N_STRAIN], e_z, zr)
    z = calib.z[:, :q.n_features]
    e_margin = _net_errors(q.nets[0], z, e_z, 0) / 256.0
    out = {"contact_margin": float(e_margin.max(initial=0.0)), "input_z": float(e_z.max(initial=0.0))}
    if calib.contact.any():
        out.update(_force_location_errors(model, q, calib, e_z, e_loc))
    return out


def _filter_errors(pre: artifact.Preprocess, q: QModel, calib: Calibration) -> np.ndarray:
    """The error bound of the filtered shifts (n, 4) in fm: the front end's roundings (the
    conversion to fm, the temperature reference's average, the Q24 coefficient, the creep
    inverse) carried through the filter, plus the Q15 taps' residue on the signal the filter
    reads and the filter's own rounding."""
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
    return (e_comp * np.abs(taps_f).sum() + np.abs(dtaps).sum() * comp_var
            + abs(dtaps.sum()) * comp_abs + 0.5)


def _standardised_errors(model: artifact.HierarchicalModel, q: QModel, calib: Calibration
                         ) -> tuple[np.ndarray, np.ndarray]:
    """The error bound of the standardised channels z (n, 4), in standardised units: the
    filtered shifts' (:func:`_filter_errors`) and the mean's rounding through the ideal
    ratio, the multiplier's residue on the shift it scales, and the rounding to Q(z_frac).
    Also returns ``zr``, the ideal standardisation ratio in Q(z_frac) per fm."""
    pre = model.preprocess
    e_filt = _filter_errors(pre, q, calib)
    zr = 2.0**q.z_frac / (1000.0 * pre.input_std)
    d = np.abs(calib.z[:, :artifact.N_STRAIN]) * 1000.0 * pre.input_std + e_filt + 0.5
    e_z = ((e_filt + 0.5) * zr + d * np.abs(q.z_mult / 2.0**q.z_shift - zr) + 0.5) / 2.0**q.z_frac
    return e_z, zr


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


def _force_location_errors(model: artifact.HierarchicalModel, q: QModel, calib: Calibration,
                           e_z: np.ndarray, e_loc: np.ndarray) -> dict[str, float]:
    """The force's and the location's error bounds on the calibration samples decided
    contact (the only ones the runtime computes them on), in N and mm. The location net
    reads the force net's output requantised to Q(z_frac), whose error (the force's, the
    multiplier's residue and the rounding) joins the input errors of z and the location
    averages."""
    c = calib.contact
    z = calib.z[:, :q.n_features]
    zc, ezc, xc = z[c], e_z[c], calib.z[c]
    e_force_mN = _net_errors(q.nets[1], zc, ezc, 0)
    fq_ratio = 2.0**q.z_frac / (1000.0 * model.force_scale)
    force_out = np.abs(calib.f[c]) * 1000.0 * abs(model.force_scale) + e_force_mN
    e_fq = ((e_force_mN + 0.5) * abs(fq_ratio) + force_out * abs(q.fq_mult / 2.0**q.fq_shift - fq_ratio)
            + 0.5) / 2.0**q.z_frac
    loc_x = floatref.location_inputs(xc, np.ones(zc.shape[0]), calib.f[c], q.n_loc)
    loc_e = np.column_stack([ezc[:, :artifact.N_STRAIN], np.zeros(zc.shape[0]), e_fq, e_loc[c]])
    return {"force_N": float((e_force_mN.max() + 0.5) / 1000.0),
            "x_mm": float((_net_errors(q.nets[2], loc_x, loc_e, 0).max() + 0.5) / 1000.0),
            "y_mm": float((_net_errors(q.nets[2], loc_x, loc_e, 1).max() + 0.5) / 1000.0)}


def _net_errors(layers: list[QLayer], x: np.ndarray, e_in: np.ndarray, row: int) -> np.ndarray:
    """Per-sample error bound of output ``row`` of a net, in output integer units: every
    layer's injected error (its weights', bias', multiplier's and rounding's) and the input
    error ``e_in``, each weighted by the gradient of the output at that sample
    (:func:`error_bounds`)."""
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


# --------------------------------------------------------------------------------------------
# A scale as integers: a multiplier and a shift
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
