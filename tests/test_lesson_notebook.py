"""A lesson opened as a notebook runs as one: the percent-format file read by jupytext and
executed cell by cell by a Jupyter kernel (nbclient + ipykernel, the ``lessons`` extra),
its figure shown inline."""

from __future__ import annotations

from pathlib import Path

import jupytext
import nbclient

ROOT = Path(__file__).resolve().parent.parent


def test_lesson_01_runs_as_a_notebook_with_its_figure_inline(tmp_path, monkeypatch):
    monkeypatch.setenv("LESSONS_OUT", str(tmp_path))  # the kernel inherits the environment
    notebook = jupytext.read(ROOT / "lessons" / "01_tape.py")
    assert sum(cell.cell_type == "markdown" for cell in notebook.cells) > 5
    client = nbclient.NotebookClient(
        notebook, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
    )
    client.execute()  # raises CellExecutionError if a cell fails
    outputs = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.outputs]
    assert any("image/png" in o.get("data", {}) for o in outputs)  # fd_error shown inline
    assert any("central difference" in o.get("text", "") for o in outputs)  # its prints
    assert (tmp_path / "01_tape" / "fd_error.png").stat().st_size > 0  # and saved
