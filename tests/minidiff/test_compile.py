"""minidiff.compile: the traced kernels against the tape they were traced from.

Every check runs a function twice: compiled (``f``) and on the tape primitive by primitive
(``f.function``), and compares the forward values, the VJP (reverse mode through ``backward``)
and the JVP (forward mode through ``md.jvp``). Programs are drawn by Hypothesis from every
supported primitive, with broadcasting between batched and shared arguments, gathers with
repeated and negative indices, and inputs that include NaN and inf.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
from minidiff import backend, codegen, compiler
from minidiff.trace import CompileError

RTOL = 1e-12


def assert_close(actual, expected, what: str, sparse_zeros: bool = False) -> None:
    """Equal to 1e-12 of the expected array's scale; NaN where and only where it is NaN;
    the same infinities.

    ``sparse_zeros`` (derivatives where values are NaN): the tape works on whole arrays, so a
    lane the result never reads still gets a zero gradient, which a NaN slope turns into
    NaN (x[:, 1] of exp(x) with x[0, 0] = NaN: 0 * exp(NaN)), and a sum that includes it
    is NaN too. The compiled program works lane by lane and never forms those products.
    So where the tape's derivative is NaN the compiled one may be anything; everywhere
    else they must agree as usual (and the compiled one must not be NaN)."""
    actual, expected = np.asarray(actual, float), np.asarray(expected, float)
    assert actual.shape == expected.shape, (what, actual.shape, expected.shape)
    nan = np.isnan(expected)
    if sparse_zeros:
        actual = np.where(nan, np.nan, actual)
    assert np.array_equal(np.isnan(actual), nan), f"{what}: NaN at different places"
    inf = np.isinf(expected)
    assert np.array_equal(actual[inf], expected[inf]), f"{what}: infinities differ"
    finite = ~nan & ~inf
    if finite.any():
        scale = max(1.0, float(np.abs(expected[finite]).max()))
        error = float(np.abs(actual[finite] - expected[finite]).max())
        assert error <= RTOL * scale, f"{what}: off by {error:.3g} at scale {scale:.3g}"


# ---------------------------------------------------------------------------------------------
# Random programs
# ---------------------------------------------------------------------------------------------
# A program is a list of steps, each applying one primitive to earlier values (by position
# in a pool that starts with the arguments). Values are (n, 3) or (n, 1) batched, (3,) or ()
# shared; reductions keep a trailing axis of 1 (x[..., None]) so that everything
# broadcasts with everything.

UNARY = ["negative", "exp", "log", "sqrt", "sin", "cos", "tan", "tanh", "abs", "normalize",
         "norm", "sum", "mean", "max", "clip", "square", "lane", "detach"]  # fmt: skip
BINARY = ["add", "subtract", "multiply", "divide", "power", "maximum", "minimum", "where",
          "dot", "cross", "stack"]  # fmt: skip


def _unary(op: str, x):
    vector = x.ndim >= 1 and x.shape[-1] == 3
    if op in ("normalize", "norm", "sum", "mean", "max", "lane") and not vector:
        return md.exp(x * 0.5)
    if op == "normalize":
        return md.normalize(x)
    if op == "norm":
        return md.norm(x)[..., None]
    if op in ("sum", "mean", "max"):
        return getattr(md, op)(x, axis=-1)[..., None]
    if op == "clip":
        return md.clip(x, -1.0, 2.0)
    if op == "square":
        return x**2.0
    if op == "lane":
        return x[..., 1:2]
    return getattr(md, op)(x)


def _binary(op: str, a, b):
    vectors = all(v.ndim >= 1 and v.shape[-1] == 3 for v in (a, b))
    if op in ("dot", "cross", "stack") and not vectors or op == "stack" and a.shape != b.shape:
        return a * b + 1.0
    if op == "dot":
        return md.dot(a, b)[..., None]
    if op == "cross":
        return md.cross(a, b)
    if op == "stack":
        return md.stack([a[..., 0], b[..., 2], a[..., 1]], axis=-1)
    if op == "where":
        return md.where(a > b, a, b * 2.0)
    return getattr(md, op)(a, b)


def make_program(steps):
    def program(x, y, s, t):
        pool = [x, y, s, t]
        for op, i, j in steps:
            a, b = pool[i % len(pool)], pool[j % len(pool)]
            pool.append(_unary(op, a) if op in UNARY else _binary(op, a, b))
        return pool[-1] + 0.0 * x, pool[-2] * y

    return md.compile(program, shared=("s", "t"))


# Magnitudes from 1e-3 to 3 (or 0): gradients that cancel (x / y * y) then agree to 1e-12
# of the terms' size, which stays near the result's size; NaN and inf come from `special`.
values = st.one_of(st.just(0.0), st.floats(1e-3, 3), st.floats(-3, -1e-3))
special = st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -0.0])


@st.composite
def arrays(draw, shape, specials: bool):
    size = int(np.prod(shape))
    flat = np.array(draw(st.lists(values, min_size=size, max_size=size)), float)
    if specials and size and draw(st.booleans()):
        flat[draw(st.integers(0, size - 1))] = draw(special)
    return flat.reshape(shape)


steps_strategy = st.lists(
    st.tuples(st.sampled_from(UNARY + BINARY), st.integers(0, 50), st.integers(0, 50)),
    min_size=1,
    max_size=12,
)


def _inputs(draw, n, specials):
    return [draw(arrays(shape, specials)) for shape in ((n, 3), (n, 1), (3,), ())]


def _tape(fn, inputs, weights):
    tensors = [md.tensor(a, requires_grad=True) for a in inputs]
    outs = fn(*tensors)
    loss = (outs[0] * weights[0]).sum() + (outs[1] * weights[1]).sum()
    loss.backward()
    # an argument the result does not depend on: None on the tape, zeros from the compiled
    # function (one node, all of whose inputs get a gradient)
    grads = [np.zeros(t.shape) if t.grad is None else t.grad for t in tensors]
    return [o.data for o in outs], grads


def _check(f, inputs, weights, tangents) -> None:
    # Derivatives with ``sparse_zeros`` whatever the inputs: a zero input makes NaN as well
    # as a NaN input does (x / x at x = 0), and the tape's NaN in the lanes the result
    # never reads is then the same artefact (``assert_close``).
    with np.errstate(all="ignore"):
        expected, expected_grads = _tape(f.function, inputs, weights)
        actual, actual_grads = _tape(f, inputs, weights)
        for k in range(2):
            assert_close(actual[k], expected[k], f"output {k}")
        for name, a, e in zip("xyst", actual_grads, expected_grads, strict=True):
            assert_close(a, e, f"gradient of {name}", sparse_zeros=True)
        _, expected_t = md.jvp(lambda *a: f.function(*a)[0], inputs, tangents)
        _, actual_t = md.jvp(lambda *a: f(*a)[0], inputs, tangents)
        assert_close(actual_t, expected_t, "tangent", sparse_zeros=True)


def _draw_and_check(data, steps, n, specials: bool) -> None:
    """A random program, its inputs (with NaN/inf if ``specials``), cotangents and tangents
    (finite), checked against the tape."""
    f = make_program(steps)
    inputs = _inputs(data.draw, n, specials=specials)
    weights = [data.draw(arrays((n, 3), False)), data.draw(arrays((n, 3), False))]
    tangents = _inputs(data.draw, n, specials=False)
    _check(f, inputs, weights, tangents)


@settings(max_examples=40)
@given(st.data(), steps_strategy, st.integers(1, 7))
def test_random_programs_equal_the_tape(data, steps, n):
    _draw_and_check(data, steps, n, specials=False)


@settings(max_examples=25)
@given(st.data(), steps_strategy, st.integers(1, 5))
def test_nan_and_inf_propagate_as_on_the_tape(data, steps, n):
    _draw_and_check(data, steps, n, specials=True)


def test_ties_and_kinks_take_the_tapes_subgradients():
    """maximum/minimum ties, clip at its bounds, abs and norm at 0, max with tied lanes."""

    @md.compile(shared=("s",))
    def kinks(x, s):
        return (
            md.maximum(x, s) + md.minimum(s, x) + md.clip(x, 0.0, 1.0) + md.abs(x),
            md.max(x, axis=-1)[:, None] + md.norm(x * 0.0 + x)[:, None] + md.normalize(x * 0.0),
        )

    x = np.array([[0.0, 1.0, 1.0], [0.5, 0.5, -2.0], [0.0, 0.0, 0.0]])
    s = np.array([0.0, 1.0, 0.5])
    w = np.arange(9.0).reshape(3, 3) - 4
    for fn in (kinks, kinks.function):
        tensors = [md.tensor(x, requires_grad=True), md.tensor(s, requires_grad=True)]
        a, b = fn(*tensors)
        ((a * w).sum() + (b * w).sum()).backward()
        if fn is kinks:
            compiled = [tensors[0].grad, tensors[1].grad]
        else:
            assert_close(compiled[0], tensors[0].grad, "x")
            assert_close(compiled[1], tensors[1].grad, "s")


# ---------------------------------------------------------------------------------------------
# Gathers
# ---------------------------------------------------------------------------------------------


@md.compile(shared=("vertices", "faces"))
def centroid_light(vertices, faces, hit, weights):
    corners = vertices[faces[hit]]  # (n, 3, 3): a table gathered through an integer table
    centre = md.mean(corners, axis=1)
    return md.normalize(centre) * weights[:, None] + vertices[hit] * 0.5


@settings(max_examples=20)
@given(st.data(), st.integers(1, 40), st.integers(1, 6))
def test_gathers_with_repeated_and_negative_indices(data, n, rows):
    vertices = data.draw(arrays((rows, 3), False))
    corner = st.integers(-rows, rows - 1)
    face = st.lists(corner, min_size=3, max_size=3)
    faces = np.array(data.draw(st.lists(face, min_size=rows, max_size=rows)))
    hit = np.array(data.draw(st.lists(st.integers(-rows, rows - 1), min_size=n, max_size=n)))
    weights = data.draw(arrays((n,), False))
    cot = data.draw(arrays((n, 3), False))
    grads = []
    for fn in (centroid_light, centroid_light.function):
        ts = [md.tensor(vertices, requires_grad=True), md.tensor(weights, requires_grad=True)]
        out = fn(ts[0], faces, hit, ts[1])
        (out * cot).sum().backward()
        grads.append((out.data, ts[0].grad, ts[1].grad))
    for a, e, what in zip(grads[0], grads[1], ("value", "d/dvertices", "d/dweights"), strict=True):
        assert_close(a, e, what)
    tangent = data.draw(arrays((rows, 3), False))
    _, t1 = md.jvp(lambda v: centroid_light(v, faces, hit, weights), (vertices,), (tangent,))
    _, t2 = md.jvp(
        lambda v: centroid_light.function(v, faces, hit, weights), (vertices,), (tangent,)
    )
    assert_close(t1, t2, "tangent")


@md.compile(shared=("table",))
def cell_blend(x, table):
    """A 1-D linear interpolation of ``table`` (m, 1) at x (n,) in cells: floor picks the
    cell, to_index makes it a row (wrapped into the table by floats: floor and to_index
    take no derivative), the blend weight x - floor(x) carries x's."""
    cell = md.floor(x)
    m = table.shape[0]
    row = cell - m * md.floor(cell / m)  # in [0, m)
    after = md.where(row + 1.0 >= m, 0.0, row + 1.0)
    w = md.reshape(x - cell, (-1, 1))
    return table[md.to_index(row)] * (1.0 - w) + table[md.to_index(after)] * w


@settings(max_examples=25)
@given(st.data(), st.integers(1, 20), st.integers(1, 6))
def test_floor_and_to_index_give_the_tapes_cells_and_derivatives(data, n, m):
    """``floor`` (a step: no derivative) and ``to_index`` (floats holding integers as
    gather rows) compiled against the tape: the same values and gradients, through the
    blend weight only; NaN and infinite x read as the tape reads them (floor passes them
    on; to_index gives row 0 for NaN)."""
    x = np.array(data.draw(st.lists(st.floats(-50, 50), min_size=n, max_size=n)))
    if data.draw(st.booleans()):
        x[data.draw(st.integers(0, n - 1))] = data.draw(st.sampled_from([np.nan, 7.0, -3.0]))
    table = data.draw(arrays((m, 1), False))
    cot = data.draw(arrays((n, 1), False))
    results = []
    for fn in (cell_blend, cell_blend.function):
        ts = [md.tensor(x, requires_grad=True), md.tensor(table, requires_grad=True)]
        out = fn(*ts)
        (out * cot).sum().backward()
        results.append((out.data, ts[0].grad, ts[1].grad))
    for a, e, what in zip(results[0], results[1], ("value", "d/dx", "d/dtable"), strict=True):
        assert_close(a, e, what, sparse_zeros=True)
    assert np.array_equal(md.floor(x).data, np.floor(x), equal_nan=True)
    ints = np.trunc(np.where(np.isnan(x), 0.0, x))
    assert np.array_equal(md.to_index(x), ints.astype(np.int64))  # toward 0, NaN as 0


@md.compile(shared=("table",))
def picked_rows(x, rows, fallback, table):
    """Rows of ``table`` (m, 3) picked by an integer ``where``: ``rows`` where x > 0, else
    ``fallback``, times x."""
    return table[md.where(x > 0.0, rows, fallback)] * md.reshape(x, (-1, 1))


@settings(max_examples=20)
@given(st.data(), st.integers(1, 30), st.integers(1, 6))
def test_where_picks_integer_indices(data, n, m):
    """``where`` on two integer arrays (indices) picks as NumPy's does, and the gather it
    feeds gets the gradient of the rows picked."""
    x = data.draw(arrays((n,), False))
    table = data.draw(arrays((m, 3), False))
    index = st.lists(st.integers(-m, m - 1), min_size=n, max_size=n)
    rows, fallback = (np.array(data.draw(index)) for _ in range(2))
    t = md.tensor(table, requires_grad=True)
    out = picked_rows(x, rows, fallback, t)
    picked = np.where(x > 0.0, rows, fallback)
    assert_close(out.data, table[picked] * x[:, None], "value")
    cot = data.draw(arrays((n, 3), False))
    (out * cot).sum().backward()
    expected = np.zeros_like(table)
    np.add.at(expected, picked, cot * x[:, None])
    assert_close(t.grad, expected, "d/dtable")


@pytest.mark.parametrize("rows", [50, codegen.PARTIAL_LIMIT // 3 + 50])
@pytest.mark.parametrize("ascending", [False, True])
def test_large_batches_add_gathered_gradients_with_the_same_bits_on_any_threads(
    ascending, rows, monkeypatch
):
    """A table of at most ``codegen.PARTIAL_LIMIT`` numbers: its gradient summed per group
    of chunks in the kernel, the groups in order afterwards. A larger one: each element's
    contribution written by the kernel (its chunks on the threads) and added by the scatter
    kernel in element order, runs of one row in registers; with the rows ascending, on the
    threads, each a range of rows, skipping the blocks of elements it has no rows in (in
    random order, on one thread). Either way the same bits on one thread, two and three,
    and the tape's gradient to rounding."""
    monkeypatch.setattr(compiler, "PARALLEL_WORK", 0)  # every kernel on the threads
    monkeypatch.setattr(compiler, "PARALLEL_SCATTER", 0)
    rng = np.random.default_rng(3)
    n = 40 * codegen.CHUNK + 100
    vertices, faces = rng.normal(size=(rows, 3)), rng.integers(-rows, rows, size=(30, 3))
    hit, weights = rng.integers(-30, 30, size=n), rng.normal(size=n)
    if ascending:  # every gather's rows ascending: the faces' by hit, the vertices' by face
        faces, hit = np.sort(faces, axis=0), np.sort(rng.integers(0, 30, size=n))
    cot = rng.normal(size=(n, 3))
    grads = []
    runs = ((1, centroid_light), (2, centroid_light), (3, centroid_light))
    for threads, fn in (*runs, (1, centroid_light.function)):
        with compiler.using_threads(threads):
            t = md.tensor(vertices, requires_grad=True)
            (fn(t, faces, hit, weights) * cot).sum().backward()
            grads.append(t.grad)
    assert np.array_equal(grads[0], grads[1]) and np.array_equal(grads[0], grads[2])
    assert_close(grads[0], grads[3], "d/dvertices")


@settings(max_examples=60, deadline=None)
@given(data=st.data(), columns=st.integers(1, 4), rows=st.integers(1, 12))
def test_scatter_kernel_adds_in_element_order(data, columns, rows):
    """``codegen.scatter_add``, which sums a run of elements on one row in registers: every
    row of the table gets ``row + c_i + c_j + ...`` over its elements in element order, the
    same bits as adding them one at a time (infinities, signed zeros and wide ranges of
    magnitude included; NaN where NaN), a negative row counted from the end. A call given a range of
    rows adds only theirs, with or without the blocks' lowest and highest rows
    (``codegen.row_bounds``, here blocks of 4 elements) to skip the blocks of other rows
    by."""
    n = data.draw(st.integers(0, 60))
    run = st.lists(st.integers(-rows, rows - 1), min_size=1, max_size=8).map(
        lambda r: [r[0]] * len(r)  # runs of one row, as hits on one triangle give
    )
    where = np.array(sum(data.draw(st.lists(run, max_size=n)), []), np.int64)
    if data.draw(st.booleans()):  # rows mostly ascending: whole blocks of other rows
        where = where[np.argsort(where % rows, kind="stable")]
    special = st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e300, -1e-300])
    value = st.one_of(st.floats(-1e6, 1e6), special)
    share = np.array(
        data.draw(st.lists(value, min_size=len(where) * columns, max_size=len(where) * columns)),
        np.float64,
    ).reshape(len(where), columns)
    start = np.array(data.draw(st.lists(value, min_size=rows * columns, max_size=rows * columns)))
    first = data.draw(st.integers(0, rows))
    end = data.draw(st.integers(first, rows))
    expected = start.reshape(rows, columns).copy()
    with np.errstate(all="ignore"):  # inf - inf: NaN, as in the kernel
        for i, r in enumerate(where):
            if first <= r % rows < end:
                expected[r] += share[i]
    block = 4
    blocks = -(-len(where) // block)
    bounds = np.full((max(1, blocks), 2), -7, np.int64)
    finder = backend.compile_ir(codegen.row_bounds(block))
    sizes = np.array([rows, 0], np.int64)
    finder._function(compiler._addresses([where, bounds, sizes]), len(where), 0, blocks)
    for b in range(blocks):  # each block's lowest and highest row
        mine = where[b * block : (b + 1) * block] % rows
        assert tuple(bounds[b]) == (mine.min(), mine.max())
    kernel = backend.compile_ir(codegen.scatter_add(columns, block))
    for skip in (0, 1):
        table = start.reshape(rows, columns).copy()
        sizes[1] = skip
        buffers = [where, share, table, sizes, bounds]
        kernel._function(compiler._addresses(buffers), len(where), first, end)
        np.testing.assert_array_equal(table, expected)  # NaN where NaN; -0.0 kept by bits
        # (a NaN's sign is not: LLVM, like C, may swap an addition's operands)
        number = ~np.isnan(expected)
        assert np.array_equal(np.signbit(table[number]), np.signbit(expected[number]))


def test_a_gather_out_of_range_is_an_index_error():
    vertices = np.zeros((4, 3))
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    with pytest.raises(IndexError, match="element 2 gathers a row out of range"):
        centroid_light(vertices, faces, np.array([0, 1, 2]), np.ones(3))
    bad = np.array([[0, 1, 7], [1, 2, 3]])
    with pytest.raises(IndexError, match="element 0"):
        centroid_light(vertices, bad, np.array([0, 1]), np.ones(2))


@md.compile(shared=("table",))
def scaled_rows(x, rows, table):
    """Rows of ``table`` (m, 3) picked by ``rows`` (n,), times x (n,): a function of its own
    (no other test calls it), so that the kernels it compiles are counted here alone."""
    return table[rows] * md.reshape(x, (-1, 1)) + 0.375


def test_one_kernel_serves_a_table_of_any_length():
    """A table read only by gathers is not part of its kernels' key: its row count is read
    when the kernel runs, so tables of other lengths (a mesh with more vertices, a scene
    with more materials) reuse the kernels compiled for the first, with the values and
    gradients of each, a negative row counted from each one's own end and a row past it
    refused. Only whether the table is small enough to have its gradient summed in the
    kernel (``codegen.PARTIAL_LIMIT``) makes another kernel."""
    rng = np.random.default_rng(11)
    x = rng.normal(size=200)
    small, large = [], []
    for m in (5, 9, 40, codegen.PARTIAL_LIMIT // 3 + 1, codegen.PARTIAL_LIMIT // 3 + 70):
        table = rng.normal(size=(m, 3))
        rows = rng.integers(-m, m, size=len(x))
        t = md.tensor(table, requires_grad=True)
        out = scaled_rows(x, rows, t)
        assert_close(out.data, table[rows] * x[:, None] + 0.375, f"value, {m} rows")
        cot = rng.normal(size=out.shape)
        (out * cot).sum().backward()
        expected = np.zeros_like(table)
        np.add.at(expected, rows, cot * x[:, None])
        assert_close(t.grad, expected, f"d/dtable, {m} rows")
        tangent = rng.normal(size=table.shape)
        forward = md.jvp(lambda v, r=rows: scaled_rows(x, r, v), (table,), (tangent,))[1]
        assert_close(forward.data, tangent[rows] * x[:, None], f"tangent, {m} rows")
        trace = next(t for t in reversed(scaled_rows._traces.values()) if t.sizes[2] == m)
        (small if m * 3 <= codegen.PARTIAL_LIMIT else large).append(trace.kernels)
        with pytest.raises(IndexError, match="gathers a row out of range"):
            scaled_rows(x[:3], np.array([0, m, 1]), table)  # one past this table's end
    # forward, vjp and jvp: once for every length; the vjp once more for the large tables
    assert len({id(k) for kernels in small + large for k, _ in kernels.values()}) == 4
    for group in (small, large):
        for mode in group[0]:
            assert all(k[mode][0] is group[0][mode][0] for k in group)
    assert small[0][("forward", ())][0] is large[0][("forward", ())][0]


# ---------------------------------------------------------------------------------------------
# Threads, the tape, the cache
# ---------------------------------------------------------------------------------------------


@md.compile(shared=("light",))
def shading(normals, points, light):
    to_light = light - points
    r2 = md.dot(to_light, to_light)
    cosine = md.maximum(md.dot(normals, md.normalize(to_light)), 0.0)
    return (cosine / r2)[:, None] * md.exp(-points * points)


def _scene(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=3) * 3


def test_the_same_bits_on_any_number_of_threads(monkeypatch):
    monkeypatch.setattr(compiler, "PARALLEL_WORK", 0)  # a batch this small on the threads too
    normals, points, light = _scene(5 * 1024 + 17)  # six chunks, the last one short
    results = []
    for threads in (1, 2, 3):
        with compiler.using_threads(threads):
            ts = [md.tensor(a, requires_grad=True) for a in (normals, points, light)]
            out = shading(*ts)
            (out * out).sum().backward()
            _, tangent = md.jvp(lambda lt: shading(normals, points, lt), (light,), (np.ones(3),))
            results.append([out.data, *(t.grad for t in ts), tangent])
    for other in results[1:]:
        for a, b in zip(results[0], other, strict=True):
            assert np.array_equal(a, b)


def test_small_kernels_run_on_one_thread(monkeypatch):
    """A kernel whose batch times its program's lines is below ``PARALLEL_WORK`` runs as
    one job (handing work to a thread costs more than it saves), a larger one on the
    threads it may use; the same bits either way (the test above)."""
    asked = []
    run = backend.Kernel.run

    def recorded(self, pointers, n, chunks, n_threads, unit=1):
        asked.append((n, n_threads))
        return run(self, pointers, n, chunks, n_threads, unit)

    monkeypatch.setattr(backend.Kernel, "run", recorded)
    lines = len(shading.trace(*_scene(10)).graph.nodes)
    assert 100 * lines < compiler.PARALLEL_WORK <= 200_000 * lines
    with compiler.using_threads(2), md.no_grad():
        shading(*_scene(100))
        shading(*_scene(200_000))
    assert asked == [(100, 1), (200_000, 2)]


def test_composes_with_the_tape_in_both_modes():
    normals, points, light = _scene(50)
    error, _, _ = md.check_grad(
        lambda p, lt: (shading(normals, p, lt) ** 2.0).sum(), points, light, argnums=(0, 1)
    )
    assert error < 1e-6  # against central differences
    value, tangent = md.jvp(
        lambda lt: md.sum(shading(normals, points, lt)), (light,), (np.array([1.0, 0, 0]),)
    )
    expected = md.jvp(
        lambda lt: md.sum(shading.function(normals, points, lt)), (light,), (np.array([1.0, 0, 0]),)
    )
    assert_close(value, expected[0], "value")
    assert_close(tangent, expected[1], "tangent")


@md.compile(shared=("light",))
def two_outputs(points, light):
    d = light - points
    return d * d, md.dot(d, d)


def _leaves(*arrays):
    return [md.tensor(a, requires_grad=True) for a in arrays]


def _gathered_case(rng):
    """A table of 20 vertices, faces, 200 hits, their weights and cotangents for
    ``centroid_light``."""
    vertices = rng.normal(size=(20, 3))
    faces = rng.integers(0, 20, size=(20, 3))
    hit, w = rng.integers(0, 20, size=200), rng.normal(size=200)
    return vertices, faces, hit, w, rng.normal(size=(200, 3))


def test_add_vjp_adds_what_backward_on_the_tape_adds():
    """``add_vjp`` (the call off the tape, its VJP added to the leaves) gives the bits
    ``backward`` through the call on the tape gives: one output and two, a gathered table,
    gradients accumulating over calls; and a batch left empty adds zeros."""
    rng = np.random.default_rng(3)
    normals, points, light = _scene(300)
    c = rng.normal(size=(300, 3))
    on_tape, direct = _leaves(points, light), _leaves(points, light)
    for _ in range(2):  # the second call adds to the first
        md.sum(shading(normals, *on_tape) * c).backward()
        shading.add_vjp(c, normals, *direct)
    for a, b in zip(on_tape, direct, strict=True):
        assert np.array_equal(a.grad, b.grad)

    c2 = rng.normal(size=300)
    on_tape, direct = _leaves(points, light), _leaves(points, light)
    squares, lengths = two_outputs(*on_tape)
    (md.sum(squares * c) + md.sum(lengths * c2)).backward()
    two_outputs.add_vjp((c, c2), *direct)
    for a, b in zip(on_tape, direct, strict=True):
        assert np.array_equal(a.grad, b.grad)

    vertices, faces, hit, w, c3 = _gathered_case(rng)
    on_tape, direct = _leaves(vertices), _leaves(vertices)
    md.sum(centroid_light(on_tape[0], faces, hit, w) * c3).backward()
    centroid_light.add_vjp(c3, direct[0], faces, hit, w)
    assert np.array_equal(on_tape[0].grad, direct[0].grad)

    lt = md.tensor(light, requires_grad=True)
    shading.add_vjp(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), lt)
    assert np.array_equal(lt.grad, np.zeros(3))


@md.compile(shared=("light",))
def self_weighted(points, light, weights):
    """Values, and an objective weighted by a constant computed from them (their cotangent
    in the program itself, as the path replay's windows compute theirs)."""
    d = light - points
    lengths = md.dot(d, d)
    scale = md.where(lengths > 1.0, weights / md.detach(lengths), 0.0)
    return d * d, lengths, scale * lengths


def test_value_and_add_vjp_is_the_call_and_add_vjp_in_one_pass(monkeypatch):
    """``value_and_add_vjp`` returns the call's values and adds ``add_vjp``'s gradient, bit
    for bit, on 1 and 2 threads, with a table gathered; without anything requiring grad it
    returns the values alone; an empty batch gives empty values and zero gradients."""
    monkeypatch.setattr(compiler, "PARALLEL_WORK", 0)  # on 2 threads below, however small
    rng = np.random.default_rng(5)
    _, points, light = _scene(3000)
    weights = rng.normal(size=3000)
    cotangents = (np.zeros((3000, 3)), np.zeros(3000), np.ones(3000))
    with md.no_grad():
        expected = [o.data for o in self_weighted(points, light, weights)]
    reference = _leaves(points, light)
    self_weighted.add_vjp(cotangents, *reference, weights)
    for threads in (1, 2):
        with compiler.using_threads(threads):
            direct = _leaves(points, light)
            values = self_weighted.value_and_add_vjp(cotangents, *direct, weights)
        for a, b in zip(values, expected, strict=True):
            assert np.array_equal(a, b)
        for a, b in zip(direct, reference, strict=True):
            assert np.array_equal(a.grad, b.grad)
    # The gradient is the tape's: the objective's, its constant held.
    on_tape = _leaves(points, light)
    md.sum(self_weighted.function(*on_tape, weights)[2]).backward()
    for a, b in zip(on_tape, reference, strict=True):
        assert_close(a.grad, b.grad, "gradient")

    vertices, faces, hit, w, c3 = _gathered_case(rng)
    on_tape, direct = _leaves(vertices), _leaves(vertices)
    md.sum(centroid_light(on_tape[0], faces, hit, w) * c3).backward()
    values = centroid_light.value_and_add_vjp(c3, direct[0], faces, hit, w)
    assert np.array_equal(on_tape[0].grad, direct[0].grad)
    with md.no_grad():
        assert np.array_equal(values, centroid_light(vertices, faces, hit, w).data)
    plain = centroid_light.value_and_add_vjp(c3, vertices, faces, hit, w)
    assert np.array_equal(plain, values)

    lt = md.tensor(light, requires_grad=True)
    empty = np.zeros((0, 3))
    values = self_weighted.value_and_add_vjp(
        (empty, np.zeros(0), np.zeros(0)), empty, lt, np.zeros(0)
    )
    assert [v.shape for v in values] == [(0, 3), (0,), (0,)]
    assert np.array_equal(lt.grad, np.zeros(3))


def test_add_vjp_refuses_what_it_cannot_add_to():
    normals, points, light = _scene(10)
    computed = md.tensor(light, requires_grad=True) * 2.0  # on the tape, not a leaf
    with pytest.raises(ValueError, match="add_vjp.*leaves only"):
        shading.add_vjp(np.ones((10, 3)), normals, points, computed)
    with pytest.raises(ValueError, match=r"add_vjp: cotangents of shapes \[\(10,\)\]"):
        shading.add_vjp(np.ones(10), normals, points, md.tensor(light, requires_grad=True))
    plain = md.tensor(light)  # nothing requires grad: nothing to add
    shading.add_vjp(np.ones((10, 3)), normals, points, plain)
    assert plain.grad is None
    # As backward in anomaly mode: a NaN gradient is refused, naming the function.
    lt = md.tensor(light, requires_grad=True)
    with md.detect_anomaly(), pytest.raises(FloatingPointError, match="compiled shading"):
        shading.add_vjp(np.full((10, 3), np.nan), normals, points, lt)
    assert lt.grad is None


def test_without_the_tape_it_returns_a_constant():
    normals, points, light = _scene(8)
    with md.no_grad():
        out = shading(md.tensor(normals, requires_grad=True), points, light)
    assert out.node is None and not out.requires_grad
    assert_close(out.data, shading.function(normals, points, light).data, "value")


def test_an_empty_batch_gives_empty_outputs_and_gradients():
    # A batch that selection left empty (no boundary sample survived, say) is a batch.
    normals, points, light = (np.zeros((0, 3)), np.zeros((0, 3)), np.ones(3))
    with md.no_grad():
        assert shading(normals, points, light).data.shape == (0, 3)
    p = md.tensor(points, requires_grad=True)
    lt = md.tensor(light, requires_grad=True)
    md.sum(shading(normals, p, lt)).backward()
    assert p.grad.shape == (0, 3) and np.array_equal(lt.grad, np.zeros(3))
    _, tangent = md.jvp(lambda x: md.sum(shading(normals, x, light)), (p,), (points,))
    assert tangent.shape == () and tangent == 0.0


def test_calls_from_several_threads_agree():
    normals, points, light = _scene(3000, seed=4)
    expected = shading.function(normals, points, light).data
    results, errors = {}, []

    def work(k):
        try:
            m = 1000 + 500 * k  # different batch sizes: different traces, the same kernel
            results[k] = shading(normals[:m], points[:m], light).data
        except Exception as error:  # noqa: BLE001 (reported below)
            errors.append(error)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(5)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for k, value in results.items():
        assert_close(value, expected[: 1000 + 500 * k], f"thread {k}")


def test_kernels_are_kept_on_disk_and_a_damaged_file_is_recompiled(tmp_path, monkeypatch):
    monkeypatch.setenv("MINIDIFF_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(backend, "_compiled", {})
    monkeypatch.setattr(backend, "_shared", None)

    @md.compile
    def fresh(x):
        return md.tanh(x * 1.25) + 0.125  # constants no other test uses: a new kernel

    x = np.linspace(-2, 2, 7)[:, None]
    expected = np.tanh(x * 1.25) + 0.125
    assert_close(fresh(x).data, expected, "first")
    files = list((tmp_path / "kernels").glob("*.o"))
    assert len(files) == 1
    monkeypatch.setattr(backend, "_compiled", {})  # as a new process would start
    monkeypatch.setattr(backend, "_shared", None)
    fresh._traces.clear()
    with monkeypatch.context() as m:  # found by the traced program: no IR written
        m.setattr(compiler.codegen, "generate", None)
        assert_close(fresh(x).data, expected, "from disk")
    files[0].write_bytes(files[0].read_bytes()[:-9] + b"corrupted")
    monkeypatch.setattr(backend, "_compiled", {})
    monkeypatch.setattr(backend, "_shared", None)
    fresh._traces.clear()
    assert_close(fresh(x).data, expected, "after damage")
    assert backend._read_object(files[0]) is not None  # rewritten whole
    # An edit of minidiff's own source (a primitive's rule, the generator) is a new key.
    monkeypatch.setattr(backend, "_source", lambda: "an edited minidiff")
    monkeypatch.setattr(backend, "_compiled", {})
    monkeypatch.setattr(backend, "_shared", None)
    fresh._traces.clear()
    assert_close(fresh(x).data, expected, "after an edit")
    assert len(list((tmp_path / "kernels").glob("*.o"))) == 2


def test_the_cache_key_names_the_rule_each_line_is_differentiated_by():
    # x * x and x ** 2 trace to the same product line, whose derivatives are two different
    # rules (d x + d x against d 2 x): the kernels' keys must tell them apart.
    from minidiff import codegen

    @md.compile
    def square(x):
        return x * x

    @md.compile
    def power(x):
        return x**2.0

    x = np.linspace(-1.0, 1.0, 5)[:, None]
    lines = [codegen.program_lines(f.trace(x)).splitlines()[-1] for f in (square, power)]
    assert lines[0].split()[:3] == lines[1].split()[:3] == ["mul", "(0,", "0)"]
    assert lines[0] != lines[1]
    for f in (square, power):
        t = md.tensor(x, requires_grad=True)
        md.sum(f(t)).backward()
        assert_close(t.grad, 2.0 * x, f"{f.__name__}'s gradient")


def test_a_scalar_form_from_outside_minidiff_keys_its_kernel_by_its_ir():
    from minidiff import codegen, trace

    def cube(x):  # an elementwise primitive written here: its rule is not minidiff's source
        y = x * x * x
        return y, (lambda d: d * 3.0 * x * x,)

    @md.compile
    def f(x):
        return trace.elementwise("cube", cube, x) if trace.is_traced((x,)) else x**3.0

    x = np.linspace(-1, 1, 5)[:, None]
    program = f.trace(x)
    assert codegen.program_lines(program) is None
    t = md.tensor(x, requires_grad=True)
    md.sum(f(t)).backward()
    assert_close(t.grad, 3.0 * x * x, "gradient")
    (traced,) = f._traces.values()
    kernel, _ = traced.kernels[("forward", ())]
    assert kernel.key == backend._key(codegen.generate(program, "forward")[0])  # by its IR


# ---------------------------------------------------------------------------------------------
# What cannot be compiled is refused at trace time, by name
# ---------------------------------------------------------------------------------------------


def _refuses(function, match, *args, shared=()):
    with pytest.raises((CompileError, TypeError, ValueError), match=match):
        md.compile(function, shared=shared)(*args)


@pytest.mark.parametrize("exponent", [1.0, 2.0, 3.0, 31.0, 32.0, 64.0])
def test_integer_constant_powers_are_products_within_ulps_of_pow(exponent):
    """``x ** n`` for a constant integer n in [1, 64] is compiled as products (no ``pow``
    call): within about n ulps of NumPy's power, with its infinities, NaN and signed zeros
    (overflow included), and the derivative n x^(n-1)."""

    @md.compile
    def power(x):
        return x**exponent

    x = np.array([0.3, -1.7, 2.5, 0.999, -0.0, 0.0, np.inf, -np.inf, np.nan, 1e200, -3e-5])
    x = np.concatenate([x, np.random.default_rng(0).uniform(-2, 2, 100)])
    assert "call double @llvm.pow" not in power.source(x)
    with np.errstate(all="ignore"):
        for fn in (power, power.function):
            t = md.tensor(x, requires_grad=True)
            y = fn(t)
            y.sum().backward()
            if fn is power:
                value, slope = y.data, t.grad
        expected, expected_slope = np.power(x, exponent), exponent * np.power(x, exponent - 1)
    assert np.array_equal(np.signbit(value), np.signbit(expected))
    for actual, wanted in ((value, expected), (slope, expected_slope)):
        assert np.array_equal(np.isnan(actual), np.isnan(wanted))
        assert np.array_equal(actual[np.isinf(wanted)], wanted[np.isinf(wanted)])
        finite = np.isfinite(wanted)
        ulps = np.abs(actual[finite] - wanted[finite]) / np.spacing(np.abs(wanted[finite]))
        assert ulps.max() <= exponent + 1


def test_a_float_compared_with_an_integer_is_compared_as_numpy_compares_them():
    """``z >= 0`` (an integer constant) and an integer array against a float: f64
    comparisons, as NumPy makes them (the generator once compared an f64 as an i64)."""

    def f(z, k):
        return (
            md.where(z >= 0, z, -2.0 * z) + md.where(k > 0.5, 1.0, 0.0) + md.where(z < k, 10.0, 0.0)
        )

    z = np.array([-1.5, -0.0, 0.0, 0.25, 2.0, np.nan])
    k = np.array([0, 1, 2, 0, 3, 1], np.int64)
    expected = f(z, k).data
    np.testing.assert_array_equal(md.compile(f)(z, k).data, expected)
    np.testing.assert_array_equal(expected, [13.0, 11.0, 11.0, 0.25, 13.0, np.nan])


def test_other_powers_call_pow():
    """A non-integer or larger constant exponent, or one known only when the kernel runs,
    stays ``pow``, NumPy's function."""
    x = np.linspace(0.1, 2.0, 7)
    assert "call double @llvm.pow" in md.compile(lambda x: x**2.5).source(x)
    assert "call double @llvm.pow" in md.compile(lambda x: x**65.0).source(x)
    assert "call double @llvm.pow" in md.compile(lambda x, b: x**b, shared=("b",)).source(
        x, np.array(3.0)
    )


def test_refusals_name_the_operation():
    x = np.ones((4, 3))
    _refuses(lambda x: md.matmul(x, x), "'matmul' is not supported", x)
    _refuses(lambda x: md.sum(x), "along the batch axis", x)
    _refuses(lambda x: md.sum(x, axis=0), "along the batch axis", x)
    _refuses(lambda x: x * 2.0 if x > 0 else x, "Python control flow", x)
    _refuses(lambda x: np.asarray(x) * 2.0, "NumPy function", x)
    _refuses(lambda x: x.data, r"\.data", x)
    _refuses(lambda x: x[0], "batch axis must be kept whole", x)
    weight = md.tensor(np.ones(3), requires_grad=True)
    _refuses(lambda x: x * weight, "pass it as an argument", x)
    _refuses(lambda x: x * np.ones((4000, 3)), "pass it as an argument", x)
    _refuses(lambda x, y: x + y, "3 elements, others 4", x, np.ones((3, 3)))
    _refuses(lambda x: x, "float32", x.astype(np.float32))
    _refuses(lambda x: x > 0, "outputs must be float", x)
    _refuses(lambda x, t: t * x, "spans the batch axis", x, np.ones((4, 3)), shared=("t",))
    _refuses(lambda x, t: md.where(t, x, x), "batched argument 't' is a 0-d", x, np.float64(1))
    with pytest.raises(ValueError, match="not parameters"):
        md.compile(lambda x: x, shared=("y",))


def test_one_trace_serves_every_batch_length_unless_the_function_reads_it():
    calls = []

    @md.compile(shared=("c",))
    def blind(x, c):
        calls.append("blind")
        return x * c

    @md.compile(shared=("c",))
    def reads(x, c):
        calls.append("reads")
        return md.broadcast_to(c, (x.shape[0], 3)) * 2.0 + x * 0.0  # n becomes a constant

    c = np.array([1.0, 2.0, 3.0])
    for n in (1, 5, 9, 5):
        x = np.arange(3.0 * n).reshape(n, 3)
        assert_close(blind(x, c).data, x * c, f"blind n={n}")
        assert_close(reads(x, c).data, np.broadcast_to(c * 2.0, (n, 3)), f"reads n={n}")
    assert calls.count("blind") == 1  # traced once, for n = 1
    assert calls.count("reads") == 3  # once per n it saw


FORK_SCRIPT = """
import multiprocessing
import numpy as np
import minidiff as md
from minidiff import compiler

compiler.PARALLEL_WORK = 0  # this small batch on the pool's threads too

@md.compile(shared=("light",))
def shading(normals, points, light):
    return md.maximum(md.dot(normals, md.normalize(light - points)), 0.0)[:, None] * points

def on_two_threads(*args):
    with compiler.using_threads(2):
        return shading(*args).data

rng = np.random.default_rng(0)
args = (rng.normal(size=(3 * 1024, 3)), rng.normal(size=(3 * 1024, 3)), np.ones(3))
expected = on_two_threads(*args)  # the parent's thread pool now exists
with multiprocessing.get_context("fork").Pool(1) as pool:
    got = pool.apply(on_two_threads, args)
assert np.array_equal(got, expected)
print("ok")
"""


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")
def test_a_forked_child_gets_its_own_thread_pool():
    """A child forked after the thread pool started still runs compiled functions (its copy
    of the pool has no threads). In a new process that imports minidiff only: forking a
    process with other libraries' threads (JAX's, in the test session) is unsafe itself."""
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-c", FORK_SCRIPT], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0 and "ok" in result.stdout, result.stderr[-2000:]


def test_tuple_arguments_are_taken_apart_and_their_gradients_returned():
    """A tuple (or list, or named tuple) argument: each array in it a slot of its own
    (shared here, by the argument's name), the rest static; a changed static part or a
    longer tuple is a new signature."""

    def lit(points, lights, scale):
        total = 0.0 * points[:, 0]
        for position, strength in lights:
            offset = position - points
            total = total + strength / md.dot(offset, offset)
        return total * scale[0]

    compiled = md.compile(lit, shared=("lights",))
    rng = np.random.default_rng(7)
    points = rng.normal(size=(50, 3))
    lights = [(md.tensor(rng.normal(size=3) + 3.0, requires_grad=True),
               md.tensor(2.0 + k, requires_grad=True)) for k in range(2)]  # fmt: skip
    grads = []
    for function in (compiled, lit):
        for position, strength in lights:
            position.grad = strength.grad = None
        md.sum(function(points, lights, (1.5,)) ** 2).backward()
        grads.append([t.grad.copy() for light in lights for t in light])
    for g_compiled, g_tape in zip(*grads, strict=True):
        assert_close(g_compiled, g_tape, "a light's gradient")
    before = len(compiled._traces)
    compiled(points, lights, (2.5,))
    compiled(points, lights[:1], (1.5,))
    assert len(compiled._traces) == before + 2


def test_tape_only_runs_the_plain_function_in_this_thread_only():
    normals, points, light = _scene(200, seed=5)
    calls = []
    plain = shading.function

    def counted(normals, points, light):
        calls.append(threading.get_ident())
        return plain(normals, points, light)

    wrapped = md.compile(counted, shared=("light",))
    results = {}
    with md.tape_only():
        results["here"] = wrapped(normals, points, light).data
        other = threading.Thread(
            target=lambda: results.setdefault("there", wrapped(normals, points, light).data)
        )
        other.start()
        other.join()
    # Here the plain function ran on arrays; there it ran once, to be traced, then the kernel.
    assert calls[0] == threading.get_ident() and len(calls) == 2
    assert calls[1] != calls[0]
    assert_close(results["there"], results["here"], "the kernel against the plain function")
    assert wrapped(normals, points, light).data is not None and len(calls) == 2  # kernel now


def test_a_kernel_s_pointers_are_the_arrays_data_whatever_ctypes_can_view():
    """``compiler._address`` reads an array's address through a ctypes view of its buffer,
    which ctypes refuses for read-only and empty arrays: every kind a call passes gets its
    data's own address, and a compiled call on read-only inputs computes what it does on
    writable ones."""
    read_only = np.arange(6.0).reshape(2, 3)
    read_only.setflags(write=False)
    arrays = [np.zeros((4, 3)), read_only, np.zeros((0, 3)), np.zeros(5, np.int64),
              np.zeros(5, np.uint8), np.zeros(()), np.zeros((3, 4))[:, 1:].copy()]  # fmt: skip
    for array in arrays:
        assert compiler._address(array) == array.__array_interface__["data"][0]
    pointers = compiler._addresses(arrays)
    assert [p for p in pointers] == [a.__array_interface__["data"][0] or None for a in arrays]

    @md.compile
    def scaled(x, y):
        return x * 2.0 + y

    x = np.arange(12.0).reshape(4, 3)
    y = np.ones((4, 3))
    frozen_x, frozen_y = x.copy(), y.copy()
    frozen_x.setflags(write=False)
    frozen_y.setflags(write=False)
    assert np.array_equal(scaled(frozen_x, frozen_y).data, scaled(x, y).data)
    assert np.array_equal(scaled(x, y).data, x * 2.0 + y)
