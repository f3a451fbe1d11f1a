"""A neural field trained through the renderer, in minidiff: one of the paper's "end-to-end
training experiments in which neural network weights and scene parameters are jointly
optimized through the differentiable renderer" (``examples/neural_field.py``; README "From
PyTorch / JAX").

A small MLP on Fourier features (Tancik et al. 2020) maps a 3-D surface point to an albedo
(``field_setup``, ``train_field_minidiff``). It is evaluated at the texel centres of the
teapot's atlas (``render.scene.teapot.teapot_atlas``: each texel knows its point on the
exact surface), which makes the texture the renderer samples; the loss compares renders
from 8 views with targets painted by ``pattern``, a function of 3-D position. ``mlp`` is
written once for any array module (minidiff or torch): the PyTorch twin of the training,
through the ``render.torch`` bridge, and the network that predicts the light's position
are experiments beside the example scripts (``examples/torch_networks.py``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import minidiff as md
from render.inverse.reconstruction import view_cameras
from render.renderer import render
from render.scene.image import psnr
from render.scene.scene import Camera, DirectionalLight, Material, Mesh, Scene
from render.scene.teapot import teapot_atlas, teapot_geometry

__all__ = [
    "pattern", "fourier_features", "init_mlp", "mlp", "FieldSetup", "field_setup",
    "field_texture", "held_out_renders", "held_out_psnr", "train_field_minidiff",
    "FIELD_LIGHTS",
]  # fmt: skip


# -- the field --------------------------------------------------------------------------


def pattern(points: np.ndarray) -> np.ndarray:
    """The target albedo, a function of 3-D position: (..., 3) points -> (..., 3) colours
    in [0.15, 0.85]. Horizontal bands (3 per unit of height) crossed with a soft checker in
    x and z, coloured differently in each channel."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    bands = 0.5 + 0.5 * np.sin(2 * np.pi * 3.0 * y)
    checker = 0.5 + 0.5 * np.tanh(3.0 * np.sin(2 * np.pi * 1.5 * x) * np.sin(2 * np.pi * 1.5 * z))
    return np.stack(
        [0.15 + 0.7 * bands, 0.15 + 0.7 * checker, 0.15 + 0.35 * (bands + checker)], axis=-1
    )


def fourier_features(points: np.ndarray, frequencies: np.ndarray) -> np.ndarray:
    """(n, 3) points -> (n, 2m) features [sin(2 pi p B), cos(2 pi p B)] for the (3, m)
    matrix of frequencies B (Tancik et al. 2020's Gaussian Fourier features): the MLP then
    sees high frequencies of position, which it could not build from p itself."""
    angles = 2.0 * np.pi * points @ frequencies
    return np.concatenate([np.sin(angles), np.cos(angles)], axis=1)


def init_mlp(sizes: list[int], seed: int) -> list[np.ndarray]:
    """Weights [W0, b0, W1, b1, ...] of an MLP with layer ``sizes``, W (in, out) drawn
    uniformly in +-sqrt(6 / (in + out)) (Glorot), biases zero."""
    rng = np.random.default_rng(seed)
    weights = []
    for n_in, n_out in zip(sizes[:-1], sizes[1:], strict=True):
        bound = np.sqrt(6.0 / (n_in + n_out))
        weights += [rng.uniform(-bound, bound, (n_in, n_out)), np.zeros(n_out)]
    return weights


def mlp(weights: list, x, ops: Any = md) -> Any:
    """The MLP: ReLU hidden layers, a sigmoid output written as 0.5 (1 + tanh(z / 2)) (the
    same operations in every framework). ``ops`` is the array module: ``minidiff`` or
    ``torch`` (its ``relu``/``tanh`` through ``maximum``/``tanh``)."""
    for k in range(0, len(weights) - 2, 2):
        x = x @ weights[k] + weights[k + 1]
        x = ops.maximum(x, 0.0 * x)
    z = x @ weights[-2] + weights[-1]
    return 0.5 * (1.0 + ops.tanh(0.5 * z))


@dataclass
class FieldSetup:
    """The field experiment: training and held-out views (scenes sharing one textured
    teapot), their targets, and the features of the atlas's texel centres."""

    views: list[Scene]
    targets: np.ndarray  # (V, H, W, 3)
    held_out: list[Scene]
    held_out_targets: np.ndarray
    features: np.ndarray  # (texels, 2m)
    atlas_shape: tuple[int, int, int]
    mesh: Mesh
    sizes: list[int] = field(default_factory=list)


#: White directional lights from the corners of a tetrahedron, so every view shows shading.
FIELD_LIGHTS = ((-1.0, -1.0, -1.0), (1.0, 1.0, -1.0), (1.0, -1.0, 1.0), (-1.0, 1.0, 1.0))


def field_setup(
    views: int = 8,
    held_out: int = 4,
    size: int = 64,
    tile: int = 16,
    frequencies: int = 16,
    scale: float = 1.0,
    hidden: tuple[int, ...] = (32, 32),
    seed: int = 0,
) -> FieldSetup:
    """The scenes and targets: the teapot with its atlas (``tile`` texels per patch side),
    ``views`` training and ``held_out`` other cameras at distance 4 (``view_cameras``,
    seeds 0 and 1), targets rendered with the atlas painted by ``pattern``; Fourier
    features with ``frequencies`` Gaussian frequencies of standard deviation ``scale``
    (seeded by ``seed``); the MLP's layer sizes."""
    vertices, faces = teapot_geometry()
    uvs, points = teapot_atlas(tile)
    truth = pattern(points)
    material = Material((0.5, 0.5, 0.5), texture=truth)
    mesh = Mesh(vertices, faces, material, uvs=uvs)
    lights = [DirectionalLight(d, 2.5) for d in FIELD_LIGHTS]

    def scenes(cameras: list[Camera]) -> list[Scene]:
        return [Scene([mesh], lights, c) for c in cameras]

    train = scenes(view_cameras(views, size, seed=0))
    other = scenes(view_cameras(held_out, size, seed=1))
    with md.no_grad():
        targets = np.stack([render(s).data for s in train])
        other_targets = np.stack([render(s).data for s in other])
    rng = np.random.default_rng(seed)
    matrix = rng.normal(0.0, scale, (3, frequencies))
    features = fourier_features(points.reshape(-1, 3), matrix)
    sizes = [features.shape[1], *hidden, 3]
    return FieldSetup(train, targets, other, other_targets, features, points.shape, mesh, sizes)


def held_out_renders(
    setup: FieldSetup, texture: np.ndarray, views: list[Scene] | None = None
) -> list[np.ndarray]:
    """The held-out views (or ``views``) rendered with ``texture`` on the teapot, without a
    tape; the material's own texture is put back afterwards."""
    material = setup.mesh.material
    kept = material.texture
    material.texture = md.tensor(texture)
    try:
        with md.no_grad():
            return [render(s).data for s in (setup.held_out if views is None else views)]
    finally:
        material.texture = kept


def held_out_psnr(setup: FieldSetup, texture: np.ndarray) -> float:
    """Mean PSNR (dB) of the held-out views rendered with ``texture``."""
    images = held_out_renders(setup, texture)
    return float(np.mean([psnr(i, t) for i, t in zip(images, setup.held_out_targets, strict=True)]))


def train_field_minidiff(
    setup: FieldSetup, weights: list[np.ndarray], iters: int = 300, lr: float = 0.01,
    frames: int = 0,
) -> dict:  # fmt: skip
    """Train the field in minidiff: the network's texture goes into the views' shared
    material, each iteration renders every view, the loss is the MSE over all of them.
    Returns the loss curve, seconds per iteration, final weights, held-out PSNR (at the
    start and the end) and, if ``frames`` > 0, held-out view 0 rendered at ``frames``
    evenly spaced iterations (for the GIF)."""
    params = [md.tensor(w, requires_grad=True) for w in weights]
    opt = md.optim.Adam(params, lr=lr)
    material = setup.mesh.material
    kept = material.texture
    features = md.tensor(setup.features)
    losses, seconds, snapshots = [], [], []
    keep = set(np.linspace(0, iters, frames).round().astype(int)) if frames else set()
    try:
        for it in range(iters + 1):
            start = time.perf_counter()
            opt.zero_grad()
            texture = md.reshape(mlp(params, features), setup.atlas_shape)
            material.texture = texture
            images = md.stack([render(s) for s in setup.views])
            loss = md.mean((images - setup.targets) ** 2)
            losses.append(loss.item())
            if it < iters:
                loss.backward()
                opt.step()
            seconds.append(time.perf_counter() - start)
            if it in keep:
                snapshots.append(texture.data.copy())
    finally:
        material.texture = kept
    final = [p.data.copy() for p in params]
    texture = field_texture(setup, final)
    first_view = setup.held_out[:1]
    frames_out = [held_out_renders(setup, snap, first_view)[0] for snap in snapshots]
    return {
        "loss": losses, "seconds": seconds, "weights": final, "texture": texture,
        "held_out_psnr_start": held_out_psnr(setup, field_texture(setup, weights)),
        "held_out_psnr": held_out_psnr(setup, texture), "frames": frames_out,
    }  # fmt: skip


def field_texture(setup: FieldSetup, weights: list[np.ndarray]) -> np.ndarray:
    """The atlas texture (H, W, 3) the field with ``weights`` gives, without a tape."""
    with md.no_grad():
        out = mlp([md.tensor(w) for w in weights], md.tensor(setup.features))
    return md.reshape(out, setup.atlas_shape).data
