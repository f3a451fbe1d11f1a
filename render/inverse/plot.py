"""Tiny line plots with Pillow (no plotting library needed): loss curves and benchmark charts."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

_COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189)]


def _ticks(lo: float, hi: float, log: bool) -> list[float]:
    """Round tick positions covering [lo, hi] (in data units; powers of ten on log axes)."""
    if log:
        return [10.0**e for e in range(math.floor(lo), math.ceil(hi) + 1)]
    step = 10 ** math.floor(math.log10(max(hi - lo, 1e-300)))
    for mult in (1, 2, 5, 10):
        if (hi - lo) / (step * mult) <= 6:
            step *= mult
            break
    return list(np.arange(math.floor(lo / step) * step, hi + step * 0.5, step))


def line_plot(
    series: dict[str, tuple[Sequence[float], Sequence[float]]],
    path: str | Path,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    logx: bool = False,
    logy: bool = False,
    size: tuple[int, int] = (640, 420),
) -> Path:
    """Draw one or more (x, y) series as lines with markers and save a PNG; returns its path.

    Non-positive values are dropped on log axes. Axis ticks are labelled in data units.
    """
    width, height = size
    left, right, top, bottom = 70, 20, 30, 50
    img = Image.new("RGB", size, "white")
    draw = ImageDraw.Draw(img)

    def transform(v: np.ndarray, log: bool) -> np.ndarray:
        return np.log10(v) if log else v

    cleaned = {}
    for name, (x, y) in series.items():
        x, y = np.asarray(x, float), np.asarray(y, float)
        keep = np.isfinite(x) & np.isfinite(y)
        keep &= (x > 0) if logx else True
        keep &= (y > 0) if logy else True
        if keep.any():
            cleaned[name] = (transform(x[keep], logx), transform(y[keep], logy))
    if not cleaned:
        raise ValueError("line_plot: no finite points to draw")
    xs = np.concatenate([x for x, _ in cleaned.values()])
    ys = np.concatenate([y for _, y in cleaned.values()])
    x0, x1 = float(xs.min()), float(xs.max())
    y0, y1 = float(ys.min()), float(ys.max())
    if x1 == x0:
        x0, x1 = x0 - 1, x1 + 1
    if y1 == y0:
        y0, y1 = y0 - 1, y1 + 1
    pad = 0.05 * (y1 - y0)
    y0, y1 = y0 - pad, y1 + pad

    def px(x, y):
        u = left + (x - x0) / (x1 - x0) * (width - left - right)
        v = height - bottom - (y - y0) / (y1 - y0) * (height - top - bottom)
        return u, v

    draw.rectangle([left, top, width - right, height - bottom], outline="black")
    for axis, (lo, hi, log) in enumerate(((x0, x1, logx), (y0, y1, logy))):
        for tick in _ticks(lo, hi, log):
            t = math.log10(tick) if log else tick
            if not lo <= t <= hi:
                continue
            label = f"{tick:g}"
            if axis == 0:
                u, _ = px(t, y0)
                draw.line([u, height - bottom, u, height - bottom + 4], fill="black")
                draw.text((u - 3 * len(label), height - bottom + 6), label, fill="black")
            else:
                _, v = px(x0, t)
                draw.line([left - 4, v, left, v], fill="black")
                draw.line([left, v, width - right, v], fill=(230, 230, 230))
                draw.text((left - 8 - 6 * len(label), v - 5), label, fill="black")
    for i, (name, (x, y)) in enumerate(cleaned.items()):
        colour = _COLOURS[i % len(_COLOURS)]
        points = [px(a, b) for a, b in zip(x, y, strict=True)]
        if len(points) > 1:
            draw.line(points, fill=colour, width=2)
        if len(points) <= 40:
            for u, v in points:
                draw.ellipse([u - 3, v - 3, u + 3, v + 3], fill=colour)
        draw.text((left + 10, top + 8 + 14 * i), name, fill=colour)
    draw.text((left, 8), title, fill="black")
    draw.text(((width - 6 * len(xlabel)) / 2, height - 20), xlabel, fill="black")
    draw.text((4, 8), ylabel if len(ylabel) < 12 else "", fill="black")
    if len(ylabel) >= 12:
        draw.text((width - right - 6 * len(ylabel), height - 20), ylabel, fill="black")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)
    return path
