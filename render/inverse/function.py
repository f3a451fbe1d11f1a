"""The renderer as a plain function of arrays: what another autodiff system needs.

PyTorch, JAX or SciPy do not know minidiff's tape. What they can use is a function of plain
arrays with its derivative products beside it:

    f = RenderFunction(scene, ["lights[0].position", "objects[0].material.albedo"])
    image = f(position, albedo)                      # (H, W, 3) ndarray
    image, pullback = f.forward(position, albedo)    # the same, with the tape kept
    d_position, d_albedo = pullback(d_image)         # vector-Jacobian product (reverse)
    image, d_image = f.jvp((position, albedo), (v_position, v_albedo))  # forward mode

Each call renders a *copy* of the scene in which the exposed parameters are fresh leaf
tensors holding the given values; the scene itself is never modified. So calls are
independent of each other (two threads may call the same function; a pullback kept from an
earlier call still differentiates that call), and the rest of the scene stays shared and
constant. The copies use the scene's render cache (``render.scene.cache``): while only a
material is exposed, visibility is reused between calls exactly as when rendering the scene
itself.

One ``forward`` is one render recorded on the tape; its pullback is one ``backward`` of it:
the same derivative as ``render.render`` followed by ``Tensor.backward`` (no finite
differences). ``render.torch`` and ``render.jax`` wrap this class.

Conversions are explicit. The function computes in one float dtype, ``dtype``: that of the
scene's parameters (float64 unless the scene was built from float32 tensors). Floating-point
values of another dtype are refused, naming the parameter (no silent float32 <-> float64
cast). Integer and boolean values are accepted as constants: converted to ``dtype``, they
get no derivative (their pullback entry is None, their tangent must be None).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

import minidiff as md
from minidiff.tensor import as_tangent
from render.inverse.gradient_image import find_parameter
from render.renderer import render
from render.scene.scene import Scene
from render.scene.substitute import substituted

__all__ = ["RenderFunction"]


class RenderFunction:
    """``image = f(*values)``: ``render(scene, **render_kwargs)`` as a function of the
    values of chosen scene ``parameters``, with its vector-Jacobian and Jacobian-vector
    products.

    scene: a ``render.Scene``, or a list of views sharing the parameters (e.g.
        ``scene.with_camera(c)`` for several cameras): the image is then their stack,
        (V, H, W, 3), and every parameter must belong to all the views.
    parameters: the exposed parameters, in the order of the function's arguments: names
        from ``scene.named_parameters()`` (``"camera.position"``) or the scene's own
        tensors. A single name or tensor is a list of one.
    render_kwargs: passed on to ``render.render`` on every call (``antialias``, ``spp``,
        ``shadows``, ...; not ``return_info``).

    Attributes: ``names`` (the parameters' names), ``shapes`` (their shapes), ``dtype``
    (the float dtype of values and images), ``image_shape``.
    """

    def __init__(
        self,
        scene: Scene | Sequence[Scene],
        parameters: str | md.Tensor | Sequence[str | md.Tensor],
        **render_kwargs: Any,
    ) -> None:
        where = "RenderFunction"
        self.views, self.stacked = _as_views(scene, where)
        if "return_info" in render_kwargs:
            raise TypeError(f"{where}: return_info is not supported (the result is an array)")
        if isinstance(parameters, str | md.Tensor):
            parameters = [parameters]
        parameters = list(parameters)
        if not parameters:
            raise ValueError(f"{where}: parameters is empty; name at least one")
        found = [find_parameter(self.views[0], p, where) for p in parameters]
        self.names = tuple(name for name, _ in found)
        self._tensors = [t for _, t in found]
        if len({id(t) for t in self._tensors}) != len(self._tensors):
            raise ValueError(f"{where}: a parameter is listed twice in {list(self.names)}")
        for k, view in enumerate(self.views[1:], start=1):
            shared = {id(t) for t in view.parameters()}
            for name, t in found:
                if id(t) not in shared:
                    raise ValueError(
                        f"{where}: {name} is a parameter of view 0 but not of view {k}; with "
                        "several views, expose only parameters that all of them share"
                    )
        self.shapes = tuple(t.shape for t in self._tensors)
        self.dtype = np.result_type(*[t.dtype for v in self.views for t in v.parameters()])
        self.render_kwargs = dict(render_kwargs)
        camera = self.views[0].camera
        for k, view in enumerate(self.views):
            if (view.camera.height, view.camera.width) != (camera.height, camera.width):
                raise ValueError(
                    f"{where}: view {k} renders {view.camera.height}x{view.camera.width} "
                    f"but view 0 {camera.height}x{camera.width}; views must have one size"
                )
        single = (camera.height, camera.width, 3)
        self.image_shape = ((len(self.views),) if self.stacked else ()) + single

    def __repr__(self) -> str:
        return (
            f"RenderFunction({', '.join(self.names)} -> image {self.image_shape} "
            f"{self.dtype}, {self.render_kwargs})"
        )

    # -- checking values -------------------------------------------------------------------

    def check_values(self, values: Sequence[Any], where: str = "RenderFunction") -> list:
        """The values as ndarrays, checked: one per parameter, each of its parameter's shape,
        floating-point of ``dtype`` or integer/boolean; errors name the parameter."""
        if len(values) != len(self.names):
            raise TypeError(
                f"{where}: expected {len(self.names)} values ({', '.join(self.names)}), "
                f"got {len(values)}"
            )
        checked = []
        for name, shape, value in zip(self.names, self.shapes, values, strict=True):
            array = np.asarray(value)
            kind = array.dtype.kind
            if kind == "f" and array.dtype != self.dtype:
                raise TypeError(
                    f"{where}: {name} is {array.dtype} but this function computes in "
                    f"{self.dtype} (the dtype of the scene's parameters); convert it "
                    "explicitly, or build the scene from tensors of that dtype"
                )
            if kind not in "fiub":
                raise TypeError(
                    f"{where}: {name} must be a real number array, got dtype {array.dtype}"
                )
            if array.shape != shape:
                raise ValueError(f"{where}: {name} must have shape {shape}, got {array.shape}")
            if kind == "f" and not np.isfinite(array).all():
                raise ValueError(f"{where}: {name} contains NaN or infinite values")
            checked.append(array)
        return checked

    # -- the function and its derivatives -------------------------------------------------

    def __call__(self, *values: Any) -> np.ndarray:
        """The image for these parameter values, without recording a tape."""
        with md.no_grad():
            image = self._render(self._leaves(values, grad=False, where="RenderFunction"))
        return np.array(image.data)

    def forward(self, *values: Any) -> tuple[np.ndarray, Callable[[Any], tuple]]:
        """The image, and its pullback: ``pullback(d_image)`` is the tuple of
        d(sum(d_image * image)) / d value for each value (None for integer or boolean
        values), arrays of the values' shapes and ``dtype``. The pullback may be called
        once (it runs ``backward`` through this render's tape and frees it)."""
        where = "RenderFunction.forward"
        if not md.is_grad_enabled():
            raise RuntimeError(f"{where}: called under minidiff.no_grad(); nothing is recorded")
        leaves = self._leaves(values, grad=True, where=where)
        image = self._render(leaves)
        used = [False]

        def pullback(d_image: Any) -> tuple:
            if used[0]:
                raise RuntimeError(
                    "RenderFunction pullback: already called once for this forward (its tape "
                    "is freed); call forward again"
                )
            used[0] = True
            seed = self._image_array(d_image, "d_image", "RenderFunction pullback")
            if image.requires_grad:
                image.backward(seed)
            return tuple(
                None if not leaf.requires_grad
                else (leaf.grad if leaf.grad is not None else np.zeros(leaf.shape, self.dtype))
                for leaf in leaves
            )  # fmt: skip

        return np.array(image.data), pullback

    def vjp(self, values: Sequence[Any], d_image: Any) -> tuple:
        """Reverse mode in one call: ``forward(*values)`` then its pullback of ``d_image``."""
        return self.forward(*values)[1](d_image)

    def jvp(self, values: Sequence[Any], tangents: Sequence[Any]) -> tuple[np.ndarray, np.ndarray]:
        """Forward mode: the image and its derivative along ``tangents`` (one per value,
        arrays of the values' shapes; None for no motion, required for integer values),
        in one render carrying tangents (``minidiff.tangents``)."""
        where = "RenderFunction.jvp"
        leaves = self._leaves(values, grad=False, where=where)
        if len(tangents) != len(leaves):
            raise TypeError(f"{where}: expected {len(leaves)} tangents, got {len(tangents)}")
        directions = {}
        for name, leaf, kind, tangent in zip(
            self.names, leaves, self._kinds(values), tangents, strict=True
        ):
            if tangent is None:
                continue
            if kind != "f":
                raise TypeError(
                    f"{where}: {name} was given as an integer/boolean value (a constant); its "
                    "tangent must be None"
                )
            directions[leaf] = as_tangent(where, f"tangent of {name}", leaf, tangent)
        with md.tangents(directions):
            image = self._render(leaves)
        tangent = image.tangent
        if tangent is None:
            tangent = np.zeros(image.shape, self.dtype)
        return np.array(image.data), np.array(tangent)

    # -- inside ---------------------------------------------------------------------------

    def _kinds(self, values: Sequence[Any]) -> list[str]:
        return [np.asarray(v).dtype.kind for v in values]

    def _leaves(self, values: Sequence[Any], grad: bool, where: str) -> list[md.Tensor]:
        """Fresh leaf tensors holding the values in ``dtype`` (floating-point ones require
        grad if ``grad``)."""
        arrays = self.check_values(values, where)
        return [
            md.tensor(a.astype(self.dtype), requires_grad=grad and a.dtype.kind == "f")
            for a in arrays
        ]

    def _render(self, leaves: list[md.Tensor]) -> md.Tensor:
        """Render the views with the exposed parameters replaced by ``leaves``."""
        new = {id(t): leaf for t, leaf in zip(self._tensors, leaves, strict=True)}
        memo: dict[int, Any] = {}
        images = [render(substituted(view, new, memo), **self.render_kwargs) for view in self.views]
        return md.stack(images) if self.stacked else images[0]

    def _image_array(self, value: Any, what: str, where: str) -> np.ndarray:
        array = np.asarray(value)
        if array.dtype != self.dtype:
            raise TypeError(f"{where}: {what} must be {self.dtype}, got {array.dtype}")
        if array.shape != self.image_shape:
            raise ValueError(
                f"{where}: {what} must have the image's shape {self.image_shape}, got {array.shape}"
            )
        return array


def _as_views(scene: Any, where: str) -> tuple[list[Scene], bool]:
    """The list of views and whether the image stacks them (a list was given)."""
    if isinstance(scene, Scene):
        return [scene], False
    if isinstance(scene, list | tuple):
        if not scene:
            raise ValueError(f"{where}: the list of views is empty")
        for k, view in enumerate(scene):
            if not isinstance(view, Scene):
                raise TypeError(
                    f"{where}: views[{k}] must be a render.Scene, got {type(view).__name__}"
                )
        return list(scene), True
    raise TypeError(
        f"{where}: scene must be a render.Scene or a list of them, got {type(scene).__name__}"
    )
