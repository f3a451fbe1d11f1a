"""The path integrator: an image from sampled paths, and its gradient.

``render_path`` renders ``spp`` paths per pixel. Nothing differentiated: the compiled
kernel's image (``render.path.twin.kernel``). With ``gradient="tape"`` the reference samples
batches of ``batch_spp`` samples and every batch stays on the tape until the caller's
``backward``: memory grows with spp x depth (plain reverse mode, the readable reference).
By default (``gradient="replay"``) the image is the kernel's, one node on the tape whose
VJP (``_backpropagate``) replays the image's paths with the caller's dL/dimage
(``render.path.gradient.replay``): the kernel records each path's decisions, and the
gradient of every parameter is compiled from the readable formulas, each path's reverse
sweep inside one kernel (``render.path.gradient.window``; one depth at a time on the tape
where that does not apply: float32, a light without compiled shading). ``backward`` gives
the tape's gradient (to rounding), and memory does not grow with spp. Forward mode
(tangents) takes the same compiled function's JVP over the kernel's records
(``_image_tangent``). An image whose paths the replay takes in one go (one batch of at
most ``replay_paths`` paths) keeps their records from the render to the ``backward``
(``_KeptPaths``), which its replay would make anyway: its paths are traced once, not
twice. A larger image keeps nothing: its replay traces its paths again.

``replay_gradient`` is the same adjoint for a loss given as a function (the structure of
radiative backpropagation, Nimier-David et al. 2020): a primal pass without a tape gives
the image and dL/dimage, then the paths are replayed with the same random numbers (the
same path ids under ``seed_grad``) and their gradient goes into the parameters.

With ``seed_grad == seed`` both ways compute the same gradient to float rounding. For an
unbiased gradient of a non-linear loss, pass a different ``seed_grad`` (as Mitsuba 3's
``seed_grad``): dL/dimage then comes from samples independent of those the derivative of
the image is estimated with, and E[dL/dI * dI/dtheta] is the product of the expectations.
``render_path``'s own replay uses the image's seed (it reproduces the tape's gradient).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

import minidiff as md
from minidiff import buffers
from minidiff.tensor import record
from render.edges.terms import curves_move, differentiated, on_every_parameter
from render.path.boundary.primary import add_path_boundary_term
from render.path.boundary.secondary import add_secondary_term, backpropagate_secondary
from render.path.gradient import window
from render.path.gradient.replay import backpropagate_paths
from render.path.gradient.transport import path_radiance
from render.path.sample import records
from render.path.sample.random import check_seed
from render.path.sample.tables import Tables, compiles
from render.path.sample.tracer import PathSampler, check_count, check_path_options
from render.path.twin import kernel
from render.scene.cache import cache_for
from render.scene.camera import camera_frame
from render.scene.placement import placed
from render.scene.scene import MAX_RAYS, Scene, check_ray_count
from render.scene.substitute import substituted

#: Default samples per pixel in one batch (one tape, for ``replay_gradient``).
BATCH_SPP = 16
#: The replay takes a batch's paths at most this many at a time, and fewer for deep paths
#: (``replay_paths``): a 512x512 batch of 16 samples would otherwise hold 4 million
#: paths' records at once (gigabytes).
REPLAY_PATHS = 2**17
#: ... so that the records of the paths replayed at once take at most about this many bytes.
REPLAY_RECORD_BYTES = 2**26
#: Default number of vertices before Russian roulette may end a path (Mitsuba's rr_depth).
RR_DEPTH = 5
#: ``antialias`` -> (primary visibility's boundary term, secondary visibility's).
EDGE_TERMS = {"boundary": (True, True), "primary": (True, False), "secondary": (False, True)}
#: How ``render_path``'s image is differentiated (its ``gradient`` argument).
GRADIENTS = ("replay", "tape")


def render_path(
    scene: Scene,
    spp: int = 16,
    max_depth: int = 5,
    seed: int = 0,
    rr_depth: int = RR_DEPTH,
    batch_spp: int = BATCH_SPP,
    antialias: bool | str = False,
    edge_spp: int | None = None,
    gradient: str = "replay",
) -> md.Tensor:
    """The (H, W, 3) image of ``scene`` by the path integrator: the mean of ``spp`` paths
    per pixel, each at most ``max_depth`` segments long (1: emitters seen directly; 2:
    direct light; 3: one indirect bounce; ...). The same seed gives the same image bit for
    bit, whatever ``batch_spp`` and the number of threads.

    antialias: False (default): no edge term, the motion of silhouettes and shadows has no
    gradient; "boundary": add the boundary terms of primary and secondary visibility (zero
    in value): the camera's silhouettes (``render.path.boundary.primary``, its jumps estimated with
    ``edge_spp`` paths per side of each edge point; None: ``spp``) and the edges of
    shadows and indirect occlusion seen from the paths' vertices
    (``render.path.boundary.secondary``, ``spp`` boundary paths per pixel); "primary" or
    "secondary": one of the two.

    gradient: how ``backward`` reaches the parameters (reverse mode; forward mode's tangents
    are computed on the tape either way). "replay" (default): the image is the kernel's,
    one node on the tape; its VJP replays the paths (``_backpropagate``): memory that does
    not grow with ``spp``, the tape's gradient to rounding. "tape": every batch of
    ``batch_spp`` samples stays on the tape until ``backward``: memory grows with spp x
    depth (~3 MB per sample per pixel at 32x32, depth 4)."""
    spp, max_depth, rr_depth = check_path_options(spp, max_depth, rr_depth)
    seed = check_seed(seed)
    batch_spp = check_count("batch_spp", batch_spp)
    edges, edge_spp = check_path_edges(antialias, edge_spp, spp)
    scene.validate()
    check_ray_count(scene.camera.width, scene.camera.height, spp)
    # Every batch has arrays of new shapes (the paths alive at each depth): reusing
    # minidiff's buffers would only fill its pool with arrays nobody asks for again.
    with buffers.fresh():
        options = (spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp)
        if _replays(scene, gradient):
            image = _replayed_image(scene, *options)
        else:
            image = _render_path(scene, *options)
    return on_every_parameter(image, scene)  # zeros for what the image cannot depend on


def _render_path(scene, spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp, kept=None,
                 sampler=None):  # fmt: skip
    if sampler is None:
        sampler = PathSampler(placed(scene), spp, max_depth, rr_depth, seed, cache_for(scene, True))
    world = sampler.scene
    if not differentiated(scene) and kernel.applies(world):
        # Nothing to differentiate: the compiled kernel alone (render.path.twin.kernel).
        if kept is None:
            return md.tensor(kernel.render_image(sampler))
        return md.tensor(kept.image(sampler))
    return _taped_image(scene, world, sampler, spp, batch_spp, edges, edge_spp)


class _KeptPaths:
    """The records and radiance of an image's paths, from the render (``image``) to the
    replay's ``backward`` (``take``), which would trace the same paths to make them: kept
    only where the replay on the tape takes every path in one go (``wanted``), so they are
    what its one chunk holds anyway."""

    def __init__(self) -> None:
        self._paths: tuple | None = None

    @staticmethod
    def wanted(world: Scene, spp: int, batch_spp: int, max_depth: int) -> bool:
        """Whether ``_replay_batches`` would replay the image of ``world`` (the placed
        scene) from the kernel's records of all its paths at once: the kernel traces it,
        and one batch holds them all, at most ``replay_paths(max_depth)`` paths."""
        camera = world.camera
        if spp > batch_spp or camera.width * camera.height * spp > replay_paths(max_depth):
            return False
        return kernel.applies(world)  # (float64 and lights it shades: placed or not)

    def image(self, sampler: PathSampler) -> np.ndarray:
        """The (H, W, 3) image of ``kernel.render_image(sampler)``, bit for bit (each
        pixel's samples summed in sample order, times 1 / spp), from the records it
        keeps."""
        camera = sampler.scene.camera
        paths = _batch_paths(sampler.scene, sampler, 0, sampler.spp)
        batch, radiance = kernel.sample_paths(sampler, paths)
        self._paths = paths, batch, radiance
        per_pixel = radiance.reshape(camera.height, camera.width, sampler.spp, 3)
        total = per_pixel[:, :, 0]
        for sample in range(1, sampler.spp):
            total = total + per_pixel[:, :, sample]
        return total * (1.0 / sampler.spp)

    def take(self, paths: np.ndarray) -> tuple | None:
        """(batch, radiance) of ``paths`` if they are the kept ones (then forgotten: a
        second ``backward`` traces them again), else None."""
        kept, self._paths = self._paths, None
        if kept is None or not np.array_equal(kept[0], paths):
            return None
        return kept[1], kept[2]


def _taped_image(scene, world, sampler, spp, batch_spp, edges, edge_spp):
    """The image of ``sampler``'s paths on the tape (the readable reference): batches of
    ``batch_spp`` samples from the plain sampler, their radiance recomputed on the tape."""
    frame = camera_frame(world.camera)
    total = None
    for first in range(0, spp, batch_spp):
        samples = _batch_samples(world, frame, sampler, first, min(first + batch_spp, spp))
        # One sample after the other, so that the sum's rounding does not depend on the
        # batches (the same seed, the same image bit for bit, whatever batch_spp).
        for s in range(samples.shape[2]):
            total = samples[:, :, s] if total is None else total + samples[:, :, s]
    image = total * (1.0 / spp)
    moves = curves_move(scene, world)  # else the edge terms are zero in derivative too
    if edges[0] and moves:
        image = add_path_boundary_term(scene, world, image, frame, sampler, edge_spp)
    if edges[1] and moves:
        image = add_secondary_term(world, image, frame, sampler)
    return image


def check_path_edges(antialias, edge_spp, spp: int) -> tuple[tuple[bool, bool], int]:
    """((whether to add primary visibility's boundary term, and secondary's), paths per side
    of a primary edge point), or a clear error: the path integrator's edge terms are
    boundary integrals only."""
    if antialias is False or antialias is None:
        edges = (False, False)
    elif isinstance(antialias, str) and antialias in EDGE_TERMS:
        edges = EDGE_TERMS[antialias]
    else:
        raise ValueError(
            'render: the path integrator takes antialias=False, "boundary" (the boundary '
            'integrals of primary and secondary visibility), "primary" or "secondary", got '
            f"{antialias!r}"
        )
    if edge_spp is None:
        return edges, spp
    if isinstance(edge_spp, bool) or not isinstance(edge_spp, int | np.integer) or edge_spp < 1:
        raise ValueError(f"render: edge_spp must be an integer >= 1 or None, got {edge_spp!r}")
    if edge_spp > MAX_RAYS:  # one edge point's paths are traced together: already too many
        raise ValueError(
            f"render: edge_spp = {edge_spp:,} paths per side of an edge point is more than "
            f"the limit of {MAX_RAYS:,} rays traced at once (2**26, the limit of width x "
            "height x spp)"
        )
    return edges, int(edge_spp)


def _batch_paths(world, sampler: PathSampler, first: int, last: int) -> np.ndarray:
    """The path ids of samples first..last-1 of every pixel, pixel by pixel: (H W (last -
    first),) int64."""
    camera = world.camera
    pixels = np.arange(camera.width * camera.height, dtype=np.int64)
    return (pixels[:, None] * sampler.spp + np.arange(first, last)[None, :]).ravel()


def _path_chunks(sampler: PathSampler, batch_spp: int):
    """The image's path ids as the compiled routes take them: a batch of ``batch_spp``
    samples of every pixel after the other (``_batch_paths``), each in chunks of at most
    ``replay_paths`` paths (memory bounded whatever the image's size and depth)."""
    at_once = replay_paths(sampler.max_depth)
    for first in range(0, sampler.spp, batch_spp):
        paths = _batch_paths(sampler.scene, sampler, first, min(first + batch_spp, sampler.spp))
        for start in range(0, len(paths), at_once):
            yield paths[start : start + at_once]


def _batch_samples(world, frame, sampler: PathSampler, first: int, last: int) -> md.Tensor:
    """The radiance of samples first..last-1 of every pixel, (H, W, last - first, 3), on the
    tape: the reference sampler's paths, their radiance recomputed on the tape."""
    camera = world.camera
    batch = sampler.sample(_batch_paths(world, sampler, first, last))
    radiance = path_radiance(world, frame, sampler, batch)
    return md.reshape(radiance, (camera.height, camera.width, last - first, 3))


def _replays(scene: Scene, gradient: str) -> bool:
    """Whether ``render_path`` returns the image as one node differentiated by replay:
    ``gradient="replay"`` and a parameter is differentiated (it requires grad with
    gradients enabled, or carries a tangent)."""
    if gradient not in GRADIENTS:
        raise ValueError(f'render: gradient must be "replay" or "tape", got {gradient!r}')
    return gradient == "replay" and differentiated(scene)


def _replayed_image(scene, spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp):
    """The image of ``_render_path`` as one node on the tape, rendered without a tape.

    Its inputs are the scene's parameters that require grad or carry a tangent; its VJP
    takes dL/dimage (H, W, 3) back to them by replay (``_backpropagate``), with the
    image's own seed, so it is the tape's gradient to rounding. The render and the replay
    both use a copy of the scene holding copies of the parameters' values at the time of
    the render (``frozen``): a parameter edited between the render and ``backward`` does
    not change the gradient of the image that was rendered.

    The copies of the moving parameters must look differentiated in the render as the
    originals do on the tape: some choices of the sampler depend on it (an emission being
    differentiated makes its surface an area light that NEE samples, ``Material.emissive``).
    The value: they require grad and the render runs under ``no_grad()`` (the kernel's
    image). With forward mode, first the tangent: each copy carries its parameter's tangent
    (zero if it has none) and nothing requires grad, so nothing is recorded
    (``_image_tangent``: the compiled paths' JVP; the image's tangent is the tape's)."""
    parameters = scene.parameters()
    copies = {id(p): md.tensor(p.data) for p in parameters}
    frozen = substituted(scene, copies, {}, copies=True)  # validated on entry, copied since
    moving = [p for p in parameters if p.requires_grad or p.tangent is not None]
    leaves = [copies[id(p)] for p in moving]
    options = (spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp)
    tangent = value = None
    if any(p.tangent is not None for p in moving):
        directions = {
            leaf: np.zeros(p.shape, p.dtype) if p.tangent is None else p.tangent
            for p, leaf in zip(moving, leaves, strict=True)
        }
        with md.tangents(directions):
            tangent, value = _image_tangent(frozen, *options)
    for leaf in leaves:
        leaf.requires_grad = True
    with md.no_grad():  # the value: the kernel's image when it applies, as without tangents
        # The sampler reads the frozen values only: the replay uses it too.
        sampler = PathSampler(placed(frozen), spp, max_depth, rr_depth, seed,
                              cache_for(frozen, True))  # fmt: skip
        kept = None
        if value is not None and not any(p.requires_grad for p in moving):
            image = md.tensor(value)  # the tangent's paths gave it: no backward to keep them for
        else:
            wanted = _KeptPaths.wanted(sampler.scene, spp, batch_spp, max_depth)
            kept = _KeptPaths() if wanted else None
            image = _render_path(frozen, *options, kept=kept, sampler=sampler)

    def vjp(d_image: np.ndarray) -> tuple[np.ndarray | None, ...]:
        for leaf in leaves:  # every moving copy, as differentiated as on the tape
            leaf.requires_grad, leaf.grad = True, None
        # Recorded even when the caller's backward runs under no_grad().
        with md.enable_grad(), buffers.fresh():
            _backpropagate(frozen, d_image, spp, max_depth, seed, rr_depth, batch_spp, edges,
                           edge_spp, kept, sampler)  # fmt: skip
        return tuple(leaf.grad for leaf in leaves)  # None: the image does not depend on it

    return record("path_image", image.data, moving, vjp, jvp=lambda *_: tangent)


def _image_tangent(scene, spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp):
    """(the tangent (H, W, 3) of ``_render_path``'s image along the tangents that the
    parameters of ``scene`` carry, the image or None), called within ``md.tangents``
    (nothing requires grad, so nothing is recorded). Where the kernel and the compiled
    paths apply, each path's radiance's tangent is the compiled JVP of its whole path
    (``window.tangent``) read from the kernel's records, at most ``replay_paths`` paths at
    a time, a batch of ``batch_spp`` samples after the other (memory bounded as the
    replay's); the edge terms add their own tangents. The kernel's radiance of those paths
    gives the image too, each pixel's samples summed in sample order as
    ``kernel.render_image`` sums them (bit for bit). Elsewhere the reference computes the
    tangent on the tape as it goes (and the image is left to the caller)."""
    sampler = PathSampler(placed(scene), spp, max_depth, rr_depth, seed, cache_for(scene, True))
    world = sampler.scene
    options = (spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp)
    if not (kernel.applies(world) and compiles(world)):
        return _render_path(scene, *options, sampler=sampler).tangent, None
    frame = camera_frame(world.camera)
    tables = Tables.of(world, frame, leaves=False)  # their tangents, from the parameters'
    camera = world.camera
    shape = (camera.height, camera.width, 3)
    total, image = np.zeros((shape[0] * shape[1], 3)), np.zeros((shape[0] * shape[1], 3))
    packed = kernel.pack(sampler)
    for paths in _path_chunks(sampler, batch_spp):
        batch, radiance = kernel.sample_paths(sampler, paths, packed)
        # Each path to its pixel (its id is pixel x spp + sample), one after the other.
        np.add.at(total, paths // spp, window.tangent(tables, batch))
        np.add.at(image, paths // spp, radiance)
    out = total.reshape(shape) * (1.0 / spp)
    if any(edges) and curves_move(scene, world):  # else the edge terms are zero in it too
        terms = md.tensor(np.zeros(out.shape))  # the edge terms alone (zero in value)
        if edges[0]:
            terms = add_path_boundary_term(scene, world, terms, frame, sampler, edge_spp)
        if edges[1]:
            terms = add_secondary_term(world, terms, frame, sampler)
        if terms.tangent is not None:
            out = out + terms.tangent
    return out, image.reshape(shape) * (1.0 / spp)


def _backpropagate(scene, d_image, spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp,
                   kept=None, sampler=None):  # fmt: skip
    """Add d_image . d image / d p (``d_image`` (H, W, 3): dL/dimage) to ``p.grad`` of every
    parameter of ``scene`` that requires grad, as ``backward`` through ``_render_path``'s
    tape would, by replaying the image's paths (the same path ids and random numbers under
    ``seed``), a batch of ``batch_spp`` samples at a time (from ``kept``'s records where it
    holds them; ``_replay_batches``). A parameter the image cannot depend on gets zeros."""
    if sampler is None:
        world = placed(scene)
        sampler = PathSampler(world, spp, max_depth, rr_depth, seed, cache_for(scene, True))
    _replay_batches(scene, sampler, d_image, batch_spp, kept)
    world = placed(scene) if any(edges) else None  # placed anew only for the edge terms
    moves = world is not None and curves_move(scene, world)  # else they are zero too
    if edges[0] and moves:
        zero = md.tensor(np.zeros(d_image.shape, d_image.dtype))
        term = add_path_boundary_term(
            scene, world, zero, camera_frame(world.camera), sampler, edge_spp
        )
        if term.requires_grad:
            md.sum(term * d_image).backward()
    if edges[1] and moves:
        backpropagate_secondary(lambda: placed(scene), sampler, d_image)
    _zeros_where_missing(scene)


def replay_paths(max_depth: int) -> int:
    """How many paths the replay takes at once for paths of up to ``max_depth`` vertices:
    ``REPLAY_PATHS``, or fewer where their records would take more than
    ``REPLAY_RECORD_BYTES`` (at least 1,024)."""
    rows = min(max_depth, kernel.RECORD_ROWS)
    return min(REPLAY_PATHS, max(1024, REPLAY_RECORD_BYTES // (records.BYTES_PER_VERTEX * rows)))


def _zeros_where_missing(scene: Scene) -> None:
    """Give every parameter of ``scene`` that requires grad and has no gradient a zero one."""
    for p in scene.parameters():
        if p.requires_grad and p.grad is None:
            p.grad = np.zeros(p.shape, p.dtype)


def _replay_batches(scene, sampler: PathSampler, d_image, batch_spp: int,
                    kept: _KeptPaths | None = None) -> None:  # fmt: skip
    """``_backpropagate``'s replay, a batch of ``batch_spp`` samples at a time. With the
    kernel (``kernel.applies``): its paths' records and radiance, replayed
    (``render.path.gradient.replay``: compiled whole paths, or one depth at a time on the
    tape; the paths' records grow with depth), at most ``replay_paths`` paths at a time
    (memory bounded whatever the image's size and depth); else the reference sampler's paths, each
    batch on one tape that its ``backward`` frees before the next batch is rendered.
    ``kept``: the render's records of the paths, if it kept them (``_KeptPaths``)."""
    spp = sampler.spp
    weights = d_image * (1.0 / spp)  # the image is total * (1 / spp)
    if kernel.applies(sampler.scene):
        per_pixel, packed = weights.reshape(-1, 3), None  # packed once it is needed
        for paths in _path_chunks(sampler, batch_spp):
            world = placed(scene)  # a fresh tape each time: placement is on it too
            traced = kept.take(paths) if kept is not None else None
            if traced is None:
                packed = kernel.pack(sampler) if packed is None else packed
                traced = kernel.sample_paths(sampler, paths, packed)
            batch, radiance = traced
            backpropagate_paths(world, camera_frame(world.camera), sampler, batch, radiance,
                                per_pixel[paths // spp])  # fmt: skip
            del batch, radiance, traced  # before the next chunk's records are made
        return
    for first in range(0, spp, batch_spp):
        last = min(first + batch_spp, spp)
        world = placed(scene)  # a fresh tape per batch: placement is on it too
        frame = camera_frame(world.camera)
        samples = _batch_samples(world, frame, sampler, first, last)
        if samples.requires_grad:  # else no parameter that requires grad moves the image
            # This batch's share of the image is sum_s samples / spp; its share of dL/dp:
            md.sum(samples * weights[:, :, None, :]).backward()


def replay_gradient(
    scene: Scene,
    loss: Callable[[md.Tensor], md.Tensor],
    spp: int = 16,
    max_depth: int = 5,
    seed: int = 0,
    seed_grad: int | None = None,
    rr_depth: int = RR_DEPTH,
    batch_spp: int = BATCH_SPP,
    antialias: bool | str = False,
    edge_spp: int | None = None,
) -> tuple[float, np.ndarray]:
    """Differentiate ``loss(image)`` by replay: adds d loss / d p to ``p.grad`` of every
    scene parameter that requires it (as ``backward`` would) and returns (the loss's value,
    the primal image (H, W, 3)). ``loss`` maps an (H, W, 3) tensor to a scalar tensor.
    ``loss``'s value may have shape () or any shape of one element, e.g. (1,); a loss that
    does not depend on the image gives the parameters zero gradients through it.
    ``seed_grad``: the seed of the gradient pass (None: ``seed + 1`` modulo 2**64,
    decorrelated; pass ``seed`` to reproduce the tape's gradient exactly). Peak memory is
    one batch's tape.
    ``antialias``, ``edge_spp``: as ``render_path``; the boundary term is computed once,
    after the batches, with ``seed_grad``'s random numbers."""
    spp, max_depth, rr_depth = check_path_options(spp, max_depth, rr_depth)
    seed = check_seed(seed)
    edges, edge_spp = check_path_edges(antialias, edge_spp, spp)
    # The default is derived from seed, already checked: it wraps rather than blame seed_grad.
    seed_grad = (seed + 1) % 2**64 if seed_grad is None else check_seed(seed_grad, "seed_grad")
    with md.no_grad():
        image = render_path(scene, spp, max_depth, seed, rr_depth, batch_spp).data
    with buffers.fresh():  # as in render_path
        return _replay(scene, loss, image, spp, max_depth, seed_grad, rr_depth, batch_spp,
                       edges, edge_spp)  # fmt: skip


def _replay(scene, loss, image, spp, max_depth, seed_grad, rr_depth, batch_spp, edges, edge_spp):
    pixels = md.tensor(image, requires_grad=True)
    value = loss(pixels)
    if not isinstance(value, md.Tensor) or value.data.size != 1:
        got = f"shape {value.shape}" if isinstance(value, md.Tensor) else type(value).__name__
        raise TypeError(
            "replay_gradient: loss must return a minidiff tensor of one element (the loss of "
            f"the (H, W, 3) image it is given), got {got}"
        )
    if value.requires_grad:  # else a constant: it depends on no image and no parameter
        value.backward()
    if pixels.grad is None:  # the loss does not read the image: nothing to replay
        _zeros_where_missing(scene)
    else:
        _backpropagate(scene, pixels.grad, spp, max_depth, seed_grad, rr_depth, batch_spp, edges,
                       edge_spp)  # fmt: skip
    return float(value.item()), image
