"""``render.jax``: the renderer as a JAX function (optional extra ``jax``).

    import jax, jax.numpy as jnp, render, render.jax
    jax.config.update("jax_enable_x64", True)     # the scene computes in float64
    f = render.jax.function(render.paper_scene(64, 64), ["lights[0].position"])
    loss = lambda p: jnp.mean((f(p) - target) ** 2)
    jax.jit(jax.grad(loss))(jnp.array([2.0, 5.0, 3.0]))

How two autodiff systems meet: JAX cannot trace NumPy code, so the render runs in a
``jax.pure_callback`` (JAX calls back into Python with concrete arrays, also under ``jit``)
and its derivative is declared with ``jax.custom_vjp``: the backward rule is another
callback, ``render.inverse.function.RenderFunction.vjp`` (one render recorded on minidiff's
tape and one ``backward``). JAX residuals must be arrays, so the backward renders again
rather than keeping the forward's tape: a gradient costs two renders and one backward.

* ``mode="reverse"`` (default): ``jax.grad``, ``jax.vjp``, ``jax.jacrev``. ``mode="forward"``:
  the derivative declared with ``jax.custom_jvp`` instead (minidiff's forward mode: one
  render with tangents, and one without for the image): ``jax.jvp``, ``jax.jacfwd``. JAX
  cannot transpose a callback, so each mode supports only its own direction (reverse mode
  of a "forward" function raises an error naming ``mode``).
* **Differentiable once**: the derivative is minidiff's tape, which JAX cannot see; a
  second derivative (``jax.hessian``, ``jax.grad`` of ``jax.grad``, ``jax.jvp`` of
  ``jax.grad``) raises the error ``SECOND_DERIVATIVES``, whatever the mode (every callback
  is a ``custom_jvp`` whose JVP refuses, ``_first_order``), not JAX's "Pure callbacks do
  not support JVP".
* ``jax.vmap`` works through ``vmap_method="sequential"``: the callback is called once per
  batch element, one render after the other.
* **dtypes**: values come and go in the function's dtype (``f.dtype``, float64 unless the
  scene is float32). float64 needs ``jax_enable_x64`` (JAX would otherwise turn every
  float64 array into float32): the call says so if it is off. A floating-point value of
  another dtype is an error naming its parameter, never a silent cast; integer and boolean
  values are constants (their cotangent is JAX's ``float0`` zero).
* Arrays are computed on the CPU (the renderer is NumPy and Numba).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import ShapedArray
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

import minidiff as md
from render.inverse.function import RenderFunction
from render.scene.scene import Scene

__all__ = ["function", "JaxRenderFunction"]

SECOND_DERIVATIVES = (
    "render.jax: the renderer's derivative is not differentiable again (it is minidiff's "
    "tape, which JAX cannot see): no second derivatives (jax.hessian, grad of grad, jvp "
    "of grad); differentiate the renderer once"
)


def function(
    scene: Scene | Sequence[Scene],
    parameters: str | md.Tensor | Sequence[str | md.Tensor],
    mode: str = "reverse",
    **render_kwargs: Any,
) -> JaxRenderFunction:
    """``render(scene, **render_kwargs)`` as a JAX function of the ``parameters`` (names
    such as ``"camera.position"``, or the scene's tensors), in that order, differentiable
    in ``mode`` "reverse" or "forward"; see ``render.inverse.function.RenderFunction`` for
    views and ``render_kwargs``."""
    return JaxRenderFunction(RenderFunction(scene, parameters, **render_kwargs), mode)


class JaxRenderFunction:
    """Call with one array per parameter (under ``jit``, ``grad``, ``vmap`` as any JAX
    function); returns the image, (H, W, 3) or (V, H, W, 3) for views. ``core`` is the
    ``RenderFunction``; ``names``, ``shapes``, ``dtype`` are its."""

    def __init__(self, core: RenderFunction, mode: str = "reverse") -> None:
        if mode not in ("reverse", "forward"):
            raise ValueError(f'render.jax: mode must be "reverse" or "forward", got {mode!r}')
        self.core, self.mode = core, mode
        self.names, self.shapes, self.dtype = core.names, core.shapes, np.dtype(core.dtype)
        self._image = jax.ShapeDtypeStruct(core.image_shape, self.dtype)
        self._render = _first_order(lambda *arrays: core(*map(np.asarray, arrays)), self._image)
        self._call = self._reverse() if mode == "reverse" else self._forward()

    def __repr__(self) -> str:
        return f"render.jax.{self.core!r} ({self.mode} mode)"

    def __call__(self, *values: Any) -> jax.Array:
        where = "render.jax"
        if self.dtype == np.float64 and not jax.config.read("jax_enable_x64"):
            raise TypeError(
                f"{where}: this function computes in float64 (the scene's parameters are "
                "float64) but jax_enable_x64 is off, so JAX would pass and return float32; "
                'run jax.config.update("jax_enable_x64", True) first (or build the scene '
                "in float32)"
            )
        if len(values) != len(self.names):
            raise TypeError(
                f"{where}: expected {len(self.names)} arrays ({', '.join(self.names)}), got "
                f"{len(values)}"
            )
        values = tuple(jnp.asarray(v) if not isinstance(v, jax.Array) else v for v in values)
        for name, shape, value in zip(self.names, self.shapes, values, strict=True):
            kind = np.dtype(value.dtype).kind
            if kind == "f" and value.dtype != self.dtype:
                raise TypeError(
                    f"{where}: {name} is {value.dtype} but this function computes in "
                    f"{self.dtype}; convert it explicitly (e.g. x.astype(jnp.{self.dtype}))"
                )
            if kind not in "fiub":
                raise TypeError(f"{where}: {name} must be real numbers, got {value.dtype}")
            if tuple(value.shape) != shape:
                raise ValueError(
                    f"{where}: {name} must have shape {shape}, got {tuple(value.shape)} "
                    "(batch with jax.vmap)"
                )
        return self._call(*values)

    def _primal(self, *values: jax.Array) -> jax.Array:
        """The image, by a callback into the renderer (no tape)."""
        return self._render(*values)

    def _reverse(self) -> Callable[..., jax.Array]:
        core = self.core

        @jax.custom_vjp
        def f(*values):
            return self._primal(*values)

        def fwd(*values):
            return self._primal(*values), values

        def bwd(values, d_image):
            floats = [np.dtype(v.dtype).kind == "f" for v in values]
            shapes = tuple(
                jax.ShapeDtypeStruct(v.shape, v.dtype) for v, fl in zip(values, floats, strict=True)
                if fl
            )  # fmt: skip

            def pullback(*arrays):
                grads = core.vjp([np.asarray(a) for a in arrays[:-1]], np.asarray(arrays[-1]))
                return tuple(g for g, fl in zip(grads, floats, strict=True) if fl)

            grads = iter(_first_order(pullback, shapes)(*values, d_image))
            return tuple(
                next(grads) if fl else np.zeros(v.shape, dtype=jax.dtypes.float0)
                for v, fl in zip(values, floats, strict=True)
            )

        f.defvjp(fwd, bwd)
        return f

    def _forward(self) -> Callable[..., jax.Array]:
        core, image = self.core, self._image

        @jax.custom_jvp
        def f(*values):
            return self._primal(*values)

        @f.defjvp
        def f_jvp(primals, tangents):
            n = len(primals)
            floats = [np.dtype(v.dtype).kind == "f" for v in primals]
            moving = [t for t, fl in zip(tangents, floats, strict=True) if fl]

            def push(*arrays):
                moves = iter(arrays[n:])
                directions = [np.asarray(next(moves)) if fl else None for fl in floats]
                return core.jvp([np.asarray(a) for a in arrays[:n]], directions)[1]

            # Not a bare callback: reverse mode would transpose it, and JAX's own error
            # ("Pure callbacks do not support transpose") names neither mode nor the fix.
            d_image = _tangent_p.bind(*primals, *moving, push=push, image=image)
            # The image by its own callback: under jax.jacfwd the tangents are batched and
            # the primals are not, and JAX needs an image that is not batched with them.
            return self._primal(*primals), d_image

        return f


def _first_order(callback: Callable, result: Any) -> Callable:
    """``jax.pure_callback(callback, result, *args)`` (``vmap_method="sequential"``) as a
    function whose derivative is refused with ``SECOND_DERIVATIVES``: the callbacks are the
    renderer and its derivatives, and only their first derivative exists (declared by
    ``custom_vjp`` or ``custom_jvp`` around them)."""

    @jax.custom_jvp
    def call(*args):
        return jax.pure_callback(callback, result, *args, vmap_method="sequential")

    @call.defjvp
    def _no_derivative(primals, tangents):
        raise ValueError(SECOND_DERIVATIVES)

    return call


def _no_second_derivative(primals, tangents, *, push, image):
    """The JVP of a ``mode="forward"`` function's tangent (``jax.jacfwd`` of ``jax.jacfwd``):
    a clear error."""
    raise ValueError(SECOND_DERIVATIVES)


# The tangent of a mode="forward" function as a primitive of its own, linear in the
# tangents: its value is the callback ``push`` (the primals and the tangents in, the image's
# tangent ``image`` out); vmap maps it one batch element after the other (``lax.map``, as
# the callback's "sequential"); its transpose, which reverse mode asks for, is an error
# naming ``mode`` (JAX has no public hook to give a callback a transpose that batches).
_tangent_p = Primitive("render_jax_forward_tangent")


def _tangent_impl(*arrays, push, image):
    return _first_order(push, image)(*arrays)


def _tangent_batch(args, dims, *, push, image):
    """vmap: ``lax.map`` over the batched arguments (batch axis first), the rest shared."""
    batched = [d is not None for d in dims]  # None: not mapped
    moved = [jnp.moveaxis(a, d, 0) if b else a for a, d, b in zip(args, dims, batched, strict=True)]

    def one(sliced):
        parts = iter(sliced)
        full = [next(parts) if b else a for a, b in zip(moved, batched, strict=True)]
        return _tangent_p.bind(*full, push=push, image=image)

    return jax.lax.map(one, [a for a, b in zip(moved, batched, strict=True) if b]), 0


def _no_reverse_mode(cotangent, *args, push, image):
    """The transpose of a ``mode="forward"`` function's tangent, which reverse mode
    (``jax.grad``, ``jax.vjp``, ``jax.jacrev``) asks for: a clear error."""
    raise ValueError(
        'render.jax: this function was made with mode="forward", which supports forward '
        "mode only (jax.jvp, jax.jacfwd, jax.linearize); for reverse mode (jax.grad, "
        'jax.vjp, jax.jacrev) make it with mode="reverse" (the default): '
        'render.jax.function(scene, parameters, mode="reverse")'
    )


_tangent_p.def_impl(_tangent_impl)
_tangent_p.def_abstract_eval(lambda *_, push, image: ShapedArray(image.shape, image.dtype))
mlir.register_lowering(_tangent_p, mlir.lower_fun(_tangent_impl, multiple_results=False))
batching.primitive_batchers[_tangent_p] = _tangent_batch
ad.primitive_transposes[_tangent_p] = _no_reverse_mode
ad.primitive_jvps[_tangent_p] = _no_second_derivative
