"""An idle pad through a model's pipeline (bench/bench_idle.py): the command, its errors, and
engines that agree on it."""
from __future__ import annotations

import json

from fbgforce.bench.bench_idle import idle_events, main


def test_the_command_counts_each_draws_false_events(small_exported_dir, capsys):
    assert main(["--model", str(small_exported_dir), "--minutes", "0.1", "--draws", "2",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["engine"] == "fixed" and len(out["draws"]) == 2
    rates = [d["false_events_per_min"] for d in out["draws"]]
    assert out["worst_per_min"] == max(rates) and all(r >= 0 for r in rates)
    assert all(0.0 <= d["contact_share"] <= 1.0 for d in out["draws"])
    assert main(["--model", str(small_exported_dir), "--minutes", "0.1", "--draws", "1"]) == 0
    assert "false contact events a minute" in capsys.readouterr().out
    assert main(["--model", str(small_exported_dir), "--draws", "0"]) == 2
    assert "--draws at least 1" in capsys.readouterr().err


def test_the_fixed_point_and_its_integer_reference_see_the_same_idle_pad(small_exported_dir):
    """The same draws through the C fixed point and export/intref.py: the same events, bit
    for bit the same contact share (a louder pad than the calibration's, so that some rise)."""
    fixed = idle_events(str(small_exported_dir), noise_pm=20.0, minutes=0.05, draws=2)
    ref = idle_events(str(small_exported_dir), noise_pm=20.0, minutes=0.05, draws=2,
                      engine="intref")
    assert fixed["draws"] == ref["draws"]
    assert any(d["contact_share"] > 0 for d in fixed["draws"])
