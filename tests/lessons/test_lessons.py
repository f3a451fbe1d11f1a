"""The course in ``lessons/`` runs, and its prose states the numbers its code computes.

Every lesson (``lessons/NN_*.py``) and every solution (``lessons/solutions/NN_*.py``) is run
as a script (``runpy``, as ``python lessons/NN_*.py`` would) with ``LESSONS_OUT`` pointing
its figures to a temporary folder. New files are picked up by the glob.

How a lesson's text is held to its code: in a markdown cell, a number the lesson computed is
written in backticks and followed by a marker naming the module-level variable that holds it,

    the tape gives `2.716917` <!-- check: grad_x -->

(the marker is an HTML comment: Jupyter and VS Code do not show it). The check passes when
the variable, rounded to the digits the prose shows, is that number: `2.716917` allows
+-5e-7, `1.2e-10` +-5e-12, `1,536` exactly 1536. ``<!-- check: name < -->`` (or ``>``)
states a bound instead: the variable must be below (above) the number.
"""

from __future__ import annotations

import importlib
import re
import runpy
import sys
from decimal import Decimal
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LESSONS = sorted((ROOT / "lessons").glob("[0-9][0-9]_*.py"))
SOLUTIONS = sorted((ROOT / "lessons" / "solutions").glob("[0-9][0-9]_*.py"))

CHECK = re.compile(
    r"`([-+]?[\d,]*\.?\d+(?:[eE][-+]?\d+)?)`\s*<!--\s*check:\s*(\w+)\s*([<>])?\s*-->"
)


def markdown_text(path: Path) -> str:
    """The markdown cells of a jupytext percent-format file, with the ``# `` prefixes
    removed."""
    text, inside = [], False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("# %%"):
            inside = line.startswith("# %% [markdown]")
            continue
        if inside:
            text.append(line[2:] if line.startswith("# ") else line.lstrip("#"))
    return "\n".join(text)


def stated_checks(markdown: str) -> list[tuple[str, str, str]]:
    """(variable name, stated number as written, relation '=', '<' or '>') for each marker."""
    return [(name, number, rel or "=") for number, name, rel in CHECK.findall(markdown)]


def half_unit(number: str) -> Decimal:
    """Half a unit in the last digit the number shows: '0.0557' -> 0.00005, '1.2e-10' ->
    5e-12, '1,536' -> 0 (integers are exact)."""
    d = Decimal(number.replace(",", ""))
    if "." not in number and "e" not in number.lower():
        return Decimal(0)
    return Decimal(5) * Decimal(10) ** (d.as_tuple().exponent - 1)


def agrees(value: float, number: str, rel: str) -> bool:
    """Whether a computed value agrees with the number the prose states (see the module
    docstring)."""
    stated = Decimal(number.replace(",", ""))
    v = Decimal(repr(float(value)))
    if rel == "<":
        return v < stated
    if rel == ">":
        return v > stated
    # A tiny relative slack so that a value exactly on the rounding boundary passes.
    return abs(v - stated) <= half_unit(number) * Decimal("1.000001")


def run_script(path: Path, out: Path, monkeypatch) -> dict:
    monkeypatch.setenv("LESSONS_OUT", str(out))
    monkeypatch.setattr(sys, "argv", [str(path)])
    monkeypatch.syspath_prepend(str(path.parent))  # a script's folder comes first on the path
    return runpy.run_path(str(path), run_name="__main__")


def test_the_checker_catches_a_changed_number():
    """Changing a stated number (or its last digit) makes the check fail."""
    md = "the tape gives `2.716917` <!-- check: g --> and `1,536` <!-- check: n -->"
    checks = stated_checks(md)
    assert checks == [("g", "2.716917", "="), ("n", "1,536", "=")]
    assert agrees(2.7169171234, "2.716917", "=")
    assert not agrees(2.7169171234, "2.716918", "=")
    assert agrees(1536, "1,536", "=") and not agrees(1537, "1,536", "=")
    assert agrees(3e-13, "1e-10", "<") and not agrees(3e-9, "1e-10", "<")
    assert agrees(1.23e-10, "1.2e-10", "=") and not agrees(1.26e-10, "1.2e-10", "=")


@pytest.mark.parametrize("path", LESSONS, ids=[p.stem for p in LESSONS])
def test_lesson_runs_and_its_prose_states_its_numbers(path, tmp_path, monkeypatch):
    namespace = run_script(path, tmp_path, monkeypatch)
    figures = list(tmp_path.rglob("*.png"))
    assert figures, f"{path.name} wrote no figure under LESSONS_OUT"
    assert all(f.is_relative_to(tmp_path / path.stem) for f in figures)

    markdown = markdown_text(path)
    checks = stated_checks(markdown)
    assert len(checks) >= 3, f"{path.name} states fewer than three checked numbers"
    assert_stated_numbers(path, checks, namespace)
    assert "Exercises" in markdown, f"{path.name} has no exercises cell"
    solution = ROOT / "lessons" / "solutions" / path.name
    if solution.exists() and runs_its_lesson(solution):
        check_solution(solution, tmp_path / "solution", monkeypatch, {path.stem: namespace})


def runs_its_lesson(solution: Path) -> bool:
    """Whether a solution reuses its lesson's functions by running it (``course.run_lesson``):
    such a solution is checked by its lesson's test, with the names the lesson's run left
    (the same code, run once: lessons 14 and 15 take ~15 and ~10 s), the others by
    ``test_solution_runs_and_its_prose_states_its_numbers``."""
    return f'run_lesson("{solution.stem}")' in solution.read_text("utf-8")


def assert_stated_numbers(path: Path, checks: list[tuple[str, str, str]], namespace: dict):
    """Every number the prose states (``stated_checks``) agrees with the script's variable."""
    wrong = []
    for name, number, rel in checks:
        assert name in namespace, f"{path.name}: the prose checks {name!r}, the code has none"
        if not agrees(namespace[name], number, rel):
            wrong.append(f"{name} = {namespace[name]!r}, the prose says {rel} {number}")
    assert not wrong, f"{path.name}: " + "; ".join(wrong)


ALONE = [p for p in SOLUTIONS if not runs_its_lesson(p)]


@pytest.mark.parametrize("path", ALONE, ids=[p.stem for p in ALONE])
def test_solution_runs_and_its_prose_states_its_numbers(path, tmp_path, monkeypatch):
    """A solution runs (its own asserts check its answers), and the numbers its text
    states, where it marks them, agree with its variables as in a lesson."""
    check_solution(path, tmp_path, monkeypatch, {})


def check_solution(path: Path, out: Path, monkeypatch, runs: dict[str, dict]) -> None:
    """Run the solution at ``path`` (figures under ``out``) and check its stated numbers;
    ``course.run_lesson`` answers from ``runs`` (lesson name -> the names its run left)
    where it can, else runs the lesson."""
    monkeypatch.syspath_prepend(str(ROOT / "lessons"))
    course = importlib.import_module("course")
    run = course.run_lesson
    monkeypatch.setattr(course, "run_lesson", lambda lesson: runs.get(lesson) or run(lesson))
    namespace = run_script(path, out, monkeypatch)
    assert_stated_numbers(path, stated_checks(markdown_text(path)), namespace)


def test_every_lesson_has_solutions_and_an_index_entry():
    assert LESSONS, "no lessons found"
    readme = (ROOT / "lessons" / "README.md").read_text(encoding="utf-8")
    solved = {p.name for p in SOLUTIONS}
    for lesson in LESSONS:
        assert lesson.name in solved, f"no lessons/solutions/{lesson.name}"
        assert lesson.name in readme, f"lessons/README.md does not list {lesson.name}"
