"""The path integrator's example and benchmarks run end to end (--quick: tiny sizes, numbers
that are not results) and write what they say they write. Run in this process (their
``main(argv)``), so that they reuse its compiled kernels."""

from __future__ import annotations

import importlib.util
import json
import math

import pytest


def test_colour_bleeding_quick(tmp_path, load_script):
    load_script("examples/colour_bleeding.py").main(["--quick", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "results.json").read_text())
    for run in result["runs"].values():
        assert math.isfinite(run["final_error"]) and run["final_error"] < 0.844  # it moved
    assert (tmp_path / "images.png").stat().st_size > 0
    assert (tmp_path / "error.png").stat().st_size > 0
    assert "| spp per iteration |" in (tmp_path / "results.md").read_text()


def test_bench_path_quick(tmp_path, load_script):
    bench = load_script("benchmarks/bench_path.py")
    bench.main(["--quick", "--part", "memory", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "bench_path.json").read_text())
    for pool in ("pool", "no_pool"):
        assert all(v > 0 for v in result["memory"][pool]["replay"].values())
        assert result["memory"][pool]["tape_mb_per_spp"] > 0
    bench.main(["--quick", "--part", "speed", "--out", str(tmp_path)])  # keeps the memory
    again = json.loads((tmp_path / "bench_path.json").read_text())
    assert again["memory"] == result["memory"]
    assert again["speed"]["forward"]["us_per_sample_per_pixel"] > 0


def test_bench_path_rays_quick(tmp_path, load_script):
    """The rays/rest split: the recorded rays are the kernel's (NEE's only where it traces
    one), so there are at least one camera ray and at most 1 + 2 (max_depth - 1) a sample."""
    load_script("benchmarks/bench_path_rays.py").main(["--quick", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "path_rays.json").read_text())["rows"]
    assert rows and all(row["all_ms"] > 0 and row["rays_ms"] > 0 for row in rows)
    assert all(1.0 <= row["rays_per_sample"] <= 1 + 2 * (row["max_depth"] - 1) for row in rows)


def test_path_gradients_quick(tmp_path, load_script):
    load_script("benchmarks/path_gradients.py").main(["--quick", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "gradients.json").read_text())["rows"]
    assert {r["parameter"] for r in rows} >= {"emission", "camera_position", "sphere_centre"}
    emission = [r for r in rows if r["parameter"] == "emission"]
    for r in emission:  # no edge moves: our gradient is the same-seed difference
        assert math.isclose(r["ours"], r["fd"], rel_tol=1e-6)


def test_bench_path_mitsuba_without_mitsuba_says_so(tmp_path, capsys, load_script):
    if importlib.util.find_spec("mitsuba") is not None:
        pytest.skip("Mitsuba is installed here: the comparison runs as a benchmark instead")
    bench = load_script("benchmarks/bench_path_mitsuba.py")
    with pytest.raises(SystemExit) as stop:
        bench.main(["--quick", "--out", str(tmp_path)])
    message = str(stop.value.code) + capsys.readouterr().err
    assert "Mitsuba 3 is not installed" in message


def test_bench_secondary_quick(tmp_path, load_script):
    load_script("benchmarks/bench_secondary.py").main(["--quick", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "cost.json").read_text())
    for row in result["cost"]:
        assert row["secondary"] > 0 and row["plain"] > 0 and row["term_over_plain"] > -1
    assert result["variance"]["std"] >= 0


def test_bench_path_compile_quick(tmp_path, load_script):
    load_script("benchmarks/bench_path_compile.py").main(["--quick", "--out", str(tmp_path)])
    data = json.loads((tmp_path / "bench_path_compile.json").read_text())
    assert data["runs"][0]["max_depth"] == 2 and data["runs"][0]["first_s"] > 0
    assert [row["extra_vertices"] for row in data["longer_mesh"]] == [1, 2, 3]
    assert all(row["first_s"] > 0 and row["second_s"] > 0 for row in data["longer_mesh"])


def test_bench_path_kinds_quick(tmp_path, load_script):
    load_script("benchmarks/bench_path_kinds.py").main(["--quick", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "kinds.json").read_text())
    for row in result["cost"]:
        assert row["over_albedo"]["albedo"] == 1.0 and row["light_position"] > 0


def test_path_secondary_quick(tmp_path, load_script):
    load_script("benchmarks/path_secondary.py").main(["--quick", "--out", str(tmp_path)])
    text = (tmp_path / "secondary.md").read_text()
    assert "A --quick smoke run" in text and "| light_position" in text
