"""The path integrator: an image from sampled paths, and its gradient two ways.

``render_path`` renders ``spp`` paths per pixel in batches of ``batch_spp`` samples. With
gradients enabled every batch stays on the tape until the caller's ``backward``: memory
grows with spp x depth (way 1, plain reverse mode).

``replay_gradient`` is the adjoint by replay (the structure of radiative backpropagation,
Nimier-David et al. 2020): a primal pass without a tape gives the image and dL/dimage; then
each batch of samples is rendered again on its own short tape, with the same random numbers
(the same path ids under ``seed_grad``), and ``backward`` takes its share of dL/dimage into
the parameters before the tape is dropped. Memory is that of one batch, whatever spp is.
Each batch's tape still holds its paths' every vertex, so memory grows with max_depth (path
replay, Vicini et al. 2021, would also make it constant in depth; not done here).

With ``seed_grad == seed`` both ways compute the same gradient to float rounding. For an
unbiased gradient of a non-linear loss, pass a different ``seed_grad`` (as Mitsuba 3's
``seed_grad``): dL/dimage then comes from samples independent of those the derivative of
the image is estimated with, and E[dL/dI * dI/dtheta] is the product of the expectations.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

import minidiff as md
from minidiff import buffers
from render.edges.terms import differentiated
from render.path.edges import add_path_boundary_term
from render.path.random import check_seed
from render.path.tracer import PathSampler, check_path_options
from render.path.transport import path_radiance
from render.scene.camera import camera_frame
from render.scene.placement import placed
from render.scene.scene import MAX_RAYS, Scene, check_ray_count

#: Default samples per pixel in one batch (one tape, for ``replay_gradient``).
BATCH_SPP = 16
#: Default number of vertices before Russian roulette may end a path (Mitsuba's rr_depth).
RR_DEPTH = 5


def render_path(
    scene: Scene,
    spp: int = 16,
    max_depth: int = 5,
    seed: int = 0,
    rr_depth: int = RR_DEPTH,
    batch_spp: int = BATCH_SPP,
    antialias: bool | str = False,
    edge_spp: int | None = None,
) -> md.Tensor:
    """The (H, W, 3) image of ``scene`` by the path integrator: the mean of ``spp`` paths
    per pixel, each at most ``max_depth`` segments long (1: emitters seen directly; 2:
    direct light; 3: one indirect bounce; ...). The same seed gives the same image bit for
    bit, whatever ``batch_spp`` and the number of threads.

    antialias: False (default): no edge term, the motion of silhouettes has no gradient;
    "boundary": add primary visibility's boundary term (``render.path.edges``; zero in
    value), its jumps estimated with ``edge_spp`` paths per side of each edge point (None:
    ``spp``)."""
    spp, max_depth, rr_depth = check_path_options(spp, max_depth, rr_depth)
    seed = check_seed(seed)
    batch_spp = check_count("batch_spp", batch_spp)
    edges, edge_spp = check_path_edges(antialias, edge_spp, spp)
    scene.validate()
    check_ray_count(scene.camera.width, scene.camera.height, spp)
    # Every batch has arrays of new shapes (the paths alive at each depth): reusing
    # minidiff's buffers would only fill its pool with arrays nobody asks for again.
    with buffers.fresh():
        return _render_path(scene, spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp)


def _render_path(scene, spp, max_depth, seed, rr_depth, batch_spp, edges, edge_spp):
    world = placed(scene)
    sampler = PathSampler(world, spp, max_depth, rr_depth, seed)
    frame = camera_frame(world.camera)
    total = None
    for first in range(0, spp, batch_spp):
        samples = _batch_samples(world, frame, sampler, first, min(first + batch_spp, spp))
        # One sample after the other, so that the sum's rounding does not depend on the
        # batches (the same seed, the same image bit for bit, whatever batch_spp).
        for s in range(samples.shape[2]):
            total = samples[:, :, s] if total is None else total + samples[:, :, s]
    image = total * (1.0 / spp)
    if edges and differentiated(scene):
        image = add_path_boundary_term(scene, world, image, frame, sampler, edge_spp)
    return image


def check_path_edges(antialias, edge_spp, spp: int) -> tuple[bool, int]:
    """(whether to add the boundary term, paths per side of an edge point), or a clear
    error: the path integrator's edge term is the boundary integral only."""
    if antialias is False or antialias is None:
        edges = False
    elif antialias == "boundary":
        edges = True
    else:
        raise ValueError(
            'render: the path integrator takes antialias=False or "boundary" (the boundary '
            f"integral of primary visibility), got {antialias!r}"
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


def check_count(name: str, value) -> int:
    """``value`` as an int if it is an integer >= 1, else a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"render: {name} must be an integer >= 1, got {value!r}")
    return int(value)


def _batch_samples(world, frame, sampler: PathSampler, first: int, last: int) -> md.Tensor:
    """The radiance of samples first..last-1 of every pixel, (H, W, last - first, 3)."""
    camera = world.camera
    pixels = np.arange(camera.width * camera.height, dtype=np.int64)
    paths = (pixels[:, None] * sampler.spp + np.arange(first, last)[None, :]).ravel()
    radiance = path_radiance(world, frame, sampler, sampler.sample(paths))
    return md.reshape(radiance, (camera.height, camera.width, last - first, 3))


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
    ``seed_grad``: the seed of the gradient pass (None: ``seed + 1``, decorrelated; pass
    ``seed`` to reproduce the tape's gradient exactly). Peak memory is one batch's tape.
    ``antialias``, ``edge_spp``: as ``render_path``; the boundary term is computed once,
    after the batches, with ``seed_grad``'s random numbers."""
    spp, max_depth, rr_depth = check_path_options(spp, max_depth, rr_depth)
    seed = check_seed(seed)
    edges, edge_spp = check_path_edges(antialias, edge_spp, spp)
    seed_grad = check_seed(seed + 1 if seed_grad is None else seed_grad, "seed_grad")
    with md.no_grad():
        image = render_path(scene, spp, max_depth, seed, rr_depth, batch_spp).data
    with buffers.fresh():  # as in render_path
        return _replay(scene, loss, image, spp, max_depth, seed_grad, rr_depth, batch_spp,
                       edges, edge_spp)  # fmt: skip


def _replay(scene, loss, image, spp, max_depth, seed_grad, rr_depth, batch_spp, edges, edge_spp):
    pixels = md.tensor(image, requires_grad=True)
    value = loss(pixels)
    if not isinstance(value, md.Tensor) or value.data.size != 1:
        raise TypeError("replay_gradient: loss must return a scalar minidiff tensor")
    value.backward()
    adjoint = pixels.grad / spp
    sampler = None
    for first in range(0, spp, batch_spp):
        world = placed(scene)  # a fresh tape per batch: placement is on it too
        if sampler is None:  # plain arrays: the same for every batch
            sampler = PathSampler(world, spp, max_depth, rr_depth, seed_grad)
        last = min(first + batch_spp, spp)
        samples = _batch_samples(world, camera_frame(world.camera), sampler, first, last)
        # This batch's share of the image is sum_s samples / spp; its share of dL/dtheta:
        md.sum(samples * adjoint[:, :, None, :]).backward()  # (adjoint already / spp)
    if edges and differentiated(scene):
        world = placed(scene)
        zero = md.tensor(np.zeros_like(image))
        term = add_path_boundary_term(
            scene, world, zero, camera_frame(world.camera), sampler, edge_spp
        )
        md.sum(term * pixels.grad).backward()
    return float(value.data), image
