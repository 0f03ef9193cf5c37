"""ONNX export: checker, graph naming, and agreement of onnxruntime with the float64 model."""
from __future__ import annotations

import numpy as np
import onnx
import pytest

from fbgforce.errors import InputError
from fbgforce.export import onnx_export as ox
from fbgforce.model.artifact import HierarchicalModel, Memory, MLP, Preprocess
from fbgforce.model.floatref import features, numpy_nets, predict, predict_from_features
from fbgforce.model.floatref import location_inputs as fm_location_inputs
from fbgforce.units import estimate_shown

EPS32 = float(np.finfo(np.float32).eps)


def _mlp(rng: np.random.Generator, sizes: list[int]) -> MLP:
    # He initialisation keeps activations O(1) through the ReLU layers, like a trained net.
    return MLP([rng.standard_normal((b, a)) * np.sqrt(2.0 / a) for a, b in zip(sizes[:-1], sizes[1:])],
               [rng.standard_normal(b) * 0.1 for b in sizes[1:]])


def _model(seed: int = 0, width: float = 1.0, memory: Memory | None = None) -> HierarchicalModel:
    rng = np.random.default_rng(seed)
    memory = memory or Memory()
    f = 4 + memory.n_states
    h = [max(2, int(round(n * width))) for n in (70, 50, 20, 40)]
    taps = np.exp(-0.5 * (np.arange(9) / 3.0) ** 2)
    pre = Preprocess(temp_coeff=[1.02, 0.98, 1.01, 0.99], filter_kind="causal", filter_sigma=3.0,
                     taps=taps / taps.sum(), input_mean=[5.0, -3.0, 8.0, 1.0],
                     input_std=[40.0, 35.0, 50.0, 45.0], memory=memory)
    return HierarchicalModel(
        preprocess=pre,
        contact=_mlp(rng, [f, h[0], h[1], h[2], 2]),
        force=_mlp(rng, [f, h[0], h[1], h[2], 1]),
        location=_mlp(rng, [6 + memory.n_loc, h[0], h[1], h[3], 2]),
        force_offset=12.0, force_scale=15.0, xy_offset=[10.5, 13.5], xy_scale=[6.0, 7.5],
        baseline_nm=[1546.1, 1548.2, 1550.3, 1552.4, 1554.5])


def _abs_forward(net: MLP, x: np.ndarray) -> np.ndarray:
    """Forward pass with |W|, |b|, |x|: the magnitude that float32 rounding errors scale with."""
    a = np.abs(x)
    for w, b in zip(net.weights, net.biases):
        a = a @ np.abs(w).T + np.abs(b)
    return a


def _bound(net: MLP, x: np.ndarray) -> np.ndarray:
    # Standard dot-product error analysis: |fl(w.a) - w.a| <= gamma_n |w|.|a| per layer, with
    # n the fan-in; summed over layers (plus input rounding), a few-fold safety factor.
    n = sum(w.shape[1] for w in net.weights) + 1
    return 4.0 * n * EPS32 * _abs_forward(net, x)


def _recording(seed: int, n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Raw wavelengths (n, 5) nm: presses of random strength/shape, noise, temperature drift."""
    rng = np.random.default_rng(seed)
    base = np.array([1546.1, 1548.2, 1550.3, 1552.4, 1554.5])
    load = np.zeros(n)
    for start in range(100, n - 400, 500):
        t = np.arange(300)
        load[start:start + 300] = rng.uniform(5, 60) * np.sin(np.pi * t / 300) ** 2
    sens = rng.uniform(-3.0, 3.0, size=(4,))  # pm per N, per strain grating
    temp_pm = np.cumsum(rng.standard_normal(n)) * 0.05
    wl = np.empty((n, 5))
    wl[:, :4] = base[:4] + 1e-3 * (load[:, None] * sens + temp_pm[:, None]
                                   + rng.standard_normal((n, 4)) * 3.0)
    wl[:, 4] = base[4] + 1e-3 * temp_pm
    return wl, base + 1e-3 * rng.standard_normal(5)


@pytest.fixture(scope="module")
def model() -> HierarchicalModel:
    return _model()


@pytest.fixture(scope="module")
def exported(model: HierarchicalModel, tmp_path_factory: pytest.TempPathFactory):
    d = tmp_path_factory.mktemp("model")
    proto = ox.export_onnx(model, d / ox.ONNX_FILE)
    return d, proto


def test_checker_opset_and_dynamic_batch(exported) -> None:
    d, proto = exported
    loaded = onnx.load(d / ox.ONNX_FILE)
    onnx.checker.check_model(loaded, full_check=True)
    assert [o.version for o in loaded.opset_import if o.domain in ("", "ai.onnx")] == [17]
    dims = loaded.graph.input[0].type.tensor_type.shape.dim
    assert dims[0].dim_param == "N" and dims[1].dim_value == 4
    assert [i.name for i in loaded.graph.input] == list(ox.INPUT_NAMES)
    decision = loaded.graph.input[1].type.tensor_type
    assert decision.elem_type == onnx.TensorProto.BOOL
    assert [d.dim_param for d in decision.shape.dim] == ["N"]
    assert [o.name for o in loaded.graph.output] == list(ox.OUTPUT_NAMES)
    props = {p.key: p.value for p in loaded.metadata_props}
    assert props[ox.LAYOUT_KEY] == ox.GRAPH_LAYOUT and ox.DECISION_NAME in props["fbgforce.location_input"]
    assert props["fbgforce.contact_decision"] == ox.CONTACT_DECISION_HOW
    assert props["fbgforce.per_sample_decision"] == "true"


def test_node_names_read_like_fig4(exported) -> None:
    _, proto = exported
    names = [n.name for n in proto.graph.node]
    assert len(names) == len(set(names))
    for net, n_layers in (("contact_net", 4), ("force_net", 4), ("location_net", 4)):
        gemms = [n for n in proto.graph.node if n.name.startswith(net + "/fc")]
        assert [n.name for n in gemms] == [f"{net}/fc{k}" for k in range(1, n_layers + 1)]
        assert all(n.op_type == "Gemm" for n in gemms)
    concat = next(n for n in proto.graph.node if n.name == "hierarchy/location_input")
    assert concat.input[1] == "hierarchy/decision_f" and concat.input[2] == "force_net/out"
    # The location net reads the decision input, not the contact net's own decision.
    cast = next(n for n in proto.graph.node if n.output[0] == "hierarchy/decision_f")
    column = next(n for n in proto.graph.node if n.output[0] == cast.input[0])
    assert column.op_type == "Unsqueeze" and column.input[0] == ox.DECISION_NAME


@pytest.mark.parametrize("width", [1.0, 0.25])
def test_onnxruntime_matches_float64_on_random_inputs(tmp_path, width: float) -> None:
    model = _model(seed=3, width=width)
    ox.export_onnx(model, tmp_path / ox.ONNX_FILE)
    rng = np.random.default_rng(1)
    # Typical, large and exactly-zero standardised inputs.
    z = np.concatenate([rng.standard_normal((2000, 4)), 8.0 * rng.standard_normal((200, 4)),
                        np.zeros((1, 4))])
    _check_agreement(model, z, ox.run_features(model, z, tmp_path))


def test_onnxruntime_matches_float64_on_realistic_recordings(model, exported) -> None:
    d, _ = exported
    for seed in range(3):
        wl, base = _recording(seed)
        z = features(model, wl, base)
        _check_agreement(model, z, ox.run_features(model, z, d))
        # The engine entry point gates exactly like fbgforce.model.floatref.predict.
        got = ox.run_recording(d, model, wl, base)
        ref = predict(model, wl, base)
        same = got["contact"] == ref["contact"]
        assert same.mean() > 0.99
        assert np.array_equal(np.isnan(got["x_mm"][same]), np.isnan(ref["x_mm"][same]))
        hidden = ~estimate_shown(got["contact"], got["status"])
        assert np.all(got["force_N"][hidden] == 0.0)
        assert np.all(np.isnan(got["y_mm"][hidden]))
        np.testing.assert_allclose(got["force_N"][same], ref["force_N"][same], rtol=0, atol=1e-3)
        assert set(got) == {"contact", "p_contact", "force_N", "x_mm", "y_mm", "status"}


def _check_agreement(model: HierarchicalModel, z: np.ndarray, got: dict[str, np.ndarray]) -> None:
    ref = predict_from_features(model, z)
    x, z = z, z[:, :model.preprocess.n_features]   # the location averages are for location only
    logits = model.contact.forward(z)
    margin = logits[:, 1] - logits[:, 0]
    lb = _bound(model.contact, z)
    np.testing.assert_array_less(np.abs(got["contact_logits"] - logits), lb + 1e-30)
    # A decision may flip only where the float32 error could reach the threshold.
    flipped = got["contact"] != ref["contact"]
    assert np.all(np.abs(margin[flipped]) <= lb[flipped].sum(axis=1))
    fb = abs(model.force_scale) * _bound(model.force, z)[:, 0] + 4 * EPS32 * np.abs(ref["force_raw_N"])
    assert np.all(np.abs(got["force_N"] - ref["force_raw_N"]) <= fb)
    # Location: compare where the contact input agrees (it is 0/1 and steers the net).
    ok = ~flipped
    _check_location(model, x, ref["contact"], ok, (got["x_mm"], got["y_mm"]),
                    (ref["x_raw_mm"], ref["y_raw_mm"]))
    np.testing.assert_allclose(got["p_contact"], ref["p_contact"], rtol=0, atol=1e-5 + lb.sum(axis=1).max())


def _check_location(model: HierarchicalModel, x: np.ndarray, contact: np.ndarray, ok: np.ndarray,
                    got: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray]) -> None:
    """float32 ``got`` (x, y) against float64 ``ref`` on the rows ``ok``, the location net fed
    ``contact``: within the float32 bound of the location net and of the force net's error
    it reads."""
    z = x[:, :model.preprocess.n_features]
    loc_in = fm_location_inputs(x, contact, model.force.forward(z)[:, 0],
                                model.preprocess.memory.n_loc)[ok]
    lbound = _bound(model.location, loc_in)
    # The force input carries the force net's own float32 error into the location net; a ReLU
    # net's Jacobian is bounded elementwise by the product of its |W|, so propagate with those.
    err_prop = _bound(model.force, z[ok])[:, 0:1] * np.abs(model.location.weights[0][:, 5])
    for w in model.location.weights[1:]:
        err_prop = err_prop @ np.abs(w).T
    xy_bound = lbound + err_prop
    for k in range(2):
        err = np.abs(got[k][ok] - ref[k][ok])
        assert np.all(err <= abs(model.xy_scale[k]) * xy_bound[:, k] + 4 * EPS32 * np.abs(ref[k][ok]))


def _loc_model() -> HierarchicalModel:
    return _model(seed=6, width=0.5, memory=Memory(ema_shifts=(3,), play_widths=(0.1,),
                                                   weights=(0.3, 0.2, 0.4, 0.1), loc_shift=5))


def test_location_reads_the_decision_fed(tmp_path) -> None:
    """x_mm and y_mm are the location of the decision fed, whatever the contact net says; and
    onnx_nets feeds the decision its caller's ``decide`` returns, as the float64 nets do, on
    the rows where that decision is not the net's own too."""
    model = _loc_model()
    ox.export_onnx(model, tmp_path / ox.ONNX_FILE)
    wl, base = _recording(0)
    x = features(model, wl, base)
    everywhere = np.ones(x.shape[0], dtype=bool)
    for decision in (everywhere, ~everywhere):
        ref = numpy_nets(model)(x, lambda margin: decision)
        got = ox.run_features(model, x, tmp_path, decision=decision)
        _check_location(model, x, decision, everywhere, (got["x_mm"], got["y_mm"]),
                        (ref["x_raw_mm"], ref["y_raw_mm"]))
    # A decision that differs from the net's own on every fifth sample (as the decision over
    # time does where it holds a contact through the release, or has not yet risen).
    flip = np.arange(x.shape[0]) % 5 == 0

    def decide(margin: np.ndarray) -> np.ndarray:
        return (margin > 0.0) ^ flip

    ref = numpy_nets(model)(x, decide)
    got = ox.onnx_nets(model, tmp_path)(x, decide)
    same = got["contact"] == ref["contact"]
    assert same.mean() > 0.99 and ref["contact"].any() and not ref["contact"].all()
    assert np.array_equal(got["contact"], (got["margin"] > 0.0) ^ flip)
    _check_location(model, x, ref["contact"], same, (got["x_raw_mm"], got["y_raw_mm"]),
                    (ref["x_raw_mm"], ref["y_raw_mm"]))
    # The check can fail: the location of the net's own decision is another one on those rows.
    own = ox.run_features(model, x, tmp_path, decision=got["margin"] > 0.0)
    assert np.abs(own["x_mm"][flip & same] - ref["x_raw_mm"][flip & same]).max() > 0.1


def _old_layout(proto: onnx.ModelProto) -> onnx.ModelProto:
    """``proto`` as a graph without the decision input and without the layout key: its
    location net reads the contact net's own decision (``hierarchy/contact_2d``)."""
    old = onnx.ModelProto()
    old.CopyFrom(proto)
    del old.graph.input[1]
    column = next(n for n in old.graph.node if n.output[0] == "hierarchy/decision_2d")
    column.op_type = "Identity"
    del column.input[:]
    column.input.append("hierarchy/contact_2d")
    keep = [p for p in old.metadata_props if p.key != ox.LAYOUT_KEY]
    del old.metadata_props[:]
    old.metadata_props.extend(keep)
    onnx.checker.check_model(old, full_check=True)
    return old


def test_graph_of_another_layout_is_not_used(tmp_path) -> None:
    """A model.onnx from these very weights but without the decision input (no layout key)
    is stale: the engine builds the current graph in memory and gives the float model's
    location, where the file would give the location of the net's own decision."""
    import onnxruntime as ort

    model = _loc_model()
    (tmp_path / ox.ONNX_FILE).write_bytes(_old_layout(ox.build_graph(model)).SerializeToString())
    props = {p.key: p.value for p in onnx.load(tmp_path / ox.ONNX_FILE).metadata_props}
    assert props[ox.DIGEST_KEY] == ox.weights_digest(model)
    assert "layout" in ox.stale_reason(props, model)
    assert ox.stale_reason({**props, ox.LAYOUT_KEY: ox.GRAPH_LAYOUT}, model) is None
    assert "weights" in ox.stale_reason({**props, ox.LAYOUT_KEY: ox.GRAPH_LAYOUT},
                                        _model(seed=7, width=0.5, memory=model.preprocess.memory))
    sess = ox.session_for(model, tmp_path)
    assert [i.name for i in sess.get_inputs()] == list(ox.INPUT_NAMES)
    wl, base = _recording(1)
    x = features(model, wl, base)
    flip = np.arange(x.shape[0]) % 4 == 0

    def decide(margin: np.ndarray) -> np.ndarray:
        return (margin > 0.0) ^ flip

    ref = numpy_nets(model)(x, decide)
    got = ox.onnx_nets(model, tmp_path)(x, decide)
    same = got["contact"] == ref["contact"]
    _check_location(model, x, ref["contact"], same, (got["x_raw_mm"], got["y_raw_mm"]),
                    (ref["x_raw_mm"], ref["y_raw_mm"]))
    stale = ort.InferenceSession(str(tmp_path / ox.ONNX_FILE), providers=["CPUExecutionProvider"])
    old_x = stale.run(["x_mm"], {ox.INPUT_NAME: x.astype(np.float32)})[0]
    assert np.abs(old_x[same & flip] - ref["x_raw_mm"][same & flip]).max() > 0.1


def test_batch_sizes_one_and_many(model, exported) -> None:
    d, _ = exported
    z = np.random.default_rng(5).standard_normal((7, 4))
    many = ox.run_features(model, z, d)
    for i in range(7):
        one = ox.run_features(model, z[i:i + 1], d)
        for key in ox.OUTPUT_NAMES:
            assert one[key].shape[0] == 1
            np.testing.assert_allclose(one[key], many[key][i:i + 1], rtol=1e-6, atol=1e-6)


def test_stale_file_is_not_used(tmp_path) -> None:
    old, new = _model(seed=1), _model(seed=2)
    ox.export_onnx(old, tmp_path / ox.ONNX_FILE)
    z = np.random.default_rng(0).standard_normal((50, 4))
    got = ox.run_features(new, z, tmp_path)
    np.testing.assert_allclose(got["force_N"], predict_from_features(new, z)["force_raw_N"],
                               rtol=1e-4, atol=1e-3)
    assert ox.session_for(new, tmp_path) is ox.session_for(new, tmp_path)


def test_corrupt_file_is_refused(tmp_path) -> None:
    (tmp_path / ox.ONNX_FILE).write_bytes(b"\x08\x07this is not a protobuf\xff\xff")
    with pytest.raises(InputError, match="ONNX"):
        ox.run_features(_model(seed=4), np.zeros((1, 4)), tmp_path)


def test_trained_model_on_simulated_recording(small_model_dir, small_dataset_path, tmp_path) -> None:
    """A model the trainer produced, on the simulator's recording: onnxruntime == float64."""
    from fbgforce.recordings import dataset as fds
    from fbgforce.model.modeldir import load
    from fbgforce.recordings.tare import tare

    model = load(small_model_dir)
    ds = fds.load(small_dataset_path)
    base = tare(ds.wl_nm, ds.contact, ds.t_s)[0]
    z = features(model, ds.wl_nm, base)
    ox.export_onnx(model, tmp_path / ox.ONNX_FILE)
    got = ox.run_features(model, z, tmp_path)
    _check_agreement(model, z, got)
    assert 0.05 < got["contact"].mean() < 0.95  # both branches of the hierarchy exercised


def test_memory_and_location_averages_reach_the_nets_they_belong_to(tmp_path) -> None:
    """With memory, the graph's input ends with the location averages: the contact and force
    nets read the columns before them, the location net z, contact, force and the averages;
    onnxruntime agrees with the float64 model on recordings."""
    model = _model(seed=5, width=0.5, memory=Memory(ema_shifts=(3,), play_widths=(0.1,),
                                                    weights=(0.3, 0.2, 0.4, 0.1), loc_shift=5))
    proto = ox.export_onnx(model, tmp_path / ox.ONNX_FILE)
    dim = proto.graph.input[0].type.tensor_type.shape.dim[1].dim_value
    assert dim == model.preprocess.n_inputs == 4 + 2 + 4
    concat = next(n for n in proto.graph.node if n.name == "hierarchy/location_input")
    assert list(concat.input[1:]) == ["hierarchy/decision_f", "force_net/out",
                                      "hierarchy/location_averages"]
    for seed in range(2):
        wl, base = _recording(seed)
        z = features(model, wl, base)
        assert z.shape[1] == 10
        _check_agreement(model, z, ox.run_features(model, z, tmp_path))
