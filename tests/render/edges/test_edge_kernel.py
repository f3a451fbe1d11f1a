"""The mesh edges' compiled factors (``render.edges.boundary.edge_kernel``) are the
reference's (``_edge_factors(..., compiled=False)``: NumPy and ``DirectRadiance``): every
call of a render's boundary term computes both and compares them, on the paper teapot
(alone and on the ground, in its shadow), two meshes under a directional and a point
light, a flat-shaded and a textured box, meshes that share edges, and a sphere that some
of the rays beside an edge hit (those points are left to the reference). Where the kernel
does not apply (a mirror, a light it cannot shade, float32) the reference runs alone.
The whole gradient is the reference's, and the same on one and two threads."""

from __future__ import annotations

import functools

import numpy as np
import pytest

import minidiff as md
from render import (
    Camera,
    DirectionalLight,
    Material,
    Mesh,
    PointLight,
    Scene,
    Sphere,
    render,
)
from render.edges.boundary import edge_kernel, mesh_edge
from render.scene.cornell import box_mesh
from render.scene.teapot import paper_scene
from tests.render.edges.test_shared_edges import _scene as shared_scene
from tests.render_helpers import same_bits_on_one_and_two_threads

SIZE = 64


def _teapot(ground: bool) -> Scene:
    """The paper teapot, its light and vertices differentiated."""
    light = md.tensor([2.0, 5.0, 3.0], requires_grad=True)
    scene = paper_scene(SIZE, SIZE, light, ground=ground)
    mesh = scene.meshes[0]
    mesh.vertices = md.tensor(mesh.vertices.data, requires_grad=True)
    return scene


def _two_lights() -> Scene:
    """The teapot on the ground under a directional light beside the point light."""
    scene = _teapot(ground=True)
    scene.lights.append(DirectionalLight((-0.4, -1.0, -0.3), 0.8, color=(1.0, 0.9, 0.7)))
    return scene


def _boxes(textured: bool, lit: bool = True) -> Scene:
    """A flat-shaded box (specular, emissive) on a second box, seen from above, before a
    coloured background; with ``textured`` the top box has all three texture maps; without
    ``lit`` no light (ambient and emitted light alone)."""
    rng = np.random.default_rng(5)
    maps = {}
    if textured:
        maps = {
            name: rng.uniform(0.2, 1.0, (3, 4, 3))
            for name in ("texture", "specular_texture", "ambient_texture")
        }
    material = Material(
        (0.7, 0.4, 0.2), specular=0.4, shininess=20.0, ambient=0.05, emission=0.1, **maps
    )
    top = box_mesh((0.0, 0.3, 0.0), (0.5, 0.3, 0.4), Material((0.5, 0.5, 0.5)))
    uvs = rng.uniform(-0.5, 1.5, (len(top.vertices.data), 2)) if textured else None
    top = Mesh(md.tensor(top.vertices.data, requires_grad=True), top.faces, material, uvs=uvs)
    below = box_mesh((0.2, -0.5, 0.1), (1.2, 0.5, 0.9), Material((0.3, 0.5, 0.6)))
    camera = Camera((1.5, 2.0, 2.5), (0.0, 0.0, 0.0), fov=45.0, width=SIZE, height=SIZE)
    lights = [PointLight((1.0, 3.0, 1.0), 30.0)] if lit else []
    return Scene([top, below], lights, camera, background=(0.2, 0.3, 0.4))


def _sphere_behind() -> Scene:
    """The teapot in front of a sphere: rays beside its silhouette hit the sphere."""
    scene = _teapot(ground=False)
    scene.objects.append(Sphere((-0.8, 0.2, -2.5), 1.6, Material((0.2, 0.6, 0.3))))
    return scene


def _shared() -> Scene:
    """Two meshes that share an edge (a seam), on the ground."""
    return shared_scene("separate", True, False, True, np.zeros(3))


def _run(scene: Scene, monkeypatch, **options) -> tuple[list, dict]:
    """Render ``scene`` with the boundary term (and render ``options``), each
    ``_edge_factors`` call computed with and without the kernel: the (compiled, reference)
    pairs, and what the kernel saw
    (``calls``, ``referred``: points it left to the reference)."""
    plain = mesh_edge._edge_factors
    side_factors = edge_kernel.side_factors
    pairs, seen = [], {"calls": 0, "referred": 0}

    def both(view, kind, on, compiled=True):
        fast = plain(view, kind, on)
        pairs.append((fast, plain(view, kind, on, compiled=False)))
        return fast

    def counted(*args):
        out, rest = side_factors(*args)
        seen["calls"] += 1
        seen["referred"] += int(rest.sum())
        return out, rest

    monkeypatch.setattr(mesh_edge, "_edge_factors", both)
    monkeypatch.setattr(edge_kernel, "side_factors", counted)
    render(scene, antialias="boundary", reuse_visibility=False, **options)
    monkeypatch.undo()
    return pairs, seen


def _assert_same(pairs: list) -> None:
    """Each pair's factors equal to rounding of their scale (in practice: bit for bit)."""
    assert pairs and any(np.any(ref != 0) for _, ref in pairs)
    for fast, ref in pairs:
        scale = max(np.abs(ref).max(), 1e-300) if ref.size else 1.0
        assert fast.shape == ref.shape
        assert np.abs(fast - ref).max(initial=0.0) <= 1e-12 * scale


@pytest.mark.parametrize(
    "make, options",
    [
        (functools.partial(_teapot, ground=False), {}),
        (functools.partial(_teapot, ground=True), {}),
        (functools.partial(_teapot, ground=True), {"shadows": False}),
        (functools.partial(_teapot, ground=True), {"bvh": False}),
        (_two_lights, {}),
        (functools.partial(_boxes, textured=False), {}),
        (functools.partial(_boxes, textured=False, lit=False), {}),
        (_shared, {}),
    ],
    ids=[
        "teapot", "teapot-ground", "no-shadows", "brute-force", "two-lights", "flat-box",
        "no-light", "shared-edge",
    ],
)  # fmt: skip
def test_the_kernel_gives_the_reference_factors(make, options, monkeypatch):
    pairs, seen = _run(make(), monkeypatch, **options)
    _assert_same(pairs)
    assert seen["calls"] > 0 and seen["referred"] == 0


def test_points_beside_a_sphere_are_left_to_the_reference(monkeypatch):
    pairs, seen = _run(_sphere_behind(), monkeypatch)
    _assert_same(pairs)
    assert seen["calls"] > 0 and seen["referred"] > 0


class _TapeOnlyLight(PointLight):
    """A point light the compiled shading does not take."""

    compiled_shading = False


def _mirror() -> Scene:
    scene = _teapot(ground=True)
    scene.meshes[1].material = Material((0.5, 0.5, 0.5), reflectance=0.4)
    return scene


def _tape_light() -> Scene:
    scene = _teapot(ground=False)
    scene.lights = [_TapeOnlyLight((2.0, 5.0, 3.0), 100.0)]
    return scene


def _float32() -> Scene:
    scene = paper_scene(SIZE, SIZE, ground=True)
    for t in scene.parameters():
        t.data = t.data.astype(np.float32)
    mesh = scene.meshes[0]
    mesh.vertices = md.tensor(mesh.vertices.data, requires_grad=True)
    return scene


@pytest.mark.parametrize(
    "make",
    [_mirror, _tape_light, _float32, functools.partial(_boxes, textured=True)],
    ids=["mirror", "light", "f32", "textured"],
)
def test_where_the_kernel_does_not_apply_the_reference_runs(make, monkeypatch):
    """Mirrors, lights the compiled shading does not take, float32 scenes and textures
    (the compiled shading does not take them yet: ``render.shade.compiled``)."""
    scene = make()
    pairs, seen = _run(scene, monkeypatch)
    assert seen["calls"] == 0 and pairs
    for fast, ref in pairs:
        np.testing.assert_array_equal(fast, ref)


def _gradient(scene: Scene) -> list[np.ndarray]:
    image = render(scene, antialias="boundary", reuse_visibility=False)
    md.sum(image * image).backward()
    return [p.grad.copy() for p in scene.parameters() if p.requires_grad]


def test_the_gradient_is_the_references(monkeypatch):
    fast = _gradient(_two_lights())
    monkeypatch.setattr(
        mesh_edge, "_edge_factors", functools.partial(mesh_edge._edge_factors, compiled=False)
    )
    reference = _gradient(_two_lights())
    assert len(fast) == 2
    for a, b in zip(fast, reference, strict=True):
        assert np.abs(b).max() > 0
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max()


#: The kernel's factors of the teapot on the ground under two lights, on 1 and 2 threads.
_THREADS = """
import numpy as np
from render import render
from render.edges.boundary import mesh_edge
from tests.render.edges.test_edge_kernel import _two_lights
plain, found = mesh_edge._edge_factors, []
def keep(view, kind, on, compiled=True):
    found.append(plain(view, kind, on))
    return found[-1]
mesh_edge._edge_factors = keep
def run():
    found.clear()
    render(_two_lights(), antialias="boundary", reuse_visibility=False)
    assert found and any(np.any(f != 0) for f in found)
    return list(found)
"""


@pytest.mark.new_processes
def test_the_same_bits_on_one_and_two_threads():
    """In a new process (a pytest-xdist worker is limited to one Numba thread)."""
    same_bits_on_one_and_two_threads(_THREADS)


def test_two_sides_sharing_their_shadow_rays_get_two_traversals_answers():
    """``_lit``'s one traversal per light for both faces of a crease (a second only where
    the - face blocks the ray) answers what two any-hit rays, each skipping its own face,
    do. (At a crease neither face blocks the other's ray but by rounding: the faces here
    are drawn, one of them often the ray's first blocker, so that every branch is taken.)"""
    from types import SimpleNamespace

    from render.trace.accel import Accelerator
    from render.trace.primitives import scene_primitives

    scene = paper_scene(8, 8, ground=True)
    accelerator = Accelerator(*scene_primitives(scene))
    bvh = accelerator.flat_tree()
    rows = np.empty(len(bvh.leaf_ids), np.int64)
    rows[bvh.leaf_ids] = np.arange(len(bvh.leaf_ids))
    rng = np.random.default_rng(2)
    n, n_tri = 400, bvh.n_tri
    points = rng.uniform(-1.5, 1.5, (n, 3))
    traced = SimpleNamespace(shadows=True, size=1.0)
    branches = set()
    for light in (PointLight((2.0, 5.0, 3.0), 1.0), DirectionalLight((0.3, -1.0, -0.2), 1.0)):
        offset = 1e-6
        shadow = edge_kernel._pack_shadows(Scene(scene.objects, [light], scene.camera), traced)
        origins, directions, tmax = light.shadow_rays(points, offset)
        first = accelerator.closest_hit(origins, directions, 0.0, tmax)[0]
        drawn = rng.integers(0, n_tri, (n, 2))
        faces = np.where((first >= 0)[:, None] & (rng.random((n, 2)) < 0.5), first[:, None], drawn)
        faces[faces[:, 0] == faces[:, 1], 1] = -1  # a side with no face here: its own ray
        expected = [
            ~accelerator.occluded(origins, directions, tmax, tmin=0.0, ignore_prim=faces[:, k])
            for k in (0, 1)
        ]
        lit, stack = np.empty((1, 2)), np.empty(bvh.stack_size, np.int64)
        for r in range(n):
            plus, minus = faces[r]
            edge_kernel._lit(
                bvh, rows, shadow, np.full((2, 1), offset), 0, points[r], plus, minus, stack, lit
            )
            assert lit[0, 0] == expected[0][r] and (minus < 0 or lit[0, 1] == expected[1][r])
            branches.add((minus >= 0, bool(expected[0][r]), bool(expected[1][r])))
    assert {(True, False, True), (True, True, False), (True, False, False)} <= branches
