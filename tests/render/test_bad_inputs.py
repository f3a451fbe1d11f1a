"""Issue 41: inputs that crashed deep inside the renderer or gave an unclear error.

Each legal but extreme input (all-degenerate meshes, a sphere too small to resolve) now
renders; each illegal one is refused at the call that is wrong, by an error that names the
argument and says what was expected.
"""

from __future__ import annotations

import numpy as np
import pytest

import render
from tests.render_helpers import QUAD_FACES

# --------------------------------------------------------------------------------------
# A sphere too small for its outline to be found
# --------------------------------------------------------------------------------------


def quad_and_sphere(radius):
    """A quad behind a sphere of ``radius`` whose centre projects exactly onto a pixel
    corner (the image centre of an even-sized image), where the outline's quadrature
    points land on pixel borders."""
    camera = render.Camera((0, 0, 4.0), (0, 0, 0), fov=40, width=16, height=12)
    quad = render.Mesh(
        [(-1, -1, -1), (1, -1, -1), (1, 1, -1), (-1, 1, -1)], QUAD_FACES,
        render.Material((0.1, 0.1, 0.1)),
    )  # fmt: skip
    objects = [quad]
    if radius is not None:
        objects.append(render.Sphere((0, 0, 0), radius, render.Material((0.9, 0.9, 0.9))))
    scene = render.Scene(objects, [render.PointLight((0, 1, 3), 10.0)], camera)
    quad.vertices.requires_grad = True
    return scene


@pytest.mark.parametrize("radius", [1e-16, 1e-100, 1e-160, 1e-300])
def test_a_sphere_too_small_to_resolve_adds_no_outline(radius):
    """Its outline's Newton steps divided by a zero gradient ("directions must be finite"
    from deep inside the boundary term) once r^2 fell below dist^2's rounding: the sphere
    subtends under 1.5e-8 radians, its outline has no length to speak of, and it is
    skipped. The image and the quad's gradient are those of the scene without it."""
    scene, alone = quad_and_sphere(radius), quad_and_sphere(None)
    image = render.render(scene, antialias="boundary")
    image.sum().backward()
    reference = render.render(alone, antialias="boundary")
    reference.sum().backward()
    np.testing.assert_array_equal(image.data, reference.data)
    grad, expected = scene.objects[0].vertices.grad, alone.objects[0].vertices.grad
    assert np.isfinite(grad).all() and np.abs(expected).max() > 0
    np.testing.assert_allclose(grad, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


# --------------------------------------------------------------------------------------
# Meshes whose faces are all degenerate
# --------------------------------------------------------------------------------------

DEGENERATE = {
    "zero-area": ([(0.2, 0.1, 0.0)] * 3, None),
    "collinear": ([(-0.5, 0.0, 0.0), (0.1, 0.2, 0.0), (0.4, 0.3, 0.0)], None),
    "sliver": ([(-2.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 1e-12, 0.0)], None),  # 4 x 1e-12
    "scaled-away": ([(-0.5, -0.5, 0), (0.5, -0.5, 0), (0, 0.5, 0)], 1e-300),
}


def degenerate_scene(case, beside):
    """The degenerate mesh of ``case`` (vertices requiring grad), alone or in front of the
    quad of ``quad_and_sphere`` (``beside``); None: the quad alone. The background requires
    grad too, so that the image is on the tape even where nothing is hit."""
    scene = quad_and_sphere(None)
    scene.background.requires_grad = True
    if not beside:
        scene.objects = []
    if case is not None:
        vertices, scale = DEGENERATE[case]
        transform = None if scale is None else render.Transform(scale=scale)
        mesh = render.Mesh(
            vertices, [[0, 1, 2]], render.Material((0.5, 0.5, 0.5)), transform=transform
        )
        mesh.vertices.requires_grad = True
        scene.objects.append(mesh)
    return scene


def image_and_grads(scene, antialias):
    """The image and the gradients of a fixed weighting of it with respect to every
    parameter that requires grad (None: not reached)."""
    image = render.render(scene, antialias=antialias)
    weights = np.random.default_rng(0).standard_normal(image.shape)
    (image * weights).sum().backward()
    grads = [scene.background.grad] + [o.vertices.grad for o in scene.objects]
    return image.data, grads


@pytest.mark.parametrize("antialias", ["pairs", "boundary"])
@pytest.mark.parametrize("beside", [False, True], ids=["alone", "beside-a-quad"])
@pytest.mark.parametrize("case", DEGENERATE)
def test_a_mesh_of_degenerate_faces_only_adds_no_edge_term(case, beside, antialias):
    """Its edge table was built from no edges and indexed out of bounds (an IndexError in
    ``render.trace.topology``). It now has no edges: the image and the gradients are those
    of the scene without it, the degenerate vertices get no (or a zero) gradient, and with
    ``antialias="boundary"`` the edge term is zero in value (the image is the plain one
    when no mixed pixel is averaged: ``interior_samples=1``)."""
    image, grads = image_and_grads(degenerate_scene(case, beside), antialias)
    without, expected = image_and_grads(degenerate_scene(None, beside), antialias)
    np.testing.assert_array_equal(image, without)
    if antialias == "boundary":
        plain = render.render(degenerate_scene(case, beside), antialias=False)
        own = render.render(degenerate_scene(case, beside), antialias="boundary",
                            interior_samples=1)  # fmt: skip
        np.testing.assert_array_equal(own.data, plain.data)
    *grads, degenerate = grads
    assert degenerate is None or not degenerate.any()
    for grad, reference in zip(grads, expected, strict=True):
        assert np.isfinite(grad).all()
        np.testing.assert_allclose(
            grad, reference, rtol=1e-12, atol=1e-12 * np.abs(reference).max()
        )


# --------------------------------------------------------------------------------------
# Transform: a rotation angle too large to mean anything
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("angle", [1e200, 1e20, 1.0000001e6])
def test_a_rotation_angle_beyond_1e6_degrees_is_refused_by_name(angle):
    """(0, 0, 1e200) was accepted and the render failed later with "triangles must be
    finite" (theta^2 overflowed); 1e20 degrees gave a rotation decided by rounding."""
    with pytest.raises(ValueError, match=r"Transform: rotation must be .*at most 1e6 degrees"):
        render.Transform(rotation=(0.0, 0.0, angle))
    with pytest.raises(ValueError, match=r"Transform: rotation must be .*at most 1e6 degrees"):
        render.Transform(rotation=(angle / np.sqrt(3),) * 3)  # the length is the angle


def test_a_rotation_angle_grown_too_large_in_place_is_refused_at_render():
    scene = quad_and_sphere(None)
    scene.objects[0].transform = render.Transform(rotation=(0.0, 0.0, 1e6))  # the largest
    render.render(scene)
    scene.objects[0].transform.rotation.data[2] = 1e200  # an optimiser ran away
    with pytest.raises(ValueError, match=r"Transform: rotation must be .*at most 1e6 degrees"):
        render.render(scene)


# --------------------------------------------------------------------------------------
# The path integrator's options
# --------------------------------------------------------------------------------------


def empty_scene():
    return render.Scene([], [], render.Camera((0, 0, 5), (0, 0, 0), width=4, height=4))


@pytest.mark.parametrize("batch_spp", [0, -1, 2.0, True, None])
def test_a_bad_batch_spp_is_named(batch_spp):
    """It was reported as "spp must be an integer >= 1", with spp itself fine."""
    with pytest.raises(ValueError, match=r"render: batch_spp must be an integer >= 1, got"):
        render.render(empty_scene(), integrator="path", spp=4, batch_spp=batch_spp)


def test_an_edge_spp_beyond_the_ray_limit_is_refused_before_tracing():
    """edge_spp=2**40 failed with a MemoryError for 8 TiB: the paths of one side of one
    edge point are traced together, so edge_spp meets the limit of width x height x spp."""
    with pytest.raises(ValueError, match=r"render: edge_spp = 1,099,511,627,776 .* limit of"):
        render.render(empty_scene(), integrator="path", antialias="boundary", edge_spp=2**40)
    with pytest.raises(ValueError, match=r"render: edge_spp = 67,108,865 .* limit of"):
        render.render(empty_scene(), integrator="path", antialias="boundary", edge_spp=2**26 + 1)
    render.render(empty_scene(), integrator="path", antialias="boundary", edge_spp=2**26)


# --------------------------------------------------------------------------------------
# Large Steps
# --------------------------------------------------------------------------------------


def test_a_face_repeating_a_vertex_index_is_named_as_degenerate():
    """It was reported as an edge "shared by 4 faces (non-manifold)"."""
    import minidiff as md
    from render.inverse.shape import LargeSteps, LargeStepsAdam, icosphere

    v, f = icosphere(1)
    faces = np.concatenate([f, [[5, 5, 7]]])
    vertices = md.tensor(v, requires_grad=True)
    match = rf"faces: face {len(f)} \[5, 5, 7\] repeats a vertex index \(a degenerate face"
    with pytest.raises(ValueError, match=match):
        LargeStepsAdam(vertices, faces)
    with pytest.raises(ValueError, match=r"faces: face 1 \[0, 2, 0\] repeats a vertex index"):
        LargeSteps(np.array([[0, 1, 2], [0, 2, 0]]), 3)


@pytest.mark.parametrize("lam", [np.inf, np.nan, -1.0, 1e9, 1e16, 1e300])
def test_lam_must_be_finite_positive_and_keep_the_solves_accurate(lam):
    """lam=inf passed the check and SciPy said "Factor is exactly singular"; lam=1e16 gave
    v = M^-1 M v off by 80% of the mesh's size, silently."""
    from render.inverse.shape import LargeSteps, icosphere

    v, f = icosphere(2)  # largest vertex degree 6: lam at most 1e10 / 12
    with pytest.raises(ValueError, match=r"LargeSteps: lam must be"):
        LargeSteps(f, len(v), lam)
    steps = LargeSteps(f, len(v), 8e8)  # the largest accepted: 6 digits kept
    np.testing.assert_allclose(steps.to_vertices(steps.to_u(v)), v, rtol=0, atol=1e-6)


@pytest.mark.parametrize("shape", [(5, 3), (42,), (42, 2), (42, 3, 1)])
def test_a_gradient_of_the_wrong_shape_is_named(shape):
    """SciPy said "b is of incompatible size" (or solved a (42,) vector as if it were
    one coordinate of every vertex)."""
    import minidiff as md
    from render.inverse.shape import LargeSteps, LargeStepsAdam, icosphere

    v, f = icosphere(1)  # 42 vertices
    steps = LargeSteps(f, len(v))
    shown = str(shape).replace("(", r"\(").replace(")", r"\)")
    with pytest.raises(
        ValueError, match=rf"LargeSteps.adjoint: grad_vertices .*\(42, 3\).*{shown}"
    ):
        steps.adjoint(np.ones(shape))
    with pytest.raises(ValueError, match=rf"LargeSteps.to_vertices: u .*\(42, 3\).*{shown}"):
        steps.to_vertices(np.ones(shape))
    with pytest.raises(ValueError, match=rf"LargeSteps.to_u: vertices .*\(42, 3\).*{shown}"):
        steps.to_u(np.ones(shape))
    vertices = md.tensor(v.copy(), requires_grad=True)
    optimizer = LargeStepsAdam(vertices, f)
    vertices.grad = np.ones(shape)
    with pytest.raises(ValueError, match=rf"LargeStepsAdam: vertices.grad .*\(42, 3\).*{shown}"):
        optimizer.step()
    np.testing.assert_array_equal(vertices.data, v)  # nothing moved


# --------------------------------------------------------------------------------------
# optimize's render_kwargs
# --------------------------------------------------------------------------------------


def optimize_problem():
    scene = quad_and_sphere(None)
    albedo = scene.objects[0].material.albedo
    albedo.requires_grad = True
    target = np.zeros((scene.camera.height, scene.camera.width, 3))
    return scene, albedo, target


@pytest.mark.parametrize("views", [False, True], ids=["scene", "views"])
def test_render_kwargs_asking_for_render_info_are_refused(views):
    """render would return an (image, info) pair: optimize failed inside the loss with
    NumPy's "inhomogeneous shape"."""
    scene, albedo, target = optimize_problem()
    problem = ([(scene, target)], None) if views else (scene, target)
    with pytest.raises(ValueError, match=r"optimize: render_kwargs must not set return_info"):
        render.optimize(*problem, [albedo], max_iters=1, quiet=True,
                        render_kwargs={"return_info": True})  # fmt: skip
    np.testing.assert_array_equal(albedo.data, [0.1, 0.1, 0.1])  # refused before any step


def test_render_kwargs_that_would_be_ignored_or_clash_are_refused():
    scene, albedo, target = optimize_problem()
    with pytest.raises(ValueError, match=r"optimize: render_kwargs must not set scene"):
        render.optimize(scene, [albedo], target, max_iters=1, render_kwargs={"scene": scene})
    with pytest.raises(TypeError, match=r"optimize: render_kwargs must be a dict"):
        render.optimize(scene, [albedo], target, max_iters=1, render_kwargs=[("spp", 4)])
    with pytest.raises(ValueError, match=r"optimize: render_kwargs apply to scenes"):
        render.optimize(lambda: render.render(scene), [albedo], target, max_iters=1,
                        render_kwargs={"spp": 4})  # fmt: skip
    _, history = render.optimize(scene, [albedo], target, max_iters=1, quiet=True,
                                 render_kwargs={"return_info": False, "spp": 4})  # fmt: skip
    assert history.iterations == 1
