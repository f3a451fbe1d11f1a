"""The shadow borders' points, compiled, against the same function on the tape; and the
boundary term's compiled discrete passes against their NumPy statements.

``render.edges.boundary.shadow_border.shadow_points`` moves the shadow borders' quadrature
points onto their borders and finds their factors' geometry with one compiled function
(``_onto_border``, traced by ``minidiff.compile``); ``shadow_points(..., compiled=False)``
runs that function on the tape, primitive by primitive (``minidiff.tape_only``), the
reference it must agree with. ``pixels.split_at_crossings`` groups the pieces by a
counting sort and splits the groups in parallel blocks; ``pixel_order`` and a
group-at-a-time loop are its statement. All must give the same results on any number of
threads (with ``kind_points``, which deals the points on the pieces to their kinds).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import render
from render.edges.boundary import pixels
from render.edges.boundary import shadow_border as sb
from render.scene.lights import PointLight
from render.scene.teapot import paper_scene
from tests.render_helpers import random_scene, same_bits_on_one_and_two_threads


def _differentiable(scene):
    """The scene with its light positions or directions, its mesh vertices, sphere centres
    and camera position requiring gradients; returns those leaves."""
    leaves = []
    for light in scene.lights:
        leaves.append(light.position if isinstance(light, PointLight) else light.direction)
    leaves += [mesh.vertices for mesh in scene.meshes]
    leaves += [sphere.center for sphere in scene.spheres]
    leaves.append(scene.camera.position)
    for leaf in leaves:
        leaf.requires_grad = True
    return leaves


def _shadow_inputs(scene, monkeypatch):
    """The arguments ``ShadowBorder.points`` hands ``shadow_points`` in a boundary render
    of ``scene``."""
    seen, points = [], sb.shadow_points

    def keep(*args, **kwargs):
        seen.append(args)
        return points(*args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(sb, "shadow_points", keep)
        render.render(scene, antialias="boundary")
    assert len(seen) == 1
    return seen[0]


def _scenes():
    """The scenes of the tests, by name: the paper teapot on its ground at 64x64 and
    128x128, a sphere casting onto a textured ground under a point and a directional light,
    and a flat-shaded pyramid and a sphere under both."""
    return {
        "teapot 64": lambda: paper_scene(64, 64, ground=True),
        "teapot 128": lambda: paper_scene(128, 128, ground=True),
        "sphere, point light": lambda: random_scene(1, pyramid=False, texture=True),
        "sphere, directional light": lambda: random_scene(
            2, lights=("directional",), pyramid=False
        ),
        "pyramid and sphere, both lights": lambda: random_scene(
            3, lights=("point", "directional"), width=48, height=40
        ),
    }


def _assert_close(got, want):
    """Equal to ~1e-12 of the largest |want| (finite entries; NaN where want has NaN)."""
    assert got.shape == want.shape
    scale = np.abs(want[np.isfinite(want)]).max(initial=0.0)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * max(scale, 1e-300))


@pytest.mark.parametrize("name", list(_scenes()))
def test_compiled_points_are_the_tapes(name, monkeypatch):
    """``shadow_points``: the compiled pass keeps the same points, with the same pixels,
    labels, coordinates and factors as its function run on the tape, to the last bit."""
    scene = _scenes()[name]()
    _differentiable(scene)
    args = _shadow_inputs(scene, monkeypatch)
    got, want = sb.shadow_points(*args), sb.shadow_points(*args, compiled=False)
    assert len(want.pixel) > 0 and np.abs(want.weight).max() > 0
    for label in ("pixel", "light", "receiver", "occluder", "coords", "weight"):
        np.testing.assert_array_equal(getattr(got, label), getattr(want, label))


@pytest.mark.parametrize("name", ["teapot 64", "pyramid and sphere, both lights"])
def test_the_gradient_is_the_reference_gradient(name, monkeypatch):
    """The whole ``render(..., antialias="boundary")`` gradient with the compiled points
    equals the one with their function on the tape (the reference), to ~1e-12 of each
    parameter's largest entry."""
    grads = []
    for compiled in (True, False):
        scene = _scenes()[name]()
        leaves = _differentiable(scene)
        with monkeypatch.context() as patch:
            if not compiled:
                reference = functools.partial(sb.shadow_points, compiled=False)
                patch.setattr(sb, "shadow_points", reference)
            image = render.render(scene, antialias="boundary")
            (image * image).sum().backward()
        grads.append([leaf.grad.copy() for leaf in leaves])
    for got, want in zip(*grads, strict=True):
        assert np.abs(want).max() > 0
        _assert_close(got, want)


class _OtherPointLight(PointLight):
    """A light class the renderer does not name: a point light's physics."""


def test_any_light_at_a_point_gets_a_point_lights_borders(monkeypatch):
    """The points are moved onto the borders with what the light says of itself (where it
    is, ``Light.location``; its rays, ``Light.ray_to``; its edge planes), not its class: a
    subclass of ``PointLight`` gives the same points and factors, bit for bit."""
    found = []
    for make in (PointLight, _OtherPointLight):
        scene = random_scene(4, pyramid=False)
        light = scene.lights[0]
        scene.lights[0] = make(light.position.data, light.intensity.data)
        _differentiable(scene)
        found.append(sb.shadow_points(*_shadow_inputs(scene, monkeypatch)))
    assert len(found[0].pixel) > 0
    for label in ("pixel", "coords", "weight"):
        np.testing.assert_array_equal(getattr(found[0], label), getattr(found[1], label))


def _split_reference(p0, p1, segment, start, end, pixel):
    """``split_at_crossings``' statement: pieces grouped by ``pixel_order``, each group
    split by ``_split_group`` one after the other."""
    order = pixels.pixel_order(pixel)
    ordered = pixel[order]
    bounds = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1], True])
    geometry = np.empty((len(order), 9))
    out, n = np.empty((1, 4)), 0  # one row: the table grows, as each job's does
    ts = np.empty(len(order) + 1)
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        pixels._piece_geometry(p0, p1, segment, start, end, order, lo, hi, geometry)
        x = lo
        while x < hi:
            n, x = pixels._split_group(geometry, segment, start, end, pixel, order, lo, hi, x,
                                       out, n, len(out), ts)  # fmt: skip
            if x < hi:
                out, _, n, _ = pixels._room(out, 0, n, len(out), hi - lo)
    return out[:n, 0].astype(np.int64), out[:n, 1], out[:n, 2], out[:n, 3].astype(np.int64)


@settings(max_examples=8, deadline=None)
@given(
    st.integers(0, 2**32 - 1), st.integers(1, 120), st.sampled_from([(3, 2), (8, 8), (300, 200)])
)
def test_split_at_crossings_is_its_statement(seed, n, size):
    """Random segments, many of them crossing in few pixels (or scattered over a large
    image, whose pieces are ordered by ``pixel_order``, not the counting sort): the
    compiled split gives its statement's pieces, row for row, and the counting sort
    ``pixel_order``'s order."""
    rng = np.random.default_rng(seed)
    width, height = size
    p0 = rng.uniform(-0.5, 1.1, (n, 2)) * [width, height]
    p1 = p0 + rng.normal(0.0, 1.5, (n, 2))
    pieces = pixels.pixel_pieces(p0, p1, width, height)
    if len(pieces[3]) == 0:
        return
    order = pixels._counting_order(pieces[3], width * height)
    np.testing.assert_array_equal(order, pixels.pixel_order(pieces[3]))
    got = pixels.split_at_crossings(p0, p1, *pieces)
    want = _split_reference(p0, p1, *pieces)
    for a, b in zip(got, want, strict=True):
        assert a.dtype == b.dtype
    np.testing.assert_array_equal(got[0], want[0])  # the segments
    np.testing.assert_array_equal(got[3], want[3])  # the pixels
    # The parameters: to rounding (the same formula, compiled inside the parallel pass
    # here and on its own in the statement, has differed in the last bit).
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-14)
    np.testing.assert_allclose(got[2], want[2], rtol=0, atol=1e-14)


def test_a_crowded_pixel_is_split_without_a_table_for_every_pair():
    """A dense mesh in a small image puts thousands of pieces in one pixel (a 160k-face
    sphere at 128 x 128: up to 3,138), which cross little. The split once took a table of
    k * k rows for a pixel of k pieces (2,000 here: 4M rows, 134 MB; a 360k-face sphere at
    128 x 128 asked for 32 GiB and failed); it grows its tables as parts come now. The
    statement's parts, and less than 20 MB allocated (NumPy's arrays, traced)."""
    import tracemalloc

    rng = np.random.default_rng(7)
    p0 = rng.uniform(0.05, 0.95, (2000, 2))  # short chords, all in pixel (0, 0)
    p1 = np.clip(p0 + rng.normal(0.0, 0.02, (2000, 2)), 0.01, 0.99)
    pieces = pixels.pixel_pieces(p0, p1, 4, 4)
    assert len(pieces[3]) == 2000 and np.all(pieces[3] == 0)
    pixels.split_at_crossings(p0[:50], p1[:50], *pixels.pixel_pieces(p0[:50], p1[:50], 4, 4))
    tracemalloc.start()
    try:
        got = pixels.split_at_crossings(p0, p1, *pieces)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6, f"{peak / 1e6:.0f} MB"
    want = _split_reference(p0, p1, *pieces)
    assert len(got[0]) > 2000  # some chords cross
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-14)


#: The compiled passes on 1 and 2 threads in one process: the teapot's shadow points, a
#: scene's whole boundary gradient and a crowded split.
_THREADS = """
import numpy as np
import render
from render.edges.boundary import pixels
from render.edges.boundary import shadow_border as sb
from render.edges.boundary.kind_points import kind_points
from render.scene.teapot import paper_scene
from tests.render_helpers import random_scene
seen, points = [], sb.shadow_points
sb.shadow_points = lambda *a: seen.append(a) or points(*a)
scene = paper_scene(96, 96, ground=True)
scene.lights[0].position.requires_grad = True
render.render(scene, antialias="boundary")
sb.shadow_points = points
rng = np.random.default_rng(5)
p0 = rng.uniform(0, 6, (400, 2))
p1 = p0 + rng.normal(0, 2, (400, 2))
def run():
    found = sb.shadow_points(*seen[0])
    other = random_scene(3, lights=("point", "directional"), width=48, height=40)
    leaf = other.lights[0].position
    leaf.requires_grad = True
    render.render(other, antialias="boundary").sum().backward()
    split = pixels.split_at_crossings(p0, p1, *pixels.pixel_pieces(p0, p1, 6, 6))
    dealt = kind_points(p0, p1, split, np.array([150, 0, 250]), 6, 6)
    assert len(found.pixel) > 0 and np.abs(leaf.grad).max() > 0
    return (found.coords, found.weight, found.pixel, leaf.grad.copy(), *split,
            *(x for kind in dealt for x in kind))
"""


@pytest.mark.new_processes
def test_the_same_bits_on_one_and_two_threads():
    same_bits_on_one_and_two_threads(_THREADS)


@pytest.mark.parametrize("short", [0.0, 0.4, 0.99])
def test_a_border_that_stops_short_of_a_crease_still_cuts_it(short):
    """A shadow border falling onto the next face of a faceted receiver is followed until
    its grazing rays either side of the crease are ``shadow_tracing.GAP`` apart, so its
    chord stops up to GAP short of the crease; the crease must still be cut where the
    border meets it (on one side the crease lies in the shadow and jumps by nothing). A
    chord ending ``short`` x GAP before a crease across pixel (0, 0): the crease is cut
    in two where the chord's line meets it; one ending twice ``pixels.JUNCTION`` before
    it is no junction."""
    from render.edges.boundary.shadow_tracing import GAP

    assert GAP < pixels.JUNCTION
    for gap, cut in ((short * GAP, True), (2.0 * pixels.JUNCTION, False)):
        way = np.array([0.5, 1.0])  # the chord's direction: its line meets the crease at 0.5
        end = np.array([0.5, 0.5]) - gap * way
        p0 = np.array([[0.1, 0.5], end - 0.3 * way])  # the crease, the chord
        p1 = np.array([[0.9, 0.5], end])
        pieces = pixels.pixel_pieces(p0, p1, 2, 2)
        segment, start, end, _ = pixels.split_at_crossings(p0, p1, *pieces)
        parts = np.sort(np.c_[start, end][segment == 0], axis=0)
        if cut:
            np.testing.assert_allclose(parts, [[0.0, 0.5], [0.5, 1.0]], atol=1e-12)
        else:
            np.testing.assert_array_equal(parts, [[0.0, 1.0]])
