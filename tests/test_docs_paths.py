"""Every file a page of documentation names exists: paths in code spans (`render/film.py`),
module names of the package (`render.inverse.shape`) and relative links, in README.md,
lessons/README.md and docs/. Code moves; the pages must follow."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [
    "README.md",
    "lessons/README.md",
    *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md")),
]
#: Top-level folders whose paths a page may name.
FOLDERS = ("minidiff/", "render/", "tests/", "examples/", "benchmarks/", "lessons/", "docs/")
#: A path in a code span: a top-level folder, then names (placeholders such as NN_*.py and
#: <name> are skipped).
PATH = re.compile(r"`((?:" + "|".join(map(re.escape, FOLDERS)) + r")[\w./-]*)")
#: A module of the package in a code span, e.g. `render.inverse.shape.LargeSteps`.
MODULE = re.compile(r"`((?:render|minidiff)(?:\.\w+)+)")
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def _resolves(dotted: str) -> bool:
    """Whether a dotted name is a module, or a module's attribute chain
    (`render.inverse.shape.LargeSteps`, `render.torch.function`)."""
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        try:
            module = importlib.import_module(".".join(parts[:k]))
        except ModuleNotFoundError as error:
            if error.name is not None and not dotted.startswith(error.name):
                return True  # an optional dependency (torch, jax) is missing: cannot tell
            continue  # a module's attribute, not a module: try shorter
        obj = module
        for name in parts[k:]:
            if not hasattr(obj, name):
                return False
            obj = getattr(obj, name)
        return True
    return False


@pytest.mark.parametrize("page", PAGES)
def test_named_paths_exist(page):
    text = (ROOT / page).read_text(encoding="utf-8")
    named = [m.group(1) for m in PATH.finditer(text) if text[m.end()] not in "*<"]
    missing = [p for p in named if not (ROOT / p.rstrip(".")).exists()]
    for link in LINK.findall(text):
        if not re.match(r"[a-z]+:", link) and not (ROOT / page).parent.joinpath(link).exists():
            missing.append(link)
    assert not missing, f"{page} names paths that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES)
def test_named_modules_exist(page):
    text = (ROOT / page).read_text(encoding="utf-8")
    missing = [m for m in MODULE.findall(text) if not _resolves(m)]
    assert not missing, f"{page} names modules that do not exist: {missing}"


#: A command line that runs a script, with its options: python examples/x.py --a 1 --b.
#: A line break may come after "python" or before an option (prose wraps); # ends it.
COMMAND = re.compile(
    r"python\s+((?:examples|benchmarks|lessons)/[\w/]+\.py)"
    r"((?:(?:[ \t]+|\n[ \t]*(?=--))[^\s`|)#]+)*)"
)
#: Where options shared by several scripts are declared.
SHARED_OPTIONS = ["examples/script_support.py", "benchmarks/timing.py"]


@pytest.mark.parametrize("page", PAGES)
def test_named_script_options_exist(page):
    """`python examples/x.py --opt` in a page: the script exists and declares --opt (in its
    own source or in the helpers that build the scripts' command lines)."""
    text = (ROOT / page).read_text(encoding="utf-8")
    shared = "".join((ROOT / p).read_text(encoding="utf-8") for p in SHARED_OPTIONS)
    missing = []
    for script, args in COMMAND.findall(text):
        if not (ROOT / script).exists():
            missing.append(script)
            continue
        source = (ROOT / script).read_text(encoding="utf-8") + shared
        for option in re.findall(r"(?<!\S)(--[a-z][\w-]*)", args):  # not "--" in a value
            if f'"{option}"' not in source:
                missing.append(f"{script} {option}")
    assert not missing, f"{page} names scripts or options that do not exist: {missing}"
