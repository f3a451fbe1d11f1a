"""Images and gradients agree with arrays saved from an earlier version: bit for bit on a
machine recorded in the file, to floating-point rounding on any other.

A refactor of the renderer or of minidiff must not change what a user gets.
``tests/data/golden_render.npz`` holds the image and the gradients of three scenes (the
reference arrays: first written at commit c1c911d, before the code was reorganised (issue
8), last written at fe90a05 on an AVX2 AMD EPYC); the test recomputes them and compares.

Why bit for bit holds on one machine only: the same code rounds differently in the last
bits where the processor or a library build differs. NumPy picks the SIMD kernels of its
vectorised float64 functions and reductions (tan, power, sums, ...) at run time among the
targets it was built with (AVX2, AVX-512, ...), by the CPU features it finds; OpenBLAS picks
its kernels by processor; Numba compiles for the CPU that LLVM names. (Issue 41: on an AMD
Zen 3, 29 of the 65 arrays differed from the saved ones by up to 1.2e-15 of their value,
while a hash of such NumPy results matched the one saved with the arrays.) Hence two checks:

1. Everywhere: each array agrees with the reference to ``RELATIVE_TOLERANCE`` = 1e-12 of its
   largest absolute value. Why that much: float64 rounds each operation to 1.1e-16 of its
   value, and other kernels round other operations, so two machines differ by a few
   roundings of each intermediate value, carried forward. An element here comes out of
   tens to hundreds of operations (rays, intersections, shading), and a gradient sums over
   the 1,920 pixels of a 48 x 40 image: the roundings of ~2,000 terms add up (2,000 x
   1.1e-16 = 2.2e-13 of the largest term), and where the terms cancel, the sum is smaller
   than they are. Measured, as a fraction of each array's largest |value|: at most 9.3e-14,
   both between the machine that first wrote the file and an AVX2 EPYC and between the file
   and an AVX-512 AMD EPYC (Zen 4; the worst array, ``paper/grad9``, is a scalar gradient
   whose sum cancels); 1.2e-15 on issue 41's Zen 3. 1e-12 is ten times the largest
   measured difference, and a change of the math (another formula, sample or term) moves
   values by far more; ``test_the_comparison_tells_rounding_from_change`` checks that 2e-12
   fails.
2. Bit for bit where this machine's fingerprint (``machine_fingerprint``: the platform,
   NumPy's version, BLAS build and the SIMD targets it dispatches to here, Numba's and
   llvmlite's versions and the CPU name and features Numba compiles for, and a hash of
   results that depend on them) equals one recorded in the file: each array's SHA-256 must
   equal the one recorded. This guards refactors on the developers' machines.

Keeping the file (``python -m tests.render.test_golden ...`` from the repository root):

- ``--record`` adds (or replaces) this machine's record: the hashes of the arrays computed
  here, after checking that they agree with the reference to the tolerance. Run it at a
  commit whose renders you trust (say so in the commit); the reference arrays stay as they
  are.
- ``--write`` replaces the reference arrays by this machine's and keeps only this
  machine's record: only for a change that is meant to alter the numbers (say so in the
  commit).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import llvmlite
import llvmlite.binding as llvm
import numba
import numpy as np
import pytest
from numba.core.codegen import get_host_cpu_features

import minidiff as md
import render
from tests.render_helpers import random_scene

GOLDEN = Path(__file__).parents[1] / "data" / "golden_render.npz"
RELATIVE_TOLERANCE = 1e-12  # of each array's largest |value|; see the module docstring
#: Keys of the file that are not arrays to compare: the machines whose hashes are recorded
#: (JSON) and where the reference arrays came from (text).
MACHINES, ABOUT = "machines", "about"


def _scenes() -> dict[str, render.Scene]:
    return {
        "paper": render.paper_scene(width=48, height=40),
        "textured": random_scene(3, lights=("point", "directional"), texture=True, smooth=True),
        "spheres": random_scene(7, lights=("directional",), pyramid=False),
    }


def golden_arrays() -> dict[str, np.ndarray]:
    """Per scene: the image, and the gradient of sum(W * image) for every parameter."""
    out = {}
    for name, scene in _scenes().items():
        # Material.reflectance came later (issue 12): differentiating it traces mirror rays,
        # so it is left out here to keep the saved renders' meaning
        # (tests/render/shade/test_reflection.py);
        # Material.emission (issue 27) likewise, so that the gradients keep their numbering.
        named = scene.named_parameters().items()
        params = [t for key, t in named if not key.endswith((".reflectance", ".emission"))]
        for p in params:
            p.requires_grad = True
        image = render.render(scene, reuse_visibility=False, antialias=False)
        weights = np.random.default_rng(0).standard_normal(image.shape)
        (image * md.tensor(weights)).sum().backward()
        out[f"{name}/image"] = image.data
        for i, p in enumerate(params):
            grad = p.grad if p.grad is not None else np.zeros_like(p.data)
            out[f"{name}/grad{i}"] = np.asarray(grad)
    return out


def _results_hash() -> str:
    """SHA-256 of BLAS products and vectorised float64 functions of fixed data: calls whose
    last bits depend on the processor and the libraries (glibc's libm among them)."""
    rng = np.random.default_rng(1)
    x, m = rng.uniform(-2, 2, (4096, 3)), rng.uniform(-2, 2, (3, 3))
    results = [x @ m, x.T @ x, np.tan(x), np.power(np.abs(x), 7.3), np.exp(x), np.log1p(x**2)]
    results += [np.sin(x), np.cos(x), np.sqrt(np.abs(x)), x.sum(axis=0), np.arctan2(x, m[0])]
    results += [x.sum(), (x * x).sum(axis=1), np.linalg.norm(x, axis=1)]
    digest = hashlib.sha256(b"".join(np.ascontiguousarray(r).tobytes() for r in results))
    return digest.hexdigest()


def machine_fingerprint() -> dict:
    """What decides the last bits of the renders here (the module docstring), as plain JSON
    values: equal fingerprints mean the same code gives the same bits."""
    simd = np.show_config(mode="dicts")["SIMD Extensions"]
    blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    # As Numba's CPU codegen chooses its target (numba.core.codegen.CPUCodegen).
    cpu_name = numba.config.CPU_NAME or llvm.get_host_cpu_name()
    cpu_features = numba.config.CPU_FEATURES or get_host_cpu_features()
    fingerprint = {
        "platform": {
            "system": platform.system(),
            "machine": platform.machine(),
            "python": f"{platform.python_implementation()} {platform.python_version()}",
            "libc": " ".join(platform.libc_ver()),
        },
        "numpy": {
            "version": np.__version__,
            # The targets NumPy dispatches to on this CPU (NPY_DISABLE_CPU_FEATURES included).
            # NumPy leaves a key out when its list is empty (every target disabled).
            "simd_baseline": simd.get("baseline", []),
            "simd_dispatched": simd.get("found", []),
            "blas": f"{blas.get('name')} {blas.get('version')}",
            "blas_build": blas.get("openblas configuration", ""),
            "OPENBLAS_CORETYPE": os.environ.get("OPENBLAS_CORETYPE", ""),
        },
        "numba": {
            "version": numba.__version__,
            "llvmlite": llvmlite.__version__,
            "cpu_name": cpu_name,
            "cpu_features": sorted(f for f in cpu_features.split(",") if f.startswith("+")),
        },
        "results_sha256": _results_hash(),
    }
    return json.loads(json.dumps(fingerprint))  # tuples become lists, as read back


def array_hashes(arrays: dict[str, np.ndarray]) -> dict[str, str]:
    """SHA-256 of each array's dtype, shape and bytes."""
    out = {}
    for key, a in arrays.items():
        a = np.ascontiguousarray(a)
        header = f"{a.dtype.str}{a.shape}".encode()
        out[key] = hashlib.sha256(header + a.tobytes()).hexdigest()
    return out


def load_golden(path: Path = GOLDEN) -> tuple[dict[str, np.ndarray], list[dict], str]:
    """The reference arrays, the machine records ({"machine", "sha256", "note"}) and the
    note on where the arrays came from."""
    with np.load(path) as saved:
        arrays = {key: saved[key] for key in saved.files if key not in (MACHINES, ABOUT)}
        machines = json.loads(str(saved[MACHINES])) if MACHINES in saved.files else []
        about = str(saved[ABOUT]) if ABOUT in saved.files else ""
    return arrays, machines, about


def recorded_hashes(machines: list[dict], fingerprint: dict) -> dict[str, str] | None:
    """The array hashes recorded for this fingerprint, or None where it is not recorded."""
    for record in machines:
        if record["machine"] == fingerprint:
            return record["sha256"]
    return None


def mismatches(
    now: dict[str, np.ndarray], reference: dict[str, np.ndarray], exact: dict[str, str] | None
) -> list[str]:
    """What fails: arrays missing or extra, a dtype or shape changed, an array farther than
    RELATIVE_TOLERANCE x its largest |value| from the reference, and where ``exact`` holds
    this machine's recorded hashes, an array whose bits changed."""
    if sorted(now) != sorted(reference):
        return [f"keys differ: {sorted(set(now) ^ set(reference))}"]
    hashes = array_hashes(now) if exact is not None else {}
    failures = []
    for key, saved in reference.items():
        a = now[key]
        if a.dtype != saved.dtype or a.shape != saved.shape:
            failures.append(f"{key}: {a.dtype}{a.shape}, saved {saved.dtype}{saved.shape}")
            continue
        scale = np.abs(saved).max(initial=0.0)
        error = np.abs(a - saved).max(initial=0.0)
        if not error <= RELATIVE_TOLERANCE * scale:
            failures.append(f"{key}: off by {error:.3g}, {error / scale:.3g} of its largest")
        elif exact is not None and hashes[key] != exact[key]:
            relative = error / scale if scale else error
            failures.append(
                f"{key}: bits changed ({relative:.3g} of its largest from the reference)"
            )
    return failures


def test_images_and_gradients_agree_with_the_saved_ones():
    reference, machines, _ = load_golden()
    exact = recorded_hashes(machines, machine_fingerprint())
    failures = mismatches(golden_arrays(), reference, exact)
    machine = "recorded: bit for bit" if exact is not None else "not recorded: to rounding"
    assert not failures, f"this machine is {machine}; " + "; ".join(failures)


def test_the_comparison_tells_rounding_from_change():
    """Without a record, last-bit differences pass and a change of a millionth of a millionth
    and more fails; with this machine's record, one bit changed anywhere fails."""
    reference, _, _ = load_golden()
    nudged = {}
    for key, a in reference.items():  # four units in the last place of the largest value
        scale = np.abs(a).max(initial=0.0)
        nudged[key] = a + 4 * np.spacing(scale) * np.sign(a)
    assert mismatches(nudged, reference, None) == []
    assert len(mismatches(nudged, reference, array_hashes(reference))) == sum(
        bool(np.abs(a).max(initial=0.0)) for a in reference.values()
    )
    assert mismatches(reference, reference, array_hashes(reference)) == []

    changed = dict(reference)
    image = reference["paper/image"].copy()
    image.flat[np.argmax(image)] *= 1 + 2e-12
    changed["paper/image"] = image
    assert [m.split(":")[0] for m in mismatches(changed, reference, None)] == ["paper/image"]

    one_bit = dict(reference)
    one_bit["spheres/grad0"] = np.nextafter(reference["spheres/grad0"], np.inf)
    assert mismatches(one_bit, reference, None) == []
    failures = mismatches(one_bit, reference, array_hashes(reference))
    assert [m.split(":")[0] for m in failures] == ["spheres/grad0"]


def _fingerprint_in_new_process(**environ: str) -> dict:
    """machine_fingerprint() computed by a new Python process with these environment
    variables (NumPy reads its dispatch settings, Numba its target, at import)."""
    code = "import json, tests.render.test_golden as t; print(json.dumps(t.machine_fingerprint()))"
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=Path(__file__).parents[2],
        env={**os.environ, **environ},
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout)


@pytest.mark.new_processes
def test_the_fingerprint_sees_numpys_dispatch_and_numbas_target():
    """A NumPy that dispatches to fewer SIMD targets (the CPU unchanged), or a Numba that
    compiles for another CPU, is another machine for the bits."""
    here = machine_fingerprint()
    assert _fingerprint_in_new_process() == here
    found = here["numpy"]["simd_dispatched"]
    if found:  # a CPU with none of NumPy's dispatch targets has nothing to switch off
        fewer = _fingerprint_in_new_process(NPY_DISABLE_CPU_FEATURES=found[-1])
        assert fewer["numpy"]["simd_dispatched"] == found[:-1]
    generic = _fingerprint_in_new_process(NUMBA_CPU_NAME="generic")
    assert generic["numba"]["cpu_name"] == "generic" != here["numba"]["cpu_name"]


def _git_head() -> str:
    command = ["git", "rev-parse", "--short", "HEAD"]
    return subprocess.run(command, capture_output=True, text=True).stdout.strip() or "?"


def _write(arrays: dict[str, np.ndarray], machines: list[dict], about: str) -> None:
    np.savez_compressed(GOLDEN, **{MACHINES: json.dumps(machines), ABOUT: about}, **arrays)


if __name__ == "__main__":
    if sys.argv[1:] not in (["--write"], ["--record"]):
        sys.exit(
            "usage: python -m tests.render.test_golden --record (adds this machine's hashes)"
            "\n       python -m tests.render.test_golden --write (overwrites the saved arrays)"
        )
    now, here = golden_arrays(), machine_fingerprint()
    record = {"machine": here, "sha256": array_hashes(now), "note": f"at {_git_head()}"}
    if sys.argv[1] == "--write":
        _write(now, [record], f"written at {_git_head()} on {here['numba']['cpu_name']}")
        print(f"wrote {GOLDEN}")
    else:
        reference, machines, about = load_golden()
        failures = mismatches(now, reference, None)
        if failures:
            sys.exit("not recorded, the arrays differ from the reference: " + "; ".join(failures))
        machines = [m for m in machines if m["machine"] != here] + [record]
        _write(reference, machines, about)
        print(f"recorded this machine's hashes in {GOLDEN} ({len(machines)} machines)")
