"""The code in the README's "From PyTorch / JAX" section and in docs/bridges.md runs as
written, each block in a fresh interpreter (the JAX block switches on float64 for its
whole process)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("jax")

# Starts new Python processes: runs after the in-process tests (tests/conftest.py).
pytestmark = pytest.mark.new_processes

ROOT = Path(__file__).resolve().parents[1]


def _blocks(path: Path, heading: str | None = None) -> list[str]:
    text = path.read_text(encoding="utf-8")
    if heading is not None:
        start = text.index(heading)
        end = text.find("\n## ", start + len(heading))
        text = text[start : end if end >= 0 else len(text)]
    return re.findall(r"```python\n(.*?)```", text, re.S)


README = _blocks(ROOT / "README.md", "## From PyTorch / JAX")
BRIDGES = _blocks(ROOT / "docs" / "bridges.md")


def _run(code: str) -> str:
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def test_readme_torch_snippet_fits_the_light():
    assert len(README) == 2, "the section should hold the PyTorch and the JAX example"
    assert "render.torch" in README[0]
    last = _run(README[0]).strip().splitlines()[-1]  # print(position)
    position = np.array([float(x) for x in re.findall(r"-?\d+\.\d+", last)[:3]])
    assert np.abs(position - [2.0, 5.0, 3.0]).max() < 0.05, last  # "close to the true"


def test_readme_jax_snippet_runs():
    assert "render.jax" in README[1]
    _run(README[1])


#: What each block of docs/bridges.md prints last, as its comments say.
BRIDGES_PRINT = ["True", "tensor([2., 4., 6.]", "[ 0.  3. 12.]"]


@pytest.mark.parametrize("k", range(len(BRIDGES_PRINT)))
def test_docs_bridges_blocks_print_what_they_say(k):
    assert len(BRIDGES) == len(BRIDGES_PRINT), "a block of docs/bridges.md without its check"
    assert BRIDGES_PRINT[k] in _run(BRIDGES[k]).strip().splitlines()[-1]
