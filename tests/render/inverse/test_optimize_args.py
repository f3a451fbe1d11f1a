"""``render.optimize`` and minidiff's optimisers refuse what cannot work, and keep the
history of a run that failed."""

from __future__ import annotations

import numpy as np
import pytest

import minidiff as md
import render


def small_problem():
    scene = render.paper_scene(24, 24)
    target = render.render(scene).data.copy()
    light = scene.lights[0]
    light.position = md.tensor([2.5, 5.0, 3.0], requires_grad=True)
    return scene, light.position, target


def test_target_given_as_a_file_name_is_loaded(tmp_path):
    scene, position, target = small_problem()
    path = render.save_image(np.clip(target, 0, 1), tmp_path / "target.png")
    _, history = render.optimize(scene, [position], str(path), lr=0.05, max_iters=2, quiet=True)
    assert history.iterations == 2


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        ({"lr": "0.1"}, TypeError, "lr"),
        ({"project": 3}, TypeError, "project must be a callable"),
        ({"project": [None, 5]}, ValueError, "2 projections for 1 params"),
        # Fails in the first step: optimize wraps it, history attached.
        ({"project": lambda x: 0.0}, render.OptimizationError, r"project\[0\] must return"),
    ],
)
def test_bad_optimiser_arguments(kwargs, error, message):
    scene, position, target = small_problem()
    with pytest.raises(error, match=message):
        render.optimize(scene, [position], target, max_iters=2, quiet=True, **kwargs)


def test_a_tensor_that_is_not_in_the_scene_is_refused():
    scene, _, target = small_problem()
    stray = md.tensor([1.0, 2.0, 3.0], requires_grad=True)
    with pytest.raises(ValueError, match=r"params\[0\] .* is not a parameter of the scene"):
        render.optimize(scene, [stray], target, max_iters=2, quiet=True)


def test_a_nan_gradient_stops_with_the_history_kept():
    scene, position, target = small_problem()
    calls = {"n": 0}

    def loss_fn(image, target):
        calls["n"] += 1
        loss = render.mse(image, target)
        return loss * float("nan") if calls["n"] == 3 else loss  # NaN at iteration 2

    with pytest.raises(render.OptimizationError, match="iteration 2") as caught:
        render.optimize(scene, [position], target, loss_fn=loss_fn, max_iters=10, quiet=True)
    history = caught.value.history
    assert history.iterations == 2 and len(history.loss) == 3
    assert np.isnan(history.loss[-1])


def test_an_integer_target_is_refused_with_its_dtype_named():
    """An 8-bit image compared as it is with a rendering in [0, 1] would be 255 times too
    bright (it was used unscaled): refused, with the way out named."""
    scene = render.paper_scene(width=8, height=8)
    light = scene.lights[0].position
    light.requires_grad = True
    for dtype in (np.uint8, np.uint16, np.int64, bool):
        with pytest.raises(TypeError, match=f"integer pixels \\({np.dtype(dtype)}\\)"):
            render.optimize(scene, [light], np.zeros((8, 8, 3), dtype), max_iters=1)
    _, history = render.optimize(scene, [light], np.zeros((8, 8, 3), np.float32), max_iters=1)
    assert history.iterations == 1


def test_a_callback_that_makes_a_parameter_nan_keeps_the_history():
    """The next render refuses the NaN parameter: that failure, like a NaN gradient, is an
    OptimizationError carrying the iterations made so far."""
    scene, position, target = small_problem()

    def poison(it, loss, image, history):
        if it == 1:
            position.data[0] = np.nan

    with pytest.raises(render.OptimizationError, match="iteration 2") as caught:
        render.optimize(scene, [position], target, lr=0.05, max_iters=5, callback=poison)
    assert caught.value.history.iterations == 2 and len(caught.value.history.loss) == 2
