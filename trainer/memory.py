"""The nets' memory states as the trainer sets them: named presets (:data:`MEMORY_PRESETS`),
the text of ``--memory`` (:func:`parse_memory`) and the load signal and gains fitted on the
training presses (:func:`fit_memory`)."""
from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np

from fbgforce import contract
from fbgforce.model import artifact as fm
from fbgforce.errors import InputError
from fbgforce.trainer.data import Prepared


def parse_memory(text: str) -> fm.Memory:
    """``none``, a preset name of :data:`MEMORY_PRESETS`, or ``<kind>:V,V,...`` for a kind of
    ``contract.MEMORY_KINDS`` (``ema:S,S``: average shifts; ``play:W,W``: play half-widths in
    standardised units) and ``loc:S`` joined by ``+`` (the location averages' shift)."""
    text = text.strip()
    if text in MEMORY_PRESETS:
        return MEMORY_PRESETS[text]
    states: dict[str, list[float]] = {k.name: [] for k in contract.MEMORY_KINDS}
    loc = 0
    try:
        for part in text.split("+"):
            kind, _, values = part.partition(":")
            nums = [v for v in values.split(",") if v.strip()]
            if kind.strip() in contract.MEMORY_KIND:
                spec = contract.MEMORY_KIND[kind.strip()]
                states[spec.name] += [(float if spec.counted_by.standardised else int)(v) for v in nums]
            elif kind.strip() == "loc":
                if len(nums) != 1 or loc:
                    raise ValueError("loc takes one shift")
                loc = int(nums[0])
                if loc < 1:
                    raise ValueError("the loc shift must be at least 1 (leave loc out for none)")
            else:
                raise ValueError(f"unknown memory kind {kind!r}")
        return fm.Memory(**{fm.memory_attr(k, k.counted_by): tuple(states[k.name])
                            for k in contract.MEMORY_KINDS}, loc_shift=loc)
    except ValueError as exc:
        raise InputError(f"bad memory {text!r}: {exc}; use none, "
                         f"{', '.join(MEMORY_PRESETS)}, or e.g. ema:3,6+play:0.1+loc:5",
                         column="--memory") from exc


#: Named memories (docs/trainer.md, "memory"): averages of about 16 and 128 ms at 1 kHz;
#: play operators of half-width 0.05 and 0.25 standard deviations of the load signal (about
#: 1 % and 5 % of the force range of a calibration run). Even counts keep the first layers'
#: widths even, which the Cortex-M4 kernels take in pairs. The default, ``both``, also gives
#: the location net the location averages of about 32 ms (``loc:5``; shifts 4 and 6 were
#: worse on the calibration scene, docs/trainer.md).
MEMORY_PRESETS: dict[str, fm.Memory] = {
    "none": fm.Memory(),
    "ema": fm.Memory(ema_shifts=(4, 7)),
    "play": fm.Memory(play_widths=(0.05, 0.25)),
    "loc": fm.Memory(loc_shift=5),
    "both": fm.Memory(ema_shifts=(4, 7), play_widths=(0.05, 0.25), loc_shift=5),
}
DEFAULT_MEMORY = "both"


def memory_time_constant_s(memory: fm.Memory, rate_hz: float) -> float:
    """The longest time constant of ``memory``'s averages, seconds (0 without averages)."""
    return 2.0 ** max(memory.ema_shifts) / rate_hz if memory.ema_shifts else 0.0


def fit_memory(memory: fm.Memory, pre: fm.Preprocess, data: "Prepared", rows: np.ndarray
               ) -> fm.Memory:
    """The memory's load signal and gains, fitted on the training ``rows``.

    Weights: least squares of the load-cell force (0 at rest) on the standardised channels,
    scaled so that ``u`` has unit spread: u tracks the load, and the play widths are fractions
    of its spread. Gains: the power of two that brings each feature's spread near 0.5, like
    the standardised inputs' (small recent changes would otherwise reach the nets as nearly
    constant inputs)."""
    if memory.n_states == 0:
        return memory
    loc_shift = memory.loc_shift
    memory = replace(memory, loc_shift=0)
    plain = copy.deepcopy(pre)
    plain.memory = fm.Memory()
    z = data.inputs(plain)[rows]
    force = np.where(data.contact[rows], np.nan_to_num(data.force_N[rows]), 0.0)
    w, *_ = np.linalg.lstsq(np.column_stack([z, np.ones(len(z))]), force, rcond=None)
    u = z @ w[:fm.N_STRAIN]
    weights = w[:fm.N_STRAIN] / max(float(np.std(u)), 1e-12)
    gain_of = {k.name: fm.memory_attr(k, k.gain) for k in contract.MEMORY_KINDS}
    trial = replace(memory, weights=tuple(weights), **{a: () for a in gain_of.values()})
    pre_trial = copy.deepcopy(pre)
    pre_trial.memory = trial
    x = data.inputs(pre_trial)[rows]
    gains = []
    for k in range(trial.n_states):
        sd = float(np.std(x[:, fm.N_STRAIN + k]))
        g = int(np.floor(np.log2(0.5 / sd))) if sd > 0 else 0
        gains.append(int(np.clip(g, 0, contract.LIMIT["MAX_MEM_GAIN"])))
    fitted, start = {}, 0
    for kind in contract.MEMORY_KINDS:     # the features' order: every kind's in turn
        fitted[gain_of[kind.name]] = tuple(gains[start:start + trial.count(kind)])
        start += trial.count(kind)
    return replace(trial, loc_shift=loc_shift, **fitted)
