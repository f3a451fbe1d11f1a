"""Recover the colour of a wall the camera never sees, from the light it bleeds.

In the Cornell box the camera looks at the right-hand part of the room: the green wall,
the floor, the back wall and the blocks, but not the red wall. The red wall's albedo still
changes the image: light bounces off it onto everything the camera sees (colour bleeding),
so a path integrator with at least one indirect bounce (max_depth >= 3) has a gradient
for it, and the direct renderer has none. Starting from grey, Adam on the image MSE with
the replay gradient (``render.path.replay_gradient``, decorrelated seeds, new samples every
iteration) recovers it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

import minidiff as md
from render.path import render_path, replay_gradient
from render.scene.camera import Camera
from render.scene.cornell import RED, cornell_box
from render.scene.scene import Scene

#: The wall whose albedo is recovered (index in ``cornell_box``'s objects): the red one.
HIDDEN_WALL = 3
START = (0.4, 0.4, 0.4)


def bleeding_scene(size: int) -> Scene:
    """The Cornell box seen by a camera that sees neither the red wall nor the light."""
    scene = cornell_box(size, size)
    scene.camera = Camera((0.45, -0.2, 3.9), (0.45, -0.6, 0.0), (0, 1, 0), 28.0, size, size)
    return scene


@dataclass
class BleedingRun:
    """One recovery: the albedo after every iteration (iterations + 1, 3) (row 0: the
    start), its error |albedo - true| / |true| per iteration, the loss per iteration, the
    seconds it took, and the target, start and final images (H, W, 3)."""

    albedo: np.ndarray
    error: np.ndarray
    loss: np.ndarray
    seconds: float
    images: dict = field(default_factory=dict)


def recover_hidden_albedo(
    size: int = 32,
    spp: int = 16,
    iterations: int = 100,
    lr: float = 0.05,
    max_depth: int = 4,
    target_spp: int = 512,
) -> BleedingRun:
    """Fit the red wall's albedo to a ``target_spp`` render of the true scene with Adam
    (step ``lr``, decaying to lr / 10), ``spp`` new samples per iteration (seed =
    iteration; the gradient pass's seed decorrelated), the albedo kept in [0, 1]."""
    truth = np.array(RED)
    target = render_path(bleeding_scene(size), spp=target_spp, max_depth=max_depth, seed=10**6).data
    scene = bleeding_scene(size)
    albedo = scene.objects[HIDDEN_WALL].material.albedo
    albedo.data = np.array(START, dtype=float)
    albedo.requires_grad = True
    optimiser = md.optim.Adam([albedo], lr=lr, project=md.optim.box(0.0, 1.0))  # a fraction

    def loss(image):
        return md.mean((image - md.tensor(target)) ** 2)

    with md.no_grad():
        start_image = render_path(scene, spp=target_spp, max_depth=max_depth, seed=10**6).data
    history, losses = [albedo.data.copy()], []
    begin = time.perf_counter()
    for it in range(iterations):
        albedo.grad = None
        # The step shrinks tenfold over the run: later steps average the noise of more
        # gradients (each from ``spp`` samples) instead of following every one.
        optimiser.lr = [lr * 0.1 ** (it / iterations)]
        value, _ = replay_gradient(
            scene, loss, spp=spp, max_depth=max_depth, seed=it, seed_grad=it + 10**7
        )
        optimiser.step()
        history.append(albedo.data.copy())
        losses.append(value)
    seconds = time.perf_counter() - begin
    with md.no_grad():
        final = render_path(scene, spp=target_spp, max_depth=max_depth, seed=10**6).data
    history = np.array(history)
    error = np.linalg.norm(history - truth, axis=1) / np.linalg.norm(truth)
    images = {"target": target, "start": start_image, "final": final}
    return BleedingRun(history, error, np.array(losses), seconds, images)
