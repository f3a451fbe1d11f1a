"""Images and gradients are bit-identical to arrays saved from an earlier version.

A refactor of the renderer or of minidiff must not change a single bit of what a user
gets. ``tests/data/golden_render.npz`` was written by running this file as a script
(``python tests/test_render_golden.py --write``) at commit c1c911d, before the code was reorganised
(issue 8); the test recomputes the same renders and gradients and compares them exactly.
Regenerate it only for a change that is meant to alter the numbers, and say so in the
commit.

Bit-identical holds on one kind of processor: NumPy's BLAS and its vectorised float64
functions (tan, power, ...) pick their kernels by the CPU's instruction sets, and those
round differently in the last bit. The file therefore also keeps a fingerprint of such
calls on the machine that wrote it; where the fingerprint differs, the arrays must agree to
1e-12 of each one's largest value instead (a refactor that changes the math shows up far
above that; measured between the machine that wrote the first file and an AVX2 AMD EPYC:
at most 9.3e-14). The arrays were rewritten on that EPYC machine after checking that the
code of commit f67f0cb (which matched the first file bit for bit where it was written) and
the code being committed give the same arrays there, bit for bit.
"""

from __future__ import annotations

import hashlib
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
        # so it is left out here to keep the saved renders' meaning (tests/test_reflection.py);
        # Material.emission (issue 27) likewise, so that the gradients keep their numbering.
        named = scene.named_parameters().items()
        params = [t for key, t in named if not key.endswith((".reflectance", ".emission"))]
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


def machine_fingerprint() -> np.ndarray:
    """(32,) uint8: a hash of BLAS products and vectorised float64 functions on fixed data,
    the calls whose last bits depend on the processor (see the module docstring)."""
    rng = np.random.default_rng(1)
    x, m = rng.uniform(-2, 2, (4096, 3)), rng.uniform(-2, 2, (3, 3))
    results = [x @ m, x.T @ x, np.tan(x), np.power(np.abs(x), 7.3), np.exp(x), np.log1p(x**2)]
    results += [np.sin(x), np.cos(x), np.sqrt(np.abs(x)), x.sum(axis=0), np.arctan2(x, m[0])]
    digest = hashlib.sha256(b"".join(np.ascontiguousarray(r).tobytes() for r in results))
    return np.frombuffer(digest.digest(), dtype=np.uint8)


def test_images_and_gradients_are_bit_identical_to_the_saved_ones():
    saved = np.load(GOLDEN)
    now = golden_arrays()
    arrays = [key for key in saved.files if key != "fingerprint"]
    assert sorted(now) == sorted(arrays)
    same_machine = np.array_equal(saved["fingerprint"], machine_fingerprint())
    for key in arrays:
        assert now[key].dtype == saved[key].dtype, key
        if same_machine:
            assert np.array_equal(now[key], saved[key]), f"{key} changed"
        else:
            scale = np.abs(saved[key]).max(initial=0.0)
            np.testing.assert_allclose(
                now[key], saved[key], rtol=0, atol=1e-12 * scale, err_msg=key
            )


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_render_golden.py --write (overwrites the saved arrays)")
    np.savez_compressed(GOLDEN, fingerprint=machine_fingerprint(), **golden_arrays())
    print(f"wrote {GOLDEN}")
