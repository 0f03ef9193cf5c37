"""The tradeoff harness, its timing helpers and quantization-aware fine-tuning."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from fbgforce.model import artifact, floatref
from fbgforce.model.decision import CUSUM_MAX
from fbgforce.tradeoff import grid, scoring, timing
from fbgforce.cli import main
from fbgforce.errors import InputError


def _mlp(rng: np.random.Generator, sizes: list[int]) -> artifact.MLP:
    return artifact.MLP([rng.standard_normal((b, a)) * np.sqrt(2.0 / a) for a, b in zip(sizes[:-1], sizes[1:])],
                  [rng.standard_normal(b) * 0.1 for b in sizes[1:]])


def _model(kind: str = "causal", seed: int = 0) -> artifact.HierarchicalModel:
    rng = np.random.default_rng(seed)
    taps = {"causal": np.exp(-0.5 * (np.arange(16) / 5.0) ** 2), "none": np.ones(1)}[kind]
    pre = artifact.Preprocess([1.01, 0.99, 1.0, 1.02], kind, 5.0 if kind == "causal" else 0.0,
                        taps / taps.sum(), [3.0, -2.0, 1.0, 0.5], [40.0, 30.0, 50.0, 45.0])
    return artifact.HierarchicalModel(pre, _mlp(rng, [4, 20, 10, 2]), _mlp(rng, [4, 20, 10, 1]),
                                _mlp(rng, [6, 20, 12, 2]), 10.0, 12.0, [10.5, 13.5], [5.0, 7.0],
                                [1530.0, 1538.0, 1546.0, 1554.0, 1562.0])


def _wavelengths(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.array([1530.0, 1538.0, 1546.0, 1554.0, 1562.0])
    load = np.clip(np.sin(np.arange(n) / 60.0), 0, None) * 40.0
    wl = base + 1e-3 * rng.standard_normal((n, 5)) * 4.0
    wl[:, :4] += 1e-3 * load[:, None] * np.array([1.5, -1.0, 2.0, 0.7])
    return wl


@pytest.mark.parametrize("kind", ["causal", "none"])
@pytest.mark.parametrize("nets", ["numpy", "onnx"])
def test_single_sample_pipeline_equals_batch(kind: str, nets: str) -> None:
    """What the single-sample timing runs is the real pipeline, sample for sample."""
    model = _model(kind)
    wl = _wavelengths(400)
    base = wl[:20].mean(axis=0)
    ref = floatref.predict(model, wl, base)
    pipe = timing.float_pipeline(model, base, nets)
    got = [pipe.push(wl[i]) for i in range(wl.shape[0])]
    contact = np.array([g["contact"][0] for g in got])
    assert 0 < contact.sum() < contact.size  # both branches exercised
    tol = 1e-9 if nets == "numpy" else 2e-3
    if nets == "numpy":
        assert np.array_equal(contact, ref["contact"])
    same = contact == ref["contact"]
    assert same.mean() > 0.99
    np.testing.assert_allclose(np.array([g["force_N"][0] for g in got])[same], ref["force_N"][same],
                               rtol=0, atol=tol * 10)
    np.testing.assert_allclose(np.array([g["x_mm"][0] for g in got])[same], ref["x_mm"][same],
                               rtol=0, atol=tol)


def test_single_sample_pipeline_refuses_centred_filter() -> None:
    model = _model()
    model.preprocess = artifact.Preprocess(model.preprocess.temp_coeff, "centred", 2.0, np.ones(5) / 5,
                                     model.preprocess.input_mean, model.preprocess.input_std)
    with pytest.raises(InputError, match="centred"):
        timing.float_pipeline(model, model.baseline_nm)


def test_measure_reports_every_engine_and_missing_callables() -> None:
    calls = {"a": 0, "b": 0}

    def single(i: int) -> None:
        calls["a"] += 1

    def batch(a: int, b: int) -> None:
        calls["b"] += b - a

    res = timing.measure([timing.Timer("x", single=single, batch=batch), timing.Timer("y")], 100,
                         single_calls=40, batch_size=30, batch_reps=4, rounds=2, warmup=5)
    assert res["x"]["single_calls"] == 40 and res["x"]["batch_calls"] == 4
    assert res["x"]["single_ns"] > 0 and res["x"]["batch_ns"] > 0
    assert res["y"]["single_ns"] is None and res["y"]["batch_ns"] is None
    assert calls["a"] == 45


def test_pareto_mask() -> None:
    pts = [(1.0, 5.0), (2.0, 1.0), (1.5, 3.0), (2.0, 6.0), (1.0, 5.0), (3.0, 1.0)]
    assert scoring.pareto_mask(pts) == [True, True, True, False, True, False]


def test_grid_shapes() -> None:
    s = grid.Settings(sigmas=(2.0, 5.0), default_sigma=5.0)
    star = [v.tag for v in grid.variants(s)]
    mems = [f"paper-causal-s5-mem-{m}" for m in ("none", "play",
                                                  "ema_4_7_play_0.03_0.1_0.25_0.5")]
    assert star == ["paper-nofilter", "paper-causal-s2", "paper-causal-s5", "half-causal-s5",
                    "quarter-causal-s5", "paper-centred-s5", *mems]
    s.grid = "full"
    # filters x widths, plus every other memory on the 2 x 3 causal variants
    assert len(grid.variants(s)) == 4 * 3 + 3 * 2 * 3
    s.grid = "memory"
    assert [v.memory for v in grid.variants(s)] == list(grid.MEMORIES)
    sizes = grid.scaled_sizes("quarter")
    assert sizes["location"] == [18, 12, 10] and sizes["contact"] == [18, 12, 5]


def test_error_index_and_match() -> None:
    ref = {"status": "ok", "contact_accuracy": 0.98, "rmse_force_N": 1.0, "rmse_x_mm": 0.5,
           "rmse_y_mm": 1.0}
    same = dict(ref, rmse_force_N=1.04)
    worse = dict(ref, rmse_y_mm=1.2)
    scoring.score([ref, same, worse], ref)
    assert ref["error_index"] == 1.0 and ref["matches_reference"]
    assert same["matches_reference"] and math.isclose(same["error_index"], 1.04 ** 0.25)
    assert not worse["matches_reference"] and worse["error_index"] > 1.0


def test_the_cortex_m4_figures_are_quoted_in_estimated_cycles(monkeypatch) -> None:
    """target-report's cycle estimate reaches the row, the summary and the table; a report
    without it falls back to instructions and says it counts one per cycle."""
    from fbgforce.tradeoff import outputs, run

    report = {"instructions_per_step": 14079, "bit_exact": True, "budget_fraction_at_168MHz": 0.0838,
              "cycles_per_step_estimate": 27075, "budget_fraction_cycles_at_168MHz": 0.1612,
              "flash_bytes": 48708, "builds": {"portable": {"instructions_per_step": 98519}}}

    class Done:
        returncode, stderr = 0, ""
        stdout = "progress\n" + json.dumps(report) + "\n"

    monkeypatch.setattr(run.subprocess, "run", lambda *a, **k: Done())
    m4 = run.target_instructions(Path("M"))
    assert m4["m4_cycles_per_step_estimate"] == 27075
    assert m4["m4_budget_fraction_cycles_at_168MHz"] == 0.1612
    assert m4["m4_instructions_portable"] == 98519
    row = {"status": "ok", "variant": "paper-causal-s5", "engine": "fixed", "width": "paper",
           "filter": "causal", "sigma": 5.0, "memory": "both", "memory_states": 8,
           "memory_state_bytes": 32, "causal": True, "contact_accuracy": 0.968,
           "rmse_force_N": 0.37, "rmse_x_mm": 0.83, "rmse_y_mm": 0.93, "error_index": 1.0,
           "is_reference": True, "matches_reference": True, "macs": 13840, "macs_nets": 13776,
           "filter_delay_ms": 3.7, "host_batch_ns": 420.0, "host_single_ns": 1060.0,
           "model_bytes": 32632, **m4}
    text = outputs.summary_paragraph({"rows": [row]})
    assert "14079 instructions per step, 27075 estimated cycles (16.1 % of a 1 kHz period" in text
    table = outputs.markdown_table({"rows": [row]})
    header, _, line = table.splitlines()[:3]
    cells = [c.strip() for c in line.split("|")]
    assert cells[[c.strip() for c in header.split("|")].index("M4 cycles (est.)")] == "27075"
    assert "m4_cycles_per_step_estimate" in outputs.CSV_COLUMNS
    old = {k: v for k, v in row.items() if "cycles" not in k}
    assert "(8.4 % of a 1 kHz period at 168 MHz at one instruction per cycle)" in \
        outputs.summary_paragraph({"rows": [old]})


def test_qat_recovers_int8_accuracy() -> None:
    """Fine-tuning with fake-quantised weights lowers the quantised net's loss."""
    from fbgforce.trainer import qat
    from fbgforce.trainer.nets import FlatMLP, fit

    rng = np.random.default_rng(0)
    x = rng.standard_normal((3000, 4))
    y = (np.sin(x[:, :1] * 1.5) + x[:, 1:2] * x[:, 2:3] - 0.3 * x[:, 3:4])
    net = FlatMLP([4, 24, 16, 1], rng)
    fit(net, "mse", x, y, epochs=40, learning_rate=3e-3, progress=False)
    mlp = net.to_mlp()
    # 3-bit weights make the quantisation loss unmistakable on a small net.
    fq = qat.FakeQuantMLP(mlp, 3, 16, x)
    before = float(np.mean((fq.forward(x) - y) ** 2))
    float_loss = float(np.mean((mlp.forward(x) - y) ** 2))
    assert before > 3 * float_loss
    fit(fq, "mse", x, y, epochs=6, learning_rate=1e-3, progress=False)
    after = float(np.mean((fq.forward(x) - y) ** 2))
    assert after < 0.5 * before
    # Straight-through: what is kept are float shadow weights, not the quantised copies.
    assert any(not np.array_equal(w, q) for w, q in zip(fq.W, fq.quantized_weights()))


def test_qat_finetune_keeps_model_contract() -> None:
    from fbgforce.trainer import qat

    model = _model()
    rng = np.random.default_rng(2)
    z = rng.standard_normal((600, 4))
    contact = z[:, 0] > 0
    force = np.where(contact, 10 + 5 * z[:, 1], 0.0)
    x = np.where(contact, 10 + z[:, 2], np.nan)
    y = np.where(contact, 13 + z[:, 3], np.nan)
    tuned, rep = qat.finetune(model, z, contact, force, x, y, epochs=1, progress=False)
    assert [n.sizes for n in tuned.nets.values()] == [n.sizes for n in model.nets.values()]
    assert tuned.metadata["qat"]["weight_bits"] == 8
    assert tuned.preprocess is model.preprocess and tuned.force_scale == model.force_scale
    assert set(rep) >= {"contact", "force", "location"}
    assert all(isinstance(rep[k]["kept_start"], bool) for k in ("contact", "force", "location"))


def test_qat_leaves_an_input_the_contact_net_does_not_read_unread() -> None:
    """A contact net trained not to read an input (its first layer's column all zero, as the
    trainer leaves the play operators) does not learn to read it in fine-tuning, even where
    the labels would reward it."""
    from fbgforce.trainer import qat

    model = _model()
    model.contact.weights[0][:, 3] = 0.0
    rng = np.random.default_rng(5)
    z = rng.standard_normal((600, 4))
    contact = z[:, 0] + z[:, 3] > 0
    force = np.where(contact, 10 + 5 * z[:, 1], 0.0)
    x = np.where(contact, 10 + z[:, 2], np.nan)
    y = np.where(contact, 13 + z[:, 3], np.nan)
    tuned, rep = qat.finetune(model, z, contact, force, x, y, epochs=3, progress=False)
    assert rep["contact"]["kept_start"] is False
    assert not tuned.contact.weights[0][:, 3].any() and tuned.contact.weights[0][:, :3].any()


@pytest.mark.slow
def test_tradeoff_quick_end_to_end(tmp_path, capsys) -> None:
    """``fbgforce tradeoff --quick`` on a small scene: every output written and consistent."""
    sim = pytest.importorskip("fbgforce.sim")
    if not hasattr(sim, "simulate"):
        pytest.skip("simulator not available")
    out = tmp_path / "t"
    code = main(["tradeoff", "--scene", "smoke", "--out", str(out), "--quick", "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    res = json.loads((out / "tradeoff.json").read_text())
    for name in ("json", "csv", "md"):
        assert (out / f"tradeoff.{name}").stat().st_size > 0
    rows = res["rows"]
    ok = [r for r in rows if r["status"] == "ok"]
    engines_ok = {r["engine"] for r in ok}
    assert {"float", "onnx"} <= engines_ok
    # Every engine is either measured or says why not; nothing silently dropped.
    assert {r["engine"] for r in rows} == {s.name for s in grid.ENGINE_SPECS}
    assert all(r["status"] == "ok" or r["status"].startswith(("missing", "n/a")) for r in rows)
    ref = [r for r in ok if r["is_reference"]]
    assert len(ref) == 1 and ref[0]["error_index"] == 1.0
    for r in ok:
        assert 0.0 <= r["contact_accuracy"] <= 1.0 and r["rmse_force_N"] >= 0
        assert r["host_batch_ns"] > 0 and r["macs"] >= r["macs_nets"] > 0
        if r["causal"]:
            assert r["host_single_ns"] > 0
    # onnxruntime and numpy score the same model alike (float32 vs float64).
    by = {(r["variant"], r["engine"]): r for r in ok}
    for (variant, engine), r in by.items():
        if engine == "onnx":
            f64 = by[(variant, "float")]
            assert abs(r["rmse_force_N"] - f64["rmse_force_N"]) < 0.01 * f64["rmse_force_N"] + 1e-3
    # The shipped causal filter delays; no filter does not; the front is non-empty.
    delays = {r["filter"]: r["filter_delay_ms"] for r in ok}
    assert delays["none"] == 0.0 and delays["causal"] > 0.0
    assert any(r["pareto_compute"] for r in ok)
    assert summary["measured"] == len(ok) and summary["summary"] == res["summary"]
    assert "reference" in res["summary"]
    csv_lines = (out / "tradeoff.csv").read_text().strip().splitlines()
    assert len(csv_lines) == len(rows) + 1


def test_engines_take_the_engine_names_and_the_documented_aliases(tmp_path, monkeypatch, capsys) -> None:
    """One vocabulary: the columns are named as fbgforce.evaluation.engines names its engines; the names
    docs/cli.md lists for --engines before are accepted for the same columns."""
    import fbgforce.tradeoff.artifacts as tart
    import fbgforce.tradeoff.run as trun

    seen: list[tuple[str, ...]] = []
    monkeypatch.setattr(tart, "prepare_data", lambda *args: [])

    def capture(paths, out, s, log=print):
        seen.append(s.engines)
        raise InputError("stop here", column="--engines")

    monkeypatch.setattr(trun, "run", capture)
    out = str(tmp_path / "t")
    assert main(["tradeoff", "--quick", "--scene", "smoke", "--out", out, "--engines", "float", "fixed-int8"]) == 2
    assert main(["tradeoff", "--quick", "--scene", "smoke", "--out", out, "--engines", "numpy-f64", "c-int8", "float"]) == 2
    assert seen == [("float", "fixed-int8"), ("float", "fixed-int8")]
    assert {spec.name for spec in grid.ENGINE_SPECS} == {"float", "onnx", "cfloat", "fixed",
                                                           "fixed-int8", "fixed-int8-qat"}
    assert main(["tradeoff", "--quick", "--scene", "smoke", "--out", out, "--engines", "numpy"]) == 2
    assert "unknown engine(s) numpy" in capsys.readouterr().err


def test_the_decision_curve_has_both_rules(small_exported_dir, small_dataset_path, tmp_path) -> None:
    """``fbgforce tradeoff --decision``'s rows: the Schmitt trigger's and the CUSUM's, scored
    through the C runtime; a threshold no press reaches detects nothing, a low one detects."""
    from fbgforce.recordings import dataset
    from fbgforce.tradeoff import decision

    ds = dataset.load(small_dataset_path)
    res = decision.decision_curve(small_exported_dir, [ds], on_scales=(1.0,), rise_counts=(3,),
                                  h_scales=(1.0, 1e12), k_offsets=(0.0,))
    rules = [r["rule"] for r in res["rows"]]
    assert rules == ["schmitt", "cusum", "cusum"]
    low, high = res["rows"][1], res["rows"][2]
    assert low["cusum_h"] == pytest.approx(res["cusum_base"]["h"])
    assert low["cusum_hi"] == pytest.approx(low["cusum_k"] + 0.5 * low["cusum_h"])
    assert low["detected_above_1N"] > 0.9 and high["detected_above_1N"] == 0.0
    # A threshold past the contract's range is swept at its edge.
    assert high["cusum_h"] == CUSUM_MAX
    assert high["cusum_hi"] == pytest.approx(high["cusum_k"] + 0.5 * CUSUM_MAX)
    assert res["rows"][0]["default"] and not low["default"]
    csv = decision.csv_text(res).splitlines()
    assert csv[0].split(",") == list(decision.CSV_COLUMNS) and len(csv) == 4
    assert csv[2].startswith("cusum,,,") and csv[1].startswith("schmitt,")
    md = decision.markdown(res)
    assert "| cusum |" in md and "| schmitt (default) |" in md
    # Beside the grid, what the recordings' own noise allows any decision at the same quiet.
    from fbgforce.evaluation.onset_bound import bound
    assert res["noise_allows"] == bound([ds], decision.QUIET_PER_MIN)
    assert (f"allows no decision within 1 false event(s) per minute at rest an onset before "
            f"{res['noise_allows']['onset_bound_ms']['median']:.1f} ms median") in md
    assert decision.plot(res, tmp_path / "d.png").stat().st_size > 1000


def test_the_quickest_quiet_setting_is_the_earliest_onset_within_the_false_event_rate() -> None:
    """Each rule's quickest row among those quiet enough; a quicker noisy row is passed over,
    a tie goes to the better detection, and a rule with no quiet row says so (None)."""
    from fbgforce.tradeoff import decision

    def row(rule: str, false: float | None, onset: float | None, det: float | None) -> dict:
        return {"rule": rule, "false_events_per_min": false, "onset_median_ms": onset,
                "onset_p90_ms": None, "detected_above_1N": det, "default": False, "cusum_k": 1.0,
                "cusum_h": 3.0, "contact_on_margin": 1.0, "contact_rise_samples": 3}

    rows = [row("cusum", 4.0, 8.0, 1.0), row("cusum", 0.5, 12.0, 0.99),
            row("cusum", 1.0, 12.0, 0.999), row("cusum", 0.0, 15.0, 1.0),
            row("schmitt", 2.0, 9.0, 1.0), row("schmitt", None, None, None)]
    best = decision.quickest_quiet(rows)
    assert best["cusum"] is rows[2] and best["schmitt"] is None
    assert decision.quickest_quiet(rows, per_min=5.0)["cusum"] is rows[0]
    md = decision.markdown({"rows": rows[:5], "quickest": best})
    assert "quickest cusum within 1 false event(s) per minute at rest: CUSUM k 1.00, h 3.00, " \
           "1.00 /min, onset 12.0 ms" in md
    assert "- schmitt: no setting of the grid stays within 1" in md


@pytest.mark.slow
def test_tradeoff_decision_cli_writes_the_csv(small_exported_dir, small_dataset_path, tmp_path,
                                              capsys) -> None:
    out = tmp_path / "dec"
    assert main(["tradeoff", "--decision", str(small_exported_dir), "--data",
                 str(small_dataset_path), "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert {r["rule"] for r in res["rows"]} == {"schmitt", "cusum"}
    for name in ("decision.json", "decision.md", "decision.csv", "decision.png"):
        assert (out / name).is_file()
