"""Smoke test of the benchmark suite: every script runs in --quick mode (tiny sizes, few
repeats) and writes a JSON with the expected keys holding finite positive numbers, a report
section and its plots. No timing is asserted (the machine is shared and noisy).

Each script's ``main(argv)`` runs in this process, reusing its compiled kernels (a new
Python process costs ~1.5 s to start, import and load Numba's cache); ``run_all.py``, which
runs the scripts in new processes with OMP_WAIT_POLICY=passive, is tested that way once.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

# Starts new Python processes (run_all; some scripts time settings in new processes):
# runs after the in-process tests (tests/conftest.py).
pytestmark = pytest.mark.new_processes

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"

# Per script: key paths (tuples; "*" = every element of a list) that must be finite and > 0.
EXPECTED = {
    "bench_visibility": [
        ("teapot_1536", "build", "median_ms"),
        ("teapot_1536", "closest_hit", "median_ms"),
        ("teapot_1536", "occluded", "median_ms"),
        ("teapot_1536", "brute", "closest_hit_ms"),
        ("teapot_fine", "closest_hit", "median_ms"),
    ],
    "bench_minidiff": [
        (variant, dtype, key, "median_ms")
        for variant in ("default", "keep_freed")
        for dtype in ("float64", "float32")
        for key in ("numpy_forward", "minidiff_forward", "minidiff_forward_backward")
    ]
    + [
        (variant, dtype, key)
        for variant in ("default", "keep_freed")
        for dtype in ("float64", "float32")
        for key in ("ratio_forward", "ratio_forward_backward")
    ],
    "bench_dispatch": [
        ("run_jobs", "1_jobs_us"),
        ("run_jobs", "2_jobs_us"),
        ("level_set", "*", "forward_1_us"),
        ("level_set", "*", "forward_backward_2_us"),
        ("fresh_memory", "pool_job_0_ms"),
        ("fresh_memory", "fresh_job_0_ms"),
    ],
    "bench_compiler": [
        ("results", route, "median_ms") for route in ("tape", "compiled_1", "compiled_2")
    ]
    + [("speedup_1_thread",), ("threads_gain",), ("compile_s",), ("fetch_s",), ("peak_mb_tape",)],
    "bench_render": [
        ("visibility", "build", "median_ms"),
        ("forward", "median_ms"),
        ("forward_backward", "median_ms"),
        ("forward_no_bvh", "median_ms"),
        ("ratio_forward_backward_to_forward",),
        ("memory_forward_backward", "tracemalloc_peak_mb"),
        ("memory_forward", "rss_peak_mb"),
        ("material_iteration_reuse", "median_ms"),
        ("iterations", "camera_boundary", "median_ms"),
        ("iterations", "shape_plain", "median_ms"),
        ("iterations", "ratio_shape"),
        ("gradient_image", "plain", "forward", "median_ms"),
        ("gradient_image", "antialias", "vertices_x", "median_ms"),
        ("gradient_image", "plain", "ratio_light_x"),
        ("gradient_image", "antialias", "ratio_camera_x"),
    ],
    "bench_mitsuba": [  # ours only: Mitsuba is optional
        ("results", name, "ours", "median_ms")
        for name in ("forward", "light_iteration", "shape_iteration")
    ],
    "bench_speed": [  # ours on 1 and 2 threads (no baseline; Mitsuba only if installed)
        ("results", name, f"ours_{threads}", "median_ms")
        for name in ("forward", "fb_plain")
        for threads in (1, 2)
    ]
    + [("ratios", "threads_forward"), ("ratios", "threads_plain")],
    "fig2_bvh": [
        ("resolution", "*", "bvh", "time", "median_ms"),
        ("resolution", "*", "no_bvh", "time", "median_ms"),
        ("resolution", "*", "bvh", "memory", "rss_peak_mb"),
        ("triangles", "*", "bvh_render", "time", "median_ms"),
        ("triangles", "*", "brute_render_estimate_ms"),
    ],
    "fig3_ad_vs_fd": [
        ("series", "*", "ad", "median_ms"),
        ("series", "*", "fd_ms"),
        ("crossover_parameters",),
        ("accuracy", "ad_error"),
        ("accuracy", "fd_error"),
        ("at_full_size", "fd_ms_per_parameter"),
    ],
    "table2_ablation": [
        ("runs", name, "seconds_for_500")
        for name in ("AD + BVH", "AD, no BVH", "FD + BVH", "FD, no BVH")
    ]
    + [("runs", "AD + BVH", "position_errors", "*")],
    "mesh_files": [("cases", name, "*", "truth_error") for name in ("tree", "teapot", "sign")],
    "mixed_pixels": [
        ("paper", "plain", "candidates"),
        ("paper", "ground", "kept"),
        ("views_total", "mixed_kept"),
        ("time", "boundary"),
        ("time", "search_without_test"),
    ],
    "boundary_budget": [
        ("rays", "hits"),
        ("rays", "candidates"),
        ("rays", "interior_hits"),
        ("time", "fb_boundary_2", "median_ms"),
        ("time", "points_1", "median_ms"),
        ("profiled_ms", "mixed_pixels", "ray_kernels"),
        ("ratios", "threads_boundary"),
    ],
    "moving_curves": [
        ("choices", name, key)
        for name in ("light_position", "albedo", "vertices", "every_parameter")
        for key in ("boundary", "every_kind", "boundary_over_plain")
    ]
    + [("fits", name, "boundary_over_plain") for name in ("albedo", "light_position")],
    "scaling": [
        ("pixels", "*", "forward", "median_ms"),
        ("pixels", "*", "forward_backward", "median_ms"),
        ("pixels", "*", "memory_forward_backward", "tracemalloc_peak_mb"),
        ("triangles", "*", "forward_backward", "median_ms"),
    ],
}


def _values(data, path):
    """All values at ``path`` ("*" expands lists)."""
    if not path:
        return [data]
    head, rest = path[0], path[1:]
    if head == "*":
        assert isinstance(data, list) and data, f"expected a non-empty list at {path}"
        return [v for item in data for v in _values(item, rest)]
    assert head in data, f"missing key {head!r}"
    return _values(data[head], rest)


def _run_in_a_new_process(args, out: Path) -> None:
    env = dict(os.environ, OMP_WAIT_POLICY="passive")
    proc = subprocess.run(
        [sys.executable, *args, "--quick", "--out", str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]


@pytest.mark.parametrize("name", list(EXPECTED))
def test_script_quick(name, tmp_path, load_script):
    load_script(f"benchmarks/{name}.py").main(["--quick", "--out", str(tmp_path)])
    data = json.loads((tmp_path / f"{name}.json").read_text(encoding="utf-8"))
    for path in EXPECTED[name]:
        for value in _values(data, path):
            assert isinstance(value, int | float) and math.isfinite(value) and value > 0, (
                f"{name}: {path} = {value!r}"
            )
    section = data["report"]
    assert section["title"] and section["rows"]
    for row in section["rows"]:
        assert set(row) == {"quantity", "ours", "reference", "status"}
        assert row["status"] in ("", "met", "not met", "met (stretch met)", "not measured")
        if row["status"] == "not measured":  # Mitsuba's half; bench_speed's quick subset
            assert name == "bench_speed" or (
                name == "bench_mitsuba" and importlib.util.find_spec("mitsuba") is None
            )
    for plot in section["plots"]:
        assert (tmp_path / plot).stat().st_size > 0
    assert data["machine"]["usable_cores"] >= 1
    if name == "bench_minidiff":  # each allocator setting reached its worker processes
        for dtype in ("float64", "float32"):
            assert data["keep_freed"][dtype]["keep_freed_memory"]
            assert not data["default"][dtype]["keep_freed_memory"]


def test_run_all_writes_report(tmp_path):
    _run_in_a_new_process([str(BENCH / "run_all.py"), "--only", "bench_visibility"], tmp_path)
    report = (tmp_path / "report.md").read_text(encoding="utf-8")
    assert "# Benchmark report" in report
    assert "Visibility only" in report
    assert "| quantity | ours | paper / target | status |" in report


def _timing(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    import timing

    return timing


def test_variants_are_timed_in_turns(monkeypatch):
    """measure_interleaved: the warm-up calls, then blocks of calls of each variant in
    turns, until each has its repeats (rounded up to whole blocks)."""
    timing = _timing(monkeypatch)
    calls = []
    fns = {name: (lambda name=name: calls.append(name)) for name in ("a", "b")}
    result = timing.measure_interleaved(fns, repeats=3, warmup=1, block=2)
    assert calls == ["a", "b"] + ["a", "a", "b", "b"] * 2
    assert result["a"]["repeats"] == result["b"]["repeats"] == 4
    assert result["a"]["min_ms"] <= result["a"]["median_ms"] <= result["a"]["max_ms"]


def test_fresh_process_environment(monkeypatch):
    """in_fresh_process sets the variables asked for and removes those mapped to None, even
    when this process has them."""
    timing = _timing(monkeypatch)
    for name, value in timing.KEEP_FREED_MEMORY.items():
        monkeypatch.setenv(name, value)
    unset = dict.fromkeys(timing.KEEP_FREED_MEMORY)
    assert timing.in_fresh_process(timing.allocator_setting, unset)["keep_freed_memory"] is False
    for name in timing.KEEP_FREED_MEMORY:
        monkeypatch.delenv(name)
    kept = timing.in_fresh_process(timing.allocator_setting, timing.KEEP_FREED_MEMORY)
    assert kept["keep_freed_memory"] is True


def test_brute_force_on_a_subsample_of_rays_matches_the_bvh(monkeypatch):
    """fig2_bvh times brute force on every n-th ray: each ray keeps its own shadow limit."""
    monkeypatch.syspath_prepend(str(BENCH))
    import bench_visibility

    w = bench_visibility.visibility_workload(24)
    result = bench_visibility.time_brute_visibility(w, 1, stride=3, warmup=0)
    assert result["extrapolated"] and result["identical_to_bvh"]
