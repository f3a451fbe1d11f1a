"""The path integrator's example and benchmarks run end to end (--quick: tiny sizes, numbers
that are not results) and write what they say they write."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / script), *args],
        capture_output=True, text=True, timeout=300, check=False, cwd=ROOT,
    )  # fmt: skip


def test_colour_bleeding_quick(tmp_path):
    done = _run("examples/colour_bleeding.py", "--quick", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((tmp_path / "results.json").read_text())
    for run in result["runs"].values():
        assert math.isfinite(run["final_error"]) and run["final_error"] < 0.844  # it moved
    assert (tmp_path / "images.png").stat().st_size > 0
    assert (tmp_path / "error.png").stat().st_size > 0
    assert "| spp per iteration |" in (tmp_path / "results.md").read_text()


def test_bench_path_quick(tmp_path):
    done = _run("benchmarks/bench_path.py", "--quick", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((tmp_path / "bench_path.json").read_text())
    for pool in ("pool", "no_pool"):
        assert all(v > 0 for v in result["memory"][pool]["replay"].values())
        assert result["memory"][pool]["tape_mb_per_spp"] > 0
    assert result["speed"]["forward"]["us_per_sample_per_pixel"] > 0
    # --part keeps the other part's results
    done = _run("benchmarks/bench_path.py", "--quick", "--part", "speed", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr[-3000:]
    again = json.loads((tmp_path / "bench_path.json").read_text())
    assert again["memory"] == result["memory"]


def test_path_gradients_quick(tmp_path):
    done = _run("benchmarks/path_gradients.py", "--quick", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((tmp_path / "gradients.json").read_text())["rows"]
    assert {r["parameter"] for r in rows} >= {"emission", "camera_position", "sphere_centre"}
    emission = [r for r in rows if r["parameter"] == "emission"]
    for r in emission:  # no edge moves: our gradient is the same-seed difference
        assert math.isclose(r["ours"], r["fd"], rel_tol=1e-6)


def test_bench_path_mitsuba_without_mitsuba_says_so(tmp_path):
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        done = _run("benchmarks/bench_path_mitsuba.py", "--quick", "--out", str(tmp_path))
        assert done.returncode == 1
        assert "Mitsuba 3 is not installed" in done.stdout + done.stderr
    else:  # pragma: no cover - a machine with Mitsuba runs the comparison itself
        done = _run("benchmarks/bench_path_mitsuba.py", "--quick", "--out", str(tmp_path))
        assert done.returncode == 0, done.stderr[-3000:]
