"""The geometry: triangle ``Mesh`` es, analytic ``Sphere`` s, and the ``Transform`` that
places either in the world (applied on the tape by ``render.scene.placement``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from minidiff import Tensor
from render.scene.fields import (
    IN_RANGE,
    MAX_COORD,
    ArrayLike,
    Field,
    HasFields,
    check_instance,
    fmt,
    normalisable,
)
from render.scene.materials import Material

__all__ = ["MAX_ROTATION_DEGREES", "Mesh", "Sphere", "Transform"]


#: The largest angle (degrees) of a rotation vector: 2,778 turns. The rotation is made of
#: sin and cos of the angle in radians, which are only as good as that angle's own
#: rounding, |theta| * 1.1e-16: 2e-12 rad here, a whole radian by 1e18 degrees (the result
#: is then meaningless), and theta^2 overflows to inf beyond ~1e156 degrees (a NaN matrix,
#: refused only later as "triangles must be finite"). No placement needs more: an angle
#: may be reduced mod 360.
MAX_ROTATION_DEGREES = 1e6


def _rotation_ok(x: np.ndarray) -> bool:
    """A rotation vector of at most ``MAX_ROTATION_DEGREES``, or a quaternion far enough
    from zero to normalise."""
    if x.shape == (3,):
        with np.errstate(over="ignore"):
            return bool(np.sqrt(np.sum(np.square(x, dtype=np.float64))) <= MAX_ROTATION_DEGREES)
    return normalisable(x)


_ROTATION = (
    _rotation_ok,
    "a rotation vector or a non-zero quaternion (a rotation vector's length, its angle, "
    "at most 1e6 degrees)",
)


class Transform(HasFields):
    """A similarity transform placing an object in the world: rotate and scale about
    ``pivot``, then translate. A point p of the object is drawn at

        world(p) = pivot + translation + scale * R (p - pivot),

    applied on the tape inside ``render`` (``render.scene.placement``), so that every field
    is a parameter like any other (``objects[i].transform.rotation``, ...), composable with
    the object's own vertex positions (the shape, in object space).

    Args:
        rotation: (3,) a rotation vector in **degrees** (the axis times the angle, like the
            scene's other angles; (0, 0, 0) is no rotation; an angle of at most 1e6
            degrees, ``MAX_ROTATION_DEGREES``), or (4,) a quaternion
            (w, x, y, z), normalised on use (any non-zero length). Rotation vectors give an
            optimiser three unconstrained coordinates; quaternions have no singular angle.
        translation: (3,) added after rotating and scaling.
        scale: scalar uniform scale, > 0.
        pivot: (3,) the point the rotation and the scale keep fixed (the object's centre,
            say, so that rotating does not also move it). Default: the origin.

    Shading normals given with a mesh (``Mesh.normals``) are rotated with it.
    """

    FIELDS = (
        Field("rotation", ((3,), (4,)), _ROTATION),
        Field("translation", ((3,),), IN_RANGE),
        Field("scale", ((),), (lambda x: 0.0 < x <= MAX_COORD, "> 0 and at most 1e60")),
        Field("pivot", ((3,),), IN_RANGE),
    )

    def __init__(
        self,
        rotation: ArrayLike = (0.0, 0.0, 0.0),
        translation: ArrayLike = (0.0, 0.0, 0.0),
        scale: ArrayLike = 1.0,
        pivot: ArrayLike = (0.0, 0.0, 0.0),
    ) -> None:
        self._set_fields(rotation=rotation, translation=translation, scale=scale, pivot=pivot)
        self.validate()


def _check_transform(obj: Any, owner: str) -> None:
    if obj.transform is not None:
        check_instance(obj.transform, owner, "transform", Transform)
        obj.transform.validate()


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------


def _as_faces(faces: Any) -> np.ndarray:
    """Faces as a C-contiguous int64 ndarray (no copy if it already is one)."""
    if isinstance(faces, Tensor):
        raise TypeError(
            "Mesh: faces must be an integer ndarray, not a minidiff.Tensor "
            "(connectivity is never differentiable)"
        )
    try:
        array = np.asarray(faces)
    except ValueError as err:  # ragged lists: NumPy says "inhomogeneous shape"
        raise ValueError(f"Mesh: faces must be an (F, 3) array of integers: {err}") from None
    if array.dtype == object:
        raise ValueError("Mesh: faces must be an (F, 3) array of integers, got ragged rows")
    if array.dtype == np.uint64 and array.size and int(array.max()) > np.iinfo(np.int64).max:
        raise ValueError(f"Mesh: faces contain an index too large for int64 ({int(array.max())})")
    if array.dtype == np.bool_ or not np.issubdtype(array.dtype, np.integer):
        if array.size == 0 and array.dtype == np.float64:
            # np.asarray([]) is float64; report the emptiness, not the dtype.
            array = array.astype(np.int64)
        else:
            raise TypeError(f"Mesh: faces must be an integer array, got dtype {array.dtype}")
    return np.ascontiguousarray(array, dtype=np.int64)


class Mesh(HasFields):
    """A triangle mesh with one shared vertex buffer and one material.

    Args:
        vertices: (V, 3) vertex positions, V >= 1.
        faces: (F, 3) integer vertex indices, F >= 1, each in [0, V). Stored as a plain
            ``int64`` ndarray (never differentiable). Counter-clockwise winding seen from
            the front: the geometric normal is ``(b - a) x (c - a)``. Degenerate
            (zero-area) triangles are legal; surfaces are shaded two-sided.
        material: the ``Material`` of every triangle.
        normals: optional (V, 3) per-vertex shading normals (need not be unit length).
        uvs: optional (V, 2) per-vertex texture coordinates (see ``Material.texture``).
        smooth: if True the renderer shades with the barycentric interpolation of the
            vertex normals (``normals``, or if None normals it computes from the current
            vertices); if False with the flat geometric normal (the paper's convention).
        transform: optional ``Transform`` placing the mesh in the world (its vertices are
            then in object space); None: the vertices are world positions.
    """

    FIELDS = (
        Field("vertices", (("V", 3),), IN_RANGE),
        Field("normals", (("V", 3),), optional=True),
        Field("uvs", (("V", 2),), optional=True),
    )

    def __init__(
        self,
        vertices: ArrayLike,
        faces: np.ndarray | Sequence[Sequence[int]],
        material: Material,
        normals: ArrayLike | None = None,
        uvs: ArrayLike | None = None,
        smooth: bool = False,
        transform: Transform | None = None,
    ) -> None:
        self._set_fields(vertices=vertices, normals=normals, uvs=uvs)
        self.faces = _as_faces(faces)
        self.material = material
        self.smooth = smooth
        self.transform = transform
        self.validate()

    @property
    def num_vertices(self) -> int:
        """V, the number of vertices."""
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        """F, the number of triangles."""
        return int(self.faces.shape[0])

    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float array of the current corner positions, ``[face, corner, xyz]``."""
        return self.vertices.data[self.faces]

    def validate(self) -> None:
        """Re-check shapes, finiteness, face indices and material/normals/uvs consistency."""
        vertices = self.vertices
        if isinstance(vertices, Tensor) and vertices.data.ndim == 2 and vertices.shape[0] == 0:
            raise ValueError("Mesh: vertices is empty (a mesh needs at least one vertex)")
        vertices = self._check_fields()["vertices"]
        faces = self.faces
        if not isinstance(faces, np.ndarray) or faces.dtype != np.int64:
            raise TypeError(
                "Mesh: faces must be an int64 ndarray, got "
                f"{getattr(faces, 'dtype', type(faces).__name__)}"
            )
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"Mesh: faces must have shape (F, 3), got {faces.shape}")
        if faces.shape[0] == 0:
            raise ValueError("Mesh: faces is empty (a mesh needs at least one triangle)")
        n_vertices = vertices.shape[0]
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0:
            raise ValueError(f"Mesh: faces contain a negative index ({lo})")
        if hi >= n_vertices:
            raise ValueError(
                f"Mesh: faces index vertex {hi} but there are only {n_vertices} vertices"
            )
        check_instance(self.material, "Mesh", "material", Material)
        self.material.validate()  # its tensors may have been edited in place too
        if not isinstance(self.smooth, bool | np.bool_):
            raise TypeError(f"Mesh: smooth must be a bool, got {type(self.smooth).__name__}")
        if self.material.textures and self.uvs is None:
            raise ValueError("Mesh: the material has a texture but the mesh has no uvs")
        _check_transform(self, "Mesh")
        if self.smooth and self.normals is not None:
            # All zero would shade every hit black without a word (one zero normal among
            # others is fine: the interpolation is still defined near the others).
            if not self.normals.data[np.unique(faces)].any():
                raise ValueError(
                    "Mesh: normals are all (0, 0, 0) on the vertices the faces use; smooth "
                    "shading needs non-zero normals (or normals=None to compute them)"
                )

    def __repr__(self) -> str:
        extras = [n for n in ("normals", "uvs", "transform") if getattr(self, n) is not None]
        return (
            f"Mesh({self.num_vertices} vertices, {self.num_faces} faces"
            f"{''.join(', ' + e for e in extras)}, smooth={self.smooth}, {self.material!r})"
        )


class Sphere(HasFields):
    """An analytic sphere.

    Args:
        center: (3,) centre in world space.
        radius: scalar radius, > 0.
        material: its ``Material`` (untextured: spheres carry no UVs).
        transform: optional ``Transform`` placing the sphere in the world (the centre moves
            with it, the radius scales with it); None: ``center`` is a world position.
    """

    FIELDS = (
        Field("center", ((3,),), IN_RANGE),
        Field("radius", ((),), (lambda x: 0.0 < x <= MAX_COORD, "> 0 and at most 1e60")),
    )

    def __init__(
        self,
        center: ArrayLike,
        radius: ArrayLike,
        material: Material,
        transform: Transform | None = None,
    ) -> None:
        self._set_fields(center=center, radius=radius)
        self.material = material
        self.transform = transform
        self.validate()

    def validate(self) -> None:
        """Re-check the current values."""
        self._check_fields()
        check_instance(self.material, "Sphere", "material", Material)
        self.material.validate()
        if self.material.textures:
            raise ValueError("Sphere: textured materials are not supported (spheres have no UVs)")
        _check_transform(self, "Sphere")

    def __repr__(self) -> str:
        return f"Sphere(center={fmt(self.center)}, radius={fmt(self.radius)}, {self.material!r})"
