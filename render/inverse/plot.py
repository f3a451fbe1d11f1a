"""Line plots with matplotlib: loss curves, error curves and benchmark charts.

``line_figure`` builds a matplotlib ``Figure`` (shown inline when it ends a notebook cell,
and yours to change: ``figure.axes[0]`` is the plot); ``line_plot`` saves one as a PNG.
Neither touches ``matplotlib.pyplot``'s global state (no current figure, no backend
switch), so plots can be drawn from several threads and inside any program.
"""

from __future__ import annotations

import io
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def line_figure(
    series: dict[str, tuple[Sequence[float], Sequence[float]]],
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    logx: bool = False,
    logy: bool = False,
    size: tuple[int, int] = (640, 420),
    references: Collection[str] = (),
) -> Figure:
    """One or more (x, y) series as lines (with markers when short) on one axes, with a
    legend; non-finite points, and non-positive ones on log axes, are left out.
    ``references``: names of series that are guides rather than data (e.g. a slope): drawn
    thin, grey, dashed (each its own dash) and beneath the data. ``size``: pixels at 100
    dpi."""
    figure = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)  # lets the figure render to PNG without pyplot
    ax = figure.add_subplot()
    drawn, dashes = 0, iter(["--", ":", "-.", (0, (5, 5))] * len(series))
    for name, (x, y) in series.items():
        x, y = np.asarray(x, float), np.asarray(y, float)
        keep = np.isfinite(x) & np.isfinite(y)
        keep &= (x > 0) if logx else True
        keep &= (y > 0) if logy else True
        if not keep.any():
            continue
        drawn += 1
        if name in references:
            ax.plot(x[keep], y[keep], linestyle=next(dashes), color="0.45", linewidth=1,
                    label=name, zorder=1)  # fmt: skip
        else:
            marker = "o" if keep.sum() <= 40 else None
            ax.plot(x[keep], y[keep], marker=marker, markersize=4, linewidth=1.5, label=name,
                    zorder=2)  # fmt: skip
    if drawn == 0:
        raise ValueError("line_plot: no finite points to draw")
    ax.set_xscale("log" if logx else "linear")
    ax.set_yscale("log" if logy else "linear")
    ax.set_title(title, fontsize=10, loc="left")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="major", color="0.9")
    if len(series) > 1:
        ax.legend(fontsize=8, frameon=False)
    return figure


def line_plot(
    series: dict[str, tuple[Sequence[float], Sequence[float]]],
    path: str | Path,
    *args: Any,
    **options: Any,
) -> Path:
    """``line_figure(series, *args, **options)`` (title, labels, ...) saved as a PNG at
    ``path`` (folders created); returns the path."""
    figure = line_figure(series, *args, **options)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    return path


def show(figure: Figure) -> None:
    """Display ``figure`` inline when this runs in Jupyter (an IPython kernel); nothing in
    a plain script (which saves its figures instead)."""
    try:
        from IPython import get_ipython
        from IPython.display import Image, display
    except ImportError:
        return
    if get_ipython() is not None:
        png = io.BytesIO()
        figure.savefig(png, format="png")
        display(Image(data=png.getvalue(), format="png"))
