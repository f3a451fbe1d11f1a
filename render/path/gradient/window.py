"""Path replay's windows, compiled: one traced kernel per depth for every parameter.

``render.path.gradient.replay`` differentiates a batch of paths one depth at a time: window k
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

The scene is read as tables shared by every path (``render.path.sample.tables.Tables``): all
meshes' vertices, shading normals and faces concatenated (a primitive id is a row of the
face table), and per object its material. They are built once per replay on the tape from
the parameters, then handed to the windows as leaves whose gradients add up window after
window; one last ``backward`` carries them to the parameters (``Tables.carried``).

It applies (``applies``) to meshes without textures, no mirror bounce among the batch's
paths, float64 and lights whose shading compiles; otherwise the windows take the tape.
``tests/render/path/test_window.py`` ties the two together for every kind of parameter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.path.sample.tables import Tables, far_side_of, role_of
from render.path.sample.tracer import CAMERA, MIRROR, PathBatch, Vertices
from render.scene.camera import ray_directions
from render.scene.materials import Material
from render.scene.scene import Mesh, Scene, Sphere
from render.shade.compiled import held_lights
from render.shade.lighting import Appearance, brdf, light_contribution
from render.shade.surface import column, surface_at, toward_ray


def applies(world: Scene, batch: PathBatch) -> bool:
    """Whether the compiled windows replay ``batch``: no object with a texture, no
    ``MIRROR`` vertex or bounce among its paths, float64 parameters and lights whose
    shading compiles (``Light.compiled_shading``)."""
    if any(obj.material.textures for obj in world.objects):
        return False
    if not all(light.compiled_shading for light in world.lights):
        return False
    if any(t.dtype != np.float64 for t in world.parameters()):
        return False
    return not any(np.any(v.form == MIRROR) or np.any(v.next == MIRROR) for v in batch.vertices)


class CompiledWindow:
    """Window k of the batch's paths ``rows`` (sorted, reaching vertex k), compiled: the
    arguments of ``window_terms`` gathered from the records once. ``replay`` is the
    replay's step (values and VJP in one compiled pass); ``values``, ``added``,
    ``factor`` and ``backward`` are ``replay._Window``'s interface (C_k (m, 3), F_k of the
    paths that go on, and their VJP), for ``replay.radiance_of`` and the pending
    channels."""

    def __init__(self, tables: Tables, batch: PathBatch, vertices: list[Vertices], k: int,
                 rows: np.ndarray):  # fmt: skip
        record = vertices[k].of_rows(rows)
        n = len(rows)
        size = len(batch.paths)
        going, next_at = np.zeros(n, bool), None
        if k + 1 < len(vertices):
            following = vertices[k + 1]
            next_at = _positions(following.rows, rows, size)
            going = next_at >= 0
        scale = 1.0 / (record.next_pdf * record.survive)  # constants of the continuation
        escape = record.escape & (record.next != 0)

        back = coords = None
        if k == 0 or vertices[k - 1].form[0] == CAMERA:
            coords = np.take(batch.coords, rows, axis=0)
        case = "camera" if k == 0 else "after_camera" if coords is not None else "after_area"
        if k > 0:
            before = vertices[k - 1]
            at = _positions(before.rows, rows, size)  # all there: rows reached vertex k
            back = (before.prim[at], np.take(before.local, at, axis=0))
        # Paths without NEE (or that do not go on) read a harmless point, their weight 0: a
        # point of the primitive here (``window_terms`` puts it in the middle).
        has_nee = record.nee_weight > 0
        nee_prim = np.where(has_nee, record.nee_prim, record.prim)
        next_prim, next_local = record.prim, record.local
        if going.any():  # gathered from the next record (row 0 for the others: unused)
            at = np.where(going, next_at, 0)
            next_prim = np.where(going, np.take(following.prim, at), record.prim)
            next_local = following.local[at]
        lit = None
        if len(tables.lights):
            lit = record.lit.T.astype(np.float64)
        batched = (
            coords,
            back,
            (record.prim, record.local),
            lit,
            record.emit_weight,
            (nee_prim, record.nee_local, record.nee_weight),
            (np.where(escape, scale, 0.0), record.escape_dir),
            (next_prim, next_local, np.where(going, scale, 0.0), going),
        )
        self._arguments = (
            *_dense(batched), tables.frame, tables.vertices, tables.normals, tables.faces,
            tables.centers, tables.radii, tables.smooth, tables.materials, tables.lights,
            tables.background, tables.primitives, (case, tables.kinds, tables.glossy),
        )  # fmt: skip
        self.rows, self._going = rows, np.flatnonzero(going)
        self._values: tuple[np.ndarray, np.ndarray] | None = None
        self._factor: np.ndarray | None = None  # F_k of the paths that go on, once taken

    def replay(self, sums, k: int, anchor: np.ndarray) -> None:
        """Window k's step of the replay (``replay._Sums``): its values and the VJP of its
        objective in one compiled pass (``_replayed``: the objective's constants computed
        from the values inside it, as ``replay._Window.replay`` computes them outside),
        then the paths' running sums moved on. ``sums``: the replay's running values
        (``replay._Sums``); ``anchor`` (N,): each path's window anchor (kept for its
        pending channels)."""
        rows, n = self.rows, len(self.rows)
        running = sums.running(rows)
        cotangents = (np.zeros((n, 3)), np.zeros((n, 3)), np.ones(n))  # the objective's
        added, factor, _ = _replayed.value_and_add_vjp(cotangents, *self._arguments, *running)
        sums.gather(rows, added)
        if len(self._going):
            going = rows[self._going]
            sums.go_on(k, going, anchor[going], factor[self._going])

    def backward(self, coefficients: list[np.ndarray] | None, scale: np.ndarray | None) -> None:
        """Add to the tables' leaves' ``grad`` the gradient of sum(coefficients * C_k) +
        sum(scale * F_k) (``coefficients``: one (m, 3) array for the window's paths, or
        None; ``scale`` (m', 3) for the paths that go on, or None): one compiled VJP
        (``md.compile``'s ``add_vjp``), what ``backward`` of that sum on the tape gives."""
        n = len(self.rows)
        of_added = np.zeros((n, 3)) if coefficients is None else coefficients[0]
        of_factor = np.zeros((n, 3))
        if scale is not None:
            of_factor[self._going] = scale
        _window.add_vjp((of_added, of_factor), *self._arguments)

    def values(self) -> tuple[np.ndarray, np.ndarray]:
        """(C_k (m, 3), F_k (m, 3)) of the window's paths (F_k of the paths that do not go
        on: unused), by the compiled forward, off the tape (computed once)."""
        if self._values is None:
            with md.no_grad():
                added, factor = _window(*self._arguments)
            self._values = (added.data, factor.data)
        return self._values

    @property
    def rows_of(self) -> list[np.ndarray]:
        """The rows of C_k's one part (``replay._Window``'s interface)."""
        return [self.rows]

    @property
    def factors(self) -> list[np.ndarray]:
        """F_k of the paths that go on, as one part (none if no path goes on)."""
        if not len(self._going):
            return []
        if self._factor is None:
            self._factor = np.take(self.values()[1], self._going, axis=0)
        return [self._factor]

    def added(self, n_paths: int) -> np.ndarray:
        """(N, 3) the values of C_k, zero for the paths not in the window."""
        here = np.zeros((n_paths, 3))
        here[self.rows] = self.values()[0]
        return here

    def factor(self) -> tuple[md.Tensor, np.ndarray]:
        """F_k (m, 3) of the paths that go on, and their rows (m,)."""
        return md.tensor(self.factors[0]), self.rows[self._going]


def _dense(arguments):
    """``arguments`` (arrays in nested tuples) with every float array C-contiguous: the
    records' fields are strided views, which both compiled calls of a window (the values,
    then the VJP) would otherwise copy each."""
    if isinstance(arguments, tuple):
        return tuple(_dense(a) for a in arguments)
    if isinstance(arguments, np.ndarray) and arguments.dtype.kind == "f":
        return np.ascontiguousarray(arguments)
    return arguments


def _positions(among: np.ndarray, rows: np.ndarray, size: int) -> np.ndarray:
    """(n,) where each of the batch's paths ``rows`` stands in ``among`` (both sorted row
    numbers below ``size``), -1 where it is not there."""
    where = np.full(size, -1, np.int64)
    where[among] = np.arange(len(among))
    return where[rows]


@dataclass
class _Vertex:
    """Path vertices inside the compiled window: points, unit geometric and shading
    normals (k, 3), the area element's ``stretch`` (k,) (1 for points found by rays), the
    direction back ``wo`` (k, 3) (set by the caller) and the object each lies on (k,)."""

    points: object
    geometric: object
    shading: object
    stretch: object
    wo: object
    obj: object


def held_world(vertices, normals, faces, centers, radii, smooth) -> tuple:
    """What ``surface`` reads, from the tables' (traced) arrays: (all meshes as one
    ``Mesh`` (smooth; ``smooth`` (O,) says which objects are), smooth, the spheres'
    centres and radii)."""
    look = Material.holding(texture=None, specular_texture=None, ambient_texture=None)
    mesh = Mesh.holding(vertices=vertices, faces=faces, normals=normals, uvs=None, smooth=True,
                        material=look, transform=None)  # fmt: skip
    return mesh, smooth, centers, radii


def surface(world, role, origins=None, directions=None, far=None) -> _Vertex:
    """Points on the primitives of ``role`` (``Tables.role``): at its coordinates ``local``
    (an ``AREA`` vertex) or where the rays meet them (``far``: which rays meet a sphere's far
    side). ``surface_at`` on the concatenated mesh and on the spheres, each point taking its
    own primitive's; a flat mesh's shading normal is its geometric one."""
    mesh, smooth, centers, radii = world
    face, sphere, on_sphere, obj, local = role
    if origins is not None:
        local = None
    found = []
    if face is not None:
        tri = surface_at(mesh, face, origins, directions, local=local, divide=True)
        tri.shading = md.where(column(smooth[obj]), tri.shading, tri.geometric)
        found.append(tri)
    if sphere is not None:
        ball = Sphere.holding(center=centers[sphere], radius=radii[sphere], material=mesh.material)
        found.append(surface_at(ball, sphere, origins, directions, local=local, far_root=far))
    if len(found) == 1:
        only = found[0]
        points, geometric, shading, stretch = (
            only.points,
            only.geometric,
            only.shading,
            only.stretch,
        )
    else:
        tri, ball = found
        pick = column(on_sphere)
        points = md.where(pick, ball.points, tri.points)
        geometric = md.where(pick, ball.geometric, tri.geometric)
        shading = md.where(pick, ball.shading, tri.shading)
        stretch = None if local is None else md.where(on_sphere, ball.stretch, tri.stretch)
    return _Vertex(points, geometric, shading, 1.0 if local is None else stretch, None, obj)


_SHARED = ("frame", "vertices", "normals", "faces", "centers", "radii", "smooth", "materials",
           "lights", "background", "primitives")  # fmt: skip


def window_terms(
    coords,
    previous,
    here,
    lit,
    emit_weight,
    nee,
    escape,
    going,
    frame,
    vertices,
    normals,
    faces,
    centers,
    radii,
    smooth,
    materials,
    lights,
    background,
    primitives,
    form,
):
    """One window of one path: (C_k (n, 3), F_k (n, 3)), ``transport._at_vertex``'s terms
    for a vertex reached without a mirror. Batched (n paths): coords (n, 2) the camera ray's
    image-plane point (when vertex k or k - 1 is the camera's); previous, here: vertices k
    - 1 (when an ``AREA`` one) and k, each (primitive (n,), barycentric coordinates (n,
    3)); lit (n, L); emit_weight (n,); nee (primitive, coordinates, weight) the point on an
    area light; escape (scale, unit direction); going (primitive, coordinates, scale, flag)
    the next vertex. Shared: the tables (``Tables``; ``primitives``: what a point on each
    primitive reads, ``role_of``). Static ``form``: (which vertex the camera's ray meets:
    "camera" (vertex k), "after_camera" (k - 1) or "after_area" (none), the lights'
    classes and parameter names, whether any material is glossy)."""
    case, kinds, glossy = form
    albedo, specular, shininess, emission = materials
    zero = md.tensor(0.0)
    world = held_world(vertices, normals, faces, centers, radii, smooth)
    scene_lights = held_lights(kinds, lights)
    if case == "camera":  # vertex k where the camera's ray meets it
        directions = ray_directions(frame, coords)
        far = far_side_of(primitives, here[0])
        v = surface(world, role_of(primitives, *here), frame[3], directions, far)
        v.wo = -md.normalize(directions)
    else:
        v = surface(world, role_of(primitives, *here))
        back_role = role_of(primitives, *previous)
        if case == "after_camera":
            far = far_side_of(primitives, previous[0])
            back = surface(world, back_role, frame[3], ray_directions(frame, coords), far).points
        else:
            back = surface(world, back_role).points
        v.wo = md.normalize(back - v.points)
    obj = v.obj

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

    # Next-event estimation on the area lights: a point on an emitting primitive, whose
    # area is half the stretch on a triangle, 4 pi times it on a sphere.
    nee_prim, nee_local, nee_weight = nee
    nee_role = role_of(primitives, nee_prim, _middle_unless(nee_weight > 0.0, nee_local))
    light = surface(world, nee_role)
    wi, d2 = toward(light.points, nee_weight > 0.0)
    cos_x = md.maximum(md.dot(ns, wi), 0.0)
    cos_z = md.abs(md.dot(light.geometric, wi))
    f = brdf(ns, view, wi, diffuse, look)
    area = light.stretch * md.where(nee_role[2], 4.0 * np.pi, 0.5)
    scale = cos_x * cos_z / d2 * area * nee_weight
    added = added + f * column(scale) * emission[light.obj]

    # Paths that leave the scene see the environment.
    escape_scale, escape_dir = escape
    added = added + bounce_weight(escape_dir, escape_scale) * background

    # The factor of the segment to the next vertex, with the change of measure to its area.
    next_prim, next_local, next_scale, goes = going
    nxt = surface(world, role_of(primitives, next_prim, _middle_unless(goes, next_local)))
    wi, d2 = toward(nxt.points, goes)
    geometry = md.where(goes, md.abs(md.dot(nxt.geometric, wi)) / d2 * nxt.stretch, 1.0)
    factor = bounce_weight(wi, next_scale) * column(geometry / md.detach(geometry))
    return added, factor


_window = md.compile(window_terms, shared=_SHARED)


@md.compile(shared=_SHARED)
def _replayed(
    coords, previous, here, lit, emit_weight, nee, escape, going, frame, vertices, normals,
    faces, centers, radii, smooth, materials, lights, background, primitives, form, weights,
    beta, radiance, gathered,
):  # fmt: skip
    """One window of one path (``window_terms``' arguments, then its replay's running
    values) and the objective whose VJP is the window's gradient: (C_k, F_k, objective).
    Batched (n, 3): ``weights`` d loss / d L, ``beta`` beta_k, ``radiance`` the path's L,
    ``gathered`` sum_{j<k} beta_j C_j. The objective is sum(weights beta_k C_k) +
    sum(weights beta_k Lrem_k / beta_{k+1} F_k) over the channels, its factors constants
    (``detach``) computed as ``replay._Window.replay`` computes them: the same bits."""
    added, factor = window_terms(
        coords, previous, here, lit, emit_weight, nee, escape, going, frame, vertices, normals,
        faces, centers, radii, smooth, materials, lights, background, primitives, form,
    )  # fmt: skip
    constants = md.detach(added), md.detach(factor), going[-1], weights, beta, radiance, gathered
    coefficients, scale = objective_weights(*constants)
    objective = md.sum(coefficients * added, axis=1) + md.sum(scale * factor, axis=1)
    return added, factor, objective


def _middle_unless(used, local) -> md.Tensor:
    """``local`` (n, 3) barycentric coordinates where ``used`` (n,), else the primitive's
    middle (1/3 each): the harmless point read by a path whose term there has weight 0 (no
    NEE; it does not go on), whatever its record holds."""
    return md.where(column(used), local, 1.0 / 3.0)


def objective_weights(added, factor, going, weights, beta, radiance, gathered) -> tuple:
    """The constants of window k's objective, sum(coefficients * C_k) + sum(scale * F_k)
    (``replay``'s module docstring), from its values (each (n, 3) but ``going`` (n,) bool:
    which paths go on): coefficients weights beta_k, and scale weights beta_k Lrem_k /
    beta_{k+1}, 0 where beta_{k+1} is or the path stops. ``added`` C_k, ``factor`` F_k,
    ``weights`` d loss / d L, ``beta`` beta_k, ``radiance`` L, ``gathered``
    sum_{j<k} beta_j C_j. On minidiff arrays: traced in ``_replayed``, plain values on the
    tape's windows (``replay._Window.replay``)."""
    coefficients = weights * beta
    after = beta * factor  # beta_{k+1}
    left = radiance - (gathered + beta * added)  # the radiance still to come, Lrem_k beta_{k+1}
    safe = md.where(after != 0.0, after, 1.0)
    arriving = md.where(after != 0.0, left / safe, 0.0)  # Lrem_k
    return coefficients, md.where(column(going), coefficients * arriving, 0.0)
