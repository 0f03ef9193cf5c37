"""Every engine against the float model, and every pair of engines against each other, on one
recording in use: presses that turn at their peak and presses held for 1-3 s, rests between
them, with the stages after the nets on (the decision over time with its rise count and
release hysteresis, the settled-hold gain, the at-rest tracker).

The tolerances are the table of docs/export-onnx.md ("Every engine against the float
model"): :data:`TOLERANCE` below is that table. A pair of engines is held to the sum of their
tolerances against the float model.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import shutil
from typing import Any, Iterator

import numpy as np
import pytest

from fbgforce.evaluation import engines
from fbgforce.evaluation import metrics as fmetrics
from fbgforce.model import artifact, modeldir
from fbgforce import sim
from fbgforce.export.exporter import export_model, recording_baseline
from fbgforce.trainer.evaluate import evaluate

ENGINES = ("float", "onnx", "cfloat", "fixed")
#: The metric keys every engine shares (docs/cli.md); the fixed-point engine is held to these.
SHARED = (".contact_accuracy", ".rmse_force_N", ".rmse_x_mm", ".rmse_y_mm", ".n_samples")
#: Per engine, against the float model (docs/export-onnx.md): the share of samples whose
#: contact decision may differ (on this recording, for the fixed-point engine), the relative
#: difference of the metrics of :func:`fbgforce.trainer.evaluate.evaluate` (``keys``: which;
#: None, every number but the onset and release delays of ``contact_timing``), their
#: difference in ms, and the per-sample rule (see :func:`_per_sample_bounds`).
TOLERANCE: dict[str, dict[str, Any]] = {
    "float": {"contact": 0.0, "metrics": 0.0, "keys": None, "timing_ms": 0.0, "samples": "equal"},
    "onnx": {"contact": 0.0, "metrics": 1e-3, "keys": None, "timing_ms": 0.0, "samples": "float32"},
    "cfloat": {"contact": 0.0, "metrics": 1e-3, "keys": None, "timing_ms": 0.0,
               "samples": "float32"},
    "fixed": {"contact": 1e-3, "metrics": 2e-2, "keys": SHARED, "timing_ms": 1.0,
              "samples": "error_bounds"},
}
#: float32 engines: force, x and y within this share of the output's scale, max(1, max |out|);
#: p_contact within it absolutely.
FLOAT32_REL = 1e-5
#: The float32 engines decide as the float model where no float64 quantity lies within this of
#: a threshold it is compared with (the margins' and forces' float32 errors are about 1e-5).
FLOAT32_CLEAR = 1e-4
#: The fixed-point engine: force within (1 + |hold_gain|) times the export's error bound on at
#: least this share of the samples both call contact (on the rest the settled-hold gain's
#: steady test fell on the other side of its band, and its ramp stands elsewhere).
FIXED_WITHIN_BOUND = 0.99
#: A settled-hold gain that acts on this small model's noisy holds: a wider band, a shorter
#: settle and ramp than the trainer's default (docs/runtime.md, "In use").
HOLD = dict(hold_gain=0.05, hold_settle=50, hold_band_N=1.0, hold_band_frac=0.1, hold_shift=5,
            hold_ramp_shift=5)


@pytest.fixture(scope="module")
def in_use_dir(small_model_dir, tmp_path_factory):
    """``small_model_dir`` (whose trained decision has a rise count and a release hysteresis,
    and whose tracker is on) with the settled-hold gain on, exported."""
    out = tmp_path_factory.mktemp("in_use") / "model"
    shutil.copytree(small_model_dir, out)
    model = modeldir.load(out)
    model.in_use = dataclasses.replace(model.in_use, **HOLD)
    modeldir.save(model, out)
    export_model(out)
    return out


@pytest.fixture(scope="module")
def recording():
    """The calibration device of ``smoke``: 10 presses, about half of them held 1-3 s at
    their peak, 0.2 s rests between them (17,359 samples)."""
    scene = sim.load_scene("smoke").replace(schedule={"n_presses": 10, "hold_s": 1.0,
                                                      "hold_max_s": 3.0, "hold_fraction": 0.5})
    return sim.simulate(scene, seed=5)


@pytest.fixture(scope="module")
def runs(in_use_dir, recording):
    """Every engine's output on the recording, its metrics, and the model."""
    model = modeldir.load(in_use_dir)
    base = recording_baseline(recording)
    out = {}
    for name in ENGINES:
        pred = engines.run_engine(name, in_use_dir, model, recording.wl_nm, base)
        out[name] = {"pred": pred, "metrics": evaluate(in_use_dir, [recording], engine=name,
                                                        model=model, predictions=[pred])}
    return model, out


def _leaves(doc: Any, path: str = "") -> Iterator[tuple[str, float]]:
    """Every number in a metrics document, by its path."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, f"{path}.{k}")
    elif isinstance(doc, (list, tuple)):
        for i, v in enumerate(doc):
            yield from _leaves(v, f"{path}[{i}]")
    elif isinstance(doc, (int, float)) and not isinstance(doc, bool):
        yield path, float(doc)


def _metric_numbers(m: dict[str, Any]) -> dict[str, float]:
    return dict(_leaves({k: v for k, v in m.items() if k not in ("engine", "model", "data")}))


def test_the_recording_exercises_every_stage(runs, recording):
    """Contact, rests and holds; the decision over time waits for its rise count and holds
    contact through a release where the net's own decision has let go; the settled-hold gain
    moves the force; the tracker is on. Without these the agreement below would prove less."""
    model, out = runs
    iu = model.in_use
    assert iu.contact_rise_samples > 1 and iu.contact_on_margin > 0 > iu.contact_off_margin
    assert iu.track_shift and iu.hold_gain == HOLD["hold_gain"]
    pred = out["float"]["pred"]
    own = pred["margin"] > 0.0
    assert np.count_nonzero(pred["contact"] & ~own) >= 10       # held through a release
    assert np.count_nonzero(~pred["contact"] & own) >= 10       # waiting for the rise count
    gained = pred["contact"] & (pred["force_N"] != pred["force_raw_N"])
    assert np.count_nonzero(gained) > 1000
    use = fmetrics.use_masks(pred["contact"], recording.contact, recording.force_N, recording.t_s)
    assert use["held"].sum() > 3000 and use["rest"].sum() > 1000
    assert 0.5 < pred["contact"].mean() < 0.95


def _per_sample_bounds(name: str, model: artifact.HierarchicalModel, in_use_dir, ref: dict[str, np.ndarray]
                       ) -> dict[str, np.ndarray | float]:
    """The bound of ``name`` against the float model on each sample both call contact: force,
    x and y (each (n,) or a number)."""
    rule = TOLERANCE[name]["samples"]
    if rule == "equal":
        return {"force_N": 0.0, "x_mm": 0.0, "y_mm": 0.0}
    if rule == "float32":
        return {k: FLOAT32_REL * max(1.0, float(np.nanmax(np.abs(ref[k])))) for k in ("force_N", "x_mm", "y_mm")}
    eb = json.loads((in_use_dir / "export_report.json").read_text())["error_bounds"]
    g = abs(model.in_use.hold_gain)
    # The gain multiplies the nets' force by 1 + g w with w in [0, 1]: their error grows by at
    # most 1 + g, and a ramp that stands elsewhere moves the force by at most g |force|.
    return {"force_N": (1.0 + g) * eb["force_N"] + g * np.abs(ref["force_N"]),
            "force_N_most": (1.0 + g) * eb["force_N"], "x_mm": eb["x_mm"], "y_mm": eb["y_mm"]}


def _clear_of_thresholds(model: artifact.HierarchicalModel, pred: dict[str, np.ndarray]) -> None:
    """The float model's margins and steady tests lie farther than :data:`FLOAT32_CLEAR` from
    every threshold they meet, so a float32 engine must decide as it does on every sample."""
    iu = model.in_use
    good = pred["status"] == 0
    margin = pred["margin"][good]
    for t in (0.0, iu.contact_on_margin, iu.contact_off_margin):
        near = np.abs(margin - t).min()
        assert near > FLOAT32_CLEAR, f"a margin lies {near:.2g} from the threshold {t}"
    force, contact = pred["force_raw_N"], pred["contact"] & (pred["status"] == 0)
    avg, primed, alpha, gaps = 0.0, False, 1.0 / (1 << iu.hold_shift), []
    for f, c in zip(force.tolist(), contact.tolist()):
        if not c:
            primed = False
            continue
        avg, primed = (avg + (f - avg) * alpha, True) if primed else (f, True)
        gaps.append(abs(abs(f - avg) - max(iu.hold_band_N, iu.hold_band_frac * abs(f))))
    assert min(gaps) > FLOAT32_CLEAR, f"a steady test lies {min(gaps):.2g} N from its band"


def _differences_begin_near_a_threshold(model: artifact.HierarchicalModel, in_use_dir,
                                        ref: dict[str, np.ndarray], differ: np.ndarray) -> None:
    """Every run of differing decisions begins at, or within the rise count after, a sample
    whose float margin lies within the export's margin bound of a threshold (0, the rise or
    the release margin)."""
    eb = json.loads((in_use_dir / "export_report.json").read_text())["error_bounds"]
    iu = model.in_use
    thresholds = np.array([0.0, iu.contact_on_margin, iu.contact_off_margin])
    near = (np.abs(ref["margin"][:, None] - thresholds).min(axis=1) <= eb["contact_margin"])
    for start in np.flatnonzero(differ & ~np.concatenate([[False], differ[:-1]])):
        window = near[max(0, start - iu.contact_rise_samples + 1):start + 1]
        assert window.any(), f"a decision differs at sample {start}, far from every threshold"


def _against_float(name: str, model: artifact.HierarchicalModel, in_use_dir, runs_out: dict[str, Any]
                   ) -> None:
    tol = TOLERANCE[name]
    ref, got = runs_out["float"]["pred"], runs_out[name]["pred"]
    if tol["samples"] == "float32":
        _clear_of_thresholds(model, ref)
    _metrics_agree(name, "float", runs_out, tol["metrics"], tol["timing_ms"], tol["keys"])
    differ = got["contact"] != ref["contact"]
    assert differ.mean() <= tol["contact"], f"{name}: {differ.sum()} contact decisions differ"
    if tol["samples"] == "error_bounds":
        _differences_begin_near_a_threshold(model, in_use_dir, ref, differ)
    both = got["contact"] & ref["contact"]
    assert np.array_equal(np.isnan(got["x_mm"][both]), np.isnan(ref["x_mm"][both]))
    bounds = _per_sample_bounds(name, model, in_use_dir, ref)
    for key in ("force_N", "x_mm", "y_mm"):
        err = np.abs(got[key] - ref[key])[both]
        bound = np.broadcast_to(bounds[key], ref[key].shape)[both]
        worst = int(np.argmax(err - bound))
        assert np.all(err <= bound), (f"{name} {key}: {err[worst]:.3g} against a bound of "
                                      f"{bound[worst]:.3g}")
    if "force_N_most" in bounds:
        within = np.abs(got["force_N"] - ref["force_N"])[both] <= bounds["force_N_most"]
        assert within.mean() >= FIXED_WITHIN_BOUND
    if tol["samples"] == "float32":
        np.testing.assert_allclose(got["p_contact"], ref["p_contact"], rtol=0, atol=FLOAT32_REL)


def _metrics_agree(a: str, b: str, runs_out: dict[str, Any], rel: float, timing_ms: float,
                   keys: tuple[str, ...] | None) -> None:
    ma, mb = (_metric_numbers(runs_out[n]["metrics"]) for n in (a, b))
    assert ma.keys() == mb.keys()
    if keys is not None:
        assert set(keys) <= ma.keys()
        ma, mb = ({k: m[k] for k in m if k in keys or k.startswith(".contact_timing.")}
                  for m in (ma, mb))

    def off(k: str) -> bool:
        if k.startswith(".contact_timing."):
            return abs(ma[k] - mb[k]) > timing_ms
        return abs(ma[k] - mb[k]) > rel * max(abs(ma[k]), abs(mb[k]))

    bad = {k: (ma[k], mb[k]) for k in ma if off(k)}
    assert not bad, f"{a} against {b}: metrics beyond {rel:.1%} or {timing_ms} ms: {bad}"


@pytest.mark.parametrize("name", ENGINES[1:])
def test_every_engine_against_the_float_model(runs, in_use_dir, name):
    """Each engine within its tolerance of the float model, per sample and on every metric
    (the onnx engine: the metrics within 0.1 %, every output within float32 rounding)."""
    model, out = runs
    _against_float(name, model, in_use_dir, out)
    assert len(_metric_numbers(out[name]["metrics"])) > 50


@pytest.mark.parametrize("a,b", list(itertools.combinations(ENGINES[1:], 2)))
def test_every_pair_of_engines(runs, in_use_dir, a, b):
    """Two engines agree within the sum of their tolerances against the float model."""
    model, out = runs
    pa, pb = out[a]["pred"], out[b]["pred"]
    ref = out["float"]["pred"]
    differ = pa["contact"] != pb["contact"]
    assert differ.mean() <= TOLERANCE[a]["contact"] + TOLERANCE[b]["contact"]
    both = pa["contact"] & pb["contact"]
    ba, bb = (_per_sample_bounds(n, model, in_use_dir, ref) for n in (a, b))
    for key in ("force_N", "x_mm", "y_mm"):
        err = np.abs(pa[key] - pb[key])[both]
        bound = np.broadcast_to(np.add(ba[key], bb[key]), ref[key].shape)[both]
        assert np.all(err <= bound), f"{a} against {b}: {key} beyond the summed bound"
    keys = [TOLERANCE[n]["keys"] for n in (a, b) if TOLERANCE[n]["keys"] is not None]
    _metrics_agree(a, b, out, TOLERANCE[a]["metrics"] + TOLERANCE[b]["metrics"],
                   TOLERANCE[a]["timing_ms"] + TOLERANCE[b]["timing_ms"],
                   keys[0] if keys else None)
