"""Scene description: camera, lights, materials and geometry.

These classes hold data only; the renderer (``render.render`` and friends) reads them.

Convention the renderer relies on
---------------------------------
Every *continuous* parameter (positions, angles, colours, intensities, vertex positions,
textures, ...) is stored as a :class:`minidiff.Tensor`, so that any of them can be made
differentiable by the user:

* if you pass a ``minidiff.Tensor`` we keep *that very object* (so a ``requires_grad=True``
  tensor you hold receives its ``.grad`` after ``backward()``);
* anything else (number, tuple, list, ndarray) is converted with
  ``minidiff.tensor(np.asarray(x, dtype=np.float64))``;
* scalars become 0-d tensors.

Discrete data stays plain: mesh ``faces`` are an ``int64`` ndarray (never differentiable),
image ``width``/``height`` are Python ints.

Validation
----------
Every class has a ``validate()`` method that re-checks the *current* values. The optimiser
updates ``tensor.data`` in place, so the renderer calls ``scene.validate()`` before every
render; it is therefore cheap (shape checks and one ``np.isfinite(...).all()`` per array).
Constructors call ``validate()`` too, so a bad scene fails where it is built, with an error
naming the class and the argument. ``Scene.validate()`` also checks the range of coordinates
and extent relative to the camera's view distance (``MAX_COORD_RELATIVE``,
``MAX_EXTENT_RELATIVE``), once for every way of tracing.

Coordinate system: right-handed, y up (the Newell teapot data, which is z up, is rotated on
loading, see ``render.teapot``). Angles are in degrees. Colours are linear RGB.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

import minidiff
from minidiff import Tensor

__all__ = [
    "Camera",
    "PointLight",
    "DirectionalLight",
    "Material",
    "Mesh",
    "Sphere",
    "Scene",
    "Transform",
]

# Anything we accept where a continuous parameter is expected.
ArrayLike = Tensor | np.ndarray | Sequence[float] | float | int


# --------------------------------------------------------------------------------------
# Helpers shared by all classes
# --------------------------------------------------------------------------------------


def _as_tensor(value: Any, owner: str, name: str) -> Tensor:
    """Return ``value`` as a float ``minidiff.Tensor``, keeping it if it already is one."""
    if isinstance(value, Tensor):
        # Keep the user's object: its identity is what carries the gradient back to them.
        return value
    if isinstance(value, str | bytes) or value is None:
        raise TypeError(f"{owner}: {name} must be numeric, got {type(value).__name__}")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(
            f"{owner}: {name} must be numeric (number, sequence or array), "
            f"got {type(value).__name__}"
        ) from err
    return minidiff.tensor(array)


def _shape_str(shape: tuple[int | str, ...]) -> str:
    """Readable shape for messages: ``(3,)``, ``(H, W, 3)``, ``() (a scalar)``."""
    if shape == ():
        return "() (a scalar)"
    inner = ", ".join(str(s) for s in shape)
    return f"({inner},)" if len(shape) == 1 else f"({inner})"


def _check_tensor(
    value: Any,
    owner: str,
    name: str,
    shapes: Sequence[tuple[int | str, ...]],
) -> np.ndarray:
    """Check that ``value`` is a finite float Tensor of one of ``shapes``; return its data.

    A shape is a tuple of ints (exact size) or strings (any size >= 1, e.g. ``'V'``).
    Only views and one ``isfinite`` reduction are made: this runs before every render.
    """
    if not isinstance(value, Tensor):
        raise TypeError(
            f"{owner}: {name} must be a minidiff.Tensor (assign a Tensor, or rebuild the "
            f"{owner}), got {type(value).__name__}"
        )
    data = value.data
    if not isinstance(data, np.ndarray) or not np.issubdtype(data.dtype, np.floating):
        dtype = getattr(data, "dtype", type(data).__name__)
        raise TypeError(f"{owner}: {name} must hold floating-point values, got {dtype}")
    if not any(_shape_matches(data.shape, s) for s in shapes):
        expected = " or ".join(_shape_str(s) for s in shapes)
        raise ValueError(f"{owner}: {name} must have shape {expected}, got {data.shape}")
    if not np.isfinite(data).all():
        raise ValueError(f"{owner}: {name} contains NaN or infinite values")
    return data


def _shape_matches(actual: tuple[int, ...], expected: tuple[int | str, ...]) -> bool:
    if len(actual) != len(expected):
        return False
    return all(
        (a >= 1) if isinstance(e, str) else (a == e) for a, e in zip(actual, expected, strict=True)
    )


def _check_int(value: Any, owner: str, name: str) -> int:
    """A strictly positive Python/NumPy integer (``bool`` is not an integer here)."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{owner}: {name} must be a positive int, got {type(value).__name__}")
    if value <= 0:
        raise ValueError(f"{owner}: {name} must be a positive int, got {value}")
    return int(value)


#: The most rays (width * height * spp) one render may trace: 2**26, e.g. 8192 x 8192
#: pixels at 1 sample or 4096 x 4096 at 4. Every camera ray costs a few hundred bytes over a
#: render and its backward pass (directions, hits, the tape's per-hit arrays), so this is
#: already tens of GB; a larger image could only fail later, inside an allocation or with
#: the machine out of memory, after gigabytes had been taken.
MAX_RAYS = 2**26


def check_ray_count(width: int, height: int, spp: int) -> None:
    """ValueError naming width, height and spp if width * height * spp exceeds MAX_RAYS.
    Python integers do not overflow, so the check itself is exact; nothing is allocated."""
    if width * height * spp > MAX_RAYS:
        raise ValueError(
            f"render: width x height x spp = {width} x {height} x {spp} = "
            f"{width * height * spp:,} rays is more than the limit of {MAX_RAYS:,} (2**26, "
            "e.g. 8192 x 8192 at spp=1): render tiles of the image, or fewer samples"
        )


#: The supported range of positions and sizes (vertices, sphere centres and radii, the
#: camera's position and look-at point, point lights): magnitudes up to 1e60. Products of
#: up to four coordinates appear in the intersection tests and the shading; this keeps them
#: far from float64 overflow (1.8e308), so that no test meets inf - inf = NaN. Checked here,
#: once, when a scene is validated, so that every tracing path (rasterised, BVH, brute
#: force, the light's view) refuses the same scenes; ``render.trace.accel`` checks its own
#: inputs against the same bound.
MAX_COORD = 1e60


def _in_range(x: np.ndarray) -> bool:
    return bool(np.all(np.abs(x.astype(np.float64)) <= MAX_COORD))


#: The constraint of a position or size field (besides being finite).
IN_RANGE = (
    _in_range,
    "at most 1e60 in magnitude (the supported range, render.scene.scene.MAX_COORD)",
)

#: The supported range relative to the scale the image resolves, the camera's view distance
#: |look_at - position| (at the look-at point, one view distance spans 700 pixels of a
#: 512-pixel-wide image at the default fov of 40 degrees), checked by ``Scene.validate``:
#:
#: * Every coordinate (vertices, sphere centres, the camera, point lights) at most
#:   MAX_COORD_RELATIVE view distances. A coordinate of magnitude M is rounded by up to
#:   M * 1.1e-16, and the shadow rays start SHADOW_ULPS = 1024 units in the last place of
#:   the largest coordinate off the surface (``render.trace.visibility.shadow_offset``): at
#:   1e8 view distances that is 2.3e-5 of one, a sixtieth of a pixel. Measured (random scenes
#:   moved that far): within 1e-6 of the unmoved image, ten times worse per decade beyond,
#:   shadows flipping from 1e11; and a quad with a vertex at 1e12 seen from 5 units had no
#:   pixel hit (``tests/render/scene/test_coordinate_range.py``). Point lights are not exempt: their
#:   position enters the shading (direction and 1 / r^2) and the shadow rays' offset, and a
#:   light 1e12 view distances away lost shadows. One at the bound shades like a
#:   ``DirectionalLight`` to 1e-8; for a farther light, use one.
#: * The geometry's bounding box (vertices, spheres) at most MAX_EXTENT_RELATIVE view
#:   distances across (its diagonal): the shadow rays also start SHADOW_EPSILON = 1e-9 of
#:   that diagonal off the surface, at the bound 1e-5 view distances (a hundredth of a
#:   pixel). A ground 1e7 view distances across lost the shadow at the foot of a wall.
#:
#: Scenes scaled by any factor and moved by up to 1e6 of their size
#: (``tests/render/test_scale_invariance.py``) stay well inside both.
MAX_COORD_RELATIVE = 1e8
MAX_EXTENT_RELATIVE = 1e4


def _box(points: np.ndarray) -> np.ndarray:
    """(2, 3) the lowest and highest corner of the bounding box of ``points`` (N, 3), one
    column at a time (NumPy's min(axis=0) sets up a loop per row of 3: ten times slower)."""
    columns = [points[:, k] for k in range(3)]
    return np.array([[c.min() for c in columns], [c.max() for c in columns]])


def _normalisable(v: np.ndarray) -> bool:
    """True if ``v / |v|`` is a finite unit vector: |v| is neither zero nor so small that
    its square underflows, nor so large that it overflows (1e-150 < |v| < 1e150)."""
    with np.errstate(over="ignore", under="ignore"):
        length = np.sqrt(np.sum(np.square(v, dtype=np.float64)))
    return bool(1e-150 < length < 1e150)


def _check_instance(value: Any, owner: str, name: str, cls: type) -> None:
    if not isinstance(value, cls):
        raise TypeError(f"{owner}: {name} must be a {cls.__name__}, got {type(value).__name__}")


def _fmt(t: Tensor) -> str:
    """Short text of a small tensor for ``__repr__`` (large ones show their shape only)."""
    data = t.data
    if data.size > 4:
        return f"<{'x'.join(map(str, data.shape))}>"
    return np.array2string(data, precision=4, separator=", ")


# --------------------------------------------------------------------------------------
# Continuous fields, declared once per class
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Field:
    """One continuous parameter of a scene class: its name, the shapes it may have (ints are
    exact sizes; a string names a size that must agree across the class's fields, e.g. the
    vertex count ``"V"``), an optional constraint on its value (``(test, requirement)``,
    e.g. ``(lambda x: x > 0, "> 0")``) and whether it may be None."""

    name: str
    shapes: tuple[tuple[int | str, ...], ...]
    constraint: tuple[Callable[[np.ndarray], Any], str] | None = None
    optional: bool = False


class _HasFields:
    """What every scene class does with its ``FIELDS``: convert the constructor's values,
    check them (``validate``), print them and name them (``named_parameters``)."""

    FIELDS: tuple[Field, ...] = ()

    def _set_fields(self, **values: Any) -> None:
        owner = type(self).__name__
        for f in self.FIELDS:
            value = values[f.name]
            if value is None and f.optional:
                setattr(self, f.name, None)
            else:
                setattr(self, f.name, _as_tensor(value, owner, f.name))

    def _check_fields(self) -> dict[str, np.ndarray]:
        """Check every field's current value; return the data of those that are set."""
        owner, sizes, data = type(self).__name__, {}, {}
        for f in self.FIELDS:
            value = getattr(self, f.name)
            if value is None and f.optional:
                continue
            # Named sizes already bound by an earlier field become exact sizes.
            shapes = [tuple(sizes.get(d, d) for d in shape) for shape in f.shapes]
            x = data[f.name] = _check_tensor(value, owner, f.name, shapes)
            for d, n in zip(f.shapes[0], x.shape, strict=False):
                if isinstance(d, str):
                    sizes.setdefault(d, n)
            if f.constraint is not None and not f.constraint[0](x):
                shown = float(x) if x.ndim == 0 else x
                raise ValueError(f"{owner}: {f.name} must be {f.constraint[1]}, got {shown}")
        return data

    def named_parameters(self, prefix: str = "") -> dict[str, Tensor]:
        """The set continuous parameters by name, e.g. ``{"position": <Tensor>, ...}``."""
        fields = {f.name: getattr(self, f.name) for f in self.FIELDS}
        return {prefix + name: t for name, t in fields.items() if t is not None}

    def validate(self) -> None:
        """Re-check the current values."""
        self._check_fields()

    def _fields_repr(self) -> str:
        return ", ".join(
            f"{f.name}={'None' if getattr(self, f.name) is None else _fmt(getattr(self, f.name))}"
            for f in self.FIELDS
        )

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._fields_repr()})"


# --------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------


class Camera(_HasFields):
    """A look-at pinhole camera.

    Args:
        position: (3,) eye position in world space.
        look_at: (3,) point the camera looks at; the view direction is
            ``look_at - position`` (must not be zero).
        up: (3,) approximate up direction; only its component orthogonal to the view
            direction matters, so it must not be parallel to the view direction.
        fov: scalar *horizontal* field of view in degrees, in (0, 180). The vertical field
            of view follows from the aspect ratio ``width / height`` (square pixels).
        width, height: image size in pixels (positive ints). One primary ray goes through
            the centre of each pixel.

    The default ``fov`` (39.5978 degrees) is a 50 mm lens on a 36 mm wide sensor, as in the
    paper's reference scene. All continuous arguments become ``minidiff.Tensor`` s
    (see the module docstring); ``width``/``height`` stay ints.
    """

    FIELDS = (
        Field("position", ((3,),), IN_RANGE),
        Field("look_at", ((3,),), IN_RANGE),
        Field("up", ((3,),)),
        Field("fov", ((),), (lambda x: 0.0 < x < 180.0, "in (0, 180) degrees")),
    )

    def __init__(
        self,
        position: ArrayLike,
        look_at: ArrayLike,
        up: ArrayLike = (0, 1, 0),
        fov: ArrayLike = 39.5978,
        width: int = 512,
        height: int = 512,
    ) -> None:
        self._set_fields(position=position, look_at=look_at, up=up, fov=fov)
        self.width = _check_int(width, "Camera", "width")
        self.height = _check_int(height, "Camera", "height")
        self.validate()

    @classmethod
    def from_focal_length(cls, focal_mm: float, sensor_mm: float = 36.0, **kwargs: Any) -> Camera:
        """Build a camera from a lens focal length and the sensor *width*, both in mm.

        ``fov = 2 * atan(sensor_mm / 2 / focal_mm)`` in degrees; e.g. 50 mm on a 36 mm
        sensor gives 39.5978 degrees. ``kwargs`` are passed to ``Camera`` (position,
        look_at, up, width, height). To optimise the field of view, pass ``fov`` as a
        Tensor to the constructor instead.
        """
        focal, sensor = (
            _positive_float(focal_mm, "focal_mm"),
            _positive_float(sensor_mm, "sensor_mm"),
        )
        if "fov" in kwargs:
            raise TypeError("Camera.from_focal_length: pass either focal_mm or fov, not both")
        fov = math.degrees(2.0 * math.atan(sensor / 2.0 / focal))
        return cls(fov=fov, **kwargs)

    def validate(self) -> None:
        """Re-check the current values (shapes, finiteness, fov range, a usable view frame)."""
        fields = self._check_fields()
        position, look_at, up = fields["position"], fields["look_at"], fields["up"]
        _check_int(self.width, "Camera", "width")
        _check_int(self.height, "Camera", "height")
        check_ray_count(self.width, self.height, 1)

        forward = look_at - position
        norm_f = float(np.linalg.norm(forward))
        if norm_f <= 1e-12 * float(max(np.abs(position).max(), np.abs(look_at).max())):
            raise ValueError(
                f"Camera: position and look_at must differ (to 12 digits), got position "
                f"{position} and look_at {look_at}"
            )
        norm_up = float(np.linalg.norm(up))
        if norm_up == 0.0:
            raise ValueError("Camera: up must be a non-zero vector")
        # sin of the angle between up and the view direction; ~0 means no usable "right" axis.
        sin_angle = float(np.linalg.norm(np.cross(forward, up))) / (norm_f * norm_up)
        if sin_angle < 1e-6:
            raise ValueError(
                f"Camera: up {up} is parallel to the view direction {forward / norm_f}"
            )

    def __repr__(self) -> str:
        return f"Camera({self._fields_repr()}, width={self.width}, height={self.height})"


def _positive_float(value: Any, name: str) -> float:
    if isinstance(value, Tensor):
        raise TypeError(
            f"Camera.from_focal_length: {name} must be a number (to optimise the field of "
            "view pass Camera(fov=<Tensor>))"
        )
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(
            f"Camera.from_focal_length: {name} must be a number, got {type(value).__name__}"
        )
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"Camera.from_focal_length: {name} must be positive, got {value}")
    return value


# --------------------------------------------------------------------------------------
# Lights
# --------------------------------------------------------------------------------------


def _strength(name: str) -> Field:
    """A light's scalar strength field (intensity or irradiance), >= 0."""
    return Field(name, ((),), (lambda x: x >= 0.0, ">= 0"))


#: A light's (3,) linear RGB colour, multiplying its strength; white unless given.
_LIGHT_COLOR = Field("color", ((3,),))
WHITE = (1.0, 1.0, 1.0)


class PointLight(_HasFields):
    """An isotropic point light.

    Args:
        position: (3,) position in world space.
        intensity: scalar radiant intensity I (W/sr), >= 0. The irradiance at distance r
            facing the light is ``I / r**2`` (inverse-square falloff).
        color: (3,) linear RGB multiplier of the intensity (white by default).
    """

    FIELDS = (Field("position", ((3,),), IN_RANGE), _strength("intensity"), _LIGHT_COLOR)

    def __init__(self, position: ArrayLike, intensity: ArrayLike, color: ArrayLike = WHITE):
        self._set_fields(position=position, intensity=intensity, color=color)
        self.validate()


class DirectionalLight(_HasFields):
    """A distant light (like the sun): parallel rays, no falloff.

    Args:
        direction: (3,) the direction in which the light **travels**, i.e. from the light
            towards the scene (the Mitsuba / glTF convention). A sun shining straight down
            has ``direction=(0, -1, 0)``. The vector towards the light, used for shading
            and shadow rays, is ``-direction / |direction|``. Need not be unit length, must
            not be zero.
        irradiance: scalar irradiance E (W/m^2) on a surface facing the light, >= 0.
        color: (3,) linear RGB multiplier of the irradiance (white by default).
    """

    # Shading and shadow rays divide by the direction's length: it must not underflow.
    _DIRECTION = Field("direction", ((3,),), (_normalisable, "a vector of length 1e-150 to 1e150"))
    FIELDS = (_DIRECTION, _strength("irradiance"), _LIGHT_COLOR)

    def __init__(self, direction: ArrayLike, irradiance: ArrayLike, color: ArrayLike = WHITE):
        self._set_fields(direction=direction, irradiance=irradiance, color=color)
        self.validate()


# --------------------------------------------------------------------------------------
# Material
# --------------------------------------------------------------------------------------


class Material(_HasFields):
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


# --------------------------------------------------------------------------------------
# Placement
# --------------------------------------------------------------------------------------


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
    return _normalisable(x)


_ROTATION = (
    _rotation_ok,
    "a rotation vector or a non-zero quaternion (a rotation vector's length, its angle, "
    "at most 1e6 degrees)",
)


class Transform(_HasFields):
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
        _check_instance(obj.transform, owner, "transform", Transform)
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


class Mesh(_HasFields):
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
        _check_instance(self.material, "Mesh", "material", Material)
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


class Sphere(_HasFields):
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
        _check_instance(self.material, "Sphere", "material", Material)
        self.material.validate()
        if self.material.textures:
            raise ValueError("Sphere: textured materials are not supported (spheres have no UVs)")
        _check_transform(self, "Sphere")

    def __repr__(self) -> str:
        return f"Sphere(center={_fmt(self.center)}, radius={_fmt(self.radius)}, {self.material!r})"


# --------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------

_OBJECT_TYPES = (Mesh, Sphere)
_LIGHT_TYPES = (PointLight, DirectionalLight)


class Scene:
    """Everything needed to render an image.

    Args:
        objects: iterable of ``Mesh`` and ``Sphere`` objects (stored as a list).
        lights: iterable of ``PointLight`` and ``DirectionalLight`` objects (stored as a
            list; may be empty, e.g. for a purely ambient scene).
        camera: the ``Camera``.
        background: (3,) linear RGB radiance of pixels whose primary ray hits nothing.
    """

    def __init__(
        self,
        objects: Iterable[Mesh | Sphere],
        lights: Iterable[PointLight | DirectionalLight],
        camera: Camera,
        background: ArrayLike = (0, 0, 0),
    ) -> None:
        self.objects = _as_list(objects, "objects")
        self.lights = _as_list(lights, "lights")
        self.camera = camera
        self.background = _as_tensor(background, "Scene", "background")
        self.validate()

    @property
    def meshes(self) -> list[Mesh]:
        """The ``Mesh`` objects, in scene order."""
        return [o for o in self.objects if isinstance(o, Mesh)]

    @property
    def spheres(self) -> list[Sphere]:
        """The ``Sphere`` objects, in scene order."""
        return [o for o in self.objects if isinstance(o, Sphere)]

    def named_parameters(self) -> dict[str, Tensor]:
        """Every continuous parameter tensor of the scene by a readable name, in a fixed
        order: ``{"camera.position": ..., "lights[0].position": ...,
        "objects[0].vertices": ..., "objects[0].transform.rotation": ...,
        "objects[0].material.albedo": ..., "background": ...}``.
        A tensor shared by several owners (e.g. one Material on two meshes) appears once,
        under its first name."""
        named = self.camera.named_parameters("camera.")
        for i, light in enumerate(self.lights):
            named.update(light.named_parameters(f"lights[{i}]."))
        for i, obj in enumerate(self.objects):
            named.update(obj.named_parameters(f"objects[{i}]."))
            if obj.transform is not None:
                named.update(obj.transform.named_parameters(f"objects[{i}].transform."))
            named.update(obj.material.named_parameters(f"objects[{i}].material."))
        named["background"] = self.background
        unique, seen = {}, set()
        for name, tensor in named.items():
            if id(tensor) not in seen:
                seen.add(id(tensor))
                unique[name] = tensor
        return unique

    def parameters(self) -> list[Tensor]:
        """Every continuous parameter tensor of the scene, each once, in the order of
        ``named_parameters``."""
        return list(self.named_parameters().values())

    def with_camera(self, camera: Camera) -> Scene:
        """Another view of this scene: a Scene with ``camera`` and the *same* objects,
        lights and background (shared, not copied, so that a parameter optimised through
        one view is the parameter of every view; ``render.optimize`` takes a list of
        (view, target) pairs). Later edits to the objects or lights show in both; the
        lists themselves are copied."""
        return Scene(self.objects, self.lights, camera, self.background)

    def validate(self) -> None:
        """Re-check every object, light, the camera and the background (cheap)."""
        for i, obj in enumerate(self.objects):
            if not isinstance(obj, _OBJECT_TYPES):
                raise TypeError(
                    f"Scene: objects[{i}] must be a Mesh or a Sphere, got {type(obj).__name__}"
                )
            obj.validate()
        for i, light in enumerate(self.lights):
            if not isinstance(light, _LIGHT_TYPES):
                raise TypeError(
                    f"Scene: lights[{i}] must be a PointLight or a DirectionalLight, "
                    f"got {type(light).__name__}"
                )
            light.validate()
        _check_instance(self.camera, "Scene", "camera", Camera)
        self.camera.validate()
        _check_tensor(self.background, "Scene", "background", [(3,)])
        self.check_relative_range()

    def check_relative_range(self) -> None:
        """The coordinates and the geometry's extent within MAX_COORD_RELATIVE and
        MAX_EXTENT_RELATIVE view distances, else a ValueError naming the parameter, the value
        and the range. A min and a max per array: this runs before every render."""
        camera = self.camera
        view = float(np.linalg.norm(camera.look_at.data - camera.position.data))
        unit = f"the camera's view distance |look_at - position| (= {view:.6g})"
        points = {"camera.position": camera.position.data, "camera.look_at": camera.look_at.data}
        for i, light in enumerate(self.lights):
            if isinstance(light, PointLight):
                points[f"lights[{i}].position"] = light.position.data
        boxes = {}  # per object the two corners (2, 3) of its bounding box
        for i, obj in enumerate(self.objects):
            if obj.transform is not None:
                boxes[i] = points[f"objects[{i}] (placed by its transform)"] = _placed_box(obj)
            elif isinstance(obj, Mesh):
                # The box's corners have the vertices' largest |coordinate|.
                boxes[i] = points[f"objects[{i}].vertices"] = _box(obj.vertices.data)
            else:
                c = points[f"objects[{i}].center"] = obj.center.data
                boxes[i] = np.array([c - obj.radius.data, c + obj.radius.data])
        for name, x in points.items():
            largest = float(np.abs(x).max())
            if largest > MAX_COORD_RELATIVE * view:
                raise ValueError(
                    f"Scene: {name} has a coordinate of magnitude {largest:.6g}; supported: at "
                    f"most {MAX_COORD_RELATIVE:g} x {unit}, i.e. "
                    f"{MAX_COORD_RELATIVE * view:.6g}"
                )
        if boxes:
            corners = np.concatenate(list(boxes.values()))
            extent = float(np.linalg.norm(corners.max(0) - corners.min(0)))
            if extent > MAX_EXTENT_RELATIVE * view:
                # Name the object reaching farthest from where the camera looks.
                reach = {i: np.abs(box - camera.look_at.data).max() for i, box in boxes.items()}
                raise ValueError(
                    f"Scene: the geometry spans {extent:.6g} (its bounding box's diagonal; "
                    f"objects[{max(reach, key=reach.get)}] reaches farthest); supported: at "
                    f"most {MAX_EXTENT_RELATIVE:g} x {unit}, i.e. "
                    f"{MAX_EXTENT_RELATIVE * view:.6g}"
                )

    def __repr__(self) -> str:
        return (
            f"Scene({len(self.meshes)} meshes, {len(self.spheres)} spheres, "
            f"{len(self.lights)} lights, {self.camera!r})"
        )


def _placed_box(obj: Mesh | Sphere) -> np.ndarray:
    """(2, 3) a box holding the object where its transform places it: a rotation about the
    pivot keeps distances to it, so the ball of radius scale * (the farthest point from the
    pivot) around pivot + translation holds it (at most sqrt(3) times larger than the
    tightest box: enough for a range check, and no rotation computed twice)."""
    t = obj.transform
    if isinstance(obj, Mesh):
        reach = float(np.sqrt(np.max(np.sum((obj.vertices.data - t.pivot.data) ** 2, axis=1))))
    else:
        reach = float(np.linalg.norm(obj.center.data - t.pivot.data) + obj.radius.data)
    centre = t.pivot.data + t.translation.data
    return np.array([centre - t.scale.data * reach, centre + t.scale.data * reach])


def _as_list(items: Any, name: str) -> list:
    # A lone object is a common slip (Scene(mesh, ...)); say so instead of iterating it.
    if isinstance(items, _OBJECT_TYPES + _LIGHT_TYPES) or not isinstance(items, Iterable):
        raise TypeError(f"Scene: {name} must be a list, got {type(items).__name__}")
    return list(items)
