"""Step 0, on the tape: objects placed in the world by their ``Transform``.

``placed(scene)`` returns the scene the later steps render: every object that has a
transform is replaced by a copy whose geometry is in world space (vertices, shading
normals, a sphere's centre and radius), computed here with minidiff from the object's own
geometry and the transform's fields. The tracers read the copy's values; the surfaces,
shading and edge terms differentiate through it, so the gradient reaches the rotation, the
translation, the scale and the object-space vertices alike. A scene without transforms is
returned as it is.

The rotation is a 3 x 3 matrix built on the tape from either form ``Transform`` accepts:

* a rotation vector r (degrees; axis times angle). With theta = |r| in radians and K the
  cross-product matrix of r in radians (K v = r x v), Rodrigues' formula

      R = I + A K + B K^2,   A = sin(theta) / theta,   B = (1 - cos(theta)) / theta^2.

  A and B are smooth functions of s = theta^2 (their series have only even powers of
  theta), but the closed forms divide by theta, whose derivative at 0 is infinite. So
  both are computed from s: by their Taylor series below ``SERIES_BELOW`` (exact there to
  double precision, derivative included), in closed form above (B written as
  2 (sin(theta / 2) / theta)^2, which loses no digits to 1 - cos). Which branch is used is
  a constant decision, as visibility is; the two agree to rounding where they meet.
* a quaternion q = (w, x, y, z), any non-zero length: R = I + (2 / |q|^2) M(q), M the
  quadratic terms of the unit-quaternion matrix; smooth wherever q is not zero.
"""

from __future__ import annotations

import copy

import numpy as np

import minidiff as md
from render.scene.scene import Mesh, Scene, Sphere, Transform

#: theta (radians) below which A and B come from their series (four terms each: the first
#: neglected one is below 1e-18 there).
SERIES_BELOW = 1e-2


def placed(scene: Scene) -> Scene:
    """The scene with every transformed object replaced by its world-space copy (on the
    tape); ``scene`` itself if no object has a transform. The copy shares the scene's
    camera, lights, materials and untransformed objects (nothing is copied but the list)."""
    if all(obj.transform is None for obj in scene.objects):
        return scene
    world = copy.copy(scene)
    world.objects = [_placed_object(obj) for obj in scene.objects]
    world.check_relative_range()
    return world


def _placed_object(obj: Mesh | Sphere) -> Mesh | Sphere:
    """A shallow copy of ``obj`` in world space, with no transform (the original's id is
    kept as ``source_id``, so that caches keyed on the object recognise it)."""
    transform = obj.transform
    if transform is None:
        return obj
    out = copy.copy(obj)
    out.transform, out.source_id = None, getattr(obj, "source_id", id(obj))
    rotation = rotation_matrix(transform.rotation)
    if isinstance(obj, Mesh):
        out.vertices = apply(transform, rotation, obj.vertices)
        if obj.normals is not None:  # a uniform scale leaves normals' directions alone
            out.normals = md.matmul(obj.normals, md.transpose(rotation))
    else:
        out.center = apply(transform, rotation, md.reshape(obj.center, (1, 3)))[0]
        out.radius = transform.scale * obj.radius
    return out


def apply(transform: Transform, rotation: md.Tensor, points: md.Tensor) -> md.Tensor:
    """World positions (n, 3) of object-space ``points`` (n, 3):
    pivot + translation + scale * R (p - pivot), with ``rotation`` = R (3, 3)."""
    local = points - transform.pivot
    return (
        transform.pivot
        + transform.translation
        + transform.scale * md.matmul(local, md.transpose(rotation))
    )


def rotation_matrix(rotation) -> md.Tensor:
    """The (3, 3) rotation matrix of a rotation vector in degrees (3,) or a quaternion
    (w, x, y, z) (4,), on the tape (see the module docstring)."""
    rotation = md.as_tensor(rotation)
    if rotation.shape in ((3,), (4,)) and _unturned(rotation):
        # What the formulas below give for it, exactly (K and m are zero), without their
        # forty steps: a transform that only moves or scales, at every render.
        return md.tensor(np.eye(3))
    if rotation.shape == (4,):
        return _quaternion_matrix(rotation)
    if rotation.shape != (3,):
        raise ValueError(
            f"rotation_matrix: rotation must have shape (3,) (a rotation vector) or (4,) "
            f"(a quaternion), got {rotation.shape}"
        )
    r = rotation * (np.pi / 180.0)
    s = md.dot(r, r)
    if float(s.data) < SERIES_BELOW**2:
        a = 1.0 - s / 6.0 + s * s / 120.0 - s * s * s / 5040.0
        b = 0.5 - s / 24.0 + s * s / 720.0 - s * s * s / 40320.0
    else:
        theta = md.sqrt(s)
        a = md.sin(theta) / theta
        half = md.sin(theta * 0.5) / theta
        b = 2.0 * half * half
    k = _cross_matrix(r)
    return np.eye(3) + a * k + b * md.matmul(k, k)


def _unturned(rotation: md.Tensor) -> bool:
    """Whether ``rotation`` (a rotation vector (3,) or a quaternion (4,)) is a constant
    whose axis part is zero: the identity, with no derivative to carry."""
    axis = rotation.data[-3:]
    if rotation.is_differentiated() or np.any(axis):
        return False
    return rotation.shape == (3,) or bool(np.isfinite(rotation.data[0]) and rotation.data[0] != 0)


def _cross_matrix(r: md.Tensor) -> md.Tensor:
    """K (3, 3) with K v = r x v."""
    x, y, z = r[0], r[1], r[2]
    zero = md.tensor(np.zeros((), dtype=r.dtype))
    return md.stack([md.stack([zero, -z, y]), md.stack([z, zero, -x]), md.stack([-y, x, zero])])


def _quaternion_matrix(q: md.Tensor) -> md.Tensor:
    """R (3, 3) of the quaternion q / |q|, q = (w, x, y, z) non-zero."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    m = md.stack([
        md.stack([-(y * y + z * z), x * y - w * z, x * z + w * y]),
        md.stack([x * y + w * z, -(x * x + z * z), y * z - w * x]),
        md.stack([x * z - w * y, y * z + w * x, -(x * x + y * y)]),
    ])  # fmt: skip
    return np.eye(3) + (2.0 / md.dot(q, q)) * m
