"""A batch of paths as data: per depth, the paths that reach it (``Vertices``, in a
``PathBatch``), and the same as dense records, every path's vertex k in row k of one set
of arrays (``Records``).

``PathBatch.vertices`` lists, per depth, only the paths that reach it. The compiled
gradient (``render.path.gradient.window``) reads every depth of every path in one pass
over the paths, so it wants the other layout: per depth k, one row per path of the batch,
zero where the path has ended. The path kernel
(``render.path.twin.kernel``) writes this layout as it traces (``sample_paths``); a batch
from the reference sampler is laid out here (``Records.of``).

Fields, depth first (a depth's paths are contiguous rows, each depth's table contiguous):
``ints`` (D, N, I_FIELDS) int64, ``floats`` (D, N, F_FIELDS) float64 and ``lit`` (D, N,
max(L, 1)) bool (which of the L point and directional lights reach the vertex). The
columns below name them; ``COUNT`` (depth 0 only) is the number of vertices of the path,
``COORD`` (depth 0 only) its camera ray's image-plane point.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

#: How a vertex was reached (``Vertices.form``) and how a path goes on (``Vertices.next``).
CAMERA, AREA, MIRROR = 0, 1, 2
STOP = 0


@dataclass
class Vertices:
    """The n paths of a batch that reach their k-th vertex, and what they do there.

    rows (n,) int64: which paths of the batch (indices into ``PathBatch.paths``);
    prim (n,) int64 the primitive hit; local (n, 3) the point's coordinates on it ((u, v, 0)
    barycentrics, or the unit direction from a sphere's centre); form (n,) int8 ``CAMERA``,
    ``AREA`` or ``MIRROR``; emit_weight (n,): the MIS weight of the emission seen here.
    NEE: nee_prim (n,) the emissive primitive picked (-1: none), nee_local (n, 3) the point
    on it, nee_weight (n,): visible * MIS weight / P(primitive) (0 if occluded or behind);
    lit (L, n) bool: which point and directional lights reach the vertex.
    Continuation: next (n,) int8 ``STOP``, ``AREA`` (diffuse or glossy) or ``MIRROR``;
    next_pdf (n,): the direction's density per steradian (``AREA``) or the lobe's
    probability (``MIRROR``); survive (n,): Russian roulette's survival probability (1
    before ``rr_depth``); escape (n,) bool: the ray left the scene; escape_dir (n, 3) its
    direction (unit)."""

    rows: np.ndarray
    prim: np.ndarray
    local: np.ndarray
    form: np.ndarray
    emit_weight: np.ndarray
    nee_prim: np.ndarray
    nee_local: np.ndarray
    nee_weight: np.ndarray
    lit: np.ndarray
    next: np.ndarray
    next_pdf: np.ndarray
    survive: np.ndarray
    escape: np.ndarray
    escape_dir: np.ndarray

    @classmethod
    def none(cls, n_lights: int) -> Vertices:
        """The record of no path."""
        i, f = np.zeros(0, np.int64), np.zeros(0)
        return cls(i, i, np.zeros((0, 3)), np.zeros(0, np.int8), f, i, np.zeros((0, 3)), f,
                   np.zeros((n_lights, 0), bool), np.zeros(0, np.int8), f, f,
                   np.zeros(0, bool), np.zeros((0, 3)))  # fmt: skip

    def take(self, at: np.ndarray) -> Vertices:
        """The paths at positions ``at`` of this record (the lights' visibility is (L, n)).
        (``np.take`` along an axis: for rows of an (n, 3) array, several times faster than
        indexing with ``at``, for the same values.)"""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return Vertices(**{name: np.take(value, at, axis=1 if name == "lit" else 0)
                           for name, value in fields.items()})  # fmt: skip

    def of_rows(self, rows: np.ndarray) -> Vertices:
        """The record of the batch's paths ``rows`` (sorted, all among ``self.rows``)."""
        if len(rows) == len(self.rows):  # then all of them
            return self
        return self.take(np.searchsorted(self.rows, rows))


class PathBatch:
    """A batch of N paths: their ids ``paths`` (N,) (``pixel * spp + sample``), the
    image-plane coordinates of their camera rays ``coords`` (N, 2), which camera rays miss
    everything ``missed`` (N,) bool (they see the environment), and their ``vertices``,
    one ``Vertices`` per depth. Given dense ``records`` instead (the path kernel writes
    that layout as it traces), the vertices are laid out from them when first asked for:
    the compiled gradient reads the records alone."""

    def __init__(self, paths: np.ndarray, coords: np.ndarray, missed: np.ndarray,
                 vertices: list[Vertices] | None = None,
                 records: Records | None = None) -> None:  # fmt: skip
        if vertices is None and records is None:
            raise ValueError("PathBatch: give its vertices, its records or both")
        self.paths, self.coords, self.missed = paths, coords, missed
        self._vertices, self.records = vertices, records

    @property
    def vertices(self) -> list[Vertices]:
        """Per depth some path reaches, the paths that reach it and their fields."""
        if self._vertices is None:  # (two threads may both lay them out: the same lists)
            self._vertices = self.records.vertices()
        return self._vertices

    def meets_mirror(self) -> bool:
        """Whether a path of the batch has a ``MIRROR`` vertex or bounce."""
        if self.records is not None:
            forms = self.records.ints[:, :, [FORM, NEXT]]
            return bool(np.any(forms == MIRROR))
        return any(np.any(v.form == MIRROR) or np.any(v.next == MIRROR) for v in self.vertices)


#: Integer columns: the primitive, the vertex's form, NEE's primitive (-1: none), the
#: continuation (``STOP``, ``AREA``, ``MIRROR``), whether the ray left the scene, the count.
PRIM, FORM, NEE_PRIM, NEXT, ESCAPE, COUNT = range(6)
I_FIELDS = 6
#: Float columns (first column of each): the point's coordinates on its primitive (3), the
#: emission's MIS weight, NEE's point (3) and weight, the continuation's density and
#: Russian roulette's survival probability, the escape direction (3), the camera ray's
#: image-plane point (2).
LOCAL, EMIT, NEE_LOCAL, NEE_WEIGHT, NEXT_PDF, SURVIVE = 0, 3, 4, 7, 8, 9
ESCAPE_DIR, COORD = 10, 13
F_FIELDS = 15
#: About how many bytes a vertex's records take (one light's visibility).
BYTES_PER_VERTEX = 8 * (I_FIELDS + F_FIELDS) + 1


@dataclass
class Records:
    """Dense records of a batch's N paths over D depths (module docstring) and the number
    of lights ``n_lights`` whose visibility ``lit`` holds."""

    ints: np.ndarray
    floats: np.ndarray
    lit: np.ndarray
    n_lights: int

    @classmethod
    def empty(cls, depth: int, n: int, n_lights: int, zeroed: bool = True) -> Records:
        """Records of ``n`` paths over ``depth`` depths: zeroed, or with ``zeroed`` False
        uninitialised, for a writer that fills every row itself (the kernel)."""
        make = np.zeros if zeroed else np.empty
        ints = make((depth, n, I_FIELDS), np.int64)
        floats = make((depth, n, F_FIELDS))
        return cls(ints, floats, make((depth, n, max(n_lights, 1)), np.bool_), n_lights)

    @classmethod
    def of(cls, batch: PathBatch, n_lights: int) -> Records:
        """The records of ``batch`` (its ``records`` if it has them), one depth per
        ``Vertices`` that some path reaches."""
        if batch.records is not None:
            return batch.records
        vertices = [v for v in batch.vertices if len(v.rows)]
        n = len(batch.paths)
        out = cls.empty(len(vertices), n, n_lights)
        for k, v in enumerate(vertices):
            rows = v.rows
            # Each depth's fields as whole rows, scattered once (a column at a time was
            # several times slower).
            out.ints[k, rows, :COUNT] = np.stack([v.prim, v.form, v.nee_prim, v.next, v.escape], 1)
            out.floats[k, rows, :COORD] = np.concatenate(
                [v.local, v.emit_weight[:, None], v.nee_local, v.nee_weight[:, None],
                 v.next_pdf[:, None], v.survive[:, None], v.escape_dir], axis=1
            )  # fmt: skip
            out.lit[k, rows, :n_lights] = v.lit.T
            out.ints[0, rows, COUNT] = k + 1  # the paths reaching depth k reach k - 1
        if len(vertices):
            out.floats[0, :, COORD : COORD + 2] = batch.coords
        return out

    @property
    def count(self) -> np.ndarray:
        """(N,) each path's number of vertices (0: its camera ray missed)."""
        return self.ints[0, :, COUNT]

    def vertices(self) -> list[Vertices]:
        """``PathBatch.vertices``: per depth, the paths that reach it and their fields
        (views of the records where every path does, else copies of its rows)."""
        count, out = self.count, []
        for k in range(len(self.ints)):
            rows = np.flatnonzero(count > k)
            if len(rows) == 0:
                break
            if len(rows) == len(count):  # every path: views, not copies
                i, f, lit = self.ints[k], self.floats[k], self.lit[k]
            else:
                arrays = (self.ints, self.floats, self.lit)
                i, f, lit = (np.take(r[k], rows, axis=0) for r in arrays)
            out.append(
                Vertices(
                    rows,
                    i[:, PRIM],
                    f[:, LOCAL : LOCAL + 3],
                    i[:, FORM].astype(np.int8),
                    f[:, EMIT],
                    i[:, NEE_PRIM],
                    f[:, NEE_LOCAL : NEE_LOCAL + 3],
                    f[:, NEE_WEIGHT],
                    lit[:, : self.n_lights].T.copy(),
                    i[:, NEXT].astype(np.int8),
                    f[:, NEXT_PDF],
                    f[:, SURVIVE],
                    i[:, ESCAPE].astype(bool),
                    f[:, ESCAPE_DIR : ESCAPE_DIR + 3],
                )  # fmt: skip
            )
        return out
