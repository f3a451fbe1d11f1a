"""Shadow-edge antialiasing (``render.edges.shadows``): hard shadows whose boundaries move.

The set-up of the closed forms: a camera looking straight down at a ground plane y = 0
from below an occluder, so that the occluder is out of view and every pixel covers the
same ground area; the occluder is a huge quad at height h whose one edge x = x_o casts the
only shadow edge in view, the line x = x_s on the ground, vertical in the image.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import minidiff as md
import render
from minidiff.threads import using_threads
from tests.render_helpers import masked_gradient_check, random_scene

SIZE, FOV, CAMERA_HEIGHT = 40, 50.0, 0.8
ALBEDO = 0.6
FAR = 50.0


def ground_and_occluder(light, x_edge=0.5, height=1.0) -> render.Scene:
    ground = render.Mesh(
        np.array([(-FAR, 0, FAR), (FAR, 0, FAR), (FAR, 0, -FAR), (-FAR, 0, -FAR)], np.float64),
        [[0, 1, 2], [0, 2, 3]],
        render.Material((ALBEDO, ALBEDO, ALBEDO)),
    )
    y = height
    occluder = render.Mesh(  # covers x < x_edge at height y, facing down and up alike
        np.array([(-FAR, y, FAR), (x_edge, y, FAR), (x_edge, y, -FAR), (-FAR, y, -FAR)]),
        [[0, 1, 2], [0, 2, 3]],
        render.Material((0.3, 0.3, 0.3)),
    )
    camera = render.Camera(
        (0.5, CAMERA_HEIGHT, 0.0), (0.5, 0.0, 0.0), up=(0, 0, -1), fov=FOV,
        width=SIZE, height=SIZE,
    )  # fmt: skip
    return render.Scene([ground, occluder], [light], camera)


def pixel_width() -> float:
    return 2.0 * CAMERA_HEIGHT * math.tan(math.radians(FOV) / 2.0) / SIZE


def column_x(col: float) -> float:
    """World x of a pixel column's centre (col may be fractional); image x = world x."""
    return 0.5 + (col + 0.5 - SIZE / 2) * pixel_width()


def test_directional_shadow_edge_coverage_and_derivatives():
    """Directional light travelling along (wx, -1, 0): the ground is lit at the constant
    radiance c = albedo / pi * E * cos, the edge of the shadow lies at x_s = x_o + wx h."""
    wx, irradiance, x_o, h = 0.3, 2.0, 0.37, 1.0
    light = render.DirectionalLight((wx, -1.0, 0.0), irradiance)
    scene = ground_and_occluder(light, x_o, h)
    occluder = scene.objects[1].vertices
    occluder.requires_grad = True
    light.direction.requires_grad = True
    image, info = render.render(scene, antialias=True, return_info=True)
    (image.sum()).backward()

    c = ALBEDO / math.pi * irradiance / math.sqrt(1.0 + wx * wx)  # per channel
    x_s = x_o + wx * h
    # The pixel that the edge crosses is lit on its right-hand part only.
    col = (x_s - column_x(0)) / pixel_width()  # fractional column of the edge
    boundary = int(math.floor(col + 0.5))
    lit_fraction = boundary + 0.5 - col
    np.testing.assert_allclose(image.data[:, boundary, 0], c * lit_fraction, rtol=1e-9)
    assert len(info.shadow_pairs.lit) == SIZE  # one pair per row

    # Moving the occluder's edge (two of its vertices) by dx moves the shadow edge by dx.
    rows_crossed = SIZE
    edge_term = -3 * c * rows_crossed / pixel_width()
    moved = occluder.grad[[1, 2], 0].sum()  # the vertices on the edge x = x_o
    assert moved == pytest.approx(edge_term, rel=1e-9)
    # The light's direction: the edge moves by h per unit wx, and every lit pixel's
    # radiance changes with cos = 1 / sqrt(1 + wx^2).
    lit_pixels = (info.lit[0, :, :, 0]).sum()
    interior = 3 * lit_pixels * c * (-wx / (1.0 + wx * wx))
    boundary_share = 3 * SIZE * (lit_fraction - 1.0) * c * (-wx / (1.0 + wx * wx))
    expected = edge_term * h + interior + boundary_share
    assert light.direction.grad[0] == pytest.approx(expected, rel=1e-6)


def point_light_edge_term(light_pos, x_o, h, dxs_dtheta) -> float:
    """-(sum over rows of the ground radiance at the shadow edge) * dx_s/dtheta / pixel
    width, summed over the channels: the edge term of d(sum of image)/dtheta."""
    lx, ly, intensity = light_pos[0], light_pos[1], 50.0
    t = ly / (ly - h)
    x_s = lx + t * (x_o - lx)
    rows = np.arange(SIZE)
    z = (rows + 0.5 - SIZE / 2) * pixel_width()  # image rows run along world z
    offset = np.stack([np.full(SIZE, lx - x_s), np.full(SIZE, ly), -z], axis=1)
    r2 = np.sum(offset**2, axis=1)
    radiance = ALBEDO / math.pi * intensity * (ly / np.sqrt(r2)) / r2
    return float(-3 * radiance.sum() * dxs_dtheta / pixel_width())


def test_point_light_shadow_edge_derivatives():
    """d(sum of image)/dtheta = the edge term (the radiance along the shadow edge times its
    speed, in closed form) + the lit pixels' own change, weighted by the lit share of each
    pixel (the renderer's pixel-centre gradient of the unshadowed ground, weighted so).
    The edge term uses the radiance at the edge; the renderer blends the colours of the
    pixel centres next to it, so they agree to about the radiance's change over a pixel."""
    light_pos, x_o, h = np.array([0.2, 2.0, 0.0]), 0.4, 1.0
    light = render.PointLight(light_pos, 50.0)
    scene = ground_and_occluder(light, x_o, h)
    occluder = scene.objects[1].vertices
    occluder.requires_grad = True
    light.position.requires_grad = True
    render.render(scene, antialias=True).sum().backward()
    aa_occluder, aa_light = occluder.grad.copy(), light.position.grad.copy()

    lx, ly = light_pos[0], light_pos[1]
    t = ly / (ly - h)
    x_s = lx + t * (x_o - lx)
    # The lit share of each pixel: columns right of the edge 1, left 0, the edge's own
    # column its right-hand part.
    col = (x_s - column_x(0)) / pixel_width()
    share = np.clip(np.arange(SIZE) + 0.5 - col, 0.0, 1.0)
    unshadowed = ground_and_occluder(render.PointLight(light_pos, 50.0), x_o, h)
    unshadowed.objects.pop(1)
    position = unshadowed.lights[0].position
    position.requires_grad = True
    weights = np.broadcast_to(share[None, :, None], (SIZE, SIZE, 3))
    (render.render(unshadowed) * md.tensor(np.array(weights))).sum().backward()
    interior = position.grad

    # x_s = lx + t (x_o - lx): d/dx_o = t, d/dlx = 1 - t, d/dly = (x_o - lx)(-h)/(ly - h)^2.
    assert aa_occluder[[1, 2], 0].sum() == pytest.approx(
        point_light_edge_term(light_pos, x_o, h, t), rel=5e-3
    )
    assert aa_light[0] == pytest.approx(
        interior[0] + point_light_edge_term(light_pos, x_o, h, 1.0 - t), rel=5e-3
    )
    dxs_dly = (x_o - lx) * (-h) / (ly - h) ** 2
    assert aa_light[1] == pytest.approx(
        interior[1] + point_light_edge_term(light_pos, x_o, h, dxs_dly), rel=5e-3
    )


# --------------------------------------------------------------------------------------
# Continuity and what the gradients estimate
# --------------------------------------------------------------------------------------

SHADOW_PARAMETERS = {
    "point light": (("point",), lambda s: [s.lights[0].position]),
    "directional light": (("directional",), lambda s: [s.lights[0].direction]),
    "occluders": (("point",), lambda s: [s.objects[1].vertices, s.objects[2].center]),
    "receiver and camera": (("point",), lambda s: [s.objects[0].vertices, s.camera.position]),
}


@pytest.mark.parametrize("name", list(SHADOW_PARAMETERS))
def test_shadow_edge_gradient_matches_finite_differences_of_the_antialiased_image(name):
    lights, params = SHADOW_PARAMETERS[name]
    scene = random_scene(4, lights=lights)
    check = masked_gradient_check(
        scene, params(scene), h_rel=1e-6, reuse_visibility=False, antialias=True
    )
    _, info = render.render(scene, antialias=True, return_info=True)
    assert len(info.shadow_pairs.lit) > 10  # the scene has shadow edges in view
    assert check.kept >= 0.9 * check.pixels
    assert check.rel_error < 1e-5, (check.g_ad, check.g_fd)


def supersampled_check(scene, tensor, h, spp=256):
    """Relative l2 error of the antialiased AD gradient of sum(W image) w.r.t. ``tensor``
    against central differences of a supersampled render, and the same for pixel
    centres. Also returns both gradients."""
    weights = np.random.default_rng(0).standard_normal((scene.camera.height, scene.camera.width, 3))
    grads = {}
    for antialias in (True, False):
        tensor.requires_grad, tensor.grad = True, None
        (render.render(scene, antialias=antialias) * md.tensor(weights)).sum().backward()
        grads[antialias] = (
            tensor.grad.reshape(-1, 3).sum(axis=0) if tensor.ndim == 2 else (tensor.grad.copy())
        )
    tensor.requires_grad = False
    base = tensor.data.copy()
    fd = []
    for component in range(3):
        values = []
        for sign in (1.0, -1.0):
            tensor.data[...] = base
            tensor.data.reshape(-1, 3)[:, component] += sign * h
            with md.no_grad():
                image = render.render(scene, spp=spp, reuse_visibility=False)
            values.append(float(np.sum(image.data * weights)))
        fd.append((values[0] - values[1]) / (2 * h))
    tensor.data[...] = base
    fd = np.array(fd)
    rel = {k: float(np.linalg.norm(g - fd) / np.linalg.norm(fd)) for k, g in grads.items()}
    return rel, grads, fd


def test_light_and_occluder_gradients_estimate_the_supersampled_derivative():
    """A floating pyramid over the ground, 96x80: the point light moved, the directional
    light turned, the pyramid moved (its silhouette moves too), against central
    differences of a 256-spp render. Measured on seeds 4, 5, 6: point light 0.059, 0.055,
    0.049; directional 0.059, 0.30, 0.065; pyramid 0.16, 0.21, 0.20 (pixel centres: 0.20 to
    1.19). The error that remains sits at the corners of shadows and outlines, where two
    edges share a pixel and the pairs of one axis see only one of them."""
    scene = random_scene(4, sphere=False, width=96, height=80)
    rel_light, *_ = supersampled_check(scene, scene.lights[0].position, h=0.02)
    scene = random_scene(4, lights=("directional",), sphere=False, width=96, height=80)
    rel_dir, *_ = supersampled_check(scene, scene.lights[0].direction, h=0.01)
    scene = random_scene(4, sphere=False, width=96, height=80)
    rel_occluder, *_ = supersampled_check(scene, scene.objects[1].vertices, h=0.01)
    assert rel_light[True] < 0.1 and rel_dir[True] < 0.1, (rel_light, rel_dir)
    assert rel_occluder[True] < 0.25, rel_occluder
    for rel in (rel_light, rel_dir, rel_occluder):
        assert rel[True] < 0.5 * rel[False]


def _border_inputs(seed, monkeypatch):
    """What a boundary render of a random scene (a pyramid and a sphere casting onto the
    ground, the sphere receiving too, under a point and a directional light) hands the
    shadow border's edge function, per light: (scene, visibility, light, occluder rows,
    receivers, ``_border_rows``' parts, the chord points (k, 2)), and the plain camera."""
    from render.edges.boundary import shadow_border as sb

    seen, rows_of, onto = [], sb._border_rows, sb._border_points

    def keep_rows(scene, visibility, light, occluder, receiver):
        parts = rows_of(scene, visibility, light, occluder, receiver)
        seen.append([scene, visibility, light, occluder, receiver, parts])
        return parts

    def keep_points(frame, receivers, occluders, light, coords, *rest):
        seen[-1].append(coords)
        seen[-1].append(frame)
        return onto(frame, receivers, occluders, light, coords, *rest)

    monkeypatch.setattr(sb, "_border_rows", keep_rows)
    monkeypatch.setattr(sb, "_border_points", keep_points)
    scene = random_scene(seed, lights=("point", "directional"))
    scene.lights[0].position.requires_grad = True
    render.render(scene, antialias="boundary").sum().backward()
    monkeypatch.undo()
    assert len(seen) == 2  # both lights cast borders
    return seen


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_border_gradient_is_the_derivative_of_the_border_function(seed, monkeypatch):
    """The shadow border's edge function off the tape (``shadow_border.border_gradient``):
    its image-plane gradient against central differences of e, and the points
    ``onto_border`` moves from the chords onto the border (e / |grad e| below 1e-12), on
    mesh edges' and the sphere's borders."""
    from render.edges.boundary import shadow_border as sb

    kinds = set()
    for *_, parts, coords, frame in _border_inputs(seed, monkeypatch):
        moved, e, grad, _, t = sb.onto_border(frame, *parts, coords)
        ok = np.isfinite(t) & (t > 0) & np.all(np.isfinite(grad), axis=1)
        assert ok.mean() > 0.9
        norm = np.linalg.norm(grad[ok], axis=1)
        assert np.max(np.abs(e[ok]) / norm) < 1e-12  # image-plane units (measured < 1e-14)
        h = 1e-6
        for axis in (0, 1):
            step = np.zeros(2)
            step[axis] = h
            plus = sb.border_gradient(frame, *parts, moved + step)[0]
            minus = sb.border_gradient(frame, *parts, moved - step)[0]
            central = (plus - minus)[ok] / (2 * h)
            # measured: within 2e-9 of the largest gradient (the differences' own error)
            np.testing.assert_allclose(central, grad[ok, axis], rtol=0, atol=1e-7 * norm.max())
        kinds |= set(parts[1][0][ok].tolist())
    assert kinds == {0, 1}  # mesh edges and the sphere both cast borders


@pytest.mark.parametrize("seed", [0, 1])
def test_shadow_term_is_the_border_function_of_the_plain_points(seed, monkeypatch):
    """One edge function on and off the tape: ``shadow_term``'s e (on the tape, each light's
    and occluder's rows gathered from the scene's tensors) equals ``border_gradient``'s
    (off it, from ``_border_rows``) at the same points, taken 0.3 pixels off the border so
    that e is not zero, to 1e-12 of its scale (measured: < 1e-13; the tape's camera rays sum
    x right + y up + forward, the Newton steps' forward + x right + y up)."""
    from render.edges.boundary import shadow_border as sb
    from render.scene.camera import camera_frame

    found = _border_inputs(seed, monkeypatch)
    scene = found[0][0]
    frame = camera_frame(scene.camera)
    for scene, _, light, occluder, receiver, parts, coords, plain in found:
        shifted = coords + 0.3 * 2.0 / scene.camera.width
        e_plain, grad = sb.border_gradient(plain, *parts, shifted)[:2]
        k = len(coords)
        j = np.full(k, scene.lights.index(light))
        points = sb.ShadowPoints(shifted, np.zeros(k, np.int64), np.ones((k, 3)), j, receiver,
                                 occluder)  # fmt: skip
        e_tape, rows = sb.shadow_term(scene, points, frame)
        ok = np.isfinite(e_plain[rows])
        assert ok.mean() > 0.9
        scale = np.abs(e_plain[rows][ok]).max()
        np.testing.assert_allclose(e_tape.data[ok], e_plain[rows][ok], rtol=0, atol=1e-12 * scale)


def _chord_inputs(seed, monkeypatch):
    """The arguments of ``bisect_chords`` in a boundary render of a random scene (a pyramid
    and a sphere under a point and a directional light), and the render's visibility."""
    from render.edges.boundary import shadow_border as sb
    from render.edges.boundary import shadow_tracing as st

    seen, bisect, rows_of = {}, st.bisect_chords, sb._border_rows

    def keep(*args):
        seen["args"] = args
        return bisect(*args)

    def keep_visibility(scene, visibility, *rest):
        seen["visibility"] = visibility
        return rows_of(scene, visibility, *rest)

    monkeypatch.setattr(st, "bisect_chords", keep)
    monkeypatch.setattr(sb, "_border_rows", keep_visibility)
    scene = random_scene(seed, lights=("point", "directional"))
    scene.lights[0].position.requires_grad = True
    render.render(scene, antialias="boundary")
    monkeypatch.undo()
    return bisect, seen["args"], seen["visibility"]


@pytest.mark.parametrize("seed", [0, 3])
def test_bisect_chords_kernel_finds_the_chords_the_numpy_bisection_finds(seed, monkeypatch):
    """``bisect_chords`` (depth first, one grazing ray at a time, in Numba) against its
    plain statement ``shadow_reference.border_chords`` (round by round, in NumPy): the same
    chords — curve, receiver and both ends — in another order, on a random scene's pyramid
    and sphere under a point and a directional light."""
    from tests.render.edges import shadow_reference

    bisect, args, visibility = _chord_inputs(seed, monkeypatch)
    x0, x1, curve, receiver = shadow_reference.border_chords(visibility, *args[1:11])
    fast = bisect(*args)

    def rows(x0, x1, curve, receiver):
        table = np.column_stack([curve, receiver, x0, x1])
        return table[np.lexsort(table.T[::-1])]

    plain, ours = rows(x0, x1, curve, receiver), rows(*fast)
    point = args[3]
    assert len(plain) > 50 and set(point[curve]) == {True, False}  # both lights' borders
    np.testing.assert_array_equal(ours[:, :2], plain[:, :2])  # curve (light, occluder), receiver
    np.testing.assert_allclose(ours[:, 2:], plain[:, 2:], rtol=0, atol=1e-9)  # pixels


def test_bisect_chords_gives_the_same_chords_when_its_blocks_run_out_of_rows(monkeypatch):
    """``bisect_chords`` writes each block's chords to rows set aside for it; a block that
    needs more makes the pass run again with more. Starting with one row per block (every
    block runs out, several times) gives the same chords in the same order, on one job and
    on several."""
    bisect, args, _ = _chord_inputs(0, monkeypatch)
    with using_threads(1):
        roomy = bisect(*args)
    assert len(roomy[2]) > 50
    for threads in (1, 3):
        with using_threads(threads):
            tight = bisect(*args, room=1)
        for a, b in zip(roomy, tight, strict=True):
            np.testing.assert_array_equal(a, b)


TREE = Path(__file__).parents[2] / "data" / "raytracerjl" / "meshes" / "tree.obj"


def _foliage_scene(shift: float = 0.0):
    """RayTracer.jl's low-poly tree's foliage (three faceted, open cones, one above the
    other, as Blender wrote them: every face with its own vertices), the tree scaled to a
    unit box and lifted by 0.5, translated by ``shift`` along x, lit from above: the upper
    cones' shadows fall across the creases of the lower ones. (``window_difference``'s
    scene maker: the scene, the translation, its direction.)"""
    meshes = render.load_mesh(TREE)
    everything = np.concatenate([np.asarray(m.vertices.data) for m in meshes])
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    leaves = meshes[1]
    vertices = (np.asarray(leaves.vertices.data) - (lo + hi) / 2) / np.max(hi - lo)
    mesh = render.Mesh(vertices + [0.0, 0.5, 0.0], np.asarray(leaves.faces), leaves.material)
    translation = md.tensor([shift, 0.0, 0.0])
    mesh.transform = render.Transform(translation=translation)
    camera = render.Camera((0.9, 0.8, 1.6), (0, 0, 0), (0, 1, 0), 40.0, 48, 48)
    light = render.PointLight((0.8, 2.0, 1.0), 6.0)
    return render.Scene([mesh], [light], camera), translation, np.array([1.0, 0.0, 0.0])


def test_a_shadow_across_the_creases_of_a_faceted_mesh_file_has_the_supersampled_gradient():
    """Where a shadow border falls onto the next face of a faceted receiver, its chord
    stops up to ``shadow_tracing.GAP`` short of the crease, and the crease must be cut
    there: its lit part jumps, its shadowed part does not. The cut reached only a tenth
    of GAP, so the crease's one point stood for its whole piece in the pixel, lit or not.
    The foliage's translation gradient, weighted on the 25 pixels where its shadows cross
    its creases (16-spp visibility), against the window difference of 4,096-spp renders:
    10.5 % off before the cut reached GAP, 0.3 % after."""
    from render.inverse.reference import window_difference, window_mean_gradient
    from render.scene.cache import RenderCache
    from render.trace.visibility import trace_visibility

    scene = _foliage_scene()[0]
    dense = trace_visibility(scene, RenderCache(), True, 16, True)
    prim = dense.primary.prim_id.reshape(-1, 16)
    lit = np.zeros(prim.size, bool)
    lit[dense.primary.hit_rays] = dense.lit[0]
    lit = lit.reshape(-1, 16)
    faces = np.array([len(set(row)) for row in prim])
    crossing = np.flatnonzero((faces >= 2) & np.all(prim >= 0, axis=1) & np.any(lit, axis=1)
                              & ~np.all(lit, axis=1))  # fmt: skip
    assert len(crossing) >= 10
    weights = np.zeros((48 * 48, 3))
    weights[crossing] = 1.0
    weights = weights.reshape(48, 48, 3)
    truth = [window_difference(_foliage_scene, weights, 0.004, 4096, seed, pixels=crossing)
             for seed in (0, 1)]  # fmt: skip
    ours = window_mean_gradient(_foliage_scene, weights, 0.004, "boundary", 16)
    mean, spread = np.mean(truth), abs(truth[1] - truth[0])
    assert abs(ours - mean) < 0.02 * abs(mean) + 3 * spread, (ours, truth)
