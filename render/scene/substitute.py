"""A scene with some of its tensors replaced: the same scene graph, other values.

Used where a render must see parameters other than the scene's own tensors: the bridges to
other frameworks (``render.inverse.function``: the framework's arrays in place of the
parameters) and the path integrator's replayed backward (``render.path.integrator``: the
values at the time of the render, copied, so that an edit before ``backward`` does not
change the gradient of the image that was rendered).
"""

from __future__ import annotations

import copy
from typing import Any

import minidiff as md
from render.scene.cache import cache_for, share_cache
from render.scene.scene import Scene


def substituted(
    scene: Scene, new: dict[int, md.Tensor], memo: dict[int, Any], copies: bool = False
) -> Scene:
    """A copy of ``scene`` in which every tensor whose id is a key of ``new`` is replaced by
    its value, wherever it occurs (a tensor shared by two owners stays shared). Owners
    (camera, lights, objects, materials, transforms) are shallow copies, memoised in
    ``memo`` so that views sharing an object share its copy; the copy uses the scene's
    render cache. The copy is validated as any scene is, unless ``copies``: ``scene`` was
    validated and every replacement is a copy of the tensor it replaces (the same values),
    which the same checks would accept again (the path integrator's frozen scene and its
    replay's leaves: 1.2 ms a scene for the Cornell box)."""

    background = new.get(id(scene.background), scene.background)
    out = Scene(
        [_owner(o, new, memo) for o in scene.objects],
        [_owner(light, new, memo) for light in scene.lights],
        _owner(scene.camera, new, memo),
        background,
        _checked=copies,
    )
    share_cache(out, cache_for(scene, True))
    return out


def _owner(obj, new: dict[int, md.Tensor], memo: dict[int, Any]):
    """``obj``'s copy for ``substituted`` (memoised), its material and transform copied too.
    (A function of its own, not a recursive closure: that would be a reference cycle keeping
    every copied tensor alive until the cyclic garbage collector runs.)"""
    if obj is None:
        return None
    if id(obj) not in memo:
        out = copy.copy(obj)
        for f in obj.FIELDS:
            t = getattr(obj, f.name)
            if t is not None and id(t) in new:
                setattr(out, f.name, new[id(t)])
        for part in ("material", "transform"):
            if hasattr(obj, part):
                setattr(out, part, _owner(getattr(obj, part), new, memo))
        if hasattr(obj, "material"):  # an object: caches keyed on it know the copy
            out.source_id = getattr(obj, "source_id", id(obj))
        memo[id(obj)] = out
    return memo[id(obj)]
