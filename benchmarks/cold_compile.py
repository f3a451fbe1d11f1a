"""Compile latency: a cold first gradient, as a fresh clone meets it.

Each case runs in a new process with empty Numba and minidiff kernel caches (fresh
temporary ``NUMBA_CACHE_DIR`` and ``MINIDIFF_CACHE_DIR``), so everything the gradient needs
is compiled on the spot:

- ``direct``: ``render(paper_scene(64, 64, ground=True), antialias="boundary")`` with every
  parameter requiring grad, then ``backward`` (issue 57's "cold first boundary-term
  gradient of the paper scene at 64x64");
- ``path``: the Cornell box with blocks at 32x32, 16 spp, depth 4, the tall block's
  translation differentiated (its "cold first path-traced gradient of the Cornell box").

Reported per case: the wall time of the first gradient (imports excluded) and the Numba
functions whose compiles took longest (Numba's compile events; a function's time includes
the functions it compiles inside it).

    python benchmarks/cold_compile.py                    # both cases, out/cold_compile.json
    python benchmarks/cold_compile.py --label before --repo /path/to/an/older/checkout

``--repo`` runs the cases against another checkout (its ``render`` and ``minidiff``
first on the path), so that two commits are measured by the same script; results are
merged into the output file under ``--label``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CASE = r"""
import json, sys, time
from numba.core import event
recorder = event.install_recorder("numba:compile")
buffer = recorder.__enter__()
import minidiff as md
import render
which = sys.argv[1]
t0 = time.perf_counter()
if which == "direct":
    scene = render.paper_scene(width=64, height=64, ground=True)
    for p in scene.parameters():
        p.requires_grad = True
    render.render(scene, antialias="boundary").sum().backward()
else:
    from render.path import render_path
    from render.scene.cornell import cornell_box
    scene = cornell_box(32, 32, blocks=True)
    scene.objects[5].transform.translation.requires_grad = True
    image = render_path(scene, spp=16, max_depth=4, seed=0)
    md.sum(image * image).backward()
seconds = time.perf_counter() - t0
recorder.__exit__(None, None, None)
starts, rows = {}, []
for stamp, ev in buffer.buffer:
    data = ev.data or {}
    dispatcher = data.get("dispatcher")
    if dispatcher is None:
        continue
    name = dispatcher.py_func.__module__ + "." + dispatcher.py_func.__qualname__
    key = (id(dispatcher), str(data.get("args")))
    if ev.is_start:
        starts[key] = stamp
    elif key in starts:
        rows.append((stamp - starts[key], name))
rows.sort(reverse=True)
top = [{"function": name, "seconds": round(s, 2)} for s, name in rows[:10]]
print(json.dumps({"first_gradient_s": seconds, "numba_functions_compiled": len(rows),
                  "longest_compiles": top}))
"""


def run_case(which: str, repo: Path) -> dict:
    """One case in a fresh process with empty caches; its report."""
    with tempfile.TemporaryDirectory() as caches:
        env = dict(os.environ)
        env["NUMBA_CACHE_DIR"] = os.path.join(caches, "numba")
        env["MINIDIFF_CACHE_DIR"] = os.path.join(caches, "minidiff")
        env["PYTHONPATH"] = os.pathsep.join([str(repo), env.get("PYTHONPATH", "")])
        start = time.perf_counter()
        result = subprocess.run(
            [sys.executable, "-c", CASE, which], env=env, cwd=caches, capture_output=True,
            text=True, check=False,
        )  # fmt: skip
        if result.returncode != 0:
            raise RuntimeError(f"{which}: {result.stderr[-2000:]}")
        report = json.loads(result.stdout.strip().splitlines()[-1])
        report["process_s"] = time.perf_counter() - start
        return report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", default=["direct", "path"],
                        choices=["direct", "path"])  # fmt: skip
    parser.add_argument("--repo", type=Path, default=ROOT, help="checkout to measure")
    parser.add_argument("--label", default="this_checkout")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "cold_compile.json")
    args = parser.parse_args(argv)
    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    commit = subprocess.run(
        ["git", "-C", str(args.repo), "rev-parse", "--short", "HEAD"], capture_output=True,
        text=True, check=False,
    ).stdout.strip()  # fmt: skip
    entry = {"commit": commit, "date": time.strftime("%Y-%m-%d %H:%M")}
    for which in args.cases:
        entry[which] = run_case(which, args.repo.resolve())
        print(which, f"{entry[which]['first_gradient_s']:.1f} s", flush=True)
    results[args.label] = entry
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
