"""Python binding of the C runtime (cffi API mode, module ``fbgforce._runtime``).

:class:`Runtime` wraps the fixed-point library: numpy wavelengths in (nm as float, or int32
femtometres), structured numpy arrays out. :class:`FloatRuntime` wraps the float build
(``fbgf_*``) with the weights of a float model directory. Every C error code has its own
exception class (:data:`ERRORS`), all subclasses of :class:`RuntimeCError`.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce import contract, samples, units
from fbgforce.model import modeldir as freshness
from fbgforce.model import artifact, modeldir
from fbgforce.errors import InputError

try:
    from fbgforce._runtime import ffi, lib
except ImportError as exc:  # pragma: no cover - depends on the build
    raise ImportError("the C extension fbgforce._runtime is not built; run "
                      "'python setup.py build_ext --inplace' in the project root") from exc

__all__ = ["Runtime", "FloatRuntime", "RuntimeCError", "ERRORS", "OUTPUT_DTYPE", "FLOAT_OUTPUT_DTYPE",
           "STATUS_FLAGS", "KERNELS", "PACKED_KERNELS", "check", "to_fm"]


class RuntimeCError(Exception):
    """A C runtime call returned an error code (``code``, ``name`` as in fbgforce.h)."""

    code = 0
    name = "FBG_ERR"

    def __init__(self, message: str = "") -> None:
        super().__init__(f"{self.name}: {message}" if message else self.name)


#: Codes that mean "this model blob is unusable": its exception classes are also InputError,
#: so that a corrupt or truncated model.fbgm given to a command is the usual one-line error
#: (exit 2) naming the file.
BLOB_ERRORS = ("FBG_ERR_TRUNCATED", "FBG_ERR_BAD_MAGIC", "FBG_ERR_VERSION", "FBG_ERR_CRC",
               "FBG_ERR_SHAPE", "FBG_ERR_RANGE", "FBG_ERR_BOUND", "FBG_ERR_SIZE")


def _make(name: str, doc: str, code: int) -> type[RuntimeCError]:
    cls_name = "".join(part.title() for part in name.removeprefix("FBG_ERR_").split("_")) + "Error"
    bases: tuple[type, ...] = (RuntimeCError, InputError) if name in BLOB_ERRORS else (RuntimeCError,)
    return type(cls_name, bases, {"code": code, "name": name, "__doc__": doc})


#: C error code -> exception class.
ERRORS: dict[int, type[RuntimeCError]] = {}
for _code in contract.ERRORS[1:]:
    _cls = _make(f"FBG_{_code.name}", _code.doc[:1].upper() + _code.doc[1:] + ".", _code.value)
    ERRORS[_cls.code] = _cls
    globals()[_cls.__name__] = _cls
    __all__.append(_cls.__name__)

#: Output status bits (fbg_output.status).
STATUS_FLAGS = dict(contract.STATUS_FLAG)
#: Dense-layer kernels of the fixed-point build by name -> FBG_OPT_KERNEL_* (docs/runtime.md,
#: "Host SIMD kernels").
KERNELS = {name[len("KERNEL_"):].lower(): value for name, value in contract.OPTION.items()
           if name.startswith("KERNEL_") and name != "KERNEL_MASK"}
KERNEL_NAME = {value: name for name, value in KERNELS.items()}
#: The kernels with a packed weight form (``fbg_pack``; docs/runtime.md, "Packed weights"),
#: which :class:`Runtime` uses by default; tests/test_simd.py checks it against the library.
PACKED_KERNELS = ("sse2", "avx2")

# The C structs fbg_output / fbgf_output, byte for byte (checked against ffi.sizeof at import).
_C_OUTPUT = np.dtype(contract.numpy_dtype(contract.OUTPUT))
_C_FOUTPUT = np.dtype(contract.numpy_dtype(contract.FLOAT_OUTPUT))
assert _C_OUTPUT.itemsize == ffi.sizeof("fbg_output")
assert _C_FOUTPUT.itemsize == ffi.sizeof("fbgf_output")

#: What :meth:`Runtime.run` returns: the raw integer outputs plus the same in SI-ish units
#: (force_N 0 and x_mm/y_mm NaN where no contact, as the float model).
OUTPUT_DTYPE = np.dtype([("contact", "?"), ("p_contact", "<f8"), ("force_N", "<f8"), ("x_mm", "<f8"),
                         ("y_mm", "<f8"), ("status", "<u4"), ("force_mN", "<i4"), ("x_um", "<i4"),
                         ("y_um", "<i4"), ("contact_margin_q8", "<i4"), ("contact_conf_q15", "<u2")])
FLOAT_OUTPUT_DTYPE = np.dtype([("contact", "?"), ("p_contact", "<f8"), ("force_N", "<f8"),
                               ("x_mm", "<f8"), ("y_mm", "<f8"), ("status", "<u4"), ("margin", "<f8")])


def check(status: int, what: str = "") -> None:
    """Raise the exception class of a C status code (no-op for FBG_OK)."""
    if status != 0:
        raise ERRORS.get(status, RuntimeCError)(what)


def to_fm(wl: Any) -> np.ndarray:
    """Wavelengths (n, 5) or (5,) -> C-contiguous int32 fm rows (n, 5): integer input is taken
    as fm, float as nm, anything else refused (:func:`fbgforce.samples.wavelength_array`).
    Non-finite values become 0 fm, a lost peak to the runtime's fault rule."""
    a = samples.wavelength_array(wl, integers_are_fm=True, single=True)
    if a.dtype.kind in "iu":
        return np.ascontiguousarray(a, dtype=np.int32)
    return np.ascontiguousarray(units.nm_to_fm(a))


def _rows(wl: Any) -> np.ndarray:
    return to_fm(wl)


class _Base:
    """Shared tare / baseline handling of the fixed and float runtimes."""

    _prefix = "fbg"

    def _fn(self, name: str) -> Any:
        return getattr(lib, f"{self._prefix}_{name}")

    def tare(self, wl: Any) -> np.ndarray:
        """Tare on samples (n, 5) (nm float or fm int): their mean becomes the baseline.

        Samples with a channel outside 1000-2000 nm are skipped. Returns the baseline (nm).
        """
        rows = _rows(wl)
        check(self._fn("tare_begin")(self._state), "tare_begin")
        ptr = ffi.cast("int32_t *", ffi.from_buffer(rows))
        for i in range(rows.shape[0]):
            check(self._fn("tare_add")(self._state, ptr + 5 * i, ffi.NULL), "tare_add")
        check(self._fn("tare_end")(self._state), "no valid sample to tare on")
        return self.baseline_nm

    def set_baseline(self, baseline: Any) -> None:
        """Set the tare baseline (5,) directly (nm float or fm int); resets the filter."""
        b = _rows(baseline).reshape(-1)
        if b.size != 5:
            raise InputError("a baseline has 5 values (wl1..wl4, wlT)")
        check(self._fn("set_baseline")(self._state, ffi.cast("int32_t *", ffi.from_buffer(b))),
              "baseline outside 1000-2000 nm")

    def reset(self) -> None:
        """Clear the filter history and fault tracker (keeps the baseline)."""
        check(self._fn("reset")(self._state), "reset")

    @property
    def baseline_fm(self) -> np.ndarray:
        return np.array(list(self._state.baseline_fm), dtype=np.int64)

    @property
    def baseline_nm(self) -> np.ndarray:
        return self.baseline_fm.astype(np.float64) * 1e-6

    @property
    def tared(self) -> bool:
        return bool(self._state.tared)

    def step(self, wl: Any) -> np.void:
        """One sample (5,) -> one record of the output dtype."""
        return self.run(to_fm(wl))[0]


class Runtime(_Base):
    """The fixed-point C runtime on a model blob.

    Parameters
    ----------
    model
        A model directory (its ``model.fbgm``), a blob file path, or the blob's bytes.
    require_tare
        Refuse to step before a tare (FBG_OPT_REQUIRE_TARE -> :class:`NotTaredError`).
    kernel
        Dense-layer kernels (:data:`KERNELS`): ``"auto"`` (the fastest this CPU runs),
        ``"portable"``, ``"sse2"``, ``"avx2"`` or ``"neon"``; every kernel gives the same bits.
        One this CPU cannot run raises :class:`ArgError`. :attr:`kernel` names the one in use.
    packed
        Run the kernel from weights packed for it (``fbg_pack``) where it has a packed form
        (SSE2, AVX2); the same bits, fewer instructions. :attr:`packed` says whether it does.
    float_model
        The directory's float model if the caller has loaded it (saves reading it again): a
        directory's blob must have been exported from it
        (:func:`fbgforce.model.modeldir.check_export`, an :class:`InputError` otherwise).

    Examples
    --------
    >>> rt = fbgforce.Runtime("runs/model")           # doctest: +SKIP
    >>> rt.tare(wl_nm[:300]); out = rt.run(wl_nm)      # doctest: +SKIP
    >>> out["force_N"], out["x_mm"], out["status"]     # doctest: +SKIP
    """

    _prefix = "fbg"

    def __init__(self, model: str | Path | bytes, *, require_tare: bool = False,
                 kernel: str = "auto", packed: bool = True, float_model: Any = None) -> None:
        if kernel not in KERNELS:
            raise InputError(f"unknown kernel {kernel!r}; one of {', '.join(KERNELS)}")
        if not isinstance(model, (str, os.PathLike, bytes, bytearray, memoryview)):
            raise InputError(f"model must be a model directory, a blob file path or the blob's "
                             f"bytes, not {type(model).__name__}")
        if isinstance(model, (bytes, bytearray, memoryview)):
            data, where = bytes(model), "<bytes>"
        else:
            path = Path(model) / contract.BLOB_FILE if Path(model).is_dir() else Path(model)
            if not path.is_file():
                raise InputError("no fixed-point model blob; run 'fbgforce export --model DIR' first",
                                 path=str(path))
            data, where = path.read_bytes(), str(path)
        # uint64 storage makes the buffer 8-byte aligned, as the zero-copy loader requires.
        self._blob = ffi.new("uint64_t[]", max(1, (len(data) + 7) // 8))
        ffi.memmove(self._blob, data, len(data))
        self._model = ffi.new("fbg_model *")
        self._state = ffi.new("fbg_state *")
        status = lib.fbg_model_from_blob(self._model, ffi.cast("uint8_t *", self._blob), len(data))
        if status != lib.FBG_OK:
            reason = ERRORS[status].__doc__ if status in ERRORS else "refused by the C loader"
            check(status, f"{where} ({len(data)} bytes): {reason}")
        if not isinstance(model, (bytes, bytearray, memoryview)) and Path(model).is_dir():
            freshness.check_export(model, float_model)
        options = (lib.FBG_OPT_REQUIRE_TARE if require_tare else 0) | KERNELS[kernel]
        check(lib.fbg_init(self._state, self._model, options),
              f"fbg_init: kernel {kernel!r} does not run on this CPU or build" if kernel != "auto"
              else "fbg_init")
        #: The dense-layer kernel this runtime runs (a key of :data:`KERNELS`, never "auto").
        self.kernel = KERNEL_NAME[lib.fbg_kernel(self._state)]
        #: Whether the kernel runs from packed weights (``packed=True`` and it has a packed form).
        self.packed = False
        size = lib.fbg_pack_bytes(self._state) if packed else 0
        if size:
            # Held as long as the state: the state points into it.
            self._pack = ffi.new("uint8_t[]", size + lib.FBG_PACK_ALIGN)
            start = (-int(ffi.cast("uintptr_t", self._pack))) % lib.FBG_PACK_ALIGN
            check(lib.fbg_pack(self._state, self._pack + start, size), "fbg_pack")
            self.packed = True
        self.blob_size = len(data)
        # Preallocated single-sample buffers: step() is what a 1 kHz loop calls.
        self._in = np.zeros(5, dtype=np.int32)
        self._in_ptr = ffi.cast("int32_t *", ffi.from_buffer(self._in))
        self._out = ffi.new("fbg_output *")

    @property
    def fault_thresholds(self) -> dict[str, Any]:
        """The blob's sensor-fault and overload thresholds as :class:`FloatRuntime` takes them
        (``jump_nm``, ``overload_N``, ``stuck_samples``), so both builds judge a sample alike."""
        m = self._model
        return {"jump_nm": m.jump_max_fm * 1e-6, "overload_N": m.overload_mN * 1e-3,
                "stuck_samples": int(m.stuck_max)}

    def step(self, wl: Any) -> np.void:
        """One sample (5,) (nm float or fm int) -> one record of :data:`OUTPUT_DTYPE`."""
        a = to_fm(wl)
        if a.shape[0] != 1:
            raise InputError(f"one sample has 5 wavelengths, got shape {np.shape(wl)}")
        self._in[:] = a[0]
        check(lib.fbg_step(self._state, self._in_ptr, self._out), "fbg_step")
        o = self._out
        contact = bool(o.contact)
        force_N, x_mm, y_mm = units.gate_outputs(units.estimate_shown(contact, o.status),
                                                 o.force_mN / 1000.0, o.x_um / 1000.0,
                                                 o.y_um / 1000.0)
        return np.array((contact, o.contact_conf_q15 / 32768.0, force_N, x_mm, y_mm,
                         o.status, o.force_mN, o.x_um, o.y_um, o.contact_margin_q8, o.contact_conf_q15),
                        dtype=OUTPUT_DTYPE)[()]

    def run_raw(self, wl: Any) -> np.ndarray:
        """Batch through ``fbg_run``; returns the C ``fbg_output`` records unchanged."""
        rows = _rows(wl)
        out = np.zeros(rows.shape[0], dtype=_C_OUTPUT)
        if rows.shape[0]:
            check(lib.fbg_run(self._state, ffi.cast("int32_t *", ffi.from_buffer(rows)), rows.shape[0],
                              ffi.cast("fbg_output *", ffi.from_buffer(out))), "fbg_run")
        return out

    def run(self, wl: Any) -> np.ndarray:
        """Batch of samples (n, 5) -> structured array of :data:`OUTPUT_DTYPE` (n,)."""
        # The unit conversion is the integer reference's, so both engines report alike.
        raw = self.run_raw(wl)
        out = np.zeros(raw.shape[0], dtype=OUTPUT_DTYPE)
        for k in ("force_mN", "x_um", "y_um", "contact_margin_q8", "contact_conf_q15"):
            out[k] = raw[k]
        for k, v in units.to_engine_dict(raw).items():
            out[k] = v
        return out


class FloatRuntime(_Base):
    """The C float build (``fbgf_*``) on a float model (directory or HierarchicalModel)."""

    _prefix = "fbgf"

    def __init__(self, model: str | Path | artifact.HierarchicalModel, *, jump_nm: float | None = None,
                 overload_N: float | None = None, stuck_samples: int = 0,
                 require_tare: bool = False) -> None:
        m = modeldir.load(model) if isinstance(model, (str, Path)) else model
        pre = m.preprocess
        taps_f = pre.runtime_taps()
        keep: list[Any] = []

        def farr(values: Any) -> Any:
            a = ffi.new("float[]", [float(v) for v in np.asarray(values, dtype=np.float64).ravel()])
            keep.append(a)
            return a

        c = ffi.new("fbgf_model *")
        jump_max_fm = round((contract.DEFAULT_JUMP_NM if jump_nm is None else jump_nm) * 1e6)
        for name, value in m.float_params(jump_max_fm, np.inf if overload_N is None else overload_N,
                                          stuck_samples).items():
            setattr(c, name, value)
        c.taps = farr(taps_f)
        for n, name in enumerate(artifact.NET_NAMES):
            net = m.nets[name]
            c.nets[n].n_layers = len(net.weights)
            for i, (w, b) in enumerate(zip(net.weights, net.biases)):
                ly = c.nets[n].layers[i]
                ly.n_in, ly.n_out = int(w.shape[1]), int(w.shape[0])
                ly.w = farr(w)
                ly.b = farr(b)
        self._keep, self._model = keep, c
        self._state = ffi.new("fbgf_state *")
        check(lib.fbgf_init(self._state, c, lib.FBG_OPT_REQUIRE_TARE if require_tare else 0), "fbgf_init")

    def run(self, wl: Any) -> np.ndarray:
        """Batch (n, 5) -> structured array of :data:`FLOAT_OUTPUT_DTYPE`."""
        rows = _rows(wl)
        raw = np.zeros(rows.shape[0], dtype=_C_FOUTPUT)
        if rows.shape[0]:
            check(lib.fbgf_run(self._state, ffi.cast("int32_t *", ffi.from_buffer(rows)), rows.shape[0],
                               ffi.cast("fbgf_output *", ffi.from_buffer(raw))), "fbgf_run")
        out = np.zeros(rows.shape[0], dtype=FLOAT_OUTPUT_DTYPE)
        contact = raw["contact"].astype(bool)
        out["contact"] = contact
        out["p_contact"] = raw["p_contact"]
        out["force_N"], out["x_mm"], out["y_mm"] = units.gate_outputs(
            units.estimate_shown(contact, raw["status"]), raw["force_N"], raw["x_mm"], raw["y_mm"])
        out["status"] = raw["status"]
        out["margin"] = raw["margin"]
        return out
