"""Many views in one problem: ``render.optimize`` over (scene, target) pairs sharing
parameters, all views or a random batch per step, rendered in one thread or several, and
``gradient_image`` over views."""

from __future__ import annotations

import numpy as np
import pytest

import minidiff as md
import render

SIZE = 20


def two_views():
    """The paper scene seen by two cameras; the teapot placed by a Transform whose
    translation is off by (0.3, -0.2, 0.2); targets rendered at the true pose."""
    scene = render.paper_scene(SIZE, SIZE)
    teapot = scene.objects[0]
    teapot.transform = render.Transform(pivot=teapot.vertices.data.mean(0))
    side = render.Camera((6.0, 3.0, 1.0), (0.0, 1.0, 0.0), width=SIZE, height=SIZE)
    views = [scene, scene.with_camera(side)]
    targets = [render.render(v).data.copy() for v in views]
    teapot.transform.translation = md.tensor([0.3, -0.2, 0.2], requires_grad=True)
    return views, targets, teapot.transform.translation


def test_views_share_the_parameters():
    views, _, translation = two_views()
    assert views[1].objects[0] is views[0].objects[0]
    assert views[1].camera is not views[0].camera
    for view in views:
        assert any(t is translation for t in view.parameters())


def test_the_loss_is_the_mean_over_views_and_its_gradient_too():
    views, targets, translation = two_views()
    grads, losses = [], []
    for view, target in zip(views, targets, strict=True):
        translation.grad = None
        loss = render.image_loss(render.render(view), target)
        loss.backward()
        grads.append(translation.grad.copy())
        losses.append(loss.item())
    seen = {}

    def record(it, loss, images, history):
        seen["loss"], seen["grad"], seen["images"] = loss, translation.grad, images
        return True

    translation.grad = None
    render.optimize(list(zip(views, targets, strict=True)), [translation], max_iters=3,
                    quiet=True, callback=record)  # fmt: skip
    assert seen["loss"] == pytest.approx(np.mean(losses), rel=1e-12)
    assert np.allclose(seen["grad"], np.mean(grads, axis=0), rtol=1e-12, atol=0)
    assert [image.shape for image in seen["images"]] == [(SIZE, SIZE, 3)] * 2


def test_two_views_recover_the_translation():
    views, targets, translation = two_views()
    pairs = list(zip(views, targets, strict=True))
    edges = {"antialias": True}  # a plain render has no gradient where the silhouette moves
    _, history = render.optimize(pairs, [translation], lr=0.03, max_iters=40, quiet=True,
                                 render_kwargs=edges)  # fmt: skip
    assert history.loss[-1] < 0.25 * history.loss[0]  # measured: 0.14
    assert np.linalg.norm(translation.data) < 0.2 * np.linalg.norm([0.3, -0.2, 0.2])  # 0.08
    assert history.views == [[0, 1]] * len(history.loss)


def test_batches_are_drawn_from_the_seed_and_threads_change_nothing():
    runs = []
    for jobs in (1, 2, 1):
        views, targets, translation = two_views()
        pairs = list(zip(views, targets, strict=True)) * 2  # four views, two distinct
        seed = 7 if len(runs) < 2 else 8
        _, history = render.optimize(pairs, [translation], lr=0.02, max_iters=6, quiet=True,
                                     batch=2, seed=seed, jobs=jobs)  # fmt: skip
        runs.append(history)
    assert all(len(v) == 2 and len(set(v)) == 2 for v in runs[0].views)
    assert runs[0].views == runs[1].views and runs[0].loss == runs[1].loss  # bit for bit
    assert runs[2].views != runs[0].views  # another seed, other batches


@pytest.mark.parametrize(
    "change, error, message",
    [
        (lambda p: [(p[0][0], p[0][1][:-1]), p[1]], ValueError,
         r"views\[0\] target has shape \(19, 20, 3\) but its scene renders \(20, 20, 3\)"),
        (lambda p: [p[0], (p[1][0],)], TypeError, r"views\[1\] must be a \(render.Scene, target\)"),
        (lambda p: [p[0], (p[1][0], np.full((SIZE, SIZE, 3), np.nan))], ValueError,
         r"views\[1\] target contains NaN"),
        (lambda p: [], ValueError, "the list of views is empty"),
    ],
)  # fmt: skip
def test_bad_views_are_named(change, error, message):
    views, targets, translation = two_views()
    pairs = change(list(zip(views, targets, strict=True)))
    with pytest.raises(error, match=message):
        render.optimize(pairs, [translation], max_iters=1, quiet=True)


@pytest.mark.parametrize(
    "kwargs, message",
    [({"batch": 3}, r"batch must be an int in \[1, 2\]"), ({"batch": 0}, "batch must be"),
     ({"jobs": 0}, "jobs must be an int >= 1"), ({"jobs": 1.5}, "jobs must be")],
)  # fmt: skip
def test_bad_batch_and_jobs_are_named(kwargs, message):
    views, targets, translation = two_views()
    with pytest.raises(ValueError, match=message):
        render.optimize(list(zip(views, targets, strict=True)), [translation], max_iters=1,
                        quiet=True, **kwargs)  # fmt: skip


def test_a_target_beside_a_list_of_views_is_refused():
    views, targets, translation = two_views()
    with pytest.raises(TypeError, match="leave target out"):
        render.optimize(list(zip(views, targets, strict=True)), [translation], targets[0])


def test_gradient_image_over_views():
    views, _, translation = two_views()
    images = render.gradient_image(views, "objects[0].transform.translation", (1.0, 0.0, 0.0))
    alone = [render.gradient_image(v, translation, (1.0, 0.0, 0.0)) for v in views]
    assert len(images) == 2
    for image, expected in zip(images, alone, strict=True):
        assert np.array_equal(image, expected) and np.abs(image).max() > 0
