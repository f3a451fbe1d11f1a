"""The soft-shadow example (``examples/soft_shadow_light.py``): in both scenes its camera
never sees the light wherever the optimiser may put it (nor, in the open scene, the
occluders); the open scene's floor barely tells the light's size when the power is held;
and its --quick run (a smoke run, numbers that are not results) writes what it says it
writes. Run in this process (``main(argv)``), so that it reuses the compiled kernels."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from render.path import render_path
from render.scene.cornell import cornell_box
from tests.render_helpers import strict_load

SCRIPT = "examples/soft_shadow_light.py"


def emitters_seen(scene) -> float:
    """The largest pixel value of the emitters the camera sees directly (max_depth 1)."""
    return float(render_path(scene, spp=4, max_depth=1, seed=3).data.max())


def placed(script, name: str, translation, scale: float):
    """The scene ``name`` at 16x16 with its light moved by ``translation`` and scaled by
    ``scale`` (its power held where the scene holds it)."""
    setup = script.SCENES[name]
    scene = setup.build(16)
    transform = scene.objects[setup.light].transform
    transform.translation.data, transform.scale.data = np.array(translation), np.array(scale)
    script.hold_power(setup, scene)
    return scene


@pytest.mark.parametrize("name", ["open", "cornell"])
def test_the_light_is_never_in_view(load_script, name):
    """At every corner of the optimiser's box of translations, at the largest scale, and
    at the start, the camera sees no emitter; the room's own camera (the check itself) does."""
    script = load_script(SCRIPT)
    setup = script.SCENES[name]
    assert emitters_seen(cornell_box(16, 16)) > 1.0
    corners = itertools.product(*zip(setup.lowest, setup.highest, strict=True))
    placements = [(c, script.LARGEST) for c in corners]
    placements.append((script.START_TRANSLATION, script.START_SCALE))
    for translation, scale in placements:
        scene = placed(script, name, translation, scale)
        assert emitters_seen(scene) == 0.0, (translation, scale)


def test_the_open_scene_shows_the_floor_alone(load_script):
    """The open scene's occluders, made to glow, are not seen either: the image is the
    floor (and its shadows)."""
    script = load_script(SCRIPT)
    scene = script.open_scene(16)
    for occluder in scene.objects[2:]:
        occluder.material.emission.data = np.ones(3)
    assert emitters_seen(scene) == 0.0


def test_the_open_floor_barely_tells_the_size_when_the_power_is_held(load_script):
    """Without occluders, the open scene's floor (same seed) at the start's scale differs
    from the floor at the true scale by < 1 % where the power is held, and by the area
    ratio 1.3^2 where the radiance is."""
    script = load_script(SCRIPT)
    setup = script.SCENES["open"]
    images = {}
    for scale, hold in ((1.0, True), (script.START_SCALE, True), (script.START_SCALE, False)):
        scene = placed(script, "open", (0.0, 0.0, 0.0), scale)
        if not hold:
            scene.objects[setup.light].material.emission.data = np.array(setup.radiance)
        del scene.objects[2:]
        images[scale, hold] = render_path(scene, spp=16, max_depth=2, seed=5).data
    true = images[1.0, True]
    held = images[script.START_SCALE, True]
    assert np.abs(held.mean() / true.mean() - 1.0) < 0.01
    kept = images[script.START_SCALE, False].mean() / held.mean()
    assert math.isclose(kept, script.START_SCALE**2, rel_tol=1e-6)


@pytest.mark.parametrize(("name", "compare"), [("open", ["--compare", "none"]), ("cornell", [])])
def test_soft_shadow_light_quick(tmp_path, load_script, name, compare):
    script = load_script(SCRIPT)
    script.main(["--quick", "--scene", name, *compare, "--out", str(tmp_path)])
    result = strict_load((tmp_path / "result.json").read_text())
    setup, steps = script.SCENES[name], result["settings"]["steps"]
    assert result["settings"]["scene"] == name
    assert result["settings"]["max_depth"] == setup.max_depth
    for run in [result] + ([result["comparison"]] if compare else []):
        translation, scale = np.array(run["translation"]), np.array(run["scale"])
        assert translation.shape == (steps + 1, 3) and scale.shape == (steps + 1,)
        assert np.array_equal(translation[0], script.START_TRANSLATION)
        assert np.all(translation >= setup.lowest) and np.all(translation <= setup.highest)
        start = np.linalg.norm(script.START_TRANSLATION) / setup.unit
        assert math.isclose(run["position_error"][0], start)
        assert math.isclose(run["size_error"][0], 0.3)
        assert len(run["loss"]) == len(run["seconds"]["per_step"]) == steps
    assert result["antialias"] == "boundary"
    assert not compare or result["comparison"]["antialias"] == "none"
    assert (tmp_path / "soft_shadow.png").stat().st_size > 0


def test_settled_below_is_the_step_from_which_the_error_stays_below(load_script):
    settled_below = load_script(SCRIPT).settled_below
    assert settled_below(np.array([0.5, 0.01, 0.03, 0.01, 0.005]), 0.02) == 3
    assert settled_below(np.array([0.01, 0.01]), 0.02) == 0
    assert settled_below(np.array([0.5, 0.01, 0.03]), 0.02) is None
