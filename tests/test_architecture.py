"""The folder layout is the pipeline (docs/architecture.md): each stage imports only from
the stages before it, nothing in ``render/`` imports in a cycle, and the renderer stays one
screen of calls."""

from __future__ import annotations

import ast
from pathlib import Path

RENDER = Path(__file__).resolve().parents[1] / "render"

#: The stages in pipeline order; a module may import from its own stage and earlier ones.
STAGES = [
    "scene", "trace", "shade", "edges", "film", "info", "path", "renderer", "inverse", "torch",
    "jax", "render",
]  # fmt: skip


def module_name(path: Path) -> str:
    parts = path.relative_to(RENDER.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def render_imports() -> dict[str, set[str]]:
    """Per module of ``render``: the ``render`` modules it imports anywhere in its body
    (function-level imports included: they hide cycles, not remove them)."""
    graph = {}
    for path in RENDER.rglob("*.py"):
        imported = set()
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            imported |= {n for n in names if n.split(".")[0] == "render"}
        graph[module_name(path)] = imported
    # keep only names that are modules (``from render.x import y`` names y too)
    return {m: {d for d in deps if d in graph and d != m} for m, deps in graph.items()}


def stage_of(module: str) -> int:
    parts = module.split(".")
    return STAGES.index(parts[1] if len(parts) > 1 else "render")


def test_every_module_has_a_stage():
    for module in render_imports():
        assert stage_of(module) >= 0, module


def test_no_stage_imports_from_a_later_one():
    wrong = [
        f"{module} imports {dep}"
        for module, deps in render_imports().items()
        for dep in deps
        if stage_of(dep) > stage_of(module) and dep != "render"
    ]
    assert wrong == []


#: The path integrator's concerns in order (``render/path/``): where paths go (off the
#: tape), what they carry and its gradient, the hand-written twin of both, the boundary
#: terms, and the integrator that chooses among them.
PATH_STAGES = ["sample", "gradient", "twin", "boundary", "integrator", "path"]


def path_stage_of(module: str) -> int:
    parts = module.split(".")
    return PATH_STAGES.index(parts[2] if len(parts) > 2 else "path")


def test_the_path_integrator_imports_its_concerns_in_order():
    """``render/path/`` is split by concern: the sampler imports none of the others, the
    gradient routes only the sampler, the twin the sampler alone, the boundary terms any
    of those, and only ``integrator`` all of them."""
    path_modules = {m: d for m, d in render_imports().items() if m.startswith("render.path")}
    assert {m.split(".")[2] for m in path_modules if m.count(".") >= 2} == set(PATH_STAGES[:-1])
    wrong = [
        f"{module} imports {dep}"
        for module, deps in path_modules.items()
        for dep in deps
        if dep.startswith("render.path") and path_stage_of(dep) > path_stage_of(module)
    ]
    assert wrong == []


def test_no_import_cycle_inside_render():
    graph = render_imports()
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(module: str, path: list[str]) -> list[str] | None:
        state[module] = 1
        for dep in sorted(graph[module]):
            if dep == "render" or module.startswith(dep + "."):
                continue  # a package's __init__ runs before its modules: not a cycle
            if state.get(dep) == 1:
                return path + [module, dep]
            if dep not in state and (cycle := visit(dep, path + [module])):
                return cycle
        state[module] = 2
        return None

    for module in sorted(graph):
        if module not in state:
            assert visit(module, []) is None


def test_the_renderer_is_one_screen_of_calls():
    lines = (RENDER / "renderer.py").read_text().splitlines()
    assert len(lines) <= 260
    start = next(i for i, line in enumerate(lines) if line.startswith("def render("))
    assert start < 130


#: The longest a function in ``render/`` may be, docstring included (issue 57).
LONGEST_FUNCTION = 150


def test_no_function_in_render_is_longer_than_the_limit():
    long = []
    for path in RENDER.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > LONGEST_FUNCTION:
                    long.append(f"{module_name(path)}.{node.name}: {lines} lines")
    assert not long, long
