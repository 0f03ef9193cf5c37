"""The fixed-point model's type: what a ``model.fbgm`` blob holds and the checks it must pass.

:class:`QModel` is ``fbg_model`` of runtime_c/include/fbgforce.h and :class:`QLayer` its
``fbg_layer``: the integers the C runtime runs, whoever made them (the quantiser,
:mod:`fbgforce.export.quantize`; the blob reader, :mod:`fbgforce.export.blob`; the tests' own
hand-made models). :meth:`QModel.check` and :func:`check_layer` apply ``fbg_model_check`` of
runtime_c/src/fbg_model.c rule for rule and in its order, so a model the C runtime would refuse
is refused here with the same ``FBG_ERR_*`` code. The field list of the parameter block is
:data:`fbgforce.contract.PARAMS`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, make_dataclass
from functools import partial
from typing import Any

import numpy as np

from fbgforce import contract

SAT16 = contract.SAT16
SAT32 = contract.SAT32
MAX_WIDTH = contract.LIMIT["MAX_WIDTH"]
NET_NAMES = contract.NET_NAMES
NET_OUTPUTS = {net.name: net.fixed_outputs for net in contract.NETS}

#: |bias| limit of fbg_model_check, so that the accumulator bound cannot overflow int64 itself.
BIAS_LIMIT = 2**60


class ModelCheckError(ValueError):
    """A model the C runtime refuses: ``code`` is the ``FBG_ERR_*`` name it returns."""

    def __init__(self, code: str, reason: str) -> None:
        self.code = code
        super().__init__(reason)


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
    #: (n_out,) = output integer units per real accumulator unit; used by
    #: :func:`fbgforce.export.quantize.error_bounds`.
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
        """(4,) ``z0``, the standardisation of a zero filtered shift as fbg_init (fbg_fixed.c) computes it,
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
