"""minidiff.buffers: arrays are reused only when nothing else refers to them, and reuse
changes no value anywhere (kernels, renders, gradients)."""

from __future__ import annotations

import weakref

import numpy as np
import pytest

import minidiff as md
from minidiff import buffers, kernels
from render import render
from render.scene.teapot import paper_scene

BIG = (50_000, 3)  # 1.2 MB of float64: above buffers.MIN_BYTES


@pytest.fixture(autouse=True)
def fresh_pool():
    buffers.set_max_bytes(512 * 2**20)
    yield
    buffers.set_max_bytes(512 * 2**20)


def test_an_array_in_use_is_never_handed_out_again():
    a = buffers.empty(BIG, np.float64)
    b = buffers.empty(BIG, np.float64)
    assert a is not b and a.shape == BIG and a.dtype == np.float64
    view = b[10:20]
    del b
    c = buffers.empty(BIG, np.float64)  # b's memory is still seen through `view`
    assert c is not a and c.base is None and not np.shares_memory(c, view)
    assert not np.shares_memory(c, a)


def test_an_array_nobody_holds_is_reused():
    a = buffers.empty(BIG, np.float64)
    address = a.__array_interface__["data"][0]
    del a
    b = buffers.empty(BIG, np.float64)
    assert b.__array_interface__["data"][0] == address
    assert buffers.empty(BIG, np.float32).dtype == np.float32  # another key: another array


def test_small_arrays_and_zeros():
    small = buffers.empty((10, 3), np.float64)
    assert small.shape == (10, 3)
    a = buffers.empty(BIG, np.float64)
    a.fill(7.0)
    del a
    z = buffers.zeros(BIG, np.float64)
    assert not z.any()


def test_the_pool_stays_within_its_limit():
    buffers.set_max_bytes(3 * 50_000 * 3 * 8)
    held = [buffers.empty((50_000 + i, 3), np.float64) for i in range(10)]
    assert buffers.held_bytes() <= 3 * 50_000 * 3 * 8
    assert all(h.shape == (50_000 + i, 3) for i, h in enumerate(held))
    buffers.set_max_bytes(0)
    assert buffers.held_bytes() == 0
    a = buffers.empty(BIG, np.float64)
    assert buffers.held_bytes() == 0 and a.shape == BIG


@pytest.mark.parametrize("bad", [-1, 1.5, True, "1"])
def test_bad_limit_raises(bad):
    with pytest.raises(ValueError, match="n must be an integer >= 0"):
        buffers.set_max_bytes(bad)


def test_kernel_results_survive_later_calls():
    rng = np.random.default_rng(0)
    a, b, c, d = (rng.normal(size=BIG) for _ in range(4))
    first = [kernels.cross3(a, b), kernels.dot_last(a, b), kernels.add(a, b)]
    saved = [x.copy() for x in first]
    for _ in range(3):  # later calls with other inputs, dropping their results
        kernels.cross3(c, d), kernels.dot_last(c, d), kernels.add(c, d)
    for x, y in zip(first, saved, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(kernels.cross3(a, b), np.cross(a, b))
    np.testing.assert_array_equal(kernels.dot_last(a, b), np.sum(a * b, axis=-1))


def _lit_function(normals, points, light):
    """A small function to compile (``minidiff.compile``) for the test below."""
    return md.maximum(md.dot(normals, md.normalize(light - points)), 0.0)[..., None] * points


_lit = md.compile(_lit_function, shared=("light",))


def test_compiled_results_survive_later_calls_and_come_from_the_pool():
    # The compiled forward, VJP and JVP take their batch-sized outputs from the pool, as
    # the tape's kernels do (fresh memory there cost the 512x512 boundary term 7 ms of page
    # faults on one thread while the other waited): what a caller holds stays as it was.
    rng = np.random.default_rng(1)
    light = np.array([0.3, 2.0, 1.0])

    def one_pass(seed):
        normals, points = (np.random.default_rng(seed).normal(size=BIG) for _ in range(2))
        p = md.tensor(points, requires_grad=True)
        out = _lit(normals, p, light)
        md.sum(out * out).backward()
        _, tangent = md.jvp(lambda x: _lit(normals, x, light), (p,), (np.ones(BIG),))
        return out.data, p.grad, tangent  # (md.jvp gives the tangent as an array)

    held = one_pass(0)
    saved = [x.copy() for x in held]
    for seed in range(1, 4):  # later calls with other inputs, their results dropped
        one_pass(seed)
    for x, y in zip(held, saved, strict=True):
        np.testing.assert_array_equal(x, y)
    # and its output array is the pool's: kept when the result is dropped, and the next
    # call of the same shape writes into it (a shape no other array here has)
    normals, points = (rng.normal(size=(40_003, 3)) for _ in range(2))
    with md.no_grad():
        before = buffers.held_bytes()
        address = _lit(normals, points, light).data.ctypes.data  # the result dropped
        grown = buffers.held_bytes() - before
        again = _lit(normals, points, light).data
    if buffers.REUSE:
        assert grown == normals.nbytes and buffers.held_bytes() - before == grown
        assert again.ctypes.data == address
    np.testing.assert_array_equal(again, _lit_function(normals, points, light).data)


def _pass(scene, vertices):
    vertices.grad = None
    image = render(scene)
    md.mean_squared_error(image, md.tensor(np.zeros(image.shape))).backward()
    return image.data, vertices.grad


def test_renders_reuse_memory_and_change_nothing():
    scene = paper_scene(96, 96)
    vertices = scene.meshes[0].vertices
    vertices.requires_grad = True
    _pass(scene, vertices)  # results dropped: their arrays go back to the pool
    held = buffers.held_bytes()
    assert held > 0
    image_1, grad_1 = _pass(scene, vertices)
    saved = image_1.copy(), grad_1.copy()
    # The second pass of the same shapes took every large array from the pool ...
    assert buffers.held_bytes() == held
    image_2, grad_2 = _pass(scene, vertices)
    # ... the third too, except those that the second pass's results (still held here)
    # live in ...
    np.testing.assert_array_equal(image_1, saved[0])
    np.testing.assert_array_equal(grad_1, saved[1])
    assert not np.shares_memory(image_1, image_2) and not np.shares_memory(grad_1, grad_2)
    # ... and the values are those of a render without reuse, bit for bit.
    buffers.set_max_bytes(0)
    image_3, grad_3 = _pass(scene, vertices)
    np.testing.assert_array_equal(image_2, image_3)
    np.testing.assert_array_equal(grad_2, grad_3)


def test_the_import_time_proof_holds_here_and_can_fail():
    """On this interpreter the proof passed (reuse is on); with a wrong idea of what an
    unheld array's count is (one higher), it catches a held array being handed out."""
    assert buffers.REUSE and buffers.REUSE_CHECK is None
    right = buffers._UNUSED
    try:
        buffers._UNUSED = right + 1
        assert "was handed out again" in buffers._proof()
    finally:
        buffers._UNUSED = right
    assert buffers._proof() is None


def test_no_held_array_is_ever_handed_out_during_renders():
    """Run renders and their backward passes while arrays from the pool are held by a user,
    a view, the tape (a tensor), a render cache and another thread: no array that came out
    of the pool afterwards shares memory with one that is held."""
    import threading

    from render.scene.cache import RenderCache

    scene = paper_scene(width=128, height=96)  # 12,288 rays: arrays above MIN_BYTES
    vertices = scene.objects[0].vertices
    vertices.requires_grad = True
    image = render(scene, antialias=True)
    (image * image).sum().backward()
    held = [buffers.empty((20_000, 3), np.float64) for _ in range(6)]
    user, view_base, tape_array, cache_array, thread_array, _ = held
    view = view_base[5:]
    tensor = md.as_tensor(tape_array)  # a tensor holds its array, as the tape does
    cache = RenderCache()
    cache.get("slot", [np.zeros(1)], lambda a=cache_array: a)
    release, ready = threading.Event(), threading.Event()

    def holder(array=thread_array):
        ready.set()
        release.wait(timeout=30)

    worker = threading.Thread(target=holder)
    worker.start()
    ready.wait(timeout=30)
    del view_base, tape_array, cache_array, thread_array
    handed_out = []
    original_empty = buffers.empty

    def watched(shape, dtype):
        out = original_empty(shape, dtype)
        handed_out.append(out)
        return out

    buffers.empty = watched
    try:
        for _ in range(2):
            image = render(scene, antialias=True, reuse_visibility=False)
            (image * image).sum().backward()
        handed_out += [original_empty((20_000, 3), np.float64) for _ in range(6)]
    finally:
        buffers.empty = original_empty
        release.set()
        worker.join()
    kept = [user, view, tensor.data, cache.get("slot", [np.zeros(1)], None)[0], held[4]]
    assert handed_out
    for out in handed_out:
        assert not any(np.shares_memory(out, k) for k in kept)


def test_fresh_keeps_nothing_and_is_local_to_its_thread():
    """Inside ``fresh()`` the pool neither grows nor hands out its arrays; another thread
    at the same time still reuses, and outside the block reuse is back."""
    import threading

    a = buffers.empty(BIG, np.float64)
    address = a.__array_interface__["data"][0]
    del a
    seen = {}

    def other():
        b = buffers.empty(BIG, np.float64)
        seen["reused"] = b.__array_interface__["data"][0] == address

    with buffers.fresh():
        held = buffers.held_bytes()
        arrays = [buffers.empty((60_000 + i, 3), np.float64) for i in range(5)]
        assert buffers.held_bytes() == held  # nothing new kept
        c = buffers.empty(BIG, np.float64)
        assert c.__array_interface__["data"][0] != address  # the free array not handed out
        del c
        worker = threading.Thread(target=other)
        worker.start()
        worker.join()
    assert seen["reused"]  # the other thread was not inside fresh()
    d = buffers.empty(BIG, np.float64)
    assert d.__array_interface__["data"][0] == address
    assert len(arrays) == 5


def test_a_path_tracer_pass_leaves_the_pool_as_it_was():
    """The path integrator's shapes change with every batch: it runs inside ``fresh()``.
    The batches are large enough (16 samples of 32 x 32 pixels: arrays of ~400 KB, above
    ``buffers.MIN_BYTES``) that, without ``fresh()``, the pool would keep ~45 MB here."""
    from render.path import render_path
    from render.scene.cornell import cornell_box

    buffers.clear()
    scene = cornell_box(32, 32)
    scene.objects[3].material.albedo.requires_grad = True
    image = render_path(scene, spp=32, max_depth=3, batch_spp=16)
    assert 32 * 32 * 16 * 3 * 8 > buffers.MIN_BYTES  # the batches' arrays would be pooled
    assert buffers.held_bytes() == 0
    image.sum().backward()
    assert np.abs(scene.objects[3].material.albedo.grad).max() > 0


def test_shapes_that_never_come_back_are_dropped_and_recurring_ones_reused():
    """A shape not asked for in ``MAX_AGE`` requests is dropped: 10 * MAX_AGE shapes asked
    for once each (as a boundary term's point counts, new every iteration) leave at most
    MAX_AGE of them in the pool, while a shape asked for every 50 requests keeps its array
    (the same array every time) and an array in use when its shape is dropped is never
    handed out again."""
    n = 10 * buffers.MAX_AGE
    largest_one_off = (16_400 + n) * 8
    assert 16_400 * 8 >= buffers.MIN_BYTES and 50 < buffers.MAX_AGE
    recurring = weakref.ref(buffers.empty(BIG, np.float64))  # the pool's array, unheld
    kept = buffers.empty((16_400 - 1,), np.float64)  # in use while its shape ages out
    kept.fill(3.0)
    most = 0
    for i in range(n):
        buffers.empty((16_400 + i,), np.float64)  # dropped by the caller at once
        if i % 50 == 0:
            assert buffers.empty(BIG, np.float64) is recurring()
        most = max(most, buffers.held_bytes())
    assert most <= (buffers.MAX_AGE + 1) * largest_one_off + BIG[0] * BIG[1] * 8
    late = buffers.empty((16_400 - 1,), np.float64)  # its shape was dropped: a new array
    assert not np.shares_memory(late, kept) and (kept == 3.0).all()


def test_a_shape_is_dropped_after_exactly_max_age_other_requests(monkeypatch):
    """The age is counted in requests of large arrays (not time, not reference counts): a
    shape asked for again after MAX_AGE - 1 other requests is reused, after MAX_AGE it is
    not. Requests inside ``fresh()`` and small arrays do not count."""
    monkeypatch.setattr(buffers, "MAX_AGE", 8)

    def reused_after(others: int, counted: bool = True) -> bool:
        buffers.clear()
        first = weakref.ref(buffers.empty(BIG, np.float64))  # kept by the pool alone
        for i in range(others):
            if counted:
                buffers.empty((20_000 + i,), np.float64)
            else:
                buffers.empty((10 + i,), np.float64)  # small: not from the pool
                with buffers.fresh():
                    buffers.empty((20_000 + i,), np.float64)
        return buffers.empty(BIG, np.float64) is first()

    assert reused_after(7) and not reused_after(8)
    assert reused_after(100, counted=False)
