"""``examples/edge_gradients.py --quick`` runs end to end and writes what it promises."""

from __future__ import annotations

import json
import runpy
import sys
from pathlib import Path

import numpy as np

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "edge_gradients.py"


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


RECONSTRUCTION = EXAMPLE.parent


def test_shape_from_views_example_quick(tmp_path, monkeypatch):
    """The teapot's run reports the handle's share of the error and writes its images."""
    script = RECONSTRUCTION / "shape_from_views.py"
    monkeypatch.syspath_prepend(str(script.parent))
    monkeypatch.setattr(sys, "argv", [str(script), "--quick", "--shape", "teapot", "--out",
                                      str(tmp_path)])  # fmt: skip
    runpy.run_path(str(script), run_name="__main__")
    (run,) = json.loads((tmp_path / "shape" / "teapot.json").read_text())["runs"]
    assert 0.0 < run["region_share_percent"] < 100.0
    assert run["chamfer_outside_region_percent"] > 0.0
    assert (tmp_path / "shape" / "teapot_2views_large_steps.png").stat().st_size > 0
    assert "handle's share" in (tmp_path / "shape" / "teapot.md").read_text()


def test_joint_reconstruction_example_quick(tmp_path, monkeypatch):
    result = run_quick(RECONSTRUCTION / "joint_reconstruction.py", tmp_path, monkeypatch,
                       "joint/joint.json")  # fmt: skip
    (run,) = result["runs"]
    assert run["final_loss"] < run["initial_loss"]
    assert (tmp_path / "joint" / f"joint_{run['views']}views.png").stat().st_size > 0
