"""The one validator of wavelength samples, for the Python API and the CLI readers alike.

:func:`fbgforce.predict`, :class:`fbgforce.Runtime` and the dataset readers take wavelengths
through :func:`wavelength_array`, so they refuse the same things with the same
:class:`~fbgforce.errors.InputError`: what is not an array of real numbers (complex, text,
bool, ragged lists, a bare number), the wrong shape (four columns instead of five) and the
wrong unit (pm, µm, m instead of nm; nm integers where femtometres are expected).

What is accepted but cannot be measured, a non-finite value or a peak outside the window of
the C runtime's sensor-fault rule (:data:`WL_RANGE_NM`, a lost peak), is a sensor fault of
that sample (:func:`sensor_fault_rows`): every engine flags it ``SENSOR_FAULT`` and gives the
safe output, never a plain "no contact".

The sample rate a model was trained at is checked against the data's by :func:`check_rate`.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from fbgforce import contract
from fbgforce.errors import InputError

#: Gratings per sample: FBG 1..4 and T.
N_GRATINGS = contract.N_STRAIN + 1
#: Peak window, nm: the C runtime's lost-peak rule (FBG_WL_MIN_FM, FBG_WL_MAX_FM) and the
#: dataset contract's accepted range.
WL_RANGE_NM = (contract.LIMIT["WL_MIN_FM"] / 1e6, contract.LIMIT["WL_MAX_FM"] / 1e6)
#: Relative difference of two sample rates still taken as the same rate (clock tolerance,
#: jitter in the time stamps).
RATE_TOLERANCE = 0.02

#: (lowest, highest, unit) of a 1000-2000 nm peak written in another unit.
_OTHER_UNITS = ((1e9, 2e9, "fm"), (1e6, 2e6, "pm"), (1.0, 2.0, "µm"), (1e-6, 2e-6, "m"))


def other_unit(value_nm: float) -> str | None:
    """The unit a 1000-2000 nm peak would have to be in to read ``value_nm`` as nm, if any."""
    for a, b, unit in _OTHER_UNITS:
        if 0.9 * a <= abs(value_nm) <= 1.1 * b:
            return unit
    return None


def unit_hint(value_nm: float) -> str:
    """Why ``value_nm`` (outside :data:`WL_RANGE_NM`) is not a peak wavelength in nm."""
    lo, hi = WL_RANGE_NM
    unit = other_unit(value_nm)
    if unit is not None:
        return (f"wavelength {float(value_nm)!r} nm outside {lo:g}-{hi:g} nm, likely a unit "
                f"mistake: it looks like {unit} (wavelengths are in nm)")
    return (f"wavelength {float(value_nm)!r} nm outside {lo:g}-{hi:g} nm, likely a unit mistake "
            "(wavelengths are in nm)")


def _real_array(value: Any, name: str) -> np.ndarray:
    try:
        a = np.asarray(value)
    except (ValueError, TypeError) as exc:  # ragged nesting
        raise InputError(f"{name} must be a rectangular array of numbers: {exc}") from None
    if a.dtype == object:
        raise InputError(f"{name} must be a rectangular array of real numbers, not a ragged or "
                         "mixed list")
    if a.dtype.kind == "b":
        raise InputError(f"{name} must be real numbers, not booleans")
    if a.dtype.kind == "c":
        raise InputError(f"{name} must be real numbers, not complex (the imaginary part would be "
                         "lost)")
    if a.dtype.kind in "USV":
        raise InputError(f"{name} must be numbers, not text")
    if a.dtype.kind not in "iuf":
        raise InputError(f"{name} must be real numbers, not {a.dtype} values")
    return a


def wavelength_array(value: Any, *, name: str = "wavelengths", integers_are_fm: bool = False,
                     single: bool = False, check_unit: bool = True) -> np.ndarray:
    """Validate peak wavelengths, shape (n, 5): gratings 1..4 and T.

    Parameters
    ----------
    value
        Anything numpy makes an array of.
    name
        What to call it in errors.
    integers_are_fm
        Integer arrays are int32 femtometres (the C runtime's unit: any int32 is what an
        interrogator can send, so their unit is not judged, the fault rule judges each value),
        floats nm; otherwise every array is nm.
    single
        Also accept one sample of shape (5,), returned as (1, 5).
    check_unit
        Judge the unit (below); off for readers that check every value themselves.

    Returns
    -------
    numpy.ndarray
        (n, 5): float64 nm, or int64 fm for integer input with ``integers_are_fm``.

    Raises
    ------
    InputError
        Not real numbers, not (n, 5), or nm in another unit: the median of the non-zero
        finite values reads as pm, fm, µm or m (:func:`other_unit`). Other values outside the
        window are lost peaks, sensor faults of their samples.
    """
    a = _real_array(value, name)
    if single and a.ndim == 1:
        a = a.reshape(1, -1)
    if a.ndim != 2 or a.shape[1] != N_GRATINGS:
        want = "(n, 5) or (5,)" if single else "(n, 5)"
        raise InputError(f"{name} must be shaped {want} (FBG 1..4 and T), got {a.shape}")
    fm = integers_are_fm and a.dtype.kind in "iu"
    if fm:
        if a.size and (a.min() < -2**31 or a.max() > 2**31 - 1):
            raise InputError(f"{name}: integer wavelengths (fm) outside the int32 range")
        return a.astype(np.int64)
    a = a.astype(np.float64)
    finite = a[np.isfinite(a) & (a != 0)] if check_unit else a[:0]
    if finite.size:
        typical = float(np.median(finite))
        lo, hi = WL_RANGE_NM
        if not lo <= typical <= hi and other_unit(typical) is not None:
            raise InputError(f"{name}: typical " + unit_hint(typical))
    return a


def sensor_fault_rows(wl_nm: np.ndarray) -> np.ndarray:
    """(n,) True where a sample has a lost peak: a non-finite value or one outside
    :data:`WL_RANGE_NM` (the C runtime's window rule, which every engine applies)."""
    wl = np.asarray(wl_nm, dtype=np.float64)
    lo, hi = WL_RANGE_NM
    with np.errstate(invalid="ignore"):
        ok = (wl >= lo) & (wl <= hi)
    return ~ok.all(axis=1)


def model_rate_hz(model: Any) -> float | None:
    """The sample rate a model was trained at (its metadata), or None if it does not say."""
    rate = (getattr(model, "metadata", None) or {}).get("filter", {}).get("sample_rate_hz")
    return float(rate) if rate else None


def check_rate(model: Any, rate_hz: float, where: str | None = None) -> None:
    """Refuse data sampled at another rate than the model was trained at.

    The filter taps and memory time constants are counted in samples: at half the rate the
    same model smooths over twice the time and reads a held load differently.

    Raises
    ------
    InputError
        Naming both rates and the remedy (resample the data, or train at its rate).
    """
    trained = model_rate_hz(model)
    if trained is None or not np.isfinite(rate_hz) or rate_hz <= 0:
        return
    if abs(rate_hz - trained) > RATE_TOLERANCE * trained:
        raise InputError(f"sampled at {rate_hz:.6g} Hz but the model was trained at "
                         f"{trained:.6g} Hz; resample the data (evaluate --resample, "
                         "fbgforce.recordings.dataset.resample) or train a model at this rate", path=where)
