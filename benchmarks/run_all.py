"""Run the whole benchmark suite and write ``OUT/report.md``.

Run:  python benchmarks/run_all.py [--out DIR] [--quick] [--only NAME ...] [--default-threading]

Each script runs in its own process (so that memory peaks, allocator state and JIT caches
do not carry over), writes ``OUT/<name>.json`` and its PNGs, and its output goes to
``OUT/logs/<name>.log``. The report collects every script's table (ours next to the paper's
number or the target) with links to the plots, and a summary of the targets.

Threading: on this 2-core machine other processes are often running. With Numba's default
OpenMP layer, idle worker threads spin-wait, and under contention every parallel region (the
renderer launches ~5 per render) can then cost a scheduler time slice (4-8 ms): timings
become bimodal and several times slower (``bench_render.py`` measures this). So by default
the scripts run with ``OMP_WAIT_POLICY=passive`` (threads sleep instead of spinning), which
makes them stable; ``--default-threading`` runs them with the environment as it is.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import timing

HERE = Path(__file__).resolve().parent
SCRIPTS = [
    "bench_visibility",
    "bench_minidiff",
    "bench_compiler",
    "bench_render",
    "bench_mitsuba",
    "fig2_bvh",
    "fig3_ad_vs_fd",
    "table2_ablation",
    "scaling",
]


def run_script(name: str, out: Path, quick: bool, env: dict) -> dict:
    """Run one script; returns its exit code, wall time and log path."""
    cmd = [sys.executable, str(HERE / f"{name}.py"), "--out", str(out)]
    if quick:
        cmd.append("--quick")
    log = out / "logs" / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    print(f"== {name} ...", flush=True)
    t0 = time.perf_counter()
    with open(log, "w", encoding="utf-8") as f:
        proc = subprocess.run(cmd, env=env, stdout=f, stderr=subprocess.STDOUT, check=False)
    seconds = time.perf_counter() - t0
    status = "ok" if proc.returncode == 0 else f"FAILED (exit {proc.returncode})"
    print(f"   {status} in {seconds:.0f} s (log: {log})", flush=True)
    return {"returncode": proc.returncode, "seconds": seconds, "log": str(log)}


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def write_report(out: Path, runs: dict, threading_note: str) -> Path:
    """``out/report.md`` from the scripts' JSON files (those that exist)."""
    results = {}
    for name in SCRIPTS:
        path = out / f"{name}.json"
        if path.exists():
            results[name] = json.loads(path.read_text(encoding="utf-8"))
    lines = ["# Benchmark report", ""]
    m = next((r["machine"] for r in results.values() if "machine" in r), None)
    if m is not None:
        lines += [
            f"Machine: {m['cpu_model']}, **{m['usable_cores']} cores**, Python {m['python']}, "
            f"NumPy {m['numpy']}, Numba {m['numba']} ({m['numba_threads']} threads, "
            f"{m['numba_threading_layer']} layer). Load average at the end of the runs: "
            + ", ".join(
                f"{n} {r['machine']['load_average_1_5_15min'][0]}"
                for n, r in results.items()
                if "machine" in r
            )
            + ".",
            "",
            "The paper's numbers come from a 6-core Intel Xeon E5-1650 v4 (Julia, Zygote). All "
            "times are medians of repeated runs after a warm-up, with the interquartile range "
            "in brackets, unless marked otherwise.",
            "",
            threading_note,
            "",
        ]
    if runs:
        lines += ["| script | status | wall time |", "|---|---|---|"]
        for name, r in runs.items():
            ok = "ok" if r["returncode"] == 0 else f"**failed** (exit {r['returncode']})"
            lines.append(f"| {name} | {ok} | {r['seconds']:.0f} s |")
        lines.append("")

    targets = [
        (res["report"]["title"], row)
        for res in results.values()
        for row in res["report"]["rows"]
        if row["status"]
    ]
    if targets:
        lines += [
            "## Targets",
            "",
            "| where | quantity | ours | target | status |",
            "|---|---|---|---|---|",
        ]
        for title, row in targets:
            lines.append(
                f"| {_md_escape(title.split('(')[-1].rstrip(')'))} | {_md_escape(row['quantity'])} "
                f"| {_md_escape(row['ours'])} | {_md_escape(row['reference'])} "
                f"| **{row['status']}** |"
            )
        lines.append("")

    for name, res in results.items():
        section = res["report"]
        lines += [f"## {section['title']}", ""]
        lines += ["| quantity | ours | paper / target | status |", "|---|---|---|---|"]
        for row in section["rows"]:
            lines.append(
                f"| {_md_escape(row['quantity'])} | {_md_escape(row['ours'])} "
                f"| {_md_escape(row['reference'])} | {row['status']} |"
            )
        lines.append("")
        lines += [f"- {_md_escape(n)}" for n in section["notes"]]
        lines.append("")
        for plot in section["plots"]:
            lines += [f"![{plot}]({plot})", ""]
        lines += [f"Raw numbers: [{name}.json]({name}.json)", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def main(argv=None) -> Path:
    parser = timing.make_parser(__doc__)
    parser.add_argument("--only", nargs="+", choices=SCRIPTS, help="run only these scripts")
    parser.add_argument(
        "--default-threading",
        action="store_true",
        help="do not set OMP_WAIT_POLICY=passive for the scripts",
    )
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if args.default_threading:
        note = "Threading: the environment as it was (Numba's default OpenMP settings)."
    else:
        env.setdefault("OMP_WAIT_POLICY", "passive")
        note = (
            f"Threading: scripts run with OMP_WAIT_POLICY={env['OMP_WAIT_POLICY']} (idle "
            "OpenMP threads sleep instead of spinning; see run_all.py and the 'config' rows "
            "of bench_render for what the default costs on this shared 2-core machine)."
        )
    note += (
        " The machine is shared (see the load averages): Numba's kernels use both cores, so a "
        "process running on the other core can slow them up to 2x for a while. Ratios are "
        "taken between numbers measured in the same run, close in time."
    )
    runs = {}
    t0 = time.perf_counter()
    for name in args.only or SCRIPTS:
        runs[name] = run_script(name, out, args.quick, env)
    path = write_report(out, runs, note)
    print(f"total {time.perf_counter() - t0:.0f} s; wrote {path}")
    failed = [n for n, r in runs.items() if r["returncode"] != 0]
    if failed:
        raise SystemExit(f"failed: {', '.join(failed)}")
    return path


if __name__ == "__main__":
    main()
