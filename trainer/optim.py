"""Adam with learning-rate decay, after scikit-learn's ``_stochastic_optimizers.py``.

The optimizer works on ONE flat float64 parameter vector (the nets in :mod:`fbgforce.trainer.nets`
keep their weights as views into it), so an update is a handful of vectorised numpy operations
whatever the number of layers: with mini-batches of 128 the per-call overhead of numpy, not the
arithmetic, is what costs time.
"""
from __future__ import annotations

import numpy as np


class AdamOptimizer:
    """Adam (Kingma & Ba, 2015) with exponential learning-rate decay per epoch.

    Parameters
    ----------
    n_params
        Length of the flat parameter vector.
    learning_rate_init
        Step size at epoch 0.
    decay
        Multiplier applied to the learning rate at the end of every epoch
        (``lr = learning_rate_init * decay ** epoch``).
    beta_1, beta_2, epsilon
        Adam's moment decay rates and numerical floor.

    Notes
    -----
    The update, with ``t`` the step count::

        m = beta_1 m + (1 - beta_1) g
        v = beta_2 v + (1 - beta_2) g^2
        theta -= lr sqrt(1 - beta_2^t) / (1 - beta_1^t) * m / (sqrt(v) + epsilon)
    """

    def __init__(self, n_params: int, learning_rate_init: float = 1e-3, decay: float = 0.97,
                 beta_1: float = 0.9, beta_2: float = 0.999, epsilon: float = 1e-8) -> None:
        self.learning_rate_init = float(learning_rate_init)
        self.learning_rate = float(learning_rate_init)
        self.decay = float(decay)
        self.beta_1 = float(beta_1)
        self.beta_2 = float(beta_2)
        self.epsilon = float(epsilon)
        self.t = 0
        self.epoch = 0
        self.ms = np.zeros(n_params)
        self.vs = np.zeros(n_params)
        self._tmp = np.empty(n_params)

    def update_params(self, params: np.ndarray, grads: np.ndarray) -> None:
        """Apply one Adam step to ``params`` in place (``grads`` has the same shape)."""
        self.t += 1
        b1, b2 = self.beta_1, self.beta_2
        self.ms *= b1
        self.ms += (1.0 - b1) * grads
        self.vs *= b2
        np.multiply(grads, grads, out=self._tmp)
        self._tmp *= 1.0 - b2
        self.vs += self._tmp
        lr = self.learning_rate * np.sqrt(1.0 - b2 ** self.t) / (1.0 - b1 ** self.t)
        np.sqrt(self.vs, out=self._tmp)
        self._tmp += self.epsilon
        np.divide(self.ms, self._tmp, out=self._tmp)
        self._tmp *= lr
        params -= self._tmp

    def scale_learning_rate(self, factor: float) -> None:
        """Multiply the learning rate (now and for every later epoch) by ``factor``."""
        self.learning_rate_init *= float(factor)
        self.learning_rate *= float(factor)

    def epoch_ends(self) -> None:
        """Decay the learning rate; call once after every epoch."""
        self.epoch += 1
        self.learning_rate = self.learning_rate_init * self.decay ** self.epoch
