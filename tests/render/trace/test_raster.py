"""Rasterised camera-ray visibility (``render.trace.raster``) against the BVH: bit-identical ids,
t, u, v, ties included (the lower id wins), and the renderer's choice between them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import render
from render.scene.camera import (
    camera_directions,
    hits_along_rays,
    image_plane_coords,
    plain_frame,
    primary_rays,
    subpixel_offsets,
    to_image_plane,
)
from render.trace.accel import Accelerator
from render.trace.primitives import scene_primitives
from render.trace.raster import raster_closest_hit, raster_occluded
from tests.render.trace.test_accel import grid_triangles

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def assert_raster_equals_bvh(triangles, centers, radii, camera: render.Camera, spp: int = 1):
    eye, directions = primary_rays(camera, spp)
    raster = raster_closest_hit(triangles, centers, radii, camera, spp)
    bvh = Accelerator(triangles, centers, radii).closest_hit(
        np.broadcast_to(eye, directions.shape), directions
    )
    for name, a, b in zip(("prim_id", "t", "u", "v"), raster, bvh, strict=True):
        np.testing.assert_array_equal(a, b, err_msg=name)
    return raster


def points(n: int, lo: float, hi: float):
    return st.lists(
        st.tuples(*[st.floats(lo, hi, allow_nan=False, allow_infinity=False)] * 3),
        min_size=n,
        max_size=n,
    ).map(np.array)


def soups(extent: float, max_spheres: int, sphere_extent: float, max_radius: float):
    """Strategy: (triangles (T, 3, 3) with corners in [-extent, extent]^3, 1 <= T <= 40;
    sphere centres (S, 3) in [-sphere_extent, sphere_extent]^3, S <= max_spheres; their
    common radius (S,), from 0.05 to max_radius)."""
    corners = st.integers(1, 40).flatmap(lambda n: points(3 * n, -extent, extent))
    centers = st.integers(0, max_spheres).flatmap(
        lambda n: points(n, -sphere_extent, sphere_extent)
    )
    radius = st.floats(0.05, max_radius)
    return st.tuples(corners, centers, radius).map(
        lambda p: (p[0].reshape(-1, 3, 3), p[1].reshape(-1, 3), np.full(len(p[1]), p[2]))
    )


@SETTINGS
@given(
    soup=soups(3.0, 4, 2.0, 1.5),
    eye=points(1, -4.0, 4.0),
    fov=st.floats(20.0, 100.0),
    spp=st.sampled_from([1, 4]),
)
def test_random_soups_and_spheres_match_the_bvh(soup, eye, fov, spp):
    """Random triangles around the eye (some behind it, some crossing its plane) and
    spheres (the eye may be inside one)."""
    eye = eye[0]
    look_at = eye + np.array([0.3, -0.2, -1.0])
    camera = render.Camera(eye, look_at, fov=fov, width=23, height=17)
    assert_raster_equals_bvh(*soup, camera, spp)


@SETTINGS
@given(
    soup=soups(3.0, 4, 2.0, 1.5),
    eye=points(1, -4.0, 4.0),
    spp=st.sampled_from([1, 4, 16]),
    chosen=st.lists(st.integers(0, 23 * 17 - 1), unique=True, max_size=60),
)
def test_some_pixels_samples_match_the_bvh(soup, eye, spp, chosen):
    """``pixels=``: the samples of some pixels only (the mixed pixels' candidates), in the
    order given, along the caller's directions (camera_directions' bits, not the raster's
    own): the accelerator's hits for those very rays."""
    eye = eye[0]
    camera = render.Camera(eye, eye + np.array([0.3, -0.2, -1.0]), fov=60.0, width=23, height=17)
    pixels = np.array(chosen, np.int64)
    offsets = subpixel_offsets(spp)
    corner = np.stack([pixels % 23, pixels // 23], axis=1).astype(np.float64)
    coords = to_image_plane((corner[:, None] + offsets).reshape(-1, 2), 23, 17)
    forward, right, up, origin = plain_frame(camera)
    directions = camera_directions(coords, right, up, forward)
    raster = raster_closest_hit(*soup, camera, spp, pixels=pixels, directions=directions)
    bvh = Accelerator(*soup).closest_hit(np.broadcast_to(origin, directions.shape), directions)
    for name, a, b in zip(("prim_id", "t", "u", "v"), raster, bvh, strict=True):
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_some_pixels_are_checked():
    """Bad ``pixels``/``directions`` are refused, naming the argument."""
    camera = render.Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=8, height=6)
    primitives = scene_primitives(render.paper_scene(8, 6))
    with pytest.raises(ValueError, match="pixels must be flat pixel indices"):
        raster_closest_hit(*primitives, camera, 1, pixels=np.array([48]),
                           directions=np.zeros((1, 3)))  # fmt: skip
    with pytest.raises(ValueError, match="pixels must be distinct"):
        raster_closest_hit(*primitives, camera, 1, pixels=np.array([3, 3]),
                           directions=np.zeros((2, 3)))  # fmt: skip
    with pytest.raises(ValueError, match=r"directions must have shape \(m \* spp, 3\)"):
        raster_closest_hit(*primitives, camera, 4, pixels=np.array([3]),
                           directions=np.zeros((1, 3)))  # fmt: skip
    with pytest.raises(ValueError, match="pixels and directions must be given together"):
        raster_closest_hit(*primitives, camera, 1, pixels=np.array([3]))
    with pytest.raises(ValueError, match="pixels must be a"):
        raster_closest_hit(*primitives, camera, 1, pixels=np.array([0.5]),
                           directions=np.zeros((1, 3)))  # fmt: skip


@pytest.mark.parametrize("spp", [1, 4, 9])
def test_rays_through_shared_edges_and_vertices(spp):
    """A grid whose vertices and edges lie exactly under pixel centres and samples: every
    tie must go to the lower id, as in the BVH."""
    triangles = grid_triangles(16, 16, size=0.125) - np.array([1.0, 1.0, 0.0])
    camera = render.Camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), fov=90.0, width=16, height=16)
    ids, *_ = assert_raster_equals_bvh(triangles, np.zeros((0, 3)), np.zeros(0), camera, spp)
    assert (ids >= 0).all()


def test_the_teapot_on_its_ground_and_a_sphere():
    scene = render.paper_scene(96, 80, ground=True)
    scene.objects.append(render.Sphere((1.5, 0.5, 1.0), 0.6, render.Material((0.5, 0.5, 0.5))))
    triangles, centers, radii = scene_primitives(scene)
    ids, *_ = assert_raster_equals_bvh(triangles, centers, radii, scene.camera, 4)
    assert (ids == len(triangles)).any()  # the sphere is in view


def test_render_uses_either_and_gets_the_same_image():
    scene = render.paper_scene(64, 48, ground=True)
    a, info_a = render.render(scene, primary="raster", reuse_visibility=False, return_info=True)
    b, info_b = render.render(scene, primary="bvh", reuse_visibility=False, return_info=True)
    np.testing.assert_array_equal(info_a.prim_id, info_b.prim_id)
    np.testing.assert_array_equal(a.data, b.data)


def test_bad_primary_is_refused():
    with pytest.raises(ValueError, match="primary must be"):
        render.render(render.paper_scene(8, 8), primary="zbuffer")


def test_hits_along_rays_are_eye_plus_t_times_the_rows_of_primary_rays():
    """The hit points are eye + t d with primary_rays' directions, bit for bit (NumPy's
    broadcast formula), and the coordinates those of image_plane_coords."""
    camera = render.Camera((0.3, 1.0, 4.0), (0.0, 0.2, 0.0), fov=47.0, width=13, height=9)
    for spp in (1, 4):
        eye, directions = primary_rays(camera, spp)
        rng = np.random.default_rng(spp)
        rays = rng.choice(len(directions), 40, replace=False)
        t = rng.uniform(0.0, 10.0, len(directions))
        points, coords = hits_along_rays(camera, rays, t, spp)
        np.testing.assert_array_equal(points, eye + t[rays, None] * directions[rays])
        np.testing.assert_array_equal(coords, image_plane_coords(camera, rays, spp))
    ids, t, u, v = raster_closest_hit(*scene_primitives(render.paper_scene(16, 12)), camera)
    assert u is not None
    _, _, u, v = raster_closest_hit(
        *scene_primitives(render.paper_scene(16, 12)), camera, with_uv=False
    )
    assert u is None and v is None


def assert_occluded_equals_bvh(triangles, centers, radii, camera, coords, rng):
    """``raster_occluded`` against the BVH's any-hit for camera rays through ``coords``
    (k, 2), their ends just before, at and beyond what they hit first, and beyond
    everything, ignoring nothing, a random primitive or the one they hit first."""
    frame = plain_frame(camera)
    forward, right, up, eye = frame
    directions = camera_directions(coords, right, up, forward)
    accel = Accelerator(triangles, centers, radii)
    origins = np.broadcast_to(eye, directions.shape)
    first, t, _, _ = accel.closest_hit(origins, directions)
    n_prims = len(triangles) + len(centers)
    k = len(coords)
    ends = np.where(np.isfinite(t), t, 1.0)
    tmax = ends * rng.choice([1.0 - 1e-6, 1.0, 1.0 + 1e-6, 2.0, 1e3], k)
    ignore = np.where(rng.uniform(size=k) < 0.5, first, rng.integers(-1, n_prims, k))
    raster = raster_occluded(
        (triangles, centers, radii), frame, camera.width, camera.height, coords, directions,
        tmax, ignore,
    )  # fmt: skip
    bvh = accel.occluded(origins, directions, tmax, tmin=0.0, ignore_prim=ignore)
    np.testing.assert_array_equal(raster, bvh)
    return raster


@SETTINGS
@given(
    soup=soups(3.0, 4, 2.0, 1.5),
    eye=points(1, -4.0, 4.0),
    fov=st.floats(20.0, 100.0),
    seed=st.integers(0, 2**31),
)
def test_occluded_camera_rays_match_the_bvh(soup, eye, fov, seed):
    """Rays through any image-plane point, a few outside the image (they are tested
    against every primitive), to every kind of end."""
    eye = eye[0]
    camera = render.Camera(eye, eye + np.array([0.3, -0.2, -1.0]), fov=fov, width=23, height=17)
    rng = np.random.default_rng(seed)
    assert_occluded_equals_bvh(*soup, camera, rng.uniform(-1.1, 1.1, (200, 2)), rng)


def test_occluded_rays_through_shared_edges_and_vertices():
    """Rays exactly through a grid's vertices and edges (pixel corners and borders), where
    a tile's list must hold every triangle the BVH would find."""
    triangles = grid_triangles(16, 16, size=0.125) - np.array([1.0, 1.0, 0.0])
    camera = render.Camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), fov=90.0, width=16, height=16)
    corners = np.stack(np.meshgrid(np.arange(17) / 8.0 - 1.0, np.arange(17) / 8.0 - 1.0), -1)
    coords = np.concatenate([corners.reshape(-1, 2), corners.reshape(-1, 2)[:, ::-1] * 0.999])
    blocked = assert_occluded_equals_bvh(
        triangles, np.zeros((0, 3)), np.zeros(0), camera, coords, np.random.default_rng(3)
    )
    assert blocked.any() and not blocked.all()


def test_occluded_rays_to_the_teapots_edges():
    """The boundary term's use: rays to points on the teapot and its ground, at 256x192."""
    scene = render.paper_scene(256, 192, ground=True)
    scene.objects.append(render.Sphere((1.5, 0.5, 1.0), 0.6, render.Material((0.5, 0.5, 0.5))))
    rng = np.random.default_rng(0)
    assert_occluded_equals_bvh(
        *scene_primitives(scene), scene.camera, rng.uniform(-1.0, 1.0, (20000, 2)), rng
    )
