"""The scene as the path integrator's compiled functions read it: one set of tables.

All meshes' vertices, vertex normals and faces concatenated (row p of the face table is
primitive p), the spheres' centres and radii, per object its material and whether it is
smooth, the lights and the environment. The paths' compiled gradient
(``render.path.gradient.window``), the secondary term's level sets
(``render.path.boundary.secondary``) and the sampler's choices (``render.path.sample.choices``)
all read them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import minidiff as md
from render.scene.scene import Mesh, Scene
from render.shade.compiled import light_arguments
from render.shade.lighting import term_present
from render.shade.surface import vertex_normals
from render.trace.primitives import primitive_ranges

#: The material's parameters a path reads, as per-object tables.
MATERIAL_FIELDS = ("albedo", "specular", "shininess", "emission", "reflectance")
#: The textures a path reads: the albedo's (which replaces it) and the specular's (which
#: multiplies it).
TEXTURE_FIELDS = ("texture", "specular_texture")


@dataclass
class Tables:
    """The scene as every path reads it. Meshes: ``vertices`` (V, 3) and vertex ``normals``
    (V, 3) of all of them (a flat mesh's rows are a constant, never used), ``faces`` (F, 3)
    int64 with global vertex ids (row p is primitive p); spheres: ``centers`` (S, 3) and
    ``radii`` (S,) (None without spheres); per object (``primitive_ranges``' order)
    ``smooth`` (O,) bool and the materials' ``albedo``, ``specular``, ``emission``,
    ``reflectance`` (O, 3) and ``shininess`` (O,); where an object has a texture, the
    meshes' ``uvs`` (V, 2) and per kind of texture (``TEXTURE_FIELDS``) its table
    (``_textures``; None for a kind no object has), else None and (); the lights'
    parameters and kinds, the environment and the camera frame. The tensors are leaves;
    ``built`` pairs each differentiated one with what it was computed from on the tape.
    Plain: ``owner`` (P,) the object of each primitive,
    ``n_triangles``, ``spare_face`` (the largest triangle, read by paths on spheres),
    ``inside`` (S,) whether the camera is inside each sphere, ``first_vertex`` (O,) each
    mesh's first row of ``vertices``, ``glossy``, and ``primitives``: what a point on each
    primitive reads (``role_of``)."""

    vertices: md.Tensor | None
    normals: md.Tensor | None
    faces: np.ndarray | None
    centers: md.Tensor | None
    radii: md.Tensor | None
    smooth: np.ndarray
    materials: tuple
    lights: tuple
    kinds: tuple
    background: md.Tensor
    frame: tuple
    glossy: bool
    owner: np.ndarray
    n_triangles: int
    spare_face: int
    inside: np.ndarray
    first_vertex: np.ndarray
    built: list
    uvs: md.Tensor | None = None
    textures: tuple = ()
    primitives: tuple = field(init=False, default=())

    def __post_init__(self) -> None:
        """``primitives``, per primitive p (P,): (its face: p, or the spare face on a
        sphere; its sphere: p's row among the spheres, or 0 on a triangle; whether it is a
        sphere; its object; whether a camera ray meets it on its far side, the camera being
        inside that sphere), face and sphere None where the scene has none, the last None
        without spheres."""
        p = np.arange(len(self.owner))
        on_sphere = p >= self.n_triangles
        face = sphere = far = None
        if self.faces is not None:
            face = np.where(on_sphere, self.spare_face, p)
        if self.centers is not None:
            sphere = np.where(on_sphere, p - self.n_triangles, 0)
            far = on_sphere & self.inside[sphere]
        self.primitives = (face, sphere, on_sphere, self.owner, far)

    @classmethod
    def of(cls, world: Scene, frame: tuple, leaves: bool = True) -> Tables:
        """The tables of ``world`` (the replay's leaf copies) and its camera ``frame``.
        ``leaves`` False: the tables are on the caller's tape (nothing to carry), for one
        ``backward`` through them."""
        ranges = primitive_ranges(world)
        objects = [obj for obj, _, _ in ranges]  # meshes first, then spheres
        meshes = [obj for obj in objects if isinstance(obj, Mesh)]
        spheres = [obj for obj in objects if not isinstance(obj, Mesh)]
        built = []

        def leaf(t):
            """A leaf copy of ``t``; ``t`` kept for ``carried`` if it is differentiated."""
            if not leaves:
                return t
            copy = md.tensor(t.data, requires_grad=t.requires_grad)
            if t.requires_grad:
                built.append((t, copy))
            return copy

        vertices = normals = faces = centers = radii = None
        spare_face = 0
        first_vertex = np.zeros(len(objects), np.int64)  # meshes come first
        if meshes:
            offsets = np.cumsum([0] + [len(m.vertices.data) for m in meshes])
            first_vertex[: len(meshes)] = offsets[:-1]
            faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=False)])
            vertices = leaf(md.concatenate([m.vertices for m in meshes]))
            if any(m.smooth for m in meshes):
                normals = leaf(md.concatenate([_normals(m) for m in meshes]))
            else:  # every mesh flat: ``_normals``' constant for all their vertices at once
                normals = _flat_normals(int(offsets[-1]))
            a, b, c = (vertices.data[faces[:, i]] for i in range(3))
            spare_face = int(np.argmax(np.linalg.norm(np.cross(b - a, c - a), axis=1)))
        inside = np.zeros(0, bool)
        if spheres:
            centers = leaf(md.stack([s.center for s in spheres]))
            radii = leaf(md.stack([s.radius for s in spheres]))
            eye = frame[3].data if isinstance(frame[3], md.Tensor) else np.asarray(frame[3])
            inside = np.linalg.norm(eye - centers.data, axis=1) < radii.data
        columns = {
            name: _stacked([getattr(o.material, name) for o in objects], 3)
            for name in ("albedo", "specular", "emission", "reflectance")
        }
        columns["shininess"] = _stacked([o.material.shininess for o in objects], None)
        uvs, textures = None, ()
        if any(o.material.textures for o in objects):
            uvs = leaf(md.concatenate([_uvs(m) for m in meshes]))
            textures = tuple(_textures([getattr(o.material, name) for o in objects], leaf)
                             for name in TEXTURE_FIELDS)  # fmt: skip
        light_parameters, kinds = light_arguments(world.lights)
        return cls(
            vertices=vertices, normals=normals,
            faces=None if faces is None else np.ascontiguousarray(faces, np.int64),
            centers=centers, radii=radii,
            smooth=np.array([isinstance(o, Mesh) and bool(o.smooth) for o in objects]),
            materials=tuple(leaf(columns[name]) for name in MATERIAL_FIELDS),
            lights=light_parameters, kinds=kinds,
            background=world.background, frame=tuple(frame),
            glossy=any(term_present(o.material.specular) for o in objects),
            owner=np.repeat(np.arange(len(objects)), [count for _, _, count in ranges]),
            n_triangles=int(sum(len(m.faces) for m in meshes)), spare_face=spare_face,
            inside=inside, first_vertex=first_vertex, built=built, uvs=uvs, textures=textures,
        )  # fmt: skip

    @property
    def harmless(self) -> int:
        """A primitive of some size, where a path that has ended reads its harmless points:
        the largest triangle, or the largest sphere in a scene of spheres."""
        if self.faces is not None:
            return self.spare_face
        return self.n_triangles + int(np.argmax(self.radii.data))

    def role(self, prims: np.ndarray, local: np.ndarray) -> tuple:
        """``role_of`` the points on primitives ``prims`` (n,) at ``local`` (n, 3)."""
        return role_of(self.primitives, prims, local)

    def far_side(self, prims: np.ndarray) -> np.ndarray | None:
        """(n,) which camera rays meeting primitives ``prims`` (n,) meet a sphere's far
        side, the camera being inside it (None without spheres): ``primitives``' last."""
        return far_side_of(self.primitives, prims)

    def carried(self) -> list[md.Tensor]:
        """The terms whose ``backward`` carries what the compiled paths put into the
        leaves' ``grad`` through the tape the tables were built on."""
        return [md.sum(t * copy.grad) for t, copy in self.built if copy.grad is not None]


def compiles(world: Scene) -> bool:
    """Whether the path integrator's compiled code reads ``world``: its kernel
    (``render.path.twin.packed``) and the compiled gradient of its paths
    (``render.path.gradient.window``): float64 parameters and lights whose shading
    compiles (``Light.compiled_shading``); otherwise the reference code runs."""
    if not all(light.compiled_shading for light in world.lights):
        return False
    return all(t.dtype == np.float64 for t in world.parameters())


def role_of(primitives: tuple, prims, local) -> tuple:
    """What a compiled function reads of points on primitives ``prims`` (n,) at ``local``
    (n, 3): (face (n,), sphere (n,), on a sphere (n,) bool, object (n,), local), gathered
    from ``Tables.primitives``; face and sphere None where the scene has none. A point on
    a sphere reads the spare face, a point on a triangle sphere 0 (harmless values, never
    selected). NumPy arrays, or traced ones inside a compiled function."""
    face_of, sphere_of, on_sphere_of, owner, _ = primitives
    face = None if face_of is None else face_of[prims]
    sphere = None if sphere_of is None else sphere_of[prims]
    return face, sphere, on_sphere_of[prims], owner[prims], local


def far_side_of(primitives: tuple, prims):
    """(n,) which camera rays meeting primitives ``prims`` (n,) meet a sphere's far side,
    the camera being inside it, from ``Tables.primitives`` (None without spheres). NumPy
    arrays, or traced ones inside a compiled function."""
    far_of = primitives[4]
    return None if far_of is None else far_of[prims]


def _uvs(mesh: Mesh) -> md.Tensor:
    """A mesh's UVs (V, 2), or zeros where it has none (then it has no texture either)."""
    return mesh.uvs if mesh.uvs is not None else md.tensor(np.zeros((len(mesh.vertices.data), 2)))


def _textures(maps: list, leaf) -> tuple | None:
    """One kind of texture of every object (``maps``: each (H, W, 3) or None) as one
    table: (texels (T, 3), a leaf, each texture's rows one after the other, and per object
    (O,) floats: its first row, width and height (0, 1 and 1 without one), and whether it
    has one (O,) bool); None if no object has one."""
    if all(m is None for m in maps):
        return None
    sizes = [0 if m is None else m.shape[0] * m.shape[1] for m in maps]
    first = np.cumsum([0, *sizes[:-1]]).astype(np.float64)
    first[[m is None for m in maps]] = 0.0  # (read by no one, and in range)
    width = np.array([1.0 if m is None else m.shape[1] for m in maps])
    height = np.array([1.0 if m is None else m.shape[0] for m in maps])
    texels = leaf(md.concatenate([md.reshape(m, (-1, 3)) for m in maps if m is not None]))
    return texels, first, width, height, np.array([m is not None for m in maps])


def _normals(mesh: Mesh) -> md.Tensor:
    """The vertex normals a mesh's shading reads: its own or computed (smooth), else a
    constant unit vector (flat: ``where`` picks the geometric normal)."""
    if not mesh.smooth:
        return _flat_normals(len(mesh.vertices.data))
    return mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices, mesh.faces)


def _flat_normals(count: int) -> md.Tensor:
    """(count, 3): the constant unit vector a flat mesh's vertices hold as normals."""
    return md.tensor(np.tile([0.0, 0.0, 1.0], (count, 1)))


def _stacked(values: list, width: int | None) -> md.Tensor:
    """The per-object ``values`` (tensors), each broadcast to (width,) (a scalar for
    ``width`` None), stacked: on the tape where one is differentiated, else the same values
    as a constant (a table of a dozen rows is cheap; its dozens of tape steps were not); an
    empty table for a scene without objects."""
    shape = () if width is None else (width,)
    if not values:
        return md.tensor(np.zeros((0, *shape)))
    if any(v.is_differentiated() for v in values):
        return md.stack([md.broadcast_to(v, shape) for v in values])
    table = np.empty((len(values), *shape))
    for row, v in enumerate(values):
        table[row] = v.data  # (broadcast to the row's shape)
    return md.tensor(table)
