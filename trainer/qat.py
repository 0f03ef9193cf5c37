"""Quantization-aware fine-tuning (QAT) of a trained float model for int8-weight export.

A few epochs of the trainer's own loop (:func:`fbgforce.trainer.nets.fit`, Adam with decay,
early stopping) on nets whose forward pass sees what the fixed-point runtime computes:

- weights fake-quantised symmetric per output row to ``weight_bits`` (scale
  ``max|W[r]| / (2^(b-1)-1)``, recomputed from the current weights at every step), the rule the
  exporter applies at export time (docs/fixed-point.md);
- activations (the net input and every layer's output) fake-quantised to ``act_bits`` with a
  fixed per-layer scale from the float net's range on the training inputs (calibration), with
  the exporter's headroom (:data:`ACT_HEADROOM`);
- gradients by the straight-through estimator: the float "shadow" weights are what Adam
  updates; rounding is treated as the identity in the backward pass.

The hierarchy is kept: the location net is fine-tuned on the contact decision and the force
output of the already fine-tuned, fake-quantised contact and force nets, as the runtime feeds it.
A net keeps its starting weights when fine-tuning does not lower its fake-quantised validation
loss, so QAT never makes the int8 model worse on the split it is judged by. The result is a
float :class:`~fbgforce.model.artifact.HierarchicalModel` (the shadow weights) that the normal exporter
quantises.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from fbgforce.model import artifact, floatref
from fbgforce.trainer.nets import LOSSES, FlatMLP, fit, predict_batched, zero_columns


def quantize_symmetric(x: np.ndarray, scale: float | np.ndarray, bits: int) -> np.ndarray:
    """Fake quantisation: round ``x / scale`` to the nearest integer, clamp to
    ``±(2^(bits-1) - 1)`` and scale back.

    Ties go to even (``np.rint``); the runtime's exact rounding rule (docs/fixed-point.md)
    differs only on exact halves, which do not matter for training.
    """
    q = float(2 ** (bits - 1) - 1)
    return np.clip(np.rint(x / scale), -q, q) * scale


#: Calibration range times this maps to the largest activation code (as the exporter).
ACT_HEADROOM = 1.25


def weight_scale(w: np.ndarray, bits: int) -> np.ndarray:
    """Per-row symmetric scales (n_out, 1): the largest weight of a row maps to ``2^(bits-1)-1``."""
    m = np.max(np.abs(w), axis=1, keepdims=True)
    return np.where(m > 0, m / (2 ** (bits - 1) - 1), 1.0)


class FakeQuantMLP(FlatMLP):
    """A :class:`~fbgforce.trainer.nets.FlatMLP` whose forward pass is fake-quantised.

    Parameters
    ----------
    init
        The float net to start from.
    weight_bits, act_bits
        Bit widths of weights and of activations (inputs and layer outputs).
    calib_x
        Inputs on which the activation ranges (hence scales) are measured with the float net.
    """

    def __init__(self, init: artifact.MLP, weight_bits: int, act_bits: int, calib_x: np.ndarray) -> None:
        super().__init__(init.sizes, init=init)
        self.weight_bits = int(weight_bits)
        self.act_bits = int(act_bits)
        qmax = 2 ** (act_bits - 1) - 1
        ranges = [np.max(np.abs(calib_x), axis=0)]
        a = calib_x
        last = len(self.W) - 1
        for layer, (w, b) in enumerate(zip(self.W, self.b)):
            a = a @ w.T + b
            if layer != last:
                a = np.maximum(a, 0.0)
            ranges.append(np.max(np.abs(a), axis=0))
        # Per-layer (not per-channel) scales, as the exporter's per-layer Q formats.
        self.act_scales = [ACT_HEADROOM * max(float(r.max()), 1e-12) / qmax for r in ranges]

    def quantized_weights(self) -> list[np.ndarray]:
        """The weight matrices as the runtime will hold them (fake-quantised, float)."""
        return [quantize_symmetric(w, weight_scale(w, self.weight_bits), self.weight_bits)
                for w in self.W]

    def forward(self, x: np.ndarray, keep: bool = False) -> np.ndarray:
        a = quantize_symmetric(x, self.act_scales[0], self.act_bits)
        acts = [a]
        last = len(self.W) - 1
        for layer, (wq, b) in enumerate(zip(self.quantized_weights(), self.b)):
            a = a @ wq.T + b
            if layer != last:
                np.maximum(a, 0.0, out=a)
            a = quantize_symmetric(a, self.act_scales[layer + 1], self.act_bits)
            acts.append(a)
        if keep:
            self._acts = acts
        return a

    def backward(self, dout: np.ndarray) -> np.ndarray:
        # Straight-through estimator: propagate through the quantised weights the forward pass
        # used, then put the float shadow weights back for Adam to update.
        shadow = [w.copy() for w in self.W]
        for w, wq in zip(self.W, self.quantized_weights()):
            w[...] = wq
        try:
            return super().backward(dout)
        finally:
            for w, s in zip(self.W, shadow):
                w[...] = s


def _targets(model: artifact.HierarchicalModel, force_N: np.ndarray, x_mm: np.ndarray,
             y_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    f = ((force_N - model.force_offset) / model.force_scale)[:, None]
    xy = (np.column_stack([x_mm, y_mm]) - model.xy_offset) / model.xy_scale
    return f, xy


def _tune(net: FakeQuantMLP, loss: str, x: np.ndarray, y: np.ndarray, xv: np.ndarray | None,
          yv: np.ndarray | None, name: str, settings: dict[str, Any],
          report: dict[str, Any]) -> None:
    """Fine-tune one fake-quantised net (:func:`~fbgforce.trainer.nets.fit` with
    ``settings``), recording how in ``report[name]``.

    The starting weights are kept unless fine-tuning lowers the quantised net's validation
    loss (without validation samples, its training loss): QAT must never make the shipped
    int8 model worse than plain quantisation.
    """
    ex, ey = (xv, yv) if xv is not None and xv.shape[0] else (x, y)
    start_theta = net.theta.copy()
    start = LOSSES[loss](predict_batched(net, ex), ey)[0]
    r = fit(net, loss, x, y, xv, yv, desc=f"qat {name}", **settings)
    kept = not r["best_val_loss"] < start
    if kept:
        net.theta[...] = start_theta
    report[name] = {"epochs_run": r["epochs_run"], "best_epoch": r["best_epoch"],
                    "start_val_loss": float(start), "best_val_loss": r["best_val_loss"],
                    "kept_start": kept}


def _location_rows(cnet: FakeQuantMLP, z: np.ndarray, contact: np.ndarray) -> np.ndarray:
    """Where the location net trains, as in the trainer: the samples where true and
    (quantised) predicted contact agree."""
    logits = cnet.forward(z)
    return contact & (logits[:, 1] > logits[:, 0])


def _location_inputs(cnet: FakeQuantMLP, fnet: FakeQuantMLP, x: np.ndarray, nf: int,
                     n_loc: int) -> np.ndarray:
    """What the runtime feeds the location net: the (quantised) contact and force nets' own
    decision and output on the first ``nf`` columns of ``x``, beside the location averages."""
    zz = x[:, :nf]
    logits = cnet.forward(zz)
    pred_c = (logits[:, 1] > logits[:, 0]).astype(np.float64)
    return floatref.location_inputs(x, pred_c, fnet.forward(zz)[:, 0], n_loc)


def finetune(model: artifact.HierarchicalModel, z: np.ndarray, contact: np.ndarray, force_N: np.ndarray,
             x_mm: np.ndarray, y_mm: np.ndarray, *, val: tuple[np.ndarray, ...] | None = None,
             weight_bits: int = 8, act_bits: int = 16, epochs: int = 3,
             learning_rate: float = 2e-4, decay: float = 0.8, batch_size: int = 128,
             seed: int = 0, progress: bool | None = None) -> tuple[artifact.HierarchicalModel, dict[str, Any]]:
    """Fine-tune all three nets with fake quantisation; return a new model and a report.

    Parameters
    ----------
    model
        The trained float model (its preprocessing and output scaling are kept unchanged).
    z
        (n, 4) standardised features of the training samples (``fbgforce.model.floatref.features`` of
        each continuous recording, restricted to the training split).
    contact, force_N, x_mm, y_mm
        Ground truth of those samples. As in the trainer, the force net trains on true-contact
        samples, the location net where true and (quantised) predicted contact agree.
    val
        Optional ``(z, contact, force_N, x_mm, y_mm)`` of the validation split, for early stopping.
    weight_bits, act_bits
        Fake-quantisation widths (int8 weights, int16 activations by default).
    epochs, learning_rate, decay, batch_size, seed
        Fine-tuning schedule: a few epochs at a learning rate well below training's.

    Returns
    -------
    model, report
        ``report`` holds per net the epochs run, the fake-quantised validation loss before and
        after, and ``kept_start`` (fine-tuning did not lower it, so the start was kept).
    """
    rng = np.random.default_rng(seed)
    # The contact and force nets read the first n_features columns; the location net also
    # the location averages at the end (fbgforce.model.floatref.location_inputs).
    nf, n_loc = model.preprocess.n_features, model.preprocess.memory.n_loc
    x_full, z = z, z[:, :nf]
    vx_full = val[0] if val is not None else None
    kw = dict(epochs=epochs, batch_size=batch_size, learning_rate=learning_rate, decay=decay,
              patience=max(2, epochs), rng=rng, progress=progress)
    c = np.asarray(contact).astype(bool)
    f_t, xy_t = _targets(model, np.asarray(force_N, float), np.asarray(x_mm, float),
                         np.asarray(y_mm, float))
    if val is not None:
        vz, vc = val[0][:, :nf], np.asarray(val[1]).astype(bool)
        vf, vxy = _targets(model, *(np.asarray(v, float) for v in val[2:5]))
    report: dict[str, Any] = {"weight_bits": weight_bits, "act_bits": act_bits}

    # Inputs the contact net was trained not to read (all-zero columns of its first layer,
    # fbgforce.trainer.fit_nets.fit_contact) stay unread.
    unread = np.flatnonzero(~model.contact.weights[0].any(axis=0))
    cz = zero_columns(z, unread)
    cnet = FakeQuantMLP(model.contact, weight_bits, act_bits, cz)
    _tune(cnet, "xent", cz, c.astype(np.int64), zero_columns(vz, unread) if val else None,
          vc.astype(np.int64) if val else None, "contact", kw, report)
    cnet.W[0][:, unread] = 0.0

    fnet = FakeQuantMLP(model.force, weight_bits, act_bits, z[c])
    _tune(fnet, "mse", z[c], f_t[c], vz[vc] if val else None, vf[vc] if val else None, "force",
          kw, report)

    lt = _location_rows(cnet, z, c)
    lx = _location_inputs(cnet, fnet, x_full[lt], nf, n_loc)
    lnet = FakeQuantMLP(model.location, weight_bits, act_bits, lx)
    if val:
        lv = _location_rows(cnet, vz, vc)
        _tune(lnet, "mse", lx, xy_t[lt], _location_inputs(cnet, fnet, vx_full[lv], nf, n_loc),
              vxy[lv], "location", kw, report)
    else:
        _tune(lnet, "mse", lx, xy_t[lt], None, None, "location", kw, report)

    meta = dict(model.metadata)
    meta["qat"] = report
    tuned = replace(model, contact=cnet.to_mlp(), force=fnet.to_mlp(), location=lnet.to_mlp(),
                    metadata=meta)
    return tuned, report
