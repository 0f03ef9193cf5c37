"""``fbgforce demo`` end to end on the small scene with very few epochs: every step runs, the
JSON summary lists the figures, and each PNG is a real image of the announced size."""
from __future__ import annotations

import pytest

import json
import struct
from pathlib import Path

import numpy as np

from fbgforce.evaluation import figures
from fbgforce.cli import main

#: Slow (pytest -m slow): the whole demo chain.
pytestmark = pytest.mark.slow

EXPECTED_FIGURES = {"force_vs_true.png", "error_map.png", "contact_by_force.png",
                    "paper_vs_ours.png", "accuracy_vs_time.png"}


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR", f"{path} is not a PNG"
    return struct.unpack(">II", head[16:24])


def test_demo_quick_writes_figures_listed_in_json(tmp_path, capsys):
    import matplotlib.image as mpimg

    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--epochs", "2", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["verify"]["mismatches"] == 0
    assert set(summary["evaluate"]) == {"float", "onnx", "fixed", "cfloat"}
    for m in summary["evaluate"].values():
        assert m["us_per_sample"] > 0 and m["split"] == "test"
    listed = summary["figures"]
    assert {Path(f["path"]).name for f in listed} == EXPECTED_FIGURES
    for f in listed:
        path = Path(f["path"])
        assert path.parent == out / "figures"
        assert (f["width_px"], f["height_px"]) == figures.SIZE_PX
        assert _png_size(path) == figures.SIZE_PX, path.name
        img = mpimg.imread(path)
        assert img.shape[:2] == (figures.SIZE_PX[1], figures.SIZE_PX[0]), path.name
        # Non-empty: more than a blank canvas (several distinct colours, ink on the page).
        rgb = img[..., :3].reshape(-1, 3)
        assert np.unique(rgb, axis=0).shape[0] > 20, path.name
        assert (rgb.sum(axis=1) < 1.5).mean() > 0.005, path.name
    assert (out / "model" / "model.fbgm").is_file() and (out / "report").is_dir()
    # The report's onset stands beside what the recordings' own noise allows.
    allows = json.loads((out / "report" / "report.json").read_text()
                        )["network"]["causal"]["metrics"]["noise_allows"]
    text = (out / "report" / "report.md").read_text()
    assert ("lets no contact decision within one false event a minute at rest find these "
            f"presses sooner than {allows['onset_bound_ms']['median']:.1f} ms median") in text
