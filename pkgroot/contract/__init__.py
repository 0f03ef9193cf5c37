"""The runtime contract, defined once: limits, codes, flags, nets, parameter blocks, outputs.

Everything that the C library, the blob and the Python side must agree on is declared here and
nowhere else:

- the limits and fixed-point constants (``LIMITS``), the library version;
- the return codes (``ERRORS``) and the output status flags (``STATUS``);
- the net table (``NETS``): name, inputs, outputs, loss, output scaling;
- the fixed-point model's parameter block (``PARAMS``): C type, count, allowed range and the
  error code a violation gives, in blob order; the float model's (``FLOAT_PARAMS``);
- the blob header and layer-table entry, the output records (``OUTPUT``, ``FLOAT_OUTPUT``);
- the kinds of memory state (``MEMORY_KINDS``: limits, parameters, from which the memory
  fields of both parameter blocks are made) and the caller-owned streaming states of both
  builds (``STATE``, ``FLOAT_STATE``).

``python -m fbgforce.contract --write`` regenerates the derived text
(:mod:`fbgforce.contract.render`): the marked sections of ``runtime_c/include/fbgforce.h``
(declarations, the state structs included), ``runtime_c/src/fbg_contract.c`` and ``.h`` (the
blob parameter decoder, the parameter checker, ``fbg_status_str``, the list of memory states the
front end clears and the dispatch over the memory kinds), ``runtime_c/src/fbgf_contract.c`` (the
float model's memory parameters), the parameter table of ``docs/model-format.md`` and the status
constants of the ROS 2 message ``interrogator/fbgforce_msgs/msg/Contact.msg``. The Python side
(the blob codec in :mod:`fbgforce.export.blob`, the checker in :mod:`fbgforce.export.qmodel`,
the numpy dtypes of :mod:`fbgforce.pybind`) reads the same tables at import.
``tests/test_contract.py`` fails when a generated file is stale.

Python rather than a schema file: every consumer but the C compiler is Python, so a schema would
need a parser and still a Python generator; here the spec is data that the tests, the codecs and
the generator import directly, with no dependency at all (this package's tables import nothing
from fbgforce, so anything may import them).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Callable

#: Library version: the C library (``fbg_version()``), the Python package and the blob's
#: ``writer_version`` field all report this one.
VERSION_STR = "0.2.0"
VERSION = tuple(int(part) for part in VERSION_STR.split("."))
VERSION_CODE = (VERSION[0] << 16) | (VERSION[1] << 8) | VERSION[2]

N_CHANNELS = 5
N_STRAIN = 4


#: Largest exponential-average shift (``FBG_MAX_EMA_SHIFT``) and memory-feature gain shift
#: (``FBG_MAX_MEM_GAIN``): bounds of the memory kinds' parameters below.
MAX_EMA_SHIFT = 15
MAX_MEM_GAIN = 8
SAT16 = 32767
SAT32 = 2**31 - 1


@dataclass(frozen=True)
class MemoryParam:
    """A per-state parameter of a memory kind: one entry per state, ``limit`` entries.

    It is the array field ``<kind>_<name>`` of both parameter blocks (``PARAMS``, in
    ``ctype`` within ``[lo, hi]``; ``FLOAT_PARAMS``, in ``float_ctype``) and the tuple
    ``<kind>_<name>s`` of :class:`fbgforce.model.artifact.Memory`. A ``float_ctype`` of ``"float"`` is
    a value in standardised units: ``float`` in the float build, Q(z_frac) in the fixed one
    (rounded, at most ``hi``), at least ``lo`` and finite in both. ``optional``: a Memory may
    leave it out (every entry 0); the kind's first other parameter counts its states.
    """

    name: str
    ctype: str
    lo: int
    hi: int
    doc: str
    float_ctype: str
    float_doc: str = ""
    optional: bool = False

    @property
    def standardised(self) -> bool:
        """True for a value in standardised units (float in the float build)."""
        return self.float_ctype == "float"


@dataclass(frozen=True)
class MemoryKind:
    """A kind of memory state of the load signal u (docs/fixed-point.md, "memory").

    A model holds up to ``limit`` states of each kind (``FBG_MAX_<NAME>``) and uses ``n_<name>``
    of them, each giving one net input after z. The states are the int32 array ``<name>`` of
    ``fbg_state`` (generated from ``STATE``), in the Q format ``q``; their parameters
    (``params``) are the ``<name>_*`` fields of ``PARAMS`` and ``FLOAT_PARAMS``, generated from
    them. ``noun`` names the states in messages, ``label`` in the teleop ablation's table.
    The update rule itself is written once per engine, reached by the kind's name:
    ``<name>_features`` (fbg_stage_memory.c), ``<name>_features_f`` (fbgf_float.c),
    ``<name>_features_avx2`` (fbg_simd_x86_stages.c) through ``FBG_MEMORY_KINDS``, and the tables
    ``fbgforce.model.floatref.FLOAT_MEMORY`` and ``fbgforce.export.intref.INT_MEMORY``.
    """

    name: str
    limit: int
    doc: str
    q: str
    params: tuple[MemoryParam, ...]
    noun: str
    label: str

    @property
    def count_field(self) -> str:
        """The parameter field counting the states in use: ``n_<name>``."""
        return f"n_{self.name}"

    @property
    def counted_by(self) -> MemoryParam:
        """The parameter whose :class:`fbgforce.model.artifact.Memory` tuple says how many states."""
        return next(p for p in self.params if not p.optional)

    @property
    def gain(self) -> MemoryParam:
        """The feature's gain shift: every kind's feature is (u - state) << gain, which the
        trainer fits and the quantiser's error bound reads."""
        return next(p for p in self.params if p.name == "gain")

    def field(self, param: MemoryParam) -> str:
        """The parameter-block field of ``param``: ``<kind>_<param>``."""
        return f"{self.name}_{param.name}"


_GAIN_DOC = "feature = sat16((u - {state}) << {kind}_gain[k])"
MEMORY_KINDS: tuple[MemoryKind, ...] = (
    MemoryKind("ema", 4, "exponential-average memory states", "Q(z_frac + FBG_EMA_FRAC)", (
        MemoryParam("shift", "uint8_t", 1, MAX_EMA_SHIFT,
                    "state += rshift_round((u << EMA_FRAC) - state, ema_shift[k])", "uint8_t",
                    "state += (u - state) / 2^ema_shift[k]"),
        MemoryParam("gain", "uint8_t", 0, MAX_MEM_GAIN,
                    _GAIN_DOC.format(state="rshift_round(state, EMA_FRAC)", kind="ema"), "uint8_t",
                    optional=True)),
        noun="averages", label="averages"),
    MemoryKind("play", 4, "play-operator memory states", "Q(z_frac)", (
        MemoryParam("gain", "uint8_t", 0, MAX_MEM_GAIN,
                    _GAIN_DOC.format(state="state", kind="play"), "uint8_t", optional=True),
        MemoryParam("width", "int16_t", 0, SAT16,
                    "state = clamp(state, u - play_width[k], u + play_width[k]), Q(z_frac)",
                    "float", "in standardised units")),
        noun="play operators", label="plays"),
)
MEMORY_KIND = {k.name: k for k in MEMORY_KINDS}

#: name -> (value, comment). Emitted as ``#define FBG_<name>``.
LIMITS: dict[str, tuple[int, str]] = {
    "N_CHANNELS": (N_CHANNELS, "wl1..wl4 (strain), wlT (temperature reference)"),
    "N_STRAIN": (N_STRAIN, "strain gratings"),
    "MAX_TAPS": (64, "causal FIR length"),
    "MAX_WIDTH": (128, "widest layer (inputs or outputs) of any net"),
    "MAX_LAYERS": (8, "layers per net"),
    **{f"MAX_{k.name.upper()}": (k.limit, k.doc) for k in MEMORY_KINDS},
    "MAX_INPUTS": (N_STRAIN + sum(k.limit for k in MEMORY_KINDS),
                   "widest net input: z and the memory features"),
    "N_NETS": (3, "contact, force, location (evaluation order)"),
    "WL_MIN_FM": (1_000_000_000, "1000 nm: a peak below this is lost (0, sentinels)"),
    "WL_MAX_FM": (2_000_000_000, "2000 nm: a peak above this is lost"),
    "TEMP_COEFF_SHIFT": (24, "temperature coefficients are Q24"),
    "EMA_FRAC": (15, "fractional bits of the exponential-average states below Q(z_frac)"),
    "MAX_EMA_SHIFT": (MAX_EMA_SHIFT, "largest exponential-average shift (time constant 2^15 samples)"),
    "MAX_MEM_GAIN": (MAX_MEM_GAIN, "largest memory-feature gain shift"),
    "LOAD_COEFF_LIMIT": (1 << 28, "|load_coeff| below this: the load proxy sum fits int64"),
    "TRACK_BLOCK": (64, "samples per update of the at-rest baseline tracker"),
    "TRACK_FRAC": (16, "fractional bits of the tracker's carried baseline correction"),
    "TRACK_LIMIT_MAX_FM": (100_000_000, "largest track_limit_fm (100 nm): a tracked baseline "
                           "stays within 100 nm of its tare"),
    "MAX_REF_SHIFT": (8, "largest shift of the temperature reference's average (time constant "
                      "256 samples): its accumulator stays below 2^39 (docs/fixed-point.md)"),
    "MAX_TRACK_CREEP_Q15": (1 << 14, "largest track_creep_q15 (creep magnitude 0.5): the "
                            "tracker's per-sample term stays below 2^17 (docs/fixed-point.md)"),
    "MAX_CREEP_Q15": ((1 << 15) - 1, "largest creep_q15: the creep inverse's gain q = kappa / "
                      "(1 - kappa) stays below 1 for a creep magnitude up to 0.5 (docs/fixed-point.md)"),
    "MAX_HOLD_GAIN_Q15": (1 << 12, "largest |hold_gain_q15| (12.5 %): the hold stage's product "
                          "stays below 2^56 (docs/fixed-point.md)"),
    "MAX_HOLD_RAMP_SHIFT": (12, "largest hold_ramp_shift (the gain ramps in over 4096 samples)"),
    "MAX_CUSUM_Q8": (1 << 29, "largest contact_cusum_h_q8 and |contact_cusum_k_q8|, |_lo_q8|, "
                     "|_hi_q8|: the CUSUM's sum stays inside int32 (docs/fixed-point.md)"),
    "RELEASE_DWELL": (8, "consecutive samples with the contact net's margin at or below 0 "
                      "before contact is released inside the decision's hold"),
    "BLOB_VERSION": (11, "blob format this library reads and writes"),
    "BLOB_HEADER_SIZE": (16, "magic, version, flags, total length, CRC-32"),
    "VERSION_MAJOR": (VERSION[0], "library version"),
    "VERSION_MINOR": (VERSION[1], ""),
    "VERSION_PATCH": (VERSION[2], ""),
}
LIMIT = {name: value for name, (value, _doc) in LIMITS.items()}


@dataclass(frozen=True)
class Code:
    """A return code of the C API (``fbg_status``)."""

    name: str
    value: int
    doc: str


ERRORS: tuple[Code, ...] = (
    Code("OK", 0, "success"),
    Code("ERR_NULL", -1, "a required pointer argument is NULL"),
    Code("ERR_TRUNCATED", -2, "blob shorter than its header or than its declared length"),
    Code("ERR_BAD_MAGIC", -3, "blob does not start with \"FBGM\""),
    Code("ERR_VERSION", -4, "blob format version or header flags not supported by this library"),
    Code("ERR_CRC", -5, "CRC-32 over the blob body does not match"),
    Code("ERR_SHAPE", -6, "layer shapes inconsistent, too large, or nets of wrong I/O"),
    Code("ERR_RANGE", -7, "a parameter outside its allowed range, or non-zero padding"),
    Code("ERR_BOUND", -8, "accumulator worst-case bound would overflow int64 (int32 for an "
                          "acc32 layer)"),
    Code("ERR_SIZE", -9, "declared length differs from the length the shapes imply"),
    Code("ERR_ALIGN", -10, "blob pointer not 8-byte aligned (arrays are used in place)"),
    Code("ERR_ENDIAN", -11, "host is not little-endian (blob arrays are little-endian)"),
    Code("ERR_STATE", -12, "state not initialised by fbg_init (or corrupted)"),
    Code("ERR_NOT_TARED", -13, "fbg_step with FBG_OPT_REQUIRE_TARE before a tare"),
    Code("ERR_TARE", -14, "tare_add/tare_end without tare_begin, or no valid sample"),
    Code("ERR_ARG", -15, "bad argument value (e.g. baseline outside the window)"),
    Code("ERR_MODEL_CHANGED", -16, "the model was reloaded under the state (its blob_crc "
                                   "differs from fbg_init's): fbg_init again"),
)
CODE = {c.name: c.value for c in ERRORS}
CODE_NAME = {c.value: f"FBG_{c.name}" for c in ERRORS}

STATUS: tuple[Code, ...] = (
    Code("NOT_TARED", 0x01, "running on the model's nominal baseline"),
    Code("SATURATED", 0x02, "some value was clamped (int16/int32) this sample"),
    Code("OVERLOAD", 0x04, "beyond the trained force range (see fbg_model)"),
    Code("SENSOR_FAULT", 0x08, "a peak lost, jumped or stuck: outputs are the safe output"),
    Code("WARMUP", 0x10, "fewer than n_taps samples since init/tare/reset"),
    Code("BASELINE_LIMIT", 0x20, "the at-rest baseline tracker is at its bound: drift beyond "
                                 "what it may correct (re-tare)"),
    Code("OUT_OF_RANGE", 0x40, "a net input (z or a memory feature) outside the range the "
                               "calibration data covered, with a margin: the nets extrapolate"),
    Code("RELEASING", 0x80, "contact has ended: the contact net's margin has stayed at or "
                            "below 0 for FBG_RELEASE_DWELL samples; the force and location "
                            "still follow the falling load until the decision's release band "
                            "ends"),
)
STATUS_FLAG = {c.name: c.value for c in STATUS}
STATUS_ALL = sum(STATUS_FLAG.values())
#: Flags a host publisher adds to a published estimate's status (the ROS 2 ``Contact`` message):
#: they describe the interrogator link, which the runtime never sees, so they sit above the
#: runtime's bits and never appear in ``fbg_output.status``.
LINK_STATUS: tuple[Code, ...] = (
    Code("SAMPLES_LOST", 0x100, "the sample counter skipped: samples were lost just before "
                                "this one (dropped frames, or a reconnect)"),
    Code("DEVICE_RESTART", 0x200, "the sample counter went backwards: the interrogator "
                                  "restarted (or the link reconnected to a restarted device)"),
)

#: fbg_init options (``#define FBG_OPT_<name>``). The KERNEL_* values (a field under
#: KERNEL_MASK) choose the dense-layer kernels of the fixed-point build (docs/runtime.md,
#: "Host SIMD kernels"); every kernel gives the same bits.
OPTIONS: tuple[Code, ...] = (
    Code("REQUIRE_TARE", 0x01, "fbg_step returns FBG_ERR_NOT_TARED until tared"),
    Code("KERNEL_MASK", 0xF0, "the dense-layer kernel field of the options"),
    Code("KERNEL_AUTO", 0x00, "the fastest kernel this CPU runs"),
    Code("KERNEL_PORTABLE", 0x10, "portable C"),
    Code("KERNEL_SSE2", 0x20, "x86-64 SSE2"),
    Code("KERNEL_AVX2", 0x30, "x86-64 AVX2 (if the CPU has it)"),
    Code("KERNEL_NEON", 0x40, "aarch64 NEON"),
)
OPTION = {c.name: c.value for c in OPTIONS}


@dataclass(frozen=True)
class Net:
    """One net of the hierarchy, in evaluation order.

    ``extra_inputs`` are appended to the feature vector (z and memory features) it reads;
    ``float_outputs`` is what the float model's net gives, ``fixed_outputs`` what the C output
    layer computes (the contact net's two logits become one margin row)."""

    name: str
    extra_inputs: tuple[str, ...]
    float_outputs: int
    fixed_outputs: int
    loss: str
    scaling: str


NETS: tuple[Net, ...] = (
    Net("contact", (), 2, 1, "softmax cross-entropy", "fixed: logit margin in Q8"),
    Net("force", (), 1, 1, "mean squared error on contact samples",
        "force_N = force_offset + force_scale * out; fixed: mN before offset"),
    Net("location", ("contact flag (0/1)", "force net output (unscaled)"), 2, 2,
        "mean squared error on contact samples",
        "xy_mm = xy_offset + xy_scale * out; fixed: um before offset"),
)
NET_NAMES = tuple(n.name for n in NETS)


def n_features(n_memory: int) -> int:
    """Width of the feature vector the contact and force nets read: the standardised channels
    and one feature per memory state, ``n_memory`` states of every kind together (the states
    follow one load signal, see PARAMS)."""
    return N_STRAIN + n_memory


#: Nets that read the load signal's memory features; the location net reads the standardised
#: channels (where a press is does not depend on the load's history; its magnitude comes in
#: through the force net's output) and, when ``loc_shift`` is on, the location averages.
MEMORY_NETS = ("contact", "force")


def n_loc(loc_shift: int) -> int:
    """Location averages of a model: one per strain channel when ``loc_shift`` is on (> 0)."""
    return N_STRAIN if loc_shift else 0


def net_inputs(net: str, n_memory: int, n_loc: int = 0) -> int:
    """Input width of a net for a model with ``n_memory`` memory states: the location net reads
    the ``n_loc`` location averages after its extra inputs."""
    spec = next(n for n in NETS if n.name == net)
    base = n_features(n_memory) if net in MEMORY_NETS else N_STRAIN
    return base + len(spec.extra_inputs) + (n_loc if net == "location" else 0)


# ------------------------------------------------------------------------------------------
# Parameter blocks
# ------------------------------------------------------------------------------------------

#: C type -> (struct format character, numpy dtype, bytes)
CTYPES = {
    "int32_t": ("i", "<i4", 4), "uint32_t": ("I", "<u4", 4), "int16_t": ("h", "<i2", 2),
    "uint16_t": ("H", "<u2", 2), "uint8_t": ("B", "u1", 1), "float": ("f", "<f4", 4),
}
#: Integer C type -> the values it holds
CTYPE_RANGE = {name: (-(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1) if fmt.islower()
               else (0, (1 << (8 * size)) - 1)
               for name, (fmt, _dtype, size) in CTYPES.items() if name != "float"}


@dataclass(frozen=True)
class Field:
    """One parameter of a model block.

    Values must lie in ``[lo, hi]`` (``None``: the C type's whole range), else ``code``.
    ``active`` names a count field: entries at or beyond that count must be 0 (any code
    ``RANGE``), entries below it lie in ``[lo, hi]``. ``blob=False`` fields are set by the
    loader (pointers) and are not part of the parameter block.
    """

    name: str
    ctype: str
    count: int = 1
    lo: int | None = None
    hi: int | None = None
    code: str = "ERR_RANGE"
    active: str | None = None
    doc: str = ""
    #: Where the C model keeps it when not as a member of the same name (``k`` is the index).
    c_member: str | None = None

    def c_lvalue(self, index: str = "k") -> str:
        """The C expression of entry ``index`` (or of the scalar) inside ``m->``."""
        if self.c_member:
            return self.c_member.replace("k", index) if self.count > 1 else self.c_member
        return f"{self.name}[{index}]" if self.count > 1 else self.name


I32_RANGE = (-SAT32, SAT32)   # INT32_MIN is refused everywhere: negation must not overflow


def memory_params() -> tuple[Field, ...]:
    """The memory kinds' fields of ``PARAMS``: every kind's count, then every kind's parameter
    arrays (entries from the count on must be 0)."""
    return (tuple(Field(k.count_field, "uint8_t", 1, 0, k.limit, "ERR_SHAPE", doc=k.doc)
                  for k in MEMORY_KINDS)
            + tuple(Field(k.field(p), p.ctype, k.limit, p.lo, p.hi, active=k.count_field, doc=p.doc)
                    for k in MEMORY_KINDS for p in k.params))


def float_memory_params() -> tuple[Field, ...]:
    """The memory kinds' fields of ``FLOAT_PARAMS``, in the order of :func:`memory_params`
    (their ranges are checked by the generated ``fbgf_memory_check``)."""
    return (tuple(Field(k.count_field, "uint8_t", doc="as fbg_model" if i == 0 else "")
                  for i, k in enumerate(MEMORY_KINDS))
            + tuple(Field(k.field(p), p.float_ctype, k.limit, doc=p.float_doc)
                    for k in MEMORY_KINDS for p in k.params))


PARAMS: tuple[Field, ...] = (
    Field("writer_version", "uint32_t", doc="VERSION_CODE of the library that wrote the blob "
          "(informational: any value loads)"),
    Field("baseline_fm", "int32_t", N_CHANNELS, LIMIT["WL_MIN_FM"], LIMIT["WL_MAX_FM"],
          doc="nominal unloaded wavelengths (fm): the baseline before any tare"),
    Field("jump_max_fm", "int32_t", 1, 1, SAT32,
          doc="SENSOR_FAULT when |wl - previous in-window wl| > jump_max_fm on any channel"),
    Field("temp_coeff_q24", "int32_t", N_STRAIN, *I32_RANGE,
          doc="comp_i = shift_i - rshift_round(shift_T * temp_coeff_q24[i], 24)  (fm)"),
    Field("mean_fm", "int32_t", N_STRAIN, *I32_RANGE,
          doc="z_i = sat16(rshift_round(sat32(filt_i - mean_fm[i]) * z_mult[i], z_shift))"),
    Field("z_mult", "int32_t", N_STRAIN, *I32_RANGE, doc="standardisation multipliers"),
    Field("fq_mult", "int32_t", 1, *I32_RANGE,
          doc="location input: f_q = sat16(rshift_round(force_out * fq_mult, fq_shift))"),
    Field("force_offset_mN", "int32_t", 1, *I32_RANGE, doc="force_mN = sat32(force_out + offset)"),
    Field("xy_offset_um", "int32_t", 2, *I32_RANGE, doc="x_um, y_um likewise"),
    Field("overload_mN", "int32_t", 1, *I32_RANGE, doc="OVERLOAD when contact and force_mN > this"),
    Field("load_coeff", "int32_t", N_STRAIN, -(LIMIT["LOAD_COEFF_LIMIT"] - 1),
          LIMIT["LOAD_COEFF_LIMIT"] - 1,
          doc="input-side overload: load_mN = rshift_round(sum_i load_coeff[i] * filt_i, "
              "load_shift)"),
    Field("load_max_mN", "int32_t", 1, *I32_RANGE, doc="OVERLOAD when load_mN > load_max_mN"),
    Field("n_taps", "uint16_t", 1, 1, LIMIT["MAX_TAPS"], "ERR_SHAPE", doc="causal FIR length"),
    Field("stuck_max", "uint16_t", doc="SENSOR_FAULT after this many identical samples on a "
          "channel; 0 disables the rule"),
    Field("tap_q", "uint8_t", 1, 1, 15, doc="FIR taps are int16 in Q(tap_q)"),
    Field("z_frac", "uint8_t", 1, 0, 14, doc="net inputs are int16 in Q(z_frac)"),
    Field("z_shift", "uint8_t", 1, 1, 62, doc="shift of the standardisation (with z_mult)"),
    Field("fq_shift", "uint8_t", 1, 1, 62, doc="shift of the location net's force input"),
    Field("load_shift", "uint8_t", 1, 1, 62, doc="shift of the load proxy"),
    Field("n_layers", "uint8_t", 3, 1, LIMIT["MAX_LAYERS"], "ERR_SHAPE",
          doc="layers of the contact, force and location nets", c_member="nets[k].n_layers"),
    Field("mem_mult", "int32_t", N_STRAIN, *I32_RANGE,
          doc="memory input u = sat16(rshift_round(sum_i mem_mult[i] * z_i, mem_shift)): a "
              "load signal in Q(z_frac)"),
    Field("mem_shift", "uint8_t", 1, 1, 62, doc="shift of the memory input"),
    *memory_params(),
    Field("loc_shift", "uint8_t", 1, 0, LIMIT["MAX_EMA_SHIFT"],
          doc="location averages (0: off): r_i = sat16(z_i - z0_i), z0_i the standardised zero "
              "shift; loc_i += rshift_round((r_i << EMA_FRAC) - loc_i, loc_shift); location "
              "input rshift_round(loc_i, EMA_FRAC)"),
    Field("contact_on_q8", "int32_t", 1, 0, SAT32,
          doc="contact rises when acc > 0 and margin_q8 >= contact_on_q8 ..."),
    Field("contact_off_q8", "int32_t", 1, -SAT32, 0,
          doc="... and stays while acc > 0 or margin_q8 > contact_off_q8"),
    Field("contact_rise_n", "uint8_t", 1, 1, 255,
          doc="consecutive samples of the rise condition before contact rises"),
    Field("track_shift", "uint8_t", 1, 0, 20,
          doc="at-rest baseline tracker (0: off): time constant 2^track_shift samples"),
    Field("track_settle", "uint16_t",
          doc="samples of rest (tared, no contact, fault or warm-up) before a tracker block counts"),
    Field("track_gain", "int32_t", N_STRAIN, *I32_RANGE,
          doc="per TRACK_BLOCK at rest: corr_i += sum(z_i - z0_i) * track_gain[i] (fm in "
              "Q(TRACK_FRAC))"),
    Field("track_step_max_fm", "int32_t", 1, 0, SAT32,
          doc="largest baseline step of one tracker block (fm)"),
    Field("track_limit_fm", "int32_t", 1, 0, LIMIT["TRACK_LIMIT_MAX_FM"],
          doc="largest |tracked - tared baseline| per channel (fm); BASELINE_LIMIT at it"),
    Field("in_lo", "int16_t", LIMIT["MAX_INPUTS"], -SAT16, SAT16,
          doc="OUT_OF_RANGE when a net input j < n_features (z, memory features) < in_lo[j] ..."),
    Field("in_hi", "int16_t", LIMIT["MAX_INPUTS"], -SAT16, SAT16,
          doc="... or > in_hi[j] (Q(z_frac); +-32767: never)"),
    Field("ref_shift", "uint8_t", 1, 0, LIMIT["MAX_REF_SHIFT"],
          doc="temperature reference average (0: off): from acc = 0, the n-th good sample "
              "adds (shift_T - rshift_round(acc, ref_shift)) * 2^(ref_shift - s), s = min(ref_shift, "
              "floor(log2 n)); r = rshift_round(acc, ref_shift) replaces shift_T in "
              "temp_coeff_q24's compensation"),
    Field("track_creep_q15", "uint16_t", 1, 0, LIMIT["MAX_TRACK_CREEP_Q15"],
          doc="the tracker's creep term (0: off; needs track_creep_shift >= 1): per sample at rest "
              "it sums (z_i - z0_i) - rshift_round((creep_i - (z0_i << EMA_FRAC)) * "
              "track_creep_q15, 30), the pad's creep magnitude in Q15"),
    Field("track_creep_shift", "uint8_t", 1, 0, LIMIT["MAX_EMA_SHIFT"],
          doc="creep_i += rshift_round((z_i << EMA_FRAC) - creep_i, track_creep_shift) on every "
              "good sample, primed at z_i << EMA_FRAC: the creep's time constant 2^k samples"),
    Field("creep_q15", "uint16_t", 1, 0, LIMIT["MAX_CREEP_Q15"],
          doc="the pad's creep inverse (0: off; needs creep_shift >= 1), on each good sample's "
              "compensated shift c_i before the FIR: L_i = rshift_round(acc_i, creep_shift), e_i = "
              "sat32(c_i + rshift_round((c_i - L_i) * creep_q15, 15)) replaces c_i, acc_i += e_i "
              "- L_i; acc_i primed at c_i << creep_shift. q = kappa / (1 - kappa), kappa = m (1 - "
              "2^-creep_shift), in Q15"),
    Field("creep_shift", "uint8_t", 1, 0, LIMIT["MAX_EMA_SHIFT"],
          doc="the pad's creep time constant 2^creep_shift samples (1..15 when creep_q15 is on)"),
    Field("hold_gain_q15", "int16_t", 1, -LIMIT["MAX_HOLD_GAIN_Q15"], LIMIT["MAX_HOLD_GAIN_Q15"],
          doc="the settled-hold gain (0: off; needs hold_shift >= 1): on a contact sample, "
              "force_mN += rshift_round(force_mN * hold_gain_q15 * w, 15 + hold_ramp_shift), w = "
              "clamp(hold_run - hold_settle, 0, 2^hold_ramp_shift)"),
    Field("hold_settle", "uint16_t",
          doc="steady contact samples before the settled-hold gain starts to ramp in"),
    Field("hold_band_mN", "int32_t", 1, 0, SAT32,
          doc="a contact sample is steady when |force_mN - rshift_round(hold_avg, EMA_FRAC)| <= "
              "max(hold_band_mN, rshift_round(|force_mN| * hold_band_q15, 15)) ..."),
    Field("hold_band_q15", "uint16_t", 1, 0, 1 << 15,
          doc="... (hold_avg += rshift_round((force_mN << EMA_FRAC) - hold_avg, hold_shift), primed "
              "at the first contact sample after no contact); hold_run counts steady samples"),
    Field("hold_shift", "uint8_t", 1, 0, LIMIT["MAX_EMA_SHIFT"],
          doc="time constant 2^hold_shift samples of the hold stage's average of force_mN"),
    Field("hold_ramp_shift", "uint8_t", 1, 0, LIMIT["MAX_HOLD_RAMP_SHIFT"],
          doc="the settled-hold gain ramps in over 2^hold_ramp_shift samples"),
    Field("contact_cusum_h_q8", "int32_t", 1, 0, LIMIT["MAX_CUSUM_Q8"],
          doc="the decision's CUSUM rise (0: off, the Schmitt trigger with its count; on: needs "
              "contact_on_q8 0, contact_rise_n 1, lo <= hi): out of contact S = max(0, S + "
              "clamp(margin_q8, lo, hi) - k), contact rises when S >= h (S = 0 then)"),
    Field("contact_cusum_k_q8", "int32_t", 1, -LIMIT["MAX_CUSUM_Q8"], LIMIT["MAX_CUSUM_Q8"],
          doc="the CUSUM's drift k (Q8 margin; 0 when the CUSUM is off)"),
    Field("contact_cusum_lo_q8", "int32_t", 1, -LIMIT["MAX_CUSUM_Q8"], LIMIT["MAX_CUSUM_Q8"],
          doc="the CUSUM's clip of the margin, lower end (0 when off)"),
    Field("contact_cusum_hi_q8", "int32_t", 1, -LIMIT["MAX_CUSUM_Q8"], LIMIT["MAX_CUSUM_Q8"],
          doc="the CUSUM's clip of the margin, upper end (0 when off)"),
)

FLOAT_PARAMS: tuple[Field, ...] = (
    Field("baseline_fm", "int32_t", N_CHANNELS),
    Field("jump_max_fm", "int32_t"),
    Field("stuck_max", "uint16_t"),
    Field("n_taps", "uint16_t", doc="1..FBG_MAX_TAPS"),
    Field("temp_coeff", "float", N_STRAIN),
    Field("input_mean_pm", "float", N_STRAIN),
    Field("input_std_pm", "float", N_STRAIN),
    Field("force_offset_N", "float"),
    Field("force_scale", "float"),
    Field("xy_offset_mm", "float", 2),
    Field("xy_scale", "float", 2),
    Field("overload_N", "float"),
    Field("mem_weight", "float", N_STRAIN, doc="memory input u = sum_i mem_weight[i] * z_i"),
    *float_memory_params(),
    Field("loc_shift", "uint8_t", doc="location averages of z - z_rest (0: off): "
          "state += (r - state) / 2^loc_shift"),
    Field("contact_on", "float", doc="decision over time as fbg_model, on the margin"),
    Field("contact_off", "float"),
    Field("contact_rise_n", "uint8_t", doc="1..255"),
    Field("track_shift", "uint8_t", doc="at-rest baseline tracker as fbg_model (0: off)"),
    Field("track_settle", "uint16_t"),
    Field("track_step_max_pm", "float", doc="per block: corr_i += clamp(sum(filt_i) / "
          "2^track_shift, +-track_step_max_pm)"),
    Field("track_limit_pm", "float", doc="|corr_i| <= track_limit_pm (BASELINE_LIMIT at it)"),
    Field("track_creep", "float", doc="the tracker's creep term as fbg_model, 0..0.5 (0: off): "
          "per sample at rest it sums filt_i - track_creep * creep_pm_i"),
    Field("track_creep_shift", "uint8_t", doc="creep_pm_i += (filt_i - creep_pm_i) / "
          "2^track_creep_shift on every good sample (1..15 when track_creep > 0)"),
    Field("hold_gain", "float", doc="the settled-hold gain as fbg_model, its excess over 1 itself, "
          "|hold_gain| <= 0.125 (0: off): force_N *= 1 + hold_gain * w / 2^hold_ramp_shift"),
    Field("hold_settle", "uint16_t"),
    Field("hold_band_N", "float", doc="steady: |force_N - hold_avg_N| <= max(hold_band_N, "
          "hold_band_frac * |force_N|), hold_avg_N += (force_N - hold_avg_N) / 2^hold_shift"),
    Field("hold_band_frac", "float", doc="0..1"),
    Field("hold_shift", "uint8_t", doc="1..15 when hold_gain is on"),
    Field("hold_ramp_shift", "uint8_t", doc="0..FBG_MAX_HOLD_RAMP_SHIFT"),
    Field("contact_cusum_h", "float", doc="the decision's CUSUM rise as fbg_model, on the margin "
          "(0: off; on: contact_on 0, contact_rise_n 1, lo <= hi): S = max(0, S + clamp(margin, "
          "lo, hi) - k), contact rises when S >= h"),
    Field("contact_cusum_k", "float"),
    Field("contact_cusum_lo", "float"),
    Field("contact_cusum_hi", "float"),
    Field("in_lo", "float", LIMIT["MAX_INPUTS"], doc="OUT_OF_RANGE as fbg_model, standardised units"),
    Field("in_hi", "float", LIMIT["MAX_INPUTS"]),
    Field("ref_shift", "uint8_t", doc="temperature reference average as fbg_model (0: off): "
          "r += (shift_T - r) / 2^s, s = min(ref_shift, floor(log2 n)) at the n-th good sample"),
    Field("creep_q", "float", doc="the pad's creep inverse as fbg_model, its gain q = kappa / "
          "(1 - kappa) itself, 0 <= q < 1 (0: off): e_i = c_i + creep_q * (c_i - creep_lag_pm_i) "
          "replaces c_i, creep_lag_pm_i += (e_i - creep_lag_pm_i) / 2^creep_shift"),
    Field("creep_shift", "uint8_t", doc="the pad's creep time constant (1..15 when creep_q > 0)"),
)


# ------------------------------------------------------------------------------------------
# The fixed-point streaming state
# ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class StateField:
    """One member of the caller-owned fixed-point state ``fbg_state``.

    ``dims`` are its array dimensions, each a ``LIMITS`` name (declared as ``FBG_<name>``) or a
    number; ``note`` is a comment on the group of members it opens.
    """

    name: str
    ctype: str
    dims: tuple[str | int, ...] = ()
    doc: str = ""
    note: str = ""

    def count(self) -> int:
        """Number of elements (1 for a scalar)."""
        n = 1
        for d in self.dims:
            n *= d if isinstance(d, int) else LIMIT[d]
        return n


def _memory_states(ctype: str, doc: Callable[[MemoryKind], str]) -> tuple[StateField, ...]:
    """The state arrays of the memory kinds, of element type ``ctype``."""
    return tuple(StateField(k.name, ctype, (f"MAX_{k.name.upper()}",), doc(k),
                            note="Memory states of the load signal u (docs/fixed-point.md, "
                                 "\"memory\"), one array per kind of "
                                 "fbgforce.contract.MEMORY_KINDS." if i == 0 else "")
                 for i, k in enumerate(MEMORY_KINDS))


#: The state members a reset clears as memory: the memory kinds' arrays, the location averages.
MEMORY_STATES: tuple[str, ...] = tuple(k.name for k in MEMORY_KINDS) + ("loc",)


def _front_head(prefix: str, signal: str) -> tuple[StateField, ...]:
    """The members both states open with (the front end's, fbg_front.h), for the build whose
    names start with ``prefix`` and whose compensated signal is ``signal``."""
    return (StateField("magic", "uint32_t", doc=f"set by {prefix}_init"),
            StateField("options", "uint32_t"),
            StateField("model", f"const {prefix}_model *"),
            StateField("baseline_fm", "int32_t", ("N_CHANNELS",)),
            StateField("prev_fm", "int32_t", ("N_CHANNELS",), "last in-window sample per channel"),
            StateField("hist", signal, ("MAX_TAPS", "N_STRAIN"), "FIR history (ring buffer)"),
            StateField("last_comp", signal, ("N_STRAIN",),
                       "the last good sample's filtered shifts, held into the FIR during a fault"))


#: The front end's counters and flags, in both states.
_RING_COUNTERS = (
    StateField("pos", "uint16_t", doc="next write index into hist"),
    StateField("since_reset", "uint16_t", doc="samples since init/tare, saturating"),
    StateField("same_run", "uint16_t", ("N_CHANNELS",), "repeats of the identical value"),
)
_FRONT_FLAGS = (
    StateField("tared", "uint8_t"),
    StateField("tare_active", "uint8_t"),
    StateField("prev_valid", "uint8_t", doc="bit c: prev_fm[c] holds a sample"),
    StateField("mem_primed", "uint8_t", doc="memory states hold a sample"),
    StateField("ref_count", "uint8_t", doc="good samples in the temperature reference's average "
               "(up to 255: its gain has reached 2^-ref_shift by 2^ref_shift <= 256)"),
    StateField("creep_primed", "uint8_t", doc="the creep inverse's lags hold a sample"),
)


#: ``fbg_state`` in declaration order: the order is the layout (the int64 arrays just before
#: ``act`` give it the 8-byte alignment the DSP kernels' LDRD needs, which fbg_fixed.c checks).
STATE: tuple[StateField, ...] = (
    *_front_head("fbg", "int32_t"),
    *_memory_states("int32_t", lambda k: f"{k.doc}, {k.q}"),
    StateField("loc", "int32_t", ("N_STRAIN",), "location averages of z - z0, Q(z_frac + FBG_EMA_FRAC)"),
    StateField("creep", "int32_t", ("N_STRAIN",), "the tracker's creep states: averages of z, "
               "Q(z_frac + FBG_EMA_FRAC), primed with the memory (mem_primed)"),
    StateField("track_sum", "int32_t", ("N_STRAIN",),
               note="At-rest baseline tracker (docs/runtime.md, \"In use\"): the block's sum of z - z0, "
                    "the correction applied to baseline_fm[0..3] since the tare, and the carried "
                    "fraction of the next step in Q(FBG_TRACK_FRAC)."),
    StateField("drift_fm", "int32_t", ("N_STRAIN",)),
    StateField("track_frac", "int64_t", ("N_STRAIN",)),
    StateField("tare_sum", "int64_t", ("N_CHANNELS",)),
    StateField("ref_acc", "int64_t", doc="the temperature reference's average r * 2^ref_shift "
               "(fm; docs/fixed-point.md, \"temperature reference\")"),
    StateField("creep_acc", "int64_t", ("N_STRAIN",), "the creep inverse's lags L_i * "
               "2^creep_shift (fm; docs/fixed-point.md, \"creep inverse\")"),
    StateField("hold_avg", "int64_t", doc="the hold stage's average of force_mN, Q(FBG_EMA_FRAC) "
               "(docs/fixed-point.md, \"settled-hold gain\")"),
    StateField("act", "int16_t", (2, "MAX_WIDTH"), "activation ping-pong buffers",
               note="Right after the int64 arrays, so 8-byte aligned on every ABI: the DSP kernels "
                    "read the activations with LDRD (no copy to an aligned buffer per layer)."),
    StateField("tare_count", "uint32_t"),
    StateField("cusum_q8", "int32_t", doc="the decision's CUSUM S (Q8 margin), in [0, "
               "contact_cusum_h_q8) out of contact and in the release band, 0 while contact is shown"),
    *_RING_COUNTERS,
    StateField("loc_z0", "int16_t", ("N_STRAIN",), "z of a zero filtered shift (the model's)"),
    *_FRONT_FLAGS,
    StateField("loc_z0_clamped", "uint8_t", doc="1: a loc_z0 clamped at +-32767"),
    StateField("decision", "uint8_t", doc="the contact decision of the last step, held through "
               "the release band"),
    StateField("released", "uint8_t", doc="1: in the release band, contact no longer shown"),
    StateField("release_run", "uint8_t", doc="samples with the margin at or below 0 so far, "
               "in contact (up to FBG_RELEASE_DWELL)"),
    StateField("rise_run", "uint8_t", doc="samples of the rise condition so far"),
    StateField("track_pos", "uint8_t", doc="samples into the tracker's block"),
    StateField("track_limited", "uint8_t", doc="1: a channel's drift_fm is at its bound"),
    StateField("rest_run", "uint16_t", doc="samples at rest, saturating"),
    StateField("hold_run", "uint16_t", doc="steady contact samples so far, saturating"),
    StateField("hold_primed", "uint8_t", doc="hold_avg holds a contact sample's force"),
    StateField("packed", "const void *", doc="fbg_pack / fbg_use_pack buffer, or NULL"),
    StateField("model_crc", "uint32_t", doc="model->blob_crc at fbg_init"),
)

#: ``fbgf_state`` (the float build) in declaration order: the front end's members under the
#: names of fbg_state's (fbg_front.h reaches both through one view), signals in float.
FLOAT_STATE: tuple[StateField, ...] = (
    *_front_head("fbgf", "float"),
    *_memory_states("float", lambda k: f"{k.doc}, standardised units"),
    StateField("loc", "float", ("N_STRAIN",), "location averages of z - z_rest"),
    StateField("creep_pm", "float", ("N_STRAIN",), "the tracker's creep states: averages of the "
               "filtered shifts (pm), primed with the memory (mem_primed)"),
    StateField("ref_pm", "float", doc="the temperature reference's average (pm)"),
    StateField("hold_avg_N", "float", doc="the hold stage's average of force_N"),
    StateField("creep_lag_pm", "float", ("N_STRAIN",), "the creep inverse's lags L_i (pm)"),
    StateField("tare_sum", "int64_t", ("N_CHANNELS",)),
    StateField("tare_count", "uint32_t"),
    StateField("cusum", "float", doc="the decision's CUSUM S (margin), as fbg_state's cusum_q8"),
    *_RING_COUNTERS,
    *_FRONT_FLAGS,
    StateField("track_sum", "float", ("N_STRAIN",),
               note="The decision over time and the at-rest baseline tracker, as fbg_state's: the "
                    "block's sum of filtered shifts (pm); the correction subtracted from the "
                    "compensated shifts is held_pm (made before the last reset) + drift_pm (since, "
                    "bounded by track_limit_pm)."),
    StateField("drift_pm", "float", ("N_STRAIN",)),
    StateField("held_pm", "float", ("N_STRAIN",)),
    StateField("rest_run", "uint16_t", doc="samples at rest, saturating"),
    StateField("decision", "uint8_t", doc="the contact decision of the last step, held through "
               "the release band"),
    StateField("released", "uint8_t", doc="1: in the release band, contact no longer shown"),
    StateField("release_run", "uint8_t", doc="samples with the margin at or below 0 so far, "
               "in contact (up to FBG_RELEASE_DWELL)"),
    StateField("rise_run", "uint8_t", doc="samples of the rise condition so far"),
    StateField("track_pos", "uint8_t", doc="samples into the tracker's block"),
    StateField("track_limited", "uint8_t", doc="1: a channel's drift_pm is at its bound"),
    StateField("hold_run", "uint16_t", doc="steady contact samples so far, saturating"),
    StateField("hold_primed", "uint8_t", doc="hold_avg_N holds a contact sample's force"),
    StateField("reserved_", "uint8_t", (1,)),
    StateField("act", "float", (2, "MAX_WIDTH"), "activation ping-pong buffers"),
)

#: File name of the blob inside a model directory.
BLOB_FILE = "model.fbgm"
#: Default of the sensor-fault jump rule, nm per sample (the exporter raises it to twice the
#: largest step of the calibration data).
DEFAULT_JUMP_NM = 2.0

#: Layer-table entry of the blob: u16 n_in, u16 n_out, u8 w_bits, u8 shift, u8 acc32, u8 zero.
LAYER_ENTRY = struct.Struct("<HHBBBB")
#: Blob header: magic, u16 version, u16 flags (0), u32 total length, u32 CRC-32 of the rest.
HEADER = struct.Struct("<4sHHII")
MAGIC = b"FBGM"


def _pad8(n: int) -> int:
    return n + (-n % 8)


PARAMS_STRUCT = struct.Struct("<" + "".join(f"{f.count}{CTYPES[f.ctype][0]}" for f in PARAMS))
#: Parameter block bytes, padded with zeros to a multiple of 8.
PARAMS_SIZE = _pad8(PARAMS_STRUCT.size)
PARAMS_END = HEADER.size + PARAMS_SIZE


def decode_params(block: bytes) -> dict[str, int | tuple[int, ...]]:
    """Parameter block -> {field: value or tuple}; no checks (see :func:`check_params`)."""
    flat = PARAMS_STRUCT.unpack_from(block)
    out: dict[str, int | tuple[int, ...]] = {}
    i = 0
    for f in PARAMS:
        vals = flat[i:i + f.count]
        out[f.name] = vals[0] if f.count == 1 else tuple(vals)
        i += f.count
    return out


def encode_params(values: dict[str, object]) -> bytes:
    """{field: value} -> the padded parameter block."""
    flat: list[int] = []
    for f in PARAMS:
        v = values[f.name]
        seq = list(v) if f.count > 1 else [v]  # type: ignore[call-overload]
        if len(seq) != f.count:
            raise ValueError(f"{f.name}: {len(seq)} values, expected {f.count}")
        flat += [int(x) for x in seq]
    raw = PARAMS_STRUCT.pack(*flat)
    return raw + b"\0" * (PARAMS_SIZE - len(raw))


def check_params(values: dict[str, object]) -> tuple[str, str] | None:
    """The generated ``fbg_params_check`` in Python: the first violated rule, in field order,
    as ``(code name, reason)``; None when every field is in range."""
    for f in PARAMS:
        v = values[f.name]
        seq = list(v) if f.count > 1 else [v]  # type: ignore[call-overload]
        n_active = int(values[f.active]) if f.active else f.count  # type: ignore[arg-type]
        for k, x in enumerate(seq):
            x = int(x)
            if f.active and k >= n_active:
                if x != 0:
                    return "ERR_RANGE", f"{f.name}[{k}] = {x}: unused entries must be 0"
                continue
            if f.lo is not None and not f.lo <= x <= f.hi:  # type: ignore[operator]
                where = f"{f.name}[{k}]" if f.count > 1 else f.name
                return f.code, f"{where} = {x} outside [{f.lo}, {f.hi}]"
    return None


# ------------------------------------------------------------------------------------------
# Output records (C structs, byte for byte)
# ------------------------------------------------------------------------------------------

OUTPUT: tuple[Field, ...] = (
    Field("force_mN", "int32_t", doc="normal force, mN (0 when no contact)"),
    Field("x_um", "int32_t", doc="contact location, um (0 when no contact)"),
    Field("y_um", "int32_t"),
    Field("contact_margin_q8", "int32_t", doc="contact-net margin (logit difference) * 256"),
    Field("status", "uint32_t", doc="FBG_STATUS_* flags"),
    Field("contact_conf_q15", "uint16_t", doc="P(contact) in Q15, 0..32767 (sigmoid of the margin)"),
    Field("contact", "uint8_t", doc="1 = contact"),
    Field("reserved", "uint8_t"),
)
FLOAT_OUTPUT: tuple[Field, ...] = (
    Field("force_N", "float", doc="0 when no contact"),
    Field("x_mm", "float", doc="0 when no contact"),
    Field("y_mm", "float"),
    Field("p_contact", "float", doc="softmax probability of contact"),
    Field("margin", "float", doc="logit[1] - logit[0]"),
    Field("status", "uint32_t", doc="FBG_STATUS_*"),
    Field("contact", "uint8_t"),
    Field("reserved", "uint8_t", 3),
)
#: The fields of the fixed-point output record that carry information (not padding).
OUTPUT_FIELDS = tuple(f.name for f in OUTPUT if f.name != "reserved")


def numpy_dtype(fields: tuple[Field, ...]) -> list[tuple]:
    """numpy dtype description of a C struct of these fields (no implicit padding: the
    records above are laid out so that none is needed, which a test checks with cffi)."""
    return [(f.name, CTYPES[f.ctype][1]) if f.count == 1 else (f.name, CTYPES[f.ctype][1], f.count)
            for f in fields]
