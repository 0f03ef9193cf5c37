"""What :func:`fbgforce.trainer.train.train` is asked to do (:class:`TrainParams`, checked
when made) and the nets' widths (:data:`DEFAULT_SIZES`, :data:`PAPER_SIZES`)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from fbgforce import contract
from fbgforce.model import artifact as fm
from fbgforce.errors import InputError
from fbgforce.trainer.creep_evidence import CREEP_MODES
from fbgforce.trainer.hysteresis import HOLD_MODES
from fbgforce.trainer.synthetic import HOLD_AUGMENT, IDLE_DRAWS, LOCATION_AUGMENT, REST_AUGMENT


#: Hidden-layer widths of the paper's Fig. 4 (the `paper` width of ``fbgforce tradeoff``).
PAPER_SIZES: dict[str, tuple[int, ...]] = {
    "contact": (70, 50, 20),
    "force": (70, 50, 20),
    "location": (70, 50, 40),
}


#: Hidden-layer widths the trainer starts from (``--sizes`` changes them; the force net's
#: weight decay then switches off the units it does not need): about half the paper's, which
#: brings a contact step within a tenth of a 168 MHz Cortex-M4 at 1 kHz by estimated cycles
#: at the paper widths' accuracy within the spread of training seeds (docs/trainer.md,
#: "Widths and the Cortex-M4").
DEFAULT_SIZES: dict[str, tuple[int, ...]] = {
    "contact": (36, 26, 10),
    "force": (50, 30, 16),
    "location": (36, 26, 20),
}


#: The contact decision's rules the trainer can set (``fbgforce train --decision``): the
#: Schmitt trigger with a rise count, or the CUSUM rise (docs/runtime.md, "In use").
DECISION_RULES = ("schmitt", "cusum")


_TRAIN_FLAGS = {"epochs": "--epochs", "seed": "--seed", "filter": "--filter", "sigma": "--sigma",
                "window": "--window", "init": "--init", "train_fraction": "--train-fraction",
                "memory": "--memory", "restarts": "--restarts", "hold_augment": "--hold-augment",
                "release_holds": "--release-holds", "wander_holds": "--wander-holds",
                "rest_augment": "--rest-augment", "ref_shift": "--ref-shift",
                "creep_inverse": "--creep-inverse", "creep": "--creep", "decision": "--decision",
                "turn_guard_s": "--turn-guard", "sizes": "--sizes",
                "track_calibration": "--track-calibration", "idle_pads": "--idle-pads",
                "contact_plays": "--contact-plays"}


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) \
        and not isinstance(value, (bool, np.bool_)) and bool(np.isfinite(value))


def _valid_sizes(sizes: Any) -> bool:
    """Hidden widths the runtime can hold: known nets, each 1 .. MAX_LAYERS - 1 hidden layers
    (the output layer is one more) of 1 .. MAX_WIDTH units (an odd width is padded to the next
    even one on export, which stays within the even MAX_WIDTH)."""
    if not isinstance(sizes, Mapping) or not set(sizes) <= set(DEFAULT_SIZES):
        return False
    for widths in sizes.values():
        if not isinstance(widths, Sequence) or isinstance(widths, str):
            return False
        if not 1 <= len(widths) <= contract.LIMIT["MAX_LAYERS"] - 1:
            return False
        if not all(_is_int(w) and 1 <= w <= contract.LIMIT["MAX_WIDTH"] for w in widths):
            return False
    return True


@dataclass
class TrainParams:
    """What :func:`~fbgforce.trainer.train.train` is asked to do, checked when made: a value out
    of its range is an :class:`~fbgforce.errors.InputError` naming the ``fbgforce train`` option
    (or the parameter, for those the command does not offer) and the allowed range.

    Attributes
    ----------
    epochs, seed, learning_rate, decay, patience, batch_size
        Training loop (see :func:`fbgforce.trainer.nets.fit`); ``seed`` fixes the split, the
        initial weights and the shuffling, so a run is reproducible.
    filter, sigma, window
        Smoothing: ``causal`` (shipped), ``centred`` (offline, the paper's) or ``none``;
        sigma in samples, default 5 ms at the data's sample rate (5 samples at 1 kHz).
    ref_shift
        The temperature reference's average (:attr:`fbgforce.model.artifact.Preprocess.ref_shift`):
        None lets the data choose (:func:`~fbgforce.trainer.preprocess.choose_ref_shift`),
        0 keeps the raw reference, 1 .. 8 averages over 2^ref_shift samples.
    creep_inverse
        Take the pad's fitted creep out before the filter (:func:`fbgforce.model.floatref.creep_inverse`)
        instead of letting the at-rest tracker discount its recovery (docs/trainer.md, "The
        pad's creep in use", measures what each costs); None (default): the inverse when the
        fitted creep is slower than the memory's longest average
        (:func:`~fbgforce.trainer.creep_evidence.takes_creep_out`).
    decision
        The contact decision's rule (:data:`DECISION_RULES`): ``cusum`` (default: quicker
        and quieter than the Schmitt trigger on the worst member of the family of fingertips,
        docs/robustness.md) or ``schmitt``; the fields the other would set are kept in
        ``metadata.decision_rules``.
    creep
        ``auto`` (default): correct for the fitted creep (the synthetic holds' creep, the
        inverse or the tracker's term) only where the calibration establishes it
        (:func:`~fbgforce.trainer.creep_evidence.creep_evidence`); ``on``: wherever the fit
        finds one; ``off``: never.
    track_calibration
        Train the nets on the calibration as the at-rest tracker hands it on (default True):
        the tracker, driven by a contact net and decision fitted first, runs over each
        recording, and the nets learn its wavelengths less the tracker's correction, so they
        read loads from the zero the runtime will hold, not from the calibration's wandering
        one (:mod:`fbgforce.trainer.tracked`; docs/trainer.md, "The tracker's zero"). False
        trains on the recordings as tared.
    contact_plays
        The contact net reads the memory's play operators too (default False: it reads the
        channels and the averages; the force and location nets read every state). At rest a
        play operator follows the noise's record low, so the longer a pad rests the further
        its feature drifts from any state a calibration's short rests show; a contact net
        that reads it takes a long rest for a light press, and the contact decision's
        threshold, read on idle pads, rises to match (docs/trainer.md, "What the contact net
        reads").
    init
        A model (or model directory) of another device to start from (paper §VII-C). Its input
        standardisation and output scaling are kept so its weights keep their meaning; tare and
        temperature coefficients are fitted on the new data.
    sizes
        Hidden widths per net, e.g. ``{"location": (70, 50, 40)}``; defaults :data:`DEFAULT_SIZES`.
        What a smaller net saves on the Cortex-M4 and costs in accuracy: docs/trainer.md,
        "Widths and the Cortex-M4".
    progress
        Progress bars on stderr (None: when stderr is a terminal).
    train_fraction
        Use only this fraction of the training presses (transfer study: "how much less data").
    time_budget_s
        Per-net wall-time cap (keeps the best weights so far).
    plateau, plateau_factor
        Reduce the learning rate on a validation plateau (see :func:`~fbgforce.trainer.nets.fit`;
        off by default).
    weight_decay
        L2 weight decay: one value for every net or per net (``{"force": 1e-2}``); a net given
        none takes :func:`~fbgforce.trainer.fit_nets.default_weight_decay` (it falls with the
        number of samples the net trains on). The model records each net's in
        ``metadata.training.NET.weight_decay``.
    location_augment
        The location net also trains on the training presses pressed up to this many times
        harder (:func:`~fbgforce.trainer.synthetic.scaled_presses`); 1 turns it off.
    hold_augment
        The contact and force nets also train on this share of the training (and validation)
        presses held at their peak for 1.5-6 s
        (:func:`~fbgforce.trainer.synthetic.synthetic_holds`); 0 turns it off. Only a model with
        memory states uses it (a memoryless net reads a hold as its peak).
    release_holds
        ``auto``: as many synthetic holds again, on the presses' releases, for the force net,
        where the calibration establishes a friction
        (:func:`~fbgforce.trainer.hysteresis.friction_hold_choice`); ``on``: always (with
        ``hold_augment`` above 0); ``off`` (default): never. Off by default: on the
        simulator's egg-grasp loop they read the grip low (docs/trainer.md, "Holds for a pad
        with friction").
    wander_holds
        ``auto`` (default): as many synthetic holds again whose load wanders below the peak
        and back, the strain sticking at each turn and sliding on the press's own rise or
        fall, for the force net, where the calibration establishes a friction
        (:func:`~fbgforce.trainer.synthetic.synthetic_holds` with ``wander``); ``on``: always
        (with ``hold_augment`` above 0); ``off``: never (docs/trainer.md, "Holds for a pad
        with friction").
    rest_augment
        The contact and force nets also train on rests of 3-60 s inserted before this share of
        the training (and validation) presses
        (:func:`~fbgforce.trainer.synthetic.synthetic_rests`); 0 turns it off.
    turn_guard_s
        The force net leaves out the samples within this many seconds after each press's turn
        (:func:`~fbgforce.trainer.fit_nets.after_turns`): a held grip then reads less low, the
        first milliseconds of each unloading worse (docs/trainer.md, "The turn"); 0 keeps them;
        None (default): :data:`~fbgforce.trainer.fit_nets.TURN_GUARD_S` with the creep inverse,
        else 0.
    memory
        The memory states (:class:`fbgforce.model.artifact.Memory`, or text for
        :func:`~fbgforce.trainer.memory.parse_memory`); ``None``: the ``init`` model's, else
        :data:`~fbgforce.trainer.memory.DEFAULT_MEMORY`. Gains are fitted.
    idle_pads
        Idle pads (:func:`~fbgforce.trainer.synthetic.idle_rests`, each
        :data:`~fbgforce.trainer.synthetic.IDLE_MINUTES` minutes of the calibration's rest
        noise) the CUSUM's threshold is also read on, so that a pad left alone for minutes
        raises no more false events than the aim (docs/robustness.md, "An idle pad"); 0 reads
        it on the rests alone. Fewer pads train faster, guard the idle pad's rare
        heavy-tailed minutes less well, and may miss a contact net that reads a long rest as
        contact, whose pads the trainer leaves out (on ``short_rests`` of tests/foreign.py 40
        pads showed it, 4 did not).
    restarts
        Initialisations tried per net (one value for every net or per net, ``None``:
        :data:`~fbgforce.trainer.fit_nets.DEFAULT_RESTARTS`); the net with the lowest validation
        loss is kept. The first draw is the one a single initialisation would make. Without
        validation presses, or with ``init`` (every draw would start from the same weights), one
        is trained.
    """

    epochs: int = 200
    seed: int = 0
    filter: str = "causal"
    sigma: float | None = None
    window: int | None = None
    ref_shift: int | None = None
    creep_inverse: bool | None = None
    creep: str = "auto"
    decision: str = "cusum"
    init: str | Path | fm.HierarchicalModel | None = None
    sizes: Mapping[str, Sequence[int]] | None = None
    learning_rate: float = 1e-3
    decay: float = 0.97
    patience: int = 10
    batch_size: int = 128
    progress: bool | None = None
    train_fraction: float = 1.0
    time_budget_s: float | None = None
    plateau: int | None = None
    plateau_factor: float = 0.3
    weight_decay: float | Mapping[str, float] | None = None
    location_augment: float = LOCATION_AUGMENT
    hold_augment: float = HOLD_AUGMENT
    release_holds: str = "off"
    wander_holds: str = "auto"
    rest_augment: float = REST_AUGMENT
    turn_guard_s: float | None = None
    memory: fm.Memory | str | None = None
    restarts: int | Mapping[str, int] | None = None
    track_calibration: bool = True
    idle_pads: int = IDLE_DRAWS
    contact_plays: bool = False

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, allowed: str) -> None:
            if not ok:
                raise InputError(f"must be {allowed}, not {getattr(self, name)!r}",
                                 column=_TRAIN_FLAGS.get(name, name))

        need(_is_int(self.epochs) and self.epochs >= 1, "epochs", "a whole number >= 1")
        need(_is_int(self.seed), "seed", "a whole number")
        need(self.filter in fm.FILTER_KINDS, "filter", "one of " + ", ".join(fm.FILTER_KINDS))
        need(self.sigma is None or (_is_real(self.sigma) and self.sigma >= 0), "sigma",
             "a number >= 0 (samples)")
        need(self.window is None or (_is_int(self.window) and self.window >= 1), "window",
             "a whole number >= 1")
        need(self.ref_shift is None or (_is_int(self.ref_shift)
                                        and 0 <= self.ref_shift <= contract.LIMIT["MAX_REF_SHIFT"]),
             "ref_shift", f"None or 0 .. {contract.LIMIT['MAX_REF_SHIFT']}")
        need(_is_real(self.learning_rate) and self.learning_rate > 0, "learning_rate", "> 0")
        need(_is_real(self.decay) and 0 < self.decay <= 1, "decay", "in (0, 1]")
        need(_is_int(self.patience) and self.patience >= 1, "patience", "a whole number >= 1")
        need(_is_int(self.batch_size) and self.batch_size >= 1, "batch_size", "a whole number >= 1")
        need(_is_real(self.train_fraction) and 0 < self.train_fraction <= 1, "train_fraction",
             "in (0, 1]")
        need(self.time_budget_s is None or (_is_real(self.time_budget_s) and self.time_budget_s > 0),
             "time_budget_s", "None or > 0 (seconds)")
        need(self.plateau is None or (_is_int(self.plateau) and self.plateau >= 1), "plateau",
             "None or a whole number >= 1")
        need(_is_real(self.plateau_factor) and 0 < self.plateau_factor < 1, "plateau_factor",
             "in (0, 1)")
        need(_is_real(self.location_augment) and self.location_augment >= 1, "location_augment",
             ">= 1 (1: off)")
        for share in ("hold_augment", "rest_augment"):
            need(_is_real(getattr(self, share)) and 0 <= getattr(self, share) <= 1, share,
                 "in [0, 1]")
        need(self.turn_guard_s is None or (_is_real(self.turn_guard_s) and 0 <= self.turn_guard_s <= 1),
             "turn_guard_s", "None or in [0, 1] s (--turn-guard takes milliseconds: 0 .. 1000)")
        need(self.creep_inverse in (None, True, False), "creep_inverse", "None, True or False")
        need(self.creep in CREEP_MODES, "creep", "one of " + ", ".join(CREEP_MODES))
        for holds in ("release_holds", "wander_holds"):
            need(getattr(self, holds) in HOLD_MODES, holds, "one of " + ", ".join(HOLD_MODES))
        need(isinstance(self.track_calibration, (bool, np.bool_)), "track_calibration",
             "True or False")
        need(isinstance(self.contact_plays, (bool, np.bool_)), "contact_plays", "True or False")
        need(_is_int(self.idle_pads) and self.idle_pads >= 0, "idle_pads",
             "a whole number >= 0 (0: the rests alone)")
        need(self.decision in DECISION_RULES, "decision", "one of " + ", ".join(DECISION_RULES))
        need(self.sizes is None or _valid_sizes(self.sizes), "sizes",
             f"hidden widths per net ({', '.join(DEFAULT_SIZES)}): 1 .. "
             f"{contract.LIMIT['MAX_LAYERS'] - 1} layers of 1 .. {contract.LIMIT['MAX_WIDTH']} "
             f"units (the runtime's limits)")

    def fit_settings(self) -> dict[str, Any]:
        """The keyword arguments of :func:`fbgforce.trainer.nets.fit` every net shares."""
        return dict(epochs=self.epochs, batch_size=self.batch_size,
                    learning_rate=self.learning_rate, decay=self.decay, patience=self.patience,
                    progress=self.progress, time_budget_s=self.time_budget_s,
                    plateau=self.plateau, plateau_factor=self.plateau_factor)
