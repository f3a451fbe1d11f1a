"""Secondary visibility's boundary term (``render.path.boundary.secondary``): soft shadows of
an area light, a point light's hard shadow seen after a bounce, checked against central differences
of renders with many more samples (common random numbers), on small scenes where the
shadow's edge carries most of the derivative (so that a missing or wrong term fails); the
compiled curve draws (``render.path.boundary.silhouettes``) against their NumPy reference; the
replay against the tape; errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.path import render_path
from render.path.boundary.silhouettes import Curves, pick_reference
from render.path.sample.tracer import PathSampler
from render.scene.cornell import box_mesh, cornell_box, grid_quad
from render.scene.placement import placed
from tests.render_helpers import same_bits_on_one_and_two_threads

X, Y, Z = np.eye(3)


def shadowed_floor(occluder: str, light: str = "area") -> render.Scene:
    """A floor under an occluder ("square", "box", "tall box" or "sphere") lit by a
    small square area light (a ``Transform`` places it), a point light ("point", "point
    seen") or the sun ("directional") above; 8 x 8 pixels. With the area light and "point
    seen" the camera looks down at the floor's shadow from under the occluder (which it
    does not see); with the others it looks up at the occluder's underside, lit only by
    the floor, whose hard shadow it sees after one bounce."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)
    objects = [render.Mesh(v, f, render.Material((0.8, 0.8, 0.8)))]
    grey = render.Material((0.5, 0.5, 0.5))
    if occluder == "square":
        v, f = grid_quad((0.1, 0.6, 0.0), 0.3 * X, 0.3 * Z)
        objects.append(render.Mesh(v, f, grey))
    elif occluder == "box":
        objects.append(box_mesh((0.1, 0.6, 0.0), (0.2, 0.05, 0.2), grey))
    elif occluder == "tall box":
        objects.append(box_mesh((0.1, 0.55, 0.0), (0.2, 0.15, 0.2), grey))
    else:
        objects.append(render.Sphere((0.1, 0.6, 0.0), 0.2, grey))
    lights = []
    down = render.Camera((0.05, 0.35, 0.05), (0.0, 0.0, 0.0), (0, 0, -1), 110.0, 8, 8)
    up = render.Camera((0.05, 0.2, 0.05), (0.1, 0.6, 0.0), (0, 0, -1), 50.0, 8, 8)
    if light == "area":
        v, f = grid_quad((0.0, 1.0, 0.0), 0.25 * X, 0.25 * Z)
        emitter = render.Material((0, 0, 0), emission=(5.0, 5.0, 5.0))
        objects.append(render.Mesh(v, f, emitter, transform=render.Transform()))
        camera = down
    elif light == "directional":
        lights.append(render.DirectionalLight((0.3, -1.0, 0.2), 2.0))
        camera = up
    else:
        lights.append(render.PointLight((0.0, 1.1, 0.1), 3.0))
        camera = down if light == "point seen" else up
    return render.Scene(objects, lights, camera)


#: parameter name -> (scene's occluder, light, the tensor, its direction of change).
CASES = {
    "light position": ("box", "area", lambda s: s.objects[2].transform.translation,
                       lambda p: np.array([0.3, 0.1, 0.2])),
    "light size": ("square", "area", lambda s: s.objects[2].transform.scale,
                   lambda p: np.ones(p.shape)),
    "sphere centre": ("sphere", "area", lambda s: s.objects[1].center,
                      lambda p: np.array([1.0, 0.3, 0.2])),
    "box corner": ("tall box", "area", lambda s: s.objects[1].vertices,
                   lambda p: corner_copies_direction(p)),
    "point light after a bounce": ("square", "point", lambda s: s.lights[0].position,
                                   lambda p: np.array([1.0, 0.2, 0.5])),
    "sun after a bounce": ("square", "directional", lambda s: s.lights[0].direction,
                           lambda p: np.array([1.0, 0.0, 0.5])),
    "point light's shadow in view": ("sphere", "point seen", lambda s: s.lights[0].position,
                                     lambda p: np.array([1.0, 0.2, 0.5])),
}  # fmt: skip


def corner_copies_direction(p: md.Tensor) -> np.ndarray:
    """(V, 3): up, for every copy of the box's top corner with the largest x + z (a box's
    sides have their own vertices: a corner moves as one only if all its copies do)."""
    direction = np.zeros(p.shape)
    mask = np.all(p.data == p.data[np.argmax(_corner_score(p.data))], axis=1)
    direction[mask] = (0.0, 1.0, 0.0)  # sideways, not differentiable: docs/path_tracing.md
    return direction


def _corner_score(v: np.ndarray) -> np.ndarray:
    return np.where(v[:, 1] == v[:, 1].max(), v[:, 0] + v[:, 2], -np.inf)


def derivative(case: str, antialias, spp: int, seed: int, delta: float = 0.0, grad=True):
    """(sum of the image, our directional derivative of it or None) for ``case``."""
    occluder, light, get, direction = CASES[case]
    scene = shadowed_floor(occluder, light)
    p = get(scene)
    d = direction(p)
    p.data = p.data + delta * d
    p.requires_grad = grad
    depth = 3 if light in ("point", "directional") else 2
    image = render_path(scene, spp=spp, max_depth=depth, seed=seed, rr_depth=100,
                        antialias=antialias)  # fmt: skip
    total = image.sum()
    if not grad:
        return total.item(), None
    total.backward()
    return total.item(), float(np.sum(p.grad * d))


#: Central differences' step, their samples per pixel and ours, both over SEEDS; the point
#: light's hard shadow is noisier on both sides (a sample flips between lit and not).
H, SEEDS = 0.05, (0, 1)
SAMPLES = {"point light after a bounce": (512, 2048), "sun after a bounce": (2048, 2048)}


@pytest.mark.parametrize("case", list(CASES))
def test_secondary_term_matches_central_differences(case):
    """Ours with the term within 10 % of the central differences (measured: 1-4 %; noise
    from seeds ~3 %), and without it at least 25 % off (what this test checks: measured
    38-100 %)."""
    spp, fd_spp = SAMPLES.get(case, (256, 1024))
    ours = np.mean([derivative(case, "secondary", spp, s)[1] for s in SEEDS])
    plain = np.mean([derivative(case, False, spp, s)[1] for s in SEEDS])
    with md.no_grad():
        fd = np.mean([
            (derivative(case, False, fd_spp, s, H, False)[0]
             - derivative(case, False, fd_spp, s, -H, False)[0]) / (2 * H)
            for s in SEEDS
        ])  # fmt: skip
    assert abs(ours - fd) <= 0.1 * abs(fd), (case, ours, fd, plain)
    assert abs(plain - fd) >= 0.25 * abs(fd), (case, ours, fd, plain)


def cornell_curves():
    world = placed(cornell_box(8, 8, blocks=True))
    sampler = PathSampler(world, 1, 3, 100, 0)
    return Curves.of(sampler), sampler


def test_kept_curves_follow_the_shapes():
    """``Curves.kept`` gives the curves ``Curves.of`` makes, the same object again while
    the shapes keep their values, and new ones (never stale) once a vertex or a sphere
    moves, or a mesh's faces change."""
    from render.scene.cache import RenderCache

    scene, cache = cornell_box(8, 8, blocks=True), RenderCache()

    def kept():
        return Curves.kept(PathSampler(placed(scene), 1, 3, 100, 0, cache))

    first = kept()
    assert kept() is first
    fresh = Curves.of(PathSampler(placed(scene), 1, 3, 100, 0))
    for got, want in zip(vars(first).values(), vars(fresh).values(), strict=True):
        np.testing.assert_array_equal(got, want)
    block, sphere = scene.objects[6], scene.objects[7]
    for move in (
        lambda: block.vertices.data.__setitem__((0, 1), block.vertices.data[0, 1] + 0.05),
        lambda: sphere.center.data.__setitem__(0, sphere.center.data[0] + 0.01),
        lambda: setattr(block, "faces", block.faces[:, ::-1].copy()),
    ):
        before = kept()
        move()
        after = kept()
        assert after is not before
        want = Curves.of(PathSampler(placed(scene), 1, 3, 100, 0))
        for got, expected in zip(vars(after).values(), vars(want).values(), strict=True):
            np.testing.assert_array_equal(got, expected)


@settings(max_examples=4, deadline=None)
@given(st.integers(0, 2**31 - 1), st.booleans())
def test_compiled_draws_equal_the_reference(seed, towards):
    """``Curves.pick`` (one Numba loop per apex) draws what ``pick_reference`` (NumPy, n x
    curves arrays) draws: the same curves, densities and points to rounding."""
    curves, sampler = cornell_curves()
    rng = np.random.default_rng(seed)
    n = 500
    apex = rng.uniform(-0.99, 0.99, (n, 3))
    u = rng.random((2, n))
    active = rng.random(n) < 0.9
    triangles = sampler.primitives[0][sampler.emitters.prims[rng.integers(0, 2, n)]]
    if towards:
        draw = curves.pick(apex, (u[0], u[1], active), (triangles, u[0], u[1], active))[1]
        reference = pick_reference(curves, apex, u[0], u[1], triangles, active)
    else:
        draw = curves.pick(apex, (u[0], u[1], active))[0]
        reference = pick_reference(curves, apex, u[0], u[1], None, active)
    same = draw[0] == reference[0]
    assert same.mean() >= 0.99  # a draw at a tie of the cumulative weights may differ
    assert np.any(draw[0] >= 0)
    ok = same & (draw[0] >= 0)
    for got, want in zip(draw[1:], reference[1:], strict=True):
        np.testing.assert_allclose(got[ok], want[ok], rtol=1e-9, atol=1e-12)


def dense_curves(n: int = 24, seed: int = 0):
    """A jittered UV sphere of 2 n^2 faces (wound outward), a lone triangle (its edges
    always silhouettes) and a floor, as curves; plus apexes around, near and inside the
    sphere and on the floor."""
    rng = np.random.default_rng(seed)
    theta, phi = np.meshgrid(np.linspace(0, np.pi, n + 1), np.linspace(0, 2 * np.pi, n,
                             endpoint=False), indexing="ij")  # fmt: skip
    v = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    v = (v.reshape(-1, 3) + rng.normal(0, 0.01, ((n + 1) * n, 3))) * 0.4 + [0, 0.6, 0]
    idx = np.arange(len(v)).reshape(n + 1, n)
    a, b = idx[:-1], np.roll(idx[:-1], -1, 1)
    c, d = idx[1:], np.roll(idx[1:], -1, 1)
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([b, d, c], -1).reshape(-1, 3)])  # fmt: skip
    grey = render.Material((0.5, 0.5, 0.5))
    v_floor, f_floor = grid_quad((0, 0, 0), np.array([2.0, 0, 0]), np.array([0, 0, -2.0]))
    lone = np.array([[0.8, 0.5, 0.0], [1.0, 0.6, 0.1], [0.9, 0.9, -0.1]])
    objects = [render.Mesh(v_floor, f_floor, grey), render.Mesh(v, faces, grey),
               render.Mesh(lone, np.array([[0, 1, 2]]), grey)]  # fmt: skip
    camera = render.Camera((0, 1, 3), (0, 0.5, 0), (0, 1, 0), 50.0, 8, 8)
    scene = render.Scene(objects, [render.PointLight((0, 2, 0), 1.0)], camera)
    sampler = PathSampler(placed(scene), 1, 3, 100, 0)
    apex = np.concatenate([
        rng.uniform(-1.5, 1.5, (300, 3)) + [0, 0.8, 0],  # around
        [0, 0.6, 0] + 0.4 * rng.normal(1, 0.02, (200, 1)) * rng.normal(size=(200, 3)) / 1.7,
        rng.uniform(-0.15, 0.15, (50, 3)) + [0, 0.6, 0],  # inside
        np.c_[rng.uniform(-1, 1, 50), np.zeros(50), rng.uniform(-1, 1, 50)],  # on the floor
    ])  # fmt: skip
    return Curves.of(sampler), sampler, apex


def test_skipped_runs_of_edges_leave_every_draw_as_it_is():
    """The draws skip runs of edges that bounds on their faces' planes show hold no
    silhouette (``Curves.clusters``): on a dense sphere, from apexes around it, near its
    surface, inside it and on the floor, the draws are those with no run skipped, bit for
    bit (a run skipped that held a silhouette would change them); and many runs are
    skipped (a third here, of this coarse sphere's; more of a finer one's)."""
    from render.path.boundary.silhouettes import _hidden_run

    curves, sampler, apex = dense_curves()
    bounds, usable = curves.clusters
    rng = np.random.default_rng(1)
    n = len(apex)
    u = rng.random((2, n))
    triangles = sampler.primitives[0][rng.integers(0, sampler.n_triangles, n)]
    towards = (triangles, u[1], u[0], np.ones(n, bool))
    skipping = curves.pick(apex, (u[0], u[1], np.ones(n, bool)), towards)
    skipped = np.mean([[_hidden_run(tuple(p), bounds, k) for k in range(len(usable))]
                       for p in apex[:300]])  # fmt: skip
    assert skipped > 0.2, skipped
    curves.__dict__["clusters"] = (bounds, np.zeros_like(usable))  # no run skipped
    every = curves.pick(apex, (u[0], u[1], np.ones(n, bool)), towards)
    for mine, theirs in zip(skipping, every, strict=True):
        for x, y in zip(mine, theirs, strict=True):
            np.testing.assert_array_equal(x, y)
    reference = pick_reference(curves, apex, u[0], u[1], None, np.ones(n, bool))
    assert np.mean(skipping[0][0] == reference[0]) >= 0.99


#: The secondary term's gradient and the curve draws on 1 and 2 threads in one process.
_THREADS = """
import sys, numpy as np
sys.path.insert(0, "tests/render/path")
from test_secondary import cornell_curves, shadowed_floor
from render.path import render_path
curves, _ = cornell_curves()
rng = np.random.default_rng(3)
apex, u = rng.uniform(-0.99, 0.99, (300, 3)), rng.random((2, 300))
def run():
    scene = shadowed_floor("sphere")
    p = scene.objects[1].center
    p.requires_grad = True
    render_path(scene, spp=16, max_depth=3, seed=2, antialias="secondary").sum().backward()
    assert np.abs(p.grad).max() > 0
    return (p.grad.copy(), *curves.pick(apex, (u[0], u[1], np.ones(300, bool)))[0])
"""


@pytest.mark.new_processes
def test_the_same_bits_on_one_and_two_threads():
    same_bits_on_one_and_two_threads(_THREADS)


def test_replay_equals_the_tape():
    """The default replay's secondary term (chunk by chunk, each its own tape) gives the
    tape's gradient (the term added to the image on one tape) to rounding."""
    grads = []
    for gradient in ("replay", "tape"):
        scene = shadowed_floor("box")
        p = scene.objects[2].transform.translation
        p.requires_grad = True
        image = render_path(scene, spp=8, max_depth=3, seed=4, antialias="secondary",
                            gradient=gradient)  # fmt: skip
        image.sum().backward()
        grads.append(p.grad.copy())
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-10, atol=1e-12 * np.abs(grads[1]).max())


def test_chunks_do_not_change_the_gradient(monkeypatch):
    import render.path.boundary.secondary as secondary

    def gradient():
        scene = shadowed_floor("sphere")
        p = scene.objects[1].center
        p.requires_grad = True
        render_path(scene, spp=4, max_depth=2, seed=1, antialias="secondary").sum().backward()
        return p.grad.copy()

    whole = gradient()
    monkeypatch.setattr(secondary, "CHUNK_PATHS", 37)
    np.testing.assert_allclose(gradient(), whole, rtol=1e-10, atol=1e-12 * np.abs(whole).max())


def test_value_is_unchanged():
    """The term adds nothing to the image."""
    images = []
    for antialias in (False, "secondary"):
        scene = shadowed_floor("box")
        scene.objects[2].transform.translation.requires_grad = True
        images.append(render_path(scene, spp=4, max_depth=2, antialias=antialias).data)
    np.testing.assert_array_equal(images[0], images[1])


def test_unknown_antialias_is_a_clear_error():
    with pytest.raises(ValueError, match='"primary" or "secondary"'):
        render_path(shadowed_floor("box"), spp=1, antialias="shadows")


def test_memory_does_not_grow_with_spp(monkeypatch):
    """The replay takes the boundary paths a chunk at a time, each on its own tape: the
    peak memory of render + backward is the same at 4x the samples (measured: 1.63, 1.68
    and 1.69 MB at 16, 64 and 256 spp)."""
    import tracemalloc

    import render.path.boundary.secondary as secondary

    monkeypatch.setattr(secondary, "CHUNK_PATHS", 512)

    def peak(spp):
        scene = shadowed_floor("box")
        scene.objects[2].transform.translation.requires_grad = True
        tracemalloc.start()
        try:
            render_path(scene, spp=spp, max_depth=3, antialias="secondary").sum().backward()
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    peak(8)  # compiled kernels and caches loaded before measuring
    small, large = peak(16), peak(64)
    assert large < 1.3 * small, (small, large)


def test_vertices_after_a_mirror_are_where_the_tape_puts_them():
    """A vertex reached through a mirror is an apex too: the tape replays its path from
    the camera (``_vertex_points``); its value is the sampler's point, to the offset the
    sampler's rays leave their surfaces by (measured: 4.4e-9)."""
    import render.path.boundary.secondary as secondary
    from render.scene.camera import camera_frame

    scene = shadowed_floor("square")
    v, f = grid_quad((0, 0.6, -1.0), 1.5 * X, 0.6 * Y)
    scene.objects.append(render.Mesh(v, f, render.Material((0, 0, 0), reflectance=1.0)))
    scene.camera = render.Camera((0.0, 2.0, 1.5), (0.0, 0.3, -1.0), (0, 1, 0), 10.0, 8, 8)
    world = placed(scene)
    sampler = PathSampler(world, 4, 3, 100, 0)
    batch = sampler.sample(np.arange(256))
    points = secondary._points(sampler, batch)
    record = batch.vertices[1]
    src = record.rows[record.form == 2]  # MIRROR
    assert len(src) > 10
    with md.no_grad():
        got = secondary._vertex_points(world, camera_frame(world.camera), sampler, batch, src,
                                       2, np.float64).data  # fmt: skip
    want = points[1][np.searchsorted(record.rows, src)]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-7)


def _written_by_a_user(light_type: type) -> type:
    """A direct subclass of ``render.Light`` with ``light_type``'s physics: its formulas,
    none of its class identity, the base class's ``shadow_apex``."""
    names = ("location", "towards", "incidence", "shadow_rays", "shadow_key", "pack",
             "edge_plane", "ray_to", "sphere_outline", "__init__")  # fmt: skip
    attrs = {name: getattr(light_type, name) for name in names}
    attrs |= {k: getattr(light_type, k) for k in ("KIND", "shadow_ray_end", "FIELDS")}
    return type(f"User{light_type.__name__}", (render.Light,), attrs)


@pytest.mark.parametrize("case", ["point light after a bounce", "sun after a bounce"])
def test_a_light_subclass_gets_the_term_its_twin_gets(case):
    """Issue 55: a light the integrator does not know by name gets the secondary term (it
    got none: a cube's shadow gradient was None). The same gradient as the library's own
    light of that physics, same seed; the term is most of it (the plain gradient is 38 %
    or more off: test above)."""
    occluder, light, get, direction = CASES[case]

    def gradient(user: bool) -> float:
        scene = shadowed_floor(occluder, light)
        if user:
            own = scene.lights[0]
            kind = _written_by_a_user(type(own))
            scene.lights[0] = kind(*(getattr(own, f.name).data for f in own.FIELDS))
        p = get(scene)
        p.requires_grad = True
        render_path(scene, spp=8, max_depth=3, seed=3, rr_depth=100,
                    antialias="secondary").sum().backward()  # fmt: skip
        return float(np.sum(p.grad * direction(p)))

    ours, twin = gradient(True), gradient(False)
    assert twin != 0 and abs(ours - twin) <= 1e-9 * abs(twin), (ours, twin)


@pytest.mark.parametrize("lights", ["area", "point and sun"])
def test_compiled_phi_is_the_tapes(monkeypatch, lights):
    """phi compiled (``secondary._level_sets``: the apex at a camera vertex, at a later one
    or at a light; x' at its place or seen by the camera) gives the gradient phi on the tape
    gives (``_phi``, the same ``level_set``), for every parameter of the Cornell box with its
    blocks (meshes and a sphere)."""
    from render.path.boundary import secondary

    scene = cornell_box(10, 10, blocks=True)
    if lights != "area":
        scene.lights = [render.PointLight((0.3, 0.6, 0.4), 1.5),
                        render.DirectionalLight((0.1, -0.3, -1.0), 0.5)]  # fmt: skip
    for name, p in scene.named_parameters().items():
        p.requires_grad = "emission" not in name or bool(np.any(p.data))
    weights = md.tensor(np.random.default_rng(1).normal(size=(10, 10, 3)))
    calls = []
    original = secondary._compiled_phi

    def gradients(antialias="secondary"):
        for p in scene.parameters():
            p.grad = None
        image = render_path(scene, spp=4, max_depth=4, seed=3, antialias=antialias)
        md.sum(image * weights).backward()
        return {n: p.grad for n, p in scene.named_parameters().items()}

    monkeypatch.setattr(secondary, "_compiled_phi", lambda *a: calls.append(a[-1]) or original(*a))
    compiled = gradients()
    kinds = set(calls)
    monkeypatch.setattr(secondary, "_compiles", lambda world: False)
    taped = gradients()
    expected = {("camera", "area"), ("area", "area"), ("light", "camera"), ("light", "area")}
    assert kinds == (expected if lights != "area" else {("camera", "area"), ("area", "area")})
    plain = gradients(antialias=False)
    moved = 0
    for name, tape in taped.items():
        if tape is None:
            assert compiled[name] is None or not np.any(compiled[name]), name
            continue
        scale = max(np.abs(tape).max(), 1e-300)
        np.testing.assert_allclose(compiled[name], tape, rtol=0, atol=1e-9 * scale, err_msg=name)
        # The term is not a rounding of the gradient: it moves it.
        moved += np.abs(tape - plain[name]).max() > 0.01 * scale
    assert moved >= 3


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_curve_gradient_is_central_differences_of_phi(seed):
    """``Curves.gradient`` (the derivative of ``level_set`` in x', by minidiff) against
    central differences of phi, on the Cornell box's edges and sphere."""
    from render.path.boundary.silhouettes import level_set

    curves, _ = cornell_curves()
    rng = np.random.default_rng(seed)
    n = 64
    index = rng.integers(0, curves.n_edges + len(curves.radius), n)
    index[:4] = curves.n_edges  # the sphere's outline in every draw
    apex, points = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) + 2.0
    is_edge = index < curves.n_edges
    edge, ball = np.where(is_edge, index, 0), np.where(is_edge, 0, index - curves.n_edges)

    def phi(x):
        with md.no_grad():
            return level_set(md.tensor(apex), md.tensor(x), curves.a[edge], curves.b[edge],
                             curves.centre[ball], curves.radius[ball], is_edge).data  # fmt: skip

    h = 1e-6
    expected = np.stack(
        [(phi(points + h * e) - phi(points - h * e)) / (2 * h) for e in np.eye(3)], axis=1
    )
    got = curves.gradient(apex, index, points)
    scale = np.abs(expected).max(axis=1, keepdims=True)
    error = np.abs(got - expected) / np.maximum(scale, 1e-3)  # relative to each row's size
    assert error.max() < 1e-6, error.max()


@pytest.mark.parametrize("gradient", ["replay", "tape"])
@pytest.mark.parametrize(
    "occluder, light", [("tall box", "area"), ("sphere", "area"), ("square", "point")]
)
def test_each_parameter_s_gradient_is_the_same_alone_or_with_every_other(occluder, light,
                                                                         gradient):  # fmt: skip
    """Each parameter of a shadowed floor differentiated alone, and with every other: the
    same gradient with both boundary terms. Alone, the secondary samples whose phi reads
    nothing differentiated are dropped before their radiance is computed
    (``secondary._moving``: the area light's position needs the samples whose x', x_k or
    curve is the light, not those of the box's shadow seen against the floor): a sample
    dropped wrongly would take its share of that parameter's gradient with it. (Not an
    emission: differentiated, it makes its mesh an emitter that next-event estimation
    picks, another estimator of the same image.)"""
    scene = shadowed_floor(occluder, light)
    weights = 1.0 + 0.5 * np.random.default_rng(2).standard_normal((8, 8, 3))

    def gradients(differentiated: list[md.Tensor]) -> list[np.ndarray]:
        for tensor in scene.parameters():
            tensor.requires_grad, tensor.grad = False, None
        for tensor in differentiated:
            tensor.requires_grad = True
        image = render_path(scene, spp=4, max_depth=3, seed=3, antialias="boundary",
                            gradient=gradient)  # fmt: skip
        md.sum(image * weights).backward()
        return [np.array(tensor.grad) for tensor in differentiated]

    tensors = [t for name, t in scene.named_parameters().items() if not name.endswith("emission")]
    every = gradients(tensors)
    for tensor, together in zip(tensors, every, strict=True):
        (alone,) = gradients([tensor])
        scale = max(np.abs(together).max(), 1e-300)
        np.testing.assert_allclose(alone, together, rtol=1e-12, atol=1e-12 * scale)
