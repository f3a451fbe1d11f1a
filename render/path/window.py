"""Path replay's windows, compiled: one traced kernel per depth for every parameter.

``render.path.replay`` differentiates a batch of paths one depth at a time: window k
recomputes vertex k from the scene's parameters (and the vertex before it, which its
direction back depends on), and gives what it adds to the path, C_k, and the factor of the
segment after it, F_k. On the tape (``replay._Window``) that is ``transport``'s code, object
by object and row subset by row subset, every step a NumPy pass over the paths, run in
one thread.

Here the same window is one function of *one path*, written with the readable formulas the
tape runs (``surface_at``, ``light_contribution``, ``brdf``) and compiled by
``minidiff.compile``: forward and VJP generated from the primitives' own rules, in parallel
over the paths, so that every parameter (vertices, transforms, light positions, the camera,
materials, lights, the environment) gets its gradient at the speed of the others. What a
row subset did on the tape is a selection here: a path without next-event estimation, or
that does not go on, has its terms multiplied by a zero weight, and the values those terms
divide by are made safe first (``md.where`` twice), so that neither value nor gradient
sees a NaN.

The scene is read as tables shared by every path (``Tables``): all meshes' vertices, shading
normals and faces concatenated (a primitive id is a row of the face table), and per object
its material. They are built once per replay on the tape from the parameters, then handed
to the windows as leaves whose gradients add up window after window; one last ``backward``
carries them to the parameters (``Tables.carry``).

It applies (``applies``) to meshes without textures, no mirror bounce among the batch's
paths, float64 and lights whose shading compiles; otherwise the windows take the tape.
``tests/render/path/test_window.py`` ties the two together for every kind of parameter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.path.tracer import CAMERA, MIRROR, PathBatch, PathSampler, Vertices
from render.scene.camera import ray_directions
from render.scene.materials import Material
from render.scene.scene import Mesh, Scene
from render.shade.lighting import Appearance, _nonzero, brdf, light_contribution
from render.shade.surface import column, surface_at, toward_ray, vertex_normals
from render.trace.primitives import primitive_ranges

#: The material's parameters a path reads, as per-object tables.
MATERIAL_FIELDS = ("albedo", "specular", "shininess", "emission")


def applies(world: Scene, sampler: PathSampler, batch: PathBatch) -> bool:
    """Whether the compiled windows replay ``batch``: every object a mesh without textures,
    no ``MIRROR`` vertex or bounce among its paths, float64 parameters and lights whose
    shading compiles (``Light.compiled_shading``)."""
    if not all(isinstance(obj, Mesh) and not obj.material.textures for obj in world.objects):
        return False
    if not all(light.compiled_shading for light in world.lights):
        return False
    if any(t.dtype != np.float64 for t in world.parameters()):
        return False
    return not any(np.any(v.form == MIRROR) or np.any(v.next == MIRROR) for v in batch.vertices)


@dataclass
class Tables:
    """The scene as every path reads it: ``vertices`` (V, 3) and vertex ``normals`` (V, 3)
    of all meshes (a flat mesh's rows are a constant, never used), ``faces`` (F, 3) int64
    with global vertex ids (row p is primitive p), ``smooth`` (O,) bool per object, the
    materials' ``albedo``, ``specular``, ``emission`` (O, 3) and ``shininess`` (O,), the
    lights' parameters and kinds, the environment and the camera frame. The tensors are
    leaves; ``built`` holds what they were computed from on the tape."""

    vertices: md.Tensor
    normals: md.Tensor
    faces: np.ndarray
    smooth: np.ndarray
    materials: tuple
    lights: tuple
    kinds: tuple
    background: md.Tensor
    frame: tuple
    glossy: bool
    built: list

    @classmethod
    def of(cls, world: Scene, frame: tuple) -> Tables:
        """The tables of ``world`` (the replay's leaf copies) and its camera ``frame``."""
        meshes = [obj for obj, _, _ in primitive_ranges(world)]  # the leaf copies, in order
        offsets = np.cumsum([0] + [len(m.vertices.data) for m in meshes])
        faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=False)])
        normals = []
        for m in meshes:
            if not m.smooth:  # any unit vector: where() picks the geometric normal
                normals.append(md.tensor(np.tile([0.0, 0.0, 1.0], (len(m.vertices.data), 1))))
            elif m.normals is not None:
                normals.append(m.normals)
            else:
                normals.append(vertex_normals(m.vertices, m.faces))
        columns = {
            name: md.stack([md.broadcast_to(getattr(m.material, name), (3,)) for m in meshes])
            for name in ("albedo", "specular", "emission")
        }
        columns["shininess"] = md.stack([m.material.shininess for m in meshes])
        built, leaves = [], {}

        def leaf(t):
            """A leaf copy of ``t``; ``t`` kept for ``carry`` if it is differentiated."""
            copy = md.tensor(t.data, requires_grad=t.requires_grad)
            if t.requires_grad:
                built.append((t, copy))
            return copy

        for name, t in columns.items():
            leaves[name] = leaf(t)
        glossy = any(_nonzero(m.material.specular) for m in meshes)
        return cls(
            vertices=leaf(md.concatenate([m.vertices for m in meshes])),
            normals=leaf(md.concatenate(normals)),
            faces=np.ascontiguousarray(faces, np.int64),
            smooth=np.array([bool(m.smooth) for m in meshes]),
            materials=tuple(leaves[name] for name in MATERIAL_FIELDS),
            lights=tuple(tuple(light.named_parameters().values()) for light in world.lights),
            kinds=tuple((type(light), tuple(light.named_parameters())) for light in world.lights),
            background=world.background,
            frame=tuple(frame),
            glossy=glossy,
            built=built,
        )

    def carry(self) -> None:
        """Backward, through the tape the tables were built on, of what the windows put
        into their leaves' ``grad``."""
        terms = [md.sum(t * copy.grad) for t, copy in self.built if copy.grad is not None]
        if terms:
            total = terms[0]
            for term in terms[1:]:
                total = total + term
            total.backward()


class CompiledWindow:
    """``replay._Window``'s C_k and F_k for the batch's paths ``rows`` (sorted, reaching
    vertex k), by one compiled call (``_window``): ``parts``/``rows_of`` C_k (m, 3) and its
    rows, ``factors``/``factor_rows`` F_k of the paths that go on and their rows."""

    def __init__(self, tables: Tables, batch: PathBatch, vertices: list[Vertices], k: int,
                 rows: np.ndarray, sampler: PathSampler):  # fmt: skip
        record = _at(vertices[k], rows)
        n = len(rows)
        following = vertices[k + 1] if k + 1 < len(vertices) else None
        going = np.zeros(n, bool)
        if following is not None:
            going = np.isin(rows, following.rows, assume_unique=True)
        nxt = _at(following, rows[going]) if going.any() else None
        scale = 1.0 / (record.next_pdf * record.survive)  # constants of the continuation
        escape = record.escape & (record.next != 0)

        previous = coords = None
        if k == 0 or vertices[k - 1].form[0] == CAMERA:
            coords = np.ascontiguousarray(batch.coords[rows], np.float64)
        case = "camera" if k == 0 else "after_camera" if coords is not None else "after_area"
        if k > 0:
            before = _at(vertices[k - 1], rows)
            previous = (before.prim, _object(sampler, before.prim), before.local)
        # Paths without NEE (or that do not go on) read a harmless point: their weight is 0.
        has_nee = record.nee_weight > 0
        nee_prim = np.where(has_nee, record.nee_prim, record.prim)
        nee_local = np.where(has_nee[:, None], record.nee_local, 1.0 / 3.0)
        next_prim, next_local = record.prim.copy(), np.full((n, 3), 1.0 / 3.0)
        if nxt is not None:
            next_prim[going], next_local[going] = nxt.prim, nxt.local
        lit = None
        if len(tables.lights):
            lit = np.ascontiguousarray(record.lit.T, np.float64)
        batched = (
            coords,
            previous,
            (record.prim, _object(sampler, record.prim), record.local),
            lit,
            record.emit_weight.astype(np.float64),
            (nee_prim, _object(sampler, nee_prim), nee_local, record.nee_weight.astype(np.float64)),
            (np.where(escape, scale, 0.0), record.escape_dir.astype(np.float64)),
            (
                next_prim,
                _object(sampler, next_prim),
                next_local,
                np.where(going, scale, 0.0),
                going,
            ),
        )
        added, factor = _window(
            *_contiguous(batched), tables.frame, tables.vertices, tables.normals, tables.faces,
            tables.smooth, tables.materials, tables.lights, tables.background,
            (case, tables.kinds, tables.glossy),
        )  # fmt: skip
        self.parts, self.rows_of = [added], [rows]
        self.factors, self.factor_rows = [], []
        if going.any():
            self.factors.append(factor[np.flatnonzero(going)])
            self.factor_rows.append(rows[going])

    def added(self, n_paths: int) -> np.ndarray:
        """(N, 3) the values of C_k, zero for the paths not in the window."""
        here = np.zeros((n_paths, 3))
        here[self.rows_of[0]] = self.parts[0].data
        return here

    def factor(self) -> tuple[md.Tensor, np.ndarray]:
        """F_k (m, 3) of the paths that go on, and their rows (m,)."""
        return self.factors[0], self.factor_rows[0]


def _at(record: Vertices, rows: np.ndarray) -> Vertices:
    """The record's fields of the batch's paths ``rows`` (all among ``record.rows``)."""
    at = np.searchsorted(record.rows, rows)
    return Vertices(
        rows, record.prim[at], record.local[at], record.form[at], record.emit_weight[at],
        record.nee_prim[at], record.nee_local[at], record.nee_weight[at], record.lit[:, at],
        record.next[at], record.next_pdf[at], record.survive[at], record.escape[at],
        record.escape_dir[at],
    )  # fmt: skip


def _object(sampler: PathSampler, prims: np.ndarray) -> np.ndarray:
    """(k,) the index of the object owning each primitive id."""
    return np.searchsorted(sampler.first, prims, side="right") - 1


def _contiguous(value):
    """Arrays (in nested tuples) as contiguous float64 / int64 / bool arrays."""
    if isinstance(value, tuple):
        return tuple(_contiguous(v) for v in value)
    if value is None:
        return None
    kind = {"f": np.float64, "i": np.int64, "u": np.int64, "b": np.bool_}[value.dtype.kind]
    return np.ascontiguousarray(value, kind)


@dataclass
class _Vertex:
    """Path vertices inside the compiled window: points, unit geometric and shading
    normals (k, 3), the area element's ``stretch`` (k,), the direction back ``wo`` (k, 3)
    and the object each lies on (k,) int64."""

    points: object
    geometric: object
    shading: object
    stretch: object
    wo: object
    obj: object


def _surface(mesh, smooth, prim, obj, local=None, origins=None, directions=None) -> _Vertex:
    """Points on the world's triangles ``prim``: at coordinates ``local`` (an ``AREA``
    vertex, ``stretch`` its area element) or where rays meet them (stretch 1); ``wo`` left
    to the caller. ``surface_at`` on the concatenated mesh, whose shading normal is then
    the geometric one on flat objects."""
    found = surface_at(mesh, prim, origins, directions, local=local, divide=True)
    shading = md.where(column(smooth[obj]), found.shading, found.geometric)
    stretch = found.stretch if local is not None else 1.0
    return _Vertex(found.points, found.geometric, shading, stretch, None, obj)


@md.compile(shared=("frame", "vertices", "normals", "faces", "smooth", "materials", "lights",
                    "background"))  # fmt: skip
def _window(coords, previous, here, lit, emit_weight, nee, escape, going, frame, vertices,
            normals, faces, smooth, materials, lights, background, form):  # fmt: skip
    """One window of one path: (C_k (n, 3), F_k (n, 3)), ``transport._at_vertex``'s terms
    for a vertex reached without a mirror. Batched (n paths): coords (n, 2) the camera ray's
    image-plane point (when vertex k or k - 1 is the camera's), previous (prim, object,
    local) of vertex k - 1 when it is an ``AREA`` one, here (prim, object, local) of vertex
    k, lit (n, L), emit_weight (n,), nee (prim, object, local, weight), escape (scale, unit
    direction) and going (prim, object, local, scale, flag) of the next vertex. Shared:
    the tables (``Tables``). Static ``form``: (which vertex the camera's ray meets:
    "camera" (vertex k), "after_camera" (k - 1) or "after_area" (none), the lights'
    classes and parameter names, whether any material is glossy)."""
    case, kinds, glossy = form
    albedo, specular, shininess, emission = materials
    zero = md.tensor(0.0)
    look_of = Material.holding(texture=None, specular_texture=None, ambient_texture=None)
    mesh = Mesh.holding(vertices=vertices, faces=faces, normals=normals, uvs=None, smooth=True,
                        material=look_of, transform=None)  # fmt: skip
    scene_lights = [
        cls.holding(**dict(zip(names, params, strict=True)))
        for (cls, names), params in zip(kinds, lights, strict=True)
    ]
    prim, obj, local = here
    if case == "camera":  # vertex k where the camera's ray meets it
        directions = ray_directions(frame, coords)
        v = _surface(mesh, smooth, prim, obj, origins=frame[3], directions=directions)
        v.wo = -md.normalize(directions)
    else:
        v = _surface(mesh, smooth, prim, obj, local=local)
        if case == "after_camera":
            directions = ray_directions(frame, coords)
            back = _surface(mesh, smooth, previous[0], previous[1], origins=frame[3],
                            directions=directions).points  # fmt: skip
        else:
            back = _surface(mesh, smooth, previous[0], previous[1], local=previous[2]).points
        v.wo = md.normalize(back - v.points)

    side = toward_ray(v.geometric, -v.wo)  # two-sided: the shading normal faces the viewer
    ns = v.shading * side
    look = Appearance(albedo[obj], specular[obj] if glossy else zero, zero, shininess[obj], None)
    diffuse = look.albedo * (1.0 / np.pi)
    view = v.wo if glossy else None

    # Emission seen here (from its front only), MIS-weighted; the point and directional
    # lights.
    added = emission[obj] * column(md.maximum(side[:, 0], 0.0) * emit_weight)
    for j, light in enumerate(scene_lights):
        added = added + light_contribution(v.points, ns, -v.wo, look, light, lit[:, j])

    def toward(point_of, valid):
        """The unit direction from the vertex to another point, with its squared distance
        (1 where ``valid`` is false, so nothing divides by zero there)."""
        to = point_of - v.points
        d2 = md.where(valid, md.dot(to, to), 1.0)
        return to / column(md.sqrt(d2)), d2

    def bounce_weight(wi, scale):
        """f cos / (p q) for unit directions wi (``scale``: 1 / (p q), 0 where unused)."""
        cos = md.maximum(md.dot(ns, wi), 0.0)
        return brdf(ns, view, wi, diffuse, look) * column(cos * scale)

    # Next-event estimation on the area lights: a point on an emitting triangle.
    nee_prim, nee_obj, nee_local, nee_weight = nee
    light = _surface(mesh, smooth, nee_prim, nee_obj, local=nee_local)
    wi, d2 = toward(light.points, nee_weight > 0.0)
    cos_x = md.maximum(md.dot(ns, wi), 0.0)
    cos_z = md.abs(md.dot(light.geometric, wi))
    f = brdf(ns, view, wi, diffuse, look)
    scale = cos_x * cos_z / d2 * (light.stretch * 0.5) * nee_weight  # area: half the stretch
    added = added + f * column(scale) * emission[nee_obj]

    # Paths that leave the scene see the environment.
    escape_scale, escape_dir = escape
    added = added + bounce_weight(escape_dir, escape_scale) * background

    # The factor of the segment to the next vertex, with the change of measure to its area.
    next_prim, next_obj, next_local, next_scale, goes = going
    nxt = _surface(mesh, smooth, next_prim, next_obj, local=next_local)
    wi, d2 = toward(nxt.points, goes)
    geometry = md.where(goes, md.abs(md.dot(nxt.geometric, wi)) / d2 * nxt.stretch, 1.0)
    factor = bounce_weight(wi, next_scale) * column(geometry / md.detach(geometry))
    return added, factor
