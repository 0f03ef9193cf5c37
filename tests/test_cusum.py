"""The contact decision's CUSUM rise, and the decision on a contact net with a negative output
multiplier.

The rule on hand-made margins; the C fixed point bit-exact with the integer reference on every
host kernel (with faults, parameters at their bounds and saturated margins); reset, tare and
fault semantics of the CUSUM's state; the float build against the float model; the loaders'
one verdict on the rules across its fields; and C = integer reference on a contact net whose
output multiplier is negative, for the Schmitt trigger's per-sample setting and the CUSUM.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from fbgforce import contract
from fbgforce.model import artifact, decision as fm_decision, floatref
from fbgforce.export import blob, intref, mutate
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import ModelCheckError, QModel
from fbgforce.pybind import FloatRuntime, Runtime

from test_decision_tracker import _drifting_model, _equal
from test_simd import host_kernels

TOP = contract.LIMIT["MAX_CUSUM_Q8"]
FAULT = contract.STATUS_FLAG["SENSOR_FAULT"]
#: A CUSUM rise with the tracker of test_decision_tracker's AGGRESSIVE.
CUSUM = artifact.InUse(contact_off_margin=-1.0, track_shift=5, track_settle=40, track_step_max_pm=0.3,
                 track_limit_pm=2.0, contact_cusum_h=1.5, contact_cusum_k=0.25,
                 contact_cusum_lo=-0.5, contact_cusum_hi=1.0)


def _cusum(q: QModel, h: int, k: int, lo: int, hi: int) -> QModel:
    return dataclasses.replace(q, contact_on_q8=0, contact_rise_n=1, contact_cusum_h_q8=h,
                               contact_cusum_k_q8=k, contact_cusum_lo_q8=lo, contact_cusum_hi_q8=hi)


def _run_both(q: QModel, wl_fm: np.ndarray, base: np.ndarray, kernel: str = "auto"):
    rt = Runtime(blob.to_bytes(q), kernel=kernel)
    rt.set_baseline(base.astype(np.int32))
    return rt.run_raw(wl_fm), intref.run(q, wl_fm, base), rt


def _bits(*runs: tuple[int, int]) -> list[int]:
    """A 0/1 list from (value, count) runs."""
    return [v for v, n in runs for _ in range(n)]


def test_the_cusum_rule_on_hand_made_margins():
    # h 10, k 2, margins clipped to [-3, 6]: S = max(0, S + clip(m) - 2).
    cusum = (10, 2, -3, 6)
    d = fm_decision.RELEASE_DWELL
    margin = np.array([1, 3, 5, 100, -100, 3, 4, 4, 4] + [-1] * (d - 1) + [4] + [-1] * d
                      + [-50, -50, 7, 7, 1, -200])
    raw = margin > 0
    # S: 0, 1, 4, 8, 3 (-5 clipped to -3 - 2), 4, 6, 8, 10 -> contact, S 0. d - 1 samples at
    # -1 do not release it (the 4 restarts the count); d more do, on the last of them; the
    # decision holds while above off = -20 and ends at -50 (S untouched); then S 0, 4, 8, 7, 2.
    want = np.array(_bits((0, 8), (1, 1 + (d - 1) + 1 + (d - 1)), (0, 1 + 6)), dtype=bool)
    held = np.array(_bits((0, 8), (1, 1 + (d - 1) + 1 + d), (0, 6)), dtype=bool)
    state = [0, 0, 0, 0, 0]
    got = fm_decision.decide_over_time(raw, margin, 0, -20, 1, state, cusum)
    assert np.array_equal(got[0], want) and np.array_equal(got[1], held)
    assert state == [0, 0, 2, 0, 0]
    # The state carries from one call to the next exactly as one call; S and the release
    # count are carried.
    state = [0, 0, 0, 0, 0]
    cuts = (0, 3, 9 + d // 2, 9 + d + 3, margin.size)
    parts = [fm_decision.decide_over_time(raw[a:b], margin[a:b], 0, -20, 1, state, cusum)[0]
             for a, b in zip(cuts, cuts[1:])]
    assert np.array_equal(np.concatenate(parts), want)
    state = [0, 0, 0, 0, 0]
    fm_decision.decide_over_time(raw[:-2], margin[:-2], 0, -20, 1, state, cusum)
    assert state == [0, 0, 8, 0, 0]
    # The integer reference runs exactly this rule on the blob's fields.
    q = QModel.__new__(QModel)
    q.contact_on_q8, q.contact_off_q8, q.contact_rise_n = 0, -20, 1
    q.contact_cusum_h_q8, q.contact_cusum_k_q8, q.contact_cusum_lo_q8, q.contact_cusum_hi_q8 = cusum
    got = intref._contact_decision(q, raw, margin, [0, 0, 0, 0, 0])
    assert np.array_equal(got[0], want) and np.array_equal(got[1], held)


def test_contact_rises_again_within_the_release_band():
    """Released after the dwell, contact shows again only by the CUSUM's rise, from S = 0; the
    decision holds until the margin falls to off."""
    cusum = (10, 2, -3, 6)
    d = fm_decision.RELEASE_DWELL
    margin = np.array([6, 6, 6] + [-1] * d + [6, 6, 6] + [-5] * d + [-30, 6])
    state = [0, 0, 0, 0, 0]
    contact, held = fm_decision.decide_over_time(margin > 0, margin, 0, -20, 1, state, cusum)
    # S 4, 8, 12: contact; the d-th -1 releases it; in the band S 4, 8, 12: contact again; the
    # d-th -5 releases it, -30 ends the band; then S 4.
    assert contact.astype(int).tolist() == _bits((0, 2), (1, d), (0, 3), (1, d), (0, 3))
    assert held.astype(int).tolist() == _bits((0, 2), (1, 1 + d + 3 + d), (0, 2))
    assert state == [0, 0, 4, 0, 0]
    # With the band empty (off = 0) the margin at -1 ends the decision itself, at once.
    contact, held = fm_decision.decide_over_time(margin > 0, margin, 0, 0, 1, [0, 0, 0, 0, 0], cusum)
    assert np.array_equal(contact, held) and contact.astype(int).tolist()[:4] == [0, 0, 1, 0]


def test_a_single_spike_cannot_raise_contact_under_the_clip():
    """hi - k < h: one sample, however high its margin, leaves S below h."""
    margin = np.array([-5.0, 1e6, -5.0, -5.0, 1e6, 1e6])
    got, _ = fm_decision.decide_over_time(margin > 0, margin, 0.0, 0.0, 1, [0, 0, 0.0, 0, 0],
                                          (2.0, 0.5, -1.0, 1.6))
    assert np.array_equal(got, [0, 0, 0, 0, 0, 1])


@pytest.mark.parametrize("kernel", ["portable", *host_kernels()])
def test_the_cusum_is_bit_exact(random_model_factory, random_walk_factory, kernel):
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, CUSUM)
    assert q.contact_cusum_h_q8 == 384 and q.contact_cusum_k_q8 == 64
    assert (q.contact_cusum_lo_q8, q.contact_cusum_hi_q8) == (-128, 256)
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    c, ref, _ = _run_both(q, wl_fm, base, kernel)
    assert (ref["status"] & FAULT).any()
    assert 0.1 < ref["contact"].mean() < 0.9
    _equal(c, ref)
    # The CUSUM, not the per-sample rule, decided: some rises come after positive margins
    # that the per-sample rule would have called contact at once.
    ok = (ref["status"] & FAULT) == 0
    late = ok & (ref["contact_margin_q8"] > 0) & (ref["contact"] == 0)
    assert late.sum() > 10


@pytest.mark.parametrize("shift_down", [0, 28], ids=["margins", "saturated_margins"])
@pytest.mark.parametrize("params", [
    (TOP, TOP, -TOP, TOP),        # d = clip - 2^29 in [-2^30, 0]: S stays 0
    (TOP, -TOP, -TOP, TOP),       # d in [0, 2^30]: S + d up to 2^29 - 1 + 2^30
    (TOP, 0, -TOP, TOP),          # d = the clipped margin itself, +-2^29
    (1, 0, -TOP, TOP),            # the smallest threshold: any positive margin rises
    (TOP, -TOP + 1, TOP, TOP),    # lo = hi: a constant step of 2^30 - 1
    (TOP, TOP, -TOP, -TOP),       # d = -2^30 on every sample
    (TOP, -(TOP - 1), 0, 0),      # d = 2^29 - 1: S stands at h - 1, then S + d = 2^30 - 2
], ids=["k_top", "k_bottom", "k_zero", "h_one", "lo_is_hi", "d_bottom", "s_at_h_minus_1"])
def test_the_cusum_at_its_bounds_is_bit_exact(random_model_factory, random_walk_factory,
                                              params, shift_down):
    """Every parameter at the contract's bounds, on every host kernel; with the contact output
    layer's shift lowered by 28 the margins saturate at +-2^31 and the clip takes them to
    +-2^29."""
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, CUSUM, seed=5)
    q = _cusum(q, *params)
    if shift_down:
        last = q.nets[0][-1]
        q.nets[0][-1] = dataclasses.replace(last, shift=last.shift - shift_down)
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    ref = intref.run(q, wl_fm, base)
    if shift_down:
        m = np.abs(ref["contact_margin_q8"])
        assert (m > TOP).mean() > 0.5 and (m == 2**31 - 1).any()
    for kernel in ("portable", *host_kernels()):
        rt = Runtime(blob.to_bytes(q), kernel=kernel)
        rt.set_baseline(base.astype(np.int32))
        _equal(rt.run_raw(wl_fm), ref)


def test_reset_tare_and_faults_on_the_cusum_state(random_model_factory, random_walk_factory):
    """S stays in [0, h) and is 0 in contact; a faulty sample holds it; a reset, a tare and a
    new baseline clear it (after a reset the runtime continues as the reference started
    afresh on the baseline the tracker reached)."""
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, CUSUM, seed=4)
    q = _cusum(q, 8 * 256, 0, -128, 256)     # a high threshold: S stays up for long stretches
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    rt = Runtime(blob.to_bytes(q))
    rt.set_baseline(base.astype(np.int32))
    lost = wl_fm[0].copy()
    lost[2] = 0
    seen, held, i = [], 0, 2000
    rt.run_raw(wl_fm[:i])

    def step(sample: np.ndarray) -> np.void:
        before = int(rt._state.cusum_q8)
        out = rt.step(sample)
        after = int(rt._state.cusum_q8)
        assert 0 <= after < q.contact_cusum_h_q8
        assert after == 0 or not out["contact"]
        if out["status"] & FAULT:
            assert after == before
        return out

    while i < 3500 or held < 3:
        out = step(wl_fm[i])
        seen.append(int(rt._state.cusum_q8))
        if seen[-1] > 0 and held < 3:
            s = seen[-1]
            assert step(lost)["status"] & FAULT
            assert rt._state.cusum_q8 == s
            held += 1
        i += 1
    assert max(seen) > 256
    while rt._state.cusum_q8 == 0:
        rt.step(wl_fm[i])
        i += 1
    reached = np.asarray(rt.baseline_fm, dtype=np.int64)
    rt.reset()
    assert rt._state.cusum_q8 == 0
    _equal(rt.run_raw(wl_fm[i:i + 1000]), intref.run(q, wl_fm[i:i + 1000], reached))
    for restart in ("tare", "baseline"):
        rt.set_baseline(base.astype(np.int32))
        i = 2000
        while rt._state.cusum_q8 == 0:
            rt.step(wl_fm[i])
            i += 1
        if restart == "tare":
            rt.tare(wl[i:i + 100])
        else:
            rt.set_baseline(base.astype(np.int32))
        assert rt._state.cusum_q8 == 0


def test_the_float_build_holds_and_clears_its_cusum(random_model_factory, random_walk_factory):
    """fbgf_state.cusum as fbg_state.cusum_q8: in [0, h), 0 in contact, held through a lost
    peak, cleared by a reset, a tare and a new baseline."""
    model, _, wl = _drifting_model(random_model_factory, random_walk_factory, CUSUM, seed=4)
    model.in_use = dataclasses.replace(CUSUM, contact_cusum_h=8.0, contact_cusum_k=0.0,
                                       contact_cusum_lo=-0.5, contact_cusum_hi=1.0)
    wl = np.where(wl == 0.0, np.roll(wl, 40, axis=0), wl)
    rt = FloatRuntime(model)
    rt.set_baseline(model.baseline_nm)
    rt.run(wl[:2000])
    lost = wl[0].copy()
    lost[2] = 0.0
    peak, held, i = 0.0, 0, 2000
    for restart in ("fault", "fault", "reset", "tare", "baseline"):
        while rt._state.cusum == 0.0:
            out = rt.run(wl[i:i + 1])
            assert 0.0 <= rt._state.cusum < 8.0 and (rt._state.cusum == 0.0 or not out["contact"][0])
            i += 1
        s = float(rt._state.cusum)
        peak = max(peak, s)
        if restart == "fault":
            assert rt.run(lost[None, :])["status"][0] & FAULT
            assert rt._state.cusum == s
            held += 1
            rt.run(wl[i:i + 50])       # past the fault, on to the next rise
            i += 50
            continue
        if restart == "reset":
            rt.reset()
        elif restart == "tare":
            rt.tare(wl[i:i + 100])
        else:
            rt.set_baseline(model.baseline_nm)
        assert rt._state.cusum == 0.0
    assert held == 2 and peak > 0.5


def test_the_float_build_and_model_run_the_same_cusum(random_model_factory, random_walk_factory):
    """The float model and the C float build agree with each other as closely as on the
    Schmitt trigger (docs/fixed-point.md, "the float engines"), and with the fixed point
    but at the margin; both hold S through nothing but their own arithmetic."""
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, CUSUM)
    wl = np.where(wl == 0.0, np.roll(wl, 40, axis=0), wl)     # no faults: the float model has no rule
    fixed = intref.to_engine_dict(intref.run(q, intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)))
    flt = floatref.predict(model, wl, model.baseline_nm)
    assert 0.1 < flt["contact"].mean() < 0.9
    assert np.mean(flt["contact"] == fixed["contact"]) > 0.98
    rt = FloatRuntime(model)
    rt.set_baseline(model.baseline_nm)
    cf = rt.run(wl)
    assert np.mean(cf["contact"] == flt["contact"]) > 0.995
    # Without the CUSUM the float model decides otherwise: the test sees the rule.
    schmitt = floatref.predict(dataclasses.replace(model, in_use=artifact.InUse()), wl, model.baseline_nm)
    assert np.mean(schmitt["contact"] != flt["contact"]) > 0.005


def test_in_use_checks_the_cusum_fields():
    artifact.InUse(contact_cusum_h=2.0, contact_cusum_k=0.5, contact_cusum_lo=-1.0, contact_cusum_hi=1.0)
    for bad in ({"contact_cusum_h": -1.0},
                {"contact_cusum_k": 1.0},                                   # off: the rest is 0
                {"contact_cusum_h": 1.0, "contact_cusum_lo": 2.0, "contact_cusum_hi": 1.0},
                {"contact_cusum_h": 1.0, "contact_on_margin": 0.5},         # two rise rules
                {"contact_cusum_h": 1.0, "contact_rise_samples": 3},
                {"contact_cusum_h": fm_decision.CUSUM_MAX * 2},
                {"contact_cusum_h": float("nan")}):
        with pytest.raises(ValueError):
            artifact.InUse(**bad)
    iu = artifact.InUse(contact_cusum_h=1e-4, contact_cusum_k=fm_decision.CUSUM_MAX, contact_cusum_lo=-3.0,
                  contact_cusum_hi=-3.0)
    got = qz.quantize_cusum(iu)
    assert got == {"contact_cusum_h_q8": 1, "contact_cusum_k_q8": TOP,
                   "contact_cusum_lo_q8": -768, "contact_cusum_hi_q8": -768}
    assert set(qz.quantize_cusum(artifact.InUse()).values()) == {0}


@pytest.mark.parametrize("fields", [
    {"contact_cusum_k_q8": 5},                                            # off, k set
    {"contact_cusum_h_q8": 10, "contact_cusum_lo_q8": 3, "contact_cusum_hi_q8": 2},
    {"contact_cusum_h_q8": 10, "contact_on_q8": 1},
    {"contact_cusum_h_q8": 10, "contact_rise_n": 2},
    {"contact_cusum_h_q8": TOP + 1},
    {"contact_cusum_h_q8": 10, "contact_cusum_hi_q8": -TOP - 1},
])
def test_both_loaders_refuse_a_bad_cusum_alike(random_model_factory, random_walk_factory, fields):
    model, q, _ = _drifting_model(random_model_factory, random_walk_factory, artifact.InUse())
    bad = dataclasses.replace(q, **fields)
    with pytest.raises(ModelCheckError):
        bad.check()
    bad.check = lambda: None          # serialise it anyway: the loaders must refuse it
    data = blob.to_bytes(bad)
    assert mutate.c_verdict(data) == mutate.python_verdict(data) == "FBG_ERR_RANGE"


@pytest.mark.parametrize("decision", ["per_sample", "schmitt", "cusum"])
def test_a_negative_output_multiplier_decides_alike_in_c_and_the_reference(
        random_model_factory, random_walk_factory, decision):
    """The contact net's output row with a negative multiplier: the margin has the opposite
    sign of acc. Both loaders accept it, and every engine computes the rule of
    contact_decision on acc > 0 and the margin as they are (docs/runtime.md, "In use")."""
    model, q, wl = _drifting_model(random_model_factory, random_walk_factory, artifact.InUse())
    if decision == "schmitt":
        q = dataclasses.replace(q, contact_on_q8=64, contact_off_q8=-128, contact_rise_n=2)
    elif decision == "cusum":
        q = _cusum(q, 256, -128, -1024, 1024)
    last = q.nets[0][-1]
    q.nets[0][-1] = dataclasses.replace(last, mult=-last.mult)
    data = blob.to_bytes(q)
    assert mutate.c_verdict(data) == mutate.python_verdict(data) == "FBG_OK"
    wl_fm, base = intref.nm_to_fm(wl), intref.nm_to_fm(model.baseline_nm)
    for kernel in ("portable", *host_kernels()):
        c, ref, _ = _run_both(q, wl_fm, base, kernel)
        _equal(c, ref)
    ok = (ref["status"] & FAULT) == 0
    contact, m = ref["contact"][ok], ref["contact_margin_q8"][ok]
    assert 0 < contact.mean() or decision == "schmitt"   # acc > 0 and margin >= 64: never
    if decision == "per_sample":
        # The rule is not the net's own decision here (acc > 0 is margin < 0): the reference
        # that took acc > 0 for it disagreed with C.
        assert np.any(contact[m < 0] == 0) or np.any(contact[m > 0] == 1)


def _ar1(rng: np.random.Generator, n: int, mean: float, rho: float = 0.9, sd: float = 0.3
         ) -> np.ndarray:
    e = rng.normal(0.0, sd, n)
    x, acc = np.empty(n), 0.0
    for i in range(n):
        acc = rho * acc + e[i]
        x[i] = acc
    return x + mean


def test_cusum_path_is_the_recursion():
    rng = np.random.default_rng(3)
    m = rng.normal(-0.5, 1.0, 2000)
    s, want = 0.0, []
    for v in m:
        s = max(0.0, s + min(max(v, -1.0), 2.0) - 0.25)
        want.append(s)
    assert np.allclose(fm_decision.cusum_path(m, 0.25, -1.0, 2.0), want, atol=1e-9)
    peaks = fm_decision.cusum_peaks(m, 0.25, -1.0, 2.0)
    w = np.asarray(want)
    assert peaks.size == np.sum((w > 0) & (np.concatenate([[0.0], w[:-1]]) == 0))
    assert peaks.max() == pytest.approx(w.max())


@pytest.mark.slow
def test_the_trainers_cusum_keeps_false_events_at_rest_rare():
    """Two minutes of correlated rest margins set h; 30 independent minutes of the same
    process then raise under the goal of one false event a minute (the aim is half that; two
    minutes of rest leave their mean, which a drift of 0 makes count, uncertain by a
    hundredth), with a drift low enough that the tail fit, not the floor, sets h."""
    rng = np.random.default_rng(2)
    calib = _ar1(rng, 120_000, -1.0)
    cs = fm_decision.cusum_parameters(calib, 1000.0, k=0.0)
    floor = fm_decision.CUSUM_FLOOR_SAMPLES * 0.5
    assert cs["h"] > 10 * floor and cs["hi"] == pytest.approx(0.5 * cs["h"])
    later = _ar1(rng, 1_800_000, -1.0)
    events = np.sum(fm_decision.cusum_peaks(later, cs["k"], cs["lo"], cs["hi"]) >= cs["h"])
    assert events / 30.0 <= 1.0
    # Aimed at the goal itself, the same rests give a lower threshold.
    loose = fm_decision.cusum_parameters(calib, 1000.0, k=0.0, false_per_min=1.0)
    assert loose["h"] < cs["h"]


def test_rests_that_never_reach_the_drift_leave_the_threshold_at_its_floor():
    """No excursion above the drift, on the rests or their extension: ``h`` is the floor of
    CUSUM_FLOOR_SAMPLES samples at the drift, and the clip still keeps one sample from
    rising."""
    rest = np.random.default_rng(5).normal(-5.0, 0.1, 60_000)
    for k in (0.2, 1.0, 3.0):
        cs = fm_decision.cusum_parameters(rest, 1000.0, k=k)
        assert cs["h"] == fm_decision.CUSUM_FLOOR_SAMPLES * max(k, 0.5)
        assert 0.0 < cs["hi"] - cs["k"] < cs["h"]


def test_recommended_sets_a_valid_cusum_from_the_rests():
    rng = np.random.default_rng(4)
    rest = _ar1(rng, 60_000, -2.0)
    iu = artifact.InUse.recommended(1000.0, rest, decision="cusum")
    cs = fm_decision.cusum_parameters(rest, 1000.0)
    q = float(np.quantile(rest, fm_decision.REST_MARGIN_QUANTILE))
    assert iu.contact_on_margin == 0.0 and iu.contact_rise_samples == 1
    assert iu.cusum == (cs["h"], cs["k"], cs["lo"], cs["hi"]) and cs["k"] == pytest.approx(max(q, 0))
    assert iu.contact_off_margin == -cs["k"]
    # No rest excursion of the calibration reaches h: it raises no false event on itself.
    assert np.all(fm_decision.cusum_peaks(rest, cs["k"], cs["lo"], cs["hi"]) < cs["h"])
    # Contact margins well above the rests move the drift to the midpoint.
    contact = rng.normal(6.0, 0.5, 5000)
    mid = fm_decision.cusum_parameters(rest, 1000.0, contact)
    assert mid["k"] == pytest.approx(0.5 * (max(q, 0.0) + np.quantile(contact, 0.1)))
    with pytest.raises(ValueError):
        artifact.InUse.recommended(1000.0, rest, decision="sprt")
    assert artifact.InUse.recommended(1000.0, rest).contact_cusum_h == 0.0


def test_the_rank_interpolation_is_numpys_bit_for_bit():
    rng = np.random.default_rng(7)
    values = np.sort(rng.logistic(-6.0, 1.0, 5000))
    x = np.concatenate([rng.uniform(-2.0, 5003.0, 20_000), np.arange(-1.0, 5002.0),
                        np.nextafter(np.arange(5000.0), np.inf)])
    assert np.array_equal(fm_decision._interp_on_ranks(x, values),
                          np.interp(x, np.arange(values.size), values))


def test_the_drift_grids_peaks_are_the_whole_series_within_its_rounding():
    """The threshold search reads each higher drift's excursion peaks within the lowest
    drift's excursions; they are :func:`cusum_peaks`' on the whole series, as many and equal
    to within the rounding of a walk summed over an hour, and so is the threshold."""
    rng = np.random.default_rng(11)
    rest = np.convolve(rng.normal(0.0, 1.0, 20_000), np.ones(8) / 3.0, "same") - 2.0
    extended = fm_decision.extended_rests(rest)
    q = float(np.quantile(rest, fm_decision.REST_MARGIN_QUANTILE))
    excursions = fm_decision._Excursions(extended, q)
    assert excursions.rows is not None and excursions.rows.size < extended.size / 100
    for k in (q, q + 0.1, q + 0.6, q + 1.5):
        whole, within = fm_decision.cusum_peaks(extended, k), excursions.peaks(k)
        assert whole.size == within.size and whole.size > 0
        np.testing.assert_allclose(within, whole, rtol=0, atol=1e-7)
        assert fm_decision._cusum_threshold(within, 60.0, rest, k, 0.5) == pytest.approx(
            fm_decision._cusum_threshold(whole, 60.0, rest, k, 0.5), rel=1e-9)
        assert np.array_equal(excursions.exact_peaks(k), whole)
    # Below the lowest drift the stretches do not hold its excursions: the whole series.
    assert np.array_equal(excursions.peaks(q - 0.5), fm_decision.cusum_peaks(extended, q - 0.5))
    # Rests that never rise at the lowest drift rise at no higher one: nothing is walked.
    quiet = fm_decision._Excursions(extended, float(extended.max()) + 1.0)
    assert quiet.lowest.size == 0 and quiet.rows is not None and quiet.rows.size == 0
    for k in (extended.max() + 1.0, extended.max() + 5.0):
        assert quiet.peaks(k).size == 0 == fm_decision.cusum_peaks(extended, k).size


def test_the_grid_interpolation_is_numpys_bit_for_bit():
    rng = np.random.default_rng(8)
    grid = np.linspace(-8.0, 8.0, 3201)
    log_tail = np.log(0.5 * np.exp(-0.5 * grid ** 2) + 1e-300)
    z = np.concatenate([rng.normal(0.0, 3.0, 50_000), grid, np.nextafter(grid, np.inf),
                        np.nextafter(grid, -np.inf), [-9.0, 9.0]])
    assert np.array_equal(fm_decision._interp_on_grid(z, grid, log_tail),
                          np.interp(z, grid, log_tail))


def test_mean_onset_counts_from_the_label_to_the_rise():
    step = np.concatenate([np.full(10, -3.0), np.full(20, 10.0)])
    # S: 10, 20, 30 from the label on: h 25 rises on its third sample, two after the label.
    assert fm_decision.mean_onset_samples([(step, 10)], 25.0, 0.0, -100.0, 100.0) == 2.0
    # A window that never rises counts its length after the label; the mean is over presses.
    never = np.full(30, -3.0)
    assert fm_decision.mean_onset_samples([(step, 10), (never, 10)], 25.0, 0.0, -100.0,
                                          100.0) == pytest.approx(0.5 * (2 + 20))
    assert fm_decision.mean_onset_samples([], 25.0, 0.0, -100.0, 100.0) == 0.0


def test_long_rests_raise_the_threshold_only_where_they_need_it():
    """The threshold holds the aim on the long rests as on the calibration's: noisier long
    rests raise it (and 10 independent minutes of them then stay within the goal), quieter
    ones leave it as the calibration's rests set it, and ones that are no rest to the net are
    left out."""
    rng = np.random.default_rng(5)
    rest = _ar1(rng, 20_000, -2.0)
    alone = fm_decision.cusum_parameters(rest, 1000.0)
    noisy = _ar1(rng, 180_000, -1.0)
    both = fm_decision.cusum_parameters(rest, 1000.0, long_rests=noisy)
    assert both["k"] == alone["k"] and both["h"] > alone["h"]
    assert both["long_minutes"] == pytest.approx(3.0) and alone["long_minutes"] == 0.0
    later = _ar1(rng, 600_000, -1.0)
    assert np.sum(fm_decision.cusum_peaks(later, both["k"], both["lo"], both["hi"])
                  >= both["h"]) / 10.0 <= 1.0
    assert np.sum(fm_decision.cusum_peaks(later, alone["k"], alone["lo"], alone["hi"])
                  >= alone["h"]) / 10.0 > 1.0
    quiet = _ar1(rng, 120_000, -4.0)
    assert fm_decision.cusum_parameters(rest, 1000.0, long_rests=quiet)["h"] == alone["h"]
    # Long rests the net reads as contact (their median past the rests' 99th percentile) are
    # no rest to it: left out, where they would have asked for a threshold no press reaches.
    contact_like = _ar1(rng, 60_000, 8.0)
    left_out = fm_decision.cusum_parameters(rest, 1000.0, long_rests=contact_like)
    assert left_out["h"] == alone["h"] and left_out["long_minutes"] == 0.0


def _creeping_idle(rng: np.random.Generator, minutes: float, end: float) -> np.ndarray:
    """An idle pad's margins: rest noise whose level climbs from -2 towards ``end`` with the
    log of the time, as the memory's play operators follow the noise's record lows."""
    n = int(minutes * 60_000)
    return _ar1(rng, n, 0.0) - 2.0 + (end + 2.0) * np.log1p(np.arange(n)) / np.log(n)


def test_idle_pads_hold_each_draw_within_the_aim():
    """A threshold read on rests that never last reaches below what a pad left alone for
    minutes comes to: there every idle draw raises many events. Given the idle draws, no draw
    raises more than the aim allows in its minutes (one in two minutes at half a minute),
    the threshold is never below the rests' alone, idle draws quieter than the rests leave it
    where the rests set it, and ones read as contact, which would hide the presses, are left
    out."""
    rng = np.random.default_rng(8)
    rest = _ar1(rng, 20_000, -2.0)
    alone = fm_decision.cusum_parameters(rest, 1000.0)
    idle = [_creeping_idle(rng, 2.0, -0.5) for _ in range(3)]
    both = fm_decision.cusum_parameters(rest, 1000.0, idle=idle)
    assert both["k"] == alone["k"] and both["h"] > alone["h"]
    assert both["idle_minutes"] == pytest.approx(6.0) and alone["idle_minutes"] == 0.0

    def events(cs: dict, margins: np.ndarray) -> int:
        return int(np.sum(fm_decision.cusum_peaks(margins, cs["k"], cs["lo"], cs["hi"])
                          >= cs["h"]))

    assert max(events(alone, m) for m in idle) > 1
    assert max(events(both, m) for m in idle) <= 1
    # The least such threshold: just below it, one draw raises a second event.
    assert fm_decision.idle_threshold(idle, both["k"], 0.5, 1000.0) == both["h"]
    lower = {**both, "h": float(np.nextafter(both["h"], 0.0))}
    assert max(events({**lower, "hi": fm_decision.CUSUM_MAX}, m) for m in idle) > 1
    quiet = [_ar1(rng, 120_000, -4.0) for _ in range(2)]
    assert fm_decision.cusum_parameters(rest, 1000.0, idle=quiet)["h"] == alone["h"]
    # Idle pads the net reads as contact (a calibration whose rests never lasted) ask for a
    # threshold no press reaches: given the presses, left out.
    presses = _rising_presses(rng, 20)
    contact_like = [_ar1(rng, 120_000, fm_decision.CUSUM_DRIFT_MAX, sd=1.0)]
    left_out = fm_decision.cusum_parameters(rest, 1000.0, idle=contact_like, presses=presses)
    plain = fm_decision.cusum_parameters(rest, 1000.0, presses=presses)
    assert left_out["h"] == plain["h"] and left_out["idle_minutes"] == 0.0
    kept = fm_decision.cusum_parameters(rest, 1000.0, idle=idle, presses=presses)
    assert kept["idle_minutes"] == pytest.approx(6.0) and kept["h"] >= plain["h"]


def _rising_presses(rng: np.random.Generator, n: int) -> list[tuple[np.ndarray, int]]:
    """Windows of presses whose margin climbs from rest to 8 at 0.4 a sample, with noise."""
    return [(np.concatenate([_ar1(rng, 100, -2.0), np.minimum(-2.0 + 0.4 * np.arange(1, 61), 8.0)
                             + rng.normal(0.0, 0.5, 60)]), 100) for _ in range(n)]


def test_the_drift_is_the_one_that_finds_the_calibrations_presses_soonest():
    """Given the calibration's presses, the drift is chosen at or above the rests' quantile,
    at the threshold that keeps the false events at their aim, where those presses rise
    soonest; on presses it never saw it is as quick as the quantile's drift or quicker.
    Long rests noisier than the calibration's make the quantile's drift wait for a high sum."""
    rng = np.random.default_rng(6)
    rest, long = _ar1(rng, 30_000, -2.0), _ar1(rng, 180_000, -1.0)
    seen, unseen = _rising_presses(rng, 20), _rising_presses(rng, 20)
    plain = fm_decision.cusum_parameters(rest, 1000.0, long_rests=long)
    chosen = fm_decision.cusum_parameters(rest, 1000.0, long_rests=long, presses=seen)
    assert plain["onset_samples"] is None and chosen["k"] > plain["k"]

    def onset(cs: dict, presses: list) -> float:
        return fm_decision.mean_onset_samples(presses, cs["h"], cs["k"], cs["lo"], cs["hi"])

    assert chosen["onset_samples"] == pytest.approx(onset(chosen, seen))
    assert onset(chosen, seen) < onset(plain, seen)
    assert onset(chosen, unseen) < onset(plain, unseen)
    highest = fm_decision.cusum_parameters(rest, 1000.0, k=fm_decision.CUSUM_DRIFT_MAX,
                                           long_rests=long)
    assert onset(highest, seen) >= onset(chosen, seen)


def _logistic_rests(rng: np.random.Generator, n: int) -> np.ndarray:
    """Rest margins with a contact net's spread and memory: an AR(1) of correlation 0.93 per
    sample (the family's rests), its values mapped to a logistic distribution about -6, whose
    upper tail is exponential (scale 0.9)."""
    z = _ar1(rng, n, 0.0, rho=0.93, sd=1.0)
    z /= z.std()
    upper = np.array([0.5 * math.erfc(v / math.sqrt(2.0)) for v in z])
    return -6.0 + 0.9 * np.log((1.0 - upper) / upper)


def test_extended_rests_keep_the_margins_spread_and_their_correlation():
    rng = np.random.default_rng(5)
    rest = _ar1(rng, 12_000, -3.0, rho=0.95, sd=0.4)
    ext = fm_decision.extended_rests(rest, 1000.0, minutes=5.0)
    assert ext.size == 300_000
    for q in (0.1, 0.5, 0.9, 0.99):
        assert np.quantile(ext, q) == pytest.approx(np.quantile(rest, q), abs=0.1 * rest.std())

    def lag1(v: np.ndarray) -> float:
        c = v - v.mean()
        return float(c[1:] @ c[:-1] / (c @ c))
    assert lag1(ext) == pytest.approx(lag1(rest), abs=0.03)
    # Past the samples' own highest, as minutes of them would go.
    assert ext.max() > rest.max()
    # One calibration, one extension; rests already that long or too few to model, as they are.
    np.testing.assert_array_equal(ext, fm_decision.extended_rests(rest, 1000.0, minutes=5.0))
    np.testing.assert_array_equal(fm_decision.extended_rests(rest, 1000.0, minutes=0.1), rest)
    np.testing.assert_array_equal(fm_decision.extended_rests(rest[:1000], 1000.0), rest[:1000])
    # Rests whose top percent ties leave no tail to fit, and are kept as they are.
    flat = np.where(rest > np.quantile(rest, 0.5), 1.0, rest)
    np.testing.assert_array_equal(fm_decision.extended_rests(flat, 1000.0), flat)


@pytest.mark.slow
def test_a_short_calibrations_cusum_stays_under_the_goal_over_minutes_of_rest():
    """Twelve seconds of rest (a 60-press calibration's) whose few highest samples set the
    drift low: on the rests as they are the threshold falls to its floor, and 30 minutes of
    the same process raise 2.8 false events a minute; on the rests extended, under the goal of
    one."""
    rng = np.random.default_rng(10)
    calib = _logistic_rests(rng, 12_000)
    later = _logistic_rests(rng, 1_800_000)
    cs = fm_decision.cusum_parameters(calib, 1000.0)
    assert cs["rest_minutes"] == pytest.approx(0.2)
    assert cs["extended_minutes"] == fm_decision.REST_EXTEND_MINUTES
    events = np.sum(fm_decision.cusum_peaks(later, cs["k"], cs["lo"], cs["hi"]) >= cs["h"])
    assert events / 30.0 <= 1.0
    # The calibration's samples as they are: the same drift, the floor or its highest peak.
    k = cs["k"]
    own = fm_decision.cusum_peaks(calib, k)
    h = max(fm_decision.CUSUM_FLOOR_SAMPLES * max(k, 0.5), float(own.max()) if own.size else 0.0)
    assert h < cs["h"]
    loud = np.sum(fm_decision.cusum_peaks(later, k, -fm_decision.CUSUM_MAX, k + h / 2) >= h)
    assert loud / 30.0 >= 2.0
