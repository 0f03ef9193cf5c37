"""The float model: the artifact the trainer writes and every later stage reads.

This module is the contract between training (``fbgforce.trainer``) and export / runtime
(``fbgforce.export``, ``fbgforce.pybind``): it defines what a model directory holds and the one
float64 implementation of the shipped pipeline, which is the reference every other engine
(onnxruntime, C float, C fixed-point) is compared against.

The pipeline, per sample ``n`` and strain channel ``i`` = 1..4 (docs/pipeline.md)::

    shift_i[n]  = 1000 * (wl_i[n] - baseline_i)                      # tare, pm
    shift_T[n]  = 1000 * (wl_T[n] - baseline_T)
    comp_i[n]   = shift_i[n] - temp_coeff_i * shift_T[n]              # temperature compensation
    filt_i[n]   = sum_k taps[k] * comp_i[n - k]                        # causal FIR, zero history
    z_i[n]      = (filt_i[n] - input_mean_i) / input_std_i            # standardisation
    logits      = contact_net(z)            -> contact = logits[1] > logits[0]
    f           = force_net(z)[0]           -> force_N = force_offset + force_scale * f
    (u, v)      = location_net([z, contact, f])
    x_mm        = xy_offset[0] + xy_scale[0] * u,   y_mm likewise
    outputs: force_N is 0 and x/y are NaN where contact is False.

The centred filter (``filter_kind == "centred"``) is the paper's offline smoothing, for
reproducing its figures; it uses future samples and cannot be exported to the runtime.
"""
from __future__ import annotations

import json
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.jsonutil import json_default
from fbgforce.errors import InputError

FORMAT_NAME = "fbgforce-model"
FORMAT_VERSION = 1
N_STRAIN = 4
FILTER_KINDS = ("causal", "centred", "none")
NET_NAMES = ("contact", "force", "location")
#: Inputs of the location net: the four standardised channels, the contact flag (0/1) and the
#: force net's own (scaled) output, exactly as it runs.
LOCATION_INPUTS = N_STRAIN + 2


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
    """

    temp_coeff: np.ndarray
    filter_kind: str
    filter_sigma: float
    taps: np.ndarray
    input_mean: np.ndarray
    input_std: np.ndarray

    def __post_init__(self) -> None:
        self.temp_coeff = np.asarray(self.temp_coeff, dtype=np.float64).reshape(N_STRAIN)
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
        The nets. Contact: 4 -> ... -> 2 logits (index 1 is "contact"). Force: 4 -> ... -> 1.
        Location: 6 -> ... -> 2 (inputs per :data:`LOCATION_INPUTS`).
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

    def __post_init__(self) -> None:
        self.xy_offset = np.asarray(self.xy_offset, dtype=np.float64).reshape(2)
        self.xy_scale = np.asarray(self.xy_scale, dtype=np.float64).reshape(2)
        self.baseline_nm = np.asarray(self.baseline_nm, dtype=np.float64).reshape(N_STRAIN + 1)
        self.force_offset = float(self.force_offset)
        self.force_scale = float(self.force_scale)
        expected = {"contact": (N_STRAIN, 2), "force": (N_STRAIN, 1), "location": (LOCATION_INPUTS, 2)}
        for name, (n_in, n_out) in expected.items():
            sizes = getattr(self, name).sizes
            if sizes[0] != n_in or sizes[-1] != n_out:
                raise ValueError(f"{name} net must map {n_in} inputs to {n_out} outputs, has {sizes}")

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

def compensate(model: HierarchicalModel, wl_nm: np.ndarray, baseline_nm: np.ndarray) -> np.ndarray:
    """Tare and temperature-compensate raw wavelengths.

    Parameters
    ----------
    wl_nm
        (n, 5) peak wavelengths of gratings 1..4 and T, nm.
    baseline_nm
        (5,) unloaded wavelengths to tare against, nm.

    Returns
    -------
    numpy.ndarray
        (n, 4) compensated strain-grating shifts in pm.
    """
    wl = np.asarray(wl_nm, dtype=np.float64)
    shift_pm = (wl - np.asarray(baseline_nm, dtype=np.float64)) * 1000.0
    return shift_pm[:, :N_STRAIN] - shift_pm[:, N_STRAIN:] * model.preprocess.temp_coeff


def apply_filter(pre: Preprocess, x: np.ndarray) -> np.ndarray:
    """Apply the model's FIR along axis 0 of ``x`` (one continuous recording).

    Causal: zero history before the first sample, as the runtime after a tare. Centred: edges
    padded with the nearest sample (offline only).
    """
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


def features(model: HierarchicalModel, wl_nm: np.ndarray, baseline_nm: np.ndarray) -> np.ndarray:
    """Standardised net inputs ``z`` (n, 4) for one continuous recording."""
    pre = model.preprocess
    filt = apply_filter(pre, compensate(model, wl_nm, baseline_nm))
    return (filt - pre.input_mean) / pre.input_std


def predict_from_features(model: HierarchicalModel, z: np.ndarray) -> dict[str, np.ndarray]:
    """Run the three nets on standardised inputs.

    Returns
    -------
    dict
        ``contact`` (bool), ``p_contact`` (softmax probability of contact), ``force_N``
        (0 where no contact), ``x_mm``/``y_mm`` (NaN where no contact), and the raw net
        outputs ``force_raw_N``, ``x_raw_mm``, ``y_raw_mm`` (before gating on contact).
    """
    z = np.asarray(z, dtype=np.float64)
    logits = model.contact.forward(z)
    margin = logits[:, 1] - logits[:, 0]
    contact = margin > 0.0
    p_contact = 1.0 / (1.0 + np.exp(-np.clip(margin, -500.0, 500.0)))
    f = model.force.forward(z)[:, 0]
    loc_in = np.column_stack([z, contact.astype(np.float64), f])
    uv = model.location.forward(loc_in)
    force_raw = model.force_offset + model.force_scale * f
    xy_raw = model.xy_offset + model.xy_scale * uv
    return {
        "contact": contact,
        "p_contact": p_contact,
        "force_N": np.where(contact, force_raw, 0.0),
        "x_mm": np.where(contact, xy_raw[:, 0], np.nan),
        "y_mm": np.where(contact, xy_raw[:, 1], np.nan),
        "force_raw_N": force_raw,
        "x_raw_mm": xy_raw[:, 0],
        "y_raw_mm": xy_raw[:, 1],
    }


def predict(model: HierarchicalModel, wl_nm: np.ndarray, baseline_nm: np.ndarray | None = None
            ) -> dict[str, np.ndarray]:
    """Full float pipeline on one continuous recording of raw wavelengths (n, 5) in nm."""
    base = model.baseline_nm if baseline_nm is None else baseline_nm
    return predict_from_features(model, features(model, wl_nm, base))


# --------------------------------------------------------------------------------------------
# Model directory I/O
# --------------------------------------------------------------------------------------------

MODEL_JSON = "model.json"
WEIGHTS_NPZ = "weights.npz"


def save(model: HierarchicalModel, directory: str | Path) -> Path:
    """Write ``model.json`` (readable parameters and metadata) and ``weights.npz``."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
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
            "group_delay_ms_at_1kHz": pre.group_delay_samples,
        },
        "nets": {name: {"sizes": net.sizes} for name, net in model.nets.items()},
        "force_offset": model.force_offset,
        "force_scale": model.force_scale,
        "xy_offset": model.xy_offset.tolist(),
        "xy_scale": model.xy_scale.tolist(),
        "baseline_nm": model.baseline_nm.tolist(),
        "metadata": model.metadata,
    }
    arrays = {}
    for name, net in model.nets.items():
        for layer, (w, b) in enumerate(zip(net.weights, net.biases)):
            arrays[f"{name}.W{layer}"] = w
            arrays[f"{name}.b{layer}"] = b
    np.savez(out / WEIGHTS_NPZ, **arrays)
    (out / MODEL_JSON).write_text(json.dumps(doc, indent=2, default=json_default) + "\n")
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
    if doc.get("version") != FORMAT_VERSION:
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
                         p["input_mean"], p["input_std"])
        return HierarchicalModel(
            preprocess=pre, force_offset=doc["force_offset"], force_scale=doc["force_scale"],
            xy_offset=doc["xy_offset"], xy_scale=doc["xy_scale"], baseline_nm=doc["baseline_nm"],
            metadata=doc.get("metadata", {}), **nets)
    except KeyError as exc:
        raise InputError(f"missing entry {exc.args[0]!r}", path=str(root)) from exc
    except ValueError as exc:
        raise InputError(str(exc), path=str(root)) from exc
