"""Vectorised numpy MLPs for training: forward, backward, losses and the mini-batch loop.

Layout follows :class:`fbgforce.model.artifact.MLP` (``W[l]`` shaped ``(n_out, n_in)``, ``a @ W.T + b``)
so a trained net converts to the model contract without transposes. All weights and biases of a
net live in ONE flat vector (``theta``) of which the per-layer arrays are views, and likewise
the gradient; the optimizer then updates everything in a few numpy calls. The backward pass is
the paper's eq. (8) with the mean over the mini-batch folded into the loss gradient.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from fbgforce.model.artifact import MLP
from fbgforce.trainer.optim import AdamOptimizer

HIDDEN_ACTIVATIONS = ("relu", "linear")

# ------------------------------------------------------------------------------------------
# Losses: each returns (mean loss, gradient of that mean loss w.r.t. the net output)
# ------------------------------------------------------------------------------------------


def softmax_xent(logits: np.ndarray, labels: np.ndarray) -> tuple[float, np.ndarray]:
    """Mean softmax cross-entropy of integer ``labels`` (n,) given ``logits`` (n, k)."""
    n = logits.shape[0]
    shifted = logits - logits.max(axis=1, keepdims=True)
    exp = np.exp(shifted)
    denom = exp.sum(axis=1, keepdims=True)
    rows = np.arange(n)
    loss = float(np.mean(np.log(denom[:, 0]) - shifted[rows, labels]))
    grad = exp / denom
    grad[rows, labels] -= 1.0
    grad /= n
    return loss, grad


def mse(pred: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray]:
    """Mean over samples of the mean squared error over outputs; ``pred``/``target`` (n, k)."""
    diff = pred - target
    loss = float(np.mean(diff * diff))
    return loss, diff * (2.0 / diff.size)


LOSSES: dict[str, Callable[[np.ndarray, np.ndarray], tuple[float, np.ndarray]]] = {
    "xent": softmax_xent,
    "mse": mse,
}


# ------------------------------------------------------------------------------------------
# The trainable net
# ------------------------------------------------------------------------------------------


class FlatMLP:
    """A ReLU (or linear) MLP with all parameters in one flat vector.

    Parameters
    ----------
    sizes
        Layer widths from input to output, e.g. ``[4, 70, 50, 20, 2]``.
    rng
        Generator for He-normal initialisation (ignored when ``init`` is given).
    init
        Start from these weights instead (transfer learning); must have the same sizes.
    hidden
        Hidden-layer activation: ``"relu"`` (the shipped nets) or ``"linear"`` (auto-encoder).
    """

    def __init__(self, sizes: Sequence[int], rng: np.random.Generator | None = None,
                 init: MLP | None = None, hidden: str = "relu") -> None:
        if hidden not in HIDDEN_ACTIVATIONS:
            raise ValueError(f"hidden must be one of {HIDDEN_ACTIVATIONS}")
        self.sizes = [int(s) for s in sizes]
        if len(self.sizes) < 2 or min(self.sizes) < 1:
            raise ValueError(f"bad layer sizes {self.sizes}")
        self.hidden = hidden
        shapes = [(o, i) for i, o in zip(self.sizes[:-1], self.sizes[1:])]
        n = sum(o * i + o for o, i in shapes)
        self.theta = np.zeros(n)
        self.grad = np.zeros(n)
        self.W: list[np.ndarray] = []
        self.b: list[np.ndarray] = []
        self.gW: list[np.ndarray] = []
        self.gb: list[np.ndarray] = []
        pos = 0
        for o, i in shapes:
            for params, grads, shape in ((self.W, self.gW, (o, i)), (self.b, self.gb, (o,))):
                size = math.prod(shape)
                params.append(self.theta[pos:pos + size].reshape(shape))
                grads.append(self.grad[pos:pos + size].reshape(shape))
                pos += size
        if init is not None:
            if init.sizes != self.sizes:
                raise ValueError(f"initial net has sizes {init.sizes}, expected {self.sizes}")
            for layer, (w, b) in enumerate(zip(init.weights, init.biases)):
                self.W[layer][...] = w
                self.b[layer][...] = b
        else:
            rng = rng if rng is not None else np.random.default_rng(0)
            for w in self.W:
                # He initialisation keeps ReLU activations' variance constant through depth.
                w[...] = rng.standard_normal(w.shape) * np.sqrt(2.0 / w.shape[1])
        self._acts: list[np.ndarray] = []

    @property
    def n_params(self) -> int:
        return self.theta.size

    def forward(self, x: np.ndarray, keep: bool = False) -> np.ndarray:
        """Outputs for a batch ``x`` (n, n_in); ``keep`` stores activations for :meth:`backward`."""
        a = x
        acts = [a]
        last = len(self.W) - 1
        for layer, (w, b) in enumerate(zip(self.W, self.b)):
            a = a @ w.T
            a += b
            if layer != last and self.hidden == "relu":
                np.maximum(a, 0.0, out=a)
            acts.append(a)
        if keep:
            self._acts = acts
        return a

    def backward(self, dout: np.ndarray) -> np.ndarray:
        """Fill :attr:`grad` from the loss gradient w.r.t. the last :meth:`forward` output.

        Returns the gradient w.r.t. the input (used by the gradient check and for chaining).
        """
        acts = self._acts
        if not acts:
            raise RuntimeError("backward() needs forward(..., keep=True) first")
        dz = dout
        for layer in range(len(self.W) - 1, -1, -1):
            a_prev = acts[layer]
            np.dot(dz.T, a_prev, out=self.gW[layer])
            np.sum(dz, axis=0, out=self.gb[layer])
            dz = dz @ self.W[layer]
            if layer and self.hidden == "relu":
                # ReLU's derivative: the activation was clipped to 0 exactly where z <= 0.
                dz *= acts[layer] > 0.0
        return dz

    def to_mlp(self) -> MLP:
        """A copy of the current weights as the model contract's :class:`~fbgforce.model.artifact.MLP`."""
        return MLP([w.copy() for w in self.W], [b.copy() for b in self.b])


def drop_unread_units(mlp: MLP) -> tuple[MLP, int]:
    """``mlp`` without the hidden units that no later layer reads, and how many were dropped.

    A unit is unread when every weight leading out of it rounds to 0 in float32: weight decay
    leaves a unit that never fires with weights of 1e-300 and below, which the float32 engines
    (onnxruntime, the C float build) already read as 0 and the quantiser exports as 0. Dropping
    such a unit, with its row and bias, leaves the float32 outputs as they were and saves its
    multiply-adds in every engine. Layers are pruned from the output back, so a unit read only
    by dropped units goes too; every layer keeps at least one unit. Units go in pairs, so an
    even width stays even: the exporter pads odd hidden widths back to even for the Cortex-M4
    kernels (which read inputs and rows in pairs), so a single unit dropped would save
    multiply-adds in the float engines only.
    """
    weights = [np.array(w, dtype=np.float64) for w in mlp.weights]
    biases = [np.array(b, dtype=np.float64) for b in mlp.biases]
    dropped = 0
    for l in range(len(weights) - 2, -1, -1):
        read = np.any(weights[l + 1].astype(np.float32) != 0, axis=0)
        if not read.any():
            read[0] = True
        if (~read).sum() % 2:
            read[np.flatnonzero(~read)[-1]] = True
        if read.all():
            continue
        dropped += int((~read).sum())
        weights[l], biases[l] = weights[l][read], biases[l][read]
        weights[l + 1] = weights[l + 1][:, read]
    return MLP(weights, biases), dropped


# ------------------------------------------------------------------------------------------
# The training loop
# ------------------------------------------------------------------------------------------


def zero_columns(x: np.ndarray, columns: Sequence[int]) -> np.ndarray:
    """A copy of ``x`` (n, m) with the ``columns`` set to 0; ``x`` itself when there are none.
    A net trained on such inputs, its first layer's weights on those columns then set to 0,
    computes the same function on the full inputs: it does not read them."""
    cols = list(columns)
    if not cols:
        return x
    out = np.array(x, dtype=np.float64, copy=True)
    out[:, cols] = 0.0
    return out


def predict_batched(net: FlatMLP, x: np.ndarray, batch: int = 65536) -> np.ndarray:
    """Forward pass over a large array in chunks (bounded memory)."""
    if x.shape[0] <= batch:
        return net.forward(x)
    return np.concatenate([net.forward(x[i:i + batch]) for i in range(0, x.shape[0], batch)])


def _train_epoch(net: FlatMLP, opt: AdamOptimizer,
                 loss_fn: Callable[[np.ndarray, np.ndarray], tuple[float, np.ndarray]],
                 x: np.ndarray, y: np.ndarray, batch_size: int, weight_decay: float,
                 input_noise: float, rng: np.random.Generator) -> float:
    """One pass over the training samples in an order drawn from ``rng``, an Adam step per
    mini-batch (inputs noised by ``input_noise``, weights decayed by ``weight_decay``);
    returns the mean training loss."""
    n = x.shape[0]
    order = rng.permutation(n)
    total = 0.0
    for start in range(0, n, batch_size):
        idx = order[start:start + batch_size]
        xb = x[idx]
        if input_noise > 0.0:
            xb = xb + rng.normal(0.0, input_noise, xb.shape)
        out = net.forward(xb, keep=True)
        batch_loss, dout = loss_fn(out, y[idx])
        net.backward(dout)
        if weight_decay > 0.0:
            for w, g in zip(net.W, net.gW):
                g += weight_decay * w
        opt.update_params(net.theta, net.grad)
        total += batch_loss * idx.size
    opt.epoch_ends()
    return total / n


def _record_epoch(history: list[dict[str, Any]], bar: Any, row: dict[str, Any], net: FlatMLP,
                  val_metrics: Callable[[FlatMLP], dict[str, float]] | None) -> None:
    """Add one epoch's ``row`` of the history, with the ``val_metrics`` of ``net``, and show
    it on the progress ``bar``."""
    if val_metrics is not None:
        row.update(val_metrics(net))
    history.append(row)
    # refresh=False: the bar's own pace decides when to draw (at most every 10 s on a pipe).
    bar.set_postfix({k: (f"{v:.4g}" if isinstance(v, float) else v)
                     for k, v in row.items() if k not in ("epoch", "lr")}, refresh=False)


@dataclass
class _EarlyStopping:
    """The best weights so far (``best_theta``, at ``best_epoch`` with ``best_loss``) and
    when :func:`fit` stops: after ``patience`` epochs without a relative improvement of
    ``min_delta``; with ``plateau``, it first goes back to the best weights at a learning rate
    ``plateau_factor`` smaller after that many."""

    best_theta: np.ndarray
    patience: int
    min_delta: float
    plateau: int | None
    plateau_factor: float
    best_loss: float = np.inf
    best_epoch: int = 0
    last_cut: int = 0

    def stops(self, epoch: int, val_loss: float, net: FlatMLP, opt: AdamOptimizer) -> bool:
        """Whether training stops after ``epoch`` (1 ..) with ``val_loss``."""
        if val_loss < self.best_loss * (1.0 - self.min_delta):
            self.best_loss, self.best_epoch = val_loss, epoch
            self.best_theta[...] = net.theta
            self.last_cut = epoch
        elif epoch - self.best_epoch >= self.patience:
            return True
        elif (self.plateau is not None
              and epoch - max(self.best_epoch, self.last_cut) >= self.plateau):
            # Smaller steps from the best point so far: a noisy plateau of the validation loss
            # is Adam's step size, not the end of what the net can learn.
            net.theta[...] = self.best_theta
            opt.scale_learning_rate(self.plateau_factor)
            self.last_cut = epoch
        return False


def fit(net: FlatMLP, loss: str, x: np.ndarray, y: np.ndarray, x_val: np.ndarray | None = None,
        y_val: np.ndarray | None = None, *, epochs: int = 100, batch_size: int = 128,
        learning_rate: float = 1e-3, decay: float = 0.97, patience: int = 10,
        min_delta: float = 1e-4, plateau: int | None = None, plateau_factor: float = 0.3,
        weight_decay: float = 0.0, input_noise: float = 0.0,
        rng: np.random.Generator | None = None,
        val_metrics: Callable[[FlatMLP], dict[str, float]] | None = None,
        desc: str = "train", progress: bool | None = None,
        time_budget_s: float | None = None) -> dict[str, Any]:
    """Mini-batch Adam with learning-rate decay and early stopping on the validation loss.

    Parameters
    ----------
    net
        Trained in place; on return it holds the weights of the best validation epoch.
    loss
        ``"xent"`` (``y`` integer labels) or ``"mse"`` (``y`` shaped like the output).
    x, y, x_val, y_val
        Training and validation data. Without validation data, the training loss is used for
        early stopping.
    epochs, batch_size, learning_rate, decay, patience, min_delta
        At most ``epochs`` passes; stop after ``patience`` epochs without a relative
        improvement of ``min_delta`` in the validation loss.
    plateau, plateau_factor
        Reduce on plateau: after ``plateau`` epochs without improvement, go back to the best
        weights and multiply the learning rate by ``plateau_factor`` (then wait ``plateau``
        epochs again). ``None`` keeps the plain exponential decay.
    weight_decay
        L2 penalty ``weight_decay * sum(W**2) / 2`` on the weights (not the biases), added to
        the gradient of every step.
    input_noise
        Standard deviation of Gaussian noise added to the inputs of every training batch
        (in input units; the validation data stay clean).
    rng
        Shuffling order and input noise (seeded by the caller for reproducibility).
    val_metrics
        Called after each epoch for extra numbers shown in the progress bar and the history.
    desc, progress
        Progress bar label; ``progress=False`` hides it (else :func:`fbgforce.progress.bar`:
        a bar on a terminal or in a notebook, periodic lines on a pipe).
    time_budget_s
        Stop (keeping the best weights) once this much wall time has passed.

    Returns
    -------
    dict
        ``epochs_run``, ``best_epoch``, ``best_val_loss``, ``seconds``, ``history`` (per epoch:
        loss, val_loss, lr and the ``val_metrics``).
    """
    from fbgforce import progress as fprogress

    loss_fn = LOSSES[loss]
    rng = rng if rng is not None else np.random.default_rng(0)
    opt = AdamOptimizer(net.n_params, learning_rate, decay)
    if x.shape[0] == 0:
        raise ValueError(f"{desc}: no training samples")
    use_val = x_val is not None and y_val is not None and x_val.shape[0] > 0
    stopping = _EarlyStopping(net.theta.copy(), patience, min_delta, plateau, plateau_factor)
    history = []
    t0 = time.perf_counter()
    bar = fprogress.bar(range(epochs), desc=desc, leave=False, enabled=progress)
    epochs_run = 0
    for epoch in bar:
        train_loss = _train_epoch(net, opt, loss_fn, x, y, batch_size, weight_decay, input_noise,
                                  rng)
        epochs_run = epoch + 1
        val_loss = loss_fn(predict_batched(net, x_val), y_val)[0] if use_val else train_loss
        _record_epoch(history, bar, {"epoch": epochs_run, "loss": train_loss,
                                     "val_loss": val_loss, "lr": opt.learning_rate},
                      net, val_metrics)
        if stopping.stops(epochs_run, val_loss, net, opt):
            break
        if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
            break
    bar.close()
    net.theta[...] = stopping.best_theta
    return {"epochs_run": epochs_run, "best_epoch": stopping.best_epoch,
            "best_val_loss": float(stopping.best_loss), "seconds": time.perf_counter() - t0,
            "history": history}
