"""Images and gradients are bit-identical to arrays saved from an earlier version.

A refactor of the renderer or of minidiff must not change a single bit of what a user
gets. ``tests/data/golden_render.npz`` was written by running this file as a script
(``python tests/test_render_golden.py --write``) at commit c1c911d, before the code was reorganised
(issue 8); the test recomputes the same renders and gradients and compares them exactly.
Regenerate it only for a change that is meant to alter the numbers, and say so in the
commit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from render_helpers import random_scene

import minidiff as md
import render

GOLDEN = Path(__file__).parent / "data" / "golden_render.npz"


def _scenes() -> dict[str, render.Scene]:
    return {
        "paper": render.paper_scene(width=48, height=40),
        "textured": random_scene(3, lights=("point", "directional"), texture=True, smooth=True),
        "spheres": random_scene(7, lights=("directional",), pyramid=False),
    }


def golden_arrays() -> dict[str, np.ndarray]:
    """Per scene: the image, and the gradient of sum(W * image) for every parameter."""
    out = {}
    for name, scene in _scenes().items():
        # Material.reflectance came later (issue 12): differentiating it traces mirror rays,
        # so it is left out here to keep the saved renders' meaning (tests/test_reflection.py).
        named = scene.named_parameters().items()
        params = [t for key, t in named if not key.endswith(".reflectance")]
        for p in params:
            p.requires_grad = True
        image = render.render(scene, reuse_visibility=False, antialias=False)
        weights = np.random.default_rng(0).standard_normal(image.shape)
        (image * md.tensor(weights)).sum().backward()
        out[f"{name}/image"] = image.data
        for i, p in enumerate(params):
            grad = p.grad if p.grad is not None else np.zeros_like(p.data)
            out[f"{name}/grad{i}"] = np.asarray(grad)
    return out


def test_images_and_gradients_are_bit_identical_to_the_saved_ones():
    saved = np.load(GOLDEN)
    now = golden_arrays()
    assert sorted(now) == sorted(saved.files)
    for key in saved.files:
        assert now[key].dtype == saved[key].dtype, key
        assert np.array_equal(now[key], saved[key]), f"{key} changed"


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_render_golden.py --write (overwrites the saved arrays)")
    np.savez_compressed(GOLDEN, **golden_arrays())
    print(f"wrote {GOLDEN}")
