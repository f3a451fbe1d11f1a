"""Gradient images of the paper scene: where in the picture each parameter acts.

Run:  python examples/gradient_images.py [--size 256] [--out out]

Writes into ``<out>/gradient_images/`` the rendered image (``render.png``) and, as
diverging-colour PNGs (red: the pixel brightens, blue: it darkens, white: unchanged; the
sum of R, G and B), the derivative of the image (``render.gradient_image``, forward mode,
``antialias=True``) with respect to

* ``light_x.png``: the light's x coordinate,
* ``light_intensity.png``: the light's radiant intensity,
* ``albedo_red.png``: the red component of the teapot's albedo,
* ``camera_x.png``: the camera's x coordinate (look-at point fixed),
* ``teapot_x.png``: every vertex of the teapot moved along +x together (a translation).

Each image is one forward-mode render. Default size 256 x 256 (a few seconds).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import minidiff as md
from render import gradient_image, render, save_image, write_gradient_png
from render.scene.teapot import paper_scene


def directions(scene) -> dict[str, tuple[str, np.ndarray]]:
    """file stem -> (parameter name, direction in that parameter's space)."""
    vertices = scene.meshes[0].vertices
    translation = np.zeros(vertices.shape)
    translation[:, 0] = 1.0  # every vertex along +x: the teapot slides sideways
    return {
        "light_x": ("lights[0].position", np.array([1.0, 0.0, 0.0])),
        "light_intensity": ("lights[0].intensity", np.array(1.0)),
        "albedo_red": ("objects[0].material.albedo", np.array([1.0, 0.0, 0.0])),
        "camera_x": ("camera.position", np.array([1.0, 0.0, 0.0])),
        "teapot_x": ("objects[0].vertices", translation),
    }


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=256, help="image side in pixels")
    parser.add_argument("--out", type=Path, default=Path("out"), help="output directory")
    args = parser.parse_args(argv)
    if args.size < 8:
        parser.error(f"--size must be at least 8, got {args.size}")
    out = args.out / "gradient_images"
    scene = paper_scene(args.size, args.size)
    with md.no_grad():
        save_image(render(scene, antialias=True), out / "render.png", srgb=True)
    scales = {}
    for stem, (name, direction) in directions(scene).items():
        start = time.perf_counter()
        image = gradient_image(scene, name, direction, antialias=True)
        seconds = time.perf_counter() - start
        channel = image.sum(axis=2)
        scale = float(np.percentile(np.abs(channel), 99.5)) or 1.0
        write_gradient_png(channel, out / f"{stem}.png", scale=scale, label=f"d image / d {stem}")
        scales[stem] = scale
        print(f"{stem:16s} {name:28s} scale {scale:.3g}  ({seconds * 1e3:.0f} ms)")
    print(f"wrote {out}")
    return scales


if __name__ == "__main__":
    main()
