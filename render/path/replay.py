"""Path replay backpropagation: a batch's gradient one depth at a time, memory flat in depth.

``render.path.transport.path_radiance`` puts every depth of every path on one tape, so the
memory of a batch's ``backward`` grows with ``max_depth``. Path replay (Vicini et al. 2021,
"Path Replay Backpropagation"; Mitsuba 3's ``prb.py``) gives the same gradient with one
depth on the tape at a time. A path's radiance is, componentwise in RGB,

    L = sum_k beta_k C_k,    beta_0 = 1,  beta_{k+1} = beta_k F_k,

with C_k what vertex k adds (emission, NEE, the lights, the environment after a last
bounce) and F_k the factor of the segment to vertex k + 1 (``transport._at_vertex``
computes both). Its derivative is

    dL = sum_k beta_k dC_k + sum_k beta_k dF_k Lrem_k,

Lrem_k = (L - sum_{j<=k} beta_j C_j) / beta_{k+1} being the radiance that arrives at vertex
k from vertex k + 1 on. So *window* k puts on a fresh tape only what C_k and F_k depend on,
with beta_k and Lrem_k as plain constants (from the windows' own values and the path's
total L), and a ``backward`` of sum(weights * (beta_k C_k + beta_k F_k Lrem_k)) takes its
share of the gradient before the next window is built.

**What a window rebuilds.** Vertex k needs its predecessor: an ``AREA`` vertex's direction
back (``wo``) needs the previous point, a ``MIRROR`` vertex is where the ray reflected at the
previous vertex meets its primitive, so it needs all of the previous vertex. A window
therefore starts at an *anchor* that stands on its own and rebuilds the vertices from there:
a ``CAMERA`` vertex (its ray is the camera's), or an ``AREA`` vertex followed by an ``AREA``
vertex (its wo is not needed, only its point). Without mirrors the anchor is k - 1; a run of
mirrors reaches back to its start. A vertex is never evaluated from a wrong origin: an
anchor's wo is left zero and is only ever used where it does not matter.

**The placement.** The placed world (``render.scene.placement``) and the camera's frame are
computed once per batch on the caller's tape, which one ``backward`` frees. The windows
therefore read leaf copies of the differentiated tensors (``substituted``), whose gradients
add up window after window; one last ``backward`` of sum_t t * grad(copy of t) carries them
through the placement to the scene's parameters.

**A limit of the algebra.** Where F_k is exactly zero in a channel (an albedo or reflectance
channel that is 0, or a cosine clamped to 0) while the path goes on, Lrem_k in that channel
cannot be recovered from L and is taken as 0, as in Mitsuba 3: the term beta_k dF_k Lrem_k
is then missing from that channel's gradient (the taped integrator has it).
"""

from __future__ import annotations

import dataclasses

import numpy as np

import minidiff as md
from render.path.tracer import AREA, CAMERA, MIRROR, PathBatch, PathSampler, Vertices
from render.path.transport import Vertex, _at_vertex, vertex_on_tape
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
    ``weights`` (N, 3) plain: d loss / d radiance."""
    dtype = np.result_type(*[t.dtype for t in world.parameters()])
    weights = np.asarray(weights, dtype)
    radiance = np.asarray(radiance, dtype)
    originals = _differentiated(world, frame)
    if not originals:
        return
    copies = {id(t): md.tensor(t.data, requires_grad=True) for t in originals}
    window_world = substituted(world, copies, {})
    window_frame = tuple(copies.get(id(t), t) for t in frame)

    missed = np.flatnonzero(batch.missed)
    if len(missed) and window_world.background.requires_grad:  # camera rays seeing the sky
        seen = md.sum(md.broadcast_to(window_world.background, (len(missed), 3)) * weights[missed])
        seen.backward()
    n_paths = len(batch.paths)
    beta = np.ones((n_paths, 3), dtype)  # the throughput before each path's current vertex
    gathered = np.zeros((n_paths, 3), dtype)  # sum_{j<=k} beta_j C_j, plain
    anchor = np.zeros(n_paths, np.int64)  # where window k starts, per path
    vertices = [v for v in batch.vertices if len(v.rows)]
    for k, record in enumerate(vertices):
        if k > 0:
            anchor[record.rows] = _anchors(vertices, k, anchor[record.rows])
        following = vertices[k + 1] if k + 1 < len(vertices) else None
        window = _Window(window_world, window_frame, sampler, batch, vertices, k, dtype)
        for start in np.unique(anchor[record.rows]):
            group = record.rows[anchor[record.rows] == start]
            window.add(group, start, following)
        # The constants of this window's objective, from its values.
        for part, rows in zip(window.parts, window.rows_of, strict=True):
            np.add.at(gathered, rows, beta[rows] * part.data)
        objective = [
            md.sum(part * (weights[rows] * beta[rows]))
            for part, rows in zip(window.parts, window.rows_of, strict=True)
        ]
        if window.factors:
            factor, rows = window.factor()
            after = beta[rows] * factor.data  # beta_{k+1}
            arriving = np.divide(radiance[rows] - gathered[rows], after,
                                 out=np.zeros_like(after), where=after != 0)  # fmt: skip
            objective.append(md.sum(factor * (weights[rows] * beta[rows] * arriving)))
            beta[rows] = after
        total = _summed(objective)
        if total is not None and total.requires_grad:
            total.backward()
        del window, objective, total  # this window's tape, before the next is built

    carried = [md.sum(t * copies[id(t)].grad) for t in originals if copies[id(t)].grad is not None]
    if carried:
        _summed(carried).backward()


def _differentiated(world, frame) -> list[md.Tensor]:
    """The tensors the windows read that require grad: the placed world's and the frame's,
    each once."""
    seen, out = set(), []
    for t in [*world.parameters(), *frame]:
        if isinstance(t, md.Tensor) and t.requires_grad and id(t) not in seen:
            seen.add(id(t))
            out.append(t)
    return out


def _summed(terms: list[md.Tensor]) -> md.Tensor | None:
    """The sum of scalar tensors (None for none)."""
    total = None
    for term in terms:
        total = term if total is None else total + term
    return total


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


def _take(record: Vertices, at: np.ndarray) -> Vertices:
    """The record's paths at positions ``at`` (the lights' visibility is (L, n))."""
    fields = {f.name: getattr(record, f.name) for f in dataclasses.fields(record)}
    return Vertices(**{name: (value[:, at] if name == "lit" else value[at])
                       for name, value in fields.items()})  # fmt: skip


class _Window:
    """Window k on its own tape: ``parts``/``rows_of``, C_k's pieces (each (m, 3) with the
    paths it belongs to), and ``factors``/``factor_rows``, F_k of the paths that go on."""

    def __init__(self, world, frame, sampler, batch, vertices, k, dtype):
        self.world, self.frame, self.sampler, self.batch = world, frame, sampler, batch
        self.vertices, self.k, self.dtype = vertices, k, dtype
        self.parts: list[md.Tensor] = []
        self.rows_of: list[np.ndarray] = []
        self.factors: list[md.Tensor] = []
        self.factor_rows: list[np.ndarray] = []

    def add(self, group: np.ndarray, start: int, following: Vertices | None) -> None:
        """C_k and F_k of the paths ``group`` (sorted rows of the batch), whose vertices are
        rebuilt from vertex ``start`` on."""
        vertex = self._standalone(group, start)
        for j in range(start + 1, self.k + 1):
            vertex = self._next(vertex, self._record(j, group))
        record = self._record(self.k, group)
        sub = None
        if following is not None:
            going = np.flatnonzero(np.isin(following.rows, group, assume_unique=True))
            sub = _take(following, going) if len(going) else None
        factor, _ = _at_vertex(self.world, self.sampler, record, sub, vertex, None, self.parts,
                               self.rows_of, self.dtype)  # fmt: skip
        if factor is not None:
            self.factors.append(factor)
            self.factor_rows.append(sub.rows)

    def factor(self) -> tuple[md.Tensor, np.ndarray]:
        """F_k (m, 3) of the paths that go on, and their rows (m,)."""
        if len(self.factors) == 1:
            return self.factors[0], self.factor_rows[0]
        return md.concatenate(self.factors), np.concatenate(self.factor_rows)

    def _record(self, j: int, group: np.ndarray) -> Vertices:
        """Vertex j's record of the paths ``group``."""
        record = self.vertices[j]
        return _take(record, np.searchsorted(record.rows, group))

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
            side = np.where(md.kernels.dot_last(v.geometric.data, v.wo.data) < 0, -1.0, 1.0)
            ns = v.shading * side.astype(self.dtype)[:, None]
            directions = 2.0 * column(md.dot(v.wo, ns)) * ns - v.wo
        return vertex_on_tape(self.world, self.sampler, record.prim, record.local, record.form,
                              v.points, directions)  # fmt: skip
