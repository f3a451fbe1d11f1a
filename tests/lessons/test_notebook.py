"""A lesson runs as a notebook by one command, ``python lessons/run_notebook.py NN`` (issue
41): the percent-format file read by jupytext, executed by nbclient in a kernel of this
Python (nothing installed: ``jupytext --execute`` fails where no kernel spec names this
interpreter), the executed notebook and the figures written under out/lessons/."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import nbformat
import pytest
from nbclient.exceptions import CellExecutionError

ROOT = Path(__file__).resolve().parents[2]

# Starts kernels, i.e. new Python processes: runs after the in-process tests (conftest.py).
pytestmark = pytest.mark.new_processes


def _runner():
    spec = importlib.util.spec_from_file_location(
        "run_notebook", ROOT / "lessons" / "run_notebook.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _outputs(notebook: nbformat.NotebookNode) -> list[dict]:
    return [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.outputs]


def test_the_command_executes_lesson_01_as_a_notebook(tmp_path):
    """The documented command, run as a user would, from another folder."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "lessons" / "run_notebook.py"), "1", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-4000:]
    notebook = nbformat.read(tmp_path / "01_tape.ipynb", as_version=4)
    assert sum(cell.cell_type == "markdown" for cell in notebook.cells) > 5
    assert notebook.metadata.kernelspec.name == "python3"
    outputs = _outputs(notebook)
    assert any("image/png" in o.get("data", {}) for o in outputs)  # fd_error shown inline
    assert any("central difference" in o.get("text", "") for o in outputs)  # its prints
    assert not any(o.output_type == "error" for o in outputs)
    assert (tmp_path / "01_tape" / "fd_error.png").stat().st_size > 0  # and saved


def test_a_notebook_writes_its_figures_to_out_lessons_beside_lessons(tmp_path, monkeypatch):
    """Without LESSONS_OUT, a lesson executed as a notebook (no __file__; the kernel starts
    in the lesson's folder) writes to out/lessons/ of the folder above it, as it does when
    run as a script: here a copy of the course in a temporary repository."""
    monkeypatch.delenv("LESSONS_OUT", raising=False)
    lesson = tmp_path / "lessons" / "01_tape.py"
    lesson.parent.mkdir()
    for name in ("01_tape.py", "course.py"):
        shutil.copy(ROOT / "lessons" / name, lesson.parent / name)
    _runner().execute_lesson(lesson, tmp_path / "notebook.ipynb")
    figures = [p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.png")]
    assert figures == ["out/lessons/01_tape/fd_error.png"]
    assert not (tmp_path / "lessons" / "out").exists()  # where a cwd-relative path put it


def test_a_failing_cell_fails_the_run_and_the_notebook_is_kept(tmp_path):
    lesson = tmp_path / "99_fails.py"
    lesson.write_text('# %%\nprint("before")\n\n# %%\nraise ValueError("a broken cell")\n')
    notebook = tmp_path / "out" / "99_fails.ipynb"
    with pytest.raises(CellExecutionError, match="a broken cell"):
        _runner().execute_lesson(lesson, notebook)
    outputs = _outputs(nbformat.read(notebook, as_version=4))
    assert outputs[0]["text"] == "before\n" and outputs[-1]["output_type"] == "error"


def test_lessons_are_found_by_number_name_or_path():
    runner = _runner()
    monte_carlo = ROOT / "lessons" / "10_monte_carlo.py"
    assert runner.find_lesson("10") == runner.find_lesson("10_monte_carlo") == monte_carlo
    assert runner.find_lesson(str(monte_carlo)) == monte_carlo
    assert runner.find_lesson("1").name == "01_tape.py"
    with pytest.raises(SystemExit, match="no single lesson named '99'"):
        runner.find_lesson("99")
