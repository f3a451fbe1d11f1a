"""Image files and image losses.

Rendered images are (H, W, 3) arrays of *linear* radiance. Writing one to an 8-bit file
clips to [0, 1] and optionally applies the sRGB transfer curve (what monitors expect);
reading one back returns floats in [0, 1], optionally decoded back to linear.

``mse`` is the paper's image loss (Eq. 1); it stays differentiable when the rendered image
is a ``minidiff.Tensor``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from minidiff import Tensor

__all__ = [
    "save_image",
    "load_image",
    "mse",
    "psnr",
    "linear_to_srgb",
    "srgb_to_linear",
    "SUPPORTED_IMAGE_EXTENSIONS",
]

#: File extensions ``save_image`` can write (the format follows the extension).
SUPPORTED_IMAGE_EXTENSIONS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1), elementwise, for x in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    # Linear segment near black avoids the infinite slope of a pure power law at 0.
    return np.where(
        x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0), 1 / 2.4) - 0.055
    )


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Inverse of ``linear_to_srgb``, elementwise, for x in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, np.power((np.maximum(x, 0.0) + 0.055) / 1.055, 2.4))


def _as_array(img: Any) -> np.ndarray:
    """The float ndarray behind an ndarray-like or a ``minidiff.Tensor``."""
    data = img.data if isinstance(img, Tensor) else img
    return np.asarray(data, dtype=np.float64)


def save_image(img: Any, path: str | Path, srgb: bool = False) -> Path:
    """Write a linear float image as an 8-bit PNG or JPEG (chosen by the extension).

    Args:
        img: (H, W, 3) colour or (H, W) grey image, ndarray or ``minidiff.Tensor``
            (its ``.data`` is used). Values are clipped to [0, 1]; +-inf clip too, NaN is
            an error (it usually means a bug upstream, better not hidden as black).
        path: destination; parent directories are created.
        srgb: apply the sRGB transfer curve before quantising (for viewing on a screen).
            Leave False to store linear values, e.g. for exact round trips in tests.

    Returns:
        The ``Path`` written.
    """
    path = Path(path)
    fmt = SUPPORTED_IMAGE_EXTENSIONS.get(path.suffix.lower())
    if fmt is None:
        supported = ", ".join(SUPPORTED_IMAGE_EXTENSIONS)
        raise ValueError(f"save_image: unsupported extension {path.suffix!r} ({supported})")
    array = _as_array(img)
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3) or 0 in array.shape:
        raise ValueError(f"save_image: img must have shape (H, W, 3) or (H, W), got {array.shape}")
    if np.isnan(array).any():
        raise ValueError("save_image: img contains NaN values")

    array = np.clip(array, 0.0, 1.0)
    if srgb:
        array = linear_to_srgb(array)
    pixels = np.round(array * 255.0).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    # uint8 (H, W) -> mode "L", (H, W, 3) -> "RGB"
    Image.fromarray(pixels).save(path, format=fmt)
    return path


def load_image(path: str | Path, srgb: bool = False) -> np.ndarray:
    """Read an image file as an (H, W, 3) float64 array in [0, 1].

    Grey, grey+alpha, RGBA and palette images are converted to RGB (alpha is dropped, not
    composited); 16-bit greyscale keeps its precision.

    Args:
        path: any format Pillow reads (PNG, JPEG, ...).
        srgb: decode the sRGB transfer curve, returning linear values.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: the file is not a readable image.
    """
    if not isinstance(path, str | Path):
        raise TypeError(f"load_image: path must be a str or Path, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"load_image: no such file: {path}")
    try:
        with Image.open(path) as im:
            if im.mode.startswith("I"):  # 16/32-bit integer greyscale (e.g. 16-bit PNG)
                grey = np.asarray(im, dtype=np.float64) / 65535.0
                array = np.repeat(np.clip(grey, 0.0, 1.0)[:, :, None], 3, axis=2)
            elif im.mode == "F":  # 32-bit float greyscale: values are taken as they are
                grey = np.asarray(im, dtype=np.float64)
                if not np.isfinite(grey).all():  # a float TIFF can hold NaN or inf
                    bad = int((~np.isfinite(grey)).sum())
                    raise ValueError(f"load_image: {path} has {bad} pixels that are NaN or inf")
                array = np.repeat(np.clip(grey, 0.0, 1.0)[:, :, None], 3, axis=2)
            else:
                array = np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0
    except Image.DecompressionBombError as err:  # Pillow's guard against huge images
        raise ValueError(
            f"load_image: {path} is larger than Pillow's safety limit of "
            f"{Image.MAX_IMAGE_PIXELS:,} pixels: {err}"
        ) from err
    except (UnidentifiedImageError, OSError, SyntaxError) as err:
        # OSError covers truncated files; SyntaxError is what some Pillow plugins raise.
        raise ValueError(f"load_image: cannot read {path} as an image: {err}") from err
    return srgb_to_linear(array) if srgb else array


def _check_same_shape(image: Any, target: Any, fn: str) -> None:
    a, b = (
        np.shape(image.data if isinstance(image, Tensor) else image),
        np.shape(target.data if isinstance(target, Tensor) else target),
    )
    if a != b:
        raise ValueError(f"{fn}: image and target shapes differ: {a} vs {b}")


def mse(image: Any, target: Any) -> Tensor | float:
    """Mean squared error ``mean((image - target) ** 2)`` over all pixels and channels.

    This is the paper's loss (Eq. 1). If ``image`` (or ``target``) is a ``minidiff.Tensor``
    the result is a 0-d Tensor built from tensor ops, so ``loss.backward()`` reaches the
    scene parameters; for plain arrays it is a Python float. Shapes must match exactly
    (no broadcasting: a mismatch is almost always a bug).
    """
    _check_same_shape(image, target, "mse")
    if isinstance(image, Tensor) or isinstance(target, Tensor):
        # Tensor.__array_ufunc__ is None, so NumPy defers to the Tensor's operators in
        # either order: the difference is a Tensor whichever side the array is on.
        image = image if isinstance(image, Tensor) else _as_array(image)
        target = target if isinstance(target, Tensor) else _as_array(target)
        d = image - target
        return (d * d).mean()
    d = _as_array(image) - _as_array(target)
    return float(np.mean(d * d))


def psnr(image: Any, target: Any, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio ``10 log10(peak^2 / mse)`` in dB; ``inf`` if equal.

    Accepts ndarrays or Tensors (their values are used; the result is not differentiable).
    """
    _check_same_shape(image, target, "psnr")
    err = float(np.mean((_as_array(image) - _as_array(target)) ** 2))
    if err == 0.0:
        return math.inf
    return 10.0 * math.log10(peak * peak / err)
