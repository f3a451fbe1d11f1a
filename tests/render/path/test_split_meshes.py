"""The path integrator's secondary term where several meshes share edges
(``render.path.boundary.silhouettes``: meshes that share an edge are welded into one), as a
multi-material file's meshes do (``render.load_mesh``: one per material).

A closed mesh split into meshes by any partition of its faces must give the gradient of the
one mesh (the same faces, in the parts' order) to rounding: the same curves in the same
order, hence the same draws. Before, every shared edge lay on the other mesh's face and was
dropped as a contact: measured on these scenes, the split box's light gradient 50-100 %
off. An L (a plate with a fin hanging from one side) as two meshes against central
differences of renders: before, 15 % off on this scene (-44.4 against -38.6).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.path import render_path
from render.path.boundary.silhouettes import Curves
from render.path.sample.tracer import PathSampler
from render.scene.cornell import box_mesh, cornell_box, grid_quad
from render.scene.placement import placed

X, Y, Z = np.eye(3)
GREY = render.Material((0.5, 0.5, 0.5))


def floor_scene(occluders: list[render.Mesh], light: str) -> render.Scene:
    """``occluders`` above a floor lit by a small square area light (a ``Transform``
    places it) or a point light; 8 x 8 pixels, the camera under the occluders looking down
    at their shadow (``tests/render/path/test_secondary.py``'s set-up)."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)
    objects = [render.Mesh(v, f, render.Material((0.8, 0.8, 0.8))), *occluders]
    lights = []
    if light == "area":
        v, f = grid_quad((0.0, 1.0, 0.0), 0.25 * X, 0.25 * Z)
        emitter = render.Material((0, 0, 0), emission=(5.0, 5.0, 5.0))
        objects.append(render.Mesh(v, f, emitter, transform=render.Transform()))
    else:
        lights.append(render.PointLight((0.0, 1.1, 0.1), 3.0))
    camera = render.Camera((0.05, 0.35, 0.05), (0.0, 0.0, 0.0), (0, 0, -1), 110.0, 8, 8)
    return render.Scene(objects, lights, camera)


def split(mesh: render.Mesh, labels: np.ndarray) -> tuple[render.Mesh, list, list]:
    """``mesh`` with its faces in the order of ``labels`` (F,) (the parts' order), and its
    parts: one mesh per label with the vertices its faces use (as ``load_mesh`` reads a
    file's materials), and each part's vertex ids in ``mesh``."""
    vertices, faces = np.asarray(mesh.vertices.data), np.asarray(mesh.faces)
    whole = render.Mesh(vertices, faces[np.argsort(labels, kind="stable")], GREY)
    parts, ids = [], []
    for label in np.unique(labels):
        used, local = np.unique(faces[labels == label], return_inverse=True)
        parts.append(render.Mesh(vertices[used], local.reshape(-1, 3), GREY))
        ids.append(used)
    return whole, parts, ids


def gradients(occluders: list[render.Mesh], light: str, spp: int = 4, seed: int = 0):
    """The image's sum's gradient in the light's position (3,) and in each occluder's
    vertices (a list of (V_k, 3); zeros where nothing reached them), the secondary term
    included."""
    scene = floor_scene(occluders, light)
    p = scene.objects[-1].transform.translation if light == "area" else scene.lights[0].position
    tensors = [p] + [m.vertices for m in scene.objects[1 : 1 + len(occluders)]]
    for t in tensors:
        t.requires_grad = True
    depth = 2 if light == "area" else 3
    image = render_path(scene, spp=spp, max_depth=depth, seed=seed, rr_depth=100,
                        antialias="secondary")  # fmt: skip
    image.sum().backward()
    return tensors[0].grad.copy(), [np.zeros(t.shape) if t.grad is None else t.grad
                                    for t in tensors[1:]]  # fmt: skip


def curves_of(occluders: list[render.Mesh]) -> Curves:
    return Curves.of(PathSampler(placed(floor_scene(occluders, "area")), 1, 2, 100, 0))


@st.composite
def split_boxes(draw):
    """A box of random proportions split into 2-6 meshes by a random partition of its 12
    faces (every part non-empty)."""
    half = draw(st.tuples(*[st.floats(0.03, 0.25)] * 3))
    k = draw(st.integers(2, 6))
    labels = np.array(draw(st.permutations(list(range(k)) + [0] * (12 - k))))
    rest = draw(st.lists(st.integers(0, k - 1), min_size=12, max_size=12))
    labels = np.where(np.arange(12) < k, labels, np.array(rest))[draw(st.permutations(range(12)))]
    return box_mesh((0.1, 0.6, 0.0), half, GREY), labels


@settings(max_examples=10, deadline=None)
@given(split_boxes())
def test_a_split_box_has_the_one_mesh_curves(case):
    """The curves of a box split into meshes are the one mesh's: the same edges with the
    same faces, in the same order, each on a part whose vertex ids place it there."""
    box, labels = case
    whole, parts, ids = split(box, labels)
    one, many = curves_of([whole]), curves_of(parts)
    for field in ("a", "b", "c"):
        np.testing.assert_array_equal(getattr(many, field), getattr(one, field))
    # The floor's 4 edges, the box's 12 (its sides' diagonals are flat), the light's 4
    # (in the order of their midpoints along a Morton curve, ``Curves.of``).
    assert one.n_edges == many.n_edges == 20
    assert np.isin(many.edge_object, 1 + np.arange(len(parts))).sum() == 12
    # ``ends``: rows of every mesh's vertices, mesh after mesh (the floor's first)
    starts = np.cumsum([0] + [len(m.vertices.data) for m in floor_scene(parts, "area").meshes])
    for k, part in enumerate(parts):
        mine = many.edge_object == 1 + k
        own = many.ends[mine] - starts[1 + k]  # the ids in the part
        np.testing.assert_array_equal(part.vertices.data[own],
                                      np.stack([many.a[mine], many.b[mine]], axis=1))  # fmt: skip
        np.testing.assert_array_equal(box.vertices.data[ids[k]][own],
                                      np.stack([many.a[mine], many.b[mine]], axis=1))  # fmt: skip


@settings(max_examples=5, deadline=None)
@given(split_boxes(), st.sampled_from(["area", "point"]), st.integers(0, 2**16))
def test_a_split_box_has_the_one_mesh_gradient(case, light, seed):
    """The light's and the box's vertices' gradients of the split box equal the one mesh's
    (the parts' vertex gradients summed back onto the box's vertices) to rounding; they are
    not zero (before: every shared edge dropped, 50-100 % off)."""
    box, labels = case
    whole, parts, ids = split(box, labels)
    light_one, (vertices_one,) = gradients([whole], light, seed=seed)
    light_many, vertices_many = gradients(parts, light, seed=seed)
    summed = np.zeros_like(vertices_one)
    for used, grad in zip(ids, vertices_many, strict=True):
        np.add.at(summed, used, grad)
    assert np.abs(light_one).max() > 0
    np.testing.assert_allclose(
        light_many, light_one, rtol=1e-9, atol=1e-9 * np.abs(light_one).max()
    )
    np.testing.assert_allclose(summed, vertices_one, rtol=1e-9,
                               atol=1e-9 * np.abs(vertices_one).max())  # fmt: skip


def l_shape(two: bool) -> list[render.Mesh]:
    """A horizontal plate with a fin hanging from its edge x = 0.3: the L's outer corner is
    a silhouette seen from the light above. As one mesh or as two that share that edge."""
    plate = grid_quad((0.1, 0.6, 0.0), 0.2 * X, -0.2 * Z)
    fin = grid_quad((0.3, 0.525, 0.0), 0.075 * Y, 0.2 * Z)
    if two:
        return [render.Mesh(*plate, GREY), render.Mesh(*fin, GREY)]
    return [render.Mesh(np.concatenate([plate[0], fin[0]]), np.concatenate([plate[1], fin[1] + 4]),
                        GREY)]  # fmt: skip


def light_derivative(two: bool, spp: int, seed: int, delta: float = 0.0, grad: bool = True):
    """(the image's sum, its derivative in the area light's x or None) with the L."""
    scene = floor_scene(l_shape(two), "area")
    p = scene.objects[-1].transform.translation
    p.data = p.data + delta * X
    p.requires_grad = grad
    image = render_path(scene, spp=spp, max_depth=2, seed=seed, rr_depth=100,
                        antialias="secondary" if grad else False)  # fmt: skip
    total = image.sum()
    if not grad:
        return total.item(), None
    total.backward()
    return total.item(), float(p.grad[0])


def test_an_l_of_two_meshes_matches_central_differences():
    """The L of two meshes: its soft shadow's gradient in the light's x is the one mesh's
    bit for bit and within 5 % of central differences (measured: 0.3 %; one seed's spread
    ~2 %, the central differences' ~1 %); before, 15 % off (every shared edge dropped)."""
    seeds, h = (0, 1), 0.02
    assert light_derivative(True, 16, 0)[1] == light_derivative(False, 16, 0)[1]
    ours = [light_derivative(True, 256, s)[1] for s in seeds]
    with md.no_grad():
        fd = np.mean([
            (light_derivative(True, 2048, s, h, False)[0]
             - light_derivative(True, 2048, s, -h, False)[0]) / (2 * h)
            for s in seeds
        ])  # fmt: skip
    assert abs(np.mean(ours) - fd) <= 0.05 * abs(fd), (ours, fd)


def test_a_split_box_standing_on_the_floor_keeps_its_contact_rule():
    """Split into meshes, a box standing on the floor still leaves out its 4 bottom edges
    (they rest inside the floor's face: a grazing ray meets the floor at the edge) and
    keeps its 4 top edges and 4 upright ones, as one mesh does."""
    box = box_mesh((0.1, 0.05, 0.0), (0.2, 0.05, 0.2), GREY)
    _, parts, _ = split(box, np.repeat(np.arange(6), 2))  # one mesh per side
    for occluders in ([box], parts):
        curves = curves_of(occluders)
        mine = (curves.edge_object >= 1) & (curves.edge_object <= len(occluders))
        heights = np.sort(np.stack([curves.a[mine, 1], curves.b[mine, 1]], axis=1), axis=1)
        assert len(heights) == 8
        assert np.all(heights[:, 1] == 0.1)  # every edge left reaches the top


def test_walls_meeting_at_a_corner_are_not_silhouettes_from_inside():
    """The Cornell box's walls are one mesh each; the edges where they meet are shared, with
    a face of each wall: concave seen from inside the room, so never a silhouette there
    (taken wall by wall they were borders, silhouettes from everywhere)."""
    curves = Curves.of(PathSampler(placed(cornell_box(4, 4, blocks=False)), 1, 2, 100, 0))
    walls = curves.edge_object < 5
    corner = walls & np.any(curves.c[:, 0] != curves.c[:, 1], axis=1)  # two faces: shared
    assert corner.sum() == 8 and (walls & ~corner).sum() == 4  # 4 rims at the open front
    apex = np.random.default_rng(0).uniform(-0.99, 0.99, (200, 3))
    angle, _ = curves.silhouettes(apex)
    assert np.all(angle[:, : curves.n_edges][:, corner] == 0)
    assert np.all(angle[:, : curves.n_edges][:, walls & ~corner] > 0)


def edges_at_height(curves: Curves, objects: list[int], y: float) -> int:
    """How many of the curves' edges of ``objects`` lie at height y."""
    mine = np.isin(curves.edge_object, objects)
    return int(np.sum(mine & (curves.a[:, 1] == y) & (curves.b[:, 1] == y)))


def test_where_more_than_two_faces_meet_the_outer_two_decide():
    """A box on a floor whose grid runs along its bottom edges shares them with the floor:
    four faces meet there (two of the floor's, two of the box's), spanning a half turn, so
    they are never silhouettes, whichever mesh comes first; so is the foot of a fin standing
    on a plate's inner edge (three faces). The fin's other edges are kept."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z, 3)  # grid lines at +-0.5
    floor = render.Mesh(v, f, GREY)
    box = box_mesh((0.0, 0.25, 0.0), (0.5, 0.25, 0.5), GREY)
    for occluders, box_at in (([box], 1), ([box, floor], 1), ([floor, box], 2)):
        scene = floor_scene(occluders, "area")
        if len(occluders) == 2:
            scene.objects = scene.objects[1:]  # the grid floor instead of the plain one
            box_at -= 1
        curves = Curves.of(PathSampler(placed(scene), 1, 2, 100, 0))
        assert edges_at_height(curves, [box_at], 0.0) == 0
        assert edges_at_height(curves, [box_at], 0.5) == 4
    plate = grid_quad((0.1, 0.6, 0.0), 0.2 * X, -0.2 * Z, 2)  # an inner edge along x = 0.1
    fin = grid_quad((0.1, 0.675, -0.1), 0.075 * Y, 0.1 * Z)  # standing on its half z < 0
    curves = curves_of([render.Mesh(*plate, GREY), render.Mesh(*fin, GREY)])
    on_line = (curves.a[:, 0] == 0.1) & (curves.b[:, 0] == 0.1)
    assert edges_at_height(curves, [1, 2], 0.6) == 8  # the plate's rim, not the fin's foot
    assert not np.any(on_line & (curves.a[:, 1] == 0.6) & (curves.b[:, 1] == 0.6))
    assert np.sum(on_line & (np.maximum(curves.a[:, 1], curves.b[:, 1]) > 0.7)) == 3


def _seam_case(apart: str):
    """A box with two T-junctions, its faces in three meshes, the last one through float32
    or its positions moved by up to 4e-6 (inside the welding of seams, 1e-6 of the scene):
    (the box, the meshes)."""
    from render.scene.surgery import in_meshes, moved_apart, through_float32, with_t_junctions

    box = with_t_junctions(box_mesh((0.1, 0.6, 0.0), (0.15, 0.1, 0.12), GREY), [(1, 0.4), (7, 0.6)])
    owner = np.random.default_rng(3).integers(0, 3, len(box.faces))
    owner[:2] = [0, 1]
    meshes = in_meshes(box, owner.tolist())
    last = meshes[-1]
    last = (
        through_float32(last)
        if apart == "float32"
        else moved_apart(last, 4e-6, np.random.default_rng(0))
    )
    return box, [*meshes[:-1], last]


def _seam_gradients(parts, seed: int, antialias: str, spp: int, edge_spp=None) -> np.ndarray:
    """The light's position and the parts' translation gradients of a fixed weighting of
    the box over a floor, 24 x 24, depth 3 (``render_path``; ``light_and_translation``)."""
    from render.scene.surgery import light_and_translation

    def image_of(scene):
        return render_path(scene, spp=spp, max_depth=3, seed=seed, antialias=antialias,
                           edge_spp=edge_spp)  # fmt: skip

    return light_and_translation(parts, image_of, 24)


def _within_noise(one: np.ndarray, many: np.ndarray) -> None:
    """The seeds' mean difference within 5 % of the mean and four standard errors."""
    difference = (many - one).mean(axis=0)
    error = (many - one).std(axis=0, ddof=1) / np.sqrt(len(one))
    assert np.all(np.abs(difference) <= 0.05 * np.abs(one.mean(axis=0)) + 4 * error), (
        difference,
        error,
        one.mean(axis=0),
    )


@pytest.mark.parametrize("apart", ["float32", "moved"])
def test_a_box_whose_seams_came_apart_has_the_one_boxs_secondary_term(apart):
    """The secondary term (8 seeds) of the box whose seams came apart (``_seam_case``): the
    one box's light and translation gradients, within the seeds' noise. Before the rays
    through an edge point passed the faces on its edge (``secondary._past_the_edge``), with
    the seams moved they met the face across the crack: the translation's x was off by
    28.4 +- 0.6 on a mean of -17.2, the light's x by -8.9."""
    box, meshes = _seam_case(apart)
    one = np.array([_seam_gradients([box], seed, "secondary", 8) for seed in range(8)])
    many = np.array([_seam_gradients(meshes, seed, "secondary", 8) for seed in range(8)])
    _within_noise(one, many)


def test_a_box_whose_seams_came_apart_has_the_one_boxs_primary_term():
    """The primary boundary term (8 seeds, 256 paths a side) of the box whose seams were
    moved 4e-6 apart: the one box's gradients, within the seeds' noise. Before its paths
    started ``INSIDE`` their faces only 1e-6 of the way and at the edge's depth
    (``PathRadiance._inside``), a face across the crack overhung the start and shadowed
    it: the translation's z was off by 0.54 +- 0.06 on a mean of 3.9 here."""
    box, meshes = _seam_case("moved")
    one = np.array([_seam_gradients([box], seed, "primary", 4, 256) for seed in range(8)])
    many = np.array([_seam_gradients(meshes, seed, "primary", 4, 256) for seed in range(8)])
    _within_noise(one, many)
