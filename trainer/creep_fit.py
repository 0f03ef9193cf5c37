"""Fitting the pad's creep (:class:`~fbgforce.trainer.creep.Creep`) on the creep recovery
after a calibration's releases (:func:`fit_creep`), and at a time constant the model can hold
(:func:`held_creep`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from fbgforce.model import artifact as fm
from fbgforce.trainer import preprocess as pp
from fbgforce.trainer.creep import Creep
from fbgforce.trainer.data import Prepared


#: Relaxation times (s) tried by :func:`fit_creep` (0.01-3.8 s, 12 per decade), how long after
#: a release its samples show the pad creeping back (the creep recovery the fit reads), and
#: the span over which the unloaded zero may wander on its own (one offset per span).
CREEP_TIME_CONSTANTS_S = tuple(0.01 * 10.0 ** (k / 12) for k in range(32))
CREEP_TAIL_S = 0.15
CREEP_ZERO_SPAN_S = 10.0

#: The release's rate effect, fitted beside the creep where the tails show it: a relaxation
#: at the grid's shortest time (the unloading's last milliseconds, where a damper's or the
#: friction's rate effect reads as a creep), and the shortest time constant a creep must have
#: to be told apart from it (:func:`~fbgforce.trainer.creep_evidence.creep_evidence`'s first test).
RATE_EFFECT_TIME_CONSTANT_S = CREEP_TIME_CONSTANTS_S[0]
CREEP_EVIDENCE_MIN_TAU_S = 0.02
#: The rate term is fitted only where the calibration shows the rate effect: its coefficient
#: beside the best creep above zero by this many standard errors (one-sided 5 %), the errors
#: clustered by release (a tail's samples share its noise). On a pad without one the term
#: only adds variance to a fast creep (the simulator's 5 % over 80 ms read 6.4 % over 68 ms
#: beside it on one seed, 5.1 % over 83 ms alone).
RATE_EFFECT_MIN_Z = 1.645


@dataclass
class CreepTails:
    """What the creep fit reads: the samples just after the releases among some rows.

    Every :data:`CREEP_ZERO_SPAN_S` span of the recordings has an offset of its own, so the
    fits below work on values less their span's mean (which is what a least-squares fit with
    one indicator column per span does to the other columns).

    Attributes
    ----------
    excess
        (m,) the load signal minus the load-cell force on those samples, N.
    span
        (m,) the span of each sample (0 ..).
    release
        (m,) which release each sample follows (0 .., numbered across recordings).
    lags
        (m, len(time_constants_s)) ``lag(F) - F`` at each relaxation time.
    time_constants_s
        The relaxation times of ``lags``' columns.
    rate_lag
        (m,) ``lag(F) - F`` at :data:`RATE_EFFECT_TIME_CONSTANT_S`: the release's rate effect,
        fitted beside the creep as the offsets are (None: no rate term; :meth:`of` leaves it
        out where the tails do not show the effect, :meth:`rate_effect_test`).
    rate_effect
        The rate effect's test on the whole grid, when :meth:`of` judged it
        (:meth:`rate_effect_test`): what the model's metadata records.
    """

    excess: np.ndarray
    span: np.ndarray
    release: np.ndarray
    lags: np.ndarray
    time_constants_s: tuple[float, ...]
    rate_lag: np.ndarray | None = None
    rate_effect: dict[str, Any] | None = None

    @classmethod
    def of(cls, data: Prepared, pre: fm.Preprocess, rows: np.ndarray,
           time_constants_s: Sequence[float] = CREEP_TIME_CONSTANTS_S) -> "CreepTails | None":
        """The tails of the releases among ``rows``; None when they hold fewer than 100
        samples or ``rows`` no contact."""
        keep = data.row_mask(rows)
        tails, spans, releases = [], [], []
        for r, sl in data.recording_slices():
            contact = np.asarray(r.ds.contact, bool)
            idx = np.arange(contact.size)
            last = np.maximum.accumulate(np.where(contact, idx, -contact.size))
            nxt = np.minimum.accumulate(np.where(contact, idx, 2 * contact.size)[::-1])[::-1]
            tail = int(round(CREEP_TAIL_S * r.rate_hz))
            tails.append(~contact & (idx - last <= tail) & (nxt - idx > tail // 2) & keep[sl])
            # Numbered across recordings: each recording's zero wanders on its own.
            first = spans[-1][-1] + 1 if spans else 0
            spans.append(first + idx // max(1, int(round(CREEP_ZERO_SPAN_S * r.rate_hz))))
            releases.append(last + (releases[-1].max() + contact.size + 1 if releases else 0))
        tail = np.concatenate(tails)
        if tail.sum() < 100 or not (keep & data.contact).any():
            return None
        _, span = np.unique(np.concatenate(spans)[tail], return_inverse=True)
        _, release = np.unique(np.concatenate(releases)[tail], return_inverse=True)
        force = np.nan_to_num(data.force_N)
        excess = load_excess(data, pre, rows)[tail]
        taus = tuple(time_constants_s)
        # The rate effect is judged on the whole grid whatever the grid asked for, so that a
        # creep refitted at one time constant (held_creep) keeps the fit's decision.
        extra = () if taus == CREEP_TIME_CONSTANTS_S else CREEP_TIME_CONSTANTS_S
        lags = np.column_stack([
            np.concatenate([Creep(1.0, tau).lag(force[sl], r.rate_hz) - force[sl]
                            for r, sl in data.recording_slices()])[tail]
            for tau in (RATE_EFFECT_TIME_CONSTANT_S, *taus, *extra)])
        mine = lags[:, 1:1 + len(taus)]
        test = cls(excess, span, release, lags[:, 1 + len(taus):] if extra else mine,
                   extra or taus, lags[:, 0]).rate_effect_test()
        return cls(excess, span, release, mine, taus,
                   lags[:, 0] if test["fitted"] else None, test)

    def subset(self, mask: np.ndarray) -> "CreepTails":
        """The samples of ``mask``."""
        return CreepTails(self.excess[mask], np.unique(self.span[mask], return_inverse=True)[1],
                          self.release[mask], self.lags[mask], self.time_constants_s,
                          None if self.rate_lag is None else self.rate_lag[mask],
                          self.rate_effect)

    def _centred(self, x: np.ndarray) -> np.ndarray:
        """``x`` (m,) or (m, k) less its span's mean, column by column."""
        n = np.bincount(self.span).astype(float)
        cols = x.reshape(x.shape[0], -1)
        means = np.stack([np.bincount(self.span, weights=c) for c in cols.T], axis=1) / n[:, None]
        return (cols - means[self.span]).reshape(x.shape)

    def _rate(self) -> np.ndarray | None:
        """The rate term, centred (None without one)."""
        return None if self.rate_lag is None else self._centred(self.rate_lag)

    def _rss_beside_rate(self, e: np.ndarray) -> float:
        """The residual of centred ``e`` once the rate term, when there is one, is fitted."""
        r = self._rate()
        return float(e @ e) - (0.0 if r is None else float(r @ e) ** 2 / max(float(r @ r), 1e-300))

    def rss_offsets(self) -> float:
        """The residual without a creep: of the offsets, and the rate term when there is one."""
        return self._rss_beside_rate(self._centred(self.excess))

    def fit(self, lags: np.ndarray | None = None) -> tuple[float, Creep]:
        """The best relaxation time's residual and creep (slope clipped to 0 .. 0.9) on these
        samples; ``lags`` replaces :attr:`lags` (the sign-flip test's).

        Without a rate term, or when the best single relaxation time is the grid's shortest
        (the rate effect itself: :func:`~fbgforce.trainer.creep_evidence.creep_evidence`
        says so), each relaxation time is fitted alone. Otherwise each one of at least
        :data:`CREEP_EVIDENCE_MIN_TAU_S` is fitted beside the rate term, so that the release's
        rate effect does not inflate a fast creep (:func:`fit_creep`)."""
        e = self._centred(self.excess)
        g = self._centred(self.lags if lags is None else lags)
        taus = np.asarray(self.time_constants_s)
        gg, ge = _projections(g, e)
        rss = float(e @ e) - ge ** 2 / gg
        j = int(np.argmin(rss))
        alone = self.rate_lag is None or (lags is None and taus[j] < CREEP_EVIDENCE_MIN_TAU_S)
        if alone or not np.any(taus >= CREEP_EVIDENCE_MIN_TAU_S):
            return float(rss[j]), Creep(float(np.clip(ge[j] / gg[j], 0.0, 0.9)), float(taus[j]))
        r = self._rate()
        assert r is not None
        rss2, slope, _ = self._beside_rate(e, g, gg, ge, r)
        j = int(np.argmin(rss2))
        return float(rss2[j]), Creep(float(np.clip(slope[j], 0.0, 0.9)), float(taus[j]))

    def _beside_rate(self, e: np.ndarray, g: np.ndarray, gg: np.ndarray, ge: np.ndarray,
                     r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each relaxation time's fit beside the rate term (centred ``e`` on centred ``g``'s
        column and the centred term ``r``, ``gg`` and ``ge`` their :func:`_projections`; the
        2x2 normal equations of all at once): the residual (inf below
        :data:`CREEP_EVIDENCE_MIN_TAU_S`; the term alone where the creep would run backwards),
        the creep's slope and the term's."""
        taus = np.asarray(self.time_constants_s)
        rr, re, rg = float(r @ r), float(r @ e), r @ g
        det = np.maximum(rr * gg - rg ** 2, 1e-300)
        rate, slope = (gg * re - rg * ge) / det, (rr * ge - rg * re) / det
        ee = float(e @ e)
        rss2 = np.where(slope > 0, ee - rate * re - slope * ge, ee - re ** 2 / max(rr, 1e-300))
        return np.where(taus >= CREEP_EVIDENCE_MIN_TAU_S, rss2, np.inf), slope, rate

    def rate_effect_test(self) -> dict[str, Any]:
        """Whether these tails show the release's rate effect: beside the best creep of at
        least :data:`CREEP_EVIDENCE_MIN_TAU_S`, the rate term's coefficient lies above zero by
        :data:`RATE_EFFECT_MIN_Z` standard errors clustered by release.

        Returns
        -------
        dict
            ``coefficient`` (the term's share of the force, as a creep's magnitude),
            ``standard_error``, ``z`` (None where there is nothing to test: no term, or no
            relaxation time long enough), ``min_z`` and ``fitted`` (bool).
        """
        out: dict[str, Any] = {"coefficient": None, "standard_error": None, "z": None,
                               "min_z": RATE_EFFECT_MIN_Z, "fitted": False}
        r = self._rate()
        if r is None or not np.any(np.asarray(self.time_constants_s) >= CREEP_EVIDENCE_MIN_TAU_S):
            return out
        e, g = self._centred(self.excess), self._centred(self.lags)
        rss2, slope, rate = self._beside_rate(e, g, *_projections(g, e), r)
        j = int(np.argmin(rss2))
        x = np.column_stack([r, g[:, j]])
        resid = e - x @ np.array([rate[j], slope[j]])
        bread = np.linalg.pinv(x.T @ x)
        # Sandwich estimate: per release, the score of its samples.
        scores = np.stack([np.bincount(self.release, weights=x[:, c] * resid) for c in range(2)],
                          axis=1)
        cov = bread @ (scores.T @ scores) @ bread
        se = float(np.sqrt(max(cov[0, 0], 0.0)))
        coef = float(rate[j])
        z = coef / se if se > 0 else None
        return {**out, "coefficient": coef, "standard_error": se, "z": z,
                "fitted": bool(se > 0 and coef > RATE_EFFECT_MIN_Z * se)}

    def rss_with(self, creep: Creep) -> float:
        """The residual on these samples of ``creep`` as given (only the offsets, and the rate
        term when there is one, fitted)."""
        j = int(np.argmin(np.abs(np.log(np.asarray(self.time_constants_s)
                                         / creep.time_constant_s))))
        return self._rss_beside_rate(self._centred(self.excess - creep.magnitude * self.lags[:, j]))


def load_excess(data: Prepared, pre: fm.Preprocess, rows: np.ndarray) -> np.ndarray:
    """On every row of ``data``: a least-squares load signal less the load cell's force. The
    signal is the force fitted, with an offset, on the compensated shifts
    (:func:`~fbgforce.trainer.preprocess.compensated`, row by row) of the contact samples among
    ``rows``; what a pad's creep or hysteresis holds back shows in its excess (``rows`` must
    hold at least one contact sample)."""
    comp = np.concatenate([pp.compensated(pre, r.ds.wl_nm, r.baseline_nm)
                           for r, _ in data.recording_slices()])
    force = np.nan_to_num(data.force_N)
    loaded = data.row_mask(rows) & data.contact
    w, *_ = np.linalg.lstsq(np.column_stack([comp[loaded], np.ones(loaded.sum())]),
                            force[loaded], rcond=None)
    return comp @ w[:fm.N_STRAIN] + w[fm.N_STRAIN] - force


def _projections(g: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each column of ``g``'s squared norm (kept off 0) and its product with ``e``: the
    single-column least-squares fits of ``e`` on ``g``'s columns, and what the fits beside
    the rate term build on."""
    return np.maximum(np.einsum("ij,ij->j", g, g), 1e-300), g.T @ e


def fit_creep(data: Prepared, pre: fm.Preprocess, rows: np.ndarray,
              time_constants_s: Sequence[float] = CREEP_TIME_CONSTANTS_S) -> Creep:
    """The pad's creep, fitted on the creep recovery after the releases among ``rows``.

    A load signal ``u`` (least squares of the load-cell force on the compensated shifts over
    the contact samples of ``rows``) minus the force is regressed on ``lag(F) - F`` over the
    first :data:`CREEP_TAIL_S` after each release, for each relaxation time of
    ``time_constants_s`` (:data:`CREEP_TIME_CONSTANTS_S`); the best fit's slope is the
    magnitude (:class:`CreepTails`). Beside the slope, each :data:`CREEP_ZERO_SPAN_S` of the
    recording has an offset of its own: the unloaded zero wanders (interrogator, fibre
    mounts), and a slow creep's residual (a second's time constant in rests of a fraction of
    one) is itself nearly an offset, which one offset for the whole log confused with that
    wander. And beside a creep clear of the grid's shortest time, the same term at
    :data:`RATE_EFFECT_TIME_CONSTANT_S`: the friction loop does not close the moment the
    load leaves, and its rate effect over the release's last milliseconds, fitted alone,
    inflates a fast creep (5 % over 50 ms read as 8.4 % over 38 ms; 5.6 % over 46 ms beside
    it). On the calibration_paper scene (5 % and 0.08 s simulated) it finds 0.050 and
    0.083 s; on tests/foreign.py's in-use fingertip (5 %, 1 s) 0.046 and 0.83 s, 0.054 and
    1.0 s on its two calibration logs.

    A fit is a hypothesis: :func:`~fbgforce.trainer.creep_evidence.creep_evidence` says whether
    the calibration establishes it.
    """
    return creep_of(CreepTails.of(data, pre, rows, time_constants_s))


def creep_of(tails: CreepTails | None) -> Creep:
    """:func:`fit_creep` on tails already gathered (none: no creep)."""
    if tails is None:
        return Creep()
    creep = tails.fit()[1]
    return creep if creep.magnitude > 0 else Creep()


def held_creep(data: Prepared, pre: fm.Preprocess, fitted: Creep) -> Creep:
    """``fitted`` at a time constant the model can hold (2^k samples, the nearest:
    :func:`fbgforce.model.artifact.creep_parameters`), its magnitude fitted again for it: a shorter
    time constant needs more magnitude to give back what the pad gives back after a release.
    """
    m, k = fm.creep_parameters(fitted.magnitude, fitted.time_constant_s * data.rate_hz)
    if m <= 0:
        return Creep()
    tau = 2.0 ** k / data.rate_hz
    m, _ = fm.creep_parameters(fit_creep(data, pre, data.rows("train"), (tau,)).magnitude, 2.0 ** k)
    return Creep(m, tau) if m > 0 else Creep()
