"""The soft-shadow example (``examples/soft_shadow_light.py``): its camera never sees the
light wherever the optimiser may put it, and its --quick run (a smoke run, numbers that are
not results) writes what it says it writes. Run in this process (``main(argv)``), so that
it reuses the compiled kernels."""

from __future__ import annotations

import itertools
import math

import numpy as np

from render.path import render_path
from render.scene.cornell import cornell_box
from tests.render_helpers import strict_load


def emitters_seen(scene) -> float:
    """The largest pixel value of the emitters the camera sees directly (max_depth 1)."""
    return float(render_path(scene, spp=4, max_depth=1, seed=3).data.max())


def test_the_light_is_never_in_view(load_script):
    """At every corner of the optimiser's box of translations, at the largest scale, and
    at the start, the camera sees no emitter; the room's own camera (the check itself) does."""
    script = load_script("examples/soft_shadow_light.py")
    assert emitters_seen(cornell_box(16, 16)) > 1.0
    corners = itertools.product(*zip(script.LOWEST, script.HIGHEST, strict=True))
    placements = [(c, script.LARGEST) for c in corners]
    placements.append((script.START_TRANSLATION, script.START_SCALE))
    for translation, scale in placements:
        scene = script.shadow_scene(16)
        transform = scene.objects[script.LIGHT].transform
        transform.translation.data, transform.scale.data = np.array(translation), np.array(scale)
        assert emitters_seen(scene) == 0.0, (translation, scale)


def test_soft_shadow_light_quick(tmp_path, load_script):
    script = load_script("examples/soft_shadow_light.py")
    script.main(["--quick", "--compare", "none", "--out", str(tmp_path)])
    result = strict_load((tmp_path / "result.json").read_text())
    steps = result["settings"]["steps"]
    for run in (result, result["comparison"]):
        translation, scale = np.array(run["translation"]), np.array(run["scale"])
        assert translation.shape == (steps + 1, 3) and scale.shape == (steps + 1,)
        assert np.array_equal(translation[0], script.START_TRANSLATION)
        assert np.all(translation >= script.LOWEST) and np.all(translation <= script.HIGHEST)
        assert math.isclose(run["position_error"][0], 0.3 * math.sqrt(2.0))
        assert math.isclose(run["size_error"][0], 0.3)
        assert run["size_error"][-1] < 0.3  # the start's light is too large: it shrank
        assert len(run["loss"]) == len(run["seconds"]["per_step"]) == steps
    assert result["antialias"] == "boundary" and result["comparison"]["antialias"] == "none"
    assert (tmp_path / "soft_shadow.png").stat().st_size > 0


def test_settled_below_is_the_step_from_which_the_error_stays_below(load_script):
    settled_below = load_script("examples/soft_shadow_light.py").settled_below
    assert settled_below(np.array([0.5, 0.01, 0.03, 0.01, 0.005]), 0.02) == 3
    assert settled_below(np.array([0.01, 0.01]), 0.02) == 0
    assert settled_below(np.array([0.5, 0.01, 0.03]), 0.02) is None
