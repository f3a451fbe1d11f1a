"""The path integrator (``render.path``) against closed forms, finite differences with common
random numbers, the direct renderer, and itself (seeds, batches, threads, replay)."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

import minidiff as md
import render
from render.inverse.shape import icosphere
from render.path import render_path, replay_gradient
from render.path.sample.emitters import polygon_irradiance
from render.scene.cornell import cornell_box, grid_quad

# --------------------------------------------------------------------------------------
# Closed forms
# --------------------------------------------------------------------------------------


def enclosure(albedo: float, emission: float) -> render.Scene:
    """A closed sphere (an icosphere mesh, faces wound inward) of uniform albedo and
    emission, with the camera inside: its radiance is emission / (1 - albedo) everywhere."""
    vertices, faces = icosphere(2, 5.0)
    mesh = render.Mesh(
        np.asarray(vertices), np.asarray(faces)[:, ::-1].copy(),
        render.Material((albedo,) * 3, emission=emission),
    )  # fmt: skip
    camera = render.Camera((0, 0, 0), (0, 0, 1), (0, 1, 0), 60.0, 8, 8)
    return render.Scene([mesh], [], camera)


@pytest.mark.parametrize("depth", [1, 2, 3, 6])
def test_white_furnace_depth_by_depth(depth):
    """max_depth d sums d - 1 bounces: emission * (1 + rho + ... + rho^(d-1)). Every path
    is a chain of cosine-sampled bounces inside the enclosure and NEE on it, so the
    estimate is exact up to MIS's mixing of the two: 0.5 % per pixel at 16 spp."""
    rho = 0.5
    image = render_path(enclosure(rho, 1.0), spp=16, max_depth=depth, seed=3, rr_depth=100).data
    expected = sum(rho**i for i in range(depth))
    assert abs(image.mean() / expected - 1) < 2e-3
    assert np.abs(image / expected - 1).max() < 0.05


def test_white_furnace_with_russian_roulette_converges_to_the_closed_form():
    """Unbounded depth, Russian roulette from the 3rd vertex: the mean converges to
    emission / (1 - rho) = 2 (64 pixels x 64 spp; the standard error is ~0.3 %)."""
    image = render_path(enclosure(0.5, 1.0), spp=64, max_depth=200, seed=1, rr_depth=3).data
    assert abs(image.mean() / 2.0 - 1) < 0.012


def test_a_convex_object_in_a_uniform_environment_reflects_albedo_times_it():
    """A diffuse sphere under a constant environment L: every cosine-sampled direction
    escapes, so each sample is exactly albedo * L (zero variance); the background shows L."""
    camera = render.Camera((0, 0, 4), (0, 0, 0), (0, 1, 0), 40.0, 12, 12)
    sphere = render.Sphere((0, 0, 0), 1.0, render.Material((0.2, 0.5, 0.8)))
    scene = render.Scene([sphere], [], camera, background=(1.0, 2.0, 0.5))
    image = render_path(scene, spp=4, max_depth=3, seed=0).data
    centre = image[6, 6]
    np.testing.assert_allclose(centre, [0.2, 1.0, 0.4], rtol=1e-12)
    np.testing.assert_allclose(image[0, 0], [1.0, 2.0, 0.5])


def test_a_mirror_in_a_uniform_environment_reflects_reflectance_times_it():
    camera = render.Camera((0, 0, 4), (0, 0, 0), (0, 1, 0), 30.0, 8, 8)
    mirror = render.Sphere((0, 0, 0), 1.0, render.Material((0.0, 0.0, 0.0), reflectance=0.7))
    scene = render.Scene([mirror], [], camera, background=(1.0, 1.0, 1.0))
    image = render_path(scene, spp=2, max_depth=4, seed=0).data
    np.testing.assert_allclose(image[4, 4], [0.7, 0.7, 0.7], rtol=1e-12)


LIGHT_CENTRE, LIGHT_HALF = np.array([0.3, 1.0, -0.2]), 0.4
TARGET = np.array([0.25, 0.0, 0.15])  # inside one triangle of the floor's 3 x 3 grid


def quad_over_plane(width: int = 6, light_radiance: float = 5.0):
    """A square light (half side 0.4, radiance 5) facing down at height 1 over a diffuse
    floor (albedo 0.6, a 3 x 3 grid of squares over [-2, 2]^2), seen by a camera with a
    thousandth of a degree's view of the point ``TARGET``: the image is albedo / pi *
    E(TARGET). (With a 1 degree view, the mean over the pixels' footprint already moves the
    vertex gradient 3 % away from the value at the central point: the view is oblique.)"""
    x, y, z = np.eye(3)
    vertices, faces = grid_quad((0, 0, 0), 2 * x, -2 * z, 3)
    floor = render.Mesh(vertices, faces, render.Material((0.6, 0.6, 0.6)))
    vertices, faces = grid_quad((0, 0, 0), LIGHT_HALF * x, LIGHT_HALF * z)
    light = render.Mesh(
        vertices, faces, render.Material((0, 0, 0), emission=light_radiance),
        transform=render.Transform(translation=LIGHT_CENTRE),
    )  # fmt: skip
    camera = render.Camera(TARGET + (0.0, 3.0, 4.0), TARGET, (0, 1, 0), 1e-3, width, width)
    return render.Scene([floor, light], [], camera)


def light_corners(centre):
    return np.array([centre + (sx * LIGHT_HALF, 0, sz * LIGHT_HALF)
                     for sx, sz in ((-1, -1), (1, -1), (1, 1), (-1, 1))])  # fmt: skip


def seen_radiance(centre=LIGHT_CENTRE, floor_vertices=None, vertex=None, radiance=5.0):
    """albedo / pi * E at the point the camera's central ray meets the floor's triangle
    under TARGET (that triangle's corners moved as ``floor_vertices`` says)."""
    scene = quad_over_plane()
    v = scene.objects[0].vertices.data if floor_vertices is None else floor_vertices
    face = scene.objects[0].faces[_target_face(scene)]
    a, b, c = v[face]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    eye = TARGET + (0.0, 3.0, 4.0)
    d = TARGET - eye
    t = np.dot(a - eye, n) / np.dot(d, n)
    return 0.6 / math.pi * polygon_irradiance(eye + t * d, n, light_corners(centre), radiance)


def _target_face(scene) -> int:
    v, faces = scene.objects[0].vertices.data, scene.objects[0].faces
    for k, (i, j, m) in enumerate(faces):
        a, b, c = v[i][[0, 2]], v[j][[0, 2]], v[m][[0, 2]]
        p = TARGET[[0, 2]]
        w = np.linalg.solve(np.stack([b - a, c - a], 1), p - a)
        if w.min() > 0.05 and w.sum() < 0.95:
            return k
    raise AssertionError("no triangle holds TARGET")


def test_an_emissive_quad_lights_a_plane_as_its_closed_form_says():
    """Direct light (max_depth 2, NEE and BSDF samples with MIS) from a square light: the
    image mean against Lambert's closed form, 2,304 paths: within 1 %."""
    image = render_path(quad_over_plane(), spp=64, max_depth=2, seed=0).data
    assert abs(image.mean() / seen_radiance() - 1) < 0.01


def _grad(scene, parameter, spp=64, seed=0):
    parameter.requires_grad = True
    render_path(scene, spp=spp, max_depth=2, seed=seed).sum().backward()
    return parameter.grad / (scene.camera.width * scene.camera.height * 3)


def _closed_form_grad(fn, x, h=1e-5):
    """Central differences of a closed form (no noise)."""
    out = np.zeros_like(x)
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        out[i] = (fn(x + e) - fn(x - e)) / (2 * h)
    return out


def test_light_position_gradient_matches_the_closed_form():
    """d image / d light translation, through area-form NEE points that move with the light
    (the light is not in view and nothing casts a shadow: the interior term is all)."""
    scene = quad_over_plane()
    grad = _grad(scene, scene.objects[1].transform.translation, spp=256)
    exact = _closed_form_grad(lambda c: seen_radiance(centre=c), LIGHT_CENTRE.copy())
    assert np.abs(grad - exact).max() < 0.02 * np.abs(exact).max()


def test_interior_vertex_gradient_matches_the_closed_form():
    """Moving one corner of the triangle the camera sees (an interior vertex of the floor)
    tilts the triangle: the point moves along the camera rays and its normal turns."""
    scene = quad_over_plane()
    floor = scene.objects[0]
    corner = int(floor.faces[_target_face(scene)][0])
    grad = _grad(scene, floor.vertices, spp=1024)[corner]  # 37k paths: ~1 % noise
    base = floor.vertices.data.copy()

    def moved(p):
        v = base.copy()
        v[corner] = p
        return seen_radiance(floor_vertices=v)

    exact = _closed_form_grad(moved, base[corner].copy())
    assert np.abs(grad - exact).max() < 0.03 * np.abs(exact).max()


def test_emission_gradient_matches_the_closed_form():
    scene = quad_over_plane()
    grad = _grad(scene, scene.objects[1].material.emission)
    assert abs(float(grad) / (seen_radiance() / 5.0) - 1) < 0.01


# --------------------------------------------------------------------------------------
# Finite differences with common random numbers
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["bleeding_albedo", "emission"])
def test_gradient_equals_same_seed_central_differences(which):
    """The red wall's albedo reaches the image only through light it reflects onto other
    walls (max_depth 4, blocks in the way); the light's emission everywhere. Both leave
    every sampling decision unchanged, so with the same seed a central difference is
    exactly the derivative of the same estimate: they agree to rounding."""
    weights = np.random.default_rng(2).standard_normal((10, 10, 3))

    def loss(delta, grad=False):
        scene = cornell_box(10, 10)
        scene.camera = render.Camera((0.6, 0, 3.9), (0.6, 0, 0), (0, 1, 0), 25.0, 10, 10)
        p = (
            scene.objects[3].material.albedo
            if which == "bleeding_albedo"
            else scene.objects[5].material.emission
        )
        p.data = p.data + delta
        p.requires_grad = grad
        value = (
            render_path(scene, spp=4, max_depth=4, seed=7, rr_depth=100) * md.tensor(weights)
        ).sum()
        return value, p

    value, p = loss(0.0, grad=True)
    value.backward()
    direction = np.array([0.3, -0.5, 0.8])
    h = 1e-4
    with md.no_grad():
        fd = (loss(h * direction)[0].item() - loss(-h * direction)[0].item()) / (2 * h)
    assert abs(fd) > 1e-3  # the wall is not seen, yet it matters
    assert abs(np.dot(p.grad, direction) - fd) < 1e-6 * abs(fd)


# --------------------------------------------------------------------------------------
# Seeds, batches, threads, replay
# --------------------------------------------------------------------------------------


def test_same_seed_same_image_whatever_the_batches_and_threads():
    scene = cornell_box(12, 12)
    reference = render_path(scene, spp=6, max_depth=4, seed=11, batch_spp=6).data
    for batch in (1, 4):
        assert np.array_equal(
            render_path(scene, spp=6, max_depth=4, seed=11, batch_spp=batch).data, reference
        )
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = render_path(scene, spp=6, max_depth=4, seed=11).data
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(single, reference)
    assert not np.array_equal(render_path(scene, spp=6, max_depth=4, seed=12).data, reference)


def test_replay_gradient_equals_the_tape_gradient_with_the_same_seed():
    """Way 2 (a primal pass, then batches on their own tapes) gives way 1's gradient."""
    target = render_path(cornell_box(10, 10), spp=4, seed=99).data

    def loss(image):
        return md.sum((image - md.tensor(target)) ** 2)

    def parameters(scene):
        ps = [scene.objects[5].transform.translation, scene.objects[0].material.albedo,
              scene.objects[2].vertices]  # fmt: skip
        for p in ps:
            p.requires_grad = True
        return ps

    scene = cornell_box(10, 10)
    scene.objects[5].transform.translation.data = np.array([0.1, -0.05, 0.05])
    taped = parameters(scene)
    loss(render_path(scene, spp=8, max_depth=4, seed=5, batch_spp=8)).backward()
    tape_grads = [p.grad.copy() for p in taped]
    for p in taped:
        p.grad = None
    value, image = replay_gradient(
        scene, loss, spp=8, max_depth=4, seed=5, seed_grad=5, batch_spp=3
    )
    for p, g in zip(taped, tape_grads, strict=True):
        np.testing.assert_allclose(p.grad, g, rtol=1e-9, atol=1e-12 * np.abs(g).max())
    assert np.abs(tape_grads[0]).max() > 0


def test_correlated_seeds_bias_the_gradient_of_a_nonlinear_loss():
    """loss = sum (I - T)^2, differentiated with respect to the light's emission k (I is
    linear in k): with the primal's own samples in the gradient pass, E[grad] = 2 sum (E[I^2]
    - T E[I]) / k, off the true 2 sum (E[I]^2 - T E[I]) / k by 2 sum Var(I) / k > 0; with
    decorrelated seeds the expectation is exact. 100 seeds at 1 spp: the correlated mean
    sits many standard errors above the decorrelated one, which is near zero (T = E[I])."""
    scene = quad_over_plane(width=4)
    target = np.full((4, 4, 3), seen_radiance())

    def loss(image):
        return md.sum((image - md.tensor(target)) ** 2)

    def gradient(seed, seed_grad):
        emission = scene.objects[1].material.emission
        emission.requires_grad, emission.grad = True, None
        replay_gradient(scene, loss, spp=1, max_depth=2, seed=seed, seed_grad=seed_grad)
        return float(emission.grad)

    correlated = np.array([gradient(s, s) for s in range(100)])
    decorrelated = np.array([gradient(s, s + 1000) for s in range(100)])
    error = math.hypot(correlated.std(), decorrelated.std()) / 10
    assert correlated.mean() - decorrelated.mean() > 5 * error
    assert abs(decorrelated.mean()) < 4 * decorrelated.std() / 10 + 0.01 * correlated.mean()


# --------------------------------------------------------------------------------------
# Against the direct renderer; emitters in the direct renderer
# --------------------------------------------------------------------------------------


def test_point_and_directional_lights_match_the_direct_renderer():
    """max_depth 2 with delta lights only is the direct renderer's job. A diffuse plane
    under a directional light is the same in every sample: equal to rounding. Under a point
    light with a glossy lobe the pixels vary, so the jittered and the stratified means differ
    by sampling noise (1.5 % per pixel at 256 spp); their image means agree to 0.1 %."""
    x, z = np.eye(3)[0], np.eye(3)[2]
    vertices, faces = grid_quad((0, 0, 0), 3 * x, -3 * z)
    camera = render.Camera((0, 2, 2), (0, 0, 0), (0, 1, 0), 30.0, 8, 8)

    def both(material, light, spp):
        scene = render.Scene([render.Mesh(vertices, faces, material)], [light], camera)
        path = render.render(scene, integrator="path", spp=spp, max_depth=2, seed=0).data
        return path, render.render(scene, spp=256).data

    sun = render.DirectionalLight((1, -2, 0.5), 0.7)
    path, direct = both(render.Material((0.5, 0.4, 0.3)), sun, 4)
    np.testing.assert_allclose(path, direct, rtol=1e-12)
    glossy = render.Material((0.5, 0.4, 0.3), specular=0.3, shininess=8.0)
    path, direct = both(glossy, render.PointLight((0.5, 2.0, 0.5), 6.0), 256)
    np.testing.assert_allclose(path, direct, rtol=0.03)
    assert abs(path.mean() / direct.mean() - 1) < 1e-3


def test_the_direct_renderer_shows_an_emitters_front_only():
    x, z = np.eye(3)[0], np.eye(3)[2]
    vertices, faces = grid_quad((0, 0, 0), x, -z)  # facing up
    quad = render.Mesh(vertices, faces, render.Material((0, 0, 0), emission=(1.0, 2.0, 3.0)))
    above = render.Camera((0, 2, 0.01), (0, 0, 0), (0, 0, -1), 30.0, 4, 4)
    below = render.Camera((0, -2, 0.01), (0, 0, 0), (0, 0, -1), 30.0, 4, 4)
    np.testing.assert_allclose(render.render(render.Scene([quad], [], above)).data[2, 2], [1, 2, 3])
    np.testing.assert_allclose(render.render(render.Scene([quad], [], below)).data[2, 2], [0, 0, 0])


# --------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------


def test_negative_radiance_is_refused():
    with pytest.raises(ValueError, match="emission must be >= 0"):
        render.Material((0.5, 0.5, 0.5), emission=(1.0, -0.1, 1.0))


@pytest.mark.parametrize(
    "options, message",
    [
        ({"spp": 0}, "spp must be an integer >= 1"),
        ({"max_depth": -1}, "max_depth must be an integer >= 1"),
        ({"max_depth": 0}, "max_depth must be an integer >= 1"),
        ({"seed": -3}, r"seed must be an integer in \[0, 2\*\*64\)"),
        ({"rr_depth": 1.5}, "rr_depth must be an integer >= 1"),
        ({"antialias": True}, 'takes antialias=False, "boundary"'),
    ],
)
def test_bad_path_options_are_named(options, message):
    with pytest.raises(ValueError, match=message):
        render.render(cornell_box(4, 4), integrator="path", **options)


def test_unknown_integrator_and_misplaced_options():
    with pytest.raises(ValueError, match='integrator must be "direct" or "path"'):
        render.render(cornell_box(4, 4), integrator="bidir")
    with pytest.raises(TypeError, match="max_depth only apply"):
        render.render(cornell_box(4, 4), max_depth=3)


def test_an_emitter_with_zero_area_is_refused():
    flat = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)  # collinear: no area
    light = render.Mesh(flat, [[0, 1, 2]], render.Material((0, 0, 0), emission=1.0))
    scene = render.Scene([light], [], render.Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 4, 4))
    with pytest.raises(ValueError, match=r"objects\[0\] is emissive but has zero area"):
        render_path(scene, spp=1)


def test_polygon_irradiance_against_its_limits():
    """Lambert's formula (``emitters.polygon_irradiance``): a tiny square gives L A cos cos
    / r^2; a huge square filling the hemisphere gives pi L; many points at once equal one
    at a time, whatever the polygon's orientation."""
    up = np.array([0.0, 0.0, 1.0])
    tiny = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * 1e-3 + [0.3, 0.1, 2.0]
    r2 = np.sum(np.array([0.3, 0.1, 2.0]) ** 2)
    cos = 2.0 / math.sqrt(r2)
    small = polygon_irradiance(np.zeros(3), up, tiny, 3.0)
    np.testing.assert_allclose(small, 3.0 * 4e-6 * cos * cos / r2, rtol=1e-5)
    huge = np.array([[-1, -1, 1e-3], [1, -1, 1e-3], [1, 1, 1e-3], [-1, 1, 1e-3]]) * [1e4, 1e4, 1]
    np.testing.assert_allclose(polygon_irradiance(np.zeros(3), up, huge[::-1], 2.0),
                               2.0 * math.pi, rtol=1e-4)  # fmt: skip
    rng = np.random.default_rng(5)
    points = rng.uniform(-0.5, 0.5, (6, 3)) * [1, 1, 0]
    normals = np.tile(up, (6, 1))
    square = tiny * 200 - [60, 20, 399.6]  # side 0.4 at height 0.4, any winding
    together = polygon_irradiance(points, normals, square)
    one_by_one = [polygon_irradiance(p, n, square) for p, n in zip(points, normals, strict=True)]
    np.testing.assert_allclose(together, one_by_one, rtol=1e-14)
    assert np.all(together > 0)
