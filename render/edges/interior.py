"""The mixed pixels of ``antialias="boundary"``: their value and interior term from 4x4 samples.

A box-filtered pixel's derivative has two parts (``render.edges.boundary``): the boundary
term of the curves where the image jumps, and the interior term, the integral over the
pixel of the shading's own derivative, df/dtheta. The tape gives the interior term from the
pixel's samples: with one sample, df/dtheta at the pixel centre stands for the whole box.
That is the midpoint rule, accurate where df/dtheta varies slowly over the pixel, and wrong
where it does not: in a pixel that a silhouette, a crease or a shadow border crosses, the
centre's surface is credited with the whole box although another surface (or the same one,
in shadow) covers part of it. On a lit sphere over a ground plane at 96x96 this left the
gradient of the sphere's centre 15 % off on one axis at 1 sample per pixel (weights
uniform in [0, 1]); faces smaller than a pixel (a teapot's) make it worse.

So those pixels get more samples:

1. Candidates: pixels whose own samples, or whose neighbours' first samples, do not all
   see the same primitive lit by the same lights (where a pixel's box is mixed, a
   neighbour's centre almost always sees the other surface), less those whose differing
   neighbours lie only across a crease that passes outside the pixel (``past_creases``).
2. Each candidate gets ``render(interior_samples=...)`` stratified samples (the
   renderer's own pattern for that spp; 4 x 4 by default), traced and shadow-tested like
   camera rays; it is *mixed* if they do not all see what its own first sample sees.
3. The mixed pixels' samples are shaded on the tape, and each mixed pixel *becomes* the
   mean of its samples, in value and in derivative. Everywhere else the render's own
   samples stand.

Steps 1 and 2 are kept in the render's cache (``render.scene.cache``) while the
visibility and the lights' positions are: an inverse problem that fits a material finds
them once. The candidates' samples' first hits are kept while the camera and the geometry
are: one that fits a light traces only the samples of the pixels its shadows' borders
have newly reached (the shadow rays, which move with the light, are traced every time).

The image is then an antialiased one (mixed pixels from 16 samples, the others from the
render's own) and the tape's derivative is the derivative of that image: for a parameter
that moves no edge (an albedo, a light's intensity or colour) the gradient is exactly the
image's, which finite differences (``torch.autograd.gradcheck`` through ``render.torch``)
confirm. The mixed pixels are found and shaded whether or not anything is differentiated,
so every route of steps 2, 3 and 5 (compiled or on the tape) gives the same image.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

import minidiff as md
from minidiff.threads import inlined, jit
from render.edges.boundary.radiance import seen_through
from render.scene.cache import RenderCache, light_key
from render.scene.camera import (
    camera_directions,
    check_square,
    plain_frame,
    sample_coords,
    subpixel_offsets,
)
from render.scene.scene import Scene
from render.shade.hits import sample_colours, shade_camera_hits, working_dtype
from render.shade.mirrors import Mirrors
from render.trace.raster import (
    EDGE_MARGIN,
    RASTER_RAYS_PER_PRIMITIVE,
    raster_closest_hit,
    screen_boxes,
)
from render.trace.visibility import PrimaryHits, Visibility

#: ``render``'s default: a mixed pixel's interior term is the mean over 4 x 4 stratified
#: samples.
INTERIOR_SAMPLES = 16


def check_interior_samples(value) -> int:
    """``render``'s ``interior_samples``, checked: a perfect square >= 1."""
    return check_square(value, "interior_samples")


def what_is_seen(visibility: Visibility, n_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """Per camera ray of ``visibility`` (n_rays of them): the primitive it sees (n_rays,)
    and which lights reach its hit (n_rays, L) bool (False for a miss)."""
    primary = visibility.primary
    lit = np.zeros((n_rays, len(visibility.lit)), bool)
    for j, mask in enumerate(visibility.lit):
        lit[primary.hit_rays, j] = mask
    return primary.prim_id, lit


def candidate_pixels(
    prim: np.ndarray, lit: np.ndarray, width: int, height: int, spp: int
) -> np.ndarray:
    """Flat indices (m,) of the pixels whose ``spp`` samples, or whose 8 neighbours' first
    samples, do not all see the same primitive lit by the same lights; ``prim``, ``lit``:
    what each of the render's rays sees (``what_is_seen``)."""
    prim, lit = prim.reshape(height, width, spp), lit.reshape(height, width, spp, -1)
    odd = np.any(prim != prim[..., :1], axis=2) | np.any(lit != lit[:, :, :1], axis=(2, 3))
    first = np.pad(prim[..., 0], 1, mode="edge")
    first_lit = np.pad(lit[:, :, 0], ((1, 1), (1, 1), (0, 0)), mode="edge")
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            other = first[dy : dy + height, dx : dx + width]
            other_lit = first_lit[dy : dy + height, dx : dx + width]
            odd |= (other != prim[..., 0]) | np.any(other_lit != lit[:, :, 0], axis=2)
    return np.flatnonzero(odd.reshape(-1))


def past_creases(
    pixels: np.ndarray,
    prim: np.ndarray,
    lit: np.ndarray,
    width: int,
    height: int,
    spp: int,
    triangles: np.ndarray,
    frame,
    grid_spp: int,
) -> np.ndarray:
    """The candidates ``pixels`` (m,) (``candidate_pixels``, ascending) less those that
    their neighbours show cannot be mixed, ascending: a pixel whose own samples all see
    one triangle T, lit alike, whose ``grid_spp`` samples all lie inside T's projection
    (so that each of their rays meets T or something in front of it), and each of whose
    differing neighbours shows the background (which no sample of the pixel can) or a
    triangle U that shares a corner with T (no silhouette lies between the two), is lit
    as T is (no shadow border lies between them), and whose projection misses the
    pixel's samples: the crease between faces of a faceted mesh passing by. Measured
    (``benchmarks/mixed_pixels.py``, docs/edges/mixed_pixels.json): on the paper scene at
    512x512, 13,351 of its 22,709 candidates are kept and none of its 11,271 mixed pixels
    is left out; over 80 random views of it (its teapot tessellated more or less finely,
    with and without the ground, 24x24 to 100x100), a sixth of the candidates are left
    out, with 17 of 54,761 mixed pixels: 15 specks of shadow and 2 slivers of another
    face inside the pixel that no neighbour's centre sees, which the search without the
    test found only because a crease happened to pass by.

    ``prim``, ``lit``: what each of the render's rays sees (``what_is_seen``);
    ``triangles`` (T, 3, 3) (or (T, 9)): the scene's triangles in world space (primitive
    ids below T); ``frame`` its plain camera frame (``plain_frame``)."""
    offsets = subpixel_offsets(grid_spp)
    # The box of the samples in their pixel, widened as the rasteriser widens it.
    box = np.concatenate([offsets.min(axis=0) - EDGE_MARGIN, offsets.max(axis=0) + EDGE_MARGIN])
    tri = np.ascontiguousarray(triangles, np.float64).reshape(-1, 3, 3)
    slot, lines = _screen_lines(pixels, prim, width, height, spp, tri, frame, offsets)
    keep = _needs_samples(np.ascontiguousarray(pixels, np.int64), prim, np.ascontiguousarray(lit),
                          width, height, spp, tri, slot, lines, box)  # fmt: skip
    return pixels[keep]


def _screen_lines(
    pixels, prim, width: int, height: int, spp: int, tri: np.ndarray, frame, offsets
) -> tuple[np.ndarray, np.ndarray]:
    """The projected edge lines of the triangles that the first samples of ``pixels`` and
    of their 8 neighbours see: (slot (T,) int64, lines (n, 3, 3)); a triangle's lines are
    row slot[t] (-1: not seen there, or not safe to use: reaching behind the eye's plane,
    or seen edge-on). Lines (a, b, c) give a X + b Y + c, the distance in pixels inside
    each edge at continuous pixel position (X, Y) (``render.trace.raster.screen_boxes``)."""
    listed = np.flatnonzero(_seen_near(pixels, prim, width, height, spp, len(tri)))
    forward, right, up, eye = frame
    _, lines = screen_boxes(tri[listed], np.zeros((0, 3)), np.zeros(0), eye, forward, right,
                            up, width, height, offsets)  # fmt: skip
    # screen_boxes leaves an unsafe triangle's lines (0, 0, 1): always true.
    known = np.all(np.abs(lines[:, :, :2]).sum(axis=2) > 0.0, axis=1)
    slot = np.full(len(tri), -1, np.int64)
    slot[listed] = np.where(known, np.arange(len(listed)), -1)
    return slot, lines


@jit(cache=True)
def _seen_near(pixels, prim, width, height, spp, n_tri):
    """(n_tri,) bool: the triangles the first samples of ``pixels`` and of their 8
    neighbours (the image's border standing for beyond it) see."""
    seen = np.zeros(n_tri, np.bool_)
    for i in range(len(pixels)):
        py, px = pixels[i] // width, pixels[i] % width
        for qy in range(max(py - 1, 0), min(py + 1, height - 1) + 1):
            for qx in range(max(px - 1, 0), min(px + 1, width - 1) + 1):
                pid = prim[(qy * width + qx) * spp]
                if 0 <= pid < n_tri:
                    seen[pid] = True
    return seen


@jit(cache=True)
def _needs_samples(pixels, prim, lit, width, height, spp, tri, slot, lines, box):
    """``past_creases``'s test, pixel by pixel: (m,) bool, False where the pixel is left
    out; ``slot`` and ``lines``: the triangles' projected edge lines (``_screen_lines``)."""
    keep = np.ones(len(pixels), np.bool_)
    for i in range(len(pixels)):
        py, px = pixels[i] // width, pixels[i] % width
        first = pixels[i] * spp
        own = prim[first]
        if _row(slot, own) < 0:
            continue
        alike = True
        for s in range(1, spp):
            alike = alike and prim[first + s] == own and _lit_alike(lit, first + s, first)
        if not alike or _least(lines, _row(slot, own), px, py, box, -1.0) <= 0.0:
            continue  # a sample of the pixel may fall outside T
        keep[i] = False
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                qy, qx = min(max(py + dy, 0), height - 1), min(max(px + dx, 0), width - 1)
                ray = (qy * width + qx) * spp
                other = prim[ray]
                if other < 0:
                    continue  # the background: the pixel cannot show it
                same_lit = _lit_alike(lit, ray, first)
                if other == own and same_lit:
                    continue
                keep[i] = not (
                    same_lit
                    and other != own
                    and _row(slot, other) >= 0
                    and _share_a_corner(tri, own, other)
                    and _least(lines, _row(slot, other), px, py, box, 1.0) < 0.0
                )
                if keep[i]:
                    break
            if keep[i]:
                break
    return keep


@inlined
def _row(slot, pid):
    """Primitive ``pid``'s row of lines (``_screen_lines``), -1 for none."""
    if pid < 0 or pid >= slot.shape[0]:
        return -1
    return slot[pid]


@inlined
def _least(lines, row, px, py, box, sign):
    """The least over the 3 edge lines of row ``row`` of ``lines`` of each line's least (``sign``
    -1) or largest (``sign`` 1) value over the samples' ``box`` (x0, y0, x1, y1), offsets
    in pixel (px, py): > 0 with -1, every sample lies inside the triangle; < 0 with 1, all
    lie outside one of its edges."""
    out = np.inf
    for k in range(3):
        a, b, c = lines[row, k, 0], lines[row, k, 1], lines[row, k, 2]
        x = px + (box[2] if a * sign > 0 else box[0])
        y = py + (box[3] if b * sign > 0 else box[1])
        out = min(out, a * x + b * y + c)
    return out


@inlined
def _lit_alike(lit, ray, other):
    """Whether rays ``ray`` and ``other`` reach the same lights (rows of ``lit``)."""
    for j in range(lit.shape[1]):
        if lit[ray, j] != lit[other, j]:
            return False
    return True


@inlined
def _share_a_corner(tri, a, b):
    """Whether triangles ``a`` and ``b`` have a corner at the very same position."""
    for k in range(3):
        for j in range(3):
            same = True
            for x in range(3):
                same = same and tri[a, k, x] == tri[b, j, x]
            if same:
                return True
    return False


def _restricted(seen: Visibility, rays: np.ndarray) -> Visibility:
    """``seen`` with only its camera rays ``rays`` (k,) (ascending), renumbered 0..k-1."""
    primary = seen.primary
    prim_id = primary.prim_id[rays]
    hit = np.flatnonzero(prim_id >= 0)
    # Their rows among the hits: a ray's row is the number of hits before it (hit_rays is
    # every hit ray, ascending). One pass, where searching the hits took three times as
    # long for the 512x512 boundary term's 180k rays.
    row_of = np.cumsum(primary.prim_id >= 0) - 1
    at = row_of[rays[hit]]
    points, coords = (np.take(x, at, axis=0) for x in (primary.points, primary.coords))
    sub = PrimaryHits(prim_id, hit, primary.depth[rays], points, coords)
    return replace(seen, primary=sub, lit=[mask[at] for mask in seen.lit])


def antialias_mixed_pixels(
    scene: Scene,
    visibility: Visibility,
    cache: RenderCache,
    image: md.Tensor,
    frame,
    spp: int,
    max_bounces: int,
    grid_spp: int = INTERIOR_SAMPLES,
) -> md.Tensor:
    """``image`` (H, W, 3) with each mixed pixel replaced by the mean of its ``grid_spp``
    (a perfect square) stratified samples, shaded on the tape (module docstring): value
    and derivative from the same samples. ``visibility``: the render's step 1 (``spp``
    samples per pixel); ``frame``: its camera frame (``camera_frame``). Nothing changes
    where ``grid_spp`` <= ``spp``."""
    camera = scene.camera
    width, height = camera.width, camera.height
    # Reused while the render's own visibility and the lights' shadow keys are (as the
    # render's step 1 is): they are all it depends on.
    key = [visibility.stamp, np.array([spp, grid_spp, visibility.shadows])]
    key += [array for light in scene.lights for array in light_key(light)]
    found, _ = cache.get("mixed pixels", key,
                         lambda: mixed_pixels(scene, visibility, spp, grid_spp, cache))  # fmt: skip
    if found is None:
        return image
    pixels, seen = found
    # 3: the mixed pixels' samples on the tape.
    mirrors = Mirrors.of(scene, seen, max_bounces)
    shading = shade_camera_hits(scene, seen, frame, RenderCache(), mirrors, surfaces=False)
    colours = sample_colours(scene, seen.primary.prim_id, shading.colour, shading.rays)
    owner = np.repeat(np.arange(len(pixels)), grid_spp)
    mean = md.scatter_add(colours, owner, len(pixels)) * (1.0 / grid_spp)
    # The pixel's own value times 0 plus the mean: exactly the mean, in value and derivative.
    keep = np.ones((width * height, 1), working_dtype(scene))
    keep[pixels] = 0.0
    flat = md.reshape(image, (width * height, 3)) * keep
    return md.reshape(flat + md.scatter_add(mean, pixels, width * height), image.shape)


def mixed_pixels(
    scene: Scene,
    visibility: Visibility,
    spp: int,
    grid_spp: int = INTERIOR_SAMPLES,
    cache: RenderCache | None = None,
) -> tuple[np.ndarray, Visibility] | None:
    """Steps 1 and 2 of the module docstring, off the tape: the flat indices (m,) of the
    mixed pixels, ascending, and their ``grid_spp`` samples' visibility (m * grid_spp rays,
    pixel by pixel; ``visibility`` is the render's, ``spp`` per pixel). None when no pixel
    is mixed, or ``grid_spp`` <= ``spp``. ``cache``: the render's, where the candidates'
    first hits are kept (``_kept_first_hits``); None: none kept."""
    camera = scene.camera
    width, height = camera.width, camera.height
    if spp >= grid_spp:
        return None
    own_prim, own_lit = what_is_seen(visibility, width * height * spp)
    pixels = candidate_pixels(own_prim, own_lit, width, height, spp)
    frame = plain_frame(scene.camera)
    pixels = past_creases(pixels, own_prim, own_lit, width, height, spp,
                          visibility.primitives[0], frame, grid_spp)  # fmt: skip
    if len(pixels) == 0:
        return None
    # 2: the candidates' samples, traced and shadow-tested as camera rays are.
    coords = sample_coords(pixels, grid_spp, width, height)
    forward, right, up, eye = frame
    directions = camera_directions(coords, right, up, forward)
    prim_id, depth = _kept_first_hits(scene, visibility, cache, pixels, directions, grid_spp)
    seen = seen_through(scene, visibility, coords, prim_id, depth, directions)
    prim, lit = what_is_seen(seen, len(coords))
    own = pixels * spp  # each candidate's first sample
    same = (prim.reshape(-1, grid_spp) == own_prim[own][:, None]) & np.all(
        lit.reshape(len(pixels), grid_spp, -1) == own_lit[own][:, None], axis=2
    )
    mixed = np.flatnonzero(~np.all(same, axis=1))
    if len(mixed) == 0:
        return None
    rays = (mixed[:, None] * grid_spp + np.arange(grid_spp)).reshape(-1)
    return pixels[mixed], _restricted(seen, rays)


#: ``_FirstHits.adding`` keeps at most this many times the rows a render needs.
KEPT_ROWS = 4


@dataclass(frozen=True)
class _FirstHits:
    """The first hits of the ``grid_spp`` samples of the pixels traced so far: each pixel's
    row (W * H,) int64 (-1: not traced), and per row its samples' prim_id and depth (rows,
    grid_spp)."""

    row: np.ndarray
    prim_id: np.ndarray
    depth: np.ndarray

    def adding(self, pixels: np.ndarray, prim_id, depth, keep: np.ndarray) -> _FirstHits:
        """These hits and those of ``pixels`` (k,) (not traced so far; ``prim_id``, ``depth``
        (k * grid_spp,)), in new arrays. Where the rows would pass ``KEPT_ROWS`` times the
        ``keep`` pixels' (m,) (those a render needs now), only theirs are kept: the store
        holds what a fit's last renders saw, not every pixel it ever saw."""
        grid = self.prim_id.shape[1]
        row, old_prim, old_depth = self.row, self.prim_id, self.depth
        if len(old_prim) + len(pixels) > KEPT_ROWS * len(keep):
            held = keep[row[keep] >= 0]
            old_prim, old_depth = old_prim[row[held]], old_depth[row[held]]
            row = np.full(len(row), -1, np.int64)
            row[held] = np.arange(len(held))
        else:
            row = row.copy()
        row[pixels] = len(old_prim) + np.arange(len(pixels))
        return _FirstHits(row, np.concatenate([old_prim, prim_id.reshape(-1, grid)]),
                          np.concatenate([old_depth, depth.reshape(-1, grid)]))  # fmt: skip


def _kept_first_hits(
    scene: Scene, visibility: Visibility, cache: RenderCache | None, pixels: np.ndarray,
    directions: np.ndarray, grid_spp: int,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``_first_hits`` of ``pixels`` (m,) (ascending), those of the pixels an earlier render
    traced taken from ``cache`` while the camera rays' hits are the same
    (``visibility.stamp``: the camera and the geometry): where a light moves, its shadows'
    borders move and some candidates with them, but every candidate's samples still meet
    what they met (a light's fit traced them all anew at every step: a fifth of its
    boundary term at 512x512)."""
    if cache is None:
        return _first_hits(scene, visibility, pixels, directions, grid_spp)
    key = [visibility.stamp, np.array([grid_spp])]
    n_pixels = scene.camera.width * scene.camera.height

    def none_yet() -> _FirstHits:
        empty = np.zeros((0, grid_spp))
        return _FirstHits(np.full(n_pixels, -1, np.int64), empty.astype(np.int64), empty)

    kept, _ = cache.get("interior first hits", key, none_yet)
    missing = np.flatnonzero(kept.row[pixels] < 0)
    if len(missing):
        rays = (missing[:, None] * grid_spp + np.arange(grid_spp)).reshape(-1)
        prim_id, depth = _first_hits(scene, visibility, pixels[missing], directions[rays],
                                     grid_spp)  # fmt: skip
        kept = kept.adding(pixels[missing], prim_id, depth, pixels)
        cache.put("interior first hits", key, kept)
    rows = kept.row[pixels]
    return kept.prim_id[rows].reshape(-1), kept.depth[rows].reshape(-1)


def _first_hits(
    scene: Scene, visibility: Visibility, pixels: np.ndarray, directions: np.ndarray, grid_spp: int
) -> tuple[np.ndarray, np.ndarray]:
    """(prim_id, depth) (m * grid_spp,) each: where the camera rays of the ``grid_spp``
    samples of ``pixels`` (m,), directions ``directions`` (m * grid_spp, 3), first meet the
    scene. Rasterised where there are many rays per primitive, as the render's own camera
    rays are (``render.trace.raster``: the very hits the accelerator finds for the same
    rays; these rays graze the silhouettes, where a BVH walks deepest: 80 ms against 14 ms
    for the teapot's 363k at 512x512), else traced. Brute force (``bvh=False``) traces."""
    triangles, centers, _ = visibility.primitives
    n_primitives = len(triangles) + len(centers)
    if visibility.bvh and n_primitives * RASTER_RAYS_PER_PRIMITIVE <= len(directions):
        prim_id, depth, _, _ = raster_closest_hit(
            *visibility.primitives, scene.camera, grid_spp, with_uv=False, pixels=pixels,
            directions=directions,
        )  # fmt: skip
        return prim_id, depth
    eye = plain_frame(scene.camera)[3]
    prim_id, depth, _, _ = visibility.accelerator().closest_hit(
        np.broadcast_to(eye, directions.shape), directions
    )
    return prim_id, depth
