"""A surface's appearance: ``Material`` (its BRDF parameters, textures, mirror coefficient
and emission; how they shade: ``render.shade.lighting``)."""

from __future__ import annotations

import numpy as np

from minidiff import Tensor
from render.scene.fields import ArrayLike, Field, HasFields

__all__ = ["Material"]


class Material(HasFields):
    """Surface appearance: a Lambertian (diffuse) term plus an optional glossy lobe.

    Args:
        albedo: (3,) diffuse reflectance (linear RGB); the diffuse BRDF is ``albedo / pi``.
        specular: scalar or (3,) specular coefficient Ks of the renderer's (Blinn-)Phong
            lobe, see ``render.shade.lighting`` (0 = none).
        shininess: scalar (Blinn-)Phong exponent, > 0.
        ambient: scalar or (3,) ambient radiance **added to the pixel** where this
            material is seen, *not* multiplied by the albedo: the classic Phong ``Ka * Ia``
            term (``render.scene.meshio`` sets it to ``Ka * ambient_light`` from an MTL file).
        texture: optional (H, W, 3) image, values usually in [0, 1], that replaces
            ``albedo`` at each hit, sampled at the hit's interpolated UV. Row 0 is the
            *top* row of the image file; UV (0, 0) is the *bottom-left* corner of the image
            and v grows upwards (the OBJ/OpenGL convention trimesh returns), so
            ``row = (1 - v) * H``, ``column = u * W``. UVs outside [0, 1] wrap around
            (repeat), as OBJ files assume. Only meshes with UVs can use a textured
            material. Values are used as stored (no sRGB decoding).
        reflectance: scalar or (3,) mirror coefficient: the radiance arriving along the
            mirror direction, times this, is added at every hit (``render.shade.mirrors``;
            ``render(..., max_bounces=)`` bounds the recursion). 0 = not a mirror.
        specular_texture: optional (H, W, 3) image multiplying ``specular`` at each hit
            (an MTL file's ``map_Ks``), sampled like ``texture``.
        ambient_texture: optional (H, W, 3) image multiplying ``ambient`` at each hit (an
            MTL file's ``map_Ka``), sampled like ``texture``.
        emission: scalar or (3,) radiance >= 0 emitted from the front of the surface (the
            side a triangle's normal ``(b - a) x (c - a)`` points to; a sphere's outside):
            the object is an area light. The path integrator (``render(...,
            integrator="path")``, ``render.path``) lights the scene with it; the direct
            renderer shows it where it is seen, like ``ambient``, but lights nothing with it.

    Values are not clamped to [0, 1]: an optimiser may overshoot while fitting an albedo.
    """

    FIELDS = (
        Field("albedo", ((3,),)),
        Field("specular", ((), (3,))),
        Field("shininess", ((),), (lambda x: x > 0.0, "> 0")),
        Field("ambient", ((), (3,))),
        Field("texture", (("H", "W", 3),), optional=True),
        Field("reflectance", ((), (3,))),
        # Own size names: the three textures need not have the same resolution.
        Field("specular_texture", (("Hs", "Ws", 3),), optional=True),
        Field("ambient_texture", (("Ha", "Wa", 3),), optional=True),
        Field("emission", ((), (3,)), (lambda x: np.all(x >= 0.0), ">= 0 (a radiance)")),
    )

    def __init__(
        self,
        albedo: ArrayLike,
        specular: ArrayLike = 0.0,
        shininess: ArrayLike = 32.0,
        ambient: ArrayLike = 0.0,
        texture: ArrayLike | None = None,
        reflectance: ArrayLike = 0.0,
        specular_texture: ArrayLike | None = None,
        ambient_texture: ArrayLike | None = None,
        emission: ArrayLike = 0.0,
    ) -> None:
        self._set_fields(
            albedo=albedo, specular=specular, shininess=shininess, ambient=ambient,
            texture=texture, reflectance=reflectance, specular_texture=specular_texture,
            ambient_texture=ambient_texture, emission=emission,
        )  # fmt: skip
        self.validate()

    @property
    def textures(self) -> list[Tensor]:
        """The textures that are set (each needs UVs at the hits)."""
        maps = (self.texture, self.specular_texture, self.ambient_texture)
        return [t for t in maps if t is not None]

    @property
    def reflective(self) -> bool:
        """Whether hits need a reflected ray: a non-zero reflectance, or one being
        differentiated (its gradient at 0 is the reflected radiance)."""
        return self.reflectance.is_differentiated() or bool(np.any(self.reflectance.data))

    @property
    def emissive(self) -> bool:
        """Whether the surface emits: a non-zero emission, or one being differentiated."""
        return self.emission.is_differentiated() or bool(np.any(self.emission.data))
