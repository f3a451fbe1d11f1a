"""Issue 55, errors a user meets: each of these once failed deep inside the renderer or with
another argument's name; now each is a clear error naming the argument and what was
expected, or works as an autodiff user expects.

1. ``replay_gradient`` with a loss of shape (1,) (one element: a scalar, as for
   ``backward``) crashed after the gradient was computed.
2. A loss that does not read the image failed with ``NoneType * float``.
3. ``seed=2**64-1`` with the default ``seed_grad`` (seed + 1) blamed ``seed_grad``.
4. ``max_depth`` or ``rr_depth`` beyond int64 failed inside Numba.
5. Path records were sized by ``max_depth`` whatever Russian roulette did
   (``max_depth=10**6`` asked for gigabytes).
6. ``torch.func.hessian`` and ``jax.hessian`` met the framework's internals instead of the
   project's "no second derivatives".
7. A differentiated parameter the image cannot depend on got zeros on one route and "this
   tensor does not require grad" on another.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

import minidiff as md
import render
from render.path import render_path, replay_gradient
from render.path.sample.tracer import PathSampler
from render.path.twin import kernel
from render.scene.cornell import box_mesh, cornell_box
from render.scene.placement import placed
from tests.render_helpers import QUAD_FACES

OPTIONS = {"spp": 1, "max_depth": 3}


def box(albedo_grad: bool = True) -> render.Scene:
    """The 8x8 Cornell box, its floor's albedo requiring grad."""
    scene = cornell_box(8, 8)
    scene.objects[0].material.albedo.requires_grad = albedo_grad
    return scene


def _sum(image: md.Tensor) -> md.Tensor:
    return md.sum(image * image)


# -- 1. a one-element loss ---------------------------------------------------------------


def test_a_loss_of_shape_one_is_a_scalar():
    scalar, one = box(), box()
    value, _ = replay_gradient(scalar, _sum, **OPTIONS)
    value_one, _ = replay_gradient(one, lambda image: md.reshape(_sum(image), (1, 1)), **OPTIONS)
    assert isinstance(value_one, float) and value_one == value
    grad = scalar.objects[0].material.albedo.grad
    assert np.abs(grad).max() > 0
    np.testing.assert_array_equal(one.objects[0].material.albedo.grad, grad)


@pytest.mark.parametrize(
    ("loss", "got"),
    [(lambda image: image * 2.0, r"got shape \(8, 8, 3\)"), (lambda image: 1.0, "got float")],
)
def test_a_loss_of_several_values_is_refused_by_shape(loss, got):
    with pytest.raises(TypeError, match=r"replay_gradient: loss must return a minidiff tensor "
                       r"of one element .*" + got):  # fmt: skip
        replay_gradient(box(), loss, **OPTIONS)


# -- 2. a loss that does not read the image ----------------------------------------------


def test_a_loss_that_ignores_the_image_gives_zero_gradients():
    scene = box()
    value, image = replay_gradient(scene, lambda image: md.tensor(3.0), **OPTIONS)
    assert value == 3.0 and image.shape == (8, 8, 3)
    np.testing.assert_array_equal(scene.objects[0].material.albedo.grad, np.zeros(3))


def test_a_loss_of_the_parameters_alone_gets_their_gradient_and_zeros_through_the_image():
    """The loss reads a parameter, not the image (a regulariser alone): that parameter gets
    the loss's own derivative, another one zeros (it used to fail with NoneType * float)."""
    scene = box()
    albedo = scene.objects[0].material.albedo
    wall = scene.objects[2].material.albedo
    wall.requires_grad = True
    value, _ = replay_gradient(scene, lambda image: md.sum(albedo * 2.0), **OPTIONS)
    assert value == pytest.approx(2.0 * albedo.data.sum(), rel=1e-15)
    np.testing.assert_array_equal(albedo.grad, np.full(3, 2.0))
    np.testing.assert_array_equal(wall.grad, np.zeros(3))


# -- 3. the largest seed -----------------------------------------------------------------


def test_the_largest_seed_wraps_its_default_seed_grad():
    last, given = box(), box()
    replay_gradient(last, _sum, seed=2**64 - 1, **OPTIONS)
    replay_gradient(given, _sum, seed=2**64 - 1, seed_grad=0, **OPTIONS)
    grad = given.objects[0].material.albedo.grad
    np.testing.assert_array_equal(last.objects[0].material.albedo.grad, grad)
    with pytest.raises(ValueError, match=r"render: seed must be an integer in \[0, 2\*\*64\)"):
        replay_gradient(box(), _sum, seed=2**64, **OPTIONS)


# -- 4. depths beyond what the kernel counts ---------------------------------------------


@pytest.mark.parametrize(
    ("name", "value"),
    [("max_depth", 2**59 + 1), ("max_depth", 2**64), ("rr_depth", 2**63), ("rr_depth", 10**30)],
)
def test_a_depth_beyond_the_kernels_integers_is_refused_by_name(name, value):
    match = rf"render: {name} must be an integer in \[1, 2\*\*59\], got {value}"
    with pytest.raises(ValueError, match=match):
        render.render(box(False), integrator="path", spp=1, **{name: value})
    with pytest.raises(ValueError, match=match):
        replay_gradient(box(), _sum, spp=1, **{name: value})


# -- 5. memory by the paths' real lengths ------------------------------------------------


def _gradients(scene, names, **options):
    params = scene.named_parameters()
    for name in names:
        params[name].requires_grad, params[name].grad = True, None
    _sum(render_path(scene, spp=1, **options)).backward()
    return [params[name].grad for name in names]


@pytest.mark.parametrize(
    "names",
    [["objects[0].material.albedo"], ["objects[1].vertices", "objects[0].material.albedo"]],
    ids=["a material", "the vertices and a material"],
)
def test_the_largest_max_depth_costs_what_the_paths_need(names):
    """Russian roulette ends every path long before max_depth = 2**59: the image and the
    gradient are those of max_depth = 64 bit for bit (no path of 64 vertices: checked),
    where records sized by max_depth could not be allocated at all."""
    sampler = PathSampler(placed(box(False)), 1, 64, 5, 0)
    batch, _ = kernel.sample_paths(sampler, np.arange(64, dtype=np.int64))
    assert len(batch.vertices) < 64
    deep = _gradients(box(False), names, max_depth=2**59)
    short = _gradients(box(False), names, max_depth=64)
    for got, want in zip(deep, short, strict=True):
        assert np.abs(want).max() > 0
        np.testing.assert_array_equal(got, want)


def test_the_records_of_a_huge_max_depth_are_small():
    """max_depth = 10**6 asked for 10 GiB of records for 64 paths; now a few kilobytes per
    path (peak measured by tracemalloc, bound 16 MB), the records of max_depth = 64."""
    sampler = PathSampler(placed(box(False)), 1, 10**6, 5, 0)
    paths = np.arange(64, dtype=np.int64)
    kernel.sample_paths(sampler, paths)  # compiled and packed before measuring
    tracemalloc.start()
    try:
        batch, radiance = kernel.sample_paths(sampler, paths)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, peak
    short, short_radiance = kernel.sample_paths(PathSampler(sampler.scene, 1, 64, 5, 0), paths)
    np.testing.assert_array_equal(radiance, short_radiance)
    assert len(batch.vertices) == len(short.vertices)
    for a, b in zip(batch.vertices, short.vertices, strict=True):
        np.testing.assert_array_equal(a.rows, b.rows)
        np.testing.assert_array_equal(a.local, b.local)
        np.testing.assert_array_equal(a.next_pdf, b.next_pdf)


def closed_room() -> render.Scene:
    """The camera inside a closed box lit by a point light: no path ever leaves, so
    without Russian roulette every path has max_depth vertices."""
    camera = render.Camera((0.0, 0.0, 0.5), (0.0, 0.0, -1.0), fov=60, width=8, height=8)
    room = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), render.Material((0.6, 0.5, 0.4)))
    return render.Scene([room], [render.PointLight((0.0, 0.5, 0.0), 2.0)], camera)


def test_paths_longer_than_the_first_records():
    """40 vertices per path, more than the kernel first makes room for (``RECORD_ROWS``):
    the records are traced again deeper, the replay takes the paths in several segments
    (``window.SEGMENT`` depths each), and the gradient of a material and of the vertices is
    still the tape's (the reference's) to rounding."""
    from render.path.gradient import window

    assert kernel.RECORD_ROWS < 40 and 40 > 2 * window.SEGMENT
    names = ["objects[0].material.albedo", "objects[0].vertices"]
    options = {"max_depth": 40, "rr_depth": 41}
    sampler = PathSampler(placed(closed_room()), 1, 40, 41, 0)
    batch, _ = kernel.sample_paths(sampler, np.arange(64, dtype=np.int64))
    assert len(batch.vertices) == 40 and len(batch.vertices[-1].rows) == 64
    replayed = _gradients(closed_room(), names, **options)
    taped = _gradients(closed_room(), names, gradient="tape", **options)
    for got, want in zip(replayed, taped, strict=True):
        scale = np.abs(want).max()
        assert scale > 0
        assert np.abs(got - want).max() <= 1e-10 * scale


# -- 6. second derivatives through the bridges -------------------------------------------

BRIDGE_NAMES = ["lights[0].position", "objects[0].material.albedo"]
POSITION, ALBEDO = np.array([0.0, 1.0, 3.0]), np.array([0.7, 0.3, 0.3])


def test_torch_hessian_is_refused_with_the_projects_message():
    torch = pytest.importorskip("torch")
    import render.torch as rtorch

    f = rtorch.function(hidden_quad_scene(False), BRIDGE_NAMES)
    albedo = torch.tensor(ALBEDO)

    def loss(p):
        return (f(p, albedo) ** 2).sum()

    position = torch.tensor(POSITION)
    second = [
        torch.func.hessian(loss),
        torch.func.jacfwd(torch.func.jacfwd(loss)),
        lambda p: torch.func.jvp(torch.func.grad(loss), (p,), (torch.ones(3, dtype=p.dtype),)),
    ]
    for transform in second:
        with pytest.raises(RuntimeError, match="render.torch: .* no second derivatives"):
            transform(position)
    assert torch.func.grad(loss)(position).shape == (3,)  # the first derivative still works


@pytest.mark.parametrize("mode", ["reverse", "forward"])
def test_jax_hessian_is_refused_with_the_projects_message(mode):
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    import render.jax as rjax

    with jax.enable_x64(True):
        f = rjax.function(hidden_quad_scene(False), BRIDGE_NAMES, mode=mode)
        albedo = jnp.asarray(ALBEDO)

        def loss(p):
            return jnp.sum(f(p, albedo) ** 2)

        position = jnp.asarray(POSITION)
        for transform in (jax.hessian, lambda g: jax.jacfwd(jax.jacfwd(g))):
            with pytest.raises(ValueError, match="render.jax: .* no second derivatives"):
                transform(loss)(position)
        first = jax.grad if mode == "reverse" else jax.jacfwd
        assert first(loss)(position).shape == (3,)  # the first derivative still works


# -- 7. a parameter the image cannot depend on -------------------------------------------


def hidden_quad_scene(textured: bool) -> render.Scene:
    """A quad in view (textured: the direct renderer's tape route) and one behind the
    camera, whose parameters the image cannot depend on."""
    camera = render.Camera((0, 0, 4.0), (0, 0, 0), fov=40, width=8, height=8)
    texture = np.full((2, 2, 3), 0.5) if textured else None
    seen = render.Mesh(
        [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], QUAD_FACES,
        render.Material((0.5, 0.5, 0.5), texture=texture),
        uvs=[(0, 0), (1, 0), (1, 1), (0, 1)] if textured else None,
    )  # fmt: skip
    hidden = render.Mesh(
        [(-1, -1, 9), (1, -1, 9), (1, 1, 9), (-1, 1, 9)], QUAD_FACES,
        render.Material((0.2, 0.3, 0.4)),
    )  # fmt: skip
    return render.Scene([seen, hidden], [render.PointLight((0, 1, 3), 10.0)], camera)


ROUTES = {
    "direct": {},
    "path, replay": {"integrator": "path", "spp": 1},
    "path, tape": {"integrator": "path", "spp": 1, "gradient": "tape"},
}


@pytest.mark.parametrize("textured", [False, True])
@pytest.mark.parametrize("name", ["objects[1].vertices", "objects[1].material.albedo"])
@pytest.mark.parametrize("route", list(ROUTES))
def test_a_parameter_the_image_cannot_depend_on_gets_zeros(route, name, textured):
    """Alone, and beside a parameter that does move the image: zeros on every route (the
    direct renderer's compiled node and its tape; the path integrator's compiled replay,
    its replay on the tape and its tape), never "does not require grad"."""
    scene = hidden_quad_scene(textured)
    hidden = scene.named_parameters()[name]
    hidden.requires_grad = True
    md.sum(render.render(scene, **ROUTES[route])).backward()
    np.testing.assert_array_equal(hidden.grad, np.zeros(hidden.shape))
    hidden.grad = None
    intensity = scene.lights[0].intensity
    intensity.requires_grad = True
    md.sum(render.render(scene, **ROUTES[route])).backward()
    np.testing.assert_array_equal(hidden.grad, np.zeros(hidden.shape))
    assert np.abs(intensity.grad).max() > 0


def test_replay_gradient_gives_zeros_to_what_the_image_cannot_depend_on():
    scene = hidden_quad_scene(False)
    vertices = scene.objects[1].vertices
    vertices.requires_grad = True
    replay_gradient(scene, _sum, spp=1)
    np.testing.assert_array_equal(vertices.grad, np.zeros(vertices.shape))
