"""The paper reproduction's first line and its --quick summary (issue 41, "Any machine").

``examples/reproduce_paper.py`` prints what it is about to compile, and about how long that
takes, before it imports the renderer (whose imports alone take seconds on a loaded machine)
or Numba; the cache check behind that line finds Numba's cache where Numba puts it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numba
import pytest
from numba.core import caching

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.new_processes
def test_the_notice_comes_before_the_renderer_is_imported():
    """The script module, its helpers and the notice import neither the renderer nor Numba
    (a fresh interpreter: this one has imported both)."""
    code = (
        "import sys; sys.path.insert(0, 'examples')\n"
        "import reproduce_paper, script_support\n"
        "print(script_support.kernel_notice('boundary'))\n"
        "print(script_support.kernel_notice(True))\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('render', 'numba')))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    boundary, pairs, modules = done.stdout.splitlines()
    assert modules == "[]"
    assert "boundary-integral edges" in boundary and "boundary" not in pairs
    for line in (boundary, pairs):
        assert "Compiling the renderer's Numba kernels" in line or "no compiling" in line


@pytest.mark.parametrize("cache_dir", ["", "numba_cache"])
def test_the_cache_folder_is_numbas(cache_dir, load_script, monkeypatch, tmp_path):
    """``numba_cache_folder`` names the folder Numba's own locator picks for a kernel's
    source file, with and without NUMBA_CACHE_DIR."""
    support = load_script("examples/script_support.py")
    source = ROOT / "render" / "trace" / "intersect.py"
    from render.trace.intersect import closest_hit_bvh

    root = str(tmp_path / cache_dir) if cache_dir else ""
    monkeypatch.setenv("NUMBA_CACHE_DIR", root)
    monkeypatch.setattr(numba.config, "CACHE_DIR", root)
    name = "UserProvidedCacheLocator" if cache_dir else "InTreeCacheLocator"
    locator = getattr(caching, name, None) or getattr(caching, "_" + name)  # older Numba: _name
    expected = locator(closest_hit_bvh.py_func, str(source)).get_cache_path()
    assert support.numba_cache_folder(source) == Path(expected)
    if cache_dir:  # an empty cache: nothing is cached
        assert not support.kernels_cached({"render.trace.intersect": "closest_hit_bvh"})


def test_the_smoke_lines_say_which_rows_end_below_their_start(load_script):
    script = load_script("examples/reproduce_paper.py")
    results = {
        "camera_calibration": [
            {"initial_position_error_pct": 11.5, "final_position_error_pct": 0.4},
            {"initial_position_error_pct": 11.5, "final_position_error_pct": 0.5},
        ],
        "material_recovery": [
            {"initial_rgb_error": 0.4, "final_rgb_error": 0.002},
            {"initial_rgb_error": 0.5, "final_rgb_error": 0.6},
        ],
    }
    camera, material = script.smoke_lines(results)
    assert camera == (
        "- camera_calibration position_error_pct: 11.5 -> 0.4, 11.5 -> 0.5: lower on every seed"
    )
    assert material.endswith("0.5 -> 0.6: NOT lower on every seed")
