"""Steps 2 and 3 compiled: a mesh's camera hits shaded by the readable formulas, traced.

The surface interaction (``render.shade.surface.surface_at``: the camera ray,
Moller-Trumbore, the normal, flat or interpolated, turned towards the ray) and the shading
(``render.shade.lighting.shade_surface``: every light's ``incidence``, the Lambert +
Blinn-Phong BRDF, the ambient and the emitted radiance) are written once, on minidiff
arrays. ``shade_mesh`` runs exactly that text through ``minidiff.compile``: traced once per
kind of mesh, material and lights (``_shade``'s static ``form``) into one loop over the
hits, whose forward, VJP and JVP the compiler generates from each primitive's own rules.
Nothing here restates the mathematics; this module only says what is shared by every hit
(the camera frame, the mesh's vertices, faces and vertex normals, the material's and the
lights' parameters) and what each hit has of its own (its image-plane point, its face, its
lit masks).

On the tape the result is one node: gradients reach the camera frame, the vertices (the
gathers' scatter-add, in hit order), the normals, the material and every light, and forward
mode works the same way. Without the tape it is the forward kernel alone. Results do not
depend on the number of threads (``minidiff.compiler``).

It applies (``applies``) to a mesh without textures (their texel lookups are discrete
gathers the tracer does not take yet), in a float64 scene, with lights whose ``incidence``
is written with minidiff operations (``Light.compiled_shading``), and no mirror ray leaving
it. Everything else takes the tape, which stays the reference:
``tests/render/shade/test_compiled_shading.py`` ties the two together.
"""

from __future__ import annotations

import numpy as np

import minidiff as md
from render.scene.camera import ray_directions
from render.scene.materials import Material
from render.scene.scene import Mesh, Scene
from render.shade.lighting import shade_surface, term_present
from render.shade.surface import surface_at, vertex_normals

#: The material's parameters the shading reads (its textures are refused by ``applies``).
MATERIAL_FIELDS = ("albedo", "specular", "shininess", "ambient", "emission")


def applies(scene: Scene, obj, reflects: bool) -> bool:
    """Whether ``shade_mesh`` shades ``obj``'s camera hits: a mesh without textures, in a
    float64 scene (its camera, the mesh, its material and the lights), ``reflects`` False
    (no mirror ray leaves it), and every light one whose shading compiles
    (``compiled_shading``)."""
    if not isinstance(obj, Mesh) or reflects or obj.material.textures:
        return False
    if not all(light.compiled_shading for light in scene.lights):
        return False
    owners = [scene.camera, obj, obj.material, *scene.lights]
    return all(t.dtype == np.float64 for owner in owners for t in owner.named_parameters().values())


def shade_mesh(mesh: Mesh, faces: np.ndarray, frame, coords: np.ndarray, lights, lit) -> md.Tensor:
    """The radiance (k, 3) of k camera rays through image-plane points ``coords`` (k, 2)
    that hit the mesh's faces ``faces`` (k,) (local ids): ``surface_at`` then
    ``shade_surface``, compiled. ``frame``: the camera frame (forward, right, up, eye),
    (3,) tensors (on the tape) or arrays; ``lit[j]`` (k,): 1 where light j reaches the hit.
    Only where ``applies``."""
    material = mesh.material
    normals = None
    if mesh.smooth:  # its own normals, or computed from its vertices (on the tape if need be)
        normals = mesh.normals
        if normals is None:
            normals = vertex_normals(mesh.vertices, mesh.faces)
    present = tuple(name for name in MATERIAL_FIELDS if _present(material, name))
    parameters, kinds = light_arguments(lights)
    visible = None
    if lights:
        visible = np.empty((len(faces), len(lights)))
        for j, mask in enumerate(lit):
            visible[:, j] = mask
    return _shade(
        np.ascontiguousarray(coords, np.float64), np.ascontiguousarray(faces, np.int64),
        visible, tuple(frame), (mesh.vertices, mesh.faces, normals),
        tuple(getattr(material, name) for name in present),
        parameters,
        (present, kinds),
    )  # fmt: skip


def light_arguments(lights) -> tuple[tuple, tuple]:
    """How a compiled function takes lights: (each light's parameters, a shared argument;
    each light's class and parameter names, static), for ``held_lights`` inside it."""
    parameters = tuple(tuple(light.named_parameters().values()) for light in lights)
    kinds = tuple((type(light), tuple(light.named_parameters())) for light in lights)
    return parameters, kinds


def held_lights(kinds: tuple, parameters: tuple) -> list:
    """The lights rebuilt around (traced) ``parameters`` (``light_arguments``), so that their
    own code (``Light.incidence``) runs on them."""
    return [
        cls.holding(**dict(zip(names, params, strict=True)))
        for (cls, names), params in zip(kinds, parameters, strict=True)
    ]


def _present(material: Material, name: str) -> bool:
    """Whether the shading reads the material's parameter ``name``: the albedo always, the
    others when they are non-zero or differentiated (``lighting.term_present``), the shininess
    with a Blinn-Phong lobe. An absent one is left out of the program."""
    if name == "albedo":
        return True
    if name == "shininess":
        return term_present(material.specular)
    return term_present(getattr(material, name))


@md.compile(shared=("frame", "mesh", "material", "lights"))
def _shade(coords, faces, lit, frame, mesh, material, lights, form):
    """``shade_mesh``'s compiled function. Batched: coords (k, 2), faces (k,), lit (k, L)
    (None without lights). Shared: frame (4 x (3,)); mesh (vertices (V, 3), faces (F, 3)
    int, vertex normals (V, 3) or None); the material's present parameters and each
    light's parameters (in ``form``'s order). Static: ``form`` = (the names of the present
    material parameters, per light its class and its parameters' names).

    The mesh, material and lights are rebuilt around the traced arrays (``holding``), so
    that their own code (``Light.incidence``, ``Material.emissive``) runs on them; an
    absent material parameter is a constant zero, which that code leaves out."""
    present, kinds = form
    zero = md.tensor(0.0)
    values = dict.fromkeys(MATERIAL_FIELDS, zero) | dict(zip(present, material, strict=True))
    look = Material.holding(
        **values, texture=None, specular_texture=None, ambient_texture=None, reflectance=zero
    )
    vertices, table, normals = mesh
    shape = Mesh.holding(
        vertices=vertices, faces=table, normals=normals, uvs=None, smooth=normals is not None,
        material=look, transform=None,
    )  # fmt: skip
    scene_lights = held_lights(kinds, lights)
    masks = [lit[:, j] for j in range(len(scene_lights))]
    directions = ray_directions(frame, coords)
    surface = surface_at(shape, faces, frame[3], directions)
    return shade_surface(surface, look, scene_lights, masks)[0]
