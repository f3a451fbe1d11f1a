"""Numba's on-disk cache, made to notice an edit to any source a kernel depends on.

A kernel compiled with ``numba.njit(cache=True)`` is saved next to its module (in
``__pycache__``) under a stamp of that module's source alone. A kernel that calls a
function of another module (inlined or not) is compiled with that function's code, so
after an edit to the other module Numba would load the old machine code, silently, until
someone deleted ``__pycache__``. Here the stamp of every kernel defined in ``minidiff/``
or ``render/`` also covers every project module its module imports, transitively (read
from the ``import`` statements, so it does not depend on what the process imported
first): an edit to any of them compiles the kernel again. An edit elsewhere (a script, a
module the kernel's module never imports) keeps the cached code.

Numba has no public hook for this; it chooses a cache "locator" per function from a list
(``numba.core.caching``). ``install()``, run when this module is first imported
(``minidiff`` imports it before its own kernels, and ``render`` imports ``minidiff`` before
any of its own), puts one in front of that list that only answers for files under this
project's package folders and otherwise does exactly what Numba's own
locator would (same folder, same file names), with the stamp widened.
``tests/minidiff/test_jitcache.py`` edits a called function in a copy of the packages and
checks that the next process runs the new code.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import warnings
from pathlib import Path

#: The folders whose kernels get the wider stamp, and whose modules it covers.
PACKAGES = ("minidiff", "render")
_BASE = Path(__file__).resolve().parent.parent


def _module_file(dotted: str) -> Path | None:
    """The source file of project module ``dotted`` (``render.path.twin.scalar``), if any."""
    parts = dotted.split(".")
    if parts[0] not in PACKAGES:
        return None
    path = _BASE.joinpath(*parts)
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


#: ``import a.b, c as d`` at the start of a line: group 1 the modules.
_IMPORT = re.compile(r"^[ \t]*import[ \t]+([^\n#;]+)", re.M)
#: ``from .a import b, c`` / ``from a import (b,\n c)`` / with backslash continuations:
#: group 1 the module (leading dots: relative), group 2 the names.
_FROM = re.compile(
    r"^[ \t]*from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|(?:[^\n#\\]|\\\n)*)", re.M
)


@functools.cache
def _imports(path: Path, mtime_ns: int, size: int) -> tuple[Path, ...]:
    """The project modules' files that the module at ``path`` imports (its ``import`` and
    ``from ... import`` statements, anywhere in the file). ``mtime_ns`` and ``size`` key the
    memo, so an edited file is read again.

    Read with two regular expressions, not ``ast.parse`` (0.75 s for the project's 100
    files, in every new process): a statement-like line inside a string counts too, which
    can only add a module (one more recompile after its edits), never miss one;
    ``tests/minidiff/test_jitcache.py`` checks that nothing ``ast`` finds is missed."""
    text = path.read_text(encoding="utf-8")
    package = path.relative_to(_BASE).with_suffix("").parts[:-1]
    if path.name == "__init__.py":
        package = path.relative_to(_BASE).parts[:-1]
    found = []
    for modules in _IMPORT.findall(text):
        found += [_module_file(m.split()[0]) for m in modules.split(",") if m.strip()]
    for base, names in _FROM.findall(text):
        level = len(base) - len(base.lstrip("."))
        base = base[level:]
        if level:  # relative: from the importing module's package upwards
            head = package[: len(package) - level + 1]
            base = ".".join([*head, *([base] if base else [])])
        # ``from a.b import c``: c is a module of its own, or a name defined in a.b.
        names = re.sub(r"#[^\n]*", "", names).strip("()").replace("\\", " ")
        for name in names.split(","):
            name = name.split()[0] if name.split() else ""
            found.append((name and _module_file(f"{base}.{name}")) or _module_file(base))
    return tuple(sorted({f for f in found if f is not None}))


def _file_key(path: Path) -> tuple[Path, int, int]:
    st = path.stat()
    return path, st.st_mtime_ns, st.st_size


@functools.cache
def _content_hash(path: Path, mtime_ns: int, size: int) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def dependencies(py_file: str | os.PathLike) -> list[Path]:
    """Every project source file that ``py_file`` imports, transitively, itself included,
    sorted."""
    start = Path(py_file).resolve()
    seen, todo = {start}, [start]
    while todo:
        for dep in _imports(*_file_key(todo.pop())):
            if dep not in seen:
                seen.add(dep)
                todo.append(dep)
    return sorted(seen)


def source_stamp(py_file: str | os.PathLike) -> str:
    """A digest of the contents of ``dependencies(py_file)`` (their paths relative to the
    project, so a moved checkout keeps its cache)."""
    digest = hashlib.sha256()
    for path in dependencies(py_file):
        digest.update(str(path.relative_to(_BASE)).encode())
        digest.update(_content_hash(*_file_key(path)).encode())
    return digest.hexdigest()


def _inside(py_file: str) -> bool:
    try:
        path = Path(py_file).resolve()
    except OSError:
        return False
    return path.suffix == ".py" and any(path.is_relative_to(_BASE / name) for name in PACKAGES)


def install() -> bool:
    """Put the project's locator first in Numba's list (once; later calls do nothing).
    Returns whether it is installed: False, with a warning, if this Numba's cache has
    another layout."""
    try:
        from numba.core import caching

        impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
        base = caching._CacheLocator
    except (ImportError, AttributeError):
        warnings.warn(
            "minidiff.jitcache: this Numba's cache has another layout; a cached kernel may "
            "run old code after an edit to a module it calls (delete __pycache__ then)",
            RuntimeWarning,
            stacklevel=2,
        )
        return False
    if any(getattr(cls, "_diffrt", False) for cls in impl._locator_classes):
        return True
    numba_locators = list(impl._locator_classes)

    class ProjectSourceLocator(base):
        """Numba's own locator for the function, with its stamp widened to every project
        module the function's module imports."""

        _diffrt = True

        def __init__(self, inner, py_file: str):
            self._inner = inner
            self._py_file = py_file

        def ensure_cache_path(self):
            return self._inner.ensure_cache_path()

        def get_cache_path(self):
            return self._inner.get_cache_path()

        def get_disambiguator(self):
            return self._inner.get_disambiguator()

        def get_source_stamp(self):
            return (self._inner.get_source_stamp(), source_stamp(self._py_file))

        @classmethod
        def from_function(cls, py_func, py_file):
            if not _inside(py_file):
                return None
            for locator in numba_locators:
                inner = locator.from_function(py_func, py_file)
                if inner is not None:
                    return cls(inner, py_file)
            return None

    impl._locator_classes.insert(0, ProjectSourceLocator)
    return True


install()
