"""``examples/edge_gradients.py --quick`` runs end to end and writes what it promises."""

from __future__ import annotations

import json
import runpy
import sys
from pathlib import Path

import numpy as np

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "edge_gradients.py"


def test_edge_gradients_example_quick(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE.parent))  # as `python examples/...` would
    monkeypatch.setattr(sys, "argv", [str(EXAMPLE), "--quick", "--out", str(tmp_path)])
    runpy.run_path(str(EXAMPLE), run_name="__main__")
    result = json.loads((tmp_path / "edge_gradients.json").read_text())
    assert len(result["calibration"]) == 2
    assert set(result["basin"]) == {"pixel centres", "edges"}
    assert all(0.0 <= c["fraction"] <= 1.0 for c in result["coverage_30deg"])
    for name in ("basin.png", "silhouette_zoom.png", "edge_gradients.md"):
        assert (tmp_path / name).stat().st_size > 0


SHADOW_EXAMPLE = EXAMPLE.parent / "shadow_light_estimation.py"


def test_shadow_light_estimation_example_quick(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE.parent))
    monkeypatch.setattr(sys, "argv", [str(SHADOW_EXAMPLE), "--quick", "--out", str(tmp_path)])
    runpy.run_path(str(SHADOW_EXAMPLE), run_name="__main__")
    result = json.loads((tmp_path / "shadow_light_estimation.json").read_text())
    assert len(result["ground"]) == 4 and len(result["paper"]) == 2
    assert {r["antialias"] for r in result["ground"]} == {False, True}
    assert all(np.isfinite(r["position_error_pct"]) for r in result["ground"])


BOUNDARY_EXAMPLE = EXAMPLE.parent / "boundary_gradients.py"


def test_boundary_gradients_example_quick(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE.parent))
    monkeypatch.setattr(sys, "argv", [str(BOUNDARY_EXAMPLE), "--quick", "--out", str(tmp_path)])
    runpy.run_path(str(BOUNDARY_EXAMPLE), run_name="__main__")
    result = json.loads((tmp_path / "boundary.json").read_text())
    assert [(r["size"], r["shadows"]) for r in result["rows"]] == [(32, True), (32, False)]
    for row in result["rows"]:
        errors = [row[m] for m in ("pixel centres", "pixel pairs", "boundary integral")]
        assert all(np.isfinite(e) and e >= 0 for e in errors)
    assert "| 32 | yes |" in (tmp_path / "boundary.md").read_text()
