"""Shading on the tape: lights, the Lambert + Blinn-Phong BRDF, textures.

All functions take per-hit arrays (k hits) as minidiff tensors and return tensors, so every
light, material and texture parameter receives gradients. Radiometric convention (see
``docs/paper_scene.md``): for a point light of radiant intensity I at distance r,

    L = (albedo / pi + f_specular) * I * color * max(0, cos theta) / r^2

and for a directional light of irradiance E: the same with I / r^2 replaced by E. The
direction to each light and its irradiance come from the light (``Light.incidence``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.scene.scene import Light, Material, Mesh
from render.shade.surface import Surface, column, surface_at


def _footprint(uv, width, height) -> tuple:
    """The bilinear footprint of (k, 2) UVs in a ``width`` x ``height`` texture, repeating
    outside [0, 1]: its columns (x0, x1) and rows (y0, y1) as integer-valued floats in the
    texture, and the blend weights (fx, fy) (k,). ``width``, ``height``: numbers, or per
    point (k,) floats. On tensors (the weights carry the UVs' derivative; the cell is a
    constant, ``md.floor``), on plain arrays, or traced inside a compiled function.

    Texel centres sit at integers: UV (0, 0) is the bottom-left corner of the image and
    (1, 1) the top-right (the OBJ convention). The UV is first taken modulo 1 (u -
    floor(u) is exact for every finite u, where u * width could round away from the
    cell, or overflow an index, for a UV as large as 1e300), so the cell's column is in
    [-1, width - 1] and -1 wraps to the last."""
    u, v = uv[:, 0], uv[:, 1]
    x = (u - md.floor(u)) * width - 0.5
    y = (1.0 - (v - md.floor(v))) * height - 0.5
    x0, y0 = md.floor(x), md.floor(y)
    weights = (x - x0, y - y0)
    x1 = md.where(x0 + 1.0 >= width, 0.0, x0 + 1.0)
    y1 = md.where(y0 + 1.0 >= height, 0.0, y0 + 1.0)
    x0 = md.where(x0 < 0.0, width - 1.0, x0)
    y0 = md.where(y0 < 0.0, height - 1.0, y0)
    return (x0, x1), (y0, y1), weights


def texel_cell(shape, uv: np.ndarray) -> np.ndarray:
    """(k,) int64: the flat index (row * W + column) of the top-left texel of each UV's
    bilinear footprint in an (H, W, ...) texture, repeating outside [0, 1].

    Bilinear filtering is smooth inside a cell and has a kink (a jump in its derivative)
    where a sample crosses into the next cell, so the cell is a discrete decision of the
    renderer, like visibility: ``RenderInfo.texel`` reports it.
    """
    with md.no_grad():
        (x0, _), (y0, _), _ = _footprint(md.tensor(np.asarray(uv, np.float64)), shape[1], shape[0])
    return md.to_index(y0 * shape[1] + x0)


def sample_texture(texture, uv) -> md.Tensor:
    """Bilinear lookup of an (H, W, C) texture at (k, 2) UVs, repeating outside [0, 1]
    (``lookup``)."""
    height, width, channels = texture.shape
    return lookup(md.reshape(texture, (height * width, channels)), uv, width, height)


def lookup(texels, uv, width, height, offset=0.0) -> md.Tensor:
    """Bilinear lookup at (k, 2) UVs of the texture whose texels are the rows of
    ``texels`` (T, C) from row ``offset`` on, ``width`` x ``height`` of them row by row,
    top row first (``width``, ``height``, ``offset``: numbers, or per point (k,) floats:
    the textures of several objects in one table, inside a compiled function). Gradients
    reach the four texels of each footprint (through the gathers) and the UVs (through
    the blend weights); the footprint itself (``texel_cell``) is a constant."""
    (x0, x1), (y0, y1), (fx, fy) = _footprint(uv, width, height)
    fx, fy = column(fx), column(fy)

    def texel(row, col):
        return texels[md.to_index(offset + row * width + col)]

    top = texel(y0, x0) * (1.0 - fx) + texel(y0, x1) * fx
    bottom = texel(y1, x0) * (1.0 - fx) + texel(y1, x1) * fx
    return top * (1.0 - fy) + bottom * fy


@dataclass
class Appearance:
    """A material's values at k hits, its textures sampled at their UVs: ``albedo`` (3,)
    or (k, 3); ``specular`` and ``ambient`` (), (3,) or (k, 3); ``shininess`` (); and
    ``texel`` (k,) int64, the diffuse texture's cell at each hit (None: untextured)."""

    albedo: md.Tensor
    specular: md.Tensor
    ambient: md.Tensor
    shininess: md.Tensor
    texel: np.ndarray | None


def appearance(material: Material, uv) -> Appearance:
    """The material at k hits with UVs ``uv`` (k, 2) (None when untextured): ``texture``
    replaces the albedo; ``specular_texture`` and ``ambient_texture`` multiply Ks and Ka,
    as an MTL file's map_Kd, map_Ks and map_Ka do."""
    albedo, texel = material.albedo, None
    if material.texture is not None:
        albedo = sample_texture(material.texture, uv)
        texel = texel_cell(material.texture.shape, uv.data)
    specular, ambient = material.specular, material.ambient
    if material.specular_texture is not None:
        specular = specular * sample_texture(material.specular_texture, uv)
    if material.ambient_texture is not None:
        ambient = ambient * sample_texture(material.ambient_texture, uv)
    return Appearance(albedo, specular, ambient, material.shininess, texel)


def term_present(x: md.Tensor) -> bool:
    """Whether a term is present: non-zero somewhere, or being differentiated."""
    return x.is_differentiated() or bool(np.any(x.data))


def light_contribution(points, normals, directions, look: Appearance, light, visible=None):
    """Radiance (k, 3) that one light reflects back along the incoming rays at k hits.

    points (k, 3); normals (k, 3) unit, facing the incoming ray; directions (k, 3) of the
    incoming rays (any length; only the specular lobe needs them); ``look`` the material
    there; visible (k,) float, 1 where the light is unoccluded (a constant: visibility is
    discrete), or None for the unoccluded contribution (the shadow-edge term needs it where
    the light is blocked too).
    """
    view = -md.normalize(directions) if term_present(look.specular) else None
    return _light_term(points, normals, view, look.albedo * (1.0 / math.pi), look, light, visible)


def brdf(normals, view, to_light, diffuse_brdf, look: Appearance):
    """The BRDF (k, 3) (or (3,)) for light arriving from unit directions ``to_light`` (k, 3)
    and leaving towards unit ``view`` (k, 3; None when there is no specular lobe), at unit
    ``normals`` (k, 3): ``diffuse_brdf`` (albedo / pi) plus the energy-normalised Blinn-Phong
    lobe  f_s = specular (n + 8) / (8 pi) max(0, n.h)^n. The cosine is the caller's."""
    if view is None:
        return diffuse_brdf
    half = md.normalize(to_light + view)
    # Clamp before the power: 0^n has an infinite log, which d/dn would need.
    n_dot_h = md.maximum(md.dot(normals, half), 1e-12)
    lobe = n_dot_h**look.shininess * ((look.shininess + 8.0) / (8.0 * math.pi))
    return diffuse_brdf + column(lobe) * look.specular


def _light_term(points, normals, view, diffuse_brdf, look: Appearance, light: Light, visible):
    """``light_contribution`` with the per-hit terms that do not depend on the light (the
    unit direction to the eye, the diffuse BRDF) computed once by the caller."""
    to_light, irradiance = light.incidence(points)
    cos_theta = md.maximum(md.dot(normals, to_light), 0.0)
    f = brdf(normals, view, to_light, diffuse_brdf, look)
    # Per-hit scalars first, then a single (k, 3) product with the colours.
    scalar = irradiance * cos_theta if visible is None else irradiance * cos_theta * visible
    return column(scalar) * (f * light.color)


def shade(points, normals, directions, look: Appearance, lights, lit) -> md.Tensor:
    """Outgoing radiance (k, 3) at k hit points: every light's ``light_contribution``
    (lit[j] (k,) float, 1 where light j is unoccluded) plus the material's ambient term."""
    diffuse_brdf = look.albedo * (1.0 / math.pi)
    view = -md.normalize(directions) if term_present(look.specular) else None  # towards the eye
    radiance = None
    for light, visible in zip(lights, lit, strict=True):
        contribution = _light_term(points, normals, view, diffuse_brdf, look, light, visible)
        radiance = contribution if radiance is None else radiance + contribution
    if radiance is None:  # no lights: only the ambient term
        radiance = 0.0 * points  # zeros, one row per hit (written so that it compiles)
    if term_present(look.ambient):
        radiance = radiance + look.ambient
    return radiance


def shade_surface(
    surface: Surface, material: Material, lights, lit
) -> tuple[md.Tensor, np.ndarray | None]:
    """Shade k hits: the radiance (k, 3) and the diffuse texture's cell at each hit (k,)
    int64 (None when there is no diffuse texture). lit[j] (k,) float visibility of light
    j. An emissive material adds its emission where the ray meets its front (it lights
    nothing here: that takes the path integrator, ``render.path``)."""
    look = appearance(material, surface.uv)
    radiance = shade(surface.points, surface.normals, surface.directions, look, lights, lit)
    if material.emissive:
        radiance = radiance + column(surface.front) * material.emission
    return radiance, look.texel


def shade_mesh(mesh: Mesh, faces_hit, eye, directions, lights, lit) -> tuple[md.Tensor, np.ndarray]:
    """``surface_at`` then ``shade_surface``: radiance (k, 3) and texel cells (k,)."""
    return shade_surface(surface_at(mesh, faces_hit, eye, directions), mesh.material, lights, lit)
