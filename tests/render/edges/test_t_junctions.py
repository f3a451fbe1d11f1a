"""Meshes with T-junctions (a face's edge running along two of another face's, a quad
split on one side only): ``render.trace.topology.cut_at_t_junctions`` cuts the long edge's
row at the vertex, so that each part is one curve with a face on each side, as in the
conforming mesh. The same surface, tessellated either way, must give the same gradients.

Measured before the cut, on a box with one side's triangle split at the middle of a box
edge (a point light, 48 x 48, the direct renderer's boundary term): the light's gradient
(-3634.6, -1045.6, 8733.4) against the box's (-3634.6, -1314.5, 3355.3), the box's
translation gradient z -13637 against -5186; the path integrator's secondary term on the
same box under an area light, light gradient z 23.95 +- 1.26 against 1.81 +- 0.70 (8
seeds, 16 spp): each face's edge counted the jump to the other face, the curve twice.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.path.boundary.silhouettes import Curves
from render.path.sample.tracer import PathSampler
from render.scene.cornell import box_mesh, grid_quad
from render.scene.placement import placed
from render.scene.surgery import (
    floor_scene,
    in_meshes,
    light_and_translation,
    moved_apart,
    through_float32,
    with_t_junctions,
    wound_at_random,
)
from render.trace.primitives import scene_primitives
from render.trace.topology import (
    SEAM_LENGTH,
    cut_at_t_junctions,
    edge_structure,
    mesh_edges,
    open_rows_of,
    seam_distance,
    welding,
)

GREY = render.Material((0.6, 0.6, 0.6))
X, Z = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])


def box() -> render.Mesh:
    return box_mesh((0.1, 0.6, 0.0), (0.15, 0.1, 0.12), GREY)


def scene_with(mesh: render.Mesh, size: int = 48) -> render.Scene:
    """A floor under ``mesh``, a point light, a camera looking down on both."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)
    light = render.PointLight((0.3, 1.6, 0.2), 3.0)
    camera = render.Camera((0.6, 1.3, 1.1), (0.05, 0.3, 0.0), (0, 1, 0), 45.0, size, size)
    return render.Scene([render.Mesh(v, f, GREY), mesh], [light], camera)


def gradients(mesh: render.Mesh, antialias="boundary") -> tuple[np.ndarray, np.ndarray, float]:
    """The light's position gradient, the mesh's translation gradient (its vertices'
    gradients summed) and the image's sum: ``scene_with`` at 48 x 48, the boundary term
    with one interior sample (16 would resample the pixels where the primitive changes,
    which a split face adds: another image, and another interior term), or the pixel
    pairs (``antialias=True``)."""
    scene = scene_with(mesh)
    position, vertices = scene.lights[0].position, scene.objects[1].vertices
    position.requires_grad = vertices.requires_grad = True
    image = render.render(scene, antialias=antialias, interior_samples=1)
    md.sum(image).backward()
    return position.grad.copy(), vertices.grad.sum(axis=0), float(image.data.sum())


@settings(max_examples=6, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 11), st.floats(0.2, 0.8)), min_size=1, max_size=4))
def test_a_box_with_t_junctions_has_the_box_gradients(picks):
    """The box with some of its faces split at points of their shared edges renders the
    same image, and the same light and translation gradients (to the quadrature's error)."""
    light, translation, total = gradients(box())
    t_box = with_t_junctions(box(), picks)
    assert len(t_box.faces) > 12
    light_t, translation_t, total_t = gradients(t_box)
    assert abs(total_t - total) <= 1e-9 * abs(total)
    # To the quadrature's error: the long edge's curve is two pieces, each with its own
    # Gauss-Legendre points (1e-5 of the gradients measured; uncut, up to 2.6 times off).
    np.testing.assert_allclose(light_t, light, rtol=1e-4, atol=1e-4 * np.abs(light).max())
    np.testing.assert_allclose(translation_t, translation, rtol=1e-4,
                               atol=1e-4 * np.abs(translation).max())  # fmt: skip


@settings(max_examples=6, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 11), st.floats(0.2, 0.8)), min_size=1, max_size=4))
def test_pixel_pairs_on_a_box_with_t_junctions_have_the_box_gradients(picks):
    """The pixel pairs (``antialias=True``) find the same edges on the box with some faces
    split as on the box: the walk across the mesh steps over a T-junction into the face
    beyond (``Pieces``), and a face split in its plane is no crease. Measured before, one
    face split at the middle of a box edge: the box's translation gradient x 52.3, the
    T-box's -10.2 (the walk took the long edge for a silhouette; and the box's own x was
    52.3 only because its faces' diagonals counted as creases: 9.35 now, supersampled
    central differences -19.8, the boundary term -12.9)."""
    light, translation, total = gradients(box(), antialias=True)
    light_t, translation_t, total_t = gradients(with_t_junctions(box(), picks), antialias=True)
    assert abs(total_t - total) <= 1e-9 * abs(total)
    np.testing.assert_allclose(light_t, light, rtol=1e-9, atol=1e-9 * np.abs(light).max())
    np.testing.assert_allclose(translation_t, translation, rtol=1e-9,
                               atol=1e-9 * np.abs(translation).max())  # fmt: skip


@pytest.mark.parametrize("fast", [False, True])
def test_the_walk_over_t_junctions_ends_where_it_ends_on_the_box(fast):
    """From the nearer sample of every pair of adjacent pixels that see different faces of
    the T-box (every face split at a box edge where it can be), both walks (NumPy, Numba)
    end on a silhouette exactly where they end on the box, crossing the same edge line.
    (Without the T-junctions' neighbours and ``Pieces`` the walk stops at a long or a short
    edge as at an open one: 27 of the 132 walks end on a silhouette the box does not
    have.)"""
    from render.edges.geometry import plain_rays, sample_grid
    from render.edges.silhouettes import candidate_pairs
    from render.trace.topology import silhouette_edges, walk_to_silhouette, walk_to_silhouette_fast
    from render.trace.visibility import trace_primary

    walk = walk_to_silhouette_fast if fast else walk_to_silhouette
    t_box = with_t_junctions(box(), [(f, 0.3 + 0.03 * f) for f in range(12)])
    ends, pairs = [], None
    for mesh in (box(), t_box):
        scene = scene_with(mesh, 64)
        hits = trace_primary(lambda s=scene: render.Accelerator(*scene_primitives(s)),
                             scene.camera, 1).prim_id  # fmt: skip
        first = scene.meshes[0].num_faces  # the floor's faces come first
        if pairs is None:  # the box's pairs, from a sample on the box
            a, b, _ = candidate_pairs(sample_grid(scene.camera, 1), hits)
            pairs = a[hits[a] >= first], b[hits[a] >= first]
        a, b = pairs
        assert np.all(hits[a] >= first)
        eye, d_a, d_b, _ = plain_rays(scene.camera, a, b, 1)
        vertices, faces = np.asarray(mesh.vertices.data), mesh.faces
        edges = mesh_edges(vertices, faces)
        silhouette = silhouette_edges(edges, vertices, faces, eye)
        face, k, s, _ = walk(edges, silhouette, vertices, faces, hits[a] - first, eye, d_a, d_b)
        found = k >= 0
        corners = vertices[faces[face[found]]]
        kk = k[found]
        line = np.cross(corners[np.arange(len(kk)), kk] - eye,
                        corners[np.arange(len(kk)), (kk + 1) % 3] - eye)  # fmt: skip
        ends.append((found, s, line / np.linalg.norm(line, axis=1, keepdims=True), edges))
    (found, s, line, _), (found_t, s_t, line_t, edges_t) = ends
    assert edges_t.pieces.end.size > 0
    np.testing.assert_array_equal(found_t, found)
    assert found.sum() > 30
    np.testing.assert_allclose(s_t[found], s[found], rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(line_t * line, axis=1)), 1.0, atol=1e-9)


def test_a_face_split_in_its_plane_is_no_crease():
    """``creases``: flat shading changes colour across a fold, not across the diagonal of
    a flat quad (nor across a T-junction in the plane), and across the seam of two meshes
    of one material in one plane only where the material or the way of shading changes;
    with smooth normals a seam of vertex ids is one."""
    from render.edges.silhouettes import creases
    from render.trace.seams import WeldedScene, shared_edges

    def jumps(*meshes: render.Mesh) -> np.ndarray:
        scene = render.Scene(list(meshes), [], render.Camera((0, 2, 0), (0, 0, 0), (0, 0, 1)))
        topology = {k: mesh_edges(np.asarray(m.vertices.data), m.faces)
                    for k, m in enumerate(meshes)}  # fmt: skip
        group = WeldedScene.of(scene, topology, shared_edges(scene, topology)).groups[0]
        return creases(group, scene), group.edges.neighbour >= 0

    v, f = grid_quad((0, 0, 0), X, -Z)
    crease, inner = jumps(render.Mesh(v, f, GREY))
    assert inner.sum() == 2 and not np.any(crease[inner]) and np.all(crease[~inner])
    folded = v.copy()
    folded[np.isclose(v[:, 0], 1.0) & np.isclose(v[:, 2], -1.0), 1] = 0.3
    assert np.all(jumps(render.Mesh(folded, f, GREY))[0][inner])
    # the quad's two triangles as two meshes: one material, then two, then one smooth
    halves = [render.Mesh(v, f[:1], GREY), render.Mesh(v, f[1:], GREY)]
    crease, inner = jumps(*halves)
    assert inner.sum() == 2 and not np.any(crease[inner])
    red = render.Mesh(v, f[1:], render.Material((0.9, 0.1, 0.1)))
    assert np.all(jumps(halves[0], red)[0][inner])
    smooth = render.Mesh(v, f[1:], GREY, smooth=True)
    assert np.all(jumps(halves[0], smooth)[0][inner])


def test_the_cut_table_has_a_face_each_side_and_the_outlines_have_no_false_border():
    """A box with a T-junction: every row of its cut table has two faces (as the box's),
    and the path integrator's curves see no border edge (a border is an outline from
    everywhere: the long edge would have been one); a mesh without T-junctions keeps its
    table (the same object)."""
    t_box = with_t_junctions(box(), [(0, 0.5)])
    table = mesh_edges(np.asarray(t_box.vertices.data), np.asarray(t_box.faces)).table
    assert np.all(np.sum(table.faces >= 0, axis=1) == 2)
    plain = box()
    structure = edge_structure(plain.faces, *welding(plain.vertices.data, plain.faces))
    assert cut_at_t_junctions(structure, np.asarray(plain.vertices.data), plain.faces) is structure
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)
    scene = render.Scene([render.Mesh(v, f, GREY), t_box], [], render.Camera(
        (0.6, 1.3, 1.1), (0.05, 0.3, 0.0), (0, 1, 0), 45.0, 8, 8))  # fmt: skip
    curves = Curves.of(PathSampler(placed(scene), 1, 2, 100, 0))
    mine = curves.edge_object == 1
    assert mine.sum() == 13  # the box's 12 edges, one of them in two (the others are flat)
    assert not np.any(np.all(curves.c[mine, 0] == curves.c[mine, 1], axis=1))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 60), st.integers(0, 60))
def test_points_inside_segments_are_those_every_pair_finds(seed, n_segments, n_points):
    """``points_inside`` (candidates from a grid of the segments' boxes) finds what testing every
    segment against every point finds: points on segments (at random t, or at an end),
    off them by less and by more than the tolerance (1e-6, or ``SEAM_LENGTH`` of the
    segment's length, whichever is larger), and anywhere."""
    from render.trace.topology import SEAM_LENGTH, points_inside

    rng = np.random.default_rng(seed)
    a, b = rng.uniform(-1, 1, (2, n_segments, 3))
    on = rng.integers(0, n_segments, n_points)
    t = rng.choice([0.0, 0.3, 0.5, 1.0, rng.uniform()], n_points)
    reach = np.maximum(1e-6, SEAM_LENGTH * np.linalg.norm(b - a, axis=1))[on, None]
    scale = rng.choice([0.0, 0.5, 2.0], (n_points, 1)) * reach
    points = a[on] + t[:, None] * (b[on] - a[on]) + scale * rng.normal(size=(n_points, 3)) / 3
    points = np.concatenate([points, rng.uniform(-1, 1, (5, 3))])
    vertices = np.concatenate([a, b, points])
    i, j = np.arange(n_segments), n_segments + np.arange(n_segments)
    ids = np.arange(len(vertices))  # every vertex its own welded id
    candidates = 2 * n_segments + np.arange(len(points))
    got = points_inside(vertices, i, j, candidates, ids, 1e-6)
    found = sorted(zip(got[0].tolist(), got[1].tolist(), strict=True))
    d = b[:, None] - a[:, None]  # (S, 1, 3)
    off = points[None] - a[:, None]  # (S, P, 3)
    length2 = np.sum(d * d, axis=2)
    tt = np.sum(off * d, axis=2) / length2
    miss = off - tt[..., None] * d
    tolerance = np.maximum(1e-6, SEAM_LENGTH * np.sqrt(length2))  # (S, 1)
    near = np.sum(miss * miss, axis=2) <= tolerance**2
    want = [(s, int(candidates[p])) for s, p in zip(*np.nonzero(near & (tt > 0) & (tt < 1)),
                                                     strict=True)]  # fmt: skip
    assert found == sorted(want)


def test_too_many_candidates_leave_the_table_uncut(monkeypatch):
    """Where the grid of open edges' boxes leaves more candidate pairs than the budget (a
    soup of long edges), the table stays as it was: the same object, no cut."""
    import render.trace.topology as topology

    t_box = with_t_junctions(box(), [(0, 0.5)])
    v, f = np.asarray(t_box.vertices.data), np.asarray(t_box.faces)
    structure = edge_structure(f, *welding(v, f))
    assert cut_at_t_junctions(structure, v, f) is not structure
    monkeypatch.setattr(topology, "_MOST_PAIRS", 0)
    assert cut_at_t_junctions(structure, v, f) is structure


def test_an_l_whose_fin_is_tessellated_otherwise_keeps_its_corner():
    """A plate and a fin hanging from its edge, the fin's top edge split at its middle (a
    T-junction between two meshes): the path integrator's curves hold the L's corner, as
    two edges with a face of each mesh (as the conforming L's one). Before the meshes
    were joined at T-junctions, both meshes' edges there rested on the other's face and
    were dropped: the area light's x gradient -42.7 +- 0.6 against the conforming L's
    -36.3 +- 1.1 (8 seeds x 16 spp; after: -36.2 +- 1.1)."""
    y = np.array([0, 1.0, 0])
    plate = grid_quad((0.1, 0.6, 0.0), 0.2 * X, -0.2 * Z)
    fv, ff = grid_quad((0.3, 0.525, 0.0), 0.075 * y, 0.2 * Z)
    top = set(np.flatnonzero(np.isclose(fv[:, 1], 0.6)).tolist())
    middle = len(fv)
    faces = []
    for tri in ff.tolist():
        for q in range(3):
            a, b, c = tri[q], tri[(q + 1) % 3], tri[(q + 2) % 3]
            if {a, b} == top:
                faces += [[a, middle, c], [middle, b, c]]
                break
        else:
            faces.append(tri)
    fin = (np.vstack([fv, fv[sorted(top)].mean(axis=0)]), np.array(faces))
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)
    camera = render.Camera((0.05, 0.35, 0.05), (0, 0, 0), (0, 0, -1), 110.0, 8, 8)
    scene = render.Scene([render.Mesh(v, f, GREY), render.Mesh(*plate, GREY),
                          render.Mesh(*fin, GREY)], [render.PointLight((0, 1.1, 0.1), 3.0)],
                         camera)  # fmt: skip
    curves = Curves.of(PathSampler(placed(scene), 1, 2, 100, 0))
    corner = np.all(np.isclose(curves.a[:, :2], [0.3, 0.6]), axis=1) & np.all(
        np.isclose(curves.b[:, :2], [0.3, 0.6]), axis=1)  # fmt: skip
    assert corner.sum() == 2
    assert not np.any(np.all(curves.c[corner, 0] == curves.c[corner, 1], axis=1))


@pytest.mark.parametrize(("antialias", "size"), [(True, 8), (True, 12), ("boundary", 40)])
def test_faces_whose_edges_overlap_have_the_conforming_gradients(antialias, size):
    """Two faces whose edges overlap along a line, each with a vertex inside the other's
    edge (both edges are cut, and each part of one has the other as ``Pieces``): the
    translation and light gradients of the pair equal those of the same surface split at
    both vertices (a rigid motion, the same for both; a vertex's own gradient is not, as
    moving a vertex of the long edge moves the whole edge). The pixel pairs at 8 and 12
    pixels, where their walk crosses the overlap: without the ``Pieces`` they differ (the
    translation's y -1.35 against -1.03 at 8), and they did with a piece's silhouette
    read from the other face's own edge, itself cut (an open edge's: always one)."""
    v = np.array([(0, 0, 0), (1, 0, 0), (0.5, 1, 0.3), (0.5, 0, 0), (1.5, 0, 0), (1, -1, 0.2)])
    overlapping = [[0, 1, 2], [3, 5, 4]]
    conforming = [[0, 3, 2], [3, 1, 2], [3, 5, 1], [1, 5, 4]]
    camera = render.Camera((0.7, -0.2, 2.0), (0.7, -0.1, 0.0), (0, 1, 0), 60.0, size, size)
    weights = md.tensor(np.random.default_rng(1).standard_normal((size, size, 3)))
    found = []
    for faces in (overlapping, conforming):
        scene = render.Scene([render.Mesh(v, np.array(faces), GREY)],
                             [render.PointLight((0.3, 0.5, 1.0), 2.0)], camera,
                             background=(0.1, 0.2, 0.3))  # fmt: skip
        vertices, light = scene.objects[0].vertices, scene.lights[0].position
        vertices.requires_grad = light.requires_grad = True
        md.sum(render.render(scene, antialias=antialias, interior_samples=1) * weights).backward()
        found.append(np.r_[vertices.grad.sum(axis=0), light.grad])
    pieces = mesh_edges(v, np.array(overlapping)).pieces
    assert sorted(pieces.face.tolist()) == [-1, -1, 0, 1]  # each edge: an open part, the other
    np.testing.assert_allclose(found[0], found[1], rtol=1e-9, atol=1e-9 * np.abs(found[1]).max())


def meshes_gradients(meshes: list[render.Mesh], antialias="boundary", shadows=True) -> np.ndarray:
    """The light's position gradient and the translation gradient of every mesh but the
    floor together (``scene_with``'s scene at 32 x 32, the boundary term with one interior
    sample or the pixel pairs, the image's weighted sum: ``surgery.light_and_translation``)."""

    def image_of(scene):
        return render.render(scene, antialias=antialias, interior_samples=1, shadows=shadows)

    return light_and_translation(meshes, image_of)


@st.composite
def boxes_in_meshes(draw) -> tuple[render.Mesh, list[render.Mesh]]:
    """A box with T-junctions (1-5 picks of ``with_t_junctions``) and its faces dealt to two
    or three meshes (``in_meshes``, perhaps with a mesh between): (the box as one mesh,
    the meshes)."""
    picks = draw(st.lists(st.tuples(st.integers(0, 11), st.floats(0.2, 0.8)), min_size=1,
                          max_size=5))  # fmt: skip
    t_box = with_t_junctions(box(), picks)
    owner = np.random.default_rng(draw(st.integers(0, 2**32 - 1))).integers(0, 3, len(t_box.faces))
    owner[:2] = [0, 1]  # two meshes at least
    return t_box, in_meshes(t_box, owner.tolist(), draw(st.booleans()))


@settings(max_examples=8, deadline=None)
@given(boxes_in_meshes())
def test_meshes_that_meet_at_t_junctions_have_the_one_meshs_gradients(case):
    """A box with T-junctions whose faces are dealt to two or three meshes (a multi-material
    file's faces, a quad split on one side of a material's border): the boundary term's
    light and translation gradients are those of the same faces in one mesh, with shadows
    (the outlines' ends lie in two meshes). Before the meshes that meet at a T-junction
    were taken as one (``render.edges.terms.mesh_units``), each counted its edge as a
    border: on a box of 16 faces in two meshes, 24 x 24, the translation's x 22.42 against
    -3.83 without shadows; with shadows the shadow borders' edges indexed the wrong
    mesh's vertices (an IndexError, or a wrong vertex). To 1e-5: the meshes' faces come
    in another order, so an edge's row may run the other way, and its shadow border's
    chords start from the other end (1e-7 of the gradients measured)."""
    t_box, meshes = case
    one = meshes_gradients([t_box])
    many = meshes_gradients(meshes)
    np.testing.assert_allclose(many, one, rtol=1e-5, atol=1e-5 * np.abs(one).max())


@settings(max_examples=8, deadline=None)
@given(boxes_in_meshes())
def test_pixel_pairs_walk_across_the_meshes_of_one_surface(case):
    """The pixel pairs (``antialias=True``) on a box whose faces are dealt to two or three
    meshes (sharing edges, and meeting at T-junctions): the same light and translation
    gradients as the one mesh's. The walk crosses from mesh to mesh
    (``render.trace.seams.WeldedScene``); before, it took an edge two meshes share for each
    one's border: a box of 12 faces in two meshes had gradients 12-13 % off the one mesh's
    at 16 x 16 and 2-6 % at 48 x 48, and another image (the seams blended as borders)."""
    t_box, meshes = case
    one = meshes_gradients([t_box], antialias=True)
    many = meshes_gradients(meshes, antialias=True)
    np.testing.assert_allclose(many, one, rtol=1e-9, atol=1e-9 * np.abs(one).max())


@settings(max_examples=6, deadline=None)
@given(boxes_in_meshes(), st.sampled_from(["boundary", True]))
def test_meshes_whose_seam_went_through_float32_have_the_one_meshs_gradients(case, antialias):
    """The same boxes in meshes, the last mesh's vertices rounded to float32 and back (a
    part stored or transformed in float32: its seams with the others 1e-8 apart, above
    the 1e-9 welding of one mesh), shadows included: the gradients are the one mesh's, as
    if the seam were closed (``render.trace.topology.seam_distance`` welds across meshes).
    Before, each side of such a seam was a border (the boundary term 20-53 % off on boxes
    split in two without T-junctions, the pixel pairs 4-8 %), and the crossing test found
    the meshes' faces crossing along it; then, with the seams welded, the boundary term
    with shadows was still up to 28 % off (3 of 16 boxes): the edge points' shadow rays
    met the face across the crack (``Visibility.lit_beside``), and a T-junction's vertex,
    one in each of two meshes, cut the long edge twice, leaving a part of no length open
    (``topology._cut_table``)."""
    t_box, meshes = case
    meshes = [*meshes[:-1], through_float32(meshes[-1])]
    one = meshes_gradients([t_box], antialias)
    many = meshes_gradients(meshes, antialias)
    np.testing.assert_allclose(many, one, rtol=1e-5, atol=1e-5 * np.abs(one).max())


def welding_reach(meshes: list[render.Mesh]) -> float:
    """How far apart the positions of ``meshes``' seams may come and still be welded: the
    least ``seam_reach`` of any vertex (``SEAM_LENGTH`` of the shortest open edge of any of
    the meshes, taken one by one, or their ``seam_distance``, whichever is larger)."""
    everything = np.concatenate([np.asarray(m.vertices.data) for m in meshes])
    shortest = np.inf
    for mesh in meshes:
        v = np.asarray(mesh.vertices.data)
        table = mesh_edges(v, np.asarray(mesh.faces)).table
        rows = open_rows_of(table)
        if len(rows):
            ends = v[table.i[rows]] - v[table.j[rows]]
            shortest = min(shortest, np.linalg.norm(ends, axis=1).min())
    return max(seam_distance(everything), SEAM_LENGTH * shortest)


def samples_that_moved(one: list[render.Mesh], many: list[render.Mesh]) -> np.ndarray:
    """(32, 32) bool: the pixels whose centre sees something else in the meshes ``many``
    than in ``one`` (their plain renders over ``floor_scene`` differ by more than 5e-3:
    moving the faces by 1e-4 changes their shading by less than 1e-3), and those pixels'
    four neighbours (the pixel pairs pair a pixel with them)."""

    def plain(meshes):
        return render.render(floor_scene(meshes, 32), antialias=False).data

    moved = np.abs(plain(many) - plain(one)).max(axis=-1) > 5e-3
    grown = moved.copy()
    grown[1:] |= moved[:-1]
    grown[:-1] |= moved[1:]
    grown[:, 1:] |= moved[:, :-1]
    grown[:, :-1] |= moved[:, 1:]
    return grown


@settings(max_examples=8, deadline=None)
@given(
    boxes_in_meshes(),
    st.sampled_from(["boundary", True]),
    st.sampled_from([(4e-6, 2e-4), (1e-4, 2e-3)]),
    st.integers(0, 2**32 - 1),
)
def test_meshes_whose_seams_came_apart_have_the_one_meshs_gradients(case, antialias, far, seed):
    """The same boxes in meshes, the last mesh's positions moved apart from the others by
    up to 4e-6 (1e-6 of the scene's meshes' size: a file whose parts were written with six
    digits) or 1e-4 (3e-4 of the box's edges: parts tessellated and rounded one by one),
    inside the welding of seams and T-junctions (``render.trace.topology.seam_reach``: the
    move is at most the meshes' least reach), shadows included: the one mesh's gradients,
    to 2e-4 and 2e-3 of the largest (the faces moved: 24 boxes of ``benchmarks/seams.py``
    were within 3e-5 and 6.5e-4), over the pixels whose centre sees the same in both (a
    face moved by 1e-4 may carry an edge or a shadow's border across a pixel's centre,
    where one sample's derivative jumps: one box's gradients 2.9e-3 off, the pixel pairs'
    1.1e-2; the same jump when the one mesh is moved: not the seams'; at most a few such
    pixels, or the crack leaks).
    Before, the seams were welded within four float32 steps only, and the boundary term's
    test for an open edge lying on another's (within 1e-6 of the scene) saw such a seam
    closed at some points and open at others: 11-85 % off at 2e-6. Then, welded: an edge
    point was hidden by the face across the crack (in front of it by more than
    ``hidden_points`` allows), the ray beyond a silhouette met that face, the pixel pairs
    took a face's edge tilted by the move for a crease, a T-junction inside the moved mesh
    was not cut (its vertex off the line by more than the mesh's own welding), and the
    shadow borders' side samples, 1e-3 pixels from the border, lay inside the crack, both
    in shadow (``shadow_border._past_the_crack``)."""
    t_box, meshes = case
    distance, tolerance = far
    distance = min(distance, welding_reach(meshes))
    meshes = [*meshes[:-1], moved_apart(meshes[-1], distance, np.random.default_rng(seed))]
    keep = ~samples_that_moved([t_box], meshes)
    assert np.sum(~keep) <= 5 * 6

    def image_of(scene):
        image = render.render(scene, antialias=antialias, interior_samples=1, shadows=True)
        return image * keep[..., None]

    one = light_and_translation([t_box], image_of)
    many = light_and_translation(meshes, image_of)
    np.testing.assert_allclose(many, one, rtol=tolerance, atol=tolerance * np.abs(one).max())


@settings(max_examples=8, deadline=None)
@given(boxes_in_meshes())
def test_a_t_junctions_vertex_in_two_meshes_cuts_the_edge_once(case):
    """The box's faces in meshes, the last one's vertices through float32 (each mesh keeps
    every vertex, so a T-junction's vertex is in two meshes, 1e-8 apart): taken as one,
    the meshes' table is the box's, every row with a face on either side. Before, the
    long edge was cut at both copies of the vertex, and the part between them, of no
    length, was an open row: a border in the boundary term."""
    from render.trace.seams import as_one_mesh, edges_as_one
    from render.trace.topology import open_rows_of

    t_box, meshes = case
    meshes = [*meshes[:-1], through_float32(meshes[-1])]
    topology = {k: mesh_edges(*as_one_mesh([m])) for k, m in enumerate(meshes)}
    table = edges_as_one(meshes, list(range(len(meshes))), topology).table
    box_table = mesh_edges(*as_one_mesh([t_box])).table
    # ``in_meshes``' lone triangle far off (its own three vertices; the box's meshes keep
    # every vertex of the box): its three edges are open
    faraway = any(len(m.vertices.data) == 3 for m in meshes)
    assert len(open_rows_of(table)) == (3 if faraway else 0)
    assert len(table.i) == len(box_table.i) + (3 if faraway else 0)


@settings(max_examples=8, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 11), st.floats(0.2, 0.8)), max_size=4),
    st.integers(0, 2**32 - 1),
    st.sampled_from(["boundary", True]),
)
def test_faces_wound_either_way_give_the_same_image_and_gradients(picks, seed, antialias):
    """A box (with T-junctions) whose faces are wound at random, as scans and soups are:
    the same surface, so the same image and light and translation gradients as the box
    wound consistently, for the boundary term and the pixel pairs: to 1e-6 (an edge's row
    may run the other way, and its shadow border's chords start from the other end: 4e-8
    of the gradients measured), the image to 1e-12. Before,
    the pairs took two neighbours wound apart for a silhouette (``facing`` is by winding;
    ``render.trace.topology.wound_alike``) and a flat crease between them (opposite
    normals): the image 0.31 off, the gradients up to 84 %."""
    t_box = with_t_junctions(box(), picks)
    flipped = wound_at_random(t_box, np.random.default_rng(seed))
    one, two = meshes_gradients([t_box], antialias), meshes_gradients([flipped], antialias)
    np.testing.assert_allclose(two, one, rtol=1e-6, atol=1e-6 * np.abs(one).max())
    images = [render.render(scene_with(m, 24), antialias=antialias).data for m in (t_box, flipped)]
    np.testing.assert_allclose(images[1], images[0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("antialias", ["boundary", True])
def test_a_shadow_across_a_seam_between_meshes_has_the_one_meshs_gradients(antialias):
    """The floor as a 4 x 4 grid, one mesh or its faces dealt to three meshes, under the
    box's shadow (which crosses the meshes' seams): the same light and box-translation
    gradients, to 1e-6 (the boundary term's shadow-border chords, found from faces in
    another order, differ by 6e-8). Before, the pixel pairs took a shadow's two samples on
    two meshes for two objects (no shadow-edge term: a teapot in four meshes had gradients
    1.5 % off its own), and shaded the dark one from the lit one's object (a wrong row)."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z, n=4)
    floor = render.Mesh(v, f, GREY)
    owner = np.random.default_rng(5).integers(0, 3, len(f))
    floors = [render.Mesh(v, f[owner == k], GREY) for k in range(3)]
    results = []
    for ground in ([floor], floors):
        scene = scene_with(box(), 32)
        scene = render.Scene([*ground, scene.objects[1]], scene.lights, scene.camera)
        light, moved = scene.lights[0].position, scene.objects[-1].vertices
        light.requires_grad = moved.requires_grad = True
        weights = np.random.default_rng(7).uniform(0, 1, (32, 32, 3))
        image = render.render(scene, antialias=antialias, interior_samples=1)
        md.sum(image * weights).backward()
        results.append(np.r_[light.grad, moved.grad.sum(axis=0)])
    one, many = results
    np.testing.assert_allclose(many, one, rtol=1e-6, atol=1e-6 * np.abs(one).max())
