"""The steps of :func:`fbgforce.trainer.train.train` that fit the three nets: the contact net
(:func:`fit_contact`), the force net on what it passes (:func:`fit_force`) and the location
net (:func:`fit_location`), each the best of its restarts (:class:`NetFitter`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from fbgforce.model import artifact, floatref
from fbgforce.errors import InputError
from fbgforce.trainer import preprocess as pp
from fbgforce.trainer.data import Prepared
from fbgforce.trainer.nets import FlatMLP, fit, predict_batched, zero_columns
from fbgforce.trainer.params import TrainParams
from fbgforce.trainer.synthetic import Held, scaled_presses


#: The default L2 weight decay of each net, as a prior of fixed strength: the decay is this
#: many training samples' worth divided by the number of samples the net trains on. A fit
#: with a fixed Gaussian prior on the weights weighs it so against a loss averaged over n
#: samples, and so a short calibration log is regularised harder than a long one: 1.1e-4 for
#: the force net on the calibration scene (132,000 samples), 4.7e-4 on a 60-press log
#: (docs/measurements/trainer.md, "What limits training" and "Restarts and force weight decay").
DEFAULT_DECAY_SAMPLES: dict[str, float] = {"contact": 0.0, "force": 15.0, "location": 0.0}


#: Initialisations tried per net, the one with the lowest validation loss kept
#: (:func:`_fit_best_of`). The force net lands 0.38-0.42 N from one initialisation to the next
#: on the calibration scene and its validation loss ranks the draws as the test presses do;
#: the location net's draws differ by less than its validation presses can rank (the lowest
#: validation loss had a worse test y), and the contact net's errors are light touches in the
#: noise (docs/trainer.md, "Restarts and force weight decay").
DEFAULT_RESTARTS: dict[str, int] = {"contact": 1, "force": 3, "location": 1}


#: A press turns at its last sample at this fraction of its peak force or more
#: (:func:`after_turns`, ``turn_guard_s``).
TURN_FRACTION = 0.995


#: The turn guard a model that takes the pad's creep out before the filter trains with by
#: default (``turn_guard_s`` None): the causal filter's length (docs/trainer.md, "The turn").
TURN_GUARD_S = 0.015


def _per_net(value: Any, defaults: Mapping[str, Any], what: str, kind: Callable[[Any], Any]
             ) -> dict[str, Any]:
    """A per-net setting: the defaults, one value for all, or per-net overrides."""
    if value is None:
        return dict(defaults)
    if isinstance(value, Mapping):
        unknown = set(value) - set(defaults)
        if unknown:
            raise InputError(f"unknown net {sorted(unknown)[0]!r} in {what}; nets are "
                             f"{', '.join(defaults)}")
        return {**defaults, **{k: kind(v) for k, v in value.items()}}
    return {k: kind(value) for k in defaults}


def _weight_decays(weight_decay: float | Mapping[str, float] | None) -> dict[str, float | None]:
    """L2 weight decay per net as given (one value for all, or per-net overrides); None
    where the net takes the default (:func:`default_weight_decay`)."""
    return _per_net(weight_decay, {k: None for k in DEFAULT_DECAY_SAMPLES}, "weight_decay", float)


def default_weight_decay(name: str, n_samples: int) -> float:
    """The default L2 weight decay of net ``name`` trained on ``n_samples`` samples:
    :data:`DEFAULT_DECAY_SAMPLES` over ``n_samples``."""
    return DEFAULT_DECAY_SAMPLES[name] / max(int(n_samples), 1)


def _fit_best_of(tries: int, name: str, seed: int, sizes: Sequence[int],
                 rng_init: np.random.Generator, rng_fit: np.random.Generator,
                 init: Any, *args: Any, **kwargs: Any) -> tuple[FlatMLP, dict[str, Any]]:
    """Train ``tries`` initialisations of one net and keep the lowest validation loss.

    The first draw uses the caller's generators, so ``tries == 1`` is a plain
    :func:`~fbgforce.trainer.nets.fit`; the others get their own streams from ``(seed, the net's
    index in NET_NAMES, draw)``, so adding draws leaves the first one and every other net
    unchanged. The report is the kept draw's, with ``restarts``: every draw's best validation
    loss and the index of the kept one.
    """
    if tries < 1:
        raise InputError(f"restarts for the {name} net must be at least 1, not {tries}")
    best: tuple[FlatMLP, dict[str, Any]] | None = None
    losses, kept = [], 0
    desc = kwargs.pop("desc", f"{name} net")
    for i in range(tries):
        if i == 0:
            r_init, r_fit = rng_init, rng_fit
        else:
            r_init, r_fit = (np.random.default_rng(s) for s in
                             np.random.SeedSequence([seed, artifact.NET_NAMES.index(name), i]).spawn(2))
        net = FlatMLP(sizes, r_init, init=init)
        rep = fit(net, *args, desc=desc if tries == 1 else f"{desc} {i + 1}/{tries}",
                  rng=r_fit, **kwargs)
        losses.append(rep["best_val_loss"])
        if best is None or rep["best_val_loss"] < best[1]["best_val_loss"]:
            best, kept = (net, rep), i
    assert best is not None
    best[1]["restarts"] = {"val_losses": losses, "kept": kept}
    return best


class NetFitter:
    """Fits each net as :func:`~fbgforce.trainer.train.train` is asked to: the best of its
    restarts, its weight decay, the shared loop settings; keeps each net's report in
    :attr:`reports`."""

    def __init__(self, params: TrainParams, net_sizes: Mapping[str, Sequence[int]],
                 init_model: artifact.HierarchicalModel | None, rng_init: np.random.Generator,
                 has_validation: bool) -> None:
        self.params, self.net_sizes, self.init_model, self.rng_init = (params, net_sizes,
                                                                       init_model, rng_init)
        self.decays = _weight_decays(params.weight_decay)
        self.tries = _per_net(params.restarts, DEFAULT_RESTARTS, "restarts", int)
        if not has_validation or init_model is not None:
            self.tries = {k: 1 for k in self.tries}
        self.reports: dict[str, Any] = {}

    def __call__(self, name: str, rng_fit: np.random.Generator, loss: str, x: np.ndarray,
                 *args: Any, **kwargs: Any) -> FlatMLP:
        given = self.decays[name]
        wd = default_weight_decay(name, len(x)) if given is None else given
        net, self.reports[name] = _fit_best_of(
            self.tries[name], name, self.params.seed, self.net_sizes[name], self.rng_init, rng_fit,
            self.init_model.nets[name] if self.init_model else None, loss, x, *args,
            weight_decay=wd, **kwargs, **self.params.fit_settings())
        self.reports[name].update(weight_decay=wd, train_samples=int(len(x)))
        return net


@dataclass
class Scaling:
    """Input standardisation and output scaling (``force_N = offset + scale * f``, x/y alike)."""

    std: pp.Standardisation
    force_offset: float
    force_scale: float
    xy_offset: np.ndarray
    xy_scale: np.ndarray


def fit_contact(fit_net: NetFitter, data: Prepared, z: np.ndarray, tr: np.ndarray,
                va: np.ndarray, synth_tr: Held, synth_va: Held, rng: np.random.Generator,
                desc: str = "contact net", unread: Sequence[int] = ()
                ) -> tuple[FlatMLP, np.ndarray]:
    """The contact net on every sample and the synthetic ones (softmax cross-entropy);
    returns it and its logits on every row. ``desc`` names it on the progress bar.

    ``unread``: input columns the net does not read. It trains with them at 0 and its
    first layer's weights on them are set to 0, so every engine computes the same function
    on the full inputs without a change to the model's format."""
    nf = z.shape[1]
    labels = data.contact.astype(np.int64)
    zc_tr = zero_columns(np.concatenate([z[tr], synth_tr[0][:, :nf]]), unread)
    zc_va = zero_columns(np.concatenate([z[va], synth_va[0][:, :nf]]), unread)
    yc_tr = labels[np.concatenate([tr, synth_tr[1]])]
    yc_va = labels[np.concatenate([va, synth_va[1]])]
    z_va = zc_va[:va.size]          # the recorded validation rows, already zeroed

    def contact_val(net: FlatMLP) -> dict[str, float]:
        return {"val_acc": float(np.mean((np.argmax(predict_batched(net, z_va), 1) == 1)
                                         == data.contact[va])) if va.size else float("nan")}

    cnet = fit_net("contact", rng, "xent", zc_tr, yc_tr, zc_va, yc_va,
                   val_metrics=contact_val, desc=desc)
    cnet.W[0][:, list(unread)] = 0.0
    return cnet, predict_batched(cnet, z)


def after_turns(data: Prepared, guard_s: float) -> np.ndarray:
    """Rows (a mask over every row of ``data``) within ``guard_s`` seconds after each press's
    turn, the last of its samples at :data:`TURN_FRACTION` of its peak force or more.

    There the load has begun to fall, but the causal filter still averages the samples before
    the turn, and a pad with friction holds or even raises its strain while the load starts
    down: the inputs are those of a held load, the labels a few percent lower. No causal
    estimator can tell the two apart for that long, and a net fitted to both reads every held
    grip low (docs/trainer.md, "The turn").
    """
    mask = np.zeros(data.split.size, dtype=bool)
    if guard_s <= 0:                      # the default: no press needs grouping
        return mask
    for r, sl in data.recording_slices():
        force = np.nan_to_num(np.asarray(r.ds.force_N, dtype=np.float64))
        loaded = np.flatnonzero(np.asarray(r.ds.contact, dtype=bool))
        if not loaded.size:
            continue
        # The contact rows grouped by press, in time order within each.
        press_id = np.asarray(r.ds.press_id)
        rows = loaded[np.argsort(press_id[loaded], kind="stable")]
        pid = press_id[rows]
        first = np.flatnonzero(np.r_[True, pid[1:] != pid[:-1]])
        sizes = np.diff(np.r_[first, rows.size])
        peak = np.maximum.reduceat(force[rows], first)
        high = np.flatnonzero(force[rows] >= TURN_FRACTION * np.repeat(peak, sizes))
        last = np.full(first.size, -1)
        np.maximum.at(last, np.repeat(np.arange(first.size), sizes)[high], high)
        turns = rows[last[last >= 0]]
        n = len(r.ds)
        for k in range(1, int(round(guard_s * r.rate_hz)) + 1):
            mask[sl.start + turns[turns + k < n] + k] = True
    return mask


def fit_force(fit_net: NetFitter, data: Prepared, z: np.ndarray, cnet: FlatMLP,
              pred_contact: np.ndarray, scaling: Scaling, tr: np.ndarray, va: np.ndarray,
              synth_tr: Held, rng: np.random.Generator) -> FlatMLP:
    """The force net on the samples the contact net passes (its output is 0 N elsewhere,
    whatever the net says), with the load-cell force as target: where the contact is real
    this is the force the metric scores; on false contacts (light touches below the label
    threshold, pad creep) it teaches ~0 N, which is what a controller should see. Missed
    contacts are left out: their output is gated to 0 N, so fitting them would only spend
    capacity; so are the samples within ``turn_guard_s`` after each press's turn
    (:func:`after_turns`), when asked: they teach the net to read every hold low.

    The synthetic samples (``synth_tr``: held and rested presses built from the training
    presses) join the training set only. Early stopping and the choice among restarts read the
    recorded validation presses alone: a synthetic hold is the trainer's extrapolation, a held
    press outweighs the recorded ones, and its error grows while theirs still falls, so judged
    with it the net stops early (docs/trainer.md, "Restarts and force weight decay")."""
    nf = z.shape[1]
    f_off, f_scale = scaling.force_offset, scaling.force_scale
    fit = pred_contact & ~after_turns(data, fit_net.params.turn_guard_s)
    ftr, fva = tr[fit[tr]], va[fit[va]]
    if ftr.size == 0:  # a contact net that never fires: fall back to the true contacts
        ftr, fva = tr[data.contact[tr]], va[data.contact[va]]
    ft = ((data.force_N - f_off) / f_scale)[:, None]

    # The synthetic (held, rested) samples join where the contact net passes them, the same
    # gate as the recorded samples.
    zh = synth_tr[0][:, :nf]
    hl = predict_batched(cnet, zh) if len(zh) else np.empty((0, 2))
    passed = hl[:, 1] > hl[:, 0]
    zf_tr = np.concatenate([z[ftr], zh[passed]])
    yf_tr = np.concatenate([ft[ftr], ft[synth_tr[1][passed]]])

    def force_val(net: FlatMLP) -> dict[str, float]:
        e = (predict_batched(net, z[fva])[:, 0] * f_scale + f_off) - data.force_N[fva]
        return {"val_rmse_N": float(np.sqrt(np.mean(e * e))) if e.size else float("nan")}

    return fit_net("force", rng, "mse", zf_tr, yf_tr, z[fva], ft[fva],
                   val_metrics=force_val, desc="force net")


def _loc_inputs(x: np.ndarray, contact: np.ndarray, f_raw: np.ndarray, n_loc: int) -> np.ndarray:
    """Location-net input exactly as :func:`fbgforce.model.floatref.predict_from_features` builds it."""
    return floatref.location_inputs(x, contact, f_raw, n_loc)


def fit_location(fit_net: NetFitter, data: Prepared, pre: artifact.Preprocess, x_all: np.ndarray,
                 pred_contact: np.ndarray, fnet: FlatMLP, scaling: Scaling, params: TrainParams,
                 tr: np.ndarray, va: np.ndarray, rng: np.random.Generator,
                 rng_augment: np.random.Generator) -> FlatMLP:
    """The location net on the samples where true and predicted contact agree (where a
    location is both defined and output), fed the contact net's decision and the force net's
    OWN estimate, and on the training presses pressed harder (``location_augment``)."""
    n_loc = pre.memory.n_loc
    f_raw = predict_batched(fnet, x_all[:, :pre.n_features])[:, 0]
    loc_x = _loc_inputs(x_all, pred_contact, f_raw, n_loc)
    xy_t = (np.column_stack([data.x_mm, data.y_mm]) - scaling.xy_offset) / scaling.xy_scale
    ltr = tr[data.contact[tr] & pred_contact[tr]]
    lva = va[data.contact[va] & pred_contact[va]]

    def loc_val(net: FlatMLP) -> dict[str, float]:
        e = (predict_batched(net, loc_x[lva]) - xy_t[lva]) * scaling.xy_scale
        if not e.size:
            return {}
        r = np.sqrt(np.mean(e * e, axis=0))
        return {"val_x_mm": float(r[0]), "val_y_mm": float(r[1])}

    loc_train_x, loc_train_y = loc_x[ltr], xy_t[ltr]
    if params.location_augment > 1.0:
        z_aug, rows_aug = scaled_presses(data, pre, ltr, params.location_augment,
                                         rng_augment)
        aug_x = _loc_inputs(z_aug, np.ones(rows_aug.size, bool),
                            predict_batched(fnet, z_aug[:, :pre.n_features])[:, 0], n_loc)
        loc_train_x = np.concatenate([loc_train_x, aug_x])
        loc_train_y = np.concatenate([loc_train_y, xy_t[rows_aug]])
    return fit_net("location", rng, "mse", loc_train_x, loc_train_y, loc_x[lva],
                   xy_t[lva], val_metrics=loc_val, desc="location net")
