"""Shadow rays answered in the light's view (``render.trace.light_view.occluded_towards_light``)
against the BVH: the same yes or no for every ray, on random soups and spheres, at shared
edges and vertices, far from the origin, and in rendered images."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import render
import render.trace.visibility as visibility
from render.trace.accel import Accelerator
from render.trace.light_view import occluded_towards_light
from render.trace.primitives import scene_primitives
from render.trace.visibility import scene_size, shadow_rays
from tests.render.trace.test_accel import grid_triangles
from tests.render.trace.test_raster import points, soups

SETTINGS = settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def shadow_answers(triangles, light, hit_points, start_prim, centers=None, radii=None):
    """(light view, BVH) answers for shadow rays from hit points on primitives start_prim
    to a point light, made as the renderer makes them (no spheres by default)."""
    if centers is None:
        centers, radii = np.zeros((0, 3)), np.zeros(0)
    primitives = (triangles, centers, radii)
    rays = shadow_rays(
        render.PointLight(light, 1.0),
        hit_points,
        start_prim,
        len(triangles),
        scene_size(primitives),
    )
    bvh = Accelerator(*primitives).occluded(
        rays.origins, rays.directions, rays.tmax, tmin=0.0, ignore_prim=rays.ignore_prim
    )
    view = occluded_towards_light(
        primitives, np.asarray(light, float), rays.origins, rays.directions, rays.tmax,
        rays.ignore_prim,
    )  # fmt: skip
    return view, bvh


def points_on(triangles: np.ndarray, rng: np.random.Generator, n: int):
    """n random points on random triangles: (points (n, 3), triangle ids (n,))."""
    ids = rng.integers(0, len(triangles), n)
    u, v = rng.uniform(size=(2, n))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = np.moveaxis(triangles[ids], 1, 0)
    return a + u[:, None] * (b - a) + v[:, None] * (c - a), ids


@SETTINGS
@given(
    soup=soups(2.0, 3, 1.5, 1.0),
    light=points(1, -1.0, 1.0),
    height=st.floats(5.0, 12.0),
    seed=st.integers(0, 2**16),
)
def test_random_soups_and_spheres_agree_with_the_bvh(soup, light, height, seed):
    """Hit points on random triangles in [-2, 2]^3 (every ray skips its own), spheres, and a
    light at least 5 above the soup's top, so that the rays always fit one view (within 60
    degrees of its axis): its answers are the BVH's."""
    triangles, centers, radii = soup
    light = light[0] + np.array([0.0, 2.0 + height, 0.0])
    hit_points, start = points_on(triangles, np.random.default_rng(seed), 200)
    view, bvh = shadow_answers(triangles, light, hit_points, start, centers, radii)
    assert view is not None
    np.testing.assert_array_equal(view, bvh)


def test_primitives_next_to_the_light_far_from_the_origin():
    """1e8 from the origin, directions from the light are exact only to ~1e-8 of a unit:
    tiny triangles a ten-thousandth below the light (within the distance where rounding
    could move their image by a cell margin, so listed in every cell) must still block
    exactly the rays the BVH says they block (a patch of the ground below the light)."""
    shift = np.array([1e8, 0.0, 1e8])
    ground = grid_triangles(8, 8, z=0.0, size=0.25)[:, :, [0, 2, 1]] + shift  # y = 0
    light = shift + np.array([1.0, 1.0, 1.0])
    near_light = 1e-5 * np.array([[[-2.0, -10.0, -2.0], [3.0, -10.0, -1.0], [0.0, -10.0, 3.0]]])
    triangles = np.concatenate([ground, near_light + light + [1e-5, 0.0, 0.0], near_light + light])
    hit_points, start = points_on(ground, np.random.default_rng(5), 4000)
    view, bvh = shadow_answers(triangles, light, hit_points, start)
    assert view is not None and 0 < bvh.sum() < len(bvh)
    np.testing.assert_array_equal(view, bvh)


def test_a_light_above_the_soup_always_gets_a_view():
    rng = np.random.default_rng(3)
    triangles = rng.uniform(-1, 1, (300, 3, 3))
    hit_points, start = points_on(triangles, rng, 5000)
    view, bvh = shadow_answers(triangles, (0.2, 6.0, 0.1), hit_points, start)
    assert view is not None and 0 < bvh.sum() < len(bvh)  # some blocked, some not
    np.testing.assert_array_equal(view, bvh)


def test_rays_through_shared_edges_and_vertices():
    """Two grids, one above the other; the light straight above vertices and edges of both,
    so that many rays pass exactly through shared edges and corners of the upper one."""
    lower = grid_triangles(8, 8, z=0.0, size=0.25)
    upper = grid_triangles(8, 8, z=1.0, size=0.25)[::3]  # gaps: some rays get through
    triangles = np.concatenate([lower, upper])
    corners = lower.reshape(-1, 3)
    hit_points = np.concatenate([corners, lower.mean(axis=1)])
    start = np.concatenate([np.repeat(np.arange(len(lower)), 3), np.arange(len(lower))])
    for light in ((1.0, 1.0, 3.0), (0.5, 1.25, 2.0), (1.0, 1.0, 1e6)):
        view, bvh = shadow_answers(triangles, light, hit_points, start)
        assert view is not None
        assert 0 < bvh.sum() < len(bvh)
        np.testing.assert_array_equal(view, bvh)


@pytest.mark.parametrize("shift, scale", [(0.0, 1.0), (1e6, 1.0), (0.0, 1e-6), (-3e4, 250.0)])
def test_the_teapot_on_its_ground_anywhere_at_any_scale(shift, scale):
    """The renderer's own shadow rays (camera hits on the teapot, its ground and a sphere)
    in a scene moved and scaled: the view's answers stay the BVH's."""
    scene = render.paper_scene(64, 64, ground=True)
    scene.objects.append(render.Sphere((1.5, 0.5, 1.0), 0.6, render.Material((0.5, 0.5, 0.5))))
    triangles, centers, radii = primitives = scene_primitives(scene)
    primary = visibility.trace_primary(None, scene.camera, 1, primitives, raster=True)
    start = primary.prim_id[primary.hit_rays]
    assert (start == len(triangles)).any()  # some rays start on the sphere

    def move(x):
        return x * scale + shift

    light = move(np.asarray(scene.lights[0].position.data, float))
    view, bvh = shadow_answers(
        move(triangles), light, move(primary.points), start, move(centers), radii * scale
    )
    assert view is not None and 0 < bvh.sum() < len(bvh)
    np.testing.assert_array_equal(view, bvh)


def test_rays_from_the_light_itself_are_lit():
    """A hit point at the light (tmax = 0): nothing can be between, in both."""
    triangles = grid_triangles(4, 4, z=0.0, size=0.5)
    hit_points, start = triangles.mean(axis=1), np.arange(len(triangles))
    light = hit_points[5]
    view, bvh = shadow_answers(triangles, light, hit_points, start)
    assert view is None or np.array_equal(view, bvh)
    assert not bvh[5]


def test_a_light_inside_the_geometry_is_left_to_the_bvh():
    """Rays fanning out all around the light do not fit one view: None (the BVH answers)."""
    rng = np.random.default_rng(0)
    triangles = rng.uniform(-1, 1, (100, 3, 3))
    hit_points, start = points_on(triangles, rng, 500)
    view, _ = shadow_answers(triangles, (0.0, 0.0, 0.0), hit_points, start)
    assert view is None


def test_render_gets_the_same_image_and_masks_either_way(monkeypatch):
    scene = render.paper_scene(64, 48, ground=True)
    monkeypatch.setattr(visibility, "LIGHT_VIEW_RAYS_PER_PRIMITIVE", 0)  # the view always
    a, info_a = render.render(scene, reuse_visibility=False, return_info=True)
    monkeypatch.setattr(visibility, "LIGHT_VIEW_RAYS_PER_PRIMITIVE", 10**9)  # the BVH only
    b, info_b = render.render(scene, reuse_visibility=False, return_info=True)
    np.testing.assert_array_equal(a.data, b.data)
    for mask_a, mask_b in zip(info_a.lit, info_b.lit, strict=True):
        np.testing.assert_array_equal(mask_a, mask_b)
    assert 0 < info_a.lit[0].sum() < info_a.lit[0].size
