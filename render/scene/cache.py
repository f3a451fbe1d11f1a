"""Reuse between renders: each stage's result, kept with the values it was computed from.

While an inverse problem optimises only a material, the geometry, the camera and the lights
keep their values, so the BVH, the camera rays' hits and the shadow rays of the previous
render are still right; while it optimises a light, each object's hit points and normals
are. ``render(..., reuse_visibility=True)`` (the default) keeps them in a ``RenderCache``
per scene and reuses a result only when the *values* it depends on compare equal (copies
are kept, since optimisers edit parameters in place): a cache can never serve stale
results.

Each stage's key is a list of arrays, written by one function below (``camera_key``,
``light_key``, ``surface_key``; the geometry's key is the primitive arrays themselves).
A stage that builds on another adds the earlier stage's *stamp* to its key: a number that
changes whenever that stage is recomputed.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable, Hashable
from typing import Any

import numpy as np

from render.scene.scene import Camera, Light, Mesh, Scene, Sphere


def same(key_a: list[np.ndarray] | None, key_b: list[np.ndarray]) -> bool:
    """True if two keys hold arrays of equal shapes and values, pairwise."""
    return (
        key_a is not None
        and len(key_a) == len(key_b)
        and all(
            a.shape == b.shape and np.array_equal(a, b) for a, b in zip(key_a, key_b, strict=True)
        )
    )


class RenderCache:
    """Stage results of earlier renders of one scene: slot -> (key, value, stamp).

    Guarded: one lock per cache, held while an entry is looked up or stored, never while a
    stage is computed. A render's two threads (the boundary term's points found beside
    the mixed pixels, ``minidiff.threads.beside``) and two threads rendering the same scene
    therefore never wait for each other's computations (held during them, the lock made
    the mixed pixels wait for the curves' tables of a moving mesh: 0.6 s of a 1.9 s
    gradient of a 160k-face sphere), and none sees another's half-stored entry. Two
    threads that need the same missing stage at once may both compute it (the same
    value): the first stored is kept, and both get it. The values are shared read-only: no
    stage writes into a value it got here."""

    def __init__(self) -> None:
        self._entries: dict[Hashable, tuple[list[np.ndarray], Any, np.ndarray]] = {}
        self._computed = 0
        self._lock = threading.Lock()

    def get(
        self, slot: Hashable, key: list[np.ndarray], compute: Callable[[], Any]
    ) -> tuple[Any, np.ndarray]:
        """The value in ``slot`` if it was computed for an equal ``key``, else ``compute()``
        (stored for next time). Also returns the value's stamp, (1,) int64, for the keys of
        the stages that build on it."""
        with self._lock:
            entry = self._entries.get(slot)
            if entry is not None and same(entry[0], key):
                return entry[1], entry[2]
        value = compute()  # unlocked: it may take long, and look up what it builds on
        with self._lock:
            entry = self._entries.get(slot)
            if entry is None or not same(entry[0], key):  # else another thread's came first
                self._computed += 1
                entry = (key, value, np.array([self._computed]))
                self._entries[slot] = entry
            return entry[1], entry[2]

    def put(self, slot: Hashable, key: list[np.ndarray], value: Any) -> None:
        """Store ``value`` in ``slot`` for ``key``, in place of what was there: a stage that
        grows its value while the key holds (``render.edges.interior``'s first hits of the
        pixels it has seen) stores a new value, never writes into the one it got."""
        with self._lock:
            self._computed += 1
            self._entries[slot] = (key, value, np.array([self._computed]))

    def latest(self, slot: Hashable) -> Any:
        """The value last stored in ``slot`` whatever its key (None if none): what a stage
        may start from when its key has changed (the BVH refitted to moved vertices,
        ``render.trace.accel.updated``). Read-only, as every value here."""
        with self._lock:
            entry = self._entries.get(slot)
            return None if entry is None else entry[1]


# One cache per scene, dropped with the scene; the dictionary itself is guarded.
_CACHES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_CACHES_LOCK = threading.Lock()


def cache_for(scene: Scene, reuse: bool) -> RenderCache:
    """The scene's cache (created on first use and dropped with the scene), or a fresh,
    empty one that nobody keeps if ``reuse`` is False."""
    if not reuse:
        return RenderCache()
    with _CACHES_LOCK:
        cache = _CACHES.get(scene)
        if cache is None:
            cache = _CACHES[scene] = RenderCache()
        return cache


def share_cache(scene: Scene, cache: RenderCache) -> None:
    """Let ``scene`` use ``cache`` from now on (e.g. a copy of a scene with some tensors
    replaced, rendered by ``render.inverse.function``, uses its source's cache). Safe
    because every stage is keyed by values, never by which tensor holds them."""
    with _CACHES_LOCK:
        _CACHES[scene] = cache


def _copies(tensors) -> list[np.ndarray]:
    return [np.array(t.data) for t in tensors]


def camera_key(camera: Camera, spp: int, bvh: bool) -> list[np.ndarray]:
    """What the camera rays depend on besides the geometry."""
    return _copies([camera.position, camera.look_at, camera.up, camera.fov]) + [
        np.array([camera.width, camera.height, spp, bvh])
    ]


def light_key(light: Light) -> list[np.ndarray]:
    """What a light's shadow rays depend on besides the hit points (``Light.shadow_key``)."""
    return light.shadow_key()


def surface_key(obj: Mesh | Sphere, owned: list, dtype) -> list[np.ndarray]:
    """What an object's hit points, normals and UVs depend on besides the camera rays'
    hits: its parameters ``owned`` (``render.shade.surface.moves_surface``), its switches and
    the working dtype."""
    # A world-space copy made for a render (``render.scene.placement``) stands for its source.
    switches = [getattr(obj, "source_id", id(obj)), np.dtype(dtype).num]
    if isinstance(obj, Mesh):
        switches += [obj.smooth, bool(obj.material.textures), obj.normals is not None]
    return _copies(owned) + [np.array(switches, dtype=np.int64)]
