"""Execute a lesson as a Jupyter notebook, with this Python's kernel.

Run:  python lessons/run_notebook.py 10            (or 10_monte_carlo, or lessons/10_monte_carlo.py)
      python lessons/run_notebook.py 10 --out DIR  (default out/lessons, or $LESSONS_OUT)

Reads the lesson's percent-format file with jupytext, executes it cell by cell with
nbclient in an IPython kernel started by the Python that runs this script (the ``lessons``
extra installs jupytext, nbclient and ipykernel), and writes the executed notebook to
``<out>/<lesson>.ipynb``: the text, the code, what each cell printed and the figures inline.
The kernel starts in ``lessons/``, as a notebook opened in Jupyter does; the lesson writes
its PNG figures to ``<out>/<lesson>/``.

Why not ``jupytext --to ipynb --execute``: it looks for an installed kernel whose command
is this very Python and fails where there is none ("No kernel found that matches the
current python executable"), e.g. in a fresh virtual environment. This script hands
nbclient a kernel spec for ``sys.executable`` made in a temporary folder: nothing is
installed.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import jupytext
import nbformat
from ipykernel.kernelspec import write_kernel_spec
from jupyter_client.kernelspec import KernelSpecManager
from jupyter_client.manager import AsyncKernelManager
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

LESSONS = Path(__file__).resolve().parent
DEFAULT_OUT = LESSONS.parent / "out" / "lessons"
KERNEL = "diffrt-lessons"  # the temporary kernel spec's name


def find_lesson(name: str) -> Path:
    """The lesson file named by its number ("10"), its name ("10_monte_carlo") or a path."""
    path = Path(name)
    if path.is_file():
        return path.resolve()
    pattern = f"{path.stem.zfill(2)}_*.py" if path.stem.isdigit() else f"{path.stem}.py"
    matches = sorted(LESSONS.glob(pattern))
    if len(matches) != 1:
        known = ", ".join(p.stem for p in sorted(LESSONS.glob("[0-9][0-9]_*.py")))
        raise SystemExit(f"no single lesson named {name!r}; the lessons: {known}")
    return matches[0]


def execute_lesson(
    lesson: Path, notebook: Path, lessons_out: Path | None = None, timeout: int = 600
) -> nbformat.NotebookNode:
    """Execute ``lesson`` (a percent-format .py file) as a notebook in a kernel of this
    Python started in the lesson's folder, and write the executed notebook to ``notebook``
    (also when a cell fails: then CellExecutionError is raised after writing).
    ``lessons_out``, if given, is the kernel's LESSONS_OUT (where the lesson writes its
    figures); otherwise the lesson's default, ``out/lessons`` in the repository.
    ``timeout``: seconds a cell may take."""
    nb = jupytext.read(lesson)
    env = dict(os.environ)
    if lessons_out is not None:
        env["LESSONS_OUT"] = str(Path(lessons_out).resolve())
    with tempfile.TemporaryDirectory() as kernels:
        # A kernel spec whose command is sys.executable, found only by this manager.
        write_kernel_spec(Path(kernels) / KERNEL)
        specs = KernelSpecManager(kernel_dirs=[kernels])
        km = AsyncKernelManager(kernel_name=KERNEL, kernel_spec_manager=specs)
        client = NotebookClient(nb, km=km, timeout=timeout, kernel_name=KERNEL)
        try:
            # cleanup_kc: shut the kernel down at the end although nbclient did not start it.
            client.execute(cleanup_kc=True, cwd=str(lesson.parent), env=env)
        finally:
            # Saved with the standard kernel's name, so that Jupyter opens it as usual.
            nb.metadata["kernelspec"] = {
                "name": "python3",
                "display_name": "Python 3 (ipykernel)",
                "language": "python",
            }
            notebook.parent.mkdir(parents=True, exist_ok=True)
            nbformat.write(nb, notebook)
    return nb


def main(argv: list[str] | None = None) -> Path:
    """The command line (see the module docstring); returns the executed notebook's path."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("lesson", help="number (10), name (10_monte_carlo) or path of a lesson")
    parser.add_argument(
        "--out",
        type=Path,
        help=f"folder of the notebook and the figures (default $LESSONS_OUT or {DEFAULT_OUT})",
    )
    parser.add_argument("--timeout", type=int, default=600, help="seconds per cell (600)")
    args = parser.parse_args(argv)
    lesson = find_lesson(args.lesson)
    out = args.out or Path(os.environ.get("LESSONS_OUT") or DEFAULT_OUT)
    notebook = out / f"{lesson.stem}.ipynb"
    try:
        execute_lesson(lesson, notebook, out, args.timeout)
    except CellExecutionError as error:
        print(error, file=sys.stderr)
        raise SystemExit(f"{lesson.name}: a cell failed; the notebook so far: {notebook}") from None
    print(f"wrote {notebook} (figures in {out / lesson.stem})")
    return notebook


if __name__ == "__main__":
    main()
