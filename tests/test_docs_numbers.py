"""Every number in README.md and docs/ comes from a committed result file.

Two kinds of page:

- **Generated pages** (a script wrote them beside its JSON): each is regenerated here from
  the committed JSON by the script's own function and must equal the committed text
  (``GENERATED``); pages whose script builds the text inside ``main`` are held to the
  number check below, against their JSON, as a whole (``WHOLE_PAGES``).
- **Written pages**: a block (a paragraph, a table or a list, up to the next blank line)
  that states measured numbers starts with a marker naming where they come from::

      <!-- numbers: docs/reproduction_results.md docs/reconstruction/camera_30deg.json -->

  Every number in the block must be one of the sources' numbers as written, rounded to the
  digits the block shows (``0.0067`` matches 0.006658; a % may show a fraction times 100, a
  ms a second times 1000). A JSON source gives its numeric values, the numbers inside its
  strings, and for every list of runs (also grouped by one or two of the settings in
  ``GROUPS``, such as the start angle) each key's count, mean, standard deviation, median,
  minimum, maximum and the number of runs where a flag is true. ``file.json:key.0``
  narrows a source to a part: the fewer numbers a source offers, the stronger the check.
  A markdown source (itself a generated page, checked against its JSON) gives the numbers
  it states. A block with a number followed by a unit of measurement (%, ms, s, x, dB,
  MB, ...) and no marker fails: measured numbers must name their source.

Sizes written as 512x512 are settings and not read as numbers. Run ``python -m
tests.test_docs_numbers FILE.md`` to list a page's numbers that no source matches.
"""

from __future__ import annotations

import importlib
import json
import math
import re
import shutil
import statistics
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Written pages: every block with a measured number needs a marker.
WRITTEN = [
    "README.md",
    "docs/results.md",
    "docs/benchmarks.md",
    "docs/how_it_works.md",
    "docs/path_tracing.md",
    "docs/bridges.md",
    "docs/paper_scene.md",
    "docs/architecture.md",
    "docs/compiler.md",
]

#: Generated pages whose script builds the text in ``main``: every number must be in the JSON.
WHOLE_PAGES = {
    "docs/edges/boundary.md": ["docs/edges/boundary.json"],
    "docs/reconstruction/shape.md": [
        f"docs/reconstruction/shape_{k}.json"
        for k in ("0_blob", "2_blob", "3_teapot", "4_teapot", "5_teapot")
    ],
    "docs/reconstruction/pose.md": ["docs/reconstruction/pose.json"],
    "docs/reconstruction/pose_seeds.md": ["docs/reconstruction/pose_seeds.json"],
    "docs/reconstruction/joint.md": ["docs/reconstruction/joint.json"],
    "docs/ml/neural_field/neural_field.md": ["docs/ml/neural_field/neural_field.json"],
    "docs/ml/light_network/light_network.md": ["docs/ml/light_network/light_network.json"],
}

#: Numbers a generated page states that are the script's settings, not in its JSON.
SETTINGS = {
    "docs/edges/boundary.md": "1,024 and 256 samples per pixel in the truth",
    "docs/ml/light_network/light_network.md": "the box [0.5, 3.5, 1.5]..[3.5, 6.5, 4.5], "
    "steps of 8, 30 Adam steps",
}

#: Settings that runs in a result file are grouped by for their statistics.
GROUPS = ("angle", "method", "search_renders", "views", "shadows", "size", "antialias")

MARKER = re.compile(r"<!--\s*numbers:\s*(.*?)-->")
#: A number as text: 1,377 / 0.0067 / 2.1e-4; not part of a name (float64, x86_64, 3D).
NUMBER = re.compile(
    r"(?<![\w.\-])[−-]?(\d{1,3}(?:,\d{3})+|\d+)(\.\d+)?(?:e([-+]?\d+))?"
    r"(?=\s?(x|ms|s|µs|ns|MB|MiB|GB|kB|dB|px|°|%)?(?![\w]))"
)
#: A measured number: followed by a unit.
MEASURED = re.compile(r"(?<![\w.])\d[\d,]*(?:\.\d+)?(?:x|\s?(?:%|ms|µs|ns|MB|MiB|GB|dB|s))(?!\w)")
#: Scales a page may show a source's value in, by the unit after the number: a fraction as a
#: percentage, seconds as milli- or microseconds.
SCALES = {"%": (1.0, 100.0), "ms": (1.0, 1e3), "µs": (1.0, 1e6)}


def _strip(text: str) -> str:
    """The prose a reader reads: no code spans, code blocks, link targets, comments or the
    numbers of an ordered list's items."""
    text = re.sub(r"```.*?```", " ", text, flags=re.S)
    text = re.sub(r"^(\s*)\d+\. ", r"\1", text, flags=re.M)  # "3. **One depth**": an item
    text = re.sub(r"<!--.*?-->", " ", text, flags=re.S)
    text = re.sub(r"`[^`\n]*`", " ", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)  # link targets
    text = re.sub(r"!\[[^\]]*\]", " ", text)  # image descriptions
    return text


def numbers_in(text: str) -> list[tuple[str, float, float, str]]:
    """The numbers a text shows: (as written, value, half a unit of its last digit, the
    unit after it or "")."""
    found = []
    for m in NUMBER.finditer(_strip(text)):
        whole, frac, exp = m.group(1), m.group(2) or "", m.group(3)
        value = float(whole.replace(",", "") + frac)
        half = 0.5 * 10.0 ** -(len(frac) - 1 if frac else 0)
        if exp is not None:
            value *= 10.0 ** int(exp)
            half *= 10.0 ** int(exp)
        found.append((m.group(0), value, half, m.group(4) or ""))
    return found


def _collect(value, pool: list[float]) -> None:
    """Every number of a JSON value and of the statistics over its lists, into pool."""
    if isinstance(value, bool):
        return
    if isinstance(value, int | float):
        pool.append(abs(float(value)))
    elif isinstance(value, str):
        pool.extend(v for _, v, _, _ in numbers_in(value))
    elif isinstance(value, dict):  # keys too: {"16": ...} says 16 samples
        for k, v in value.items():
            _collect(k, pool)
            _collect(v, pool)
    elif isinstance(value, list):
        pool.append(float(len(value)))
        for v in value:
            _collect(v, pool)
        _statistics([v for v in value if _is_number(v)], pool)
        rows = [v for v in value if isinstance(v, dict)]
        for group in _groups(rows):
            for key in {k for r in group for k in r}:
                column = [r[key] for r in group if key in r]
                if all(isinstance(v, bool) for v in column):
                    pool += [float(sum(column)), float(len(column) - sum(column))]
                else:
                    _statistics([v for v in column if _is_number(v)], pool)


def _groups(rows: list[dict]) -> list[list[dict]]:
    """The runs, and the runs grouped by one or two of the settings in ``GROUPS`` that
    vary between them (e.g. the start angle and the method)."""
    settings = [k for k in GROUPS if len({str(r.get(k)) for r in rows}) > 1]
    groups = [rows]
    for i, a in enumerate(settings):
        for b in [None, *settings[i + 1 :]]:
            keys = {(r.get(a), r.get(b) if b else None) for r in rows}
            groups += [[r for r in rows if (r.get(a), r.get(b) if b else None) == k] for k in keys]
    return groups


def _is_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _statistics(values: list[float], pool: list[float]) -> None:
    if len(values) < 2:
        return
    pool += [statistics.mean(values), statistics.median(values), min(values), max(values)]
    pool += [statistics.pstdev(values), statistics.stdev(values), float(len(values))]
    pool += [abs(v) for v in values]


def source_numbers(names: list[str]) -> list[float]:
    """The numbers the named result files give (paths relative to the repository)."""
    pool: list[float] = []
    for name in names:
        name, _, part = name.partition(":")
        path = ROOT / name
        assert path.exists(), f"numbers source {name} does not exist"
        if path.suffix == ".json":
            data = json.loads(path.read_text(encoding="utf-8"))
            for key in part.split(".") if part else []:
                data = data[int(key)] if isinstance(data, list) else data[key]
            _collect(data, pool)
        else:
            pool += [v for _, v, _, _ in numbers_in(path.read_text(encoding="utf-8"))]
    return pool


def unmatched(text: str, pool: list[float], scales: tuple | None = None) -> list[str]:
    """The numbers of text that no value of pool rounds to, at the scales their unit allows
    (``SCALES``) or at ``scales`` (a generated table whose header names the unit)."""
    values = np.asarray(pool, dtype=float)
    return [
        written
        for written, value, half, unit in numbers_in(text)
        if not any(
            np.any(np.abs(values * s - abs(value)) <= half * (1 + 1e-9))
            for s in scales or SCALES.get(unit, (1.0,))
        )
    ]


def blocks(text: str) -> list[str]:
    """Paragraphs, tables and lists: text between blank lines, code blocks kept whole."""

    def keep_whole(code: re.Match) -> str:  # no blank line inside a code block
        return re.sub(r"\n([ \t]*)(?=\n)", "\n\\1\0", code.group(0))

    text = re.sub(r"```.*?```", keep_whole, text, flags=re.S)
    return [b.replace("\0", "") for b in re.split(r"\n\s*\n", text) if b.strip()]


def marked_blocks(path: str) -> list[tuple[list[str], str]]:
    """(sources, block) for each block of a written page; sources empty if unmarked."""
    out = []
    for block in blocks((ROOT / path).read_text(encoding="utf-8")):
        m = MARKER.search(block)
        out.append((m.group(1).split() if m else [], block))
    return out


@pytest.mark.parametrize("path", WRITTEN)
def test_marked_numbers_come_from_their_sources(path):
    problems = []
    for sources, block in marked_blocks(path):
        if sources:
            missing = unmatched(block, source_numbers(sources))
            if missing:
                problems.append(f"{missing} not in {sources}:\n{block[:300]}")
    assert not problems, f"{path}:\n\n" + "\n\n".join(problems)


@pytest.mark.parametrize("path", WRITTEN)
def test_measured_numbers_name_their_source(path):
    unmarked = [
        block[:300]
        for sources, block in marked_blocks(path)
        if not sources and MEASURED.search(_strip(block))
    ]
    assert not unmarked, f"{path}: blocks with measured numbers and no marker:\n\n" + (
        "\n\n".join(unmarked)
    )


@pytest.mark.parametrize("path", sorted(WHOLE_PAGES))
def test_generated_pages_numbers_come_from_their_json(path):
    text = (ROOT / path).read_text(encoding="utf-8")
    pool = source_numbers(WHOLE_PAGES[path])
    pool += [v for _, v, _, _ in numbers_in(SETTINGS.get(path, ""))]
    missing = unmatched(text, pool, scales=(1.0, 100.0, 1000.0))
    assert not missing, f"{path}: {missing} not in {WHOLE_PAGES[path]}"


def _script(name: str):
    for folder in ("examples", "benchmarks"):
        if (ROOT / folder / f"{name}.py").exists():
            sys.path.insert(0, str(ROOT / folder))
            try:
                return importlib.import_module(name)
            finally:
                sys.path.remove(str(ROOT / folder))
    raise AssertionError(f"no script {name}")


def _json(path: str):
    return json.loads((ROOT / path).read_text(encoding="utf-8"))


#: Generated page -> (script, its function from the JSON to the page's text, the JSON).
GENERATED = {
    "docs/edges/edge_gradients.md": ("edge_gradients", "report", "docs/edges/edge_gradients.json"),
    "docs/shadows/shadow_light_estimation.md": (
        "shadow_light_estimation",
        "report",
        "docs/shadows/shadow_light_estimation.json",
    ),
    "docs/reflection/mirror_reflection.md": (
        "mirror_reflection",
        "report",
        "docs/reflection/mirror_reflection.json",
    ),
    "docs/path_tracing/bleeding/results.md": (
        "colour_bleeding",
        "report",
        "docs/path_tracing/bleeding/results.json",
    ),
    "docs/path_tracing/mitsuba/results.md": (
        "bench_path_mitsuba",
        "markdown",
        "docs/path_tracing/mitsuba/results.json",
    ),
    "docs/path_tracing/secondary/secondary.md": (
        "path_secondary",
        "markdown",
        "docs/path_tracing/secondary/secondary.json",
    ),
    "docs/path_tracing/secondary/mitsuba.md": (
        "path_secondary_mitsuba",
        "markdown",
        "docs/path_tracing/secondary/mitsuba.json",
    ),
}


@pytest.mark.parametrize("path", sorted(GENERATED))
def test_generated_pages_equal_their_script_output(path):
    script, function, source = GENERATED[path]
    text = getattr(_script(script), function)(_json(source))
    assert (ROOT / path).read_text(encoding="utf-8") == text


def test_boundary_page_tables_are_its_json():
    module = _script("boundary_gradients")
    data = _json("docs/edges/boundary.json")
    text = (ROOT / "docs/edges/boundary.md").read_text(encoding="utf-8")
    rows = data["teapot translation"]
    size = module._table(
        ["size", "shadows"],
        module.METHODS,
        rows,
        lambda r: [str(r["size"]), "yes" * r["shadows"] or "no"],
    )
    kinds = module._table(
        ["parameter"], module.PARAMETER_METHODS, data["parameters"], lambda r: [r["parameter"]]
    )
    assert "\n".join(size) in text and "\n".join(kinds) in text


def test_path_gradients_page_equals_its_script_output():
    data = _json("docs/path_tracing/gradients.json")
    text = _script("path_gradients").markdown(data["rows"], data["seeds"], data["spp"], data["h"])
    assert (ROOT / "docs/path_tracing/gradients.md").read_text(encoding="utf-8") == text


def test_reproduction_page_is_the_table_of_its_json():
    """docs/reproduction_results.md: the table from the JSON, and its targets' means."""
    module = _script("reproduce_paper")
    results = _json("docs/reproduction_results.json")
    text = (ROOT / "docs/reproduction_results.md").read_text(encoding="utf-8")
    assert module.table(results) in text
    head, targets = text.split(module.table(results))
    assert not unmatched(head, source_numbers(["docs/reproduction_results.json"]))
    for experiment, metric, bound in module.TARGETS:
        mean = statistics.mean(r[metric] for r in results[experiment])
        assert f"- {experiment} {metric}: {mean:.4g} (target < {bound})" in targets


def test_benchmark_report_is_its_json(tmp_path):
    """docs/benchmarks/report.md is run_all.py's report from the committed JSON files (less
    the wall time of each script, which no JSON holds)."""
    for path in (ROOT / "docs" / "benchmarks").glob("*.json"):
        shutil.copy(path, tmp_path)
    committed = (ROOT / "docs/benchmarks/report.md").read_text(encoding="utf-8")
    note = next(line for line in committed.splitlines() if line.startswith("Threading:"))
    text = _script("run_all").write_report(tmp_path, {}, note).read_text(encoding="utf-8")
    assert committed == text


def test_every_page_is_checked():
    """A new page under docs/ must be listed here: written, or generated from its JSON."""
    checked = {*WRITTEN, *WHOLE_PAGES, *GENERATED}
    checked |= {"docs/path_tracing/gradients.md", "docs/reproduction_results.md"}
    checked |= {"docs/benchmarks/report.md"}
    pages = {str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md")}
    assert pages <= checked, f"pages no test checks: {sorted(pages - checked)}"


def test_the_check_reads_numbers_as_written():
    assert [w for w, _, _, _ in numbers_in("1,377 tests, 0.0067 %, 2.1e-4, float64, 3D, 2.6x")] == [
        "1,377",
        "0.0067",
        "2.1e-4",
        "2.6",
    ]
    pool = [0.006658, 1377.0, 0.0128]
    assert unmatched("0.0067 % and 1,377 and 12.8 ms", pool) == []
    assert unmatched("0.0068 % and 1,378", pool) == ["0.0068", "1,378"]


if __name__ == "__main__":  # list a page's unmatched numbers, block by block
    for page in sys.argv[1:]:
        page = str(Path(page).resolve().relative_to(ROOT))
        if page in WHOLE_PAGES:
            text = (ROOT / page).read_text(encoding="utf-8")
            print(page, unmatched(text, source_numbers(WHOLE_PAGES[page]), (1.0, 100.0, 1e3)))
            continue
        for sources, block in marked_blocks(page):
            if sources:
                missing = unmatched(block, source_numbers(sources))
                if missing:
                    print(f"-- {sources}: {missing}\n{block[:200]}\n")
            elif MEASURED.search(_strip(block)):
                print(f"-- UNMARKED:\n{block[:200]}\n")
