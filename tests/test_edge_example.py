"""``examples/edge_gradients.py --quick`` runs end to end and writes what it promises."""

from __future__ import annotations

import json
import runpy
import sys
from pathlib import Path

import numpy as np

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "edge_gradients.py"


def run_quick(script: Path, tmp_path: Path, monkeypatch, result: str) -> dict:
    """Run ``script --quick --out tmp_path`` as ``python examples/...`` would; its JSON."""
    monkeypatch.syspath_prepend(str(script.parent))
    monkeypatch.setattr(sys, "argv", [str(script), "--quick", "--out", str(tmp_path)])
    runpy.run_path(str(script), run_name="__main__")
    return json.loads((tmp_path / result).read_text())


def test_edge_gradients_example_quick(tmp_path, monkeypatch):
    result = run_quick(EXAMPLE, tmp_path, monkeypatch, "edge_gradients.json")
    assert len(result["calibration"]) == 2
    assert set(result["basin"]) == {"pixel centres", "edges"}
    assert all(0.0 <= c["fraction"] <= 1.0 for c in result["coverage_30deg"])
    for name in ("basin.png", "silhouette_zoom.png", "edge_gradients.md"):
        assert (tmp_path / name).stat().st_size > 0


SHADOW_EXAMPLE = EXAMPLE.parent / "shadow_light_estimation.py"


def test_shadow_light_estimation_example_quick(tmp_path, monkeypatch):
    result = run_quick(SHADOW_EXAMPLE, tmp_path, monkeypatch, "shadow_light_estimation.json")
    assert len(result["ground"]) == 4 and len(result["paper"]) == 2
    assert {r["antialias"] for r in result["ground"]} == {False, True}
    assert all(np.isfinite(r["position_error_pct"]) for r in result["ground"])


BOUNDARY_EXAMPLE = EXAMPLE.parent / "boundary_gradients.py"


def test_boundary_gradients_example_quick(tmp_path, monkeypatch):
    result = run_quick(BOUNDARY_EXAMPLE, tmp_path, monkeypatch, "boundary.json")
    rows = result["teapot translation"]
    assert [(r["size"], r["shadows"]) for r in rows] == [(24, True)]
    assert [r["parameter"] for r in result["parameters"]] == ["field of view", "sphere radius"]
    for row in rows + result["parameters"]:
        errors = [row[m] for m in ("pixel centres", "pixel pairs", "boundary integral")]
        assert all(np.isfinite(e) and e >= 0 for e in errors)
    report = (tmp_path / "boundary.md").read_text()
    assert "| 24 | yes |" in report and "| sphere radius |" in report
