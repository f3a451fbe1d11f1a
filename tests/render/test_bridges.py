"""The renderer as a function of arrays (``RenderFunction``) and its PyTorch and JAX
bridges: the same gradient as minidiff's own, under every transform the bridges promise."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.inverse.function import RenderFunction

torch = pytest.importorskip("torch")
jax = pytest.importorskip("jax")
jnp = pytest.importorskip("jax.numpy")
import render.jax as rjax  # noqa: E402
import render.torch as rtorch  # noqa: E402

NAMES = ["lights[0].position", "objects[0].material.albedo", "camera.position"]
VALUES = [np.array([2.0, 5.0, 3.0]), np.array([0.7, 0.3, 0.3]), np.array([3.0, 2.0, 5.0])]
SIZE = 16


def _scene(size: int = SIZE, **kwargs) -> render.Scene:
    return render.paper_scene(size, size, ground=True, **kwargs)


def _target(size: int = SIZE) -> np.ndarray:
    """A target image that is not the scene's render: a different light and albedo."""
    scene = _scene(size, light_position=(1.0, 4.0, 2.0), albedo=(0.3, 0.6, 0.4))
    return render.render(scene).data


def _minidiff_grads(seed: np.ndarray, antialias) -> list[np.ndarray]:
    """The reference: render the scene with requires_grad leaves and backward ``seed``."""
    leaves = [md.tensor(v, requires_grad=True) for v in VALUES]
    scene = _scene(light_position=leaves[0], albedo=leaves[1], camera_position=leaves[2])
    render.render(scene, antialias=antialias).backward(seed)
    return [leaf.grad for leaf in leaves]


def _close(a, b, rel=1e-12) -> None:
    a, b = np.asarray(a), np.asarray(b)
    scale = max(np.abs(b).max(), np.finfo(np.float64).tiny)
    assert np.abs(a - b).max() <= rel * scale, (a, b)


# -- the framework-neutral core ---------------------------------------------------------


@pytest.mark.parametrize("antialias", [False, "pairs", "boundary"])
def test_core_vjp_is_minidiffs_gradient(antialias):
    f = RenderFunction(_scene(), NAMES, antialias=antialias)
    seed = np.random.default_rng(1).normal(size=f.image_shape)
    image, pullback = f.forward(*VALUES)
    for got, want in zip(pullback(seed), _minidiff_grads(seed, antialias), strict=True):
        _close(got, want)
    with md.no_grad():
        _close(image, render.render(_scene(), antialias=antialias).data)
    with pytest.raises(RuntimeError, match="already called once"):
        pullback(seed)


def test_core_jvp_is_the_dot_product_of_the_vjp():
    f = RenderFunction(_scene(), NAMES, antialias="boundary")
    rng = np.random.default_rng(2)
    seed = rng.normal(size=f.image_shape)
    directions = [rng.normal(size=v.shape) for v in VALUES]
    image, tangent = f.jvp(VALUES, directions)
    grads = f.vjp(VALUES, seed)
    _close(image, f(*VALUES))
    _close(
        (seed * tangent).sum(), sum((g * d).sum() for g, d in zip(grads, directions, strict=True))
    )
    with pytest.raises(TypeError, match="expected 3 tangents"):
        f.jvp(VALUES, directions[:2])


@settings(max_examples=8)
@given(
    st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3),
    st.lists(st.floats(0.1, 0.9), min_size=3, max_size=3),
    st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6),
)
def test_core_jvp_matches_central_differences(light_shift, albedo, direction):
    """Light position and albedo move no silhouette: the image is smooth in them (as long as
    no sample flips in or out of shadow, which the step is far too small for here)."""
    f = RenderFunction(_scene(), NAMES[:2])
    values = [VALUES[0] + np.array(light_shift), np.array(albedo)]
    moves = [np.array(direction[:3]), np.array(direction[3:])]
    h = 1e-6
    plus = f(*[v + h * d for v, d in zip(values, moves, strict=True)])
    minus = f(*[v - h * d for v, d in zip(values, moves, strict=True)])
    numeric = (plus - minus) / (2 * h)
    _, tangent = f.jvp(values, moves)
    assert np.abs(tangent - numeric).max() <= 1e-6 * max(np.abs(numeric).max(), 1e-3)


def test_core_views_stack_and_sum():
    scene = _scene()
    second = scene.with_camera(
        render.Camera.from_focal_length(
            50.0, position=(-3, 2, 5), look_at=(0, 0, 0), width=SIZE, height=SIZE
        )
    )
    f = RenderFunction([scene, second], NAMES[:2])
    assert f.image_shape == (2, SIZE, SIZE, 3)
    seed = np.random.default_rng(3).normal(size=f.image_shape)
    both = f.vjp(VALUES[:2], seed)
    one = RenderFunction(scene, NAMES[:2]).vjp(VALUES[:2], seed[0])
    two = RenderFunction(second, NAMES[:2]).vjp(VALUES[:2], seed[1])
    for b, x, y in zip(both, one, two, strict=True):
        _close(b, x + y)
    with pytest.raises(ValueError, match="camera.position is a parameter of view 0 but not"):
        RenderFunction([scene, second], ["camera.position"])


def test_core_leaves_the_scene_alone_and_is_independent_between_calls():
    scene = _scene()
    before = {name: t.data.copy() for name, t in scene.named_parameters().items()}
    f = RenderFunction(scene, NAMES[:2])
    first_image, first_pullback = f.forward(*VALUES[:2])
    moved = [VALUES[0] + 1.0, VALUES[1] * 0.5]
    f.forward(*moved)  # a later call must not change the first one's tape
    seed = np.ones(f.image_shape)
    _close(first_pullback(seed)[1], RenderFunction(_scene(), NAMES[1]).vjp([VALUES[1]], seed)[0])
    for name, t in scene.named_parameters().items():
        np.testing.assert_array_equal(t.data, before[name], err_msg=name)
        assert t.grad is None


def test_core_from_threads():
    f = RenderFunction(_scene(), NAMES, antialias="boundary")
    seed = np.random.default_rng(4).normal(size=f.image_shape)
    values = [[v + 0.05 * k for v in VALUES] for k in range(4)]
    serial = [f.vjp(v, seed) for v in values]
    results: dict[int, tuple] = {}

    def work(k):
        results[k] = f.vjp(values[k], seed)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k in range(4):
        for a, b in zip(results[k], serial[k], strict=True):
            np.testing.assert_array_equal(a, b)


def test_core_integer_values_are_constants():
    f = RenderFunction(_scene(), NAMES[:2])
    grads = f.vjp([np.array([2, 5, 3]), VALUES[1]], np.ones(f.image_shape))
    assert grads[0] is None and grads[1].shape == (3,)
    _close(f(np.array([2, 5, 3]), VALUES[1]), f(*VALUES[:2]))
    with pytest.raises(TypeError, match="its tangent must be None"):
        f.jvp([np.array([2, 5, 3]), VALUES[1]], [np.ones(3), None])


def test_core_errors_name_the_parameter():
    f = RenderFunction(_scene(), NAMES[:2])
    with pytest.raises(TypeError, match=r"lights\[0\].position is float32 but this function"):
        f(VALUES[0].astype(np.float32), VALUES[1])
    with pytest.raises(ValueError, match=r"material.albedo must have shape \(3,\), got \(2,\)"):
        f(VALUES[0], VALUES[1][:2])
    with pytest.raises(ValueError, match=r"lights\[0\].position contains NaN"):
        f(np.array([np.nan, 5.0, 3.0]), VALUES[1])
    with pytest.raises(TypeError, match="expected 2 values"):
        f(VALUES[0])
    with pytest.raises(TypeError, match="must be a real number array"):
        f(VALUES[0], np.array(["a", "b", "c"]))
    with pytest.raises(ValueError, match="RenderFunction: the scene has no parameter 'light'"):
        RenderFunction(_scene(), ["light"])
    with pytest.raises(ValueError, match="listed twice"):
        RenderFunction(_scene(), [NAMES[0], NAMES[0]])
    with pytest.raises(TypeError, match="d_image must be float64"):
        f.vjp(VALUES[:2], np.ones(f.image_shape, np.float32))
    with pytest.raises(ValueError, match="d_image must have the image's shape"):
        f.vjp(VALUES[:2], np.ones((3, 3, 3)))


def _float32_scene() -> render.Scene:
    leaves = {
        k: md.tensor(np.asarray(v, np.float32))
        for k, v in dict(light_position=(2, 5, 3), light_intensity=100.0, albedo=(0.7, 0.3, 0.3),
                         camera_position=(3, 2, 5), look_at=(0, 0, 0)).items()
    }  # fmt: skip
    scene = render.paper_scene(SIZE, SIZE, **leaves)
    for t in scene.parameters():  # the camera's up and fov, the background
        t.data = t.data.astype(np.float32)
    return scene


def test_core_float32_scene_computes_in_float32():
    f = RenderFunction(_float32_scene(), NAMES[:1])
    assert f.dtype == np.float32
    image = f(VALUES[0].astype(np.float32))
    assert image.dtype == np.float32
    (grad,) = f.vjp([VALUES[0].astype(np.float32)], np.ones(f.image_shape, np.float32))
    assert grad.dtype == np.float32
    with pytest.raises(TypeError, match="is float64 but this function computes in float32"):
        f(VALUES[0])


# -- PyTorch ----------------------------------------------------------------------------


def _torch_values(requires_grad=True):
    return [torch.tensor(v, dtype=torch.float64, requires_grad=requires_grad) for v in VALUES]


@pytest.mark.parametrize("antialias", [False, "boundary"])
def test_torch_autograd_equals_minidiff(antialias):
    f = rtorch.function(_scene(), NAMES, antialias=antialias)
    target = torch.from_numpy(_target())
    values = _torch_values()
    loss = ((f(*values) - target) ** 2).mean()
    loss.backward()
    image = f(*[v.detach() for v in values]).numpy()
    seed = 2.0 * (image - target.numpy()) / image.size
    for v, want in zip(values, _minidiff_grads(seed, antialias), strict=True):
        assert v.grad.dtype == torch.float64
        _close(v.grad.numpy(), want)


def test_torch_gradcheck_and_torch_func():
    f = rtorch.function(_scene(8), NAMES[:2])
    values = _torch_values()[:2]
    assert torch.autograd.gradcheck(f, tuple(values), eps=1e-6, atol=1e-7, rtol=1e-5)
    # torch.func: grad, jvp, vmap (forward and setup_context are kept apart for these)
    target = torch.from_numpy(_target(8))

    def loss(p, a):
        return ((f(p, a) - target) ** 2).mean()

    plain = [v.detach() for v in values]
    grads = torch.func.grad(loss, argnums=(0, 1))(*plain)
    a, b = values
    loss(a, b).backward()
    for g, v in zip(grads, values, strict=True):
        _close(g.numpy(), v.grad.numpy())
    direction = torch.tensor([0.3, -1.0, 0.5], dtype=torch.float64)
    _, tangent = torch.func.jvp(lambda p: loss(p, plain[1]), (plain[0],), (direction,))
    _close(tangent.numpy(), (grads[0] @ direction).numpy(), rel=1e-10)
    positions = torch.tensor(
        [[2.0, 5.0, 3.0], [2.5, 5.0, 3.0], [1.0, 4.0, 3.0]], dtype=torch.float64
    )
    mapped = torch.func.vmap(lambda p: f(p, plain[1]))(positions)
    looped = torch.stack([f(p, plain[1]) for p in positions])
    assert torch.equal(mapped, looped)
    batched = f(positions, plain[1])  # a leading batch dimension loops the same way
    assert torch.equal(batched, looped)


def test_torch_gradcheck_with_boundary_antialiasing():
    """With antialias="boundary" a mixed pixel's image is the mean of the 16 samples its
    interior derivative comes from (``render.edges.interior``), so gradcheck passes for the
    parameters that move no edge: an albedo, the light's intensity and colour, on a 12x12
    teapot whose silhouette and shadow on the ground cross mixed pixels. (Its image was
    the centre sample, its derivative the 16 samples' mean: gradcheck failed for all
    three.) Fast mode (random projections of the Jacobian): a full check costs a render
    per pixel."""
    from render.edges.interior import mixed_pixels
    from render.scene.cache import RenderCache
    from render.trace.visibility import trace_visibility

    scene = _scene(12)
    seen = trace_visibility(scene, RenderCache(), True, 1, True)
    pixels, samples = mixed_pixels(scene, seen, 1)
    assert len(pixels) > 5 and not samples.lit[0].all()  # some samples hit in shadow
    names = ["objects[0].material.albedo", "lights[0].intensity", "lights[0].color"]
    f = rtorch.function(scene, names, antialias="boundary")
    values = [[0.7, 0.3, 0.3], 100.0, [1.0, 0.9, 0.8]]
    values = tuple(torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in values)
    assert torch.autograd.gradcheck(f, values, eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)


def test_torch_func_jacobians_and_batched_gradients_equal_loops():
    """jacrev, jacfwd and vmap(grad(f)) raised "You tried to vmap over _Pull (_Push), but
    it does not have vmap support": the derivatives' operations now loop under vmap, and
    give what plain loops of torch.autograd.grad give."""
    f = rtorch.function(_scene(8), NAMES[:2])
    p, a = (v.detach() for v in _torch_values()[:2])

    def pixels(p, a):  # a few outputs: a Jacobian costs a render per row
        return f(p, a)[::3, ::3, 0].reshape(-1)

    def loss(p, a):
        return (f(p, a) ** 2).mean()

    rows = []
    for k in range(9):
        leaves = [p.clone().requires_grad_(), a.clone().requires_grad_()]
        rows.append(torch.autograd.grad(pixels(*leaves)[k], leaves))
    looped = [torch.stack([row[i] for row in rows]) for i in range(2)]
    for got, want in zip(torch.func.jacrev(pixels, argnums=(0, 1))(p, a), looped, strict=True):
        assert got.shape == (9, 3) and np.abs(want.numpy()).max() > 0
        _close(got.numpy(), want.numpy())
    for got, want in zip(torch.func.jacfwd(pixels, argnums=(0, 1))(p, a), looped, strict=True):
        _close(got.numpy(), want.numpy(), rel=1e-10)  # forward vs reverse mode: rounding

    positions = torch.tensor([[2.0, 5.0, 3.0], [2.5, 5.0, 3.0], [1.0, 4.0, 3.0]], dtype=p.dtype)
    mapped = torch.func.vmap(torch.func.grad(loss), in_dims=(0, None))(positions, a)
    for row, position in zip(mapped, positions, strict=True):
        leaf = position.clone().requires_grad_()
        (want,) = torch.autograd.grad(loss(leaf, a), [leaf])
        _close(row.numpy(), want.numpy())


def test_torch_scalar_parameter_of_shape_1_is_refused_as_ambiguous():
    """A (1,) value of a scalar parameter was read as a batch of one: the image got a
    leading 1 (and broadcast silently against an (H, W, 3) target)."""
    f = rtorch.function(_scene(8), ["lights[0].intensity"])
    with pytest.raises(ValueError, match=r"lights\[0\].intensity is a scalar parameter but was "
                       r"given shape \(1,\)"):  # fmt: skip
        f(torch.tensor([10.0], dtype=torch.float64))
    one = f(torch.tensor(10.0, dtype=torch.float64))
    assert one.shape == (8, 8, 3)
    two = f(torch.tensor([10.0, 20.0], dtype=torch.float64))  # unambiguous: a batch
    assert two.shape == (2, 8, 8, 3) and torch.equal(two[0], one)
    mapped = torch.func.vmap(f)(torch.tensor([10.0], dtype=torch.float64))  # a batch of one
    assert torch.equal(mapped, one[None])


def test_torch_float32_scene_takes_and_gives_float32():
    f = rtorch.function(_float32_scene(), NAMES[:1], antialias="boundary")
    position = torch.tensor([2.0, 5.0, 3.0], requires_grad=True)  # float32
    image = f(position)
    assert image.dtype == torch.float32 and f.dtype == torch.float32
    image.sum().backward()
    assert position.grad.dtype == torch.float32 and torch.isfinite(position.grad).all()
    (want,) = RenderFunction(_float32_scene(), NAMES[:1], antialias="boundary").vjp(
        [VALUES[0].astype(np.float32)], np.ones((SIZE, SIZE, 3), np.float32)
    )
    np.testing.assert_array_equal(position.grad.numpy(), want)
    with pytest.raises(TypeError, match="is torch.float64 but this function computes in"):
        f(position.double())


def test_torch_conversions_are_explicit():
    f = rtorch.function(_scene(), NAMES[:2])
    position, albedo = _torch_values()[:2]
    with pytest.raises(TypeError, match=r"lights\[0\].position is torch.float32"):
        f(position.float(), albedo)
    with pytest.raises(ValueError, match=r"albedo must have shape \(3,\)"):
        f(position, albedo[:2])
    with pytest.raises(TypeError, match="must be a torch.Tensor"):
        f(VALUES[0], albedo)
    with pytest.raises(ValueError, match="has a batch of 2, another value 3"):
        f(position.expand(3, 3), albedo.expand(2, 3))
    image = f(torch.tensor([2, 5, 3]), albedo)  # an integer tensor: a constant
    assert image.dtype == torch.float64
    image.sum().backward()
    assert albedo.grad is not None
    # differentiable once: a second derivative is refused, never silently zero
    (g,) = torch.autograd.grad((f(position, albedo) ** 2).sum(), [albedo], create_graph=True)
    with pytest.raises(RuntimeError, match="not differentiable again"):
        g.sum().backward()

    def loss(p):
        return (f(p, albedo.detach()) ** 2).sum()

    with pytest.raises(RuntimeError, match="not differentiable again"):
        torch.func.grad(lambda p: torch.func.grad(loss)(p).sum())(position.detach())


# -- JAX --------------------------------------------------------------------------------


def test_jax_grad_jit_vmap_equal_minidiff():
    target = _target()
    with jax.enable_x64(True):
        f = rjax.function(_scene(), NAMES, antialias="boundary")
        values = [jnp.asarray(v) for v in VALUES]

        def loss(*values):
            return jnp.mean((f(*values) - target) ** 2)

        argnums = tuple(range(len(values)))
        grads = jax.grad(loss, argnums)(*values)
        jitted = jax.jit(jax.grad(loss, argnums))(*values)
        image = np.asarray(f(*values))
        seed = 2.0 * (image - target) / image.size
        for g, j, want in zip(grads, jitted, _minidiff_grads(seed, "boundary"), strict=True):
            assert g.dtype == jnp.float64
            _close(np.asarray(g), want)
            _close(np.asarray(j), want)
        positions = jnp.array([[2.0, 5.0, 3.0], [2.5, 5.0, 3.0], [1.0, 4.0, 3.0]])
        mapped = jax.vmap(lambda p: f(p, values[1], values[2]))(positions)
        looped = jnp.stack([f(p, values[1], values[2]) for p in positions])
        np.testing.assert_array_equal(mapped, looped)
        per_row = jax.jit(jax.vmap(jax.grad(loss), in_axes=(0, None, None)))(positions, *values[1:])
        for k in range(3):
            np.testing.assert_array_equal(per_row[k], jax.grad(loss)(positions[k], *values[1:]))


def test_jax_forward_mode():
    with jax.enable_x64(True):
        reverse = rjax.function(_scene(), NAMES[:2])
        forward = rjax.function(_scene(), NAMES[:2], mode="forward")
        p, a = (jnp.asarray(v) for v in VALUES[:2])
        direction = jnp.array([0.3, -1.0, 0.5])
        image, tangent = jax.jvp(lambda p: forward(p, a), (p,), (direction,))
        np.testing.assert_array_equal(image, reverse(p, a))
        _, want = RenderFunction(_scene(), NAMES[:2]).jvp(VALUES[:2], [np.asarray(direction), None])
        _close(np.asarray(tangent), want)
        jac_fwd = jax.jacfwd(lambda p: jnp.mean(forward(p, a)))(p)
        jac_rev = jax.jacrev(lambda p: jnp.mean(reverse(p, a)))(p)
        _close(np.asarray(jac_fwd), np.asarray(jac_rev))


def test_jax_reverse_mode_of_a_forward_function_names_mode():
    """JAX said "Pure callbacks do not support transpose" without naming mode or the fix;
    forward mode (jvp, jacfwd, also jitted and under vmap) is unchanged."""
    with jax.enable_x64(True):
        forward = rjax.function(_scene(), NAMES[:2], mode="forward")
        p, a = (jnp.asarray(v) for v in VALUES[:2])

        def loss(p):
            return jnp.mean(forward(p, a))

        match = r'mode="forward", which supports forward mode only.*mode="reverse"'
        for reverse in (jax.grad, jax.jacrev, lambda g: jax.jit(jax.grad(g))):
            with pytest.raises(ValueError, match=match):
                reverse(loss)(p)
        with pytest.raises(ValueError, match=match):
            jax.vjp(lambda p: forward(p, a), p)[1](jnp.ones((SIZE, SIZE, 3)))
        with pytest.raises(ValueError, match=match):
            jax.vmap(jax.grad(loss))(jnp.stack([p, p + 0.1]))
        directions = jnp.eye(3)
        mapped = jax.jit(jax.vmap(lambda d: jax.jvp(lambda p: forward(p, a), (p,), (d,))[1]))
        looped = [jax.jvp(lambda p: forward(p, a), (p,), (d,))[1] for d in directions]
        np.testing.assert_array_equal(mapped(directions), jnp.stack(looped))


def test_jax_conversions_are_explicit():
    f = rjax.function(_scene(), NAMES[:2])
    with jax.enable_x64(False), pytest.raises(TypeError, match="jax_enable_x64 is off"):
        f(jnp.array([2.0, 5.0, 3.0]), jnp.array([0.7, 0.3, 0.3]))
    with jax.enable_x64(True):
        p, a = (jnp.asarray(v) for v in VALUES[:2])
        with pytest.raises(TypeError, match=r"lights\[0\].position is float32"):
            f(p.astype(jnp.float32), a)
        with pytest.raises(ValueError, match=r"albedo must have shape \(3,\), got \(2,\)"):
            f(p, a[:2])
        grad = jax.grad(lambda a: jnp.mean(f(jnp.array([2, 5, 3]), a)))(a)  # int: a constant
        assert grad.shape == (3,) and np.all(np.isfinite(grad))
        # first-order only: the backward's callback refuses to be differentiated
        with pytest.raises(ValueError, match="no second derivatives"):
            jax.grad(lambda a: jax.grad(lambda a: jnp.sum(f(p, a) ** 2))(a).sum())(a)
    with pytest.raises(ValueError, match="mode must be"):
        rjax.function(_scene(), NAMES[:1], mode="sideways")
