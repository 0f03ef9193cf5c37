"""Auto-encoder study (paper §VII-D): how many features do the four strain channels hold?

A single-hidden-layer auto-encoder ``4 -> k -> 4`` with linear units is trained (Adam, the same
loop as the nets) for k = 1, 2, 3 on the standardised, compensated, filtered shifts of the
contact samples. Its reconstruction RMSE (standardised units) says how many independent
features the data has: with rigid-pad statics the four beam forces are a linear function of
(F, F x, F y), so three features must suffice and two must not. The exact optimum of a linear
auto-encoder is the principal subspace, so the PCA residual is reported beside it as a check
that training converged.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fbgforce.trainer.nets import FlatMLP, fit, predict_batched

MAX_SAMPLES = 60000


def autoencoder_study(z: np.ndarray, ks: Sequence[int] = (1, 2, 3), *, seed: int = 0,
                      epochs: int = 30, progress: bool | None = None) -> dict[str, Any]:
    """Reconstruction RMSE of ``4 -> k -> 4`` auto-encoders on features ``z`` (n, 4).

    Returns
    -------
    dict
        ``ks``, ``rmse`` (per k, auto-encoder), ``rmse_pca`` (per k, optimal linear),
        ``explained_variance`` (PCA, fraction per component), ``n_samples``, and
        ``embedding`` (the k=3 codes of up to 5000 samples, for the plot) and
        ``embedding_rows`` (their row indices in ``z``).
    """
    rng = np.random.default_rng(seed)
    rows = np.arange(z.shape[0])
    if z.shape[0] > MAX_SAMPLES:
        rows = np.sort(rng.choice(z.shape[0], MAX_SAMPLES, replace=False))
        z = z[rows]
    mean = z.mean(axis=0)
    zc = z - mean
    _, svals, vt = np.linalg.svd(zc, full_matrices=False)
    var = svals ** 2
    out: dict[str, Any] = {"ks": list(ks), "rmse": [], "rmse_pca": [],
                           "explained_variance": (var / var.sum()).tolist(),
                           "n_samples": int(z.shape[0])}
    n_val = max(1, z.shape[0] // 10)
    codes = None
    for k in ks:
        resid = zc - zc @ vt[:k].T @ vt[:k]
        out["rmse_pca"].append(float(np.sqrt(np.mean(resid ** 2))))
        net = FlatMLP([z.shape[1], k, z.shape[1]], np.random.default_rng(seed + k), hidden="linear")
        fit(net, "mse", z[n_val:], z[n_val:], z[:n_val], z[:n_val], epochs=epochs, patience=5,
            learning_rate=3e-3, decay=0.9, rng=np.random.default_rng(seed), progress=progress,
            desc=f"auto-encoder k={k}")
        rec = predict_batched(net, z)
        out["rmse"].append(float(np.sqrt(np.mean((rec - z) ** 2))))
        if k == 3:
            pick = rng.permutation(z.shape[0])[:5000]
            codes = (z[pick] @ net.W[0].T + net.b[0], rows[pick])
    if codes is not None:
        out["embedding"], out["embedding_rows"] = codes
    return out


def plot_embedding(codes: np.ndarray, force_N: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray,
                   path: str | Path) -> bool:
    """The paper's Fig. 10: three features coloured by force, x and y. False without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig = plt.figure(figsize=(14, 4))
    panels = [("all samples", None), ("force (N)", force_N), ("x (mm)", x_mm), ("y (mm)", y_mm)]
    for i, (title, colour) in enumerate(panels):
        ax = fig.add_subplot(1, 4, i + 1, projection="3d")
        style = {"c": colour, "cmap": "viridis"} if colour is not None else {"c": "tab:blue"}
        sc = ax.scatter(codes[:, 0], codes[:, 1], codes[:, 2], s=1, **style)
        ax.set_title(title)
        ax.set_xlabel("f1")
        ax.set_ylabel("f2")
        ax.set_zlabel("f3")
        if colour is not None:
            fig.colorbar(sc, ax=ax, shrink=0.6)
    fig.tight_layout()
    from fbgforce import fileio

    try:
        fileio.write_with(path, lambda fh: fig.savefig(fh, dpi=110, format="png"), "--plot")
    finally:
        plt.close(fig)
    return True
