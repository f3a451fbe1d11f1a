"""Every JSON file the project writes parses with a strict parser (no NaN / Infinity). (The
reproduction script's own results.json is checked where the script runs end to end:
tests/render/inverse/test_inverse_rendering.py.)"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from render.inverse.jsonio import to_json, write_json
from tests.render_helpers import strict_load

ROOT = Path(__file__).resolve().parents[1]


def test_non_finite_values_become_null():
    value = {"a": float("nan"), "b": [np.float32("inf"), -np.inf, 1.5], "c": np.arange(2)}
    assert strict_load(to_json(value)) == {"a": None, "b": [None, None, 1.5], "c": [0, 1]}


def test_plain_python_nan_would_not_parse_strictly():
    """The check itself can fail: Python's own json writes NaN."""
    with pytest.raises(ValueError, match="non-standard"):
        strict_load(json.dumps({"a": float("nan")}))


def test_unknown_objects_are_refused():
    with pytest.raises(TypeError):
        to_json({"a": object()})


@pytest.mark.parametrize("path", sorted(ROOT.glob("docs/**/*.json")), ids=lambda p: p.name)
def test_committed_json_files_are_strict(path):
    strict_load(path.read_text(encoding="utf-8"))


def test_benchmark_json_is_strict(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import timing
    finally:
        sys.path.pop(0)
    path = timing.write_json(tmp_path, "x", {"never": float("nan"), "ms": np.float64(1.0)})
    assert strict_load(path.read_text())["never"] is None
    write_json(tmp_path / "y.json", [np.nan])
    assert strict_load((tmp_path / "y.json").read_text()) == [None]
