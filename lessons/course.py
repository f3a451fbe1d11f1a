"""What every lesson shares: the folder its figures go to, and how a figure is kept.

A lesson imports it as ``course``: Python puts a script's own folder (lessons/) on the import
path, and a notebook's kernel starts in lessons/. A solution that runs its lesson puts
lessons/ on the path first.
"""

from __future__ import annotations

import os
from pathlib import Path

from matplotlib.figure import Figure

from render.inverse.plot import show


def figures_folder(lesson: str) -> Path:
    """``out/lessons/<lesson>/`` in the repository (beside lessons/), or
    ``$LESSONS_OUT/<lesson>`` where that variable is set; created if missing. The same
    folder whether the lesson runs as a script or as a notebook (which has no ``__file__``
    of its own)."""
    repository = Path(__file__).resolve().parent.parent
    folder = Path(os.environ.get("LESSONS_OUT") or repository / "out" / "lessons") / lesson
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def save_and_show(figure: Figure, path: Path) -> None:
    """Save ``figure`` as a PNG at ``path`` and, when the lesson runs as a notebook, show it
    inline (a script only saves it)."""
    figure.savefig(path)
    show(figure)
