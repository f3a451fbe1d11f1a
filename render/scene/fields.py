"""The machinery every scene class shares: continuous parameters declared once per class
(``Field``), converted to ``minidiff.Tensor`` s and re-checked before every render
(``HasFields``), and the supported ranges they are checked against.

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
naming the class and the argument.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

import minidiff
from minidiff import Tensor

# Anything we accept where a continuous parameter is expected.
ArrayLike = Tensor | np.ndarray | Sequence[float] | float | int


def as_parameter(value: Any, owner: str, name: str) -> Tensor:
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


def check_tensor(
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
    if not isinstance(data, np.ndarray) or data.dtype.kind != "f":  # (np.floating's kind)
        dtype = getattr(data, "dtype", type(data).__name__)
        raise TypeError(f"{owner}: {name} must hold floating-point values, got {dtype}")
    if data.shape not in shapes and not any(_shape_matches(data.shape, s) for s in shapes):
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


def check_int(value: Any, owner: str, name: str) -> int:
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


def normalisable(v: np.ndarray) -> bool:
    """True if ``v / |v|`` is a finite unit vector: |v| is neither zero nor so small that
    its square underflows, nor so large that it overflows (1e-150 < |v| < 1e150)."""
    with np.errstate(over="ignore", under="ignore"):
        length = np.sqrt(np.sum(np.square(v, dtype=np.float64)))
    return bool(1e-150 < length < 1e150)


def check_instance(value: Any, owner: str, name: str, cls: type) -> None:
    if not isinstance(value, cls):
        raise TypeError(f"{owner}: {name} must be a {cls.__name__}, got {type(value).__name__}")


def fmt(t: Tensor) -> str:
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

    @functools.cached_property
    def named(self) -> bool:
        """Whether a shape names a size (then checked against the other fields')."""
        return any(isinstance(d, str) for shape in self.shapes for d in shape)


class HasFields:
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
                setattr(self, f.name, as_parameter(value, owner, f.name))

    def _check_fields(self) -> dict[str, np.ndarray]:
        """Check every field's current value; return the data of those that are set."""
        owner, sizes, data = type(self).__name__, {}, {}
        for f in self.FIELDS:
            value = getattr(self, f.name)
            if value is None and f.optional:
                continue
            if not f.named:
                x = data[f.name] = check_tensor(value, owner, f.name, f.shapes)
            else:
                # Named sizes already bound by an earlier field become exact sizes.
                shapes = [tuple(sizes.get(d, d) for d in shape) for shape in f.shapes]
                x = data[f.name] = check_tensor(value, owner, f.name, shapes)
                for d, n in zip(f.shapes[0], x.shape, strict=False):
                    if isinstance(d, str):
                        sizes.setdefault(d, n)
            if f.constraint is not None and not f.constraint[0](x):
                shown = float(x) if x.ndim == 0 else x
                raise ValueError(f"{owner}: {f.name} must be {f.constraint[1]}, got {shown}")
        return data

    @classmethod
    def holding(cls, **values: Any):
        """An instance whose attributes are ``values``, unchecked and without a call to
        ``__init__``: how a compiled function (``minidiff.compile``) runs the class's own
        formulas on traced arrays (``render.shade.compiled``)."""
        instance = cls.__new__(cls)
        for name, value in values.items():
            setattr(instance, name, value)
        return instance

    def named_parameters(self, prefix: str = "") -> dict[str, Tensor]:
        """The set continuous parameters by name, e.g. ``{"position": <Tensor>, ...}``."""
        fields = {f.name: getattr(self, f.name) for f in self.FIELDS}
        return {prefix + name: t for name, t in fields.items() if t is not None}

    def validate(self) -> None:
        """Re-check the current values."""
        self._check_fields()

    def _fields_repr(self) -> str:
        return ", ".join(
            f"{f.name}={'None' if getattr(self, f.name) is None else fmt(getattr(self, f.name))}"
            for f in self.FIELDS
        )

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._fields_repr()})"
