"""A cached Numba kernel runs the current code of every project module it calls.

Numba's own cache checks only the kernel's file: after an edit to a function it calls in
another module (inlined or not) it would load the old machine code. ``minidiff.jitcache``
widens the stamp to every project module the kernel's module imports. Here a copy of the
``minidiff`` package gets a kernel calling a compiled function of a second module and an
inlined one of a third; each process prints the kernel's result and whether it came from
the cache, and between processes the called functions are edited.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import minidiff
from minidiff import jitcache

KERNEL = """
import numba
from minidiff import _probe_called
from minidiff._probe_inlined import shift

@numba.njit(cache=True)
def kernel(x):
    return _probe_called.scale(x) + shift(x)
"""
CALLED = "import numba\n\n@numba.njit\ndef scale(x):\n    return {} * x\n"
INLINED = "import numba\n\n@numba.njit(inline='always')\ndef shift(x):\n    return {}\n"
RUN = """
import json, minidiff
from minidiff import _probe_kernel as k
value = k.kernel(1.0)
print(json.dumps([minidiff.__file__, value, sum(k.kernel.stats.cache_hits.values())]))
"""


@pytest.fixture
def copy(tmp_path: Path) -> Path:
    """A copy of the minidiff package (no caches) with the three probe modules."""
    package = tmp_path / "minidiff"
    shutil.copytree(Path(minidiff.__file__).parent, package,
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    (package / "_probe_kernel.py").write_text(KERNEL)
    (package / "_probe_called.py").write_text(CALLED.format(2.0))
    (package / "_probe_inlined.py").write_text(INLINED.format(1.0))
    return tmp_path


def _run(root: Path) -> tuple[float, int]:
    """(the kernel's result, cache hits) in a new process importing the copy."""
    env = {**os.environ, "PYTHONPATH": str(root), "NUMBA_CACHE_DIR": ""}
    env.pop("NUMBA_CACHE_DIR")
    out = subprocess.run([sys.executable, "-c", RUN], cwd=root, env=env, check=True,
                         capture_output=True, text=True).stdout  # fmt: skip
    where, value, hits = json.loads(out.strip().splitlines()[-1])
    assert Path(where).resolve().is_relative_to(root.resolve())
    return value, hits


@pytest.mark.new_processes
def test_an_edit_to_a_called_module_compiles_the_kernel_again(copy: Path) -> None:
    package = copy / "minidiff"
    assert _run(copy) == (3.0, 0)  # compiled and saved
    assert _run(copy) == (3.0, 1)  # loaded from the cache
    (package / "_probe_called.py").write_text(CALLED.format(3.0))
    assert _run(copy) == (4.0, 0)  # a called (not inlined) function edited
    (package / "_probe_inlined.py").write_text(INLINED.format(5.0))
    assert _run(copy) == (8.0, 0)  # an inlined one edited
    (package / "optim.py").write_text((package / "optim.py").read_text() + "\n# edited\n")
    assert _run(copy) == (8.0, 1)  # a module the kernel never imports: still cached


def test_dependencies_follow_imports_transitively() -> None:
    """The path kernel's stamp covers the modules it calls (scalar, packed) and what they
    import (the lights, the BVH), and not the modules that only use it."""
    root = Path(minidiff.__file__).resolve().parent.parent
    names = {
        str(p.relative_to(root)) for p in jitcache.dependencies(root / "render/path/twin/kernel.py")
    }
    assert {"render/path/twin/scalar.py", "render/path/twin/packed.py", "render/scene/lights.py",
            "render/trace/intersect.py", "render/path/twin/kernel.py"} <= names  # fmt: skip
    assert "render/path/integrator.py" not in names and "render/renderer.py" not in names


def test_the_locator_is_installed_first() -> None:
    from numba.core import caching

    impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
    assert getattr(impl._locator_classes[0], "_diffrt", False)
    assert jitcache.install()  # a second call changes nothing
    assert sum(getattr(c, "_diffrt", False) for c in impl._locator_classes) == 1


def _imports_by_ast(path: Path) -> set[Path]:
    """What ``jitcache._imports`` must find at least: the modules of the file's ``import``
    statements as Python's parser reads them."""
    import ast

    package = path.relative_to(jitcache._BASE).with_suffix("").parts[:-1]
    if path.name == "__init__.py":
        package = path.relative_to(jitcache._BASE).parts[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {jitcache._module_file(alias.name) for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                head = package[: len(package) - node.level + 1]
                base = ".".join([*head, *([base] if base else [])])
            for alias in node.names:
                name = f"{base}.{alias.name}"
                found.add(jitcache._module_file(name) or jitcache._module_file(base))
    return found - {None}


def test_the_import_scan_finds_every_import_the_parser_finds(tmp_path: Path, monkeypatch) -> None:
    """On every project file, and on the forms a file can take (relative, parenthesised over
    lines, backslash-continued, aliased, indented): nothing Python's parser reads as an
    import of a project module is missed."""
    root = jitcache._BASE
    files = [f for name in jitcache.PACKAGES for f in (root / name).rglob("*.py")]
    for path in files:
        scanned = set(jitcache._imports(*jitcache._file_key(path)))
        assert _imports_by_ast(path) <= scanned, path
    forms = (
        "import render.path.twin.scalar as s, minidiff.kernels\n"
        "from .. import kernels\n"
        "from ..scene import (\n    lights,  # a comment\n    camera as c,\n)\n"
        "from render.trace import \\\n    bvh, intersect\n"
        "def f():\n    from render.path.twin import packed\n"
    )
    # The probe and the modules it names, in a tree of their own (not the project's).
    names = ["render/path/twin/scalar.py", "minidiff/kernels.py", "render/scene/lights.py",
             "render/scene/camera.py", "render/trace/bvh.py", "render/trace/intersect.py",
             "render/path/twin/packed.py"]  # fmt: skip
    for name in [
        *names,
        "render/__init__.py",
        "render/path/__init__.py",
        "render/path/twin/__init__.py",
    ]:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).touch()
    probe = tmp_path / "render" / "path" / "probe.py"
    probe.write_text(forms, encoding="utf-8")
    monkeypatch.setattr(jitcache, "_BASE", tmp_path)
    scanned = set(jitcache._imports(*jitcache._file_key(probe)))
    assert _imports_by_ast(probe) <= scanned
    assert set(names) <= {str(p.relative_to(tmp_path)) for p in scanned}, scanned
