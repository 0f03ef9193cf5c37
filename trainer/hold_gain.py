"""The settled-hold gain (:class:`fbgforce.model.artifact.InUse`) the trained nets need, measured on
synthetic holds (:func:`hold_gain`)."""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from fbgforce.model import artifact, floatref
from fbgforce.trainer.data import Prepared
from fbgforce.trainer.synthetic import HOLD_AUGMENT_STEP_S, Held


#: The settled-hold gain is measured on at least this many synthetic holds, else left off.
HOLD_GAIN_MIN_HOLDS = 3


def hold_gain(model: artifact.HierarchicalModel, data: Prepared, holds: Sequence[Held]) -> dict[str, Any]:
    """The settled-hold gain (:class:`fbgforce.model.artifact.InUse`) the trained nets need: their
    least-squares gain on the samples of the synthetic ``holds``
    (:func:`~fbgforce.trainer.synthetic.synthetic_holds`) at least
    :data:`fbgforce.model.artifact.HOLD_SETTLE_S` into each hold, minus 1.

    The nets read a hold a little low (docs/trainer.md, "The turn": a causal estimator cannot
    tell a load that stands from one that has just begun to fall, and they compromise); once
    a load has stood still longer than a turn lasts the runtime may take that compromise
    back, by as much as the nets leave on synthetic holds.

    The same samples give the nets' noise on a load that stands still, ``noise_N``, from
    which the runtime's steadiness band is set (:meth:`fbgforce.model.artifact.InUse.recommended`):
    the hold carries the recording's own interrogator noise, so a noisier pad's nets scatter
    more around a held load, and a band narrower than that scatter restarts the settle count
    on most holds and leaves the gain off where it was measured.

    Returns
    -------
    dict
        ``gain`` (0.0 with fewer than :data:`HOLD_GAIN_MIN_HOLDS` holds), ``holds``,
        ``samples``, the force bias over those samples (N) ``bias_before_N`` and
        ``bias_after_N``, and ``noise_N`` (:func:`hold_noise`; None without the gain).
    """
    x = np.concatenate([h[0] for h in holds]) if holds else np.empty((0, 0))
    src = np.concatenate([h[1] for h in holds]) if holds else np.empty(0, dtype=np.int64)
    if src.size < 2:
        return {"gain": 0.0, "holds": 0, "samples": 0, "bias_before_N": None, "bias_after_N": None,
                "noise_N": None}
    # A hold is a run of samples that take one row's labels (each sample after it takes its
    # own); HOLD_AUGMENT_STEP_S apart.
    new_run = np.r_[True, src[1:] != src[:-1]]
    starts = np.flatnonzero(new_run)
    lengths = np.diff(np.r_[starts, src.size])
    position = np.arange(src.size) - np.repeat(starts, lengths)
    step_s = max(1, int(round(HOLD_AUGMENT_STEP_S * data.rate_hz))) / data.rate_hz
    held = np.repeat(lengths > 1, lengths)
    settled = held & (position * step_s >= artifact.HOLD_SETTLE_S)
    label = data.force_N[src]
    settled &= np.isfinite(label) & (label > 0)
    n_holds = int(np.unique(src[settled]).size)
    if n_holds < HOLD_GAIN_MIN_HOLDS:
        return {"gain": 0.0, "holds": n_holds, "samples": int(settled.sum()),
                "bias_before_N": None, "bias_after_N": None, "noise_N": None}
    f = floatref.predict_from_features(model, x[settled])["force_raw_N"]
    y = label[settled]
    gain = float(np.clip(np.dot(y, f) / max(float(np.dot(f, f)), 1e-12) - 1.0,
                         -artifact.HOLD_GAIN_MAX, artifact.HOLD_GAIN_MAX))
    return {"gain": gain, "holds": n_holds, "samples": int(settled.sum()),
            "bias_before_N": float(np.mean(f - y)), "bias_after_N": float(np.mean(f * (1 + gain) - y)),
            "noise_N": hold_noise(f, src[settled])}


def hold_noise(force_N: np.ndarray, hold: np.ndarray) -> float:
    """The nets' scatter (N) around loads that stand still: the root mean square of the
    settled samples' ``force_N`` about a straight line through each hold's own (``hold``
    labels them; a hold's creep is slow and no part of the scatter), pooled over the holds
    with the degrees of freedom the lines take."""
    f = np.asarray(force_N, dtype=np.float64)
    starts = np.flatnonzero(np.r_[True, hold[1:] != hold[:-1]])
    sse, dof = 0.0, 0
    for a, b in zip(starts, np.r_[starts[1:], f.size]):
        if b - a < 3:
            continue
        t = np.arange(b - a, dtype=np.float64)
        line = np.polyval(np.polyfit(t, f[a:b], 1), t)
        sse += float(np.sum((f[a:b] - line) ** 2))
        dof += b - a - 2
    return float(np.sqrt(sse / dof)) if dof else 0.0
