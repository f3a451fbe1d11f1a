"""Gradient images: where in the picture a parameter acts.

``gradient_image(scene, parameter, direction)`` is the derivative of the rendered image
along one direction in one parameter's space, d image / d t of ``render(scene)`` with the
parameter at ``p + t * direction``: an (H, W, 3) array showing, pixel by pixel, how the
picture changes when the parameter moves that way. It is computed in forward mode
(``minidiff.tangents``) through the unchanged ``render.render``, in one pass costing a
small multiple of a plain render, instead of one reverse pass per pixel.

It is the derivative the renderer's reverse mode differentiates too: for any image loss L,
sum(dL/dI * gradient_image) equals the reverse-mode dL/dp . direction, with the same
treatment of visibility (constant, or blended across edges with ``antialias=True``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

import minidiff as md
from minidiff.tensor import as_tangent
from render.renderer import render
from render.scene.scene import Scene

__all__ = ["gradient_image", "find_parameter"]


def find_parameter(
    scene: Scene, parameter: md.Tensor | str, where: str = "gradient_image"
) -> tuple[str, md.Tensor]:
    """The (name, tensor) of one of ``scene``'s parameters, given as a Tensor of the scene
    (the very object) or as a name from ``scene.named_parameters()`` such as
    ``"lights[0].position"``. Anything else is a ValueError listing the names; errors
    start with ``where``."""
    named = scene.named_parameters()
    if isinstance(parameter, str):
        if parameter not in named:
            raise ValueError(
                f"{where}: the scene has no parameter {parameter!r}; its parameters "
                f"are {', '.join(named)}"
            )
        return parameter, named[parameter]
    if isinstance(parameter, md.Tensor):
        for name, t in named.items():
            if t is parameter:
                return name, t
        raise ValueError(
            f"{where}: parameter is a Tensor of shape {parameter.shape} that is not "
            f"one of the scene's parameters (pass the scene's own tensor, or one of the "
            f"names {', '.join(named)})"
        )
    raise TypeError(
        f"{where}: parameter must be a minidiff Tensor of the scene or a parameter "
        f"name (str), got {type(parameter).__name__}"
    )


def gradient_image(
    scene: Scene | Sequence[Scene],
    parameter: md.Tensor | str,
    direction: Any = None,
    **render_kwargs: Any,
) -> np.ndarray | list[np.ndarray]:
    """The derivative of ``render(scene, **render_kwargs)`` along ``direction`` in the space
    of one ``parameter`` (a Tensor of the scene, or a name such as ``"camera.position"``).

    direction: an array of the parameter's shape; the result is one (H, W, 3) image,
        d image / dt at t = 0 for the parameter moved to ``p + t * direction``. None: one
        image per component of the parameter (the derivative with respect to that
        component), stacked as (*parameter.shape, H, W, 3): one forward-mode render per
        component, so for large parameters (a mesh's vertices) prefer a direction.
    render_kwargs: passed on to ``render.render`` (``antialias``, ``spp``, ``shadows``, ...;
        not ``return_info``).

    The parameter is not changed and need not require grad. Pixels whose visibility a
    move would change show the renderer's derivative for fixed decisions, as reverse mode
    does (see ``render.render``). The dtype is the image's.

    Many views (a list of scenes sharing the parameter, ``Scene.with_camera``): the list of
    their gradient images, one per view.
    """
    if isinstance(scene, list | tuple):
        if not scene:
            raise ValueError("gradient_image: the list of views is empty")
        return [gradient_image(view, parameter, direction, **render_kwargs) for view in scene]
    if not isinstance(scene, Scene):
        raise TypeError(f"gradient_image: scene must be a render.Scene, got {type(scene).__name__}")
    if "return_info" in render_kwargs:
        raise TypeError("gradient_image: return_info is not supported (the result is an array)")
    name, tensor = find_parameter(scene, parameter)
    if direction is not None:
        what = f"direction (for {name})"
        return _along(
            scene, tensor, as_tangent("gradient_image", what, tensor, direction), render_kwargs
        )
    images = [
        _along(scene, tensor, basis, render_kwargs) for basis in _basis(tensor.shape, tensor.dtype)
    ]
    return np.stack(images).reshape(tensor.shape + images[0].shape)


def _basis(shape: tuple[int, ...], dtype) -> list[np.ndarray]:
    """The unit vectors of a parameter's space, each an array of ``shape``."""
    size = int(np.prod(shape, dtype=np.int64))
    return [np.eye(1, size, k, dtype=dtype).reshape(shape) for k in range(size)]


def _along(scene: Scene, tensor: md.Tensor, direction: np.ndarray, render_kwargs) -> np.ndarray:
    """One forward-mode render: the tangent of the image for ``tensor``'s ``direction``."""
    with md.tangents({tensor: direction}):
        image = render(scene, **render_kwargs)
    if image.tangent is None:  # nothing in the image depends on the parameter
        return np.zeros(image.shape, dtype=image.dtype)
    return np.array(image.tangent)
