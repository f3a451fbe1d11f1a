"""Fill Numba's on-disk cache with the renderer's kernels, in two processes at once.

On a fresh clone every kernel compiles on first use: about 370 s of CPU here (2-core AMD
EPYC; the path integrator's ~130 s, the direct renderer's ~240 s), more than all the
tests' own work. pytest-xdist's workers would compile them as their tests reach them, the
ones they both need at once twice over, and the largest on whichever worker's critical
path. So before the workers start, ``tests/conftest.py`` runs this module in two processes
(``python -m tests.warm_kernels CLAIMS``): each takes the next unclaimed task of
``TASKS`` (an atomically created file in the folder ``CLAIMS`` marks a claim; the largest
first) and renders or differentiates a tiny scene as the tests do, which compiles and
caches its kernels; the workers then load them. With a warm cache both finish in seconds.
Nothing is checked here: the tests check.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

import minidiff as md
import render
from render.path import render_path
from render.scene.cornell import cornell_box


def _grad(tensor: md.Tensor) -> md.Tensor:
    return md.tensor(tensor.data, requires_grad=True)


def path_boundary() -> None:
    """The path kernel, the replay on the tape, both boundary terms."""
    scene = cornell_box(8, 8)
    transform = scene.objects[5].transform
    transform.translation = _grad(transform.translation)
    render_path(scene, spp=2, max_depth=3, antialias="boundary").sum().backward()


def path_compiled_replay() -> None:
    """The path kernel's image and its compiled replay (materials)."""
    scene = cornell_box(8, 8)
    material = scene.objects[0].material
    material.albedo = _grad(material.albedo)
    render_path(scene, spp=2, max_depth=3).sum().backward()


def direct_boundary() -> None:
    """The direct renderer's boundary term: mesh edges, shadow borders, a sphere's."""
    scene = render.paper_scene(width=12, height=12)
    scene.objects.append(render.Sphere((0.0, 0.5, 0.0), 0.5, render.Material((0.5, 0.4, 0.3))))
    scene.objects[-1].center = _grad(scene.objects[-1].center)
    scene.lights[0].position = _grad(scene.lights[0].position)
    render.render(scene, antialias="boundary").sum().backward()


def direct_routes() -> None:
    """The fused passes, the adjoint node, the tape, the pair-sampled edges."""
    for antialias in (False, True):
        scene = render.paper_scene(width=12, height=12)
        render.render(scene, antialias=antialias)
        scene.objects[0].vertices = _grad(scene.objects[0].vertices)
        render.render(scene, antialias=antialias).sum().backward()
        scene.lights[0].position = _grad(scene.lights[0].position)
        render.render(scene, antialias=antialias).sum().backward()


def direct_raster() -> None:
    """The rasteriser and the light's view on the random scenes of the tests (a sphere, both
    light kinds; a fresh clone compiled them inside ``test_coordinate_range``)."""
    from tests.render_helpers import random_scene

    with md.no_grad():
        for seed in (1, 4):
            for primary in ("raster", "bvh"):
                render.render(random_scene(seed, width=14, height=12), primary=primary)


#: Largest first, so that the two processes end together.
TASKS: list[Callable[[], None]] = [path_boundary, direct_boundary, direct_routes,
                                   path_compiled_replay, direct_raster]  # fmt: skip


def run(claims: Path) -> None:
    """Run every task of ``TASKS`` that no other process has claimed in ``claims``."""
    for task in TASKS:
        try:
            os.close(os.open(claims / task.__name__, os.O_CREAT | os.O_EXCL))
        except FileExistsError:
            continue
        task()


if __name__ == "__main__":
    run(Path(sys.argv[1]))
