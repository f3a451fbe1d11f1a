"""Shared helpers for the renderer tests (``test_render_*.py``).

* ``pinhole_rays``: camera rays computed independently of ``render.scene.camera``, straight from
  the documented camera model, for closed-form checks.
* ``random_scene``: a small random scene (ground quad, a floating pyramid, a sphere, one
  light) whose parameters are all stored as Tensors in the scene.
* ``masked_gradient_check``: tape gradient of a render-level loss vs. central finite
  differences, restricted to the pixels whose visibility the perturbations leave alone (see
  ``tests/render/test_gradients.py`` for why).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

import minidiff as md
import render

# --------------------------------------------------------------------------------------
# Independent camera model
# --------------------------------------------------------------------------------------


def pinhole_rays(position, look_at, up, fov_degrees, width, height, spp_offset=(0.5, 0.5)):
    """(H, W, 3) unit directions of the rays through the pixel centres, row 0 at the top.

    Written from the documentation, not from ``render.scene.camera``: ``fov`` is the horizontal
    field of view, pixels are square, the image plane at distance 1 spans
    [-tan(fov/2), tan(fov/2)] horizontally.
    """
    eye = np.asarray(position, np.float64)
    forward = np.asarray(look_at, np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, np.float64))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    half_w = math.tan(math.radians(fov_degrees) / 2.0)
    pixel = 2.0 * half_w / width  # side of a square pixel on the image plane
    cols = (np.arange(width) + spp_offset[0]) * pixel - half_w
    rows = half_w * height / width - (np.arange(height) + spp_offset[1]) * pixel
    d = (
        forward[None, None, :]
        + cols[None, :, None] * right[None, None, :]
        + rows[:, None, None] * true_up[None, None, :]
    )
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# --------------------------------------------------------------------------------------
# Small random scenes
# --------------------------------------------------------------------------------------

QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])
PYRAMID_FACES = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])  # apex 0, open base


def ground_quad(size=4.0, y=0.0, material=None, uv_repeat=1.0):
    """A square y = const, normal +y, as two triangles with uvs."""
    s = size
    vertices = [(-s, y, s), (s, y, s), (s, y, -s), (-s, y, -s)]
    uvs = np.array([(0, 0), (1, 0), (1, 1), (0, 1)], np.float64) * uv_repeat
    material = material or render.Material(albedo=(0.6, 0.6, 0.6))
    return render.Mesh(vertices, QUAD_FACES, material, uvs=uvs)


def random_material(rng, specular=True, ambient=True, texture=None):
    return render.Material(
        albedo=rng.uniform(0.2, 0.9, 3),
        specular=rng.uniform(0.1, 0.5) if specular else 0.0,
        shininess=rng.uniform(4.0, 40.0),
        ambient=rng.uniform(0.01, 0.1) if ambient else 0.0,
        texture=texture,
    )


def random_pyramid(rng, material, smooth=False, normals=None):
    """A floating four-sided pyramid (5 shared vertices, 4 faces, open base), left of x = 0
    (``random_scene`` puts its sphere to the right)."""
    centre = np.array([rng.uniform(-1.2, -0.4), rng.uniform(0.9, 1.4), rng.uniform(-0.8, 0.8)])
    angles = np.arange(4) * np.pi / 2 + rng.uniform(-0.3, 0.3, 4) + rng.uniform(0, np.pi)
    base = np.stack([np.cos(angles), np.full(4, -0.3), np.sin(angles)], axis=1) * rng.uniform(
        0.55, 0.8
    )
    apex = np.array([rng.uniform(-0.1, 0.1), rng.uniform(0.4, 0.7), rng.uniform(-0.1, 0.1)])
    vertices = centre + np.concatenate([apex[None], base])
    return render.Mesh(vertices, PYRAMID_FACES, material, normals=normals, smooth=smooth)


def random_light(rng, kind="point"):
    colour = rng.uniform(0.5, 1.0, 3)
    if kind == "point":
        position = (rng.uniform(-2, 2), rng.uniform(3, 5), rng.uniform(-1, 3))
        return render.PointLight(position, rng.uniform(20, 60), colour)
    direction = (rng.uniform(-0.6, 0.6), -1.0, rng.uniform(-0.6, 0.6))
    return render.DirectionalLight(direction, rng.uniform(1, 3), colour)


def random_camera(rng, width=28, height=24):
    position = (rng.uniform(-1, 1), rng.uniform(1.8, 3.0), rng.uniform(4.5, 6.0))
    look_at = (rng.uniform(-0.3, 0.3), rng.uniform(0.2, 0.6), rng.uniform(-0.3, 0.3))
    return render.Camera(position, look_at, fov=rng.uniform(38, 50), width=width, height=height)


def random_scene(
    seed,
    lights=("point",),
    sphere=True,
    pyramid=True,
    smooth=False,
    texture=False,
    width=32,
    height=28,
    background=(0.05, 0.1, 0.2),
):
    """Ground quad + floating pyramid + sphere + lights, all random but well-posed.

    ``lights`` lists the light kinds ("point", "directional"). Every material has a
    specular lobe and an ambient term, so that every shading path is exercised.

    Everything sits in front of a camera about 5 units away, the pyramid and the sphere cast
    shadows on the ground, the far edge of the ground is visible (background pixels exist).
    """
    rng = np.random.default_rng(seed)
    ground_texture = rng.uniform(0.1, 0.9, (4, 5, 3)) if texture else None
    objects = [
        ground_quad(
            material=random_material(rng, texture=ground_texture), uv_repeat=1.7 if texture else 1
        )
    ]
    if pyramid:
        objects.append(random_pyramid(rng, random_material(rng), smooth=smooth))
    if sphere:
        radius = rng.uniform(0.3, 0.5)
        centre = (rng.uniform(0.5, 1.3), radius + rng.uniform(0.05, 0.4), rng.uniform(-1, 1))
        objects.append(render.Sphere(centre, radius, random_material(rng)))
    return render.Scene(
        objects,
        [random_light(rng, kind) for kind in lights],
        random_camera(rng, width, height),
        background,
    )


# --------------------------------------------------------------------------------------
# Gradient check with visibility masking
# --------------------------------------------------------------------------------------


@dataclass
class GradientCheck:
    rel_error: float  # Eq. 3: ||g_ad - g_fd|| / (||g_fd|| + 1e-8)
    g_ad: np.ndarray  # all parameters, flattened and concatenated
    g_fd: np.ndarray
    kept: int  # pixels compared (same visibility in every perturbed render)
    pixels: int
    directions: np.ndarray  # (k, n): g_ad and g_fd are the derivatives along these rows


def _same_visibility(info, reference) -> np.ndarray:
    """(H, W) bool: every sample of the pixel hits the same primitive with the same shadows
    and looks up the same texture cell (bilinear filtering has a kink between cells)."""
    same = (info.prim_id == reference.prim_id).all(axis=-1)
    same &= (info.texel == reference.texel).all(axis=-1)
    if reference.lit.size:
        same &= (info.lit == reference.lit).all(axis=(0, -1))
    assert len(info.bounces) == len(reference.bounces)
    # Mirror rays: where both renders traced one (-2: none, e.g. a reflectance moved off
    # 0, which changes the image smoothly), the same primitive and the same lights.
    for b, (now, ref) in enumerate(zip(info.bounces, reference.bounces, strict=True)):
        both = (now != -2) & (ref != -2)
        lit_now, lit_ref = info.bounce_lit[b], reference.bounce_lit[b]
        agree = (now == ref) & (lit_now == lit_ref).all(axis=0)
        same &= (agree | ~both).all(axis=-1)
    spp = reference.prim_id.shape[-1]
    if reference.pairs is not None:
        same &= _same_edge_pairs(_pair_rows(info.pairs), _pair_rows(reference.pairs), same, spp)
    if reference.shadow_pairs is not None:
        now, ref = _shadow_rows(info.shadow_pairs), _shadow_rows(reference.shadow_pairs)
        same &= _same_edge_pairs(now, ref, same, spp)
    return same


def _pair_rows(pairs) -> np.ndarray:
    columns = [pairs.near, pairs.far, pairs.prim, pairs.edge, pairs.other, pairs.horizontal]
    return np.stack(columns, axis=1)


def _shadow_rows(pairs) -> np.ndarray:
    columns = [pairs.lit, pairs.dark, pairs.light, pairs.occluder, pairs.edge, pairs.horizontal]
    return np.stack(columns, axis=1)


def _same_edge_pairs(now, ref, same, spp) -> np.ndarray:
    """(H, W) bool: False at both pixels of every antialiasing pair (rows of ray ids and
    choices, the two rays first) present in only one of the two renders, and of every
    pair whose other pixel changed its decisions (a blended pixel shows its neighbour's
    colour too)."""
    ok = np.ones(same.size, dtype=bool)
    for a, b in ((ref, now), (now, ref)):
        in_b = (a[:, None, :] == b[None, :, :]).all(-1).any(1) if len(b) else np.zeros(len(a), bool)
        ok[a[~in_b, 0] // spp] = False
        ok[a[~in_b, 1] // spp] = False
    flat_same = same.reshape(-1) & ok
    near, far = ref[:, 0] // spp, ref[:, 1] // spp
    touched = ~flat_same[near] | ~flat_same[far]
    ok[near[touched]] = False
    ok[far[touched]] = False
    return ok.reshape(same.shape)


def masked_gradient_check(
    scene, params, h_rel=1e-6, order=4, seed=1234, mask=True, directions=None, **render_kwargs
):
    """Compare the tape gradient of loss = sum(image * W) with central differences.

    ``params`` are Tensors stored in ``scene`` (perturbed in place through ``.data``). The
    weights W are a fixed random image, zeroed at every pixel whose discrete decisions
    (``prim_id``, ``lit`` and ``texel`` of every sample) differ from the unperturbed render
    in any perturbed render; the tape gradient is then computed with that same masked W.
    ``mask=False`` compares every pixel (only to demonstrate why the mask is needed).

    ``order=2``: the central difference D(h) = (f(x + h) - f(x - h)) / 2h, error O(h^2).
    ``order=4`` (default): Richardson's (4 D(h) - D(2h)) / 3, error O(h^4). A pixel whose ray
    grazes a sphere depends on the square root of a nearly zero discriminant: its higher
    derivatives are huge, and the O(h^2) term alone reached 5e-5 relative on one random
    scene in 40 (h = 1e-6), while the tape gradient is exact there.

    ``directions``: None differentiates along each scalar of the parameters in turn (g_ad
    and g_fd are the gradient, all parameters flattened and concatenated); k > 0 along k
    random directions u_j instead (seeded by ``seed``; g_ad and g_fd are the k derivatives
    g . u_j). With u_j = D v_j, v_j ~ N(0, I / k) and D the elements' step scales
    max(1, |x|), E |(g_ad - g_fd) . u|^2 over the draws is |D (g_ad - g_fd)|^2 / k: k
    directions see the same relative error as all n scalars, in expectation, for 4k renders
    instead of 4n (24 vertex coordinates: 96 renders, 16 with k = 4).
    """
    kwargs = dict(render_kwargs, return_info=True)
    with md.no_grad():
        image, reference = render.render(scene, **kwargs)
    height, width = image.shape[:2]
    weights = np.random.default_rng(seed).standard_normal(image.shape)
    multiples = {2: (1,), 4: (1, 2)}[order]
    flats = [p.data.reshape(-1) for p in params]
    assert all(np.shares_memory(f, p.data) for f, p in zip(flats, params, strict=True)), (
        "parameter data must be contiguous"
    )
    x = np.concatenate([f.copy() for f in flats])
    scale = h_rel * np.maximum(1.0, np.abs(x))  # each scalar's step h
    if directions is None:
        steps = np.diag(scale)  # one scalar at a time
    else:
        draws = np.random.default_rng(seed + 1).standard_normal((directions, x.size))
        steps = draws / np.sqrt(directions) * scale

    ends = np.cumsum([f.size for f in flats])[:-1]

    def put(values):
        for f, part in zip(flats, np.split(values, ends), strict=True):
            f[:] = part

    same = np.ones((height, width), dtype=bool)
    quotients, taken = [], []  # per direction and step multiple: (f(x+m s) - f(x-m s)) / m
    try:
        for step in steps:
            per_multiple = []
            for m in multiples:
                images, stored = [], []
                for value in (x + m * step, x - m * step):
                    put(value)
                    stored.append(np.concatenate(flats))  # as stored: rounded
                    with md.no_grad():
                        img, info = render.render(scene, **kwargs)
                    if mask:
                        same &= _same_visibility(info, reference)
                    images.append(img.data)
                per_multiple.append((images[0] - images[1]) / m)
                if m == 1:  # the step as stored (rounded), whose derivative is compared
                    taken.append((stored[0] - stored[1]) / 2.0)
            quotients.append(per_multiple)
    finally:
        put(x)

    masked = weights * same[:, :, None]
    fd = np.array([[np.sum(q * masked) for q in per_multiple] for per_multiple in quotients])
    lengths = np.array([np.abs(t).max() for t in taken])  # each step's length, to divide by
    fd = fd / (2.0 * lengths[:, None])
    g_fd = fd[:, 0] if order == 2 else (4.0 * fd[:, 0] - fd[:, 1]) / 3.0

    saved = [(p.requires_grad, p.grad) for p in params]
    for p in params:
        p.requires_grad, p.grad = True, None
    try:
        img = render.render(scene, **render_kwargs)
        if img.requires_grad:  # else nothing in view depends on the parameters
            (img * md.tensor(masked)).sum().backward()
        gradient = np.concatenate(
            [np.ravel(p.grad if p.grad is not None else np.zeros_like(p.data)) for p in params]
        )
    finally:
        for p, (requires_grad, grad) in zip(params, saved, strict=True):
            p.requires_grad, p.grad = requires_grad, grad
    along = np.array(taken) / lengths[:, None]  # (k, n): the directions compared
    g_ad = along @ gradient
    rel = float(np.linalg.norm(g_ad - g_fd) / (np.linalg.norm(g_fd) + 1e-8))
    return GradientCheck(rel, g_ad, g_fd, int(same.sum()), height * width, along)


def strict_load(text: str):
    """JSON parsed strictly: NaN, Infinity and -Infinity (which Python's json writes and
    reads, but the JSON standard does not have) are refused."""

    def refuse(token):
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def count_calls(monkeypatch, module, name: str) -> list:
    """Replace ``module.name`` (for the test's duration) by a spy that calls it and appends
    1 to the returned list at each call: which code a render took."""
    calls = []
    original = getattr(module, name)

    def spy(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, spy)
    return calls


# --------------------------------------------------------------------------------------
# Thread-count independence
# --------------------------------------------------------------------------------------


def run_on_two_threads(script: str) -> str:
    """Run the Python ``script`` in a new process with Numba allowed two threads (a
    pytest-xdist worker is limited to one) from the repository root; returns its stdout
    (stripped) and fails the test if it fails. Tests that use it are marked
    ``new_processes``."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {**os.environ, "NUMBA_NUM_THREADS": "2"}
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=300, cwd=root)  # fmt: skip
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


#: What ``same_bits_on_one_and_two_threads`` appends to a script that defines ``run()``.
_ONE_AND_TWO_THREADS = """
import numba as _numba
import numpy as _np
from minidiff import compiler as _compiler
_compiler.PARALLEL_WORK = 0  # compiled kernels split however small (only the speed differs)
_runs = []
for _n in (1, 2):
    _numba.set_num_threads(_n)
    assert _numba.get_num_threads() == _n
    _runs.append(list(run()))
assert len(_runs[0]) == len(_runs[1]) > 0
for _a, _b in zip(*_runs, strict=True):
    assert _np.array_equal(_a, _b), "differ"
print("same bits")
"""


def same_bits_on_one_and_two_threads(script: str) -> None:
    """Fail unless ``script`` (Python that defines ``run()``, returning a sequence of
    arrays) gives the same arrays bit for bit when ``run()`` is called on one and then on
    two Numba threads, in one new process (``run_on_two_threads``), with every compiled
    kernel split into jobs, however small its batch (``minidiff.compiler.PARALLEL_WORK``
    0 there)."""
    assert run_on_two_threads(script + _ONE_AND_TWO_THREADS) == "same bits"
