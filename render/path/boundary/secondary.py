"""Secondary visibility's boundary term for the path integrator: soft shadows, hard shadows
seen after a bounce, and indirect occlusion.

``render.path.gradient.transport`` writes a path in area measure: every vertex after the
camera's is a fixed place on its surface (barycentrics), so the integral over the next
vertex x' of a vertex x is over surfaces that move with the parameters, and the only
discontinuities left inside it are those of visibility V(x, x'). Where the segment x -> x'
grazes an occluder's silhouette (a mesh edge whose two faces lie on one side of the plane
through x and the edge, a mesh's border, a sphere's outline as seen from x), V jumps between
1 and 0 along a curve on the surfaces behind, and that curve moves with the parameters.
Reynolds' transport theorem gives the derivative of the integral: the interior term the tape
computes, plus

    int_curve  (F_+ - F_-) dphi/dtheta / |grad_S phi|  dl

where phi(x') is a level set function that is zero on the curve (positive on the side
marked +), F the integrand in area measure, grad_S phi its gradient along the surface and
dl the curve's length. For a mesh edge (a, b) seen from x: phi = (x' - x) . ((a - x) x
(b - x)); for a sphere (c, r): phi = distance(c, line(x, x')) - r. Where the occluder is,
F = 0; on the other side F is the whole path through x' (``docs/path_tracing.md`` has the
derivation). Next-event estimation needs no term of its own: its point on an area light is
one more x' in the same area measure, and its MIS weight and the BSDF-sampled one sum to 1.

The estimator, per vertex x_k of a path (k >= 1; after a mirror too): pick a
silhouette with probability proportional to the angle it subtends at x_k, a point m on it
uniformly in that angle (``render.path.boundary.silhouettes``), trace the ray x_k -> m (it must
reach m) and on beyond m to x'; the sample is

    beta_k f_k G(x_k, x') L(x' -> x_k) |dx'/dt| / |grad_S phi| / p(curve, t) * sign * dphi/dtheta,

beta_k the path's weight up to x_k, L estimated by a path continued from x'. Two such
samples per vertex split F: x''s emission, from the curves' parts whose rays meet an
emitter picked as next-event estimation picks it; the rest, from whole curves. A point
light at l casts hard shadows: its NEE at x' jumps where the segment x' -> l grazes a
silhouette seen from l, a curve on the surfaces, in the integral over x' from x_k. The
same construction with l as the apex samples it; the jump is the light's contribution at
x'. A directional light is a point light ``FAR`` scene sizes away. Everything but
dphi/dtheta is a constant computed off the tape (beta_k f_k G L by ``replay.radiance_of``:
the compiled paths' values); phi is recomputed from x_k, x' (their places on their
surfaces), the curve and the light (``silhouettes.level_set``, compiled per sample: one
node on the tape), so ``backward`` reaches every parameter that moves them. Each sample's
value is phi - phi = 0: the term adds nothing to the image.

The lights' shadows that the camera sees directly are the same curves in the image
plane's integral (``_seen_shadows``). Not covered: edges seen in a mirror (from the camera
or from a vertex: the mirror's reflection has no area integral to carry them), an
environment seen past an edge after a bounce, and occluders in contact with the surface
behind them (a block standing on the floor: its bottom edges are left out, which is exact
while the contact holds, except for the contact line's own motion along the surface: a
block sliding on the floor moves the dark line under it, and that term is missed).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from functools import partial

import numpy as np

import minidiff as md
from minidiff.threads import beside
from render.edges.boundary.moving import camera_moves, moving, objects_move
from render.path.boundary.silhouettes import Curves, level_set
from render.path.gradient import window
from render.path.gradient.replay import plain_tables, radiance_of
from render.path.gradient.transport import next_vertex, vertex_on_tape, viewer_side
from render.path.sample.choices import geometric_normal, padded_role, padded_tables
from render.path.sample.random import bounce_dimension, uniform
from render.path.sample.records import PathBatch, Vertices
from render.path.sample.sampling import dot
from render.path.sample.tables import Tables
from render.path.sample.tracer import AREA, CAMERA, MIRROR, STOP, PathSampler
from render.path.twin import kernel
from render.scene.camera import camera_frame, project, ray_directions, to_image_plane
from render.shade.surface import column, geometric_normals
from render.trace.outlines import CONTACT
from render.trace.visibility import blocked_past, hit_past, shadow_offset

#: The boundary paths' seed is the render's seed XOR this (independent of the image's).
SEED_KEY = 0x5EC0_DA7A_0B0D_1E55
#: The seed of the curve choices: the boundary paths' seed XOR this times (1 + light index).
CHOICE_KEY = 0x2545_F491_4F6C_DD1D
#: A directional light's shadows are cast from a point this many scene sizes away in its
#: direction (the parallel projection to a relative 1e-6; phi stays exact in float64).
FAR = 1e6
#: Boundary paths traced together (bounds the memory of one chunk's tape).
CHUNK_PATHS = 1 << 14


@dataclass
class _Crossing:
    """Boundary samples behind curves: which are valid (n,) bool; for the valid ones (k of
    them, in order), x' on primitive ``prim`` (k,) at ``local`` (k, 3), ``points`` (k, 3),
    its geometric normal facing ``viewer`` (k, 3) and the constant weight |dx'/dt| /
    |grad_S phi| / P(curve) * sign (k,)."""

    valid: np.ndarray
    prim: np.ndarray
    local: np.ndarray
    points: np.ndarray
    normal: np.ndarray
    weight: np.ndarray
    index: np.ndarray


def _cross(sampler, curves: Curves, apex, index, probability, side, t, viewer, origin,
           moves=None):  # fmt: skip
    """Boundary samples behind the curves ``index`` (n,) (-1: none) seen from ``apex``
    (n, 3): the point at t (n,) on the curve must be seen from the apex (rays leave from
    ``origin`` (n, 3), the apex lifted off its surface), and the first surface beyond it,
    x', must not touch the curve; its normal is turned to face ``viewer`` (n, 3).
    ``probability`` (n,): the density of the sample, P(curve) times the density of t.
    ``moves``: None, or which samples to keep once x' is found, ``moves(rows, prim,
    index)`` (k,) bool of the samples at rows ``rows`` (k,) of these arrays, x' on
    primitives ``prim``, behind curves ``index`` (``_moving``): the others are no
    samples, and their rays past x' are not traced. The arithmetic on either side of the
    rays is compiled (``Curves.aim``, ``_weigh``)."""
    rows = np.flatnonzero((index >= 0) & (probability > 0))

    def of(values, at):  # rows of (n, ...) arrays (np.take: see tracer.Vertices.take)
        return np.take(values, at, axis=0)

    apex, index, side = of(apex, rows), index[rows], side[rows]
    size = sampler.size
    m, tangent, off, direction = curves.aim(apex, index, side, t[rows], 1e-9 * size)
    start = of(origin, rows)
    wanted = None if moves is None else (lambda at, prim, index: moves(rows[at], prim, index))
    seen, (prim, far, u, v) = _past_the_edge(sampler.accelerator, curves, index, start, off,
                                             direction, wanted)  # fmt: skip
    ok = np.flatnonzero(seen & (prim >= 0) & (far > CONTACT * size))
    rows, apex, index, side, m, tangent, direction, prim, far, u, v = (
        of(x, ok) for x in (rows, apex, index, side, m, tangent, direction, prim, far, u, v)
    )
    points = m + far[:, None] * direction
    grad = curves.gradient(apex, index, points)
    face, sphere, on_sphere, _, _ = padded_role(sampler.tables, prim)
    vertices, _, faces, _, centers, _ = padded_tables(sampler.tables)
    normal, weight, good = (x.data for x in _weigh(
        apex, m, tangent, points, of(viewer, rows), grad, np.where(index < curves.n_edges,
        -side, 1.0), probability[rows], face, sphere, on_sphere, vertices, faces, centers,
    ))  # fmt: skip
    good = good > 0
    valid = np.zeros(len(probability), bool)
    valid[rows] = good
    prim, points = prim[good], points[good]
    local = sampler.local_coordinates(prim, points, u[good], v[good])
    return _Crossing(valid, prim, local, points, normal[good], weight[good], index[good])


def _past_the_edge(accelerator, curves: Curves, index, start, off, direction, wanted=None):
    """Whether the points ``off`` (n, 3) beside the curves ``index`` (n,) are seen from
    ``start`` (n, 3), and the closest hits (prim, t, u, v) of the rays from them along
    ``direction`` (n, 3). Both rays pass through the curve: they pass an edge's faces
    (``render.trace.visibility.hit_past``), which they meet only across a seam's crack
    (meshes welded within ``seam_distance``: a box split into meshes whose seams were moved
    4e-6 apart had its light's gradient 40 % off the one mesh's). Rays are traced as any
    other first, again past the faces only where they met one. ``wanted``: None, or which
    of the rows (k,) that met a primitive (those primitives, the rows' curves) are wanted,
    (k,) bool: the others are not seen, and not tested."""
    passing = np.full((len(index), 2), -1, np.int64)
    edge = np.flatnonzero(index < curves.n_edges)
    passing[edge] = curves.faces[index[edge]]
    hits = accelerator.closest_hit(off, direction, tmin=0.0)
    again = np.flatnonzero((hits[0] >= 0) & np.any(hits[0][:, None] == passing, axis=1))
    if len(again):
        past = hit_past(accelerator, off[again], direction[again], passing[again])
        for whole, part in zip(hits, past, strict=True):
            whole[again] = part
    test = np.flatnonzero(hits[0] >= 0)
    if wanted is not None:
        test = test[wanted(test, hits[0][test], index[test])]
    seen = np.zeros(len(index), bool)
    seen[test] = ~accelerator.occluded(start[test], off[test] - start[test], 1.0, tmin=0.0)
    again = test[~seen[test] & np.any(passing[test] >= 0, axis=1)]
    seen[again] = ~blocked_past(accelerator, start[again], off[again] - start[again],
                                np.ones(len(again)), passing[again])  # fmt: skip
    return seen, hits


@md.compile(shared=("vertices", "faces", "centers"))
def _weigh(apex, m, tangent, points, viewer, grad, sign, probability, face, sphere, on_sphere,
           vertices, faces, centers):  # fmt: skip
    """The boundary samples' x' (``points`` (n, 3), beyond the curve points m (n, 3) seen
    from ``apex`` (n, 3), dm/dt ``tangent``): their geometric normals facing ``viewer``
    (the primitive's: ``face``, ``sphere``, ``on_sphere`` into the path tables), and the
    constant weight |dx'/dt| / |grad_S phi| / P(curve) * sign (``grad``: phi's gradient in
    x'; ``sign``: -1 or +1 by the side F is zero on; ``probability``: the sample's density),
    with 1.0 where that is defined (0.0: leave the sample out)."""
    normal = geometric_normal(face, sphere, on_sphere, points, vertices, faces, centers)
    normal = normal * column(md.where(md.dot(normal, viewer - points) < 0, -1.0, 1.0))
    # |dx'/dt|: x' is m projected from the apex onto the plane of x'.
    w = m - apex
    stretch = md.norm(points - apex) / md.norm(w)
    wn = md.dot(w, normal)
    along = stretch * md.norm(
        tangent - column(md.dot(tangent, normal) / md.where(wn != 0, wn, 1.0)) * w
    )
    across = md.norm(grad - column(md.dot(grad, normal)) * normal)
    # Edges: F is 0 on the faces' side of phi; spheres: inside the cone (phi < 0).
    good = (wn != 0) & (across > 0)
    weight = md.where(good, along / md.where(good, across, 1.0), 0.0) * sign / probability
    return normal, weight, md.where(good, 1.0, 0.0)


def add_secondary_term(world, image: md.Tensor, frame, sampler: PathSampler) -> md.Tensor:
    """The image (H, W, 3) plus secondary visibility's boundary term (zero in value),
    estimated with ``sampler.spp`` boundary paths per pixel; on the tape of ``world``."""
    own, curves, packed = _boundary_sampler(sampler)
    terms = []
    for paths in _paths(own, curves):
        prefixes = _prefixes(own, packed, paths)
        terms.append(_terms(world, frame, own, curves, prefixes, _depths(own, prefixes[0]), True))
    terms = [t for t in terms if t is not None]
    if not terms:
        return image
    camera = world.camera
    values = md.concatenate([v for v, _ in terms]) if len(terms) > 1 else terms[0][0]
    pixels = np.concatenate([p for _, p in terms])
    term = md.scatter_add(values, pixels, camera.width * camera.height) * (1.0 / sampler.spp)
    return image + md.reshape(term, image.shape)


def backpropagate_secondary(placed_world, sampler: PathSampler, d_image: np.ndarray) -> None:
    """Add d_image . d term / d p to the gradients of the parameters, ``d_image`` (H, W, 3)
    dL/dimage: one chunk of ``CHUNK_PATHS`` boundary paths at a time (memory bounded by a
    chunk, whatever the spp), each in two shares of its depths, each share on a fresh tape
    from ``placed_world()``. The shares' samples are found side by side (``beside``: much
    of their time is NumPy and Python between kernels, which one thread alone leaves the
    other idle for), and their backward passes run after, one after the other in the
    shares' order: each tape is one thread's, and the gradients are summed in the same
    order whatever the number of threads."""
    own, curves, packed = _boundary_sampler(sampler)
    weights = d_image.reshape(-1, 3) * (1.0 / sampler.spp)
    for paths in _paths(own, curves):
        prefixes = _prefixes(own, packed, paths)
        shares = _shares(_depths(own, prefixes[0]), prefixes[0])
        find = []
        for depths, seen in zip(shares, (False, True), strict=True):
            world = placed_world()  # made here, in turn: one tape a share
            frame = camera_frame(world.camera)
            find.append(partial(_terms, world, frame, own, curves, prefixes, depths, seen))
        with beside(find[0]) as first:
            second = find[1]()
        for term in (first(), second):
            if term is not None and term[0].requires_grad:
                values, pixels = term
                md.sum(values * weights[pixels]).backward()


def _boundary_sampler(sampler: PathSampler):
    """What every chunk of boundary paths shares: the render's sampler with the boundary
    paths' seed (``SEED_KEY``), the scene's curves (kept from the last gradient while the
    shapes stay, ``Curves.kept``), and the kernel's arrays (None where the kernel does not
    apply)."""
    own = copy.copy(sampler)
    own.seed = (sampler.seed ^ SEED_KEY) & (2**64 - 1)
    return own, Curves.kept(own), kernel.pack(own) if kernel.applies(own.scene) else None


def _paths(sampler: PathSampler, curves: Curves):
    """The boundary paths' ids (pixel x spp + sample, as the image's), a chunk at a time
    (none when there are no curves to sample)."""
    if curves.n_edges + len(curves.radius) == 0:
        return
    camera = sampler.scene.camera
    total = camera.width * camera.height * sampler.spp
    for start in range(0, total, CHUNK_PATHS):
        yield np.arange(start, min(start + CHUNK_PATHS, total), dtype=np.int64)


def _prefixes(sampler: PathSampler, packed, paths: np.ndarray):
    """The boundary paths ``paths`` traced (by the kernel with ``packed``, else by the
    reference) up to the vertices where their samples stand: (the ``PathBatch``, each
    depth's vertex positions, the paths)."""
    # The samples stand at vertices 1 .. max_depth - 1 and read only where the prefix went
    # (a vertex's place, and how the path left the ones before it): traced one vertex
    # short, the same records up to there, without the last vertex's lights and rays.
    short = copy.copy(sampler)
    short.max_depth = max(1, sampler.max_depth - 1)
    if packed is not None:
        batch, _ = kernel.sample_paths(short, paths, packed)
    else:
        batch = short.sample(paths)
    return batch, _points(sampler, batch), paths


def _depths(sampler: PathSampler, batch: PathBatch) -> list[int]:
    """The depths k whose vertices hold samples: 1 .. max_depth - 1, as far as any path
    went."""
    return list(range(1, min(len(batch.vertices), sampler.max_depth - 1) + 1))


def _shares(depths: list[int], batch: PathBatch) -> tuple[list[int], list[int]]:
    """``depths`` in two shares of about as many vertices each, each in order (the first
    depth, which has the most, alone in the first share while the rest have more)."""
    first, second = [], []
    sizes = [0, 0]
    for k in depths:
        share = 0 if sizes[0] <= sizes[1] else 1
        (first, second)[share].append(k)
        sizes[share] += len(batch.vertices[k - 1].rows)
    return first, second


def _terms(world, frame, sampler: PathSampler, curves: Curves, prefixes, depths, seen: bool):
    """(values (M, 3) on the tape of ``world``, pixel (M,)) of the boundary samples at the
    vertices of depths ``depths`` of the paths ``prefixes`` (``_prefixes``) and, with
    ``seen``, of the lights' shadows the camera sees; None if none."""
    batch, points, paths = prefixes
    tables = Tables.of(world, frame, leaves=False)  # what phi reads, on this tape
    plain = plain_tables(world, frame)  # what the samples' radiance reads, made once
    values, pixels = [], []
    for k in depths:
        for term in _terms_at(sampler, curves, batch, points, k, world, frame, tables, plain):
            values.append(term[0])
            pixels.append(batch.paths[term[1]] // sampler.spp)
    if seen and sampler.max_depth >= 2:  # the lights' shadows seen by the camera
        for value, pixel in _seen_shadows(sampler, curves, paths, world, frame, tables, plain):
            values.append(value)
            pixels.append(pixel)
    if not values:
        return None
    joined = md.concatenate(values) if len(values) > 1 else values[0]
    return joined, np.concatenate(pixels)


def _seen_shadows(sampler, curves, paths, world, frame, tables, plain):
    """The borders of point and directional lights' shadows that the camera sees, one
    sample per boundary path and light: a point x on a shadow's border drawn from the light
    (as ``_terms_at`` does for later vertices), seen by the camera at the image-plane point
    s. The pixel integral is over s, so the sample carries the light's contribution at x
    times ds/dA (the image plane's area per unit of the surface's at x); the N = W H spp
    samples estimate every pixel's term at once, each going to the pixel holding s.
    Yields (values (m, 3) on the tape, their pixels (m,))."""
    camera = sampler.scene.camera
    width, height = camera.width, camera.height
    forward, right, up, eye = sampler.frame
    for j, light in enumerate(sampler.scene.lights):
        seed = sampler.seed ^ ((CHOICE_KEY * (j + 2 + len(sampler.scene.lights))) & (2**64 - 1))
        u = (uniform(seed, paths, 0), uniform(seed, paths, 1))
        at, cross = _from_light(sampler, curves, light, *u, np.ones(len(paths), bool),
                                np.broadcast_to(eye, (len(paths), 3)))  # fmt: skip
        px, depth = project(cross.points, sampler.frame, width, height)
        inside = (depth > 0) & np.all((px >= 0) & (px < [width, height]), axis=1)
        inside &= dot(cross.normal, at - cross.points) > 0  # lit from the camera's side
        eyes = np.broadcast_to(eye, cross.points.shape)
        inside &= ~sampler.accelerator.occluded(eyes, cross.points - eye, 1.0 - 1e-7, tmin=0.0)
        hit = _take(cross, inside)
        if len(hit.prim) == 0:
            continue
        m = len(hit.prim)
        coords = to_image_plane(px[inside], width, height)
        lit = np.zeros((len(sampler.scene.lights), m), bool)
        lit[j] = True
        first = _quiet(np.arange(m), hit.prim, hit.local, np.full(m, CAMERA, np.int8), lit)
        rays = PathBatch(paths[np.flatnonzero(cross.valid)[inside]], coords, np.zeros(m, bool),
                         [first])  # fmt: skip
        radiance = radiance_of(world, frame, sampler, rays, plain)
        stretch = _image_area(hit.points, hit.normal, sampler.frame)
        # Every pixel's estimate divides by N = W H spp (1 / spp is the caller's) and by the
        # pixel's area in the image plane, 4 / (W H).
        weight = hit.weight * stretch / 4.0
        apex = _apex(world.lights[j], sampler)
        there = (hit.prim, hit.local, coords)
        if _compiles(world):
            phi = _level_sets(tables, curves, hit.index, apex, None, there, ("light", "camera"))
        else:
            directions = ray_directions(frame, coords.astype(radiance.dtype))
            origins = md.broadcast_to(frame[3], (m, 3))
            camera = np.full(m, CAMERA, np.int8)
            seen = vertex_on_tape(world, sampler, hit.prim, hit.local, camera, origins,
                                  directions).points  # fmt: skip
            phi = _phi(tables, curves, hit.index, md.broadcast_to(apex, (m, 3)), seen)
        moved = phi - md.detach(phi)
        pixel = np.minimum(px[inside].astype(np.int64), [width - 1, height - 1])
        yield (md.tensor(radiance * weight[:, None]) * column(moved),
               pixel[:, 1] * width + pixel[:, 0])  # fmt: skip


def _points(sampler, batch: PathBatch) -> list[np.ndarray]:
    """Each depth's vertex positions (k, 3), plain, from their places on their primitives
    (or, at camera and mirror vertices, where their rays met them: the same point)."""
    out = []
    triangles, centres, radii = sampler.primitives
    for record in batch.vertices:
        prim, local = record.prim, record.local
        p = np.zeros((len(prim), 3))
        tri = prim < sampler.n_triangles
        t = triangles[prim[tri]]
        u, v = local[tri, :1], local[tri, 1:2]
        p[tri] = (1 - u - v) * t[:, 0] + u * t[:, 1] + v * t[:, 2]
        s = prim[~tri] - sampler.n_triangles
        p[~tri] = centres[s] + radii[s, None] * local[~tri]
        out.append(p)
    return out


def _terms_at(sampler, curves, batch, points, k: int, world, frame, tables, plain):
    """The boundary samples at the paths' k-th vertices: behind silhouettes seen from
    them (the next segment's visibility) and, for every point or directional light,
    behind silhouettes seen from the light (its shadow at the next vertex). Yields
    (values (M, 3), the samples' rows in the batch (M,))."""
    record = batch.vertices[k - 1]
    rows = record.rows
    eye = sampler.frame[3]
    if k == 1:
        previous = np.broadcast_to(eye, (len(rows), 3))
    else:
        before = batch.vertices[k - 2]
        previous = points[k - 2][np.searchsorted(before.rows, rows)]
    here = points[k - 1]
    normal = geometric_normals(sampler.primitives, record.prim, here)
    normal *= np.where(dot(normal, previous - here) < 0, -1.0, 1.0)[:, None]
    obj = np.searchsorted(sampler.first, record.prim, side="right") - 1
    lobes = sampler.lobes.probability[obj]
    can = lobes[:, 0] + lobes[:, 1] > 0  # a pure mirror's reflection has no area integral
    ids = batch.paths[rows]
    origin = here + shadow_offset(here, sampler.size) * normal
    dims = bounce_dimension(k, "lobe")  # bounce k's block of dimensions (its first)
    seed = sampler.seed ^ CHOICE_KEY
    # Only the samples whose phi can carry a derivative: the others' terms are zero in
    # derivative too; found once x' is, before the rays that test the rest.
    moves = partial(_moving, world, sampler, curves, batch, k, None)

    # Two estimators of the next segment's term, for two parts of F: x''s emission, by
    # curves clipped to where their rays meet an emitter picked as NEE picks it (a soft
    # shadow's edges are mostly seen against the light); and all the rest, by whole curves.
    emitters = sampler.emitters
    u_curve, u_point = uniform(seed, ids, dims), uniform(seed, ids, dims + 1)
    towards = None
    if len(emitters):
        row = emitters.pick(uniform(seed, ids, dims + 2))
        target = emitters.prims[row]
        on = target < sampler.n_triangles  # a sphere's rays are not clipped
        triangle = (
            sampler.primitives[0][np.where(on, target, 0)]
            if sampler.n_triangles
            else np.zeros((len(ids), 3, 3))
        )
        u_near = (uniform(seed, ids, dims + 3), uniform(seed, ids, dims + 4))
        towards = (triangle, *u_near, can & on)
    whole, near = curves.pick(here, (u_curve, u_point, can), towards)
    if len(emitters):
        if not on.all():
            other = curves.pick(here, (*u_near, can & ~on))[0]
            for mine, theirs in zip(near, other, strict=True):
                mine[~on] = theirs[~on]
        index, density, faces, t = near
        density = density * emitters.probability[row]
        cross = _cross(sampler, curves, here, index, density, faces, t, here, origin, moves)
        sub = np.flatnonzero(cross.valid)
        keep = (dot(normal[sub], cross.points - here[sub]) > 0) & (cross.prim == target[sub])
        yield from _samples(
            world, frame, tables, plain, sampler, curves, batch, k, cross, keep, here, "emission"
        )

    cross = _cross(sampler, curves, here, *whole[:3], whole[3], here, origin, moves)
    front = dot(normal[cross.valid], cross.points - here[cross.valid]) > 0
    yield from _samples(
        world, frame, tables, plain, sampler, curves, batch, k, cross, front, here, "rest"
    )

    # Point lights' shadows at x' seen from x_k (x' must still get the light's NEE).
    if k + 1 > sampler.max_depth - 1:
        return
    for j, light in enumerate(sampler.scene.lights):
        seed_j = sampler.seed ^ ((CHOICE_KEY * (j + 2)) & (2**64 - 1))
        u = (uniform(seed_j, ids, dims), uniform(seed_j, ids, dims + 1))
        moves_j = partial(_moving, world, sampler, curves, batch, k, j)
        at, cross = _from_light(sampler, curves, light, *u, can, here, moves_j)
        sub = np.flatnonzero(cross.valid)
        to = cross.points - here[sub]
        ok = (dot(normal[sub], to) > 0) & (dot(cross.normal, at - cross.points) > 0)
        ok &= ~sampler.accelerator.occluded(origin[sub], cross.points - origin[sub],
                                            1.0 - 1e-7, tmin=0.0)  # fmt: skip
        yield from _samples(
            world, frame, tables, plain, sampler, curves, batch, k, cross, ok, here, "light", j
        )


def _samples(world, frame, tables, plain, sampler, curves, batch, k, cross, keep, here, part,
             light=None):  # fmt: skip
    """The samples behind silhouettes that ``keep`` selects among ``cross``'s valid ones,
    their jump F at x' being: ``part`` "emission", x''s emission alone; "rest", the path
    continued from x' but for the emitters' emission (the other estimator's); "light",
    light ``light``'s contribution at x' (its shadow's border). Yields (values (M, 3),
    rows in the batch (M,)). ``tables``: the tables on the tape, what phi reads; ``plain``:
    the same off the tape, what the samples' radiance reads."""
    record = batch.vertices[k - 1]
    sub = np.flatnonzero(cross.valid)[keep]
    if len(sub) == 0:
        return
    hit = _take(cross, keep)
    src = record.rows[sub]
    m = len(src)
    prefix = _prefix(sampler, batch, k, src, here[sub], hit)
    if part == "rest":
        tail = sampler.resume(batch.paths[src], k + 1, hit.prim, hit.local, hit.points, here[sub])
        tail[0].emit_weight[:] = np.where(sampler.emitters.row_of[hit.prim] >= 0, 0.0, 1.0)
    else:
        lit = np.zeros((len(sampler.scene.lights), m), bool)
        if part == "light":
            lit[light] = True
        tail = [_quiet(np.arange(m), hit.prim, hit.local, np.full(m, AREA, np.int8), lit)]
        tail[0].emit_weight[:] = 1.0 if part == "emission" else 0.0
    records = prefix + tail
    yield (
        _value(world, frame, tables, plain, sampler, curves, batch, k, src, hit, records, light),
        src,
    )


def _moving(world, sampler, curves, batch, k, light, rows, there, index) -> np.ndarray:
    """(m,) bool: which samples' phi can carry a derivative (at the k-th vertices of the
    batch's record rows ``rows`` (m,): the apexes ``_terms_at`` hands ``_cross``; x' on
    primitives ``there`` (m,), curves ``index`` (m,), the apex light ``light`` or None):
    the camera, the apex light's placement, x_k's, x''s or the curve's object
    differentiated in ``world``, or x_k reached through a mirror (replayed from the
    camera: every sample kept). ``curves_move`` gates the whole term likewise."""
    objects = objects_move(world)
    apex = light is not None and moving(*world.lights[light].placement())
    if camera_moves(world) or apex:
        return np.ones(len(rows), bool)
    record = batch.vertices[k - 1]
    owner = np.zeros(len(index), np.int64)  # the curve's object
    edge = index < curves.n_edges
    owner[edge] = curves.edge_object[index[edge]]
    owner[~edge] = curves.sphere_object[index[~edge] - curves.n_edges]
    of = partial(np.searchsorted, sampler.first, side="right")
    out = objects[of(record.prim[rows]) - 1] | objects[of(there) - 1] | objects[owner]
    return out | (record.form[rows] == MIRROR)


def _from_light(sampler, curves, light, u_curve, u_point, active, viewer, moves=None):
    """Points x' on the borders of ``light``'s shadows, one per row of the uniforms
    (n,) where ``active``: a silhouette seen from the light and a point on it, the first
    surface beyond; normals turned to ``viewer`` (n, 3); ``moves``: as ``_cross``'s.
    Returns (where the light casts from (1, 3), the ``_Crossing``)."""
    with md.no_grad():
        at = np.asarray(_apex(light, sampler).data, np.float64)[None]
    index, density, side, t = curves.pick(at, (u_curve, u_point, active))[0]
    apex = np.repeat(at, len(u_curve), 0)
    return at, _cross(sampler, curves, apex, index, density, side, t, viewer, apex, moves)


def _apex(light, sampler: PathSampler):
    """Where a light's shadows are cast from (``Light.shadow_apex``): a point light's
    position; for a light at infinity, a point ``FAR`` scene sizes from the scene's centre
    towards it. (3,), on the tape (the light's fields are tensors)."""
    triangles, centres, _ = sampler.primitives
    points = np.concatenate([triangles.reshape(-1, 3), centres])
    middle = 0.5 * (points.min(axis=0) + points.max(axis=0))
    return light.shadow_apex(middle, FAR * sampler.size)


def _image_area(points, normals, frame) -> np.ndarray:
    """(k,): ds/dA, the image plane's area (its coordinates s in [-1, 1]^2) per unit area of
    the surfaces at ``points`` (k, 3) with unit ``normals`` (k, 3), as the camera
    (``frame``: forward, right, up, eye) projects them: s = (r . right / (z |right|^2),
    r . up / (z |up|^2)), r = x - eye, z = r . forward; the determinant of ds/dx on the
    tangent plane."""
    forward, right, up, eye = frame
    r = points - eye
    z = r @ forward
    rows = []
    for axis in (right, up):
        scale = axis @ axis
        rows.append(axis[None] / (scale * z[:, None]) - ((r @ axis) / (scale * z**2))[:, None]
                    * forward[None])  # fmt: skip
    return np.abs(dot(np.cross(rows[0], rows[1]), normals))


def _take(cross: _Crossing, keep: np.ndarray) -> _Crossing:
    """The valid samples of ``cross`` that ``keep`` (over the valid ones) selects."""
    return _Crossing(cross.valid, cross.prim[keep], cross.local[keep], cross.points[keep],
                     cross.normal[keep], cross.weight[keep], cross.index[keep])  # fmt: skip


def _quiet(rows, prim, local, form, lit) -> Vertices:
    """A vertex record that gains nothing but from the lights ``lit`` (L, m) and stops."""
    m = len(rows)
    return Vertices(rows, prim, local, form, np.zeros(m), np.full(m, -1, np.int64),
                    np.zeros((m, 3)), np.zeros(m), lit, np.full(m, STOP, np.int8), np.ones(m),
                    np.ones(m), np.zeros(m, bool), np.zeros((m, 3)))  # fmt: skip


def _prefix(sampler, batch, k, src, here, hit: _Crossing) -> list[Vertices]:
    """The records of depths 1..k of the batch's paths ``src`` (m,), renumbered 0..m-1,
    that gain nothing on the way (their emission, NEE and lights belong to the image) and
    go on from x_k (``here`` (m, 3)) to x' (``hit``) with density 1 in area measure."""
    m = len(src)
    records = []
    for d in range(k):
        rec = batch.vertices[d]
        pos = np.searchsorted(rec.rows, src)
        out = _quiet(np.arange(m), rec.prim[pos], rec.local[pos], rec.form[pos],
                     np.zeros((len(sampler.scene.lights), m), bool))  # fmt: skip
        out.next, out.next_pdf, out.survive = rec.next[pos], rec.next_pdf[pos], rec.survive[pos]
        records.append(out)
    to = hit.points - here
    d2 = dot(to, to)
    cos = np.abs(dot(hit.normal, to)) / np.sqrt(d2)
    last = records[-1]
    # The tape's factor f cos / next_pdf times its change of measure (value 1): with
    # next_pdf = r^2 / cos', f G, the integrand in area measure.
    last.next, last.next_pdf, last.survive = np.full(m, AREA, np.int8), d2 / cos, np.ones(m)
    return records


def _value(world, frame, tables, plain, sampler, curves, batch, k, src, hit, records, light):
    """(m, 3) on the tape: each sample's constant F |dx'/dt| / |grad_S phi| / P * sign
    (F: the radiance of the path ``records``, computed off the tape) times phi - phi."""
    rays = PathBatch(batch.paths[src], batch.coords[src], np.zeros(len(src), bool), records)
    radiance = radiance_of(world, frame, sampler, rays, plain)
    here = _Rows(batch.vertices[k - 1], src)
    apex = None if light is None else _apex(world.lights[light], sampler)
    if _compiles(world) and (apex is not None or not np.any(here.form == MIRROR)):
        # The apex is a light, or x_k: where the camera's ray meets it (k = 1) or its place.
        kinds = ("light" if apex is not None else "camera" if k == 1 else "area", "area")
        vertex = None if apex is not None else (here.prim, here.local, batch.coords[src])
        there = (hit.prim, hit.local, None)
        phi = _level_sets(tables, curves, hit.index, apex, vertex, there, kinds)
    else:  # on the tape: after a mirror, x_k is where the reflected ray meets it
        if apex is None:
            points = _vertex_points(world, frame, sampler, batch, src, k, radiance.dtype)
        else:
            points = md.broadcast_to(apex, (len(src), 3))
        far = vertex_on_tape(world, sampler, hit.prim, hit.local,
                             np.full(len(src), AREA, np.int8), None, None).points  # fmt: skip
        phi = _phi(tables, curves, hit.index, points, far)
    moved = phi - md.detach(phi)  # zero, with phi's derivative
    return md.tensor(radiance * hit.weight[:, None]) * column(moved)


def _vertex_points(world, frame, sampler, batch, src, k, dtype) -> md.Tensor:
    """(m, 3) on the tape: the k-th vertices of the batch's paths ``src`` (m,), as the tape
    places them: at their places on their surfaces, where the camera's rays meet them, or,
    after a mirror, where the reflected rays do (the path replayed from its camera vertex,
    ``transport.next_vertex``)."""
    directions = ray_directions(frame, batch.coords[src].astype(dtype))
    origins = md.broadcast_to(frame[3], (len(src), 3))
    here = _Rows(batch.vertices[k - 1], src)
    if not np.any(here.form == MIRROR):  # no reflected ray to replay
        return vertex_on_tape(world, sampler, here.prim, here.local, here.form, origins,
                              directions).points  # fmt: skip
    first = _Rows(batch.vertices[0], src)
    v = vertex_on_tape(world, sampler, first.prim, first.local, first.form, origins, directions)
    for d in range(1, k):
        step = _Rows(batch.vertices[d], src)
        v = next_vertex(world, sampler, v, v.shading * viewer_side(v), np.arange(len(src)), step)
    return v.points


class _Rows:
    """The primitive, place and form of the paths ``src`` in a ``Vertices`` record (what
    ``vertex_on_tape`` and ``next_vertex`` read)."""

    def __init__(self, record: Vertices, src: np.ndarray):
        pos = np.searchsorted(record.rows, src)
        self.prim, self.local, self.form = record.prim[pos], record.local[pos], record.form[pos]


def _compiles(world) -> bool:
    """Whether phi is compiled (``_level_sets``): every parameter float64."""
    return all(t.dtype == np.float64 for t in world.parameters())


def _curve_rows(tables: Tables, curves: Curves, index: np.ndarray) -> tuple:
    """Of curves ``index`` (m,): each edge's endpoints as rows of ``tables.vertices`` (two
    (m,) int64), each sphere's row of ``tables.centers`` (m,) and which are edges (m,) bool
    (0 in the rows of the other kind: a harmless value, never selected)."""
    is_edge = index < curves.n_edges
    m = len(index)
    start, end = np.zeros(m, np.int64), np.zeros(m, np.int64)
    if curves.n_edges:  # ``Outlines.ends``: rows of every mesh's vertices, as the tables'
        e = index[is_edge]
        start[is_edge], end[is_edge] = curves.ends[e, 0], curves.ends[e, 1]
    ball = np.where(is_edge, 0, index - curves.n_edges)
    return start, end, ball, is_edge


def _phi(tables: Tables, curves: Curves, index, apex, far) -> md.Tensor:
    """(m,) on the tape: phi of curves ``index`` (m,) seen from ``apex`` (m, 3) at the points
    ``far`` (m, 3), the curves read from ``tables``."""
    curve = _curve_rows(tables, curves, index)
    return _phi_of(apex, far, curve, tables.vertices, tables.centers, tables.radii)


def _phi_of(apex, far, curve, vertices, centers, radii) -> md.Tensor:
    """``level_set`` of the curves ``curve`` (``_curve_rows``), their edges' endpoints and
    spheres read from the tables ``vertices``, ``centers``, ``radii`` (None: none such), on
    the tape or traced."""
    start, end, ball, is_edge = curve
    a = b = centre = radius = None
    if vertices is not None:
        a, b = vertices[start], vertices[end]
    if centers is not None:
        centre, radius = centers[ball], radii[ball]
    return level_set(apex, far, a, b, centre, radius, is_edge)


def _level_sets(tables: Tables, curves: Curves, index, apex, here, there, kinds):
    """(m,) on the tape: phi of curves ``index`` (m,) at x' seen from the apex, compiled
    (``_compiled_phi``). The apex: a light's, ``apex`` (3,), or the vertices ``here``; x':
    ``there``; each of those (prim (m,), local (m, 3), the camera ray's image-plane point
    (m, 2) or None). ``kinds``: the apex's ("light", "camera": where the camera's ray meets
    it, or "area": at its place) and x''s ("camera" or "area")."""

    def point(place, kind):
        if place is None:
            return None
        prim, local, coords = place
        role = tables.role(prim, local)
        if kind != "camera":
            return role, None, None
        return role, coords, tables.far_side(prim)

    return _compiled_phi(
        point(here, kinds[0]), point(there, kinds[1]), _curve_rows(tables, curves, index), apex,
        tables.frame, tables.vertices, tables.normals, tables.faces, tables.centers,
        tables.radii, tables.smooth, kinds,
    )  # fmt: skip


@md.compile(shared=("apex", "frame", "vertices", "normals", "faces", "centers", "radii",
                    "smooth"))  # fmt: skip
def _compiled_phi(here, there, curve, apex, frame, vertices, normals, faces, centers, radii,
                  smooth, kinds):  # fmt: skip
    """phi of one boundary sample (``_level_sets``). Batched: here, there (``Tables.role``,
    the camera ray's image-plane point, whether it meets a sphere's far side; here None
    when the apex is a light's); curve (the edge's endpoints' rows, the sphere's row,
    whether it is an edge). Shared: apex (3,) (a light's, else None) and the tables."""
    world = window.held_world(vertices, normals, faces, centers, radii, smooth)

    def place(point, kind):
        role, coords, far = point
        if kind == "camera":
            return window.surface(world, role, frame[3], ray_directions(frame, coords), far).points
        return window.surface(world, role).points

    p = apex if kinds[0] == "light" else place(here, kinds[0])
    return _phi_of(p, place(there, kinds[1]), curve, vertices, centers, radii)
