"""Every script in examples/ and benchmarks/ writes under out/ unless told otherwise (issue
41): run as documented, none overwrites the committed figures and results in docs/, which
are regenerated only by an explicit ``--out docs/...``.

Each script's ``main`` is called with no arguments, up to the point where it parses its
command line: the parser it built is caught there (nothing is computed or written) and
its ``--out`` default read."""

from __future__ import annotations

import argparse
import inspect
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(
    path.relative_to(ROOT).as_posix()
    for folder in ("examples", "benchmarks")
    for path in (ROOT / folder).glob("*.py")
    if 'if __name__ == "__main__":' in path.read_text(encoding="utf-8")
)
#: Scripts with no output at all: they only print.
PRINTS_ONLY = {"examples/minidiff_demo.py"}


class _Parsed(Exception):
    """Raised in place of parsing a command line, carrying the parser that would parse it."""

    def __init__(self, parser: argparse.ArgumentParser) -> None:
        super().__init__()
        self.parser = parser


def command_line_parser(module, monkeypatch) -> argparse.ArgumentParser | None:
    """The parser that ``module.main`` builds for an empty command line, caught before it
    parses, or None where ``main`` returned without parsing one."""

    def catch(parser, args=None, namespace=None):
        raise _Parsed(parser)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", catch)
    monkeypatch.setattr(sys, "argv", [module.__file__])  # for a main() that reads sys.argv
    takes_argv = bool(inspect.signature(module.main).parameters)
    try:
        module.main([]) if takes_argv else module.main()
    except _Parsed as parsed:
        return parsed.parser
    return None


def is_under_out(path: Path) -> bool:
    """Whether ``path`` is in ``out/``: relative (to where the script runs) or in the
    repository's."""
    if path.is_absolute():
        return path.is_relative_to(ROOT / "out")
    return path.parts[:1] == ("out",)


def test_the_scripts_are_found():
    assert {"examples/colour_bleeding.py", "benchmarks/bench_path.py"} <= set(SCRIPTS)
    assert "benchmarks/timing.py" not in SCRIPTS and "examples/script_support.py" not in SCRIPTS


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_default_output_is_under_out(script, load_script, monkeypatch, tmp_path):
    module = load_script(script)
    if script in PRINTS_ONLY:
        monkeypatch.chdir(tmp_path)
        assert command_line_parser(module, monkeypatch) is None
        assert not any(tmp_path.iterdir()), f"{script} wrote files"
        return
    parser = command_line_parser(module, monkeypatch)
    assert parser is not None, f"{script}: main() parsed no command line"
    default = parser.get_default("out")
    assert default is not None, f"{script} has no --out default"
    assert is_under_out(Path(default)), f"{script} writes to {default} by default"
    # The usage line of the docstring shows the default (or a placeholder).
    shown = re.findall(r"\[--out (\S+?)\]", module.__doc__)
    assert all(s == "DIR" or Path(s) == Path(default) for s in shown), (script, shown)


def test_a_default_into_docs_is_caught(monkeypatch):
    """The check itself: a script whose --out defaults to docs/ fails it."""

    class Script:
        __file__ = "script.py"
        __doc__ = "Run: python script.py [--out docs/path_tracing]"

        @staticmethod
        def main(argv=None):
            parser = argparse.ArgumentParser()
            parser.add_argument("--out", default="docs/path_tracing")
            parser.parse_args(argv)

    parser = command_line_parser(Script, monkeypatch)
    assert parser.get_default("out") == "docs/path_tracing"
    assert not is_under_out(Path(parser.get_default("out")))
    assert is_under_out(Path("out/colour_bleeding")) and is_under_out(ROOT / "out" / "x")
    assert not is_under_out(ROOT / "docs") and not is_under_out(Path("outside/x"))
