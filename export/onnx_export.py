"""ONNX export of the float model and the onnxruntime engine.

The graph holds the part of :mod:`fbgforce.model`'s pipeline after preprocessing: the three
nets of the paper's Fig. 4 and their hierarchy, in one graph, evaluated in float32::

    z [N,F] ─► contact_net ─► contact_logits [N,2] ─► hierarchy/contact (logit1 > logit0)
      │                                                  ─► contact [N], p_contact [N]
      ├──────► force_net ─► f [N,1] ──► hierarchy/force_scale ─► force_N [N]
      │                       │
    contact_decision [N] ─────┤
      │                       │
      └──────────────► hierarchy/location_input = [z[:, :4], contact_decision, f]
                                 ─► location_net ─► hierarchy/xy_scale ─► x_mm [N], y_mm [N]

The location net reads the contact *decision* as 0/1, and the decision is a second input,
``contact_decision``, because the decision the float model gates on is not the contact net's
own: with the model's in-use parameters it is the decision over time
(:func:`fbgforce.model.decision.decide_over_time`, a Schmitt trigger with a rise count whose state runs
from sample to sample), which one evaluation of a feed-forward graph cannot give. The caller
decides from the graph's ``contact_logits`` and runs the location with that decision
(:func:`onnx_nets` does it in two runs, the second on the samples decided "contact" only).
The location net also reads the force net's *unscaled* output ``f``, as trained.

The outputs ``force_N``, ``x_mm`` and ``y_mm`` are *ungated*: the graph does not zero the force
or blank the location; the caller gates them with the decision it fed (``run_recording`` does,
by :func:`fbgforce.units.gate_outputs`, the one rule of every engine). This keeps the graph
free of NaN constants and lets a user see what the nets say near the threshold.

Tare, temperature compensation, filtering, standardisation and the memory features stay
outside the graph: they are recording-level (recursive) operations done in float64 by
:mod:`fbgforce.model` (the C runtime does them in fixed point); the graph's input ``z`` is the
whole feature vector, ``[N, F]`` with F = 4 without memory. So do the stages after the nets
(the decision over time, the settled-hold gain, the at-rest tracker), whose parameters the
graph's metadata carries (``fbgforce.in_use``).
"""
from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any, Callable

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from fbgforce import __version__
from fbgforce.errors import InputError
from fbgforce.model.freshness import weights_digest
from fbgforce.model.artifact import HierarchicalModel, MLP
from fbgforce.model.floatref import (features, FloatPipeline, Nets, predict_from_features,
                                     safe_output)
from fbgforce.samples import sensor_fault_rows

#: File name of the exported graph inside a model directory.
ONNX_FILE = "model.onnx"
OPSET = 17
#: IR version 8 is what opset 17 was released with; every onnxruntime >= 1.14 reads it.
IR_VERSION = 8
INPUT_NAME = "z"
#: The second input: the contact decision (bool [N]) the location net reads.
DECISION_NAME = "contact_decision"
#: Input names, in graph order.
INPUT_NAMES = (INPUT_NAME, DECISION_NAME)
#: Output names, in graph order.
OUTPUT_NAMES = ("contact_logits", "contact", "p_contact", "force_N", "x_mm", "y_mm")
#: Metadata key holding :func:`fbgforce.model.freshness.weights_digest` of the model the graph was
#: made from.
DIGEST_KEY = "fbgforce.weights_sha256"
#: Metadata key of the graph's layout (its inputs, outputs and their meaning) and the layout
#: this module writes and runs. A graph without the key, or with another value, has other
#: inputs (without ``contact_decision`` its location net read the contact net's own decision):
#: :func:`session_for` never runs it.
LAYOUT_KEY = "fbgforce.graph_layout"
GRAPH_LAYOUT = "2"
_BATCH = "N"
_NET_PREFIX = {"contact": "contact_net", "force": "force_net", "location": "location_net"}


class _Graph:
    """The nodes and initialisers of a graph being built, kept in the order they are added:
    the order the file stores them in, so the same model always gives the same bytes."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []

    def const(self, name: str, value: Any, dtype: type = np.float32) -> str:
        """Add an initialiser; returns its name."""
        self.inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def node(self, op: str, inputs: list[str], output: str, name: str, **attrs: Any) -> str:
        """Add a node with one output; returns the output's name."""
        self.nodes.append(helper.make_node(op, inputs, [output], name=name, **attrs))
        return output

    def mlp(self, net: MLP, prefix: str, x: str, out: str) -> None:
        """Add Gemm/Relu nodes named ``prefix/fc1``, ``prefix/relu1``, ... computing ``net(x)``."""
        last = len(net.weights) - 1
        prev = x
        for layer, (w, b) in enumerate(zip(net.weights, net.biases)):
            k = layer + 1
            w_name = self.const(f"{prefix}/fc{k}/W", w)
            b_name = self.const(f"{prefix}/fc{k}/b", b)
            gemm_out = out if layer == last else f"{prefix}/fc{k}/out"
            # transB=1: weights stay (n_out, n_in) as in fbgforce.model and the C runtime.
            self.node("Gemm", [prev, w_name, b_name], gemm_out, f"{prefix}/fc{k}", transB=1,
                      doc_string=f"{w.shape[1]} -> {w.shape[0]}" + ("" if layer == last else ", ReLU next"))
            if layer != last:
                prev = self.node("Relu", [gemm_out], f"{prefix}/h{k}", f"{prefix}/relu{k}")


def build_graph(model: HierarchicalModel) -> onnx.ModelProto:
    """Build (without saving) the ONNX model of ``model``'s nets; see the module docstring."""
    g = _Graph()
    z, axis_1 = _net_features(g, model)
    g.mlp(model.contact, _NET_PREFIX["contact"], z, "contact_logits")
    g.mlp(model.force, _NET_PREFIX["force"], z, "force_net/out")
    columns = _contact_nodes(g)
    _location_nodes(g, model, z, axis_1, columns["axis1"])
    _output_nodes(g, model, columns)
    graph = helper.make_graph(
        g.nodes, "fbgforce_hierarchical_net", _graph_inputs(model), _graph_outputs(), g.inits,
        doc_string="Hierarchical network of Kim et al. RA-L 2019 Fig. 4: contact -> force -> "
                   "location. The location net reads the input 'contact_decision'; outputs are "
                   "ungated: gate force/x/y with the decision fed.")
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              ir_version=IR_VERSION, producer_name="fbgforce",
                              producer_version=__version__,
                              doc_string="fbgforce float model after preprocessing (float32)")
    helper.set_model_props(proto, _metadata(model))
    return proto


def _net_features(g: _Graph, model: HierarchicalModel) -> tuple[str, str]:
    """The contact and force nets' input, and the name of the axis-1 constant ("" without
    location averages). With location averages the graph's input ends with them, and the
    two nets read the columns before them."""
    pre = model.preprocess
    if not pre.memory.n_loc:
        return INPUT_NAME, ""
    axis_1 = g.const("hierarchy/axis_1", [1], np.int64)
    z = g.node("Slice", [INPUT_NAME, g.const("hierarchy/features_begin", [0], np.int64),
                         g.const("hierarchy/features_end", [pre.n_features], np.int64), axis_1],
               "hierarchy/features", "hierarchy/features")
    return z, axis_1


def _contact_nodes(g: _Graph) -> dict[str, str]:
    """The contact net's own decision, sample by sample: margin = logit1 - logit0 > 0, as
    :mod:`fbgforce.model` decides (strict inequality), and its sigmoid. Returns the names of
    the column-slicing constants, which the output nodes use again."""
    starts0, starts1 = g.const("hierarchy/idx0", [0], np.int64), g.const("hierarchy/idx1", [1], np.int64)
    ends1, ends2 = starts1, g.const("hierarchy/idx2", [2], np.int64)
    axis1 = g.const("hierarchy/axis1", [1], np.int64)
    l0 = g.node("Slice", ["contact_logits", starts0, ends1, axis1], "hierarchy/logit0",
                "hierarchy/logit0")
    l1 = g.node("Slice", ["contact_logits", starts1, ends2, axis1], "hierarchy/logit1",
                "hierarchy/logit1")
    margin = g.node("Sub", [l1, l0], "hierarchy/margin", "hierarchy/margin")
    zero = g.const("hierarchy/zero", 0.0)
    contact_2d = g.node("Greater", [margin, zero], "hierarchy/contact_2d", "hierarchy/contact")
    g.node("Squeeze", [contact_2d, axis1], "contact", "hierarchy/contact_out")
    p_2d = g.node("Sigmoid", [margin], "hierarchy/p_contact_2d", "hierarchy/p_contact")
    g.node("Squeeze", [p_2d, axis1], "p_contact", "hierarchy/p_contact_out")
    return {"starts0": starts0, "ends1": ends1, "starts1": starts1, "ends2": ends2, "axis1": axis1}


def _location_nodes(g: _Graph, model: HierarchicalModel, z: str, axis_1: str, axis1: str) -> None:
    """The location net on [z, decision, f, location averages]: the decision the caller gates
    on (an input: see the module docstring) and the force net's unscaled output, as trained.
    The location net reads the four standardised channels, not the load signal's memory
    features."""
    pre = model.preprocess
    decision_f = g.node("Cast", [g.node("Unsqueeze", [DECISION_NAME, axis1], "hierarchy/decision_2d",
                                        "hierarchy/decision_column")],
                        "hierarchy/decision_f", "hierarchy/decision_as_float", to=TensorProto.FLOAT)
    z4 = g.node("Slice", [z, g.const("hierarchy/z_begin", [0], np.int64),
                          g.const("hierarchy/z_end", [4], np.int64),
                          g.const("hierarchy/z_axis", [1], np.int64)], "hierarchy/z4", "hierarchy/z4")
    loc_parts = [z4, decision_f, "force_net/out"]
    if pre.memory.n_loc:
        loc_parts.append(g.node("Slice", [INPUT_NAME, g.const("hierarchy/loc_begin", [pre.n_features], np.int64),
                                          g.const("hierarchy/loc_end", [pre.n_inputs], np.int64), axis_1],
                                "hierarchy/location_averages", "hierarchy/location_averages"))
    loc_in = g.node("Concat", loc_parts, "hierarchy/location_input", "hierarchy/location_input",
                    axis=1)
    g.mlp(model.location, _NET_PREFIX["location"], loc_in, "location_net/out")


def _output_nodes(g: _Graph, model: HierarchicalModel, columns: dict[str, str]) -> None:
    """The outputs in the model's units (force_N, x_mm, y_mm): the scales and offsets, taken
    in float64 on the host then rounded once to float32 constants."""
    axis1 = columns["axis1"]
    f_scaled = g.node("Add", [g.node("Mul", ["force_net/out", g.const("hierarchy/force_scale",
                                                                     [model.force_scale])],
                                     "hierarchy/force_times_scale", "hierarchy/force_times_scale"),
                              g.const("hierarchy/force_offset", [model.force_offset])],
                      "hierarchy/force_N_2d", "hierarchy/force_scale")
    g.node("Squeeze", [f_scaled, axis1], "force_N", "hierarchy/force_N_out")
    xy = g.node("Add", [g.node("Mul", ["location_net/out", g.const("hierarchy/xy_scale", model.xy_scale)],
                               "hierarchy/xy_times_scale", "hierarchy/xy_times_scale"),
                        g.const("hierarchy/xy_offset", model.xy_offset)],
                "hierarchy/xy_mm", "hierarchy/xy_scale")
    x2 = g.node("Slice", [xy, columns["starts0"], columns["ends1"], axis1], "hierarchy/x_2d", "hierarchy/x")
    y2 = g.node("Slice", [xy, columns["starts1"], columns["ends2"], axis1], "hierarchy/y_2d", "hierarchy/y")
    g.node("Squeeze", [x2, axis1], "x_mm", "hierarchy/x_out")
    g.node("Squeeze", [y2, axis1], "y_mm", "hierarchy/y_out")


def _graph_inputs(model: HierarchicalModel) -> list[onnx.ValueInfoProto]:
    """The graph's inputs, z and the contact decision, with what a caller feeds them."""
    return [helper.make_tensor_value_info(
        INPUT_NAME, TensorProto.FLOAT, [_BATCH, model.preprocess.n_inputs],
        doc_string="net inputs: standardised features (filtered compensated shift - input_mean) / "
                   "input_std, then the memory features and the location averages "
                   "(fbgforce.model.memory_features)"),
        helper.make_tensor_value_info(
            DECISION_NAME, TensorProto.BOOL, [_BATCH],
            doc_string="the contact decision the location net reads (as 0/1) and the caller "
                       "gates force_N, x_mm, y_mm with; see metadata fbgforce.contact_decision")]


def _graph_outputs() -> list[onnx.ValueInfoProto]:
    """The graph's outputs (:data:`OUTPUT_NAMES`), with their meaning."""
    return [
        helper.make_tensor_value_info("contact_logits", TensorProto.FLOAT, [_BATCH, 2],
                                      doc_string="contact net logits; index 1 is 'contact'"),
        helper.make_tensor_value_info("contact", TensorProto.BOOL, [_BATCH],
                                      doc_string="logit1 > logit0: the contact net's own "
                                                 "decision, sample by sample"),
        helper.make_tensor_value_info("p_contact", TensorProto.FLOAT, [_BATCH],
                                      doc_string="sigmoid(logit1 - logit0)"),
        helper.make_tensor_value_info("force_N", TensorProto.FLOAT, [_BATCH],
                                      doc_string="force, N, NOT gated by the decision"),
        helper.make_tensor_value_info("x_mm", TensorProto.FLOAT, [_BATCH],
                                      doc_string="x in the pad frame, mm, given contact_decision; "
                                                 "NOT gated by it"),
        helper.make_tensor_value_info("y_mm", TensorProto.FLOAT, [_BATCH],
                                      doc_string="y in the pad frame, mm, given contact_decision; "
                                                 "NOT gated by it"),
    ]


def _metadata(model: HierarchicalModel) -> dict[str, str]:
    """The graph's metadata: the weights it was made from and its layout (what
    :func:`stale_reason` checks), the nets' sizes, how to feed the decision, and the in-use
    stages' parameters, which run outside the graph."""
    sizes = {name: net.sizes for name, net in model.nets.items()}
    return {
        DIGEST_KEY: weights_digest(model),
        LAYOUT_KEY: GRAPH_LAYOUT,
        "fbgforce.net_sizes": str(sizes),
        "fbgforce.outputs_gated": "false",
        "fbgforce.location_input": f"[z1, z2, z3, z4, {DECISION_NAME} (0/1), force_net raw output"
                                   + (", location averages a1..a4]" if model.preprocess.memory.n_loc else "]"),
        "fbgforce.contact_decision": CONTACT_DECISION_HOW,
        "fbgforce.per_sample_decision": str(model.in_use.per_sample).lower(),
        "fbgforce.in_use": json.dumps(model.in_use.to_json(), sort_keys=True),
    }


#: How to feed ``contact_decision`` (metadata ``fbgforce.contact_decision``).
CONTACT_DECISION_HOW = (
    "bool [N]. Feed the decision the outputs are gated on. With the per-sample decision "
    "(fbgforce.per_sample_decision = true) it is the output 'contact'; otherwise it is the "
    "decision over time of the parameters in "
    "fbgforce.in_use on the margin m = logit1 - logit0 of consecutive samples "
    "(fbgforce.model.decide_over_time; docs/runtime.md, 'In use'). Either way the margin comes "
    "first: run with contact_decision all false, decide, then run the samples "
    "decided true again with true and take their x_mm, y_mm from that run.")


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
    # One thread: on the 2-core machines the project runs on it is faster than two for single
    # samples and batches alike (docs/export-onnx.md), and timing figures stay comparable with
    # the single-threaded C runtime.
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    return so


def stale_reason(props: dict[str, str], model: HierarchicalModel) -> str | None:
    """Why a stored graph with metadata ``props`` must not run as ``model``'s nets, or None.

    A graph is current when it was exported from these very weights
    (:func:`~fbgforce.model.freshness.weights_digest`, :data:`DIGEST_KEY`) in this module's layout
    (:data:`LAYOUT_KEY`): a graph of another layout has other inputs, and fed by this module it
    would either fail or compute the location from another contact input.
    """
    layout = props.get(LAYOUT_KEY)
    if layout != GRAPH_LAYOUT:
        return (f"graph layout {layout or 'without ' + LAYOUT_KEY}, not {GRAPH_LAYOUT} (its inputs "
                f"differ: run 'fbgforce export' again)")
    if props.get(DIGEST_KEY) != weights_digest(model):
        return "exported from other weights (retrained after export: run 'fbgforce export' again)"
    return None


def session_for(model: HierarchicalModel, model_dir: str | Path | None = None) -> Any:
    """The cached onnxruntime ``InferenceSession`` for ``model``.

    Uses ``model_dir/model.onnx`` when it exists and is current (:func:`stale_reason`: these
    very weights, this layout); otherwise builds the graph in memory, so a missing or stale
    file never changes the numbers. One session per (file, digest) is kept for the life of
    the process.
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
                if stale_reason({p.key: p.value for p in stored.metadata_props}, model) is None:
                    payload = source
            sess = ort.InferenceSession(payload, sess_options=_session_options(),
                                        providers=["CPUExecutionProvider"])
            _SESSIONS[key] = sess
        return sess


def _as_input(model: HierarchicalModel, z: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(z).reshape(-1, model.preprocess.n_inputs),
                                dtype=np.float32)


def _run(sess: Any, z32: np.ndarray, decision: np.ndarray) -> dict[str, np.ndarray]:
    values = sess.run(list(OUTPUT_NAMES), {INPUT_NAME: z32, DECISION_NAME: decision})
    return dict(zip(OUTPUT_NAMES, values))


def _decided(sess: Any, z32: np.ndarray, decide: Callable[[np.ndarray], np.ndarray]
             ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The graph's outputs with the location of the decision ``decide(margin)``; also that
    decision and the margin (float64 of the float32 logits).

    The decision needs the contact net's margin, so it cannot be fed in the run that computes
    it: the first run feeds "no contact" everywhere, and the rows decided "contact" run again
    with "contact" for their location. Every row's location, the ungated ``x_raw_mm`` and
    ``y_raw_mm`` of rows without contact included, is then the one the float model computes
    for it. "No contact" first because most samples of a gripper in use are at rest: a stream
    of single samples runs the graph once at rest and twice in contact. ``decide`` is called
    once (the decision over time carries its state from call to call).
    """
    n = z32.shape[0]
    out = _run(sess, z32, np.zeros(n, dtype=bool))
    logits = out["contact_logits"].astype(np.float64)
    margin = logits[:, 1] - logits[:, 0]
    decision = np.asarray(decide(margin), dtype=bool).reshape(n)
    rows = np.flatnonzero(decision)
    if rows.size:
        again = _run(sess, z32[rows], np.ones(rows.size, dtype=bool))
        for key in ("x_mm", "y_mm"):
            out[key][rows] = again[key]
    return out, decision, margin


def run_features(model: HierarchicalModel, z: np.ndarray, model_dir: str | Path | None = None,
                 decision: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Run the graph on net inputs ``z`` (n, F + location averages); returns the raw (ungated)
    outputs :data:`OUTPUT_NAMES`.

    ``decision``: (n,) the contact decision the location net reads (one run); None: the
    contact net's own, ``margin > 0`` (the ``contact`` output; two runs, :func:`_decided`),
    as :func:`fbgforce.model.floatref.predict_from_features` without ``decide``.
    """
    sess = session_for(model, model_dir)
    z32 = _as_input(model, z)
    if decision is not None:
        return _run(sess, z32, np.asarray(decision, dtype=bool).reshape(z32.shape[0]))
    return _decided(sess, z32, lambda margin: margin > 0.0)[0]


def onnx_nets(model: HierarchicalModel, model_dir: str | Path | None = None) -> Nets:
    """The nets in onnxruntime float32 (:data:`fbgforce.model.floatref.Nets`), for the float pipeline
    (:func:`fbgforce.model.floatref.predict_from_features`, :class:`fbgforce.model.floatref.FloatPipeline`):
    the location net reads the decision ``decide`` returns, as in
    :func:`fbgforce.model.floatref.numpy_nets`, so every stage after the nets (the decision over time,
    the settled-hold gain, the tracker) sees what it sees in the float model.

    ``model_dir``: where an exported ``model.onnx`` may be (:func:`session_for`).
    """
    def nets(x: np.ndarray, decide: Callable[[np.ndarray], np.ndarray]) -> dict[str, np.ndarray]:
        raw, contact, margin = _decided(session_for(model, model_dir), _as_input(model, x), decide)
        return {"contact": contact, "margin": margin,
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
