"""Step 4 in one call: the pairs of samples across moving edges, and what blending them adds.

``add_edge_terms`` is what the renderer calls with ``antialias=True``. It finds, on plain
arrays, the pairs of adjacent samples across a silhouette or crease
(``render.edges.silhouettes.edge_pairs``) and across a shadow edge
(``render.edges.shadows.shadow_pairs``), each reused from the render cache while the
visibility they come from is unchanged; then, on the tape, where each edge crosses its
pair and how much of each sample's box lies beyond it, and adds the blends to the
samples' colours. With ``antialias="boundary"`` nothing is blended: ``add_boundary_term``
adds the exact term of every edge and shadow border to the image instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.edges.boundary import (
    DirectRadiance,
    boundary_points,
    boundary_term,
    crossing_segments,
    global_welded,
)
from render.edges.geometry import add_to_samples
from render.edges.shadow_boundary import border_chords, shadow_points, shadow_term
from render.edges.shadows import ShadowPairs, shadow_pairs, shadow_terms
from render.edges.silhouettes import EdgePairs, crossings, edge_pairs, edge_updates
from render.scene.cache import RenderCache, light_key
from render.scene.scene import Scene
from render.shade.hits import CameraShading, working_dtype
from render.trace.seams import shared_edges
from render.trace.topology import edge_structure, welding
from render.trace.visibility import Visibility


@dataclass
class EdgeDecisions:
    """The pairs one render blended (constants): across silhouettes and creases
    (``EdgePairs``; None when the boundary integral handles those), across shadow edges
    (``ShadowPairs``, None without shadows)."""

    silhouettes: EdgePairs | None
    shadows: ShadowPairs | None


def mesh_topology(scene: Scene, visibility: Visibility, cache: RenderCache) -> dict:
    """``mesh_edges`` per mesh index in ``scene.meshes``, reused from ``cache`` while the
    geometry is unchanged, and while a mesh's faces and their ``welding`` are (vertices
    that move without merging or collapsing a face, as in a shape optimisation: only the
    welding is computed again)."""

    def per_mesh() -> dict:
        out = {}
        for i, mesh in enumerate(scene.meshes):
            ids, degenerate = welding(mesh.vertices.data, mesh.faces)
            out[i], _ = cache.get(
                ("topology", i),
                [mesh.faces, ids, degenerate],
                lambda f=mesh.faces, w=ids, d=degenerate: edge_structure(f, w, d),
            )
        return out

    topology, _ = cache.get("topology", [visibility.geometry], per_mesh)
    return topology


def find_pairs(scene: Scene, visibility: Visibility, cache: RenderCache, spp: int):
    """The pairs of adjacent samples across moving edges (``EdgeDecisions``), from the
    camera rays' hits and lit masks of step 1, reused from ``cache`` while those are."""
    primary, traced = visibility.primary, visibility.stamp
    topology = mesh_topology(scene, visibility, cache)
    pairs, _ = cache.get(
        "pairs",
        [traced, np.array([m.smooth for m in scene.meshes], dtype=bool)],  # smooth: creases
        lambda: edge_pairs(scene, primary.prim_id, primary.depth, spp, topology),
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
            topology,
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


def add_boundary_term(
    scene: Scene,
    visibility: Visibility,
    cache: RenderCache,
    image: md.Tensor,
    frame,
    max_bounces: int,
    radiance=None,
) -> md.Tensor:
    """The image (H, W, 3) plus the boundary term of every silhouette, crease, sphere
    outline and intersection of surfaces (``render.edges.boundary``): the same values, the
    exact edge derivative. ``radiance``: what the camera sees either side of an edge (None:
    the direct renderer's, ``DirectRadiance``, and the shadow borders of its lights are
    included; another integrator's object: primary visibility only)."""
    topology = mesh_topology(scene, visibility, cache)
    crossings, _ = cache.get(
        "crossings",
        [visibility.geometry],
        lambda: crossing_segments(visibility.primitives[0], global_welded(scene, topology)),
    )
    # Edges that meshes share (a multi-material file's seams) are counted once.
    shared, _ = cache.get(
        "shared edges", [visibility.geometry], lambda: shared_edges(scene, topology)
    )
    direct = radiance is None
    if direct:
        radiance = DirectRadiance(scene, visibility, frame, max_bounces)
    chords = border_chords(scene, visibility, frame, topology, shared) if direct else None
    extra = (chords.start, chords.end) if direct else None
    points, on_chords = boundary_points(
        scene, visibility, frame, topology, crossings, radiance, extra, shared
    )
    shadows = None
    if direct:
        borders = shadow_points(scene, visibility, frame, chords, on_chords, radiance)
        found = shadow_term(scene, borders, frame)
        if found is not None:
            e, rows = found
            shadows = (e, borders.weight[rows], borders.pixel[rows])
    term = boundary_term(scene, points, frame, shadows)
    return image if term is None else image + term
