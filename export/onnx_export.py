"""ONNX export of the float model and the onnxruntime engine.

The graph holds the part of :mod:`fbgforce.model`'s pipeline after preprocessing: the three
nets of the paper's Fig. 4 and their hierarchy, in one graph, evaluated in float32::

    z [N,F] ─► contact_net ─► contact_logits [N,2] ─► hierarchy/contact (logit1 > logit0)
      │                                                    │
      ├──────► force_net ─► f [N,1] ──► hierarchy/force_scale ─► force_N [N]
      │                       │                            │
      └──────────────► hierarchy/location_input = [z[:, :4], contact, f] ─► location_net
                                                 ─► hierarchy/xy_scale ─► x_mm [N], y_mm [N]

Exactly as :func:`fbgforce.model.predict_from_features`, the location net is fed the contact
flag as 0/1 and the force net's *unscaled* output ``f``. The outputs ``force_N``, ``x_mm`` and
``y_mm`` are *ungated*: the graph does not zero the force or blank the location where it says
"no contact"; the caller gates them with the ``contact`` output (``run_recording`` does, by
:func:`fbgforce.units.gate_outputs`, the one rule of every engine). This
keeps the graph free of NaN constants and lets a user see what the nets say near the threshold.

Tare, temperature compensation, filtering, standardisation and the memory features stay
outside the graph: they are recording-level (recursive) operations done in float64 by
:mod:`fbgforce.model` (the C runtime does them in fixed point); the graph's input ``z`` is the
whole feature vector, ``[N, F]`` with F = 4 without memory.
"""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from fbgforce import __version__
from fbgforce.errors import InputError
from fbgforce.freshness import weights_digest
from fbgforce.model import (MLP, FloatPipeline, HierarchicalModel, Nets, features,
                            predict_from_features, safe_output)
from fbgforce.samples import sensor_fault_rows

#: File name of the exported graph inside a model directory.
ONNX_FILE = "model.onnx"
OPSET = 17
#: IR version 8 is what opset 17 was released with; every onnxruntime >= 1.14 reads it.
IR_VERSION = 8
INPUT_NAME = "z"
#: Output names, in graph order.
OUTPUT_NAMES = ("contact_logits", "contact", "p_contact", "force_N", "x_mm", "y_mm")
#: Metadata key holding :func:`fbgforce.freshness.weights_digest` of the model the graph was
#: made from.
DIGEST_KEY = "fbgforce.weights_sha256"
_BATCH = "N"
_NET_PREFIX = {"contact": "contact_net", "force": "force_net", "location": "location_net"}


def _mlp_nodes(net: MLP, prefix: str, x: str, out: str, inits: list[onnx.TensorProto],
               nodes: list[onnx.NodeProto]) -> None:
    """Append Gemm/Relu nodes named ``prefix/fc1``, ``prefix/relu1``, ... computing ``net(x)``."""
    last = len(net.weights) - 1
    prev = x
    for layer, (w, b) in enumerate(zip(net.weights, net.biases)):
        k = layer + 1
        w_name, b_name = f"{prefix}/fc{k}/W", f"{prefix}/fc{k}/b"
        inits.append(numpy_helper.from_array(w.astype(np.float32), w_name))
        inits.append(numpy_helper.from_array(b.astype(np.float32), b_name))
        gemm_out = out if layer == last else f"{prefix}/fc{k}/out"
        # transB=1: weights stay (n_out, n_in) as in fbgforce.model and the C runtime.
        nodes.append(helper.make_node(
            "Gemm", [prev, w_name, b_name], [gemm_out], name=f"{prefix}/fc{k}", transB=1,
            doc_string=f"{w.shape[1]} -> {w.shape[0]}" + ("" if layer == last else ", ReLU next")))
        if layer != last:
            prev = f"{prefix}/h{k}"
            nodes.append(helper.make_node("Relu", [gemm_out], [prev], name=f"{prefix}/relu{k}"))


def build_graph(model: HierarchicalModel) -> onnx.ModelProto:
    """Build (without saving) the ONNX model of ``model``'s nets; see the module docstring."""
    nodes: list[onnx.NodeProto] = []
    inits: list[onnx.TensorProto] = []

    def const(name: str, value: Any, dtype: type = np.float32) -> str:
        inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def node(op: str, inputs: list[str], output: str, name: str, **attrs: Any) -> str:
        nodes.append(helper.make_node(op, inputs, [output], name=name, **attrs))
        return output

    z = INPUT_NAME
    pre = model.preprocess
    n_loc = pre.memory.n_loc
    axis_1 = ""
    if n_loc:
        axis_1 = const("hierarchy/axis_1", [1], np.int64)
        # The input ends with the location averages; the contact and force nets read the
        # columns before them.
        z = node("Slice", [INPUT_NAME, const("hierarchy/features_begin", [0], np.int64),
                           const("hierarchy/features_end", [pre.n_features], np.int64), axis_1],
                 "hierarchy/features", "hierarchy/features")
    _mlp_nodes(model.contact, _NET_PREFIX["contact"], z, "contact_logits", inits, nodes)
    _mlp_nodes(model.force, _NET_PREFIX["force"], z, "force_net/out", inits, nodes)

    # Contact decision: margin = logit1 - logit0 > 0, as fbgforce.model (strict inequality).
    starts0, starts1 = const("hierarchy/idx0", [0], np.int64), const("hierarchy/idx1", [1], np.int64)
    ends1, ends2 = starts1, const("hierarchy/idx2", [2], np.int64)
    axis1 = const("hierarchy/axis1", [1], np.int64)
    l0 = node("Slice", ["contact_logits", starts0, ends1, axis1], "hierarchy/logit0",
              "hierarchy/logit0")
    l1 = node("Slice", ["contact_logits", starts1, ends2, axis1], "hierarchy/logit1",
              "hierarchy/logit1")
    margin = node("Sub", [l1, l0], "hierarchy/margin", "hierarchy/margin")
    zero = const("hierarchy/zero", 0.0)
    contact_2d = node("Greater", [margin, zero], "hierarchy/contact_2d", "hierarchy/contact")
    contact_f = node("Cast", [contact_2d], "hierarchy/contact_f", "hierarchy/contact_as_float",
                     to=TensorProto.FLOAT)
    node("Squeeze", [contact_2d, axis1], "contact", "hierarchy/contact_out")
    p_2d = node("Sigmoid", [margin], "hierarchy/p_contact_2d", "hierarchy/p_contact")
    node("Squeeze", [p_2d, axis1], "p_contact", "hierarchy/p_contact_out")

    # Location net input [z, contact, f, location averages]: the force net's unscaled output,
    # as trained. The location net reads the four standardised channels, not the load
    # signal's memory features.
    z4 = node("Slice", [z, const("hierarchy/z_begin", [0], np.int64), const("hierarchy/z_end", [4], np.int64),
                        const("hierarchy/z_axis", [1], np.int64)], "hierarchy/z4", "hierarchy/z4")
    loc_parts = [z4, contact_f, "force_net/out"]
    if n_loc:
        loc_parts.append(node("Slice", [INPUT_NAME, const("hierarchy/loc_begin", [pre.n_features], np.int64),
                                        const("hierarchy/loc_end", [pre.n_inputs], np.int64), axis_1],
                              "hierarchy/location_averages", "hierarchy/location_averages"))
    loc_in = node("Concat", loc_parts, "hierarchy/location_input", "hierarchy/location_input",
                  axis=1)
    _mlp_nodes(model.location, _NET_PREFIX["location"], loc_in, "location_net/out", inits, nodes)

    # Output scaling, in float64 on the host then rounded once to float32 constants.
    f_scaled = node("Add", [node("Mul", ["force_net/out", const("hierarchy/force_scale",
                                                                 [model.force_scale])],
                                 "hierarchy/force_times_scale", "hierarchy/force_times_scale"),
                            const("hierarchy/force_offset", [model.force_offset])],
                    "hierarchy/force_N_2d", "hierarchy/force_scale")
    node("Squeeze", [f_scaled, axis1], "force_N", "hierarchy/force_N_out")
    xy = node("Add", [node("Mul", ["location_net/out", const("hierarchy/xy_scale", model.xy_scale)],
                           "hierarchy/xy_times_scale", "hierarchy/xy_times_scale"),
                      const("hierarchy/xy_offset", model.xy_offset)],
              "hierarchy/xy_mm", "hierarchy/xy_scale")
    x2 = node("Slice", [xy, starts0, ends1, axis1], "hierarchy/x_2d", "hierarchy/x")
    y2 = node("Slice", [xy, starts1, ends2, axis1], "hierarchy/y_2d", "hierarchy/y")
    node("Squeeze", [x2, axis1], "x_mm", "hierarchy/x_out")
    node("Squeeze", [y2, axis1], "y_mm", "hierarchy/y_out")

    inputs = [helper.make_tensor_value_info(
        INPUT_NAME, TensorProto.FLOAT, [_BATCH, model.preprocess.n_inputs],
        doc_string="net inputs: standardised features (filtered compensated shift - input_mean) / "
                   "input_std, then the memory features and the location averages "
                   "(fbgforce.model.memory_features)")]
    outputs = [
        helper.make_tensor_value_info("contact_logits", TensorProto.FLOAT, [_BATCH, 2],
                                      doc_string="contact net logits; index 1 is 'contact'"),
        helper.make_tensor_value_info("contact", TensorProto.BOOL, [_BATCH],
                                      doc_string="logit1 > logit0"),
        helper.make_tensor_value_info("p_contact", TensorProto.FLOAT, [_BATCH],
                                      doc_string="sigmoid(logit1 - logit0)"),
        helper.make_tensor_value_info("force_N", TensorProto.FLOAT, [_BATCH],
                                      doc_string="force, N, NOT gated by contact"),
        helper.make_tensor_value_info("x_mm", TensorProto.FLOAT, [_BATCH],
                                      doc_string="x in the pad frame, mm, NOT gated by contact"),
        helper.make_tensor_value_info("y_mm", TensorProto.FLOAT, [_BATCH],
                                      doc_string="y in the pad frame, mm, NOT gated by contact"),
    ]
    graph = helper.make_graph(
        nodes, "fbgforce_hierarchical_net", inputs, outputs, inits,
        doc_string="Hierarchical network of Kim et al. RA-L 2019 Fig. 4: contact -> force -> "
                   "location. Outputs are ungated; gate force/x/y with 'contact'.")
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              ir_version=IR_VERSION, producer_name="fbgforce",
                              producer_version=__version__,
                              doc_string="fbgforce float model after preprocessing (float32)")
    sizes = {name: net.sizes for name, net in model.nets.items()}
    helper.set_model_props(proto, {
        DIGEST_KEY: weights_digest(model),
        "fbgforce.net_sizes": str(sizes),
        "fbgforce.outputs_gated": "false",
        "fbgforce.location_input": "[z1, z2, z3, z4, contact (0/1), force_net raw output"
                                   + (", location averages a1..a4]" if n_loc else "]"),
    })
    return proto


def export_onnx(model: HierarchicalModel, path: str | Path) -> onnx.ModelProto:
    """Write ``model``'s nets as one ONNX graph (opset 17, dynamic batch) and return it.

    Parameters
    ----------
    model
        The float model.
    path
        File to write (conventionally ``MODEL_DIR/model.onnx``); parent directories are made.

    Returns
    -------
    onnx.ModelProto
        The graph written, already through ``onnx.checker.check_model(full_check=True)``.
    """
    from fbgforce import fileio

    proto = checked_graph(model)
    fileio.write_bytes(path, proto.SerializeToString())
    return proto


def checked_graph(model: HierarchicalModel) -> onnx.ModelProto:
    """:func:`build_graph` through ``onnx.checker.check_model(full_check=True)``."""
    proto = build_graph(model)
    onnx.checker.check_model(proto, full_check=True)
    return proto


# --------------------------------------------------------------------------------------------
# onnxruntime engine
# --------------------------------------------------------------------------------------------

_SESSIONS: dict[tuple[str, str], Any] = {}
_LOCK = threading.Lock()


def _session_options() -> Any:
    import onnxruntime as ort

    so = ort.SessionOptions()
    # One thread: on these 2-core machines it is faster for both single samples and batches
    # (shared/recipes B), and timing figures stay comparable with the single-threaded C runtime.
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    return so


def session_for(model: HierarchicalModel, model_dir: str | Path | None = None) -> Any:
    """The cached onnxruntime ``InferenceSession`` for ``model``.

    Uses ``model_dir/model.onnx`` when it exists and was exported from these very weights
    (checked by :func:`~fbgforce.freshness.weights_digest`); otherwise builds the graph in memory, so a missing or
    stale file never changes the numbers. One session per (file, digest) is kept for the
    life of the process.
    """
    import onnxruntime as ort

    digest = weights_digest(model)
    path = Path(model_dir) / ONNX_FILE if model_dir is not None else None
    source = str(path.resolve()) if path is not None and path.is_file() else "<memory>"
    key = (source, digest)
    with _LOCK:
        sess = _SESSIONS.get(key)
        if sess is None:
            payload: bytes | str = build_graph(model).SerializeToString()
            if source != "<memory>":
                try:
                    stored = onnx.load(source, load_external_data=False)
                except Exception as exc:  # protobuf raises several types for a corrupt file
                    raise InputError(f"cannot read ONNX graph: {exc}", path=source) from exc
                props = {p.key: p.value for p in stored.metadata_props}
                if props.get(DIGEST_KEY) == digest:
                    payload = source
            sess = ort.InferenceSession(payload, sess_options=_session_options(),
                                        providers=["CPUExecutionProvider"])
            _SESSIONS[key] = sess
        return sess


def run_features(model: HierarchicalModel, z: np.ndarray, model_dir: str | Path | None = None
                 ) -> dict[str, np.ndarray]:
    """Run the graph on standardised features ``z`` (n, 4); returns the raw (ungated) outputs."""
    sess = session_for(model, model_dir)
    z32 = np.ascontiguousarray(np.asarray(z).reshape(-1, model.preprocess.n_inputs), dtype=np.float32)
    values = sess.run(list(OUTPUT_NAMES), {INPUT_NAME: z32})
    return dict(zip(OUTPUT_NAMES, values))


def onnx_nets(model: HierarchicalModel, model_dir: str | Path | None = None) -> Nets:
    """The nets in onnxruntime float32 (:data:`fbgforce.model.Nets`), for the float pipeline
    (:func:`fbgforce.model.predict_from_features`, :class:`fbgforce.model.FloatPipeline`).

    ``model_dir``: where an exported ``model.onnx`` may be (:func:`session_for`).
    """
    def nets(x: np.ndarray, decide: Any) -> dict[str, np.ndarray]:
        # The graph gates the location net on the net's own contact; the decision over time
        # differs from it only near its thresholds, where the location is not scored apart.
        raw = run_features(model, x, model_dir)
        logits = raw["contact_logits"].astype(np.float64)
        margin = logits[:, 1] - logits[:, 0]
        return {"contact": decide(margin), "margin": margin,
                "p_contact": raw["p_contact"].astype(np.float64),
                "force_raw_N": raw["force_N"].astype(np.float64),
                "x_raw_mm": raw["x_mm"].astype(np.float64), "y_raw_mm": raw["y_mm"].astype(np.float64)}
    return nets


def run_recording(model_dir: str | Path | None, model: HierarchicalModel, wl_nm: np.ndarray,
                  baseline_nm: np.ndarray) -> dict[str, np.ndarray]:
    """The ``onnx`` engine: float64 preprocessing in numpy, the nets in onnxruntime float32
    (:func:`onnx_nets`).

    Parameters
    ----------
    model_dir
        Model directory whose ``model.onnx`` to use if present and current (else built in
        memory); may be ``None``.
    model
        The loaded float model.
    wl_nm
        (n, 5) raw peak wavelengths of ONE continuous recording, nm.
    baseline_nm
        (5,) tare wavelengths, nm.

    Returns
    -------
    dict
        ``contact`` (bool), ``p_contact``, ``force_N`` (0 where no contact), ``x_mm``,
        ``y_mm`` (NaN where no contact), all float64 arrays of length n (``contact`` bool),
        ``status`` (``SENSOR_FAULT`` on samples with a lost peak, which get the safe output).
    """
    nets = onnx_nets(model, model_dir)
    wl = np.asarray(wl_nm, dtype=np.float64)
    if model.runs_in_use:
        out = FloatPipeline(model, baseline_nm, nets=nets).push(wl)
    else:
        out = safe_output(predict_from_features(model, features(model, wl, baseline_nm), nets=nets),
                          sensor_fault_rows(wl))
    return {k: out[k] for k in ("contact", "p_contact", "force_N", "x_mm", "y_mm", "status")}
