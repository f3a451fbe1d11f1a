"""The paths' gradient compiled: the depths of a path in one traced function, its VJP each
path's reverse sweep inside the kernel.

A path's radiance is L = sum_k beta_k C_k with beta_0 = 1 and beta_{k+1} = beta_k F_k: C_k
what vertex k adds (emission, next-event estimation, the point and directional lights, the
environment after a last bounce), F_k the factor of the segment to vertex k + 1.
``vertex_terms`` computes C_k and F_k of one vertex from the scene's parameters and the
path's recorded decisions (which primitive, where on it, which light sample), with the
readable formulas the tape runs (``surface_at``, ``light_contribution``, ``brdf``);
``path_terms`` places vertex 0, 1, ... in turn (``next_vertex``: each once, handed on)
and sums L. ``minidiff.compile`` traces that into one function of *one path* (up to
``SEGMENT`` depths of it), run in parallel over the paths, its VJP generated from the
primitives' own rules: reverse mode through the path, with the path's values held inside
the kernel while its reverse sweep runs, so nothing is kept per depth but the batch's
records (``render.path.sample.records``), which the render wrote anyway. Every parameter
(vertices, transforms, light positions, the camera, materials, lights, the environment)
gets its gradient at the speed of the others.

On the tape (``replay._Window``) the same gradient is taken one depth at a time, a window
per depth, each on its own tape (Vicini et al.'s path replay), for what does not compile
here. What a row subset did on the tape is a selection here: a path without next-event
estimation, that does not go on, or that has ended, has its terms multiplied by a zero
weight, and the values those terms divide by are made safe first (``md.where`` twice, a
harmless point on the primitive), so that neither value nor gradient sees a NaN.

The scene is read as tables shared by every path (``render.path.sample.tables.Tables``): all
meshes' vertices, shading normals and faces concatenated (a primitive id is a row of the
face table), and per object its material. They are built once per batch on the tape from
the parameters, handed to the compiled function as leaves, and one last ``backward``
carries their gradients to the parameters (``Tables.carried``).

Mirror bounces are followed (the next vertex where the reflected ray meets its primitive),
and textures read (``lighting.lookup``, the tape's own lookup, from one table of every
object's texels). It applies to float64 scenes whose lights' shading compiles
(``tables.compiles``); otherwise the tape's windows take the batch.
``tests/render/path/test_window.py`` and ``test_replay_depth.py`` tie the two together
for every kind of parameter. The paths are replayed ``SEGMENT`` depths at a time
(``backpropagate``), so that each kernel stays small enough to compile in a second or
two; the kernels are then cached on disk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.path.sample import records
from render.path.sample.records import MIRROR, STOP, PathBatch
from render.path.sample.tables import MATERIAL_FIELDS, TEXTURE_FIELDS, Tables, far_side_of, role_of
from render.scene.camera import ray_directions
from render.scene.materials import Material
from render.scene.scene import Mesh, Sphere
from render.shade.compiled import held_lights
from render.shade.lighting import Appearance, brdf, light_contribution, lookup
from render.shade.surface import column, surface_at, toward_ray


@dataclass
class _Vertex:
    """Path vertices inside the compiled function: points, unit geometric and shading
    normals (k, 3), the area element's ``stretch`` (k,) (1 for points found by rays), the
    direction back ``wo`` (k, 3) (set by the caller), the object each lies on (k,) and its
    UV (k, 2) (where the scene has a texture, else None)."""

    points: object
    geometric: object
    shading: object
    stretch: object
    wo: object
    obj: object
    uv: object = None


def held_world(vertices, normals, faces, centers, radii, smooth, uvs=None, texels=None) -> tuple:
    """What ``surface`` reads, from the tables' (traced) arrays: (all meshes as one
    ``Mesh`` (smooth; ``smooth`` (O,) says which objects are), smooth, the spheres'
    centres and radii, the untextured material the spheres hold). With ``uvs`` (V, 2) and
    a table of ``texels``, the mesh is textured: its points get their UVs."""
    plain = Material.holding(texture=None, specular_texture=None, ambient_texture=None)
    look = plain if uvs is None else Material.holding(
        texture=texels, specular_texture=None, ambient_texture=None
    )  # fmt: skip
    mesh = Mesh.holding(vertices=vertices, faces=faces, normals=normals, uvs=uvs, smooth=True,
                        material=look, transform=None)  # fmt: skip
    return mesh, smooth, centers, radii, plain


def surface(world, role, origins=None, directions=None, far=None) -> _Vertex:
    """Points on the primitives of ``role`` (``Tables.role``): at its coordinates ``local``
    (an ``AREA`` vertex) or where the rays meet them (``far``: which rays meet a sphere's far
    side). ``surface_at`` on the concatenated mesh and on the spheres, each point taking its
    own primitive's; a flat mesh's shading normal is its geometric one."""
    mesh, smooth, centers, radii, plain = world
    face, sphere, on_sphere, obj, local = role
    if origins is not None:
        local = None
    found = []
    if face is not None:
        tri = surface_at(mesh, face, origins, directions, local=local, divide=True)
        tri.shading = md.where(column(smooth[obj]), tri.shading, tri.geometric)
        found.append(tri)
    if sphere is not None:
        ball = Sphere.holding(center=centers[sphere], radius=radii[sphere], material=plain)
        found.append(surface_at(ball, sphere, origins, directions, local=local, far_root=far))
    uv = found[0].uv if face is not None else None  # (a sphere has none: never read)
    if len(found) == 1:
        only = found[0]
        points, geometric, shading, stretch = (
            only.points,
            only.geometric,
            only.shading,
            only.stretch,
        )
    else:
        tri, ball = found
        pick = column(on_sphere)
        points = md.where(pick, ball.points, tri.points)
        geometric = md.where(pick, ball.geometric, tri.geometric)
        shading = md.where(pick, ball.shading, tri.shading)
        stretch = None if local is None else md.where(on_sphere, ball.stretch, tri.stretch)
    stretch = 1.0 if local is None else stretch
    return _Vertex(points, geometric, shading, stretch, None, obj, uv)


_SHARED = ("frame", "vertices", "normals", "faces", "centers", "radii", "smooth", "materials",
           "lights", "background", "primitives", "harmless", "uvs", "textures")  # fmt: skip


def path_terms(coords, first_prim, start, ints, floats, lit, count, frame, vertices, normals,
               faces, centers, radii, smooth, materials, lights, background, primitives,
               harmless, uvs, textures, form):  # fmt: skip
    """The radiance (n, 3) of a segment of paths, sum_k beta_k C_k with beta_{k+1} = beta_k
    F_k, vertex after vertex (``vertex_terms``, ``next_vertex``). Batched (n paths): the
    segment's first vertex, ``start`` None: the camera's ray through ``coords`` (n, 2) meets
    ``first_prim`` (n,); else (beta, points, geometric, shading, wo[, uv]) of the vertex
    and its throughput, from the segment before; per depth k of the segment (tuples): the
    records' ``ints`` (n, I_FIELDS), ``floats`` (n, F_FIELDS) and ``lit`` (n, max(L, 1))
    (``render.path.sample.records``), one more than the segment's vertices when a segment
    follows (its first vertex is placed here); ``count`` (n,) each path's number of
    vertices from the segment's first on. Shared: the tables (``Tables``; ``primitives``:
    what a point on each primitive reads, ``role_of``; ``uvs`` and ``textures``: None and
    () without textures), and ``harmless`` () a primitive of some size
    (``Tables.harmless``). Static ``form``: (the lights' classes and parameter names,
    whether any material is glossy, the number of lights L, whether a path meets a mirror,
    whether a segment follows: then the outputs are the radiance and the next segment's
    ``start``).

    Where a path has ended (vertex k >= count), vertex k is read at a harmless point: on
    the ``harmless`` primitive at fixed coordinates that differ from one depth to the
    next, so that two such vertices in a row are never the same point (the direction
    between them is divided by its length). Its C_k and the factor before it are zero, so
    neither value nor gradient sees it."""
    kinds, glossy, n_lights, mirrors, follows = form
    texels = next((t[0] for t in textures if t is not None), None)
    world = held_world(vertices, normals, faces, centers, radii, smooth, uvs, texels)
    scene = (world, held_lights(kinds, lights), materials, textures, background, primitives,
             harmless, glossy)  # fmt: skip
    beta = None
    if start is None:  # vertex 0: where the camera's ray meets
        directions = ray_directions(frame, coords)
        far = far_side_of(primitives, first_prim)
        role = role_of(primitives, first_prim, _UNUSED[0])
        v = surface(world, role, frame[3], directions, far)
        v.wo = -md.normalize(directions)
    else:  # the vertex the segment before placed, on the primitive it placed it on
        beta, points, geometric, shading, wo = start[:5]
        prim = md.where(count > 0, ints[0][:, records.PRIM], harmless)
        obj = role_of(primitives, prim, _UNUSED[0])[3]
        uv = start[5] if uvs is not None else None
        v = _Vertex(points, geometric, shading, None, wo, obj, uv)
    total = None
    for k in range(len(floats) - (1 if follows else 0)):
        exists, goes = count > k, count > k + 1
        here = (ints[k], floats[k], md.where(lit[k][:, :n_lights], 1.0, 0.0) if n_lights else None)
        nxt = None
        if k + 1 < len(ints):
            mirror = (ints[k][:, records.NEXT] == MIRROR) & goes if mirrors else None
            following = (ints[k + 1], floats[k + 1])
            nxt = next_vertex(world, primitives, harmless, v, following, goes, mirror, k + 1)
        added, factor = vertex_terms(scene, v, here, nxt, goes, mirrors)
        added = md.where(column(exists), added, 0.0)
        added = added if beta is None else beta * added
        total = added if total is None else total + added
        beta = factor if beta is None else beta * factor
        v = nxt
    if not follows:
        return total
    handed = (beta, v.points, v.geometric, v.shading, v.wo)
    return (total, *handed, v.uv) if uvs is not None else (total, *handed)


def next_vertex(world, primitives, harmless, v: _Vertex, record, goes, mirror, depth: int):
    """Vertex ``depth`` of the paths, which follows ``v`` (``record``: its ints and floats):
    ``AREA`` ones at their recorded coordinates on their primitives, where ``mirror``
    (None: nowhere) where the ray reflected at ``v`` meets the primitive
    (``transport.next_vertex``), its direction back ``wo`` set. Where the path does not go
    on (``goes`` false) a harmless point (``path_terms``)."""
    ints, floats = record
    prim = md.where(goes, ints[:, records.PRIM], harmless)
    local = md.where(column(goes), floats[:, : records.LOCAL + 3], _UNUSED[depth % 2])
    role = role_of(primitives, prim, local)
    placed = surface(world, role)
    placed.wo = md.normalize(v.points - placed.points)
    if mirror is None:
        return placed
    # The reflected ray about the shading normal facing the viewer, from the vertex. Where
    # the path does not bounce off a mirror, a ray along the placed point's normal to it
    # (it meets the primitive there: no ray that misses, so no NaN in the unused values).
    ns = v.shading * toward_ray(v.geometric, -v.wo)
    reflected = 2.0 * column(md.dot(v.wo, ns)) * ns - v.wo
    pick = column(mirror)
    origins = md.where(pick, v.points, placed.points + placed.geometric)
    far = None
    if role[1] is not None:  # a ray that starts inside a sphere meets its far side
        _, _, centers, radii, _ = world
        far = md.norm(origins - centers[role[1]]) < radii[role[1]]
    found = surface(world, role, origins, md.where(pick, reflected, -placed.geometric), far)
    return _Vertex(
        md.where(pick, found.points, placed.points),
        md.where(pick, found.geometric, placed.geometric),
        md.where(pick, found.shading, placed.shading),
        md.where(mirror, 1.0, placed.stretch),
        md.where(pick, -md.normalize(reflected), placed.wo),
        placed.obj,
        None if placed.uv is None else md.where(pick, found.uv, placed.uv),
    )


def vertex_terms(scene, v: _Vertex, here, nxt: _Vertex | None, goes, mirrors: bool):
    """(C_k (n, 3), F_k (n, 3)): what vertex ``v`` adds to its path and the factor of the
    segment to the next vertex ``nxt`` (None after the last depth: F_k is then unused),
    ``transport._at_vertex``'s terms. ``scene``: (the held world, its lights, the material
    and texture tables, the environment, ``Tables.primitives``, a harmless primitive,
    whether any material is glossy);
    ``here``: the vertex's records (ints, floats, the lights that reach it (n, L) or None);
    ``goes`` (n,): whether the path goes on; ``mirrors``: whether a path meets a mirror."""
    world, scene_lights, materials, textures, background, primitives, harmless, glossy = scene
    albedo, specular, shininess, emission, reflectance = materials
    ints, floats, lit = here
    zero = md.tensor(0.0)
    obj = v.obj
    side = toward_ray(v.geometric, -v.wo)  # two-sided: the shading normal faces the viewer
    ns = v.shading * side
    textured = dict(zip(TEXTURE_FIELDS, textures or (None, None), strict=True))
    look = Appearance(
        _textured(albedo[obj], textured["texture"], obj, v.uv, replaces=True),
        _textured(specular[obj], textured["specular_texture"], obj, v.uv) if glossy else zero,
        zero, shininess[obj], None,
    )  # fmt: skip
    diffuse = look.albedo * (1.0 / np.pi)
    view = v.wo if glossy else None

    # Emission seen here (from its front only), MIS-weighted; the point and directional
    # lights.
    added = emission[obj] * column(md.maximum(side[:, 0], 0.0) * floats[:, records.EMIT])
    for j, light in enumerate(scene_lights):
        added = added + light_contribution(v.points, ns, -v.wo, look, light, lit[:, j])

    def toward(point_of, valid):
        """The unit direction from the vertex to another point, with its squared distance
        (1 where ``valid`` is false, so nothing divides by zero there)."""
        to = point_of - v.points
        d2 = md.where(valid, md.dot(to, to), 1.0)
        return to / column(md.sqrt(d2)), d2

    def bounce_weight(wi, scale):
        """f cos / (p q) for unit directions wi (``scale``: 1 / (p q), 0 where unused)."""
        cos = md.maximum(md.dot(ns, wi), 0.0)
        return brdf(ns, view, wi, diffuse, look) * column(cos * scale)

    # Next-event estimation on the area lights: a point on an emitting primitive, whose
    # area is half the stretch on a triangle, 4 pi times it on a sphere.
    nee_weight = floats[:, records.NEE_WEIGHT]
    nee_local = floats[:, records.NEE_LOCAL : records.NEE_LOCAL + 3]
    sampled = nee_weight > 0.0
    nee_prim = md.where(sampled, ints[:, records.NEE_PRIM], harmless)
    nee_role = role_of(primitives, nee_prim, _middle_unless(sampled, nee_local))
    light = surface(world, nee_role)
    wi, d2 = toward(light.points, sampled)
    cos_x = md.maximum(md.dot(ns, wi), 0.0)
    cos_z = md.abs(md.dot(light.geometric, wi))
    f = brdf(ns, view, wi, diffuse, look)
    area = light.stretch * md.where(nee_role[2], 4.0 * np.pi, 0.5)
    scale = cos_x * cos_z / d2 * area * nee_weight
    added = added + f * column(scale) * emission[light.obj]

    # The continuation's constant 1 / (p q): the direction's density (a mirror: the lobe's
    # probability), Russian roulette's survival (0 where the path ended: then unused).
    density = floats[:, records.NEXT_PDF] * floats[:, records.SURVIVE]
    scale = 1.0 / md.where(density != 0.0, density, 1.0)
    after_mirror = ints[:, records.NEXT] == MIRROR if mirrors else None

    def bounce(wi, weight):
        """F_k for unit directions wi, ``weight`` 1 / (p q) where used, else 0: f cos /
        (p q), or off a mirror its reflectance / q."""
        factor = bounce_weight(wi, weight)
        if after_mirror is None:
            return factor
        return md.where(column(after_mirror), reflectance[obj] * column(weight), factor)

    # Paths that leave the scene see the environment.
    leaves = (ints[:, records.ESCAPE] != 0) & (ints[:, records.NEXT] != STOP)
    away = floats[:, records.ESCAPE_DIR : records.ESCAPE_DIR + 3]
    added = added + bounce(away, md.where(leaves, scale, 0.0)) * background
    if nxt is None:
        return added, added

    # The factor of the segment to the next vertex, with the change of measure to its area
    # (a mirror's next vertex is where its ray meets: no change of measure).
    wi, d2 = toward(nxt.points, goes)
    measured = goes if after_mirror is None else goes & ~after_mirror
    geometry = md.where(measured, md.abs(md.dot(nxt.geometric, wi)) / d2 * nxt.stretch, 1.0)
    factor = bounce(wi, md.where(goes, scale, 0.0)) * column(geometry / md.detach(geometry))
    return added, factor


#: The coordinates of a vertex after its path has ended, by the parity of its depth.
_UNUSED = (np.full(3, 1.0 / 3.0), np.array([0.5, 0.25, 0.25]))

_path = md.compile(path_terms, shared=_SHARED)


#: A path is replayed this many depths at a time: one compiled function of a segment of
#: its vertices, the segment's last vertex and throughput handed to the next (its gradient
#: handed back). A kernel's compile time grows faster than its depths (one of 32 depths
#: took 4.2 s where one of 8 takes 0.5), and a later segment runs only over the paths
#: that reach it; shorter segments would trace the first segments' values twice, once to
#: hand them on and once in the VJP (4 depths: a depth-8 gradient 24 % slower).
SEGMENT = 8


@dataclass
class _Segment:
    """``SEGMENT`` depths (or fewer, the last) of a batch's paths ``rows`` (those that reach
    the first of them; None: every path), where they stand among the rows of the segment
    before (``within``; None for the first), the arguments of ``path_terms`` but its start,
    and whether a segment follows."""

    rows: np.ndarray | None
    within: np.ndarray | None
    arguments: tuple
    follows: bool


def _segments(tables: Tables, batch: PathBatch) -> list[_Segment]:
    """The batch's paths as segments of ``SEGMENT`` depths (``path_terms``' arguments):
    the batch's records (``Records.of``), a camera ray that misses read as one that hits
    (the first path's that does: its terms are zero), and the tables."""
    rec = records.Records.of(batch, len(tables.lights))
    depth, count = int(rec.count.max(initial=0)), rec.count
    coords = np.ascontiguousarray(rec.floats[0, :, records.COORD : records.COORD + 2])
    first_prim = rec.ints[0, :, records.PRIM].copy()
    missed = np.flatnonzero(count == 0)
    if len(missed) and depth:
        seen = int(np.argmax(count > 0))
        coords[missed], first_prim[missed] = coords[seen], first_prim[seen]
    shared = (
        tables.frame, tables.vertices, tables.normals, tables.faces, tables.centers,
        tables.radii, tables.smooth, tables.materials, tables.lights, tables.background,
        tables.primitives, np.int64(tables.harmless), tables.uvs, tables.textures,
    )  # fmt: skip
    # (no reflectance anywhere: no path meets a mirror, and its records need no reading)
    reflectance = tables.materials[MATERIAL_FIELDS.index("reflectance")]
    mirrors = bool(np.any(reflectance.data)) and batch.meets_mirror()
    out, before = [], None
    for first in range(0, depth, SEGMENT):
        last = min(first + SEGMENT, depth)
        follows = last < depth
        rows = within = None
        if first > 0:
            rows = np.flatnonzero(count > first)
            within = rows if before is None else np.searchsorted(before, rows)

        def take(array, rows=rows):
            return array if rows is None else np.take(array, rows, axis=0)

        depths = range(first, last + (1 if follows else 0))
        fields = (rec.ints, rec.floats, rec.lit)
        per_depth = tuple(tuple(take(r[k]) for k in depths) for r in fields)
        form = (tables.kinds, tables.glossy, rec.n_lights, mirrors, follows)
        arguments = (take(coords), take(first_prim), *per_depth, take(count) - first, *shared,
                     form)  # fmt: skip
        out.append(_Segment(rows, within, arguments, follows))
        before = rows
    return out


def _call(segment: _Segment, start) -> tuple:
    """``path_terms``' arguments for ``segment`` with its ``start``."""
    coords, first_prim, *rest = segment.arguments
    return (coords, first_prim, start, *rest)


def _sweep(segments: list[_Segment], handed_on):
    """Each segment with its start (None for the first: the camera's rays) and its outputs
    as Tensors (its radiance, then what it hands on), segment after segment: a segment's
    start is ``handed_on(x, segment.within)`` of each thing the segment before handed on
    (the rows of it that go on here)."""
    result = None
    for segment in segments:
        start = None
        if result is not None:
            start = tuple(handed_on(x, segment.within) for x in result[1:])
        result = _path(*_call(segment, start))
        result = result if isinstance(result, tuple) else (result,)
        yield segment, start, result


def _forward(segments: list[_Segment]) -> tuple[list[tuple], list[tuple | None]]:
    """Each segment's outputs (its radiance, then what it hands on) and its start (None
    for the first: the camera's rays), off the tape."""
    outputs, starts = [], []
    with md.no_grad():
        for _, start, result in _sweep(segments, lambda x, at: np.take(x.data, at, axis=0)):
            outputs.append(tuple(r.data for r in result))
            starts.append(start)
    return outputs, starts


def radiance(tables: Tables, batch: PathBatch) -> np.ndarray:
    """(N, 3): the radiance of each path of ``batch`` (the environment where its camera
    ray misses), by the compiled forward of ``path_terms``, segment after segment, off the
    tape."""
    total = np.zeros((len(batch.paths), 3))
    if not batch.missed.all():
        segments = _segments(tables, batch)
        for segment, outputs in zip(segments, _forward(segments)[0], strict=True):
            if segment.rows is None:  # zero where a camera ray misses
                total += outputs[0]
            else:
                total[segment.rows] += outputs[0]
    total[batch.missed] = tables.background.data
    return total


def tangent(tables: Tables, batch: PathBatch) -> np.ndarray:
    """(N, 3): the tangent of each path's radiance (``radiance``'s value) along the
    tangents the tables' tensors carry (forward mode: ``md.tangents`` on the parameters the
    tables are computed from, ``Tables.of(..., leaves=False)``): the compiled JVP of
    ``path_terms``, each path's forward sweep with its tangents inside the kernel, segment
    after segment, each handing its start on with its tangent. Nothing requires grad, so
    nothing is recorded: memory is the batch's records and a few (N, 3) arrays. Where a
    camera ray misses, the environment's tangent."""
    total = np.zeros((len(batch.paths), 3))
    if not batch.missed.all():
        # What a segment hands on goes on as Tensors, carrying their tangents.
        for segment, _, result in _sweep(_segments(tables, batch), lambda x, at: x[at]):
            if result[0].tangent is not None:
                if segment.rows is None:
                    total += result[0].tangent
                else:
                    total[segment.rows] += result[0].tangent
    if tables.background.tangent is not None:
        total[batch.missed] = tables.background.tangent
    return total


def backpropagate(tables: Tables, batch: PathBatch, weights: np.ndarray) -> None:
    """Add the gradient of sum(weights * L) over the paths of ``batch`` that meet the
    scene (``weights`` (N, 3): d loss / d L) to ``grad`` of the tables' leaves: the VJP of
    ``path_terms``, each path's reverse sweep inside the compiled kernel, segment by
    segment from the last (each hands the gradient of its start to the segment before)."""
    if batch.missed.all():
        return
    segments = _segments(tables, batch)
    if len(segments) == 1:  # one segment: its radiance is the objective's only output
        _path.add_vjp(weights, *_call(segments[0], None))
        return
    outputs, starts = _forward(segments)
    handed_back = None  # the gradient of the sum with respect to what segment j hands on
    for j in range(len(segments) - 1, -1, -1):
        segment = segments[j]
        own = weights if segment.rows is None else np.take(weights, segment.rows, axis=0)
        cotangents = (own, *handed_back) if segment.follows else own
        start = None
        if starts[j] is not None:
            start = tuple(md.tensor(x, requires_grad=True) for x in starts[j])
        _path.add_vjp(cotangents, *_call(segment, start))
        if start is not None:  # back to the rows of the segment before
            handed_back = []
            for t, handed in zip(start, outputs[j - 1][1:], strict=True):
                g = np.zeros_like(handed)
                if t.grad is not None:
                    g[segment.within] = t.grad
                handed_back.append(g)


def _textured(value, table, obj, uv, replaces: bool = False):
    """A material's ``value`` (n, 3) at points on objects ``obj`` (n,) with UVs ``uv``:
    where the object has a texture of ``table`` (``Tables.textures``' kind; None: no
    object has one), the texture's lookup, which replaces the value (``replaces``: the
    albedo's) or multiplies it (the specular's), as ``lighting.appearance`` reads them."""
    if table is None:
        return value
    texels, first, width, height, has = table
    sampled = lookup(texels, uv, width[obj], height[obj], first[obj])
    return md.where(column(has[obj]), sampled if replaces else value * sampled, value)


def _middle_unless(used, local) -> md.Tensor:
    """``local`` (n, 3) barycentric coordinates where ``used`` (n,), else the primitive's
    middle (1/3 each): the harmless point read by a path whose term there has weight 0 (no
    NEE; it does not go on), whatever its record holds."""
    return md.where(column(used), local, 1.0 / 3.0)
