"""Scene description: the ``Scene`` and its ``Camera``; and, re-exported from the modules
that define them, lights (``render.scene.lights``), materials (``render.scene.materials``),
meshes, spheres and transforms (``render.scene.shapes``).

These classes hold data (and lights their own geometry); the renderer (``render.render`` and
friends) reads them. Every continuous parameter is a ``minidiff.Tensor``, checked before
every render (``render.scene.fields``: the convention and the validation they share).
``Scene.validate()`` also checks the range of coordinates and extent relative to the
camera's view distance (``MAX_COORD_RELATIVE``, ``MAX_EXTENT_RELATIVE``), once for every way
of tracing.

Coordinate system: right-handed, y up (the Newell teapot data, which is z up, is rotated on
loading, see ``render.teapot``). Angles are in degrees. Colours are linear RGB.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from minidiff import Tensor
from render.scene.fields import (
    IN_RANGE,
    MAX_COORD,
    MAX_RAYS,
    ArrayLike,
    Field,
    HasFields,
    as_parameter,
    check_instance,
    check_int,
    check_ray_count,
    check_tensor,
)
from render.scene.lights import DirectionalLight, Light, PointLight
from render.scene.materials import Material
from render.scene.shapes import MAX_ROTATION_DEGREES, Mesh, Sphere, Transform

__all__ = [
    "MAX_COORD",
    "MAX_COORD_RELATIVE",
    "MAX_EXTENT_RELATIVE",
    "MAX_RAYS",
    "MAX_ROTATION_DEGREES",
    "ArrayLike",
    "Camera",
    "DirectionalLight",
    "Light",
    "Material",
    "Mesh",
    "PointLight",
    "Scene",
    "Sphere",
    "Transform",
    "check_ray_count",
]

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


# --------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------


class Camera(HasFields):
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
    (``render.scene.fields``); ``width``/``height`` stay ints.
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
        self.width = check_int(width, "Camera", "width")
        self.height = check_int(height, "Camera", "height")
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
        check_int(self.width, "Camera", "width")
        check_int(self.height, "Camera", "height")
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
# Scene
# --------------------------------------------------------------------------------------

_OBJECT_TYPES = (Mesh, Sphere)


class Scene:
    """Everything needed to render an image.

    Args:
        objects: iterable of ``Mesh`` and ``Sphere`` objects (stored as a list).
        lights: iterable of ``Light`` s (``PointLight``, ``DirectionalLight``; stored as a
            list; may be empty, e.g. for a purely ambient scene).
        camera: the ``Camera``.
        background: (3,) linear RGB radiance of pixels whose primary ray hits nothing.
    """

    def __init__(
        self,
        objects: Iterable[Mesh | Sphere],
        lights: Iterable[Light],
        camera: Camera,
        background: ArrayLike = (0, 0, 0),
        *,
        _checked: bool = False,
    ) -> None:
        self.objects = _as_list(objects, "objects")
        self.lights = _as_list(lights, "lights")
        self.camera = camera
        self.background = as_parameter(background, "Scene", "background")
        if not _checked:  # (internal: parts of a validated scene holding copies of its values)
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
        named = {}
        for prefix, owner in self._owners():
            named.update(owner.named_parameters(prefix))
        named["background"] = self.background
        unique, seen = {}, set()
        for name, tensor in named.items():
            if id(tensor) not in seen:
                seen.add(id(tensor))
                unique[name] = tensor
        return unique

    def parameters(self) -> list[Tensor]:
        """Every continuous parameter tensor of the scene, each once, in the order of
        ``named_parameters`` (the same walk without the names: the path integrator asks
        a dozen times a gradient)."""
        seen, out = set(), []
        for _, owner in self._owners():
            for field in owner.FIELDS:
                t = getattr(owner, field.name)
                if t is not None and id(t) not in seen:
                    seen.add(id(t))
                    out.append(t)
        if id(self.background) not in seen:
            out.append(self.background)
        return out

    def _owners(self) -> Iterator[tuple[str, Any]]:
        """(name prefix, owner) of every owner of parameters but the scene itself, in the
        order of ``named_parameters``: the camera, the lights, each object with its
        transform and material."""
        yield "camera.", self.camera
        for i, light in enumerate(self.lights):
            yield f"lights[{i}].", light
        for i, obj in enumerate(self.objects):
            yield f"objects[{i}].", obj
            if obj.transform is not None:
                yield f"objects[{i}].transform.", obj.transform
            yield f"objects[{i}].material.", obj.material

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
            if not isinstance(light, Light):
                raise TypeError(
                    f"Scene: lights[{i}] must be a PointLight or a DirectionalLight, "
                    f"got {type(light).__name__}"
                )
            light.validate()
        check_instance(self.camera, "Scene", "camera", Camera)
        self.camera.validate()
        check_tensor(self.background, "Scene", "background", [(3,)])
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
            if light.location() is not None:  # a light at infinity has no position
                points[f"lights[{i}].position"] = light.location()
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
    if isinstance(items, (*_OBJECT_TYPES, Light)) or not isinstance(items, Iterable):
        raise TypeError(f"Scene: {name} must be a list, got {type(items).__name__}")
    return list(items)
