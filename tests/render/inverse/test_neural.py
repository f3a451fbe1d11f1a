"""Networks trained through the renderer (``render.inverse.networks``, and
``examples/torch_networks.py`` in PyTorch): the teapot's atlas,
the field trained in minidiff and in PyTorch giving the same losses, the light network,
and the two example scripts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import minidiff as md
from render.inverse.networks import (
    field_setup,
    fourier_features,
    init_mlp,
    mlp,
    pattern,
    train_field_minidiff,
)
from render.scene.teapot import ATLAS_TILES, teapot_atlas, teapot_geometry
from render.shade.lighting import sample_texture
from tests.render.edges.test_edge_examples import run_quick

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"


def test_atlas_blocks_hold_their_patch_and_points_lie_on_it():
    tile, nu, nv = 6, 4, 6
    uvs, points = teapot_atlas(tile, nu, nv)
    vertices, _ = teapot_geometry(nu, nv)
    rows, columns = ATLAS_TILES
    assert points.shape == (rows * tile, columns * tile, 3)
    # A texture whose every texel holds its block's patch number: bilinear lookups at the
    # vertices' UVs must return exactly the vertex's own patch (no bleeding between blocks).
    block = np.arange(rows * columns).reshape(rows, columns).repeat(tile, 0).repeat(tile, 1)
    texture = md.tensor(np.repeat(block[..., None], 3, axis=2).astype(np.float64))
    patch = np.arange(len(vertices)) // ((nu + 1) * (nv + 1))
    looked_up = sample_texture(texture, md.tensor(uvs)).data[:, 0]
    np.testing.assert_allclose(looked_up, patch, atol=1e-9)
    # The block's corner texels are the patch's corner vertices, exactly on the surface.
    grid = vertices.reshape(32, nu + 1, nv + 1, 3)
    for p in (0, 9, 31):
        ty, tx = divmod(p, columns)
        corners = points[ty * tile, tx * tile], points[(ty + 1) * tile - 1, (tx + 1) * tile - 1]
        np.testing.assert_allclose(corners[0], grid[p, 0, 0], atol=1e-12)
        np.testing.assert_allclose(corners[1], grid[p, -1, -1], atol=1e-12)
    with pytest.raises(ValueError, match="tile must be an int >= 2"):
        teapot_atlas(1)


def test_mlp_is_the_same_function_in_minidiff_and_torch():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    features = fourier_features(rng.normal(size=(20, 3)), rng.normal(size=(3, 4)))
    weights = init_mlp([8, 16, 3], seed=1)
    ours = mlp([md.tensor(w) for w in weights], md.tensor(features)).data
    theirs = mlp([torch.from_numpy(w) for w in weights], torch.from_numpy(features), ops=torch)
    np.testing.assert_allclose(ours, theirs.numpy(), rtol=1e-13, atol=0)
    assert np.all((ours > 0) & (ours < 1))
    colours = pattern(rng.normal(size=(50, 3)))
    assert colours.shape == (50, 3) and colours.min() >= 0.15 and colours.max() <= 0.85 + 1e-12


def test_field_training_gives_the_same_losses_in_minidiff_and_torch(load_script):
    pytest.importorskip("torch")
    train_field_torch = load_script("examples/torch_networks.py").train_field_torch

    setup = field_setup(views=2, held_out=1, size=12, tile=4, frequencies=4, hidden=(8,))
    weights = init_mlp(setup.sizes, seed=3)
    mine = train_field_minidiff(setup, weights, iters=4, lr=0.01, frames=2)
    theirs = train_field_torch(setup, weights, iters=4, lr=0.01)
    a, b = np.array(mine["loss"]), np.array(theirs["loss"])
    assert a[-1] < a[0]  # it learns
    np.testing.assert_allclose(a, b, rtol=1e-12)
    for w, v in zip(mine["weights"], theirs["weights"], strict=True):
        np.testing.assert_allclose(w, v, rtol=1e-9, atol=1e-12)
    assert len(mine["frames"]) == 2 and np.isfinite(mine["held_out_psnr"])
    # the scene's own texture is left as it was
    np.testing.assert_array_equal(setup.mesh.material.texture.data, pattern(teapot_atlas(4)[1]))


def test_neural_field_example_quick(tmp_path, monkeypatch):
    pytest.importorskip("torch")
    result = run_quick(EXAMPLES / "neural_field.py", tmp_path, monkeypatch,
                       "neural_field/neural_field.json")  # fmt: skip
    assert result["loss_max_relative_difference"] < 1e-10
    layers = result["layers"]
    assert result["parameters"] == sum(a * b + b for a, b in zip(layers, layers[1:], strict=False))
    for name in ("neural_field.png", "loss.png", "training.gif", "neural_field.md"):
        assert (tmp_path / "neural_field" / name).stat().st_size > 0


def test_light_network_example_quick(tmp_path, monkeypatch):
    pytest.importorskip("torch")
    result = run_quick(EXAMPLES / "light_network.py", tmp_path, monkeypatch,
                       "light_network/light_network.json")  # fmt: skip
    assert result["training_renders"] == 6 + 2 * 8 * 10  # held-out targets + 2 per sample
    for key in ("error_network", "error_refined_from_network", "error_refined_from_centre"):
        assert np.isfinite(result[key]["median"])
    for name in ("light_network.png", "loss.png", "light_network.md"):
        assert (tmp_path / "light_network" / name).stat().st_size > 0
