"""Path replay backpropagation: a batch's gradient one depth at a time, its tape flat in depth.

``render.path.gradient.transport.path_radiance`` puts every depth of every path on one tape,
so the memory of a batch's ``backward`` grows with ``max_depth``. Where the batch's paths
compile (``tables.compiles``) their gradient is one compiled function of the whole path,
whose reverse sweep runs path by path inside the kernel (``window.path_terms``): no tape
at all. Otherwise (a mirror bounce, a texture) path replay (Vicini et al. 2021, "Path
Replay Backpropagation"; Mitsuba 3's ``prb.py``) gives the same gradient with one depth on
the tape at a time. A path's radiance is, componentwise in RGB,

    L = sum_k beta_k C_k,    beta_0 = 1,  beta_{k+1} = beta_k F_k,

with C_k what vertex k adds (emission, NEE, the lights, the environment after a last
bounce) and F_k the factor of the segment to vertex k + 1 (``transport._at_vertex``
computes both). Its derivative is

    dL = sum_k beta_k dC_k + sum_k beta_k dF_k Lrem_k,

Lrem_k = (L - sum_{j<=k} beta_j C_j) / beta_{k+1} being the radiance that arrives at vertex
k from vertex k + 1 on. So *window* k computes only what C_k and F_k depend on, with beta_k
and Lrem_k as plain constants (from the windows' own values and the path's total L), and the
gradient of sum(weights * (beta_k C_k + beta_k F_k Lrem_k)) is taken before the next window
is built (``objective_weights`` computes those constants from the window's values), by
``backward`` on the window's own tape.

**What a window rebuilds.** Vertex k needs its predecessor: an ``AREA`` vertex's direction
back (``wo``) needs the previous point, a ``MIRROR`` vertex is where the ray reflected at the
previous vertex meets its primitive, so it needs all of the previous vertex. A window
therefore starts at an *anchor* that stands on its own and rebuilds the vertices from there:
a ``CAMERA`` vertex (its ray is the camera's), or an ``AREA`` vertex followed by an ``AREA``
vertex (its wo is not needed, only its point). Without mirrors the anchor is k - 1; a run of
mirrors reaches back to its start. A vertex is never evaluated from a wrong origin: an
anchor's wo, left zero, is never read.

**The placement.** The placed world (``render.scene.placement``) and the camera's frame are
computed once per batch on the caller's tape, which one ``backward`` frees. The windows
therefore read leaf copies of the differentiated tensors (``substituted``), whose gradients
add up window after window; one last ``backward`` of sum_t t * grad(copy of t) carries them
through the placement to the scene's parameters.

**Where the throughput becomes zero.** Where F_k is zero in a channel (an albedo,
specular or reflectance channel that is 0, a cosine clamped to 0) while beta_k is not, L
says nothing of Lrem_k in that channel, yet beta_k dF_k Lrem_k need not be zero (the
derivative of that albedo channel). The later windows then gather Lrem_k as well (plain
(N, 3) arrays, at most one such depth per channel: beta is zero after it) and window k is
built again for those paths at the end (``_Pending``), so the gradient stays exact (Mitsuba
3's ``prb.py`` takes the inverse of a zero BSDF value as 0, leaving that term out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.path.gradient import window
from render.path.gradient.transport import Vertex, _at_vertex, vertex_on_tape, viewer_side
from render.path.sample.records import PathBatch, Vertices
from render.path.sample.tables import Tables, compiles
from render.path.sample.tracer import AREA, CAMERA, MIRROR, PathSampler
from render.scene.camera import ray_directions
from render.scene.substitute import substituted
from render.shade.surface import column


def backpropagate_paths(
    world, frame, sampler: PathSampler, batch: PathBatch, radiance: np.ndarray, weights
) -> None:
    """Add to ``grad`` of every tensor that requires grad what
    ``md.sum(path_radiance(world, frame, sampler, batch) * weights).backward()`` would, one
    depth of the paths at a time (module docstring). ``world``: the placed scene the batch
    was sampled in; ``frame``: its camera frame (``camera_frame``); ``radiance`` (N, 3): each
    path's radiance (the plain value of ``path_radiance``, e.g. ``kernel.sample_paths``');
    ``weights`` (N, 3) plain: d loss / d radiance. Memory: one depth's tape (a window) and
    a few (N, 3) arrays, whatever ``max_depth``."""
    with md.enable_grad():  # its own tapes, recorded even inside a caller's no_grad()
        _backpropagate(world, frame, sampler, batch, radiance, weights)


def radiance_of(
    world, frame, sampler: PathSampler, batch: PathBatch, tables: Tables | None = None
) -> np.ndarray:
    """(N, 3) plain: the radiance each path of ``batch`` carries, the value of
    ``transport.path_radiance`` (L = sum_k beta_k C_k, the module docstring): compiled and
    parallel over the paths where they compile (``window.radiance``), else summed window by
    window on the tape without recording. For the constants of the
    boundary terms (``render.path.boundary.secondary``, ``render.path.boundary.primary``).
    ``tables``: ``plain_tables(world, frame)`` if the caller has them (a caller asking
    about many batches of one world makes them once)."""
    with md.no_grad():
        if compiles(world):
            return window.radiance(tables or Tables.of(world, frame), batch)
        paths = _Paths.of(world, frame, sampler, batch)
        n_paths = len(batch.paths)
        total = np.zeros((n_paths, 3), paths.dtype)
        total[batch.missed] = world.background.data  # camera rays that see the environment
        beta = np.ones((n_paths, 3), paths.dtype)
        anchor = np.zeros(n_paths, np.int64)
        for k, record in enumerate(paths.vertices):
            if k > 0:
                anchor[record.rows] = _anchors(paths.vertices, k, anchor[record.rows])
            here = _Window(paths, k, record.rows, anchor[record.rows])
            total += beta * here.added(n_paths)
            if here.factors:
                factor, rows = here.factor()
                beta[rows] *= factor.data
    return total


def _backpropagate(world, frame, sampler, batch, radiance, weights) -> None:
    """``backpropagate_paths``, with the tape on."""
    dtype = np.result_type(*[t.dtype for t in world.parameters()])
    weights = np.asarray(weights, dtype)
    radiance = np.asarray(radiance, dtype)
    originals = _differentiated(world, frame)
    if not originals:
        return
    copies = {id(t): md.tensor(t.data, requires_grad=True) for t in originals}
    window_world = substituted(world, copies, {}, copies=True)
    window_frame = tuple(copies.get(id(t), t) for t in frame)

    missed = np.flatnonzero(batch.missed)
    if len(missed) and window_world.background.requires_grad:  # camera rays seeing the sky
        seen = md.sum(md.broadcast_to(window_world.background, (len(missed), 3)) * weights[missed])
        seen.backward()
    if compiles(window_world):  # compiled: each path's reverse sweep in a kernel
        tables = Tables.of(window_world, window_frame)
        window.backpropagate(tables, batch, weights)
        _backward(tables.carried())  # the tables' gradients, through their tape
    else:
        paths = _Paths.of(window_world, window_frame, sampler, batch)
        vertices = paths.vertices
        sums = _Sums.of(weights, radiance)
        anchor = np.zeros(len(batch.paths), np.int64)  # where window k starts, per path
        for k, record in enumerate(vertices):
            if k > 0:
                anchor[record.rows] = _anchors(vertices, k, anchor[record.rows])
            here_window = _Window(paths, k, record.rows, anchor[record.rows])
            here_window.replay(sums, k, anchor)
            del here_window  # this window's tape, before the next is built
        sums.pending.close(paths, weights)

    carried = [md.sum(t * copies[id(t)].grad) for t in originals if copies[id(t)].grad is not None]
    _backward(carried)


@dataclass
class _Sums:
    """What the replay carries from window to window, per path (N, 3) plain: ``weights``
    d loss / d L, ``radiance`` L, ``beta`` the throughput before the path's current vertex,
    ``gathered`` sum_{j<=k} beta_j C_j so far, and the ``pending`` channels."""

    weights: np.ndarray
    radiance: np.ndarray
    beta: np.ndarray
    gathered: np.ndarray
    pending: _Pending

    @classmethod
    def of(cls, weights: np.ndarray, radiance: np.ndarray) -> _Sums:
        n, dtype = len(weights), weights.dtype
        beta, gathered = np.ones((n, 3), dtype), np.zeros((n, 3), dtype)
        return cls(weights, radiance, beta, gathered, _Pending.none(n, dtype))

    def gather(self, rows: np.ndarray, added: np.ndarray) -> None:
        """Add what the paths ``rows`` (m,) add at their current vertex, C_k (m, 3)."""
        self.gathered[rows] = np.take(self.gathered, rows, axis=0) + (
            np.take(self.beta, rows, axis=0) * added
        )
        self.pending.gather(rows, added)

    def running(self, rows: np.ndarray) -> list[np.ndarray]:
        """(weights, beta, radiance, gathered) of the paths ``rows``, each (m, 3)."""
        arrays = (self.weights, self.beta, self.radiance, self.gathered)
        return [np.take(a, rows, axis=0) for a in arrays]

    def go_on(self, k: int, rows: np.ndarray, anchor: np.ndarray, factor: np.ndarray) -> None:
        """The paths ``rows`` (m,) go on from vertex k with factors F_k ``factor`` (m, 3):
        their throughput moves on, and their pending channels."""
        before = np.take(self.beta, rows, axis=0)  # beta_k (np.take: see Vertices.take)
        after = before * factor  # beta_{k+1}
        self.pending.carry(rows, factor)
        self.pending.open(k, rows, anchor, before, after)
        self.beta[rows] = after


@dataclass
class _Pending:
    """The paths' channels whose factor F_e is zero where their throughput beta_e is not
    (a zero albedo or reflectance channel, a cosine clamped to zero): L says nothing of the
    radiance Lrem_e arriving at vertex e there, so the windows after e gather it (with
    gamma, the throughput from vertex e + 1 on) and ``close`` adds beta_e dF_e Lrem_e
    once it is known, by building window e again for those paths. Each array (N, 3):
    ``depth`` e (-1: none; at most one per channel, as beta is zero after it), ``anchor``
    window e's anchor, ``beta`` beta_e, ``gamma``, ``arriving`` Lrem_e so far."""

    depth: np.ndarray
    anchor: np.ndarray
    beta: np.ndarray
    gamma: np.ndarray
    arriving: np.ndarray
    open_any: bool = False  # whether any channel is pending (else gather and carry wait)

    @classmethod
    def none(cls, n: int, dtype) -> _Pending:
        depth = np.full((n, 3), -1, np.int64)
        zeros = np.zeros((n, 3), dtype)
        return cls(depth, depth.copy(), zeros, zeros.copy(), zeros.copy())

    def gather(self, rows: np.ndarray, added: np.ndarray) -> None:
        """Add what the paths ``rows`` add at their current vertices (C_k (m, 3)) to the
        radiance arriving."""
        if self.open_any:
            pending = np.take(self.depth, rows, axis=0) >= 0
            gamma = np.take(self.gamma, rows, axis=0)
            self.arriving[rows] += np.where(pending, gamma * added, 0.0)

    def carry(self, rows: np.ndarray, factor: np.ndarray) -> None:
        """The paths ``rows`` go on with factors F_k ``factor`` (m, 3). (Only pending
        channels read gamma; ``open`` sets a channel's to 1.)"""
        if self.open_any:
            self.gamma[rows] *= factor

    def open(self, k: int, rows, anchor, beta, after) -> None:
        """Channels of the paths ``rows`` (m,) that go on with throughput ``after``
        (beta_{k+1}, (m, 3)) zero from ``beta`` (beta_k) non-zero."""
        new = (after == 0) & (beta != 0)
        if not new.any():
            return
        self.open_any = True
        at, channel = np.nonzero(new)
        row = rows[at]
        self.depth[row, channel], self.anchor[row, channel] = k, anchor[at]
        self.beta[row, channel], self.gamma[row, channel] = beta[at, channel], 1.0
        self.arriving[row, channel] = 0.0

    def close(self, paths: _Paths, weights: np.ndarray) -> None:
        """Backward, for each depth e with pending channels, of
        sum(weights beta_e F_e Lrem_e) over those channels (window e built again)."""
        for e in np.unique(self.depth[self.depth >= 0]):
            mine = self.depth == e  # (N, 3)
            rows = np.flatnonzero(mine.any(axis=1))
            anchor = self.anchor[rows, np.argmax(mine[rows], axis=1)]
            # Every one of ``rows`` goes on.
            again = _Window(paths, int(e), rows, anchor)
            _, going = again.factor()
            again.backward(None, np.where(mine, weights * self.beta * self.arriving, 0.0)[going])


def _backward(terms: list[md.Tensor]) -> None:
    """Backward of the sum of scalar tensors (nothing if none requires grad)."""
    terms = [t for t in terms if t.requires_grad]
    if terms:
        total = terms[0]
        for term in terms[1:]:
            total = total + term
        total.backward()


def _differentiated(world, frame) -> list[md.Tensor]:
    """The tensors the windows read that require grad: the placed world's and the frame's,
    each once."""
    seen, out = set(), []
    for t in [*world.parameters(), *frame]:
        if isinstance(t, md.Tensor) and t.requires_grad and id(t) not in seen:
            seen.add(id(t))
            out.append(t)
    return out


def _anchors(vertices: list[Vertices], k: int, before: np.ndarray) -> np.ndarray:
    """(n,) the anchor of window k for the paths reaching vertex k, given their anchor of
    window k - 1 ``before`` (n,): k - 1 where vertex k - 1 stands on its own for vertex k
    (a ``CAMERA`` vertex, or an ``AREA`` one when vertex k is ``AREA`` too), else the
    anchor of window k - 1."""
    rows = vertices[k].rows
    previous = vertices[k - 1]
    form_before = previous.form[np.searchsorted(previous.rows, rows)]
    form = vertices[k].form
    alone = (form_before == CAMERA) | ((form_before == AREA) & (form == AREA))
    return np.where(alone, k - 1, before)


@dataclass
class _Paths:
    """What the windows read: the world and camera frame of the leaf copies, the sampler,
    the batch and its vertices (the depths some path reaches), the dtype."""

    world: object
    frame: tuple
    sampler: PathSampler
    batch: PathBatch
    vertices: list[Vertices]
    dtype: np.dtype

    @classmethod
    def of(cls, world, frame, sampler: PathSampler, batch: PathBatch) -> _Paths:
        """The windows' view of ``batch`` in ``world`` (its dtype, the depths some path
        reaches)."""
        dtype = np.result_type(*[t.dtype for t in world.parameters()])
        vertices = [v for v in batch.vertices if len(v.rows)]
        return cls(world, frame, sampler, batch, vertices, dtype)


def plain_tables(world, frame) -> Tables:
    """The tables ``radiance_of`` reads for ``world`` and its camera ``frame``, off the
    tape."""
    with md.no_grad():
        return Tables.of(world, frame)


class _Window:
    """Window k of the paths ``rows`` (sorted rows of the batch reaching vertex k) on its
    own tape, their vertices rebuilt from their ``anchors`` (m,): ``parts``/``rows_of``,
    C_k's pieces (each (m', 3) with the paths it belongs to), and ``factors`` /
    ``factor_rows``, F_k (m', 3) of the paths that go on, by anchor."""

    def __init__(self, paths: _Paths, k: int, rows: np.ndarray, anchors: np.ndarray):
        self.world, self.frame, self.sampler = paths.world, paths.frame, paths.sampler
        self.rows = rows
        self.batch, self.vertices, self.dtype, self.k = paths.batch, paths.vertices, paths.dtype, k
        self.parts: list[md.Tensor] = []
        self.rows_of: list[np.ndarray] = []
        self.factors: list[md.Tensor] = []
        self.factor_rows: list[np.ndarray] = []
        following = self.vertices[k + 1] if k + 1 < len(self.vertices) else None
        for start in np.unique(anchors):
            self._add(rows[anchors == start], int(start), following)

    def added(self, n_paths: int) -> np.ndarray:
        """(N, 3) the values of C_k, zero for the paths not in the window."""
        here = np.zeros((n_paths, 3), self.dtype)
        for part, rows in zip(self.parts, self.rows_of, strict=True):
            np.add.at(here, rows, part.data)
        return here

    def _add(self, group: np.ndarray, start: int, following: Vertices | None) -> None:
        """C_k and F_k of the paths ``group`` (sorted rows of the batch), whose vertices are
        rebuilt from vertex ``start`` on."""
        vertex = self._standalone(group, start)
        for j in range(start + 1, self.k + 1):
            vertex = self._next(vertex, self._record(j, group))
        record = self._record(self.k, group)
        sub = None
        if following is not None:
            going = np.flatnonzero(np.isin(following.rows, group, assume_unique=True))
            sub = following.take(going) if len(going) else None
        factor, _ = _at_vertex(self.world, self.sampler, record, sub, vertex, None, self.parts,
                               self.rows_of, self.dtype)  # fmt: skip
        if factor is not None:
            self.factors.append(factor)
            self.factor_rows.append(sub.rows)

    def replay(self, sums: _Sums, k: int, anchor: np.ndarray) -> None:
        """Window k's step of the replay: its values added to the running ``sums``, the
        constants of its objective computed from them, that objective's ``backward``, and
        the paths that go on moved on. ``anchor`` (N,): each path's window anchor."""
        rows = self.rows
        added = np.zeros((len(rows), 3), self.dtype)  # C_k, its parts added up
        for part, part_rows in zip(self.parts, self.rows_of, strict=True):
            np.add.at(added, np.searchsorted(rows, part_rows), part.data)
        factor = np.zeros_like(added)  # F_k where the path goes on
        going = np.zeros(len(rows), bool)
        if self.factors:
            factor_of, going_rows = self.factor()
            going_at = np.searchsorted(rows, going_rows)
            factor[going_at], going[going_at] = factor_of.data, True
        with md.no_grad():  # (as tensors: a Python number then takes their dtype)
            values = [md.tensor(a) for a in (added, factor)]
            running = [md.tensor(a) for a in sums.running(rows)]
            weights = objective_weights(*values, going, *running)
        coefficients, scale = (w.data for w in weights)
        sums.gather(rows, added)
        if self.factors:
            sums.go_on(k, going_rows, anchor[going_rows], factor_of.data)
            scale = scale[going_at]
        else:
            scale = None
        parts = [np.take(coefficients, np.searchsorted(rows, r), axis=0) for r in self.rows_of]
        self.backward(parts, scale)

    def backward(self, coefficients: list[np.ndarray] | None, scale: np.ndarray | None) -> None:
        """``backward`` of sum(coefficients * C_k) + sum(scale * F_k) on this window's tape
        (``coefficients``: one array per part of C_k, or None; ``scale`` for the paths
        that go on, in ``factor``'s order, or None)."""
        objective = []
        if coefficients is not None:
            objective += [md.sum(p * c) for p, c in zip(self.parts, coefficients, strict=True)]
        if scale is not None:
            objective.append(md.sum(self.factor()[0] * scale))
        _backward(objective)

    def factor(self) -> tuple[md.Tensor, np.ndarray]:
        """F_k (m, 3) of the paths that go on, and their rows (m,)."""
        if len(self.factors) == 1:
            return self.factors[0], self.factor_rows[0]
        return md.concatenate(self.factors), np.concatenate(self.factor_rows)

    def _record(self, j: int, group: np.ndarray) -> Vertices:
        """Vertex j's record of the paths ``group``."""
        return self.vertices[j].of_rows(group)

    def _standalone(self, group: np.ndarray, start: int) -> Vertex:
        """Vertex ``start`` of the paths ``group``, built from nothing before it: the camera
        vertex from the camera's rays, an ``AREA`` vertex from its place on its primitive
        (wo zero: not needed)."""
        record = self._record(start, group)
        if start > 0:
            return vertex_on_tape(self.world, self.sampler, record.prim, record.local,
                                  record.form, None, None)  # fmt: skip
        coords = self.batch.coords[group].astype(self.dtype)
        directions = ray_directions(self.frame, coords)
        origins = md.broadcast_to(self.frame[3], (len(group), 3))
        return vertex_on_tape(self.world, self.sampler, record.prim, record.local, record.form,
                              origins, directions)  # fmt: skip

    def _next(self, v: Vertex, record: Vertices) -> Vertex:
        """The vertices that follow ``v`` (the same paths), as ``_at_vertex`` finds them:
        ``AREA`` ones at their place, ``MIRROR`` ones along the ray reflected at ``v``."""
        mirror = record.form == MIRROR
        directions = None
        if mirror.any():  # the reflected ray, as in _at_vertex (shading normal facing wo)
            ns = v.shading * viewer_side(v).astype(self.dtype)
            directions = 2.0 * column(md.dot(v.wo, ns)) * ns - v.wo
        return vertex_on_tape(self.world, self.sampler, record.prim, record.local, record.form,
                              v.points, directions)  # fmt: skip


def objective_weights(added, factor, going, weights, beta, radiance, gathered) -> tuple:
    """The constants of window k's objective, sum(coefficients * C_k) + sum(scale * F_k)
    (``replay``'s module docstring), from its values (each (n, 3) but ``going`` (n,) bool:
    which paths go on): coefficients weights beta_k, and scale weights beta_k Lrem_k /
    beta_{k+1}, 0 where beta_{k+1} is or the path stops. ``added`` C_k, ``factor`` F_k,
    ``weights`` d loss / d L, ``beta`` beta_k, ``radiance`` L, ``gathered``
    sum_{j<k} beta_j C_j. Plain values, as tensors (``_Window.replay``)."""
    coefficients = weights * beta
    after = beta * factor  # beta_{k+1}
    left = radiance - (gathered + beta * added)  # the radiance still to come, Lrem_k beta_{k+1}
    safe = md.where(after != 0.0, after, 1.0)
    arriving = md.where(after != 0.0, left / safe, 0.0)  # Lrem_k
    return coefficients, md.where(column(going), coefficients * arriving, 0.0)
