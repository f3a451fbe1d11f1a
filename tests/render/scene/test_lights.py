"""Tests for render.scene.lights: what each light answers, on the tape and on plain arrays."""

import math

import numpy as np
import pytest

import minidiff as md
from render.scene.lights import DIRECTIONAL, POINT, DirectionalLight, Light, PointLight

RNG = np.random.default_rng(7)
POINTS = RNG.normal(size=(6, 3))
V_I, V_J = RNG.normal(size=(6, 3)), RNG.normal(size=(6, 3))
LIGHTS = [
    PointLight((0.3, 4.0, -1.0), 10.0, (1.0, 0.5, 0.25)),
    DirectionalLight((0.2, -3.0, 0.4), 2.0),
]


def test_light_is_abstract():
    with pytest.raises(TypeError):
        Light()


@pytest.mark.parametrize("light", LIGHTS, ids=["point", "directional"])
def test_tape_and_plain_are_one_formula(light):
    """towards, edge_plane and ray_to give the same values on tensors and on arrays."""
    points, v_i, v_j = md.tensor(POINTS), md.tensor(V_I), md.tensor(V_J)
    np.testing.assert_array_equal(light.towards(points).data, light.towards(POINTS))
    for tape, plain in zip(light.edge_plane(v_i, v_j), light.edge_plane(V_I, V_J), strict=True):
        np.testing.assert_array_equal(np.broadcast_to(tape.data, plain.shape), plain)
    for tape, plain in zip(light.ray_to(points), light.ray_to(POINTS), strict=True):
        np.testing.assert_array_equal(tape.data, plain)


@pytest.mark.parametrize("light", LIGHTS, ids=["point", "directional"])
def test_edge_plane_holds_the_edge_and_the_light(light):
    """The plane through the edge contains both ends, and the light's rays along it: for a
    point light the light itself, for a directional light every point plus the direction."""
    m, base = light.edge_plane(V_I, V_J)
    for p in (V_I, V_J):
        assert np.allclose(np.sum(m * (p - base), axis=1), 0.0, atol=1e-12)
    if light.KIND == POINT:
        assert np.allclose(np.sum(m * (light.location() - base), axis=1), 0.0, atol=1e-12)
    else:
        assert np.allclose(m @ light.direction.data, 0.0, atol=1e-12)


def test_incidence_point_light_inverse_square():
    light = LIGHTS[0]
    to_light, irradiance = light.incidence(md.tensor(POINTS))
    offset = light.position.data - POINTS
    r2 = np.sum(offset**2, axis=1)
    np.testing.assert_allclose(to_light.data, offset / np.sqrt(r2)[:, None], rtol=1e-14)
    np.testing.assert_allclose(irradiance.data, 10.0 / r2, rtol=1e-14)
    # A light on the surface: no 0/0 (the direction is zero, the contribution too).
    _, at_light = light.incidence(md.tensor(light.position.data[None]))
    assert np.isfinite(at_light.data).all()


def test_incidence_directional_light():
    light = LIGHTS[1]
    to_light, irradiance = light.incidence(md.tensor(POINTS))
    w = light.direction.data
    np.testing.assert_allclose(to_light.data, -w / np.linalg.norm(w), rtol=1e-15)
    assert float(irradiance.data) == 2.0


def test_incidence_differentiates_the_light():
    position = md.tensor(np.array([0.3, 4.0, -1.0]), requires_grad=True)
    light = PointLight(position, 10.0)
    _, irradiance = light.incidence(md.tensor(POINTS))
    md.sum(irradiance).backward()
    offset = position.data - POINTS
    r2 = np.sum(offset**2, axis=1)
    expected = np.sum(-20.0 * offset / r2[:, None] ** 2, axis=0)
    np.testing.assert_allclose(position.grad, expected, rtol=1e-12)


def test_shadow_rays_end_at_the_light_or_never():
    point, directional = LIGHTS
    origins, directions, tmax = point.shadow_rays(POINTS, 1e-6)
    assert point.shadow_ray_end == 1.0 and directional.shadow_ray_end == math.inf
    # Unnormalised directions to the light: origin + 1 * direction is the light.
    np.testing.assert_allclose(origins + directions, np.broadcast_to(point.location(), (6, 3)))
    assert np.all((tmax > 0.99) & (tmax < 1.0))
    origins, directions, tmax = directional.shadow_rays(POINTS, 1e-6)
    w = directional.direction.data
    np.testing.assert_allclose(directions, np.broadcast_to(-w / np.linalg.norm(w), (6, 3)))
    np.testing.assert_allclose(origins - POINTS, 1e-6 * directions)
    assert tmax == np.inf and directional.location() is None


def test_keys_and_packs_name_the_kind():
    point, directional = LIGHTS
    assert point.shadow_key()[1][0] == 0.0 and directional.shadow_key()[1][0] == 1.0
    key = point.shadow_key()[0]
    key[0] = 99.0  # a copy: the light is unchanged
    assert point.position.data[0] == 0.3
    assert point.pack()[0] == POINT and directional.pack()[0] == DIRECTIONAL
    w = directional.direction.data
    np.testing.assert_array_equal(directional.pack()[1], w)
    np.testing.assert_array_equal(directional.pack(unit=True)[1], w / np.linalg.norm(w))
    kind, vec, strength = directional.shading_pack()
    assert kind == DIRECTIONAL and float(strength) == 2.0
    np.testing.assert_allclose(vec, -w / np.linalg.norm(w), rtol=1e-15)
    assert point.shading_pack()[0] == POINT and float(point.shading_pack()[2]) == 10.0


@pytest.mark.parametrize("light", LIGHTS, ids=["point", "directional"])
def test_sphere_outline_is_where_the_light_grazes(light):
    """Every point of the outline circle lies on the sphere, and the light's ray to it is
    tangent there (perpendicular to the radius)."""
    centre, radius = np.array([0.5, 0.0, 0.2]), 0.7
    circle, u1, u2 = light.sphere_outline(centre, radius)
    for phi in np.linspace(0.0, 2.0 * math.pi, 7):
        s = circle + math.cos(phi) * u1 + math.sin(phi) * u2
        assert abs(np.linalg.norm(s - centre) - radius) < 1e-12
        _, direction = light.ray_to(s[None])
        assert abs(float(np.sum(direction * (s - centre)))) < 1e-12


def test_sphere_outline_light_inside():
    assert PointLight((0.0, 0.0, 0.0), 1.0).sphere_outline(np.zeros(3), 1.0) is None


class HalfLight(PointLight):
    """A new light type defined here only: a point light at half its intensity, shaded on
    the tape (no compiled kernel knows it)."""

    compiled_shading = False

    def incidence(self, points):
        to_light, irradiance = super().incidence(points)
        return to_light, irradiance * 0.5


def test_a_new_light_type_needs_only_its_class():
    """A light type the renderer has never seen renders (shadows, shading, the cache) and
    differentiates through its own ``incidence``, with every other method inherited."""
    from render.renderer import render
    from render.scene.teapot import paper_scene
    from render.shade import compiled

    scene = paper_scene(24, 24, ground=True)
    with md.no_grad():
        full = render(scene).data
    light = scene.lights[0]
    half = HalfLight(md.tensor(light.position.data.copy(), requires_grad=True), light.intensity)
    scene.lights[0] = half
    with md.no_grad():  # nothing differentiated, yet the compiled pass does not know it
        assert not compiled.applies(scene, scene.objects[0], reflects=False)
    image = render(scene)
    np.testing.assert_allclose(image.data, full * 0.5, rtol=1e-12, atol=1e-15)
    md.sum(image).backward()
    assert np.any(half.position.grad != 0.0)
