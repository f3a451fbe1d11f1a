"""Steps 2, 3 and 5 as one tape node with a hand-written adjoint, for the common case.

When something is differentiated, ``shade_camera_hits`` then ``image_from_hits`` recompute
the camera hits' surfaces (``surface_at``), shade them (``shade_surface``) and average them
into pixels on the tape: some forty NumPy passes over (k, 3) arrays forward and as many
backward. For the common material model (meshes without textures, point and directional
lights, nothing that reflects, float64) ``image`` records the whole of it as one node,
in the manner of path replay:

* forward: the image of ``render.shade.fused.image_values`` (``compiled.shade_hit`` per
  hit, ``fused._film`` per pixel: the same bits as a render that nothing differentiates);
* backward (``render.shade.adjoint_kernels``): every hit re-evaluated, and the incoming
  pixel gradient (over spp for each sample) carried back by hand through the shading, the
  normal and Moller-Trumbore to the node's inputs: the camera frame (``camera_frame``, whose
  own tape takes it on to position, look_at, up and fov), every mesh's vertices and
  per-vertex normals (a smooth mesh's computed ones on the tape, ``vertex_normals``), every
  material's albedo, specular, shininess, ambient and emission, every light's position or
  direction, strength and colour, and the background.

The tape stays the reference: ``tests/render/shade/test_adjoint.py`` ties this node's
gradients to those of ``shade_camera_hits`` + ``image_from_hits`` for every parameter
type. Forward mode (a tangent on any input) takes the tape.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

import minidiff as md
from minidiff import buffers
from minidiff.tensor import record
from render.scene.camera import plain_camera
from render.scene.lights import POINT
from render.scene.scene import Scene
from render.shade import compiled, fused
from render.shade.adjoint_kernels import (
    CHUNKS,
    FRAME,
    LIGHT_SIZE,
    MATERIAL_SIZE,
    backward_rows,
    sum_by_vertex,
    vertex_order,
)
from render.shade.lighting import _nonzero
from render.shade.surface import moves_surface, vertex_normals
from render.trace.visibility import Visibility


def applies(scene: Scene, max_bounces: int) -> bool:
    """Whether ``image`` gives ``scene``'s image (in world space, ``placed``): every object
    a mesh without textures, every light one the compiled kernels shade
    (``compiled_shading``), no material that reflects (with ``max_bounces`` > 0), every
    parameter float64, and none carrying a forward-mode tangent (forward mode takes the
    tape). The caller checks that pixel pairs are off and something is differentiated."""
    if scene.spheres or not all(light.compiled_shading for light in scene.lights):
        return False
    for mesh in scene.meshes:
        if mesh.material.textures or (max_bounces > 0 and mesh.material.reflective):
            return False
    parameters = scene.parameters()
    if any(t.dtype != np.float64 for t in parameters):
        return False
    return all(t.tangent is None for t in parameters)


def route(scene: Scene, pairs: bool, max_bounces: int) -> str:
    """Which code computes steps 2, 3 and 5 of a render of ``scene`` (in world space):

    * "fused": nothing is differentiated and ``fused.applies``: compiled passes, no tape;
    * "node": ``applies`` and something that moves the camera hits is differentiated (the
      camera, a mesh's vertices or normals): ``image``, one node with a compiled adjoint;
    * "tape": the reference (``shade_camera_hits`` + ``image_from_hits``): pixel pairs
      (``pairs``), mirrors, spheres, textures, forward mode, and a scene where only lights
      or materials move, whose hits' surfaces the tape reuses from the render cache
      (faster there than re-evaluating every hit)."""
    grad = md.is_grad_enabled()
    moving = [p for p in scene.parameters() if p.tangent is not None or (grad and p.requires_grad)]
    if pairs:
        return "tape"
    if not moving:
        return "fused" if fused.applies(scene, max_bounces) else "tape"
    camera = scene.camera
    movers = [camera.position, camera.look_at, camera.up, camera.fov]
    movers += [t for mesh in scene.meshes for t in moves_surface(mesh)]
    if any(p.is_differentiated() for p in movers) and applies(scene, max_bounces):
        return "node"
    return "tape"


@dataclass
class _Inputs:
    """The node's inputs (tensors on the tape) and where each one's gradient comes from.

    frame: (forward, right, up, eye) (3,) each; per mesh its vertices (V, 3) and, if
    smooth, its vertex normals (V, 3) (else None); per material (one per mesh, in mesh
    order) albedo, specular, shininess, ambient, emission; per light its vector (a point
    light's position, a directional light's direction of travel), strength and colour; the
    background."""

    frame: tuple
    vertices: list
    normals: list
    materials: list
    lights: list
    background: md.Tensor

    def flat(self) -> list[md.Tensor]:
        """Every input, in the order ``_gradients`` returns theirs."""
        normals = [n for n in self.normals if n is not None]
        materials = [t for m in self.materials for t in m]
        lights = [t for light in self.lights for t in light]
        return [*self.frame, *self.vertices, *normals, *materials, *lights, self.background]


def _inputs(scene: Scene, frame) -> _Inputs:
    """The node's inputs for ``scene`` and its camera ``frame`` (``camera_frame``). A smooth
    mesh without normals of its own gets ``vertex_normals`` computed here, on the tape, so
    that the tape carries their gradient on to the vertices."""
    normals = []
    for mesh in scene.meshes:
        if not mesh.smooth:
            normals.append(None)
        elif mesh.normals is not None:
            normals.append(mesh.normals)
        else:
            normals.append(vertex_normals(mesh.vertices, mesh.faces))
    materials = [
        (m.albedo, m.specular, m.shininess, m.ambient, m.emission)
        for m in (mesh.material for mesh in scene.meshes)
    ]
    lights = []
    for light in scene.lights:
        vector = light.position if light.KIND == POINT else light.direction
        strength = light.intensity if light.KIND == POINT else light.irradiance
        lights.append((vector, strength, light.color))
    vertices = [mesh.vertices for mesh in scene.meshes]
    return _Inputs(tuple(frame), vertices, normals, materials, lights, scene.background)


def image(scene: Scene, visibility: Visibility, frame, spp: int) -> md.Tensor:
    """The (H, W, 3) image of ``scene`` (world space; only where ``applies``) from its
    ``visibility`` (camera rays, ``spp`` per pixel, their hits and lit masks) and its camera
    ``frame`` (``camera_frame``, on the tape): steps 2, 3 and 5 as one node on the tape,
    whose value is ``fused.image_values``' and whose VJP ``_backward`` computes."""
    inputs = _inputs(scene, frame)
    camera = plain_camera(frame)
    values, _ = fused.image_values(scene, visibility, camera, spp)
    reaching = _reaching(scene, inputs, visibility)
    used = [t for t, reaches in zip(inputs.flat(), reaching, strict=True) if reaches]
    if not (md.is_grad_enabled() and any(t.requires_grad for t in used)):
        return md.Tensor(values)  # nothing to carry back: no node
    packed = _pack(scene, inputs, camera)

    def vjp(g_image: np.ndarray) -> tuple[np.ndarray | None, ...]:
        grads = _backward(scene, visibility, inputs, packed, spp, g_image)
        return tuple(g for g, reaches in zip(grads, reaching, strict=True) if reaches)

    return record("shaded_image", values, used, vjp, saves=used)


def _reaching(scene: Scene, inputs: _Inputs, visibility: Visibility) -> list[bool]:
    """Per input (``_Inputs.flat``'s order), whether the image depends on it as it does on
    the tape: the background always; the camera and the lights where some ray hits; a
    mesh's vertices, normals and material where some ray hits it, its shininess only with
    a lobe (``lighting._nonzero(specular)``). An input that does not reach the image gets
    no gradient (None, as from the tape), and one that alone is differentiated leaves the
    image a constant."""
    primary = visibility.primary
    meshes = scene.meshes
    faces_per_mesh = [mesh.num_faces for mesh in meshes]
    if len(primary.hit_rays):
        per_face = np.bincount(primary.prim_id[primary.hit_rays], minlength=sum(faces_per_mesh))
        starts = np.cumsum([0] + faces_per_mesh[:-1])
        hit = np.array(
            [per_face[a : a + n].any() for a, n in zip(starts, faces_per_mesh, strict=True)]
        )
    else:
        hit = np.zeros(len(meshes), bool)
    anything = bool(np.any(hit))
    reaching = [anything] * len(inputs.frame) + list(hit)
    reaching += [bool(h) for h, n in zip(hit, inputs.normals, strict=True) if n is not None]
    for h, mesh in zip(hit, meshes, strict=True):
        lobe = bool(h) and _nonzero(mesh.material.specular)
        reaching += [bool(h), bool(h), lobe, bool(h), bool(h)]
    reaching += [anything] * (3 * len(inputs.lights))
    return reaching + [True]


@dataclass
class _Packed:
    """What the backward kernel reads, as plain arrays: the camera (eye, right, up,
    forward); the meshes stacked (vertices (V, 3), faces (F, 3) with global vertex ids,
    vertex normals (V, 3) (zero rows on flat meshes), the mesh of every face (F,), per mesh
    smooth (M,)); the materials stacked (``_materials``); the lights
    (``compiled.lights_pack``); the vertex count per mesh."""

    camera: tuple
    meshes: tuple
    materials: tuple
    lights: tuple
    vertex_counts: list


def _pack(scene: Scene, inputs: _Inputs, camera) -> _Packed:
    forward, right, up, eye = camera
    meshes = scene.meshes
    counts = [mesh.vertices.shape[0] for mesh in meshes]
    starts = np.cumsum([0] + counts[:-1])
    vertices = np.concatenate([mesh.vertices.data for mesh in meshes]).reshape(-1, 3)
    faces = np.concatenate(
        [mesh.faces + start for mesh, start in zip(meshes, starts, strict=True)]
    ).reshape(-1, 3)
    normals = np.concatenate(
        [
            np.zeros((count, 3)) if n is None else np.asarray(n.data, np.float64)
            for n, count in zip(inputs.normals, counts, strict=True)
        ]
    ).reshape(-1, 3)
    mesh_of = np.repeat(np.arange(len(meshes)), [mesh.num_faces for mesh in meshes])
    smooth = np.array([mesh.smooth for mesh in meshes], bool)
    return _Packed(
        (eye, right, up, forward),
        (vertices, np.ascontiguousarray(faces, np.int64), normals, mesh_of, smooth),
        _materials(meshes),
        compiled.lights_pack(scene.lights),
        counts,
    )


def _materials(meshes) -> tuple:
    """Per mesh (M rows): albedo, specular, ambient, emission (M, 3) each, shininess (M,),
    and whether the Blinn-Phong lobe is on (``lighting._nonzero(specular)``, as the tape
    decides) (M,) bool."""
    materials = [mesh.material for mesh in meshes]

    def rows(name: str) -> np.ndarray:
        values = [np.broadcast_to(getattr(m, name).data, (3,)) for m in materials]
        return np.array(values, np.float64).reshape(-1, 3)

    shininess = np.array([float(m.shininess.data) for m in materials], np.float64)
    lobe = np.array([_nonzero(m.specular) for m in materials], bool)
    return rows("albedo"), rows("specular"), rows("ambient"), rows("emission"), shininess, lobe


def _backward(scene, visibility, inputs: _Inputs, packed: _Packed, spp, g_image) -> tuple:
    """The node's VJP: the gradient of every input (``_Inputs.flat``'s order; None for those
    that do not require grad) from dL/dimage ``g_image`` (H, W, 3)."""
    primary = visibility.primary
    k = len(primary.hit_rays)
    n_lights = len(scene.lights)
    lit = np.empty((n_lights, k))
    for j, mask in enumerate(visibility.lit):
        lit[j] = mask
    geometry = any(t.requires_grad for t in inputs.frame) or any(
        t.requires_grad for t in inputs.vertices
    )
    corners_wanted = any(t.requires_grad for t in inputs.vertices) or any(
        n is not None and n.requires_grad for n in inputs.normals
    )
    shininess_wanted = any(m[2].requires_grad for m in inputs.materials)
    normals_wanted = any(n is not None and n.requires_grad for n in inputs.normals)
    n_meshes = len(inputs.vertices)
    width = FRAME + LIGHT_SIZE * n_lights + MATERIAL_SIZE * n_meshes
    sums = np.zeros((CHUNKS, width))
    corner_v = buffers.empty((k if corners_wanted else 0, 3, 3), np.float64)
    corner_n = buffers.empty((k if normals_wanted else 0, 3, 3), np.float64)
    pixels = np.ascontiguousarray(g_image, np.float64).reshape(-1, 3)
    threads = numba.get_num_threads()
    backward_rows(
        primary.prim_id, primary.hit_rays, primary.coords, spp, pixels, packed.camera,
        packed.meshes, packed.materials, packed.lights, lit, (geometry or corners_wanted,
        shininess_wanted), threads, sums, corner_v, corner_n,
    )  # fmt: skip
    totals = np.sum(sums, axis=0)  # chunk by chunk, in order: the same on any thread count
    grads: list[np.ndarray | None] = []
    grads += _frame_grads(inputs.frame, totals)
    grads += _vertex_grads(inputs, packed, primary, corner_v, corner_n, threads)
    grads += _material_grads(inputs.materials, totals, n_lights)
    grads += _light_grads(scene.lights, inputs.lights, totals)
    grads.append(_background_grad(scene, primary.prim_id, pixels, spp))
    return tuple(grads)


def _frame_grads(frame, totals) -> list:
    """forward, right, up, eye: their sums' first twelve numbers."""
    return [
        totals[3 * i : 3 * i + 3].copy() if t.requires_grad else None for i, t in enumerate(frame)
    ]


def _vertex_grads(inputs: _Inputs, packed: _Packed, primary, corner_v, corner_n, threads):
    """Per mesh its vertices' gradient (V, 3), then per smooth mesh its normals' (V, 3):
    every hit's contributions to its face's corners, summed vertex by vertex in hit
    order (``vertex_order``, ``sum_by_vertex``)."""
    wanted_v = [t.requires_grad for t in inputs.vertices]
    wanted_n = [n.requires_grad for n in inputs.normals if n is not None]
    if not any(wanted_v) and not any(wanted_n):
        return [None] * (len(wanted_v) + len(wanted_n))
    faces = packed.meshes[1]
    n_vertices = sum(packed.vertex_counts)
    start, order = vertex_order(primary.prim_id, primary.hit_rays, faces, n_vertices, threads)
    g_v = np.zeros((n_vertices, 3))
    g_n = np.zeros((n_vertices if corner_n.shape[0] else 0, 3))
    sum_by_vertex(start, order, corner_v, corner_n, threads, g_v, g_n)
    ends = np.cumsum(packed.vertex_counts)
    parts_v = np.split(g_v, ends[:-1])
    out = [part if want else None for part, want in zip(parts_v, wanted_v, strict=True)]
    for index, n in enumerate(inputs.normals):
        if n is not None:
            out.append(np.split(g_n, ends[:-1])[index] if n.requires_grad else None)
    return out


def _material_grads(materials, totals, n_lights: int) -> list:
    """Per material albedo (3,), specular, shininess (), ambient, emission (their own
    shapes: a scalar's channels summed)."""
    out = []
    for index, tensors in enumerate(materials):
        base = FRAME + LIGHT_SIZE * n_lights + MATERIAL_SIZE * index
        parts = (
            totals[base : base + 3],
            totals[base + 3 : base + 6],
            totals[base + 6],
            totals[base + 7 : base + 10],
            totals[base + 10 : base + 13],
        )
        for tensor, part in zip(tensors, parts, strict=True):
            out.append(_shaped(part, tensor) if tensor.requires_grad else None)
    return out


def _shaped(gradient: np.ndarray | float, tensor: md.Tensor) -> np.ndarray:
    """``gradient`` (3,) or () summed to ``tensor``'s shape (a scalar parameter broadcast to
    three channels gets their sum)."""
    gradient = np.asarray(gradient, np.float64)
    if tensor.shape == () and gradient.shape == (3,):
        return np.asarray(gradient.sum())
    return gradient.reshape(tensor.shape).copy()


def _light_grads(lights, tensors, totals) -> list:
    """Per light its vector's (3,), strength's () and colour's (3,) gradients. The kernel
    sums a directional light's gradient with respect to the unit vector towards it,
    l = normalize(-w); w's is -(g - l (l . g)) / |w| (``md.normalize``'s adjoint)."""
    out = []
    for j, (light, (vector, strength, colour)) in enumerate(zip(lights, tensors, strict=True)):
        base = FRAME + LIGHT_SIZE * j
        g_vector = totals[base : base + 3].copy()
        if light.KIND != POINT:
            w = np.asarray(vector.data, np.float64)
            length = math.sqrt(float(w @ w))
            unit = -w / length
            g_vector = -(g_vector - unit * float(unit @ g_vector)) / length
        out.append(g_vector if vector.requires_grad else None)
        out.append(np.asarray(totals[base + 3]) if strength.requires_grad else None)
        out.append(totals[base + 4 : base + 7].copy() if colour.requires_grad else None)
    return out


def _background_grad(scene: Scene, prim_id, pixels, spp: int) -> np.ndarray | None:
    """The background's gradient: each pixel's gradient times its share of misses."""
    if not scene.background.requires_grad:
        return None
    n_pixels = pixels.shape[0]
    misses = np.bincount(np.flatnonzero(prim_id < 0) // spp, minlength=n_pixels)
    return np.sum(pixels * (misses / spp)[:, None], axis=0)
