"""Path replay compiled: the gradient of materials, lights' strengths and colours, and the
environment, with no tape.

When every parameter that requires grad is one of these (``covers``), the adjoint of a
path-traced image needs no vertex on a tape: ``render.path.twin.kernel``'s path replay traces
each path, replays it with its radiance and the pixel's dL/dimage, and adds each vertex's
share to one gradient vector (``kernel.replay_gradient``), in memory independent of spp and
of the paths' depth. ``backpropagate`` adds that vector to the parameters' ``.grad``.

Covered: ``Material.albedo`` (not under a texture: the texture replaces it), ``specular``
(not under a specular texture), ``shininess``, ``reflectance``, ``emission``; a point
light's ``intensity``, a directional light's ``irradiance``, either's ``color``; the
scene's ``background``. ``ambient`` is read by no path (its gradient stays None, as on the
tape). Anything that moves geometry (vertices, transforms, spheres, the camera, a light's
position or direction) or a texture takes the tape (``render.path.integrator``).
"""

from __future__ import annotations

import numpy as np

import minidiff as md
from render.path.sample.tracer import PathSampler
from render.path.twin import chain, kernel
from render.scene.lights import DIRECTIONAL, POINT
from render.scene.scene import Scene

#: The strength field of each kind of light the kernel shades.
_STRENGTH = {POINT: "intensity", DIRECTIONAL: "irradiance"}
#: A material's covered fields and where they sit in an object's gradient entries.
_MATERIAL = (
    ("albedo", chain._G_ALBEDO, 3),
    ("specular", chain._G_SPECULAR, 3),
    ("shininess", chain._G_SHININESS, 1),
    ("reflectance", chain._G_REFLECTANCE, 3),
    ("emission", chain._G_EMISSION, 3),
)


def covers(world: Scene) -> bool:
    """Whether the compiled path replay computes the gradient of every parameter of
    ``world`` (placed) that requires grad, and the kernel traces the scene."""
    if not kernel.applies(world):
        return False
    wanted = {id(p) for p in world.parameters() if p.requires_grad}
    if not wanted:
        return False
    covered = {id(world.background)}
    for obj in world.objects:
        m = obj.material
        covered |= {id(m.albedo), id(m.shininess), id(m.reflectance), id(m.emission), id(m.ambient)}
        if m.specular_texture is None:
            covered.add(id(m.specular))
    for light in world.lights:
        covered |= {id(light.color), id(getattr(light, _STRENGTH[light.KIND]))}
    return wanted <= covered


def backpropagate(world: Scene, sampler: PathSampler, d_image: np.ndarray) -> None:
    """Add d_image . d image / d p (``d_image`` (H, W, 3): dL/dimage) to ``p.grad`` of every
    parameter of ``world`` that requires grad, by the kernel's path replay with
    ``sampler``'s paths (``covers(world)`` must hold)."""
    grad = kernel.replay_gradient(sampler, d_image)
    for o, obj in enumerate(sampler.objects):
        m = obj.material
        base = chain._G_OBJECT * o
        for name, at, size in _MATERIAL:
            if name == "albedo" and m.texture is not None:
                continue  # the texture replaces the albedo: it does not move the image
            if name == "reflectance" and sampler.lobes.probability[o, 2] == 0:
                continue  # no path picks the mirror lobe: the tape does not read it either
            _add(getattr(m, name), grad[base + at : base + at + size])
    for j, light in enumerate(world.lights):
        base = chain._G_OBJECT * len(sampler.objects) + chain._G_LIGHT * j
        _add(getattr(light, _STRENGTH[light.KIND]), grad[base : base + 1])
        _add(light.color, grad[base + 1 : base + 4])
    base = chain._G_OBJECT * len(sampler.objects) + chain._G_LIGHT * len(world.lights)
    _add(world.background, grad[base : base + 3])


def _add(p: md.Tensor, g: np.ndarray) -> None:
    """p.grad += g, as ``backward`` accumulates (a material shared by several objects gets
    each one's share), summed to p's shape: a () parameter was broadcast to the three
    channels."""
    if not p.requires_grad:
        return
    g = g.reshape(p.shape) if g.size == p.data.size else np.full(p.shape, g.sum())
    g = g.astype(p.dtype)
    p.grad = g if p.grad is None else p.grad + g
