"""Evidence before correction: the trainer corrects for a fitted creep only where the
calibration's own releases establish it (trainer.creep_evidence)."""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce.errors import InputError
from fbgforce.trainer.creep import Creep
from fbgforce.trainer.creep_evidence import (CREEP_EVIDENCE_MIN_TAU_S, creep_evidence,
                                             creep_press_check)
from fbgforce.trainer.creep_fit import (CREEP_TAIL_S, CREEP_TIME_CONSTANTS_S, CREEP_ZERO_SPAN_S,
                                        RATE_EFFECT_MIN_Z, RATE_EFFECT_TIME_CONSTANT_S, CreepTails,
                                        creep_of)
from fbgforce.trainer.params import TrainParams
from fbgforce.trainer.train import prepare

RATE = 1000.0


def _tails(creep: Creep, noise_N: float, seed: int = 0, rate_effect: float = 0.0,
           releases: int = 80, rate_term: bool = False, rate_tau: float = 0.002) -> CreepTails:
    """Tails of ``releases`` presses (0.2 s ramps to 5-40 N, 0.15 s tails read), the excess
    the creep leaves there, a rate effect at the release (a relaxation over ``rate_tau``),
    wandering offsets and white noise; ``rate_term``: the fit's rate term beside them, as
    ``CreepTails.of`` gathers it."""
    rng = np.random.default_rng(seed)
    taus = CREEP_TIME_CONSTANTS_S
    tail_n = int(CREEP_TAIL_S * RATE)
    force, is_tail, release = [], [], []
    for k in range(releases):
        peak = rng.uniform(5.0, 40.0)
        press = np.r_[np.linspace(0, peak, 200), np.linspace(peak, 0, 200)[1:]]
        force += [press, np.zeros(tail_n + 50)]
        is_tail += [np.zeros(press.size, bool), np.r_[np.ones(tail_n, bool), np.zeros(50, bool)]]
        release += [np.full(press.size + tail_n + 50, k)]
    f, tail, rel = np.concatenate(force), np.concatenate(is_tail), np.concatenate(release)
    lags = np.column_stack([(Creep(1.0, tau).lag(f, RATE) - f)[tail] for tau in taus])
    span = (np.arange(f.size) // int(CREEP_ZERO_SPAN_S * RATE))[tail]
    truth = (creep.magnitude * (creep.lag(f, RATE) - f) if creep.magnitude else 0 * f)[tail]
    fast = rate_effect * (Creep(1.0, rate_tau).lag(f, RATE) - f)[tail]
    excess = truth + fast + rng.normal(0.0, 0.05, span.max() + 1)[span] \
        + rng.normal(0.0, noise_N, tail.sum())
    rate = (Creep(1.0, RATE_EFFECT_TIME_CONSTANT_S).lag(f, RATE) - f)[tail] if rate_term else None
    return CreepTails(excess, np.unique(span, return_inverse=True)[1],
                      np.unique(rel[tail], return_inverse=True)[1], lags, tuple(taus), rate)


@pytest.mark.parametrize("tau", [0.05, 1.0])
def test_a_creep_the_releases_show_is_established(tau):
    tails = _tails(Creep(0.05, tau), noise_N=0.05)
    found = creep_of(tails)
    assert found.magnitude == pytest.approx(0.05, rel=0.3)
    ev = creep_evidence(tails, found)
    assert ev["established"], ev["why"]
    assert min(ev["tests"]["held_out_gain"]) > ev["tests"]["noise_removed_share_max"]


def test_noise_alone_establishes_nothing():
    for seed in range(3):
        tails = _tails(Creep(), noise_N=0.05, seed=seed)
        found = creep_of(tails)
        ev = creep_evidence(tails, found, seed=seed)
        assert not ev["established"], (seed, found)


def test_a_rate_effect_at_the_release_is_not_taken_for_a_creep():
    # A damper's last milliseconds of unloading fit as a creep at the grid's shortest time
    # constant; the evidence says so and the trainer leaves it alone.
    tails = _tails(Creep(), noise_N=0.02, rate_effect=0.3)
    found = creep_of(tails)
    assert found.magnitude > 0 and found.time_constant_s < CREEP_EVIDENCE_MIN_TAU_S
    ev = creep_evidence(tails, found)
    assert not ev["established"] and "shortest" in ev["why"]


def test_a_rate_effect_beside_a_fast_creep_does_not_inflate_it():
    # The release's rate effect overlaps a 50 ms creep's first milliseconds: fitted alone,
    # the creep takes it up; beside the rate term, it is read at its own size.
    truth = Creep(0.05, 0.05)
    alone = creep_of(_tails(truth, noise_N=0.02, rate_effect=0.1, rate_tau=0.01))
    beside = _tails(truth, noise_N=0.02, rate_effect=0.1, rate_tau=0.01, rate_term=True)
    found = creep_of(beside)
    assert alone.magnitude > 1.3 * truth.magnitude
    assert found.magnitude == pytest.approx(truth.magnitude, rel=0.2)
    assert found.time_constant_s == pytest.approx(truth.time_constant_s, rel=0.3)
    assert creep_evidence(beside, found)["established"]


def test_the_rate_term_is_kept_only_where_the_tails_show_the_rate_effect():
    # A pad that lets go of 10 % over 10 ms at the release shows it beside its creep; one that
    # does not keeps the fit it had alone, whatever the noise's draw. (A creep between two of
    # the grid's time constants leaves a residue the term takes up, significant where the
    # noise is this low: the one on the grid here keeps the test on the rate effect.)
    creep = Creep(0.05, CREEP_TIME_CONSTANTS_S[11])
    assert _tails(creep, noise_N=0.02, rate_effect=0.1, rate_tau=0.01,
                  rate_term=True).rate_effect_test()["fitted"]
    for seed in range(5):
        assert not _tails(creep, noise_N=0.05, seed=seed,
                          rate_term=True).rate_effect_test()["fitted"], seed
    assert not _tails(creep, noise_N=0.05).rate_effect_test()["fitted"]


def test_the_rate_effects_test_gives_its_figures():
    # What model.json records: the term's coefficient (10 % simulated), its standard error
    # clustered by release, and z against the one-sided 5 % level.
    creep = Creep(0.05, CREEP_TIME_CONSTANTS_S[11])
    shown = _tails(creep, noise_N=0.02, rate_effect=0.1, rate_tau=0.01,
                   rate_term=True).rate_effect_test()
    assert shown["fitted"] and shown["z"] > RATE_EFFECT_MIN_Z == shown["min_z"]
    assert shown["coefficient"] == pytest.approx(0.1, rel=0.2)
    assert shown["z"] == pytest.approx(shown["coefficient"] / shown["standard_error"])
    none = _tails(creep, noise_N=0.05, rate_term=True).rate_effect_test()
    assert not none["fitted"] and none["z"] <= RATE_EFFECT_MIN_Z
    assert _tails(creep, noise_N=0.05).rate_effect_test()["z"] is None


def test_the_rate_term_alone_establishes_no_creep():
    # A rate effect and no creep: the fit still names the grid's shortest time, and the rate
    # term, fitted beside the offsets whatever the creep, leaves it nothing to remove.
    tails = _tails(Creep(), noise_N=0.02, rate_effect=0.3, rate_term=True)
    found = creep_of(tails)
    ev = creep_evidence(tails, found)
    assert not ev["established"] and "shortest" in ev["why"]
    for seed in range(3):
        noise = _tails(Creep(), noise_N=0.05, seed=seed, rate_term=True)
        assert not creep_evidence(noise, creep_of(noise), seed=seed)["established"]


def test_the_fit_is_the_least_squares_fit_with_one_offset_per_span():
    # The span means taken out first give what the indicator columns in lstsq give.
    tails = _tails(Creep(0.04, 0.3), noise_N=0.05)
    offsets = np.eye(tails.span.max() + 1)[tails.span]
    best = None
    for j, tau in enumerate(tails.time_constants_s):
        design = np.column_stack([tails.lags[:, j], offsets])
        coef, *_ = np.linalg.lstsq(design, tails.excess, rcond=None)
        rss = float(np.sum((tails.excess - design @ coef) ** 2))
        if best is None or rss < best[0]:
            best = (rss, coef[0], tau)
    rss, creep = tails.fit()
    assert rss == pytest.approx(best[0], rel=1e-9)
    assert creep.magnitude == pytest.approx(best[1], rel=1e-9) and creep.time_constant_s == best[2]
    assert tails.rss_offsets() == pytest.approx(
        np.sum((tails.excess - offsets @ np.linalg.lstsq(offsets, tails.excess, rcond=None)[0]) ** 2))


def test_creep_modes():
    with pytest.raises(InputError, match="--creep"):
        TrainParams(creep="sometimes")
    assert TrainParams().creep == "auto"


def test_the_presses_do_not_stand_in_for_the_noise_test():
    tails = _tails(Creep(), noise_N=0.05)
    found = Creep(0.04, 3.8)
    better = {"presses": 80, "better": 60, "p_value": 1e-5, "rmse_N": 0.54,
              "rmse_inverse_N": 0.52, "passes": True}
    worse = {**better, "better": 40, "p_value": 0.55, "passes": False}
    # The noise test still applies: a creep the tails do not show at all stays unproven,
    # whatever the presses say.
    assert not creep_evidence(tails, found, presses=lambda: better)["established"]
    assert not creep_evidence(tails, found, presses=lambda: worse)["established"]
    # ... and the press check is not even run then.
    assert "presses" not in creep_evidence(tails, found, presses=lambda: better)["tests"]
    # Releases that show the creep on held-out halves need no press check.
    shown = _tails(Creep(0.05, 1.0), noise_N=0.05)

    def unexpected():
        raise AssertionError("the press check ran though the releases establish the creep")
    assert creep_evidence(shown, creep_of(shown), presses=unexpected)["established"]


@pytest.mark.slow
def test_press_check_on_a_slow_creeping_pad():
    import sys
    from dataclasses import replace
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    import foreign as fg

    spec = replace(fg.IN_USE_VARIANTS["calib_1K"], **fg.FAMILY["creep_5s"])
    ds = fg.log(fg.device(spec, 200), 1, 60)
    data = prepare([ds], seed=0, creep="off")
    slow = creep_press_check(data, data.pre, data.rows("train"), Creep(0.05, 4.0))
    assert slow["presses"] >= 40 and slow["rmse_inverse_N"] < slow["rmse_N"]
    assert slow["better"] > slow["presses"] / 2
    # No creep to take out: nothing to test.
    assert not creep_press_check(data, data.pre, data.rows("train"), Creep())["passes"]


def test_coverage_names_what_a_log_cannot_establish():
    import sys
    from dataclasses import replace
    from pathlib import Path

    from fbgforce.trainer.coverage import coverage, coverage_lines

    sys.path.insert(0, str(Path(__file__).parent))
    import foreign as fg

    spec = fg.IN_USE_VARIANTS["calib_1K"]
    short = coverage([fg.log(fg.device(spec, 200), 1, 6)])
    assert any("held load" in u for u in short["cannot_establish"])
    assert any("slower than its rests" in u for u in short["cannot_establish"])
    assert any("thermal response" in u for u in short["cannot_establish"])
    assert any("left alone for minutes" in u for u in short["cannot_establish"])
    assert any(line.startswith("  it cannot establish: ") for line in coverage_lines(short))
    held = replace(spec, hold_s=(2.0, 2.5), rest_s=(6.0, 7.0), drift_K=6.0)
    long = coverage([fg.log(fg.device(held, 200), 1, 3)])
    assert not any("held load" in u or "slower than its rests" in u or "thermal response" in u
                   for u in long["cannot_establish"])
    idle = coverage([fg.log(fg.device(replace(spec, rest_s=(121.0, 122.0)), 200), 1, 2)])
    assert not any("left alone" in u for u in idle["cannot_establish"])
    # Presses that rise once and fall once never show the pad a load turning back; grips whose
    # force wanders do.
    assert any("turns back" in u for u in short["cannot_establish"])
    assert short["turns"]["presses_turning"] == 0 and short["turns"]["deepest_fraction"] < 0.02
    grips = coverage([fg.log(fg.device(fg.IN_USE_VARIANTS["held_grips"], 200), 1, 12)])
    assert grips["turns"]["presses_turning"] >= 1
    assert not any("turns back" in u for u in grips["cannot_establish"])
