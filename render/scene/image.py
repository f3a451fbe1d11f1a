"""Image files and image losses.

Rendered images are (H, W, 3) arrays of *linear* radiance. Writing one to an 8-bit file
clips to [0, 1] and optionally applies the sRGB transfer curve (what monitors expect);
reading one back returns floats in [0, 1], optionally decoded back to linear.

``mse`` is the paper's image loss (Eq. 1); it stays differentiable when the rendered image
is a ``minidiff.Tensor``. ``write_gradient_png`` writes a signed gradient image
(``render.gradient_image``) in diverging colours with a scale bar.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, UnidentifiedImageError

from minidiff import Tensor, mean_squared_error

__all__ = [
    "save_image",
    "load_image",
    "mse",
    "psnr",
    "linear_to_srgb",
    "srgb_to_linear",
    "SUPPORTED_IMAGE_EXTENSIONS",
    "write_gradient_png",
    "diverging_colours",
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
        return mean_squared_error(image, target)
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


# Diverging colours (ColorBrewer RdBu): -1 blue, 0 white, +1 red, with lighter tints at +-0.5.
_DIVERGING_STOPS = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
_DIVERGING_RGB = np.array(
    [[33, 102, 172], [146, 197, 222], [255, 255, 255], [244, 165, 130], [178, 24, 43]],
    dtype=np.float64,
)


def diverging_colours(values: np.ndarray, scale: float) -> np.ndarray:
    """uint8 RGB (..., 3) for ``values`` (...): 0 white, positive red, negative blue, full
    colour at +-scale and beyond (values are clipped to [-scale, scale])."""
    t = np.clip(np.asarray(values, dtype=np.float64) / scale, -1.0, 1.0)
    rgb = np.stack([np.interp(t, _DIVERGING_STOPS, c) for c in _DIVERGING_RGB.T], axis=-1)
    return np.round(rgb).astype(np.uint8)


def write_gradient_png(
    image_or_channel: Any,
    path: str | Path,
    scale: float | None = None,
    label: str = "",
    min_width: int = 256,
) -> Path:
    """Write a gradient image (``render.gradient_image``) as a diverging-colour PNG with a
    scale bar; returns the ``Path`` written.

    image_or_channel: (H, W, 3) (its three channels are summed: the derivative of R + G + B)
        or (H, W) (e.g. one channel), ndarray or ``minidiff.Tensor``.
    scale: the value shown in full colour, symmetric: -scale blue, 0 white, +scale red;
        larger magnitudes are clipped. None: the 99.5th percentile of |value| over the
        pixels (a few silhouette pixels with much larger values would otherwise wash out
        the rest), or 1 if all values are 0.
    label: a caption drawn above the scale bar (e.g. the parameter's name).
    min_width: the picture is enlarged by an integer factor (nearest neighbour) to at
        least this width, so that small images and the bar's numbers stay legible.
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"write_gradient_png: path must end in .png, got {path.suffix!r}")
    array = _as_array(image_or_channel)
    if array.ndim == 3 and array.shape[2] == 3:
        array = array.sum(axis=2)
    if array.ndim != 2 or 0 in array.shape:
        raise ValueError(
            "write_gradient_png: image_or_channel must have shape (H, W, 3) or (H, W), got "
            f"{_as_array(image_or_channel).shape}"
        )
    if not np.isfinite(array).all():
        raise ValueError("write_gradient_png: image_or_channel contains NaN or inf values")
    if scale is None:
        scale = float(np.percentile(np.abs(array), 99.5)) or float(np.abs(array).max()) or 1.0
    elif not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"write_gradient_png: scale must be a positive number, got {scale!r}")

    factor = max(1, math.ceil(min_width / array.shape[1]))
    picture = np.repeat(np.repeat(diverging_colours(array, scale), factor, 0), factor, 1)
    height, width = picture.shape[:2]
    bar_top, bar_height, margin = height + (22 if label else 8), 14, 34
    canvas = Image.new("RGB", (width, bar_top + bar_height + margin), "white")
    canvas.paste(Image.fromarray(picture), (0, 0))
    draw = ImageDraw.Draw(canvas)
    if label:
        draw.text((6, height + 5), label, fill="black")
    left, right = 12, width - 12
    ramp = diverging_colours(np.linspace(-scale, scale, right - left), scale)
    canvas.paste(Image.fromarray(np.repeat(ramp[None], bar_height, 0)), (left, bar_top))
    draw.rectangle([left, bar_top, right - 1, bar_top + bar_height - 1], outline="black")
    for u, value in ((left, -scale), ((left + right) // 2, 0.0), (right - 1, scale)):
        text = "0" if value == 0 else f"{value:+.3g}"
        draw.line([u, bar_top + bar_height, u, bar_top + bar_height + 4], fill="black")
        x = min(max(u - 3 * len(text), 0), width - 6 * len(text))
        draw.text((x, bar_top + bar_height + 7), text, fill="black")
    path.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(path, format="PNG")
    return path
