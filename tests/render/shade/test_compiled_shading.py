"""``render.shade.compiled`` computes what the tape code computes: ``shade_mesh_values``
against ``surface_at`` + ``shade_surface`` on random meshes, materials (every texture,
flat and smooth, emission) and lights, and whole renders with nothing differentiated (the
compiled pass) against the same renders on the tape.

Bit for bit where no Blinn-Phong lobe is computed; with one, NumPy's vectorised ``power``
and the C library's ``pow`` may round the last bit differently, so the check is then to a
few ulps of the largest value."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.scene.camera import camera_directions, camera_frame
from render.shade import compiled
from render.shade.lighting import shade_surface
from render.shade.surface import surface_at
from tests.render_helpers import random_scene

#: Where a lobe is computed: a few ulps of the largest value compared.
ULPS = 8 * np.finfo(np.float64).eps


def _mesh(rng, smooth: bool, normals: bool, maps: tuple[bool, bool, bool], specular: bool):
    vertices = rng.uniform(-1.0, 1.0, (7, 3)) + np.array([0.0, 0.0, 4.0])
    faces = np.array([rng.choice(7, 3, replace=False) for _ in range(9)])
    texture, specular_map, ambient_map = (
        rng.uniform(0.0, 1.0, (int(rng.integers(1, 5)), int(rng.integers(1, 5)), 3)) if on else None
        for on in maps
    )
    material = render.Material(
        rng.uniform(0.1, 0.9, 3),
        specular=rng.uniform(0.0, 0.5, 3) if specular else 0.0,
        shininess=rng.uniform(1.0, 60.0),
        ambient=rng.uniform(0.0, 0.1),
        texture=texture,
        specular_texture=specular_map,
        ambient_texture=ambient_map,
        emission=rng.uniform(0.0, 0.3, 3) if rng.uniform() < 0.5 else 0.0,
    )
    return render.Mesh(
        vertices, faces, material,
        normals=rng.normal(size=(7, 3)) if normals else None,
        uvs=rng.uniform(-1.5, 2.5, (7, 2)) if any(maps) else None,
        smooth=smooth,
    )  # fmt: skip


def _lights(rng, kinds):
    lights = []
    for kind in kinds:
        colour = rng.uniform(0.5, 1.0, 3)
        if kind == "point":
            lights.append(render.PointLight(rng.uniform(-3, 3, 3), rng.uniform(1, 20), colour))
        else:
            lights.append(render.DirectionalLight(rng.normal(size=3), rng.uniform(0.5, 3), colour))
    return lights


def _assert_same(now, tape, bitwise: bool):
    if bitwise:
        np.testing.assert_array_equal(now, tape)
    else:
        np.testing.assert_allclose(now, tape, rtol=0, atol=ULPS * np.abs(tape).max())


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    smooth=st.booleans(),
    normals=st.booleans(),
    maps=st.tuples(st.booleans(), st.booleans(), st.booleans()),
    specular=st.booleans(),
    kinds=st.lists(st.sampled_from(["point", "directional"]), max_size=3),
)
def test_shade_mesh_values_equals_surface_at_then_shade_surface(
    seed, smooth, normals, maps, specular, kinds
):
    rng = np.random.default_rng(seed)
    mesh = _mesh(rng, smooth, normals and smooth, maps, specular)
    lights = _lights(rng, kinds)
    k = 50
    faces_hit = rng.integers(0, mesh.num_faces, k)
    coords = rng.uniform(-0.4, 0.4, (k, 2))
    camera = render.Camera([0.1, -0.2, 0.0], [0.0, 0.1, 4.0], [0.0, 1.0, 0.0], 45.0, 16, 16)
    frame = camera_frame(camera)
    lit = [rng.uniform(size=k) < 0.7 for _ in lights]

    colour, texel = compiled.shade_mesh_values(
        mesh, faces_hit, [t.data for t in frame], coords, lights, lit
    )
    with md.no_grad():
        forward, right, up, eye = frame
        directions = md.tensor(camera_directions(coords, right.data, up.data, forward.data))
        surface = surface_at(mesh, faces_hit, eye, directions)
        tape, cells = shade_surface(surface, mesh.material, lights, [m * 1.0 for m in lit])
    _assert_same(colour, tape.data, bitwise=not (specular and lights))
    np.testing.assert_array_equal(texel, cells)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize(
    "options",
    [
        dict(lights=("point", "directional"), texture=True, smooth=True),
        dict(lights=("directional",)),
        dict(lights=("point",), smooth=True, sphere=False),
    ],
)
@pytest.mark.parametrize("specular", [True, False])
def test_a_render_nothing_differentiates_equals_the_same_render_on_the_tape(
    seed, options, specular
):
    scene = random_scene(seed, **options)
    if not specular:
        for obj in scene.objects:
            obj.material.specular.data[...] = 0.0
    plain, info = render.render(scene, reuse_visibility=False, return_info=True)
    for p in scene.parameters():
        p.requires_grad = True
    taped, taped_info = render.render(scene, reuse_visibility=False, return_info=True)
    assert taped.node is not None  # the tape code ran
    _assert_same(plain.data, taped.data, bitwise=not specular)
    np.testing.assert_array_equal(info.texel, taped_info.texel)


def test_a_mirror_takes_the_tape_code_and_what_it_shows_the_compiled_pass():
    """A reflective ground (its mirror rays need the tape code's Hits) beside meshes the
    compiled pass shades, under no_grad: the same image as on the tape, bit for bit."""
    scene = random_scene(4, lights=("point", "directional"))
    scene.objects[0].material.reflectance = md.tensor(0.6)
    for obj in scene.objects:
        obj.material.specular.data[...] = 0.0
    with md.no_grad():
        plain = render.render(scene, reuse_visibility=False)
    for p in scene.parameters():
        p.requires_grad = True
    taped = render.render(scene, reuse_visibility=False)
    assert taped.node is not None
    np.testing.assert_array_equal(plain.data, taped.data)


def test_applies_only_where_nothing_needs_the_tape():
    scene = random_scene(0)  # a ground quad, a pyramid, a sphere
    quad, _, sphere = scene.objects
    assert compiled.applies(scene, quad, reflects=False)
    assert not compiled.applies(scene, quad, reflects=True)  # mirror rays: the tape code
    assert not compiled.applies(scene, sphere, reflects=False)
    for owner in (scene.camera, quad, quad.material, scene.lights[0]):
        tensor = next(iter(owner.named_parameters().values()))
        tensor.requires_grad = True
        assert not compiled.applies(scene, quad, reflects=False)
        with md.no_grad():  # values only (the edge terms' shading)
            assert compiled.applies(scene, quad, reflects=False)
        tensor.requires_grad = False
    single = random_scene(0)
    single.objects[0].vertices = md.tensor(single.objects[0].vertices.data.astype(np.float32))
    assert not compiled.applies(single, single.objects[0], reflects=False)


@pytest.mark.parametrize("scale", [1e100, -1e300, 1e15 + 0.25])
def test_huge_texture_coordinates_give_the_tape_codes_image(scale):
    """UVs far beyond [0, 1] repeat the texture on both paths. The compiled lookup took
    Numba's math.floor, an int64, which 1e100 overflowed: the image's maximum was 1.2e201
    where the tape gave 0.76."""
    quad = np.array([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    uvs = np.array([[0.0, 0.0], [1, 0], [1, 1], [0, 1]]) * scale
    texture = np.random.default_rng(2).uniform(0.0, 1.0, (4, 5, 3))
    material = render.Material(albedo=(1.0, 1.0, 1.0), texture=texture)
    mesh = render.Mesh(quad, [[0, 1, 2], [0, 2, 3]], material, uvs=uvs)
    camera = render.Camera((0.2, 0.1, 3.0), (0, 0, 0), width=12, height=10)
    scene = render.Scene([mesh], [render.PointLight((1.0, 2.0, 4.0), 20.0)], camera)
    with md.no_grad():
        plain = render.render(scene, reuse_visibility=False)
    mesh.vertices.requires_grad = True
    taped = render.render(scene, reuse_visibility=False)
    assert taped.node is not None
    assert np.all(np.isfinite(plain.data)) and plain.data.max() < 10.0
    np.testing.assert_allclose(plain.data, taped.data, rtol=1e-12, atol=0)
