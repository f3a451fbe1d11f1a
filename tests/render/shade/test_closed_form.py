"""Closed-form checks of ``render.render``: pixel values and coverage computed independently.

Every expected value here is computed in the test from the documented conventions (the
camera model of ``render.Camera``: horizontal fov, square pixels, rays through pixel
centres, row 0 at the top; the radiometry of ``docs/paper_scene.md``: L = albedo / pi * I *
max(0, cos theta) / r^2 for a point light, E * albedo / pi * cos theta for a directional
light), using ``render_helpers.pinhole_rays`` for the rays, never the renderer's own code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import minidiff as md
import render
from tests.render_helpers import QUAD_FACES, ground_quad, pinhole_rays, random_scene


def render_centres(scene, **kwargs):
    """The renderer without edge antialiasing: every closed form here is the value at the
    pixel (or sample) centre. ``tests/render/edges/test_pairs.py`` checks the antialiased image."""
    return render.render(scene, antialias=False, **kwargs)


RTOL = 1e-10


def camera_rays(camera):
    return pinhole_rays(
        camera.position.data,
        camera.look_at.data,
        camera.up.data,
        float(camera.fov.data),
        camera.width,
        camera.height,
    )


def plane_hits(camera, a, b, c):
    """Analytic hits of every pixel ray with the plane of triangle abc: points (H, W, 3),
    barycentrics (u, v) of b and c, and the unit normal facing the camera (H, W, 3)."""
    eye = camera.position.data
    d = camera_rays(camera)
    a, b, c = (np.asarray(x, np.float64) for x in (a, b, c))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    t = ((a - eye) @ n) / (d @ n)
    p = eye + t[..., None] * d
    # Barycentrics: p - a = u (b - a) + v (c - a), solved in the plane.
    e1, e2, w = b - a, c - a, p - a
    g = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
    rhs = np.stack([w @ e1, w @ e2], axis=-1)
    uv = np.linalg.solve(g, rhs[..., None])[..., 0]
    facing = np.where((d @ n)[..., None] < 0, n, -n)
    return p, uv[..., 0], uv[..., 1], t, facing


def lambert_point(albedo, intensity, colour, light, points, normals):
    to_light = np.asarray(light, np.float64) - points
    r2 = np.sum(to_light**2, axis=-1)
    cos = np.maximum(np.sum(normals * to_light, axis=-1) / np.sqrt(r2), 0.0)
    return (np.asarray(albedo) / math.pi) * intensity * np.asarray(colour) * (cos / r2)[..., None]


# --------------------------------------------------------------------------------------
# A triangle and a plane under a point light
# --------------------------------------------------------------------------------------

TRIANGLE_CASES = [
    # camera position, look_at, fov, (width, height), triangle corners, light position
    ((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), 60.0, (40, 30), [(-2, -1.5, 0), (2, -1.5, 0), (0, 2, 0)],
     (0.3, 0.5, 2.0)),
    ((1.0, 2.0, 4.0), (0.2, 0.1, -0.3), 45.0, (33, 41), [(-1.5, -1, 0.5), (2, -0.5, -1),
     (0, 2, -0.5)], (-1.0, 3.0, 2.5)),
    ((-2.0, 0.5, 3.0), (0.0, 0.0, 0.0), 39.5978, (48, 32), [(0, -2, -2), (0.5, -1.5, 2.5),
     (-0.3, 2.5, 0)], (1.0, 1.0, 1.0)),
]  # fmt: skip


@pytest.mark.parametrize("case", TRIANGLE_CASES)
def test_lambert_triangle_matches_closed_form(case):
    position, look_at, fov, (width, height), corners, light_position = case
    albedo, intensity, colour = (0.7, 0.3, 0.5), 30.0, (1.0, 0.9, 0.8)
    camera = render.Camera(position, look_at, fov=fov, width=width, height=height)
    mesh = render.Mesh(corners, [[0, 1, 2]], render.Material(albedo))
    scene = render.Scene([mesh], [render.PointLight(light_position, intensity, colour)], camera)
    image, info = render_centres(scene, return_info=True)

    p, u, v, t, normal = plane_hits(camera, *corners)
    inside = (u > 1e-6) & (v > 1e-6) & (1 - u - v > 1e-6) & (t > 0)
    outside = (u < -1e-6) | (v < -1e-6) | (1 - u - v < -1e-6) | (t < 0)
    hit = info.prim_id[..., 0] == 0
    assert inside.sum() > 0.15 * width * height  # a meaningful number of pixels
    assert hit[inside].all() and not hit[outside].any()
    assert (info.prim_id[..., 0][~hit] == -1).all()

    expected = lambert_point(albedo, intensity, colour, light_position, p, normal)
    np.testing.assert_allclose(image.data[hit], expected[hit], rtol=RTOL, atol=0)
    assert (image.data[~hit] == 0).all()  # black background


def test_lambert_plane_of_two_triangles_matches_closed_form():
    """The ground quad (two triangles sharing a diagonal) filling the lower part of the
    view; every ground pixel obeys the closed form, whichever triangle it hits."""
    camera = render.Camera((0.5, 2.0, 5.0), (0.0, 0.0, 0.0), fov=50, width=36, height=30)
    light = (1.0, 2.5, 1.5)
    scene = render.Scene(
        [ground_quad(size=4.0, material=render.Material((0.2, 0.5, 0.9)))],
        [render.PointLight(light, 12.0)],
        camera,
    )
    image, info = render_centres(scene, return_info=True)
    s = 4.0
    p, u, v, t, normal = plane_hits(camera, (-s, 0, s), (s, 0, s), (s, 0, -s))
    inside = (np.abs(p[..., 0]) < s - 1e-6) & (np.abs(p[..., 2]) < s - 1e-6) & (t > 0)
    hit = info.prim_id[..., 0] >= 0
    np.testing.assert_array_equal(hit, inside)  # no pixel near the quad's border here
    assert set(np.unique(info.prim_id[hit])) == {0, 1}
    expected = lambert_point((0.2, 0.5, 0.9), 12.0, (1, 1, 1), light, p, normal)
    np.testing.assert_allclose(image.data[hit], expected[hit], rtol=RTOL, atol=0)
    assert np.allclose(normal[hit], (0, 1, 0))


def test_smooth_shading_interpolates_vertex_normals():
    """smooth=True: the shading normal is the normalised barycentric blend of the vertex
    normals ((1 - u - v) n_a + u n_b + v n_c), given explicitly or, when not given, the
    normalised area-weighted sums of the face normals (computed here with NumPy)."""
    vertices = np.array([(-1.5, -1.0, 0.0), (1.5, -1.2, -0.6), (0.0, 1.4, 0.1), (1.8, 1.3, 0.8)])
    faces = np.array([[0, 1, 2], [1, 3, 2]])  # a bent "tent" of two triangles
    light, intensity = np.array([0.5, 1.0, 3.0]), 9.0
    camera = render.Camera((0.2, 0.1, 4.0), (0.1, 0, 0), fov=55, width=40, height=36)
    rng = np.random.default_rng(2)
    explicit = rng.uniform(-0.3, 0.3, (4, 3)) + (0, 0, 1.0)

    corners = vertices[faces]
    face_n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    computed = np.zeros((4, 3))
    for i in range(3):
        np.add.at(computed, faces[:, i], face_n)
    computed /= np.linalg.norm(computed, axis=1, keepdims=True)

    for given, vertex_normals in ((explicit, explicit), (None, computed)):
        mesh = render.Mesh(vertices, faces, render.Material((0.6, 0.5, 0.4)), normals=given,
                           smooth=True)  # fmt: skip
        scene = render.Scene([mesh], [render.PointLight(light, intensity)], camera)
        image, info = render_centres(scene, return_info=True)
        checked = 0
        for f in range(2):
            a, b, c = vertices[faces[f]]
            p, u, v, _, facing = plane_hits(camera, a, b, c)
            hit = info.prim_id[..., 0] == f
            n = ((1 - u - v)[..., None] * vertex_normals[faces[f, 0]]
                 + u[..., None] * vertex_normals[faces[f, 1]]
                 + v[..., None] * vertex_normals[faces[f, 2]])  # fmt: skip
            n /= np.linalg.norm(n, axis=-1, keepdims=True)
            n *= np.sign(np.sum(n * facing, axis=-1, keepdims=True))  # the geometric side
            expected = lambert_point((0.6, 0.5, 0.4), intensity, (1, 1, 1), light, p, n)
            np.testing.assert_allclose(image.data[hit], expected[hit], rtol=1e-9)
            checked += hit.sum()
        assert checked > 300


def test_textured_quad_matches_bilinear_closed_form():
    """A textured quad facing the camera under a head-on directional light: pixel =
    E * texture(uv) / pi, with uv from the analytic hit, bilinear between texel centres,
    uv (0, 0) at the bottom-left of the image, repeating outside [0, 1]."""
    rng = np.random.default_rng(3)
    texture = rng.uniform(0.1, 0.9, (3, 5, 3))
    corners = np.array([(-1.0, -1.0, 0.0), (1.0, -1.0, 0.0), (1.0, 1.0, 0.0), (-1.0, 1.0, 0.0)])
    uvs = np.array([(0, 0), (1, 0), (1, 1), (0, 1)], np.float64) * 1.5 - 0.2  # wraps
    camera = render.Camera((0.1, -0.2, 3.0), (0.0, 0.0, 0.0), fov=40, width=40, height=40)
    mesh = render.Mesh(corners, QUAD_FACES, render.Material((1, 1, 1), texture=texture), uvs=uvs)
    scene = render.Scene([mesh], [render.DirectionalLight((0, 0, -2.0), 2.5)], camera)
    image, info = render_centres(scene, return_info=True)
    hit = info.prim_id[..., 0] >= 0

    p, _, _, _, _ = plane_hits(camera, *corners[:3])
    s = (p[..., 0] + 1) / 2  # the quad's uvs are affine in x and y
    q = (p[..., 1] + 1) / 2
    uv = np.stack([s * 1.5 - 0.2, q * 1.5 - 0.2], axis=-1)
    height, width = texture.shape[:2]
    x = uv[..., 0] * width - 0.5
    y = (1 - uv[..., 1]) * height - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    i0, j0 = x0.astype(int) % width, y0.astype(int) % height
    i1, j1 = (i0 + 1) % width, (j0 + 1) % height
    sampled = (1 - fy) * ((1 - fx) * texture[j0, i0] + fx * texture[j0, i1]) + fy * (
        (1 - fx) * texture[j1, i0] + fx * texture[j1, i1]
    )
    assert hit.sum() > 400
    np.testing.assert_allclose(image.data[hit], (2.5 / math.pi) * sampled[hit], rtol=1e-9)


# --------------------------------------------------------------------------------------
# Spheres
# --------------------------------------------------------------------------------------


def projected_sphere_area(distance, radius, off_axis):
    """Area on the image plane at distance 1 of a sphere seen at angle ``off_axis`` from the
    optical axis: the ellipse cut by its tangent cone (half-angle alpha),
    pi sin^2(alpha) cos(alpha) / (cos^2(beta) - sin^2(alpha))^(3/2)."""
    sin_a = radius / distance
    cos_a = math.sqrt(1 - sin_a**2)
    return math.pi * sin_a**2 * cos_a / (math.cos(off_axis) ** 2 - sin_a**2) ** 1.5


@pytest.mark.parametrize(
    ("centre", "radius"),
    [((0.0, 0.0, 0.0), 1.0), ((0.0, 0.0, 0.0), 0.4), ((1.2, 0.7, 0.0), 0.6)],
)
def test_sphere_silhouette(centre, radius):
    """Hit pixels = pixels whose centre ray meets the sphere (independent ray-sphere test,
    away from the limb), and their count matches the analytic projected area."""
    camera = render.Camera((0, 0, 6.0), (0, 0, 0), fov=40, width=161, height=141)
    sphere = render.Sphere(centre, radius, render.Material((0.5, 0.5, 0.5)))
    scene = render.Scene([sphere], [render.PointLight((0, 5, 5), 10.0)], camera)
    _, info = render_centres(scene, return_info=True)
    hit = info.prim_id[..., 0] == 0

    d = camera_rays(camera)
    oc = camera.position.data - np.asarray(centre)
    b = d @ oc
    disc = b**2 - (oc @ oc - radius**2)  # d is unit
    assert (hit[disc > 1e-9]).all() and not hit[disc < -1e-9].any()

    to_centre = np.asarray(centre) - camera.position.data
    distance = np.linalg.norm(to_centre)
    off_axis = math.acos(-to_centre[2] / distance)
    pixel = 2 * math.tan(math.radians(40 / 2)) / 161
    expected = projected_sphere_area(distance, radius, off_axis) / pixel**2
    assert abs(hit.sum() - expected) < 0.02 * expected, (hit.sum(), expected)


def test_sphere_centre_pixel_radiance():
    """The centre pixel of an odd-sized image looks straight at the sphere's centre: it sees
    the point c - R f with normal -f. Diffuse + energy-normalised Blinn-Phong + ambient."""
    eye = np.array([1.0, 2.0, 4.0])
    centre = np.array([0.2, -0.1, 0.3])
    radius, albedo, ks, shininess, ambient = 0.8, np.array([0.6, 0.4, 0.2]), 0.35, 20.0, 0.03
    light, intensity, colour = np.array([2.0, 3.0, 1.0]), 25.0, np.array([1.0, 0.8, 0.6])
    camera = render.Camera(eye, centre, fov=30, width=31, height=21)
    material = render.Material(albedo, specular=ks, shininess=shininess, ambient=ambient)
    scene = render.Scene(
        [render.Sphere(centre, radius, material)],
        [render.PointLight(light, intensity, colour)],
        camera,
    )
    image = render_centres(scene).data

    f = (centre - eye) / np.linalg.norm(centre - eye)
    p, n = centre - radius * f, -f
    to_light = light - p
    r2 = to_light @ to_light
    l_dir = to_light / math.sqrt(r2)
    h = (l_dir - f) / np.linalg.norm(l_dir - f)  # view direction is -f
    brdf = albedo / math.pi + ks * (shininess + 8) / (8 * math.pi) * max(n @ h, 0) ** shininess
    expected = brdf * intensity * colour * max(n @ l_dir, 0) / r2 + ambient
    np.testing.assert_allclose(image[10, 15], expected, rtol=RTOL)


# --------------------------------------------------------------------------------------
# Directional light: the cosine law
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("theta", [0.0, 25.0, 60.0, 89.0, 120.0, 180.0])
def test_directional_light_cosine_law(theta):
    """A plane z = 0 facing the camera, lit by a directional light at angle theta from its
    normal: every pixel is E * albedo / pi * max(0, cos theta). Beyond 90 degrees the light
    is behind the plane (seen from the camera) and the plane is black."""
    albedo, irradiance, colour = np.array([0.8, 0.5, 0.3]), 2.0, np.array([1.0, 0.9, 0.7])
    th, phi = math.radians(theta), 0.7
    to_light = np.array([math.sin(th) * math.cos(phi), math.sin(th) * math.sin(phi), math.cos(th)])
    light = render.DirectionalLight(-2.5 * to_light, irradiance, colour)  # need not be unit
    camera = render.Camera((0.3, 0.2, 4.0), (0, 0, 0), fov=50, width=24, height=20)
    plane = render.Mesh(
        [(-9, -9, 0), (9, -9, 0), (9, 9, 0), (-9, 9, 0)], QUAD_FACES, render.Material(albedo)
    )
    image, info = render_centres(render.Scene([plane], [light], camera), return_info=True)
    assert (info.prim_id >= 0).all()  # the plane fills the view
    expected = irradiance * colour * albedo / math.pi * max(math.cos(th), 0.0)
    np.testing.assert_allclose(image.data, np.broadcast_to(expected, image.shape), rtol=1e-12)


# --------------------------------------------------------------------------------------
# Shadows
# --------------------------------------------------------------------------------------


def test_occluder_shadow_matches_geometry():
    """A small square occluder at height 1 over the ground: a ground pixel is dark exactly
    when the segment from its point to the light passes through the square (checked away
    from the shadow's edge), and has the closed-form value otherwise."""
    light = np.array([0.3, 4.0, 0.2])
    half, height = 0.5, 1.0
    occluder = render.Mesh(
        [(-half, height, half), (half, height, half), (half, height, -half),
         (-half, height, -half)],
        QUAD_FACES,
        render.Material((0.5, 0.5, 0.5)),
    )  # fmt: skip
    camera = render.Camera((0.0, 5.0, 4.0), (0, 0, 0), fov=55, width=48, height=48)
    scene = render.Scene(
        [ground_quad(size=3.0, material=render.Material((0.6, 0.6, 0.6))), occluder],
        [render.PointLight(light, 20.0)],
        camera,
    )
    image, info = render_centres(scene, return_info=True)
    on_ground = np.isin(info.prim_id[..., 0], (0, 1))
    lit = info.lit[0, ..., 0]

    p, _, _, _, normal = plane_hits(camera, (-3, 0, 3), (3, 0, 3), (3, 0, -3))
    q = light + (p - light) * ((light[1] - height) / light[1])  # where p -> light crosses y=1
    inner = np.maximum(np.abs(q[..., 0]), np.abs(q[..., 2]))
    shadowed, clear = inner < half - 0.02, inner > half + 0.02
    assert (on_ground & shadowed).sum() > 30  # the shadow is in view
    assert not lit[on_ground & shadowed].any()
    assert lit[on_ground & clear].all()
    assert (image.data[on_ground & ~lit] == 0).all()
    expected = lambert_point((0.6, 0.6, 0.6), 20.0, (1, 1, 1), light, p, normal)
    np.testing.assert_allclose(image.data[on_ground & lit], expected[on_ground & lit], rtol=RTOL)


@pytest.mark.parametrize("length", [1e-6, 1.0, 1e4, 1e7])
def test_directional_shadow_does_not_depend_on_the_direction_length(length):
    """``direction`` need not be unit length: its length must not change the shadows."""
    occluder = render.Mesh(
        [(-0.5, 0.3, 0.5), (0.5, 0.3, 0.5), (0.5, 0.3, -0.5), (-0.5, 0.3, -0.5)],
        QUAD_FACES,
        render.Material((0.5, 0.5, 0.5)),
    )
    camera = render.Camera((0.0, 5.0, 4.0), (0, 0, 0), fov=55, width=40, height=40)

    def shadowed(scale):
        light = render.DirectionalLight(np.array([1.0, -0.6, 0.2]) * scale, 1.0)
        scene = render.Scene([ground_quad(size=3.0), occluder], [light], camera)
        _, info = render_centres(scene, return_info=True)
        return np.isin(info.prim_id[..., 0], (0, 1)) & ~info.lit[0, ..., 0]

    reference = shadowed(1.0)
    assert reference.sum() > 20
    np.testing.assert_array_equal(shadowed(length), reference)


def test_light_outside_a_sphere_does_not_reach_its_inside():
    """Seen from inside, a sphere shadows itself (it is not convex from there)."""
    camera = render.Camera((0, 0, 0.2), (0, 0, -1), fov=90, width=16, height=16)
    sphere = render.Sphere((0, 0, 0), 2.0, render.Material((0.5, 0.5, 0.5)))
    scene = render.Scene([sphere], [render.PointLight((0, 0, 5.0), 5.0)], camera)
    image, info = render_centres(scene, return_info=True)
    assert (info.prim_id >= 0).all()
    assert not info.lit.any() and (image.data == 0).all()


@pytest.mark.parametrize(
    ("centre", "radius", "light"),
    [
        ((0.0, 0.0, 0.0), 1.0, render.PointLight((2.0, 1.5, 1.0), 10.0)),
        ((0.0, 0.0, 0.0), 1.0, render.DirectionalLight((-1.0, -0.2, -0.1), 1.0)),
        ((0.0, -1000.0, 0.0), 1000.0, render.PointLight((3.0, 0.2, -2.0), 10.0)),  # grazing
    ],
    ids=["point", "directional", "giant-ground-sphere"],
)
def test_no_shadow_acne_on_spheres(centre, radius, light):
    """Every sphere point that faces the light (analytic normal, cos > 1e-6) is lit: the
    shadow ray does not find the sphere it starts on."""
    camera = render.Camera((0.3, 1.0, 4.0), (0, 0, 0), fov=50, width=48, height=48)
    sphere = render.Sphere(centre, radius, render.Material((0.5, 0.5, 0.5)))
    image, info = render_centres(render.Scene([sphere], [light], camera), return_info=True)
    hit = info.prim_id[..., 0] == 0

    d = camera_rays(camera)
    oc = camera.position.data - np.asarray(centre)
    b = d @ oc
    t = -b - np.sqrt(np.maximum(b**2 - (oc @ oc - radius**2), 0))
    p = camera.position.data + t[..., None] * d
    n = (p - np.asarray(centre)) / radius
    if isinstance(light, render.PointLight):
        to_light = light.position.data - p
    else:
        to_light = np.broadcast_to(-light.direction.data, p.shape)
    cos = np.sum(n * to_light, axis=-1) / np.linalg.norm(to_light, axis=-1)
    facing = hit & (cos > 1e-6)
    assert facing.sum() > 100
    assert info.lit[0, ..., 0][facing].all()
    assert (image.data[facing] > 0).all()


def grid_plane(n, size, material):
    """A y = 0 square split into n x n cells (2 n^2 triangles sharing edges and vertices)."""
    xs = np.linspace(-size, size, n + 1)
    gx, gz = np.meshgrid(xs, xs)
    vertices = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1]
    faces = np.concatenate([np.stack([a, d.ravel(), c], 1), np.stack([a, c, b], 1)])
    return render.Mesh(vertices, faces, material)


@pytest.mark.parametrize(
    "light",
    [
        render.PointLight((0.5, 3.0, 0.5), 10.0),
        render.PointLight((9.0, 0.05, -7.0), 10.0),  # grazing: 0.3 degrees above the plane
        render.DirectionalLight((1.0, -0.01, 0.3), 1.0),  # grazing directional light
    ],
    ids=["point", "grazing-point", "grazing-directional"],
)
def test_no_shadow_acne_on_an_unoccluded_plane(light):
    """With nothing between the plane and the light every plane pixel is lit: no hit point
    shadows itself, nor is shadowed by a neighbouring triangle across a shared edge."""
    camera = render.Camera((0.7, 3.0, 4.0), (0, 0, 0), fov=60, width=48, height=40)
    material = render.Material((0.5, 0.5, 0.5))
    for plane in (ground_quad(size=3.0, material=material), grid_plane(12, 3.0, material)):
        for bvh in (True, False):
            image, info = render_centres(
                render.Scene([plane], [light], camera), bvh=bvh, return_info=True
            )
            hit = info.prim_id[..., 0] >= 0
            assert hit.sum() > 0.5 * hit.size
            assert info.lit[0][hit].all()
            assert (image.data[hit] > 0).all()


def uv_sphere_mesh(n_lat, n_lon, radius):
    """A convex polyhedron inscribed in a sphere (latitude-longitude grid, poles shared)."""
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack(
        [np.outer(np.sin(lat), np.cos(lon)), np.outer(np.cos(lat), np.ones(n_lon)),
         np.outer(np.sin(lat), np.sin(lon))], axis=-1,
    ).reshape(-1, 3)  # fmt: skip
    vertices = np.concatenate([[(0, 1, 0)], ring, [(0, -1, 0)]]) * radius
    top, bottom, faces = 0, len(vertices) - 1, []
    for j in range(n_lon):
        k = (j + 1) % n_lon
        faces.append((top, 1 + k, 1 + j))
        for i in range(n_lat - 2):
            a, b = 1 + i * n_lon + j, 1 + i * n_lon + k
            faces += [(a, b, b + n_lon), (a, b + n_lon, a + n_lon)]
        base = 1 + (n_lat - 2) * n_lon
        faces.append((bottom, base + j, base + k))
    return render.Mesh(vertices, np.array(faces), render.Material((0.5, 0.5, 0.5)))


def test_no_shadow_acne_on_a_convex_mesh():
    """On a convex polyhedron no face can shadow another face's point that faces the light,
    so every visible pixel with cos > 0 (flat normal) must be lit."""
    mesh = uv_sphere_mesh(16, 24, 1.0)
    light_position = np.array([2.0, 1.5, 1.0])
    camera = render.Camera((0.5, 0.8, 4.0), (0, 0, 0), fov=35, width=48, height=48)
    scene = render.Scene([mesh], [render.PointLight(light_position, 10.0)], camera)
    image, info = render_centres(scene, return_info=True)
    hit = info.prim_id[..., 0] >= 0
    corners = mesh.vertices.data[mesh.faces[info.prim_id[..., 0][hit]]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    facing_light = np.einsum("ij,ij->i", normal, light_position - corners[:, 0]) > 0
    assert facing_light.sum() > 200
    assert info.lit[0][hit][facing_light].all()
    assert (image.data[hit][facing_light] > 0).all()


# --------------------------------------------------------------------------------------
# The paper scene
# --------------------------------------------------------------------------------------


def test_paper_teapot_render():
    """512 x 512 teapot (docs/paper_scene.md): ~41k hit pixels (40,929 when written), finite,
    and the BVH and brute force give bit-identical images and visibility."""
    scene = render.paper_scene()
    image, info = render_centres(scene, return_info=True)
    hits = int((info.prim_id >= 0).sum())
    assert 40_000 <= hits <= 42_000, hits
    assert np.isfinite(image.data).all() and (image.data >= 0).all()
    assert image.shape == (512, 512, 3)
    assert (image.data[info.prim_id[..., 0] < 0] == 0).all()
    lit = info.lit[0, ..., 0] & (info.prim_id[..., 0] >= 0)
    assert 0.3 * hits < lit.sum() < hits  # self-shadowing happens, most is lit
    brute_image, brute_info = render_centres(scene, bvh=False, return_info=True)
    np.testing.assert_array_equal(brute_info.prim_id, info.prim_id)
    np.testing.assert_array_equal(brute_info.lit, info.lit)
    np.testing.assert_array_equal(brute_image.data, image.data)


# --------------------------------------------------------------------------------------
# Two-sided shading, samples per pixel, background, ambient
# --------------------------------------------------------------------------------------


def test_two_sided_shading():
    """A triangle seen from behind (winding away from the camera) is lit exactly like the
    same triangle seen from the front when the light is on the viewer's side; a light on the
    far side leaves both black."""
    corners = np.array([(-1.5, -1.0, 0.2), (1.5, -1.2, -0.2), (0.1, 1.5, 0.0)])
    camera = render.Camera((0.4, 0.3, 3.0), (0, 0, 0), fov=50, width=32, height=32)

    def draw(order, light):
        mesh = render.Mesh(corners[order], [[0, 1, 2]], render.Material((0.3, 0.6, 0.9)))
        scene = render.Scene([mesh], [render.PointLight(light, 8.0)], camera)
        return render_centres(scene, return_info=True)

    front, info = draw([0, 1, 2], (1.0, 1.0, 2.0))  # normal +z: towards the camera
    back, back_info = draw([0, 2, 1], (1.0, 1.0, 2.0))  # normal -z: seen from behind
    hit = info.prim_id[..., 0] == 0
    assert hit.sum() > 100 and (front.data[hit] > 0).all()
    np.testing.assert_array_equal(back_info.prim_id, info.prim_id)
    np.testing.assert_allclose(back.data, front.data, rtol=1e-12, atol=0)
    for order in ([0, 1, 2], [0, 2, 1]):
        dark, _ = draw(order, (1.0, 1.0, -2.0))  # light behind the triangle
        assert (dark.data == 0).all()


def test_four_samples_per_pixel_of_a_constant_region():
    """A plane filling the view under a directional light is one constant colour, so the
    mean of 4 samples equals the single centre sample."""
    plane = render.Mesh(
        [(-9, -9, 0), (9, -9, 0), (9, 9, 0), (-9, 9, 0)],
        QUAD_FACES,
        render.Material((0.8, 0.5, 0.3), ambient=0.01),
    )
    camera = render.Camera((0.3, 0.2, 4.0), (0, 0, 0), fov=50, width=24, height=20)
    scene = render.Scene([plane], [render.DirectionalLight((0.2, -0.3, -1.0), 2.0)], camera)
    one = render_centres(scene).data
    four = render_centres(scene, spp=4).data
    np.testing.assert_allclose(four, one, rtol=1e-14)
    np.testing.assert_allclose(one, np.broadcast_to(one[0, 0], one.shape), rtol=1e-14)


def test_four_samples_mix_object_and_background_by_coverage():
    """With spp = 4 an edge pixel is (hits * colour + misses * background) / 4: a constant
    (ambient-only) triangle over a coloured background."""
    background = np.array([0.1, 0.2, 0.3])
    colour = np.array([0.9, 0.4, 0.05])
    mesh = render.Mesh(
        [(-1, -1, 0), (1.2, -0.8, 0), (0.1, 1.1, 0)],
        [[0, 1, 2]],
        render.Material((0.5, 0.5, 0.5), ambient=colour),
    )
    camera = render.Camera((0, 0, 3.0), (0, 0, 0), fov=50, width=30, height=26)
    scene = render.Scene([mesh], [], camera, background=background)
    image, info = render_centres(scene, spp=4, return_info=True)
    coverage = (info.prim_id >= 0).mean(axis=-1)[..., None]
    assert ((coverage > 0) & (coverage < 1)).sum() > 20  # there are edge pixels
    expected = coverage * colour + (1 - coverage) * background
    np.testing.assert_allclose(image.data, expected, rtol=1e-14)


def test_background_fills_misses():
    background = (0.25, 0.5, 0.75)
    camera = render.Camera((0, 0, 5.0), (0, 0, 0), fov=40, width=20, height=16)
    empty = render_centres(render.Scene([], [], camera, background=background))
    np.testing.assert_array_equal(empty.data, np.broadcast_to(background, (16, 20, 3)))

    sphere = render.Sphere((0.3, 0, 0), 0.8, render.Material((0.5, 0.5, 0.5)))
    light = render.PointLight((1, 2, 4), 10.0)
    scene = render.Scene([sphere], [light], camera, background=background)
    image, info = render_centres(scene, return_info=True)
    miss = info.prim_id[..., 0] < 0
    assert 0 < miss.sum() < miss.size
    np.testing.assert_array_equal(
        image.data[miss], np.broadcast_to(background, image.data[miss].shape)
    )
    # Hit pixels carry no background: same as rendering over black.
    black = render_centres(render.Scene([sphere], [light], camera)).data
    np.testing.assert_array_equal(image.data[~miss], black[~miss])


@pytest.mark.parametrize("ambient", [0.07, (0.02, 0.05, 0.11)])
def test_ambient_adds_exactly_ambient(ambient):
    """Ambient radiance is added to the pixel (not scaled by albedo or lights), only where
    the material is seen; with no lights a pixel is exactly the ambient term."""
    camera = render.Camera((0.5, 1.5, 4.0), (0, 0.3, 0), fov=45, width=28, height=24)
    ground = ground_quad(size=2.0, material=render.Material((0.4, 0.5, 0.6)))

    def draw(amb, lights, spec=0.2):
        material = render.Material((0.6, 0.3, 0.2), specular=spec, ambient=amb)
        sphere = render.Sphere((0, 0.6, 0), 0.6, material)
        scene = render.Scene([ground, sphere], lights, camera, background=(0.1, 0.1, 0.1))
        return render_centres(scene, return_info=True)

    lights = [render.PointLight((2, 4, 3), 20.0), render.DirectionalLight((0, -1, -1), 1.0)]
    base, info = draw(0.0, lights)
    with_ambient, _ = draw(ambient, lights)
    on_sphere = info.prim_id[..., 0] == 2
    assert on_sphere.sum() > 30
    expected = base.data.copy()
    expected[on_sphere] += np.asarray(ambient)
    np.testing.assert_allclose(with_ambient.data, expected, rtol=1e-14, atol=1e-15)
    unlit, _ = draw(ambient, [])
    np.testing.assert_array_equal(
        unlit.data[on_sphere], np.broadcast_to(ambient, unlit.data[on_sphere].shape)
    )
    assert (unlit.data[~on_sphere & (info.prim_id[..., 0] >= 0)] == 0).all()  # ground: black


def test_stored_tensors_are_used_as_given():
    """Tensors passed to the scene are the ones rendered (and receive gradients)."""
    intensity = md.tensor(10.0, requires_grad=True)
    scene = render.Scene(
        [ground_quad(size=2.0)],
        [render.PointLight((0, 2, 0), intensity)],
        render.Camera((0, 2, 3), (0, 0, 0), width=8, height=8),
    )
    assert scene.lights[0].intensity is intensity
    image = render_centres(scene)
    image.sum().backward()
    np.testing.assert_allclose(intensity.grad, image.data.sum() / 10.0, rtol=1e-12)


def test_specular_and_ambient_maps_multiply_ks_and_ka():
    """map_Ks / map_Ka: a constant texture c renders as Ks * c / Ka * c without one."""
    scene = random_scene(4, lights=("point",), texture=True)
    material = scene.objects[0].material
    plain = render.render(scene).data
    material.specular_texture = md.tensor(np.ones((2, 3, 3)))
    material.ambient_texture = md.tensor(np.ones((4, 1, 3)))
    np.testing.assert_array_equal(render.render(scene).data, plain)
    c_s, c_a = np.array([0.5, 0.25, 1.0]), np.array([0.3, 0.6, 0.9])
    material.specular_texture = md.tensor(np.ones((2, 3, 3)) * c_s)
    material.ambient_texture = md.tensor(np.ones((4, 1, 3)) * c_a)
    textured = render.render(scene).data
    material.specular_texture = material.ambient_texture = None
    material.specular = md.tensor(material.specular.data * c_s)
    material.ambient = md.tensor(material.ambient.data * c_a)
    np.testing.assert_allclose(textured, render.render(scene).data, rtol=1e-12, atol=1e-15)
