"""Render-level gradient checks: the tape gradient of ``render`` vs. central finite differences.

For every kind of continuous scene parameter (lights, materials, textures, uvs, vertex
positions and normals, spheres, the camera, the background) we build a small random scene
(``render_helpers.random_scene``: a ground quad, a floating pyramid, a sphere, one or two
lights, a ~32 x 28 image, all positions drawn within sensible ranges), take the loss
``sum(image * W)`` for a fixed random weight image W, and compare its tape gradient with
central differences in float64, h = 1e-6 relative: D(h) = (loss(x + h) - loss(x - h)) / 2h
extrapolated to (4 D(h) - D(2h)) / 3 (fourth order; a ray grazing a sphere makes the O(h^2)
error of D(h) alone exceed the tolerance now and then, see ``masked_gradient_check``).
Parameters of more than ``DIRECTIONS_ABOVE`` scalars (a mesh's vertices) are differentiated
along 4 random directions instead of scalar by scalar: as sensitive to an error in any
scalar, in expectation (``masked_gradient_check``), for a fraction of the renders.
The error measure is the paper's Eq. 3, ``||g_ad - g_fd|| / (||g_fd|| + 1e-8)``, which must
stay below 1e-5; the finite-difference gradient must also be clearly non-zero, so that a
renderer that forgot a dependency cannot pass.

Why only pixels whose visibility does not change
------------------------------------------------
The image is a smooth function of the parameters only while the discrete visibility
decisions stay fixed: which primitive each camera ray hits, and whether each hit point sees
each light. The renderer computes those decisions with the BVH and treats them as constants
on the tape (``render.renderer``, steps 2-3); it differentiates the shading *given* the
visibility, and by design it does not model the jump a pixel makes when an edge or a shadow
boundary sweeps across its sample (that would need edge sampling / reparameterisation).
Finite differences, on the other hand, see that jump: a pixel that changes triangle or
shadow state between the +h and -h renders contributes ``jump / 2h`` to the difference
quotient, an arbitrarily large term that the tape gradient does not contain. Comparing such
pixels would test something the renderer does not claim to compute. So
``render_helpers.masked_gradient_check`` renders every perturbation with
``return_info=True`` and keeps only the pixels whose ``prim_id`` and ``lit`` (every sample,
every light) agree with the unperturbed render in *all* perturbed renders; W is zeroed
everywhere else, and the tape gradient is computed with that same masked W. (With
h = 1e-6 this rarely removes a pixel; ``test_masking_removes_exactly_the_visibility_jumps``
shows the effect with a large h.) The same holds for textures: bilinear filtering is smooth
only inside one texel cell, so the mask also requires every sample to keep its cell
(``RenderInfo.texel``).
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from tests.render_helpers import masked_gradient_check, random_scene


@pytest.fixture(autouse=True, scope="module")
def one_numba_thread():
    """These tests make thousands of 32 x 28 renders. At that size a parallel Numba kernel
    launch costs more than the work, and on a loaded machine much more (measured with 2
    cores under load: 75 ms per render with 2 threads, 3 ms with 1). Same results."""
    previous = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(previous)


TOLERANCE = 1e-5  # Eq. 3 relative error, float64
SEEDS = st.integers(0, 2**32 - 1)
FEW = settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])


#: Parameters with more scalars than this are checked along random directions (4 of them,
#: ``masked_gradient_check``): as sensitive in expectation, 4 x 4 renders instead of 4 each.
DIRECTIONS_ABOVE = 8


def assert_gradient_matches(scene, params, min_norm=1e-3, tolerance=TOLERANCE, **kwargs):
    if sum(p.data.size for p in params) > DIRECTIONS_ABOVE:
        kwargs.setdefault("directions", 4)
    result = masked_gradient_check(scene, params, **kwargs)
    # The mask must not hide the comparison: almost every pixel is compared.
    assert result.kept >= 0.9 * result.pixels, f"only {result.kept}/{result.pixels} pixels kept"
    norm = float(np.linalg.norm(result.g_fd))
    assert np.isfinite(result.g_ad).all()
    if norm <= min_norm:
        # A random scene where the parameters do not affect the image (e.g. a smooth
        # pyramid whose normals all face away from the light: ambient only). AD must agree
        # that the gradient vanishes; the example is then discarded as void, so that a pass
        # always means a non-trivial comparison (the fixed @example seeds are non-void).
        assert float(np.linalg.norm(result.g_ad)) <= min_norm, f"AD {result.g_ad}, FD ~0"
        assume(False)
    assert result.rel_error < tolerance, (
        f"relative error {result.rel_error:.3g}\n AD {result.g_ad}\n FD {result.g_fd}"
    )
    return result


# --------------------------------------------------------------------------------------
# One case per parameter type: (scene options, parameters to check)
# --------------------------------------------------------------------------------------


def materials(scene):
    return [obj.material for obj in scene.objects]


def ground(scene):
    return scene.objects[0]


def pyramid(scene):
    return scene.objects[1]


def sphere(scene):
    return scene.spheres[0]


def colour_specular(scene):
    """Make the sphere's specular coefficient an RGB (3,) tensor, the others stay scalar."""
    m = sphere(scene).material
    m.specular = md.tensor(np.full(3, float(m.specular.data)) * [1.0, 0.7, 0.4])
    return [mat.specular for mat in materials(scene)]


def rgb_ambient(scene):
    m = ground(scene).material
    m.ambient = md.tensor(np.full(3, float(m.ambient.data)) * [1.0, 0.5, 2.0])
    return [mat.ambient for mat in materials(scene)]


def explicit_normals(scene):
    """Give the smooth pyramid its own vertex normals: the area-weighted ones (so that they
    agree with the winding, which decides the side) perturbed and not of unit length."""
    mesh = pyramid(scene)
    corners = mesh.vertices.data[mesh.faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(mesh.vertices.data)
    for i in range(3):
        np.add.at(normals, mesh.faces[:, i], face_normals)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals += 0.3 * np.random.default_rng(0).standard_normal(normals.shape)
    mesh.normals = md.tensor(normals * np.linspace(0.5, 2.0, len(normals))[:, None])
    return [mesh.normals]


def specular_and_ambient_maps(scene):
    """Give the textured ground map_Ks and map_Ka textures of their own sizes."""
    m, rng = ground(scene).material, np.random.default_rng(5)
    m.specular_texture = md.tensor(rng.uniform(0.2, 1.0, (3, 4, 3)))
    m.ambient_texture = md.tensor(rng.uniform(0.2, 1.0, (5, 2, 3)))
    return [m.specular_texture, m.ambient_texture, m.specular, m.ambient]


def placed(obj, scene, quaternion=False):
    """Give ``obj`` a random Transform close to the identity (pivot near its centre), drawn
    from the scene's own random values, and return its four fields."""
    rng = np.random.default_rng(int(scene.camera.fov.data * 1e6))
    if quaternion:
        rotation = np.array([1.0, 0.0, 0.0, 0.0]) + rng.uniform(-0.2, 0.2, 4)
        rotation *= rng.uniform(0.5, 2.0)  # any non-zero length
    else:
        rotation = rng.uniform(-20.0, 20.0, 3)  # degrees
    centre = obj.vertices.data.mean(0) if isinstance(obj, render.Mesh) else obj.center.data
    obj.transform = render.Transform(
        rotation,
        rng.uniform(-0.15, 0.15, 3),
        rng.uniform(0.9, 1.1),
        centre + rng.uniform(-0.2, 0.2, 3),
    )
    t = obj.transform
    return [t.rotation, t.translation, t.scale, t.pivot]


POINT, DIRECTIONAL, BOTH = ("point",), ("directional",), ("point", "directional")

CASES = {
    "point_light_position": ({"lights": POINT}, lambda s: [s.lights[0].position]),
    "point_light_intensity": ({"lights": POINT}, lambda s: [s.lights[0].intensity]),
    "point_light_color": ({"lights": POINT}, lambda s: [s.lights[0].color]),
    "directional_light_direction": ({"lights": DIRECTIONAL}, lambda s: [s.lights[0].direction]),
    "directional_light_irradiance": (
        {"lights": DIRECTIONAL},
        lambda s: [s.lights[0].irradiance],
    ),
    "directional_light_color": ({"lights": DIRECTIONAL}, lambda s: [s.lights[0].color]),
    "albedo": ({"lights": BOTH}, lambda s: [m.albedo for m in materials(s)]),
    "specular": ({"lights": BOTH}, lambda s: [m.specular for m in materials(s)]),
    "specular_rgb": ({"lights": BOTH}, colour_specular),
    "shininess": ({"lights": BOTH}, lambda s: [m.shininess for m in materials(s)]),
    "ambient": ({"lights": POINT}, lambda s: [m.ambient for m in materials(s)]),
    "ambient_rgb": ({"lights": POINT}, rgb_ambient),
    "texture_texels": ({"lights": BOTH, "texture": True}, lambda s: [ground(s).material.texture]),
    "uvs": ({"lights": POINT, "texture": True}, lambda s: [ground(s).uvs]),
    "specular_ambient_textures": ({"lights": BOTH, "texture": True}, specular_and_ambient_maps),
    "vertices_flat": ({"lights": BOTH}, lambda s: [pyramid(s).vertices]),
    "vertices_flat_ground": ({"lights": POINT, "pyramid": False}, lambda s: [ground(s).vertices]),
    "vertices_smooth": (
        {"lights": BOTH, "smooth": True},  # normals computed from the vertices, on the tape
        lambda s: [pyramid(s).vertices],
    ),
    "vertex_normals": ({"lights": BOTH, "smooth": True}, explicit_normals),
    "vertices_smooth_explicit_normals": (
        {"lights": POINT, "smooth": True},
        lambda s: [*explicit_normals(s), pyramid(s).vertices],
    ),
    "sphere_center": ({"lights": BOTH}, lambda s: [sphere(s).center]),
    "sphere_radius": ({"lights": BOTH}, lambda s: [sphere(s).radius]),
    "camera_position": ({"lights": POINT}, lambda s: [s.camera.position]),
    "camera_look_at": ({"lights": POINT}, lambda s: [s.camera.look_at]),
    "camera_up": ({"lights": POINT}, lambda s: [s.camera.up]),
    "camera_fov": ({"lights": POINT}, lambda s: [s.camera.fov]),
    "background": ({"lights": POINT}, lambda s: [s.background]),
    "transform_rotation_vector": ({"lights": BOTH}, lambda s: placed(pyramid(s), s)),
    "transform_quaternion_smooth": (
        {"lights": POINT, "smooth": True},
        lambda s: placed(pyramid(s), s, quaternion=True),
    ),
    "transform_with_vertices_and_normals": (
        {"lights": POINT, "smooth": True},
        lambda s: [*explicit_normals(s), pyramid(s).vertices, *placed(pyramid(s), s)[:2]],
    ),
    "transform_sphere": ({"lights": BOTH}, lambda s: placed(sphere(s), s)),
}


@pytest.mark.parametrize("case", list(CASES))
@FEW
@given(seed=SEEDS)
@example(seed=0)
def test_gradient_matches_finite_differences(case, seed):
    options, params = CASES[case]
    scene = random_scene(seed, **options)
    assert_gradient_matches(scene, params(scene))


@settings(FEW, max_examples=2)
@given(seed=SEEDS)
@example(seed=1)
@example(seed=6636)
def test_gradient_with_four_samples_per_pixel(seed):
    """spp = 4: the pixel is the mean of four sub-pixel rays, each with its own visibility
    (the mask requires all four to keep theirs); the background enters through the miss
    fraction of edge pixels.

    The camera moves over the textured ground, which slides the UVs across texel cells:
    bilinear interpolation has a kink at every cell boundary, and a sample within h of one
    makes the finite difference average two slopes. Seed 6636 did exactly that (the AD
    derivative of the offending pixel equalled the finite difference at h = 1e-7 and
    differed at h = 1e-6), which is why ``RenderInfo.texel`` exists and the mask uses it.
    """
    scene = random_scene(seed, lights=BOTH, texture=True)
    params = [
        scene.lights[0].position,
        pyramid(scene).vertices,
        sphere(scene).radius,
        ground(scene).material.texture,
        scene.background,
        scene.camera.position,
    ]
    assert_gradient_matches(scene, params, spp=4)


def test_texel_cell_changes_are_masked():
    """The two failures hypothesis found (a camera move at spp = 4, a UV move at spp = 1)
    came from samples crossing a texel cell boundary. With a step large enough to cross
    many boundaries, comparing every pixel fails and the texel-aware mask repairs it."""
    scene = random_scene(43653231, lights=POINT, texture=True)
    params = [ground(scene).uvs]
    masked = masked_gradient_check(scene, params, h_rel=1e-4)
    assert masked.kept < masked.pixels  # some samples changed cell
    assert masked.rel_error < 1e-5
    unmasked = masked_gradient_check(scene, params, h_rel=1e-4, mask=False)
    assert unmasked.rel_error > 1e-3


@pytest.mark.parametrize("bvh", [True, False])
def test_gradient_without_shadows_and_with_brute_force(bvh):
    """The other render switches do not change the differentiable part."""
    scene = random_scene(7, lights=BOTH)
    params = [scene.lights[0].position, pyramid(scene).vertices, scene.camera.look_at]
    assert_gradient_matches(scene, params, bvh=bvh, shadows=False, reuse_visibility=False)


def test_masking_removes_exactly_the_visibility_jumps():
    """With a large step, moving the pyramid makes some pixels change triangle or shadow
    state. Without the mask their jumps dominate the difference quotient (and the check
    fails); with it, the remaining pixels agree with the tape gradient."""
    scene = random_scene(3, lights=POINT)
    params = [pyramid(scene).vertices]
    masked = masked_gradient_check(scene, params, h_rel=1e-3)
    assert masked.kept < masked.pixels  # the step is large enough to move edges/shadows
    assert masked.rel_error < 1e-4  # only the truncation error of the large step

    unmasked = masked_gradient_check(scene, params, h_rel=1e-3, mask=False)
    assert unmasked.rel_error > 1e-2


def test_visibility_cache_sees_in_place_edits():
    """The finite differences above perturb ``tensor.data`` in place and rely on the
    visibility cache noticing. Check that directly: after an in-place move of the light,
    the camera and the vertices, the cached render equals a render from scratch."""
    scene = random_scene(5, lights=POINT)
    _, before = render.render(scene, return_info=True)
    edits = [
        (scene.lights[0].position, (0, 1.5)),
        (scene.camera.position, (0, 0.4)),
        (pyramid(scene).vertices, ((0, 1), 0.3)),
        (sphere(scene).center, (2, -0.5)),
    ]
    for tensor, (index, delta) in edits:
        tensor.data[index] += delta
        cached_image, cached = render.render(scene, return_info=True)
        fresh_image, fresh = render.render(scene, return_info=True, reuse_visibility=False)
        np.testing.assert_array_equal(cached.prim_id, fresh.prim_id)
        np.testing.assert_array_equal(cached.lit, fresh.lit)
        np.testing.assert_array_equal(cached_image.data, fresh_image.data)
        assert not (
            np.array_equal(cached.prim_id, before.prim_id)
            and np.array_equal(cached.lit, before.lit)
        ), "the edit should have changed the visibility"
        before = cached


def test_surface_cache_sees_every_edit():
    """While nothing that moves the geometry requires grad, ``render`` reuses each object's
    hit points, normals and UVs (``renderer._cached_surface``). Every edit that changes
    them must be seen: in-place edits of normals, UVs, vertices and the camera, switching
    smooth shading or the texture, and a grad-requiring vertex tensor (recomputed on the
    tape, with a gradient)."""
    scene = random_scene(11, lights=BOTH, smooth=True, texture=True)
    mesh = pyramid(scene)
    explicit_normals(scene)  # the pyramid gets its own vertex normals

    def check(label):
        cached = render.render(scene).data
        fresh = render.render(scene, reuse_visibility=False).data
        np.testing.assert_array_equal(cached, fresh, err_msg=label)
        return cached

    before = check("first render")
    edits = [
        ("normals", lambda: mesh.normals.data.__setitem__((0, 0), 0.7)),
        ("uvs", lambda: ground(scene).uvs.data.__setitem__((0, 1), 0.35)),
        ("vertices", lambda: mesh.vertices.data.__setitem__((0, 1), 0.2)),
        ("camera", lambda: scene.camera.look_at.data.__setitem__(0, 0.05)),
        ("smooth off", lambda: setattr(mesh, "smooth", False)),
        ("texture off", lambda: setattr(ground(scene).material, "texture", None)),
    ]
    for label, edit in edits:
        edit()
        after = check(label)
        assert not np.array_equal(after, before), f"the edit of {label} changed nothing"
        before = after

    light = scene.lights[0].position
    light.requires_grad = True  # the surfaces stay cached: only the light is differentiated
    render.render(scene).sum().backward()
    assert light.grad is not None and np.any(light.grad)
    mesh.vertices.requires_grad = True  # now the pyramid's surface must be on the tape
    render.render(scene).sum().backward()
    assert mesh.vertices.grad is not None and np.any(mesh.vertices.grad)


# --------------------------------------------------------------------------------------
# float32
# --------------------------------------------------------------------------------------


def float32_scene(seed):
    """A random scene whose differentiable parameters are float32 tensors."""
    scene = random_scene(seed, lights=POINT)
    light, mesh = scene.lights[0], pyramid(scene)
    light.position = md.tensor(light.position.data.astype(np.float32))
    light.intensity = md.tensor(light.intensity.data.astype(np.float32))
    mesh.vertices = md.tensor(mesh.vertices.data.astype(np.float32))
    mesh.material.albedo = md.tensor(mesh.material.albedo.data.astype(np.float32))
    scene.validate()
    return scene, [light.position, light.intensity, mesh.vertices, mesh.material.albedo]


def test_float32_parameters_end_to_end():
    """float32 leaves render, get float32 gradients, and those match finite differences.

    What happens: the parts computed from float32 leaves (triangle edges and normals from
    float32 vertices) run in float32, so the image carries float32 rounding (~6e-8
    relative). The step is therefore
    1e-3 relative, and the plain central difference is used (Richardson's extrapolation
    amplifies that rounding). Measured on 12 seeds: median 3e-5, worst 2.3e-4; the tolerance
    is the 1e-3 that ``minidiff.check_grad`` documents for float32 (float64 tests: 1e-5).
    """
    scene, params = float32_scene(11)
    image = render.render(scene)
    assert np.isfinite(image.data).all()
    assert_gradient_matches(scene, params, h_rel=1e-3, order=2, tolerance=1e-3)
    for p in params:
        p.requires_grad = True
    render.render(scene).sum().backward()
    assert all(p.grad.dtype == np.float32 and np.isfinite(p.grad).all() for p in params)


def test_all_float32_scene_renders_a_float32_image():
    """With every parameter float32 (Scene.parameters() lists them all, uvs included), the
    image and the gradients stay float32; one float64 parameter promotes the image."""
    scene = random_scene(11, lights=POINT, sphere=False)
    for t in scene.parameters():
        t.data = t.data.astype(np.float32)
    scene.validate()
    position = scene.lights[0].position
    position.requires_grad = True
    image = render.render(scene)
    image.sum().backward()
    assert position.grad.dtype == np.float32
    scene.meshes[0].uvs.data = scene.meshes[0].uvs.data.astype(np.float64)
    assert render.render(scene).dtype == np.float64
    scene.meshes[0].uvs.data = scene.meshes[0].uvs.data.astype(np.float32)
    assert render.render(scene).dtype == np.float32


def test_random_directions_are_the_projections_of_the_scalar_by_scalar_check():
    """``directions=k`` compares derivatives along k directions: they are the per-scalar
    finite differences projected on those directions, and so are the tape's."""
    scene = random_scene(3)
    params = [pyramid(scene).vertices]
    each = masked_gradient_check(scene, params)
    along = masked_gradient_check(scene, params, directions=3)
    assert len(along.g_fd) == 3 and len(each.g_fd) == params[0].data.size
    assert along.rel_error < TOLERANCE and each.rel_error < TOLERANCE
    n = params[0].data.size
    np.testing.assert_allclose(each.directions, np.eye(n), rtol=0, atol=1e-9)  # one at a time
    u = along.directions
    assert u.shape == (3, n) and np.all(np.count_nonzero(u, axis=1) == n)  # every scalar moves
    np.testing.assert_allclose(
        along.g_fd, u @ each.g_fd, rtol=1e-6, atol=1e-9 * np.abs(each.g_fd).max()
    )
    np.testing.assert_allclose(
        along.g_ad, u @ each.g_ad, rtol=1e-9, atol=1e-12 * np.abs(each.g_ad).max()
    )
