"""Trainer: nets, optimizer, preprocessing, metrics, engines, baseline, training (no simulator)."""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce.evaluation import engines, metrics
from fbgforce.model import artifact, floatref, modeldir
from fbgforce.errors import InputError
from fbgforce.trainer import baseline as bl
from fbgforce.trainer import preprocess as pp
from fbgforce.recordings import tare as fbgtare  # noqa: E402
from fbgforce.trainer.nets import FlatMLP, fit, mse, predict_batched, softmax_xent
from fbgforce.trainer.optim import AdamOptimizer


# ------------------------------------------------------------------------------ nets
@pytest.mark.parametrize("hidden", ["relu", "linear"])
@pytest.mark.parametrize("loss", ["xent", "mse"])
def test_gradient_matches_finite_differences(hidden, loss):
    rng = np.random.default_rng(3)
    net = FlatMLP([4, 9, 7, 3], rng, hidden=hidden)
    net.theta += rng.normal(0, 0.1, net.theta.size)  # non-zero biases too
    x = rng.standard_normal((11, 4))
    y = rng.integers(0, 3, 11) if loss == "xent" else rng.standard_normal((11, 3))
    fn = softmax_xent if loss == "xent" else mse
    out = net.forward(x, keep=True)
    _, dout = fn(out, y)
    dx = net.backward(dout)
    analytic = net.grad.copy()
    numeric = np.empty_like(analytic)
    eps = 1e-6
    for i in range(net.theta.size):
        old = net.theta[i]
        net.theta[i] = old + eps
        lp = fn(net.forward(x), y)[0]
        net.theta[i] = old - eps
        lm = fn(net.forward(x), y)[0]
        net.theta[i] = old
        numeric[i] = (lp - lm) / (2 * eps)
    assert np.max(np.abs(analytic - numeric)) < 1e-7 * max(1.0, np.max(np.abs(numeric)))
    # Input gradient too (chained nets and the gradient check of the data path).
    num_dx = np.empty_like(x)
    for idx in np.ndindex(*x.shape):
        xp, xm = x.copy(), x.copy()
        xp[idx] += eps
        xm[idx] -= eps
        num_dx[idx] = (fn(net.forward(xp), y)[0] - fn(net.forward(xm), y)[0]) / (2 * eps)
    assert np.allclose(dx, num_dx, atol=1e-7)


def test_flat_mlp_matches_model_contract():
    rng = np.random.default_rng(0)
    net = FlatMLP([4, 70, 50, 20, 2], rng)
    x = rng.standard_normal((50, 4))
    assert np.allclose(net.forward(x), net.to_mlp().forward(x))
    again = FlatMLP([4, 70, 50, 20, 2], init=net.to_mlp())
    assert np.array_equal(again.theta, net.theta)
    with pytest.raises(ValueError):
        FlatMLP([4, 10, 2], init=net.to_mlp())


def test_adam_minimises_a_quadratic():
    target = np.array([3.0, -2.0, 0.5])
    theta = np.zeros(3)
    opt = AdamOptimizer(3, learning_rate_init=0.1, decay=0.99)
    for _ in range(2000):
        opt.update_params(theta, 2 * (theta - target))
        if opt.t % 100 == 0:
            opt.epoch_ends()
    assert np.allclose(theta, target, atol=1e-3)
    assert opt.learning_rate == pytest.approx(0.1 * 0.99 ** 20)


def test_contact_net_learns_a_nonlinear_boundary():
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (6000, 4))
    y = (x[:, 0] ** 2 + x[:, 1] ** 2 > 0.4).astype(np.int64)
    net = FlatMLP([4, 70, 50, 20, 2], rng)
    fit(net, "xent", x[:5000], y[:5000], x[5000:], y[5000:], epochs=40, progress=False, rng=rng)
    acc = np.mean(np.argmax(net.forward(x[5000:]), 1) == y[5000:])
    assert acc > 0.95


@pytest.mark.slow
def test_force_and_location_nets_learn_regressions():
    rng = np.random.default_rng(2)
    x = rng.uniform(-1, 1, (6000, 6))
    f = (x[:, 0] * x[:, 1] + np.sin(2 * x[:, 2]))[:, None]
    xy = np.column_stack([x[:, 3] - x[:, 4] ** 2, x[:, 5] * x[:, 0]])
    for sizes, inp, target in (([4, 70, 50, 20, 1], x[:, :4], f), ([6, 70, 50, 40, 2], x, xy)):
        net = FlatMLP(sizes, rng)
        start = mse(net.forward(inp[5000:]), target[5000:])[0]
        rep = fit(net, "mse", inp[:5000], target[:5000], inp[5000:], target[5000:], epochs=40,
                  progress=False, rng=rng)
        end = mse(predict_batched(net, inp[5000:]), target[5000:])[0]
        assert end < 0.02 * np.var(target) and end < 0.1 * start
        assert rep["best_val_loss"] == pytest.approx(end)


def test_early_stopping_keeps_best_epoch():
    rng = np.random.default_rng(4)
    x = rng.standard_normal((400, 4))
    y = rng.standard_normal((400, 1))  # pure noise: validation loss cannot keep improving
    net = FlatMLP([4, 70, 50, 20, 1], rng)
    rep = fit(net, "mse", x[:300], y[:300], x[300:], y[300:], epochs=200, patience=3,
              learning_rate=1e-2, progress=False, rng=rng)
    assert rep["epochs_run"] < 200
    assert rep["epochs_run"] - rep["best_epoch"] == 3
    assert mse(net.forward(x[300:]), y[300:])[0] == pytest.approx(rep["best_val_loss"])


# ------------------------------------------------------------------------------ preprocessing
@pytest.mark.parametrize("sigma", [1.0, 3.0, 8.0])
def test_causal_filter_uses_no_future_sample(sigma):
    taps = pp.gaussian_taps("causal", sigma)
    assert taps.sum() == pytest.approx(1.0) and np.all(np.diff(taps) < 0)
    pre = pp.make_preprocess("causal", sigma, np.ones(4))
    rng = np.random.default_rng(0)
    x = rng.standard_normal((500, 4))
    y = floatref.apply_filter(pre, x)
    for n0 in (0, 1, 137, 499):
        x2 = x.copy()
        x2[n0:] += rng.standard_normal(x2[n0:].shape) * 100
        y2 = floatref.apply_filter(pre, x2)
        assert np.array_equal(y2[:n0], y[:n0])
        assert not np.allclose(y2[n0], y[n0])
    # Group delay of a half-Gaussian ~ sigma * sqrt(2/pi), reported in ms at the sample rate.
    assert pp.group_delay_ms(pre, 1000.0) == pytest.approx(np.dot(np.arange(taps.size), taps))
    if sigma >= 3:
        assert pp.group_delay_ms(pre, 1000.0) == pytest.approx(sigma * np.sqrt(2 / np.pi), rel=0.15)
    assert pp.group_delay_ms(pre, 500.0) == pytest.approx(2 * pp.group_delay_ms(pre, 1000.0))


def test_centred_filter_is_symmetric_and_none_is_identity():
    taps = pp.gaussian_taps("centred", 4.0)
    assert taps.size % 2 == 1 and np.allclose(taps, taps[::-1])
    assert pp.gaussian_taps("none", 4.0).tolist() == [1.0]
    assert pp.make_preprocess("causal", 0.0, np.ones(4)).filter_kind == "none"
    with pytest.raises(InputError):
        pp.gaussian_taps("boxcar", 2.0)


def test_compensation_removes_a_pure_temperature_ramp(synthetic_recording):
    coeff = np.array([0.95, 1.0, 1.03, 1.08])
    # No contact at all: 30 presses with zero force are just rest; 400 pm of drift (~20 K).
    ds = synthetic_recording(n_press=30, temp_ramp_pm=400.0, noise_pm=2.0, temp_coeff=coeff)
    free = ds.subset(~ds.contact)
    base, info = fbgtare.tare(free.wl_nm, free.contact, free.t_s)
    shift = (free.wl_nm - base) * 1000.0
    mask = fbgtare.contact_free_mask(free.contact, free.t_s)
    k, tinfo = pp.fit_temp_coeff([shift], [mask])
    assert np.allclose(k, coeff, atol=0.01)
    assert min(tinfo["temp_coeff_identified"]) > 0.99
    pre = pp.make_preprocess("causal", 5.0, k)
    comp = pp.recording_features(pre, free.wl_nm, base)
    raw = shift[:, :4] - shift[:, 4:]  # plain reference subtraction, k = 1
    assert np.std(comp[50:]) < 2.0  # noise only (2 pm white, smoothed)
    assert np.ptp(raw[:, 3]) > 25.0  # the ramp would have stayed without the fitted k


def test_temperature_fit_falls_back_to_one_without_temperature_variation(synthetic_recording):
    ds = synthetic_recording(n_press=20, temp_ramp_pm=0.0, noise_pm=5.0)
    base, _ = fbgtare.tare(ds.wl_nm, ds.contact, ds.t_s)
    shift = (ds.wl_nm - base) * 1000.0
    k, info = pp.fit_temp_coeff([shift], [fbgtare.contact_free_mask(ds.contact, ds.t_s)])
    assert np.allclose(k, 1.0, atol=0.05)
    assert max(info["temp_coeff_identified"]) < 0.5


def test_tare_prefers_start_and_rejects_files_without_rest():
    wl = np.tile([1530.0, 1538.0, 1546.0, 1554.0, 1562.0], (100, 1))
    contact = np.zeros(100, bool)
    contact[40:] = True
    wl[40:, :4] -= 0.5
    wl[90:] += 0.01  # late drift after unloading must not move a start tare
    contact[90:] = False
    base, info = fbgtare.tare(wl, contact)
    assert info["tare_from"] == "start" and info["tare_samples"] == 40
    assert np.allclose(base, [1530, 1538, 1546, 1554, 1562])
    with pytest.raises(InputError, match="no contact-free"):
        fbgtare.tare(wl, np.ones(100, bool), path="x.csv")


# ------------------------------------------------------------------------------ metrics
def test_metric_definitions():
    tc = np.array([1, 1, 1, 0, 0, 1], bool)
    tf = np.array([10.0, 20.0, 3.0, 0.0, 0.0, 6.0])
    tx = np.array([1.0, 2.0, 3.0, np.nan, np.nan, 10.0])
    ty = np.array([4.0, 5.0, 6.0, np.nan, np.nan, 13.0])
    pred = {"contact": np.array([1, 1, 0, 1, 0, 1], bool),
            "force_N": np.array([11.0, 18.0, 99.0, 2.0, 0.0, 6.0]),  # 99 is gated to 0
            "x_mm": np.array([1.5, 2.0, np.nan, 7.0, np.nan, 10.0]),
            "y_mm": np.array([4.0, 6.0, np.nan, 7.0, np.nan, 13.0])}
    m = metrics.compute(pred, tc, tf, tx, ty, pad_mm=(21.0, 27.0))
    assert m["n_samples"] == 6
    assert m["contact_accuracy"] == pytest.approx(4 / 6)
    # Force over the 4 true contacts, the missed one counting its full 3 N.
    assert m["rmse_force_N"] == pytest.approx(np.sqrt((1 + 4 + 9 + 0) / 4))
    # Location over the 3 samples where both say contact.
    assert m["rmse_x_mm"] == pytest.approx(np.sqrt(0.25 / 3))
    assert m["rmse_y_mm"] == pytest.approx(np.sqrt(1 / 3))
    assert m["contact_accuracy_above_5N"] == pytest.approx(1.0)  # 10, 20, 6 N all detected
    assert m["false_contact_rate"] == pytest.approx(0.5)
    low = m["by_force"][0]
    assert low["range_N"] == [0.0, 5.0] and low["n_samples"] == 1
    assert low["rmse_force_N"] == pytest.approx(3.0) and low["rmse_x_mm"] is None
    # Only sample 0 (x = 1 mm) is closer than 2 mm to an edge; sample 1 is exactly 2 mm away.
    assert m["boundary"]["n_samples"] == 1 and m["interior"]["n_samples"] == 3
    assert m["boundary"]["rmse_x_mm"] == pytest.approx(0.5)
    core = metrics.compute(pred, tc, tf, tx, ty, extras=False)
    assert set(core) == {"contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm", "n_samples"}


def test_common_location_scores_every_estimator_on_the_same_samples():
    tc = np.array([1, 1, 1, 0], bool)
    tx = np.array([1.0, 2.0, 3.0, np.nan])
    ty = np.array([4.0, 5.0, 6.0, np.nan])
    # "lax" misses the hard third touch, so its own x RMSE looks better than "keen"'s.
    lax = {"contact": np.array([1, 1, 0, 0], bool), "x_mm": np.array([1.0, 3.0, np.nan, np.nan]),
           "y_mm": np.array([4.0, 5.0, np.nan, np.nan])}
    keen = {"contact": np.array([1, 1, 1, 1], bool), "x_mm": np.array([1.5, 2.0, 7.0, 0.0]),
            "y_mm": np.array([4.0, 5.5, 6.0, 0.0])}
    own = {k: metrics.compute({**p, "force_N": np.ones(4)}, tc, np.ones(4), tx, ty,
                              extras=False)["rmse_x_mm"]
           for k, p in (("lax", lax), ("keen", keen))}
    assert own["lax"] < own["keen"]
    c = metrics.common_location({"lax": lax, "keen": keen}, tc, tx, ty)
    assert c["n_samples"] == 2
    assert c["lax"]["rmse_x_mm"] == pytest.approx(np.sqrt(1 / 2))
    assert c["keen"]["rmse_x_mm"] == pytest.approx(np.sqrt(0.25 / 2))
    assert c["keen"]["rmse_y_mm"] == pytest.approx(np.sqrt(0.25 / 2))
    assert c["keen"]["rmse_x_mm"] < c["lax"]["rmse_x_mm"]
    none = metrics.common_location({"lax": lax, "never": {**keen, "contact": np.zeros(4, bool)}},
                                   tc, tx, ty)
    assert none["n_samples"] == 0 and none["lax"]["rmse_x_mm"] is None


# ------------------------------------------------------------------------------ engines
def _tiny_model(rng):
    pre = pp.make_preprocess("causal", 2.0, np.ones(4))
    nets = {name: FlatMLP(s, rng).to_mlp() for name, s in
            (("contact", [4, 8, 2]), ("force", [4, 8, 1]), ("location", [6, 8, 2]))}
    return artifact.HierarchicalModel(preprocess=pre, force_offset=1.0, force_scale=2.0,
                                xy_offset=[10, 13], xy_scale=[3, 4],
                                baseline_nm=[1530, 1538, 1546, 1554, 1562], **nets)


def test_float_engine_and_errors(tmp_path):
    rng = np.random.default_rng(0)
    model = _tiny_model(rng)
    wl = model.baseline_nm + rng.normal(0, 0.05, (200, 5))
    out = engines.run_engine("float", None, model, wl, model.baseline_nm)
    ref = floatref.predict(model, wl, model.baseline_nm)
    for k in ("contact", "force_N", "p_contact"):
        assert np.array_equal(out[k], ref[k])
    modeldir.save(model, tmp_path / "m")
    again = engines.run_engine("float", tmp_path / "m", None, wl, model.baseline_nm)
    assert np.allclose(again["force_N"], ref["force_N"])
    with pytest.raises(InputError, match="unknown engine"):
        engines.run_engine("gpu", None, model, wl, model.baseline_nm)
    with pytest.raises(InputError, match=r"\(n, 5\)"):
        engines.run_engine("float", None, model, wl[:, :4], model.baseline_nm)
    assert engines.available()["float"] is True


# ------------------------------------------------------------------------------ baseline
def test_nominal_baseline_inverts_the_nominal_model_and_fit_recovers_a_device():
    from fbgforce.geometry import NOMINAL

    rng = np.random.default_rng(0)
    f = rng.uniform(1, 70, 3000)
    x, y = rng.uniform(0, 21, 3000), rng.uniform(0, 27, 3000)
    shift = (NOMINAL.forward(f, x, y) - NOMINAL.base_wl_nm)[:, :4] * 1000.0
    nom = bl.nominal()
    nom.contact_threshold_N = 0.5
    p = nom.predict(shift)
    assert np.allclose(p["force_N"], f) and np.allclose(p["x_mm"], x) and np.allclose(p["y_mm"], y)
    device = NOMINAL.replace(gain=[0.9, 1.1, 0.95, 1.05],
                             supports_mm=NOMINAL.supports_mm + [[0.3, 1.0], [-0.2, 0.8],
                                                                [0.1, -1.2], [0.0, 0.5]])
    dshift = (device.forward(f, x, y) - device.base_wl_nm)[:, :4] * 1000.0
    wrong = nom.predict(dshift)
    fitted = bl.fit(dshift, f, x, y)
    fitted.contact_threshold_N = 0.5
    # A rigid pad has 3 degrees of freedom, so the four shifts span a 3-D subspace and the 12
    # parameters are identifiable only up to one null direction; the PREDICTIONS are exact.
    good = fitted.predict(dshift)
    for key, truth in (("force_N", f), ("x_mm", x), ("y_mm", y)):
        assert np.allclose(good[key], truth, atol=1e-6)
    assert np.sqrt(np.mean((wrong["y_mm"] - y) ** 2)) > 0.3


# ------------------------------------------------------------------------------ training
@pytest.mark.slow
def test_train_is_reproducible_and_metadata_matches_evaluate(synthetic_recording, tmp_path):
    from fbgforce.recordings import dataset
    from fbgforce.trainer.evaluate import evaluate
    from fbgforce.trainer.train import train

    ds = synthetic_recording(n_press=30, seed=1, temp_ramp_pm=100.0)
    path = tmp_path / "rec.npz"
    dataset.save(ds, path)
    kw = dict(epochs=4, seed=7, progress=False, idle_pads=0,
              sizes={"contact": [16, 8], "force": [16, 8], "location": [16, 8]})
    a = train([path], **kw)
    b = train([ds], **kw)
    for name in artifact.NET_NAMES:
        for wa, wb in zip(a.nets[name].weights, b.nets[name].weights):
            assert np.array_equal(wa, wb)
    md = a.metadata
    assert md["data"][0]["sha256"] and md["seed"] == 7
    # The location net reads the four channels, the contact flag and the force, not the
    # load signal's memory features, then the location averages of the default memory
    # (fbgforce.contract.net_inputs).
    assert md["sizes"]["location"] == [artifact.N_STRAIN + 2 + artifact.N_STRAIN, 16, 8, 2]
    assert md["split"]["samples"]["train"] > 5 * md["split"]["samples"]["test"] > 0
    modeldir.save(a, tmp_path / "m")
    ev = evaluate(tmp_path / "m", [path], split="test")
    for k in ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm", "n_samples"):
        assert ev[k] == pytest.approx(md["metrics"]["test"][k], rel=1e-9)
    # Contact timing: the same presses and delays whether scored by train or by evaluate.
    assert ev["contact_timing"] == md["metrics"]["test"]["contact_timing"]
    assert ev["contact_timing"]["presses"] >= 1


@pytest.mark.slow
def test_restarts_keep_the_lowest_validation_loss_and_leave_the_first_draw(synthetic_recording):
    from fbgforce.trainer.train import train

    ds = synthetic_recording(n_press=30, seed=3)
    kw = dict(epochs=3, seed=5, progress=False, idle_pads=0, track_calibration=False,
              sizes={"contact": [16, 8], "force": [16, 8], "location": [16, 8]})
    one = train([ds], restarts=1, **kw)
    three = train([ds], restarts={"force": 3}, **kw)
    # The contact net never restarts; the force net's first draw is the single-draw net.
    for wa, wb in zip(one.contact.weights, three.contact.weights):
        assert np.array_equal(wa, wb)
    single, best_of = one.metadata["training"]["force"], three.metadata["training"]["force"]
    draws = best_of["restarts"]["val_losses"]
    assert len(draws) == 3 and draws[0] == single["best_val_loss"]
    assert len(set(draws)) == 3  # independent initialisations, not copies
    assert best_of["best_val_loss"] == min(draws) == draws[best_of["restarts"]["kept"]]
    assert len(three.metadata["training"]["location"]["restarts"]["val_losses"]) == 1
    if best_of["restarts"]["kept"] != 0:
        assert not np.array_equal(one.force.weights[0], three.force.weights[0])


def test_unread_units_are_dropped_and_float32_outputs_stay():
    from fbgforce.model.artifact import MLP
    from fbgforce.trainer.nets import drop_unread_units

    rng = np.random.default_rng(4)
    sizes = [6, 9, 7, 5, 2]
    w = [rng.normal(size=(o, i)) for i, o in zip(sizes[:-1], sizes[1:])]
    b = [rng.normal(size=o) for o in sizes[1:]]
    w[3][:, [1, 2]] = 1e-318       # units 1, 2 of the last hidden layer: switched off by decay
    w[2][:, [4, 5]] = 0.0          # units 4, 5 of the middle layer: never read
    w[1][:, [1, 3]] = 0.0          # units 1, 3 of the first: read only by ...
    w[1][4, 1] = w[1][5, 3] = 0.7  # ... middle units 4 and 5, which go: so they go too
    w[3][1, 3] = 1e-30             # small, but float32 reads it: unit 3 stays
    full = MLP(w, b)
    pruned, dropped = drop_unread_units(full)
    assert dropped == 6 and pruned.sizes == [6, 7, 5, 3, 2]
    x = rng.normal(size=(500, 6)) * 3

    def f32(m: MLP) -> np.ndarray:
        a = x.astype(np.float32)
        for l, (wl, bl) in enumerate(zip(m.weights, m.biases)):
            a = a @ wl.astype(np.float32).T + bl.astype(np.float32)
            if l < len(m.weights) - 1:
                a = np.maximum(a, 0)
        return a

    np.testing.assert_allclose(f32(pruned), f32(full), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(pruned.forward(x), full.forward(x), rtol=1e-12, atol=1e-12)
    # A layer nobody reads keeps one unit, so every layer still has a width.
    w2 = [wl.copy() for wl in w]
    w2[3][:] = 0.0
    empty, n = drop_unread_units(MLP(w2, b))
    assert empty.sizes == [6, 7, 5, 1, 2] and n == 4 + 2 + 2
    # Units go in pairs: one unread unit alone stays, so widths keep their parity.
    w3 = [wl + 1.0 for wl in w]
    w3[3][:, 2] = 0.0
    same, none = drop_unread_units(MLP(w3, b))
    assert none == 0 and same.sizes == sizes


@pytest.mark.slow
def test_default_weight_decay_falls_with_the_training_samples(synthetic_recording):
    from fbgforce.trainer.fit_nets import DEFAULT_DECAY_SAMPLES
    from fbgforce.trainer.train import train

    kw = dict(epochs=2, seed=5, progress=False, restarts=1, idle_pads=0,
              track_calibration=False,
              sizes={"contact": [16, 8], "force": [16, 8], "location": [16, 8]})
    short_log = synthetic_recording(n_press=20, seed=3)
    short = train([short_log], **kw)
    long = train([synthetic_recording(n_press=40, seed=3)], **kw)
    for m in (short, long):
        tr = m.metadata["training"]
        assert tr["force"]["weight_decay"] == pytest.approx(
            DEFAULT_DECAY_SAMPLES["force"] / tr["force"]["train_samples"])
        assert tr["contact"]["weight_decay"] == DEFAULT_DECAY_SAMPLES["contact"]
    n_short = short.metadata["training"]["force"]["train_samples"]
    n_long = long.metadata["training"]["force"]["train_samples"]
    assert n_long > 1.5 * n_short
    assert short.metadata["training"]["force"]["weight_decay"] > \
        1.5 * long.metadata["training"]["force"]["weight_decay"]
    # The recorded decay is the one used: given explicitly, it trains the same force net;
    # a value given for one net leaves the others at their defaults.
    wd = short.metadata["training"]["force"]["weight_decay"]
    again = train([short_log], weight_decay={"force": wd}, **kw)
    for wa, wb in zip(short.force.weights, again.force.weights):
        assert np.array_equal(wa, wb)
    # Units the decay switches off leave the model: what it records adds up.
    for m in (short, long):
        for name, net in m.nets.items():
            kept = sum(net.sizes[1:-1])
            assert kept + m.metadata["training"][name]["dropped_units"] == sum(kw["sizes"][name])
    other = train([short_log], weight_decay={"force": 10 * wd}, **kw)
    assert other.metadata["training"]["force"]["weight_decay"] == 10 * wd
    assert not np.array_equal(other.force.weights[0], short.force.weights[0])
    for wa, wb in zip(short.contact.weights, other.contact.weights):
        assert np.array_equal(wa, wb)


@pytest.mark.slow
def test_train_learns_synthetic_device_and_transfer_starts_closer(synthetic_recording, tmp_path):
    from fbgforce.trainer.train import train

    ds = synthetic_recording(n_press=30, seed=2, noise_pm=3.0)
    # Trained until it knows the device (40 epochs: 0.18 N on its test presses); one stopped
    # at 20 epochs or fewer starts the other device closer or not by the luck of its draw.
    # The subject is the transfer: the nets learn the recordings as tared.
    quick = dict(seed=0, progress=False, idle_pads=0, track_calibration=False)
    model = train([ds], epochs=40, **quick)
    test = model.metadata["metrics"]["test"]
    assert test["contact_accuracy"] > 0.95
    assert test["rmse_force_N"] < 3.0 and test["rmse_x_mm"] < 2.0 and test["rmse_y_mm"] < 2.5
    other = synthetic_recording(n_press=20, seed=3, base_nm=[1531, 1539, 1545, 1553, 1561])
    fresh = train([other], epochs=1, **quick)
    warm = train([other], epochs=1, init=model, **quick)
    f_loss = fresh.metadata["history"]["force"][0]["val_loss"]
    w_loss = warm.metadata["history"]["force"][0]["val_loss"]
    assert w_loss < f_loss
    assert np.array_equal(warm.preprocess.input_std, model.preprocess.input_std)


def test_train_rejects_bad_inputs(synthetic_recording):
    from fbgforce.trainer.train import train

    ds = synthetic_recording(n_press=5, seed=1)
    with pytest.raises(InputError, match="no training data"):
        train([], progress=False)
    no_rest = ds.subset(ds.contact)
    with pytest.raises(InputError, match="contact-free"):
        train([no_rest], epochs=1, progress=False)


def test_contact_by_force_and_press_delays():
    tc = np.array([0, 1, 1, 1, 1, 0, 0, 1, 1, 0], bool)
    tf = np.array([0.0, 0.3, 0.8, 1.5, 12.0, 0.0, 0.0, 3.0, 7.0, 0.0])
    pc = np.array([0, 0, 1, 1, 1, 1, 0, 0, 1, 0], bool)
    nan = np.full(10, np.nan)
    m = metrics.compute({"contact": pc, "force_N": tf, "x_mm": nan, "y_mm": nan}, tc, tf, nan,
                        nan)
    bins = {tuple(b["range_N"]): (b["n_samples"], b["contact_accuracy"])
            for b in m["contact_by_force"]}
    assert bins[(0.0, 0.5)] == (1, 0.0) and bins[(0.5, 1.0)] == (1, 1.0)
    assert bins[(2.0, 5.0)] == (1, 0.0) and bins[(10.0, 20.0)] == (1, 1.0)
    assert bins[(5.0, 10.0)] == (1, 1.0)
    assert m["contact_accuracy_above_1N"] == pytest.approx(3 / 4)
    # Two presses at 1 kHz: the first is detected 1 ms late and released 1 ms late, the
    # second 1 ms late and on time.
    t = np.arange(10) * 1e-3
    pid = np.array([5, 5, 5, 5, 5, 5, 9, 9, 9, 9])
    onset, release = metrics.press_delays(pc, tc, t, pid)
    assert np.allclose(onset, [1.0, 1.0]) and np.allclose(release, [1.0, 0.0])
    # Early onset (prediction already on before the true onset), early release, a miss, keep.
    pc2 = np.array([0, 1, 1, 1, 0, 0, 0, 0, 0, 0], bool)
    onset, release = metrics.press_delays(pc2, tc, t, pid)
    assert np.allclose(onset[:1], [0.0]) and np.allclose(release[:1], [-1.0])
    assert np.isnan(onset[1]) and np.isnan(release[1])
    pc3 = np.array([1, 1, 1, 1, 1, 1, 1, 1, 1, 1], bool)
    onset, release = metrics.press_delays(pc3, tc, t, pid, keep=np.arange(10) >= 6)
    assert np.allclose(onset, [-1.0]) and np.allclose(release, [1.0])  # runs to the end
    # Time stamps 83 s into a log: a 12-sample onset is 12 ms exactly, not a hair over the
    # in-use goal's 12 ms.
    tc12, pc12 = np.zeros(40, bool), np.zeros(40, bool)
    tc12[5:30], pc12[17:30] = True, True
    late = np.round(83.2717 + np.arange(40) / 1000.0, 6)
    onset, _ = metrics.press_delays(pc12, tc12, late, np.zeros(40, int))
    assert onset[0] == 12.0
    s = metrics.timing_summary(np.array([1.0, 3.0, np.nan]), np.array([0.0, 2.0, np.nan]))
    assert s["presses"] == 3 and s["missed_presses"] == 1
    assert s["onset_delay_ms"]["median"] == pytest.approx(2.0)
    assert s["release_delay_ms"]["max"] == pytest.approx(2.0)


def test_weight_decay_shrinks_weights():
    rng = np.random.default_rng(4)
    x = rng.standard_normal((400, 4))
    y = (x @ np.array([1.0, -2.0, 0.5, 0.0]))[:, None]
    norms = []
    for wd in (0.0, 5.0):
        net = FlatMLP([4, 16, 1], np.random.default_rng(0))
        # Adam moves each weight by about the learning rate per step: enough steps to shrink.
        fit(net, "mse", x, y, epochs=30, batch_size=16, learning_rate=3e-3, weight_decay=wd,
            progress=False, rng=np.random.default_rng(1))
        norms.append(sum(float(np.sum(w * w)) for w in net.W))
    assert norms[1] < 0.5 * norms[0]


def test_scaled_presses_scale_the_strain_features_per_press(synthetic_recording):
    from fbgforce.trainer.synthetic import scaled_presses
    from fbgforce.trainer.train import prepare

    ds = synthetic_recording(n_press=6, seed=3, noise_pm=0.0, temp_ramp_pm=50.0)
    data = prepare([ds], seed=0)
    pre = data.pre  # unit standardisation and no memory: the inputs are the filtered shifts
    rows = np.flatnonzero(data.contact & (data.force_N > 10.0))
    z, kept = scaled_presses(data, pre, rows, 3.0, np.random.default_rng(0))
    assert np.array_equal(kept, rows) and z.shape == (rows.size, data.inputs(pre).shape[1])
    # Deep inside a press the (linear) filter has forgotten the previous press: the strain
    # inputs are the original ones times the press's own factor in [1, 3].
    ratio = z[:, :artifact.N_STRAIN] / data.inputs(pre)[rows, :artifact.N_STRAIN]
    pid = np.asarray(ds.press_id)[rows]
    for p in np.unique(pid):
        r = ratio[pid == p]
        assert 1.0 <= r.min() and r.max() <= 3.0
        assert np.ptp(r) < 1e-6 * r.mean()


def test_training_progress_on_a_pipe_is_a_line_per_bar(monkeypatch):
    """On a pipe or in a log the bar draws at its own pace (one line at most every 10 s),
    also while the epochs update its numbers: not a line per epoch."""
    import io

    from fbgforce.trainer.nets import FlatMLP, fit

    err = io.StringIO()
    monkeypatch.setattr("sys.stderr", err)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(256, 4))
    y = x @ np.array([[1.0], [0.5], [-0.3], [0.2]])
    fit(FlatMLP([4, 8, 1], rng), "mse", x, y, x, y, epochs=30, patience=100, progress=True,
        desc="pipe")
    lines = [ln for ln in err.getvalue().replace("\r", "\n").splitlines() if "pipe" in ln]
    assert 1 <= len(lines) <= 3, lines


@pytest.mark.parametrize("name,value,column", [
    ("epochs", 0, "--epochs"), ("epochs", 2.5, "--epochs"), ("filter", "gauss", "--filter"),
    ("sigma", -1.0, "--sigma"), ("train_fraction", 1.5, "--train-fraction"),
    ("hold_augment", -0.1, "--hold-augment"), ("hold_augment", float("nan"), "--hold-augment"),
    ("turn_guard_s", -0.001, "--turn-guard"), ("turn_guard_s", 2.0, "--turn-guard"),
    ("learning_rate", 0.0, "learning_rate"), ("batch_size", True, "batch_size"),
    ("location_augment", 0.5, "location_augment"), ("plateau_factor", 1.0, "plateau_factor"),
    ("sizes", {"contact": [129]}, "--sizes"), ("sizes", {"contact": [0, 4]}, "--sizes"),
    ("sizes", {"force": [8] * 8}, "--sizes"), ("sizes", {"gripper": [8]}, "--sizes"),
    ("sizes", {"force": []}, "--sizes"), ("sizes", {"force": [8.5]}, "--sizes"),
    ("idle_pads", -1, "--idle-pads"), ("idle_pads", 2.0, "--idle-pads"),
    ("contact_plays", "on", "--contact-plays")])
def test_train_params_refuse_a_value_out_of_range_naming_the_option(name, value, column):
    from fbgforce.trainer.params import TrainParams

    with pytest.raises(InputError) as exc:
        TrainParams(**{name: value})
    assert exc.value.column == column and repr(value) in str(exc.value)


def test_train_takes_params_and_options_and_refuses_unknown_ones(synthetic_recording):
    from fbgforce.trainer.params import TrainParams
    from fbgforce.trainer.train import train

    with pytest.raises(TypeError, match="epoch"):
        train([synthetic_recording], epoch=3)
    with pytest.raises(InputError, match="--train-fraction"):
        train([synthetic_recording], TrainParams(epochs=1), train_fraction=0.0)


def test_sizes_set_the_hidden_widths_and_leave_the_other_nets_at_the_default(small_dataset_path,
                                                                             tmp_path):
    """``fbgforce train --sizes`` reaches the model; nets it does not name keep DEFAULT_SIZES
    (whose widths the force net's decay may trim, never widen)."""
    from fbgforce.model import modeldir as fm
    from fbgforce.cli import main
    from fbgforce.trainer.params import DEFAULT_SIZES

    out = tmp_path / "m"
    code = main(["train", "--data", str(small_dataset_path), "--out", str(out), "--epochs", "1",
                 "--restarts", "1", "--idle-pads", "0",
                 "--sizes", "contact=12-6,location=10-8-6-4"])
    assert code == 0
    nets = fm.load(out).nets
    assert nets["contact"].sizes[1:-1] == [12, 6]
    assert nets["location"].sizes[1:-1] == [10, 8, 6, 4]
    kept = nets["force"].sizes[1:-1]
    assert len(kept) == len(DEFAULT_SIZES["force"])
    assert all(0 < k <= d for k, d in zip(kept, DEFAULT_SIZES["force"]))


@pytest.mark.parametrize("flags, inverse, guard_s", [
    ([], False, 0.0),                                   # the smoke pad's creep is fast
    (["--creep-inverse"], True, 0.015),
    (["--creep-inverse", "--turn-guard", "4"], True, 0.004),
    (["--no-creep-inverse", "--turn-guard", "15"], False, 0.015)])
def test_creep_and_turn_guard_flags_reach_the_model(small_dataset_path, tmp_path, flags, inverse,
                                                    guard_s):
    """``--creep-inverse`` / ``--no-creep-inverse`` override the trainer's choice, and the
    turn guard follows the inverse unless ``--turn-guard`` sets it."""
    from fbgforce.model import modeldir as fm
    from fbgforce.cli import main

    out = tmp_path / "m"
    assert main(["train", "--data", str(small_dataset_path), "--out", str(out), "--epochs", "1",
                 "--restarts", "1", "--idle-pads", "0", "--track-calibration", "off",
                 *flags]) == 0
    md = fm.load(out).metadata
    assert md["creep"]["inverse"] is inverse and md["turn_guard_s"] == pytest.approx(guard_s)
