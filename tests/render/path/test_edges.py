"""Primary visibility's boundary term in the path integrator (``render.path.boundary.primary``): its
jumps against the direct renderer's where both are exact, the camera's gradient against
central differences of high-spp renders, replay against the tape, bad input."""

from __future__ import annotations

import numpy as np
import pytest

import minidiff as md
import render
from render.path import render_path, replay_gradient
from render.scene.cornell import box_mesh, cornell_box

BACKGROUND = (1.0, 2.0, 0.5)


def lone_object(kind: str, path: bool) -> render.Scene:
    """One convex object under a constant environment. For the path integrator (``path``)
    it is diffuse: every bounce escapes, so each sample is albedo x environment exactly (zero
    variance); for the direct renderer its twin emits that radiance and nothing is lit."""
    albedo = np.array([0.5, 0.3, 0.2]) if kind == "box" else np.array([0.2, 0.5, 0.8])
    material = (
        render.Material(albedo)
        if path
        else render.Material((0.0, 0.0, 0.0), emission=albedo * np.array(BACKGROUND))
    )
    if kind == "box":
        obj = box_mesh((-0.5, 0.1, 0.0), (0.5, 0.4, 0.6), material)
    else:
        obj = render.Sphere((0.4, -0.3, 0.5), 0.6, material)
    camera = render.Camera((0.3, 0.2, 4.0), (0, 0, 0), (0, 1, 0), 40.0, 24, 20)
    return render.Scene([obj], [], camera, background=BACKGROUND)


def _parameters(scene: render.Scene) -> list[md.Tensor]:
    obj = scene.objects[0]
    shape = [obj.vertices] if isinstance(obj, render.Mesh) else [obj.center, obj.radius]
    params = shape + [scene.camera.position, scene.camera.look_at]
    for p in params:
        p.requires_grad = True
        p.grad = None
    return params


def _gradient(scene, weights, **options) -> list[np.ndarray]:
    params = _parameters(scene)
    md.sum(render.render(scene, **options) * md.tensor(weights)).backward()
    return [np.zeros_like(p.data) if p.grad is None else p.grad.copy() for p in params]


@pytest.mark.parametrize("kind", ["box", "sphere"])
def test_path_boundary_term_equals_the_direct_renderers_where_both_are_exact(kind):
    """With zero-variance jumps the path integrator's boundary term (its gradient with the
    term minus without, same seed) is the direct renderer's boundary term of the emissive
    twin (whose image has no other derivative), for the shape and the camera."""
    weights = np.random.default_rng(1).random((20, 24, 3))
    options = {"integrator": "path", "spp": 4, "max_depth": 3, "seed": 2}
    with_term = _gradient(lone_object(kind, True), weights, antialias="primary", **options)
    without = _gradient(lone_object(kind, True), weights, **options)
    direct = _gradient(lone_object(kind, False), weights, antialias="boundary")
    for a, b, d in zip(with_term, without, direct, strict=True):
        assert np.abs(d).max() > 1.0  # the edges move: a real term
        np.testing.assert_allclose(a - b, d, rtol=0, atol=1e-9 * np.abs(d).max())


def test_camera_gradient_in_the_cornell_box_matches_central_differences():
    """Moving the camera moves only primary visibility (shadows and indirect occlusion stay
    where they are), so with the boundary term the gradient is unbiased. Against central
    differences (h = 0.1, 2.6 % of the camera's distance) of 512-spp renders with common
    random numbers (the same seed both sides), in y and z; means over seeds with their
    standard errors. Without the term the gradient is a fraction of the truth."""
    size, depth, h = 8, 2, 0.1
    weights = np.random.default_rng(0).random((size, size, 3))

    def loss(scene, **options):
        image = render.render(scene, integrator="path", max_depth=depth, **options)
        return md.sum(image * md.tensor(weights))

    def gradient(seed, antialias):
        scene = cornell_box(size, size)
        scene.camera.position.requires_grad = True
        loss(scene, spp=32, seed=seed, antialias=antialias).backward()
        return scene.camera.position.grad[1:].copy()

    def central(seed):
        out = np.zeros(2)
        for i in (1, 2):
            values = []
            for sign in (1.0, -1.0):
                scene = cornell_box(size, size)
                scene.camera.position.data = scene.camera.position.data + sign * h * np.eye(3)[i]
                with md.no_grad():
                    values.append(float(loss(scene, spp=512, seed=seed).data))
            out[i - 1] = (values[0] - values[1]) / (2 * h)
        return out

    ours = np.array([gradient(s, "boundary") for s in range(4)])
    plain = np.array([gradient(s, False) for s in range(4)])
    truth = np.array([central(100 + s) for s in range(3)])
    error = np.hypot(ours.std(0) / np.sqrt(4), truth.std(0) / np.sqrt(3))  # standard errors
    difference = np.abs(ours.mean(0) - truth.mean(0))
    assert np.all(difference < 4 * error + 0.05 * np.abs(truth.mean(0))), (ours, truth)
    # The test can fail: without the term the gradient is off by many errors.
    assert np.all(np.abs(plain.mean(0) - truth.mean(0)) > 4 * error), (plain, truth)


def test_replay_with_the_boundary_term_equals_the_tape_with_the_same_seed():
    """The boundary term uses the gradient pass's seed and path ids after the image's: with
    ``seed_grad == seed`` replay and tape agree, whatever the batches."""
    target = render_path(cornell_box(8, 8), spp=2, seed=9).data

    def loss(image):
        return md.sum((image - md.tensor(target)) ** 2)

    scene = cornell_box(8, 8)
    sphere = scene.objects[7]
    params = [sphere.center, scene.camera.position]
    for p in params:
        p.requires_grad = True
    options = {"spp": 4, "max_depth": 3, "seed": 5, "antialias": "boundary", "edge_spp": 3}
    loss(render_path(scene, batch_spp=4, **options)).backward()
    taped = [p.grad.copy() for p in params]
    for p in params:
        p.grad = None
    replay_gradient(scene, loss, seed_grad=5, batch_spp=3, **options)
    for p, g in zip(params, taped, strict=True):
        assert np.abs(g).max() > 0
        np.testing.assert_allclose(p.grad, g, rtol=1e-9, atol=1e-12 * np.abs(g).max())


def test_the_boundary_term_leaves_the_image_unchanged():
    """The term is zero in value: with a parameter differentiated (so the term is added),
    the image is the plain one bit for bit."""
    scene = cornell_box(6, 6)
    plain = render_path(scene, spp=2, seed=1).data
    scene.camera.position.requires_grad = True
    with_term = render_path(scene, spp=2, seed=1, antialias="boundary")
    np.testing.assert_array_equal(with_term.data, plain)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"antialias": True}, 'takes antialias=False, "boundary"'),
        ({"antialias": "pairs"}, 'takes antialias=False, "boundary"'),
        ({"antialias": "boundary", "edge_spp": 0}, "edge_spp must be an integer >= 1"),
        ({"antialias": "boundary", "edge_spp": 2.5}, "edge_spp must be an integer >= 1"),
    ],
)
def test_bad_edge_options_are_named(options, message):
    with pytest.raises(ValueError, match=message):
        render.render(cornell_box(4, 4), integrator="path", **options)


def test_box_mesh_faces_point_outward():
    """Every face's (b - a) x (c - a) points away from the box's centre (emitters emit from
    that side; the boundary tests above compare such a box with an emissive twin)."""
    box = box_mesh((0.3, -0.2, 0.1), (0.5, 0.4, 0.6), render.Material((1, 1, 1)))
    v = box.vertices.data[box.faces]
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    outward = v.mean(axis=1) - np.array([0.3, -0.2, 0.1])
    assert np.all(np.einsum("ij,ij->i", normal, outward) > 0)


def test_both_integrators_radiances_are_side_radiances():
    """The direct renderer's and the path integrator's radiance either side of a curve
    (``DirectRadiance``, ``PathRadiance``) implement the one ``SideRadiance`` interface: the
    same methods with the same parameters and annotations."""
    import inspect

    from render.edges.boundary.radiance import DirectRadiance, SideRadiance
    from render.path.boundary.primary import PathRadiance

    for method in ("seen", "along"):
        want = inspect.signature(getattr(SideRadiance, method))
        for cls in (DirectRadiance, PathRadiance):
            assert inspect.signature(getattr(cls, method)) == want, (cls.__name__, method)
