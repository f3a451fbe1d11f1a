"""What every lesson shares: the folder its figures go to, how a figure is kept, and how a
solution runs its lesson to reuse the lesson's functions.

A lesson imports it as ``course``: Python puts a script's own folder (lessons/) on the import
path, and a notebook's kernel starts in lessons/. A solution that runs its lesson puts
lessons/ on the path first.
"""

from __future__ import annotations

import contextlib
import io
import os
import runpy
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


def run_lesson(lesson: str) -> dict:
    """The module-level names of ``lessons/<lesson>.py`` after running it, its printout
    hidden: how a solution reuses the functions its lesson wrote instead of writing them
    again (the lesson's figures are written as usual)."""
    with contextlib.redirect_stdout(io.StringIO()):
        return runpy.run_path(str(Path(__file__).resolve().parent / f"{lesson}.py"))
