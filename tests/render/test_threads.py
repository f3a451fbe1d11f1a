"""Rendering from several threads at once gives every thread what it would get alone.

Users do this: Numba kernels release the GIL, and fitting several views with a thread pool
is the obvious way to use more than one core. Each thread renders its own scenes with
``backward`` (plain, antialiased, the boundary term, 4 samples per pixel, mirrors), and all
of them render one shared scene read-only; every image and gradient must be bit-identical
to the same work done alone, and gradient mode must be what it was in every thread
afterwards.
"""

from __future__ import annotations

import threading
from copy import deepcopy

import numpy as np

import minidiff as md
import render
from render import Material
from render.scene.cache import cache_for, share_cache
from tests.render_helpers import random_scene

N_THREADS = 4


def scene_and_options(job: int):
    """A different scene and render options for each job number."""
    kind = job % 6
    if kind == 0:
        return render.paper_scene(width=40, height=32), {}
    if kind == 1:
        return render.paper_scene(width=40, height=32), {"antialias": True}
    if kind == 2:
        return random_scene(job, lights=("point", "directional"), texture=True), {"spp": 4}
    if kind == 3:
        mirror = Material((0.05, 0.05, 0.05), reflectance=0.8)
        return render.paper_scene(width=32, height=24, ground_material=mirror), {}
    if kind == 5:  # its curve points found beside the mixed pixels (threads.beside)
        return render.paper_scene(width=40, height=32, ground=True), {"antialias": "boundary"}
    return random_scene(job, smooth=True), {"antialias": True}


def render_with_gradients(job: int) -> list[np.ndarray]:
    """The image and the gradient of a fixed weighted sum of it for every parameter (two
    renders of the same scene, so that the second one reuses the cache)."""
    scene, options = scene_and_options(job)
    params = [t for _, t in sorted(scene.named_parameters().items())]
    for p in params:
        p.requires_grad = True
    for _ in range(2):
        for p in params:
            p.grad = None
        image = render.render(scene, **options)
        weights = np.random.default_rng(job).standard_normal(image.shape)
        (image * md.tensor(weights)).sum().backward()
    grads = [np.zeros_like(p.data) if p.grad is None else np.array(p.grad) for p in params]
    return [image.data.copy()] + grads


def run_in_threads(work, jobs_per_thread: list[list[int]]):
    """Run ``work(job)`` for every job, each list of jobs in its own thread, all threads
    released at once; returns {job: result} and each thread's grad mode at the end."""
    results, modes, errors = {}, {}, []
    barrier = threading.Barrier(len(jobs_per_thread))

    def thread_main(index: int, jobs: list[int]) -> None:
        try:
            barrier.wait()
            for job in jobs:
                results[job] = work(job)
            modes[index] = md.is_grad_enabled()
        except BaseException as error:  # reported in the main thread
            errors.append(error)

    threads = [
        threading.Thread(target=thread_main, args=(i, jobs))
        for i, jobs in enumerate(jobs_per_thread)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return results, modes


def assert_identical(got: list[np.ndarray], expected: list[np.ndarray]) -> None:
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)


def test_threads_rendering_different_scenes_with_backward_match_the_work_done_alone():
    jobs = [[t + N_THREADS * k for k in range(3)] for t in range(N_THREADS)]
    alone = {job: render_with_gradients(job) for row in jobs for job in row}
    together, modes = run_in_threads(render_with_gradients, jobs)
    for job, expected in alone.items():
        assert_identical(together[job], expected)
    assert modes == {i: True for i in range(N_THREADS)}
    assert md.is_grad_enabled()


def test_no_kernel_uses_numbas_parallel_loops():
    """Every Numba kernel of the renderer and of minidiff runs on ``minidiff.threads``'s
    pool (``nogil``), none through Numba's ``parallel=True``: Numba's fallback threading
    layer (workqueue) aborts the process when two threads launch parallel kernels at once
    (docs/architecture.md)."""
    import importlib
    import pkgutil

    from numba.core.registry import CPUDispatcher

    kernels, parallel = 0, []
    for package in ("render", "minidiff"):
        root = importlib.import_module(package)
        for info in pkgutil.walk_packages(root.__path__, package + "."):
            if info.name in ("render.torch", "render.jax"):
                continue  # optional bridges: their frameworks may be absent
            module = importlib.import_module(info.name)
            for value in vars(module).values():
                if isinstance(value, CPUDispatcher) and value.py_func.__module__ == info.name:
                    kernels += 1
                    if value.targetoptions.get("parallel"):
                        parallel.append(info.name + "." + value.py_func.__name__)
    assert kernels > 50 and parallel == []


def test_threads_rendering_one_shared_scene_read_only_match_a_render_alone():
    scene = render.paper_scene(width=48, height=40)
    options = [{}, {"antialias": True}, {"spp": 4}, {"antialias": True, "spp": 4}]
    alone = {}
    for i, opts in enumerate(options):
        with md.no_grad():
            alone[i] = render.render(scene, reuse_visibility=False, **opts).data.copy()

    def work(job: int) -> list[np.ndarray]:
        opts = options[job % len(options)]
        if job % 2:  # with the tape on (nothing requires grad: a constant image)
            return [render.render(scene, **opts).data.copy()]
        with md.no_grad():
            return [render.render(scene, **opts).data.copy()]

    jobs = [[t + N_THREADS * k for k in range(4)] for t in range(N_THREADS)]
    together, modes = run_in_threads(work, jobs)
    for job, (image,) in together.items():
        np.testing.assert_array_equal(image, alone[job % len(options)])
    assert modes == {i: True for i in range(N_THREADS)}
    assert md.is_grad_enabled()


def test_no_grad_in_one_thread_does_not_switch_the_tape_off_in_another():
    inside, other_saw = threading.Event(), []
    release = threading.Event()

    def holder() -> None:
        with md.no_grad():
            inside.set()
            release.wait(timeout=10)

    def watcher() -> None:
        inside.wait(timeout=10)
        x = md.tensor(np.ones(3), requires_grad=True)
        other_saw.append((md.is_grad_enabled(), (x * 2.0).requires_grad))
        release.set()

    threads = [threading.Thread(target=holder), threading.Thread(target=watcher)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert other_saw == [(True, True)]
    assert md.is_grad_enabled()


def boundary_gradients() -> list[np.ndarray]:
    """The image and every parameter's gradient of the paper scene on a ground, with the
    boundary term (its points found beside the mixed pixels where there are threads)."""
    scene = render.paper_scene(width=48, height=40, ground=True)
    params = [t for _, t in sorted(scene.named_parameters().items())]
    for p in params:
        p.requires_grad = True
    image = render.render(scene, antialias="boundary")
    weights = np.random.default_rng(3).standard_normal(image.shape)
    (image * md.tensor(weights)).sum().backward()
    return [image.data.copy()] + [np.array(p.grad) for p in params]


def test_the_boundary_terms_points_found_beside_the_mixed_pixels_change_no_bit(monkeypatch):
    """With two threads or more the renderer finds the boundary term's curve points on a
    second thread while it finds and shades the mixed pixels (``minidiff.threads.beside``):
    the image and every gradient are those of one thread, bit for bit."""
    import render.renderer as renderer
    from minidiff.threads import using_threads

    where = []
    find = renderer.terms.boundary_points_of

    def recorded(*args):
        where.append(threading.get_ident())
        return find(*args)

    monkeypatch.setattr(renderer.terms, "boundary_points_of", recorded)

    with using_threads(1):
        alone = boundary_gradients()
    assert where == [threading.get_ident()]
    for count in (2, 3):
        with using_threads(count):
            assert_identical(boundary_gradients(), alone)
    assert len(where) == 3 and threading.get_ident() not in where[1:]


def test_the_curve_kinds_points_taken_by_the_mixed_pixels_thread_change_no_bit(monkeypatch):
    """Once its mixed pixels are done, the renderer's own thread takes the kinds' points
    (and the mesh edges' side passes) that the second thread has not begun
    (``minidiff.threads.share_tasks``). Forced here: the first kind's points wait until
    another kind's have been found on the renderer's thread. The image and every gradient
    are those of one thread, bit for bit."""
    from minidiff.threads import using_threads
    from render.edges.boundary import term

    runs = []
    boundary_points = term.boundary_points

    def forcing(view, kinds):
        taken, where = threading.Event(), []
        for k, kind in enumerate(kinds):
            monkeypatch.setattr(kind, "points", waiting(kind.points, k, taken, where))
        found = boundary_points(view, kinds)
        runs.append(where)
        return found

    def waiting(points, k, taken, where):
        def points_here(*args):
            if k == 0 and threading.get_ident() != main:
                assert taken.wait(10.0)  # another kind's points, found on the main thread
            result = points(*args)
            where.append((k, threading.get_ident()))
            if threading.get_ident() == main:
                taken.set()
            return result

        return points_here

    main = threading.get_ident()
    with using_threads(1):
        alone = boundary_gradients()
    monkeypatch.setattr(term, "boundary_points", forcing)
    with using_threads(2):
        assert_identical(boundary_gradients(), alone)
    assert len(runs) == 1 and len(runs[0]) >= 3
    assert {k for k, thread in runs[0] if thread == main} - {0}  # some taken by this thread
    first = [thread for k, thread in runs[0] if k == 0]
    assert len(first) == 1 and first[0] != main  # the first kind's, on the second thread


def test_threads_sharing_one_render_cache_with_lights_of_their_own_match_a_render_alone():
    """Copies of one scene, each with its light elsewhere, sharing the scene's render cache
    (``share_cache``, as ``render.inverse.function``'s copies do), rendered with the
    boundary term from several threads at once: the mixed pixels' kept first hits, grown by
    every render, give each the image it gets alone without reuse."""
    scene = render.paper_scene(width=48, height=40, ground=True)
    cache = cache_for(scene, True)

    def moved(job: int) -> render.Scene:
        copy = deepcopy(scene)
        copy.lights[0].position.data[:] += (0.04 * (job % 5), 0.0, 0.03 * (job % 3))
        share_cache(copy, cache)
        return copy

    with md.no_grad():
        alone = {job: render.render(moved(job), antialias="boundary", reuse_visibility=False)
                 .data.copy() for job in range(3 * N_THREADS)}  # fmt: skip

    def work(job: int) -> list[np.ndarray]:
        with md.no_grad():
            return [render.render(moved(job), antialias="boundary").data.copy()]

    jobs = [[t + N_THREADS * k for k in range(3)] for t in range(N_THREADS)]
    together, _ = run_in_threads(work, jobs)
    for job, (image,) in together.items():
        np.testing.assert_array_equal(image, alone[job])
    assert cache.latest("interior first hits") is not None
