"""Every Python block in README.md and docs/ runs as written, each in a fresh interpreter (a
block may switch on process-wide settings, such as JAX's float64), and prints what its
comments say where ``EXPECTED`` names it."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# Starts new Python processes: runs after the in-process tests (tests/conftest.py).
pytestmark = pytest.mark.new_processes

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md"))]


def python_blocks(page: str) -> list[str]:
    """The ```python blocks of a page, in order."""
    return re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(encoding="utf-8"), re.S)


BLOCKS = [(page, k, code) for page in PAGES for k, code in enumerate(python_blocks(page))]


def _close_to_the_true_light(last: str) -> None:
    position = np.array([float(x) for x in re.findall(r"-?\d+\.\d+", last)[:3]])
    assert np.abs(position - [2.0, 5.0, 3.0]).max() < 0.05, last


#: What a block prints last, as its comments say: a substring, or a check of the line.
EXPECTED = {
    ("README.md", 0): _close_to_the_true_light,
    ("README.md", 2): "[",
    ("docs/bridges.md", 0): _close_to_the_true_light,
    ("docs/bridges.md", 2): "True",
    ("docs/bridges.md", 3): "tensor([2., 4., 6.]",
    ("docs/bridges.md", 4): "[ 0.  3. 12.]",
}

#: Modules a block may need that are optional extras.
OPTIONAL = ("torch", "jax", "dask")


def test_the_expected_outputs_name_existing_blocks():
    assert set(EXPECTED) <= {(page, k) for page, k, _ in BLOCKS}
    assert len(python_blocks("README.md")) >= 3, "README: the first example, views, Dask"


@pytest.mark.parametrize(("page", "k", "code"), BLOCKS, ids=[f"{p}#{k}" for p, k, _ in BLOCKS])
def test_block_runs_as_written(page, k, code):
    for module in OPTIONAL:
        if re.search(rf"^\s*(import|from) {module}\b", code, re.M):
            if importlib.util.find_spec(module) is None:
                pytest.skip(f"needs {module}")
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.strip().splitlines()
    expected = EXPECTED.get((page, k))
    if callable(expected):
        expected(lines[-1])
    elif expected is not None:
        assert expected in lines[-1], lines[-3:]
