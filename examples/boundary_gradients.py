"""Edge gradients against the truth: pixel centres, pixel pairs and the boundary integral.

Run:  python examples/boundary_gradients.py [--out out] [--quick]

The check (``render.inverse.reference``): a parameter is moved by s along a direction and
L(s) = sum(W * image(s)), W a fixed random weight image. The mean of a method's dL/ds over
the window [-h, h] (16 points, one reverse pass each at one sample per pixel) must equal
(L(h) - L(-h)) / 2h computed from jittered supersampled renders (box-filtered pixels), by
the fundamental theorem of calculus; h is half a pixel of image motion, which keeps the
supersampled difference precise (a tiny h measures sampling noise: at 64x64 the teapot's
vertical derivative moved between 70 and 76 with h on a 1,024-sample grid).

1. The paper teapot moved rigidly, at 64, 128 and 512 pixels, with and without shadows
   (1,024 samples per pixel; at 512 only the pixels around the teapot, the rest being
   background in every render).
2. Every kind of parameter at 128 pixels on the teapot standing on its ground beside a
   sphere that casts a shadow (256 samples per pixel): camera position, look-at and field
   of view, the sphere's centre and radius, the light, a vertex on the outline and one
   inside.

Writes ``boundary.md`` / ``boundary.json`` (relative l2 errors) and
``boundary_gradient_images.png`` (the window-mean d image / d y of each method next to the
supersampled one). ``--quick`` runs small sizes with few samples (for tests; not results).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.ndimage import binary_dilation
from script_support import command_line, write_results

from render.inverse.gradient_image import gradient_image
from render.inverse.reference import (
    moved_along,
    supersampled_image,
    window_difference,
    window_mean_gradient,
)
from render.renderer import render
from render.scene.scene import Material, Scene, Sphere
from render.scene.teapot import paper_scene

METHODS = {"pixel centres": False, "pixel pairs": True, "boundary integral": "boundary"}
POINTS = 16  # window points
#: The parameter table adds the boundary integral over an image of 16 samples per pixel:
#: the interior term (shading differentiated at fixed visibility) is then estimated from 16
#: points of each pixel instead of its centre, which matters where the parameter moves a
#: few small faces (a single vertex's fan of six at 128x128).
PARAMETER_METHODS = {**METHODS, "boundary integral, 16 spp": ("boundary", 16)}
QUICK = {"--quick": {"action": "store_true", "help": "small sizes, few samples (not results)"}}


def _pixel_size(scene) -> float:
    """World size of one pixel at the look-at point."""
    camera = scene.camera
    distance = np.linalg.norm(camera.look_at.data - camera.position.data)
    return 2.0 * distance * np.tan(np.radians(float(camera.fov.data)) / 2.0) / camera.width


def window_errors(
    build, tensor_of, directions, weights, h, spp, shadows=True, pixels=None, points=POINTS,
    methods=METHODS,
):  # fmt: skip
    """Per method, the relative l2 error over ``directions`` of the window mean against
    the supersampled window difference; and the truth. ``methods``: name -> antialias, or
    (antialias, samples per pixel)."""
    truth, ours = [], {name: [] for name in methods}
    for direction in directions:
        make = moved_along(build, tensor_of, direction)
        truth.append(window_difference(make, weights, h, spp, shadows=shadows, pixels=pixels))
        for name, method in methods.items():
            antialias, samples = method if isinstance(method, tuple) else (method, 1)
            mean = window_mean_gradient(make, weights, h, antialias, points, samples, shadows)
            ours[name].append(mean)
    truth = np.array(truth)
    row = {"truth": truth.tolist()}
    for name, values in ours.items():
        row[name] = float(np.linalg.norm(np.array(values) - truth) / np.linalg.norm(truth))
    return row


def teapot_translation(size: int, shadows: bool, spp: int, points: int = POINTS) -> dict:
    """Section 1: the teapot moved along x, y and z."""
    weights = np.random.default_rng(0).uniform(0.0, 1.0, (size, size, 3))
    scene = paper_scene(width=size, height=size)
    _, info = render(scene, return_info=True)
    seen = binary_dilation((info.prim_id >= 0).any(axis=2), iterations=3)  # h: half a pixel
    vertices = scene.meshes[0].vertices
    directions = [np.broadcast_to(e, vertices.shape).copy() for e in np.eye(3)]
    row = window_errors(
        lambda: paper_scene(width=size, height=size), lambda s: s.meshes[0].vertices,
        directions, weights, 0.5 * _pixel_size(scene), spp, shadows, np.flatnonzero(seen),
        points,
    )  # fmt: skip
    return {"size": size, "shadows": shadows, **row}


def _teapot_and_sphere(size: int):
    """The teapot on its ground with a sphere beside it casting a shadow on both."""
    scene = paper_scene(width=size, height=size, ground=True)  # the ground at y = -0.5
    sphere = Sphere((1.3, -0.05, 1.5), 0.45, Material((0.3, 0.5, 0.8)))
    return Scene(scene.objects + [sphere], scene.lights, scene.camera, scene.background)


def _vertices(scene) -> tuple[int, int]:
    """Two teapot vertices used by a single vertex id (not on a patch seam), each with
    every face around it seen at some pixel centre: one on the outline (teapot and
    something else both in the 3x3 pixels around its image), one inside (the teapot alone
    in the 7x7 pixels around it, the nearest such to the image centre)."""
    mesh = scene.meshes[0]
    v = mesh.vertices.data
    _, inverse, counts = np.unique(v.round(9), axis=0, return_inverse=True, return_counts=True)
    _, info = render(scene, return_info=True)
    prim = info.prim_id[..., 0]
    faces = mesh.faces
    seen = np.zeros(len(faces), bool)
    seen[np.unique(prim[(prim >= 0) & (prim < len(faces))])] = True
    all_seen = np.ones(len(v), bool)
    np.logical_and.at(all_seen, faces.ravel(), np.repeat(seen, 3))
    used = np.zeros(len(v), bool)
    used[faces.ravel()] = True
    candidates = np.flatnonzero(used & all_seen & (counts[inverse.ravel()] == 1))
    from render.scene.camera import plain_frame, project

    px, _ = project(v[candidates], plain_frame(scene.camera), *prim.shape[::-1])
    col, row = px[:, 0].astype(int), px[:, 1].astype(int)
    teapot = np.pad((prim >= 0) & (prim < len(faces)), 3)

    def teapot_share(r):
        return np.array([teapot[y + 3 - r : y + 4 + r, x + 3 - r : x + 4 + r].mean()
                         for y, x in zip(row, col, strict=True)])  # fmt: skip

    near, around = teapot_share(1), teapot_share(3)
    centre = np.hypot(col - prim.shape[1] / 2, row - prim.shape[0] / 2)
    outline = candidates[np.argmin(np.where((near > 0.3) & (near < 0.7), centre, np.inf))]
    inside = candidates[np.argmin(np.where(around == 1.0, centre, np.inf))]
    return int(outline), int(inside)


def parameter_types(size: int, spp: int, only=None, points: int = POINTS) -> list[dict]:
    """Section 2: every kind of parameter on the teapot-and-sphere scene."""
    weights = np.random.default_rng(1).uniform(0.0, 1.0, (size, size, 3))
    scene = _teapot_and_sphere(size)
    pixel = _pixel_size(scene)
    wanted = only is None or any(name.startswith("vertex") for name in only)
    outline, inside = _vertices(scene) if wanted else (0, 0)
    axes = list(np.eye(3))

    def vertex(index):
        return [np.where(np.arange(len(scene.meshes[0].vertices.data))[:, None] == index, e, 0.0)
                for e in axes]  # fmt: skip

    cases = {
        "camera position": (lambda s: s.camera.position, axes, pixel),
        "camera look-at": (lambda s: s.camera.look_at, axes, pixel),
        "field of view": (lambda s: s.camera.fov, [np.array(1.0)], 0.5 / size * 39.6),
        "sphere centre": (lambda s: s.objects[-1].center, axes, 0.5 * pixel),
        "sphere radius": (lambda s: s.objects[-1].radius, [np.array(1.0)], 0.5 * pixel),
        "light position": (lambda s: s.lights[0].position, axes, 2.0 * pixel),
        "vertex on the outline": (lambda s: s.meshes[0].vertices, vertex(outline), 0.5 * pixel),
        "vertex inside": (lambda s: s.meshes[0].vertices, vertex(inside), 0.5 * pixel),
    }
    rows = []
    for name, (tensor_of, directions, h) in cases.items():
        if only is not None and name not in only:
            continue
        row = window_errors(
            lambda: _teapot_and_sphere(size), tensor_of, directions, weights, h, spp,
            points=points, methods=PARAMETER_METHODS,
        )  # fmt: skip
        rows.append({"parameter": name, "size": size, **row})
    return rows


def figure(path: Path, size: int, spp: int) -> None:
    """The window-mean d image / d y (red) of each method next to the supersampled one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene = paper_scene(width=size, height=size)
    h = 0.5 * _pixel_size(scene)
    direction = np.zeros(scene.meshes[0].vertices.shape)
    direction[:, 1] = 1.0

    make = moved_along(
        lambda: paper_scene(width=size, height=size), lambda s: s.meshes[0].vertices, direction
    )
    truth = (supersampled_image(make(h)[0], spp) - supersampled_image(make(-h)[0], spp)) / (2 * h)
    panels = {f"truth ({spp:,} jittered spp, across the window)": truth[..., 0]}
    for name, antialias in METHODS.items():
        mean = 0.0
        for k in range(POINTS):
            moved, vertices, _ = make(-h + (k + 0.5) * 2 * h / POINTS)
            grad = gradient_image(moved, vertices, direction, antialias=antialias)
            mean = mean + grad[..., 0] / POINTS
        panels[name] = mean
    crop = (slice(size // 8, size * 7 // 8), slice(size // 8, size * 15 // 16))
    scale = np.abs(truth[..., 0][crop]).max()
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.6))
    for ax, (name, values) in zip(axes, panels.items(), strict=True):
        ax.imshow(values[crop], cmap="RdBu", vmin=-scale, vmax=scale)
        ax.set_title(name, fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"paper teapot moved up: d red / d y, {size}x{size}, mean over the window")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _table(keys: list[str], methods, rows: list[dict], label) -> list[str]:
    """Markdown lines: columns ``keys`` (each row's ``label(row)``) then one error per
    method."""
    lines = ["| " + " | ".join([*keys, *methods]) + " |", "|" + "---|" * (len(keys) + len(methods))]
    for row in rows:
        lines.append("| " + " | ".join([*label(row), *(f"{row[m]:.3f}" for m in methods)]) + " |")
    return lines


def main() -> None:
    args = command_line(__doc__, None, extra=QUICK, default_size=None, iterative=False)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.quick:  # every code path once, at a toy size
        spp, spp_params, size_params = 16, 16, 24
        rows = [teapot_translation(24, True, spp, points=2)]
        params = parameter_types(24, 16, only=("field of view", "sphere radius"), points=2)
    else:
        spp, spp_params, size_params = 1024, 256, 128
        rows = [teapot_translation(size, shadows, spp) for size in (64, 128, 512)
                for shadows in (True, False)]  # fmt: skip
        params = parameter_types(size_params, spp_params)
    lines = [
        "The window check (`examples/boundary_gradients.py`, `render.inverse.reference`): "
        "relative l2 error of each method's gradient of L = sum(W * image), averaged over "
        "a window of half a pixel of motion, against the supersampled difference across "
        f"the window ({spp:,} jittered samples per pixel). One sample per pixel for every "
        "method.",
        "",
        "Rigid translation of the paper teapot:",
        "",
        *_table(
            ["size", "shadows"],
            METHODS,
            rows,
            lambda r: [str(r["size"]), "yes" if r["shadows"] else "no"],
        ),  # fmt: skip
    ]
    lines += [
        "",
        "For context, Mitsuba 3.9 `direct_projective` on a translation check of this "
        "teapot at 128x128 (issue 23, against a 4,096-sample central difference): 1.6.",
        "",
        f"Every kind of parameter, {size_params}x{size_params}, the teapot on its ground "
        f"beside a sphere casting a shadow ({spp_params} samples per pixel in the truth):",
        "",
        *_table(["parameter"], PARAMETER_METHODS, params, lambda r: [r["parameter"]]),
    ]
    lines += ["", "![gradient images](boundary_gradient_images.png)"]
    if not args.quick:
        figure(out / "boundary_gradient_images.png", 128, spp)
    result = {"teapot translation": rows, "parameters": params}
    write_results(out, "boundary", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
