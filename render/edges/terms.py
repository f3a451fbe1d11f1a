"""Step 4 in one call: the pairs of samples across moving edges, and what blending them adds.

``add_edge_terms`` is what the renderer calls with ``antialias=True``. It finds, on plain
arrays, the pairs of adjacent samples across a silhouette or crease
(``render.edges.silhouettes.edge_pairs``) and across a shadow edge
(``render.edges.shadows.shadow_pairs``), each reused from the render cache while the
visibility they come from is unchanged; then, on the tape, where each edge crosses its
pair and how much of each sample's box lies beyond it, and adds the blends to the
samples' colours. With ``antialias="boundary"`` nothing is blended: ``add_boundary_term``
adds the exact term of every edge and shadow border to the image instead, curve kind by
curve kind (``primary_kinds``, ``ShadowBorder``; ``render.edges.boundary``), at the points
``boundary_points_of`` finds off the tape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from minidiff.tensor import record
from render.edges.boundary.crossing import SurfaceCrossing, crossing_segments, global_welded
from render.edges.boundary.curves import CurveKind, CurvePoints
from render.edges.boundary.mesh_edge import MeshEdge
from render.edges.boundary.moving import geometry_moves
from render.edges.boundary.occlusion import Occluders
from render.edges.boundary.radiance import DirectRadiance
from render.edges.boundary.shadow_border import ShadowBorder
from render.edges.boundary.sphere import SphereCut, SphereOutline
from render.edges.boundary.term import curve_points, with_boundary_term
from render.edges.geometry import add_to_samples
from render.edges.shadows import ShadowPairs, shadow_pairs, shadow_terms
from render.edges.silhouettes import EdgePairs, crossings, edge_pairs, edge_updates
from render.scene.cache import RenderCache, light_key
from render.scene.scene import Scene
from render.shade.hits import CameraShading, working_dtype
from render.trace.outlines import Outlines
from render.trace.seams import (
    WeldedScene,
    as_one_mesh,
    edges_as_one,
    shared_between,
    shared_edges,
    t_junction_pairs,
)
from render.trace.topology import cut_at_t_junctions, edge_structure, seam_distance, welding
from render.trace.visibility import Visibility


@dataclass
class EdgeDecisions:
    """The pairs one render blended (constants): across silhouettes and creases
    (``EdgePairs``; None when the boundary integral handles those), across shadow edges
    (``ShadowPairs``, None without shadows)."""

    silhouettes: EdgePairs | None
    shadows: ShadowPairs | None


def mesh_topology(scene: Scene, geometry: np.ndarray, cache: RenderCache) -> dict:
    """``mesh_edges`` per mesh index in ``scene.meshes``, reused from ``cache`` while the
    geometry (its stamp ``geometry``) is unchanged, and while a mesh's faces and their
    ``welding`` are (vertices that move without merging or collapsing a face, as in a shape
    optimisation: only the welding, and the cuts at T-junctions, are computed again)."""

    def per_mesh() -> dict:
        out = {}
        # T-junctions within the meshes' seam distance, as between meshes (a T-junction's
        # vertex rounded in a file lies off the long edge's line)
        cut = seam_distance(as_one_mesh(scene.meshes)[0]) if scene.meshes else None
        for i, mesh in enumerate(scene.meshes):
            ids, degenerate = welding(mesh.vertices.data, mesh.faces)
            structure, _ = cache.get(
                ("topology", i),
                [mesh.faces, ids, degenerate],
                lambda f=mesh.faces, w=ids, d=degenerate: edge_structure(f, w, d),
            )
            vertices = np.asarray(mesh.vertices.data, np.float64)
            out[i] = cut_at_t_junctions(structure, vertices, mesh.faces, cut)
        return out

    topology, _ = cache.get("topology", [geometry], per_mesh)
    return topology


def find_pairs(scene: Scene, visibility: Visibility, cache: RenderCache, spp: int):
    """The pairs of adjacent samples across moving edges (``EdgeDecisions``), from the
    camera rays' hits and lit masks of step 1, reused from ``cache`` while those are."""
    primary, traced = visibility.primary, visibility.stamp
    topology = mesh_topology(scene, visibility.geometry, cache)
    shared, _ = cache.get(
        "shared edges", [visibility.geometry], lambda: shared_edges(scene, topology)
    )
    welded, _ = cache.get(
        "welded meshes", [visibility.geometry], lambda: WeldedScene.of(scene, topology, shared)
    )
    pairs, _ = cache.get(
        "pairs",
        [traced, np.array([m.smooth for m in scene.meshes], dtype=bool)],  # smooth: creases
        lambda: edge_pairs(scene, primary.prim_id, primary.depth, spp, welded, topology),
    )
    if not visibility.shadows:
        return EdgeDecisions(pairs, None)
    light_keys = [k for light in scene.lights for k in light_key(light)]
    shadow, _ = cache.get(
        "shadow pairs",
        light_keys + [traced],
        lambda: shadow_pairs(
            scene,
            visibility.accelerator(),
            primary,
            visibility.lit,
            spp,
            welded,
            visibility.size,
        ),  # fmt: skip
    )
    return EdgeDecisions(pairs, shadow)


def add_edge_terms(
    scene: Scene,
    visibility: Visibility,
    cache: RenderCache,
    samples: md.Tensor,
    shading: CameraShading,
    frame,
    spp: int,
) -> tuple[md.Tensor, EdgeDecisions]:
    """The samples' colours (N, 3) with every silhouette, crease and shadow edge between
    adjacent samples blended by coverage (on the tape), and the pairs that were blended.
    ``shading``: the camera hits' colours of steps 2-3; ``frame``: the camera frame."""
    found = find_pairs(scene, visibility, cache, spp)
    s, slope = crossings(scene, found.silhouettes, frame, spp, working_dtype(scene))
    silhouettes = edge_updates(samples, found.silhouettes, s, slope)
    shadows = None
    if found.shadows is not None:
        prim_id = visibility.primary.prim_id
        shadows = shadow_terms(scene, found.shadows, prim_id, shading.hits, frame, spp)
    return add_to_samples(samples, [silhouettes, shadows]), found


def differentiated(scene: Scene) -> bool:
    """Whether a derivative can flow from some scene parameter into the image (reverse mode
    with grad enabled, or forward mode): the boundary term is zero in value, so without
    one it would change nothing."""
    grad = md.is_grad_enabled()
    return any(p.tangent is not None or (grad and p.requires_grad) for p in scene.parameters())


def curves_move(scene: Scene, world: Scene) -> bool:
    """Whether a boundary term can carry a derivative: something is differentiated
    (``differentiated``) among what places a curve (``geometry_moves``, in ``world``: the
    scene's objects placed in world space). Not for a material's or a light's strength
    alone, whose gradients need no curve."""
    return differentiated(scene) and geometry_moves(world)


def on_every_parameter(image: md.Tensor, scene: Scene) -> md.Tensor:
    """``image`` (any shape), so that ``backward`` gives every parameter of ``scene`` that
    requires grad (gradients enabled) a gradient, zeros where the image cannot depend on it
    (a mesh no ray sees), whatever route computed the image. Those the image's tape does
    not reach are added as inputs of one more node, with a zero derivative; the image is
    returned as it is when it reaches them all. Without this a scene whose only
    differentiated parameters cannot reach the image left it a constant, and ``backward``
    said that no input required grad, where a compiled route gave zeros."""
    if not md.is_grad_enabled():
        return image
    reached = _leaves_reached(image)
    missing = [p for p in scene.parameters() if p.requires_grad and id(p) not in reached]
    if not missing:
        return image

    def vjp(g: np.ndarray) -> tuple[np.ndarray, ...]:
        return (g,) + tuple(np.zeros(p.shape, p.dtype) for p in missing)

    return record("on_every_parameter", image.data, [image, *missing], vjp, view_of=image,
                  jvp=lambda tangent, *_: tangent)  # fmt: skip


def _leaves_reached(output: md.Tensor) -> set[int]:
    """The ids of the leaf tensors ``output``'s tape reaches (itself, if it is a leaf)."""
    leaves, seen, stack = set(), set(), [output]
    while stack:
        tensor = stack.pop()
        node = tensor.node
        if node is None:
            leaves.add(id(tensor))
        elif id(node) not in seen:
            seen.add(id(node))
            stack.extend(node.inputs)
    return leaves


def primary_kinds(scene: Scene, occluders: Occluders, cache: RenderCache) -> list[CurveKind]:
    """The curve kinds of primary visibility (``render.edges.boundary``): every mesh's
    edges, the surfaces' crossings, every sphere's outline, the spheres' cuts, in the order
    their points are named (the path integrator draws its random numbers by those names).
    What depends on the geometry alone is reused from ``cache``: the mesh topology, the
    crossings and the edges meshes share (``render.trace.seams``: counted once)."""
    topology, crossings, shared = _geometry_tables(scene, occluders, cache)
    (units, shared), _ = cache.get(
        "mesh units", [occluders.geometry], lambda: mesh_units(scene, topology, shared)
    )
    first = np.cumsum([0] + [m.num_faces for m in scene.meshes])
    meshes = [
        MeshEdge(unit, table, int(first[unit.start]), None if shared is None else shared[u])
        for u, (unit, table) in enumerate(units)
    ]
    outlines = [SphereOutline(k) for k in range(len(scene.spheres))]
    return [*meshes, SurfaceCrossing(*crossings), *outlines, SphereCut()]


def mesh_units(scene: Scene, topology: dict, shared) -> tuple[list, list | None]:
    """The meshes whose edges one ``MeshEdge`` takes, each with its table, and the edges
    they share (``shared``: ``shared_edges`` of the meshes, each alone): ([(range of
    indices into ``scene.meshes``, ``EdgeTable``)], ``SharedEdges`` per range or None).
    Each mesh alone, but meshes that meet at a T-junction (a vertex of one inside an open
    edge of the other, ``render.trace.seams.t_junction_pairs``), with every mesh between
    them, as one mesh: their vertices and faces concatenated, welded, and cut at the
    T-junction (``mesh_edges``), so that the edge of one and the edges of the other that
    lie along it are one curve with a face on each side, as in one mesh. Kept apart, each
    counted its edge as a border (a box in two meshes, one face split at a box edge into
    the other mesh's two: the translation gradient's x 22.42 against the one mesh's -3.83,
    without shadows, 24x24). The range keeps the faces' global ids one run."""
    meshes = scene.meshes
    spans: list[list[int]] = []
    pairs = t_junction_pairs(meshes, [topology[k] for k in range(len(meshes))])
    for k, o in sorted(tuple(sorted(p)) for p in pairs):
        if spans and k <= spans[-1][1]:
            spans[-1][1] = max(spans[-1][1], o)
        else:
            spans.append([k, o])
    if not spans:
        return [(range(k, k + 1), topology[k].table) for k in range(len(meshes))], shared
    units, k = [], 0
    for low, high in spans:
        units += [range(m, m + 1) for m in range(k, low)] + [range(low, high + 1)]
        k = high + 1
    units += [range(m, m + 1) for m in range(k, len(meshes))]
    tables = [
        topology[unit.start].table if len(unit) == 1 else edges_as_one(meshes, unit, topology).table
        for unit in units
    ]
    vertices = [as_one_mesh([meshes[m] for m in unit])[0] for unit in units]
    n_faces = [sum(meshes[m].num_faces for m in unit) for unit in units]
    return list(zip(units, tables, strict=True)), shared_between(vertices, tables, n_faces)


def _geometry_tables(scene: Scene, occluders: Occluders, cache: RenderCache) -> tuple:
    """The mesh topology (``mesh_topology``), the crossings of surfaces
    (``crossing_segments``: pairs (m, 2), segments (m, 2, 3)) and the edges meshes share
    (``render.trace.seams.shared_edges``), each reused from ``cache`` while the geometry is
    unchanged."""
    geometry = occluders.geometry
    topology = mesh_topology(scene, geometry, cache)
    crossings, _ = cache.get(
        "crossings",
        [geometry],
        lambda: crossing_segments(occluders.primitives[0], global_welded(scene, topology)),
    )
    shared, _ = cache.get("shared edges", [geometry], lambda: shared_edges(scene, topology))
    return topology, crossings, shared


def scene_outlines(scene: Scene, occluders: Occluders, cache: RenderCache) -> Outlines:
    """The scene's curves that can be outlines seen from a light (``render.trace.outlines``),
    reused from ``cache`` while the geometry is unchanged."""
    topology, _, shared = _geometry_tables(scene, occluders, cache)
    tables = [topology[k] for k in range(len(scene.meshes))], shared
    found, _ = cache.get(
        "outlines",
        [occluders.geometry],
        lambda: Outlines.of(scene, occluders.primitives[0], occluders.size, tables),
    )
    return found


def boundary_points_of(
    scene: Scene, visibility: Visibility, cache: RenderCache, frame, max_bounces: int
) -> tuple[list[CurveKind], list[CurvePoints]]:
    """Off the tape: the curve kinds of the direct renderer's boundary term (every
    silhouette, crease, sphere outline, intersection of surfaces and shadow border,
    ``render.edges.boundary``) and their quadrature points with their constant factors
    (``boundary_points``). The radiance either side of a curve is the renderer's own
    shading (``DirectRadiance``). Nothing is recorded on the tape, so that the renderer
    may find them on another thread while it shades (``minidiff.threads.beside``)."""
    with md.no_grad():
        occluders = Occluders.of(visibility)
        kinds = [
            *primary_kinds(scene, occluders, cache),
            ShadowBorder(visibility, frame, scene_outlines(scene, occluders, cache)),
        ]
        radiance = DirectRadiance(scene, visibility, frame, max_bounces)
        return kinds, curve_points(scene, occluders, radiance, kinds)


def add_boundary_term(
    scene: Scene, image: md.Tensor, frame, found: tuple[list[CurveKind], list[CurvePoints]]
) -> md.Tensor:
    """The direct renderer's image (H, W, 3) plus the boundary term of the curves ``found``
    (``boundary_points_of``): the same values, the exact edge derivative."""
    return with_boundary_term(scene, image, frame, *found)
