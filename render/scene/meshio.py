"""Loading triangle meshes (OBJ + MTL, PLY, STL, OFF, GLB) into ``render.scene.scene.Mesh`` objects.

trimesh parses the geometry (and triangulates polygons); this module turns what it returns
into our ``Mesh``/``Material`` classes:

* one ``Mesh`` per trimesh geometry instance, i.e. per material group for OBJ files
  (trimesh merges faces that share a material), ordered by (geometry name, node name) so the
  result does not depend on dictionary order;
* ``process=False``: vertices are neither merged nor reordered, except that trimesh must
  duplicate a vertex used with several normals/UVs (OBJ corners are per-face);
* vertex normals and UVs are kept when the file has them;
* non-triangle geometry (OBJ ``l`` polylines, point clouds) is skipped.

Materials of OBJ files are read from the MTL file(s) by our own small parser rather than
from trimesh's ``SimpleMaterial``, because trimesh quantises colours to 8 bits and refuses
textures outside the OBJ's folder (``map_Kd ../textures/x.png`` is common). Mapping:

====== ============================== =============================================
MTL    Material                       note
====== ============================== =============================================
Kd     albedo (3,)                    default (0.8, 0.8, 0.8)
Ks     specular (3,)                  default 0
Ns     shininess                      values <= 0 (some exporters write 0) become 1
Ka     ambient = Ka * ambient_light   an added radiance (classic Phong ``Ka * Ia``)
map_Kd texture (H, W, 3) in [0, 1]    read with Pillow, stored values (no sRGB decode)
map_Ks specular_texture (H, W, 3)     multiplies Ks at each hit
map_Ka ambient_texture (H, W, 3)      multiplies Ka * ambient_light at each hit
====== ============================== =============================================

What we do not model is not read silently: a warning names it, once per MTL file. That
includes transparency (``d`` < 1, ``Tr`` > 0: RayTracer.jl reads ``d`` as a reflection
coefficient; here it means dissolve, and mirrors are ``Material(reflectance=...)``, set by
the user), emission (``Ke``), the ray-traced illumination models (``illum`` 3-9) and
other maps (bump, displacement, dissolve, ...). Keys without an effect on a rendering
(``illum`` 0-2, ``Ni`` outside refraction) pass quietly.

GLB/PLY/... materials come from trimesh (base colour, base colour texture); files without
a material get grey albedo (0.8, 0.8, 0.8).

UV convention: as trimesh returns them, i.e. OBJ/OpenGL (v = 0 at the *bottom* of the
texture image; see ``Material``).
"""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from render.scene.image import load_image
from render.scene.scene import Material, Mesh

if TYPE_CHECKING:  # at run time imported where a file is read (trimesh, with SciPy: ~1.1 s)
    import trimesh

__all__ = ["load_mesh", "SUPPORTED_MESH_EXTENSIONS", "DEFAULT_ALBEDO"]

#: Extensions ``load_mesh`` accepts (lower case).
SUPPORTED_MESH_EXTENSIONS = (".obj", ".ply", ".stl", ".off", ".glb")

#: Albedo of meshes whose file defines no material.
DEFAULT_ALBEDO = (0.8, 0.8, 0.8)


def load_mesh(
    path: str | Path, material: Material | None = None, ambient_light: Any = 0.0
) -> list[Mesh]:
    """Load a mesh file as a list of ``Mesh`` objects, one per material group.

    Args:
        path: an ``.obj`` (with its ``mtllib`` MTL files), ``.ply``, ``.stl``, ``.off`` or
            ``.glb`` file.
        material: if given, used for *every* mesh instead of the file's materials.
        ambient_light: scalar or (3,) ambient light radiance ``Ia``; each material's
            ``ambient`` is ``Ka * ambient_light`` (so the default 0 means no ambient term).

    Returns:
        Non-empty list of flat-shaded (``smooth=False``) meshes; set ``mesh.smooth = True``
        to shade with the file's vertex normals when it has them.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: unsupported extension, unparsable content, or no triangles in the file.
    """
    if not isinstance(path, str | Path):
        raise TypeError(f"load_mesh: path must be a str or pathlib.Path, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"load_mesh: no such file: {path}")
    ext = path.suffix.lower()
    if ext not in SUPPORTED_MESH_EXTENSIONS:
        raise ValueError(
            f"load_mesh: unsupported file type {path.suffix!r} for {path}; "
            f"supported: {', '.join(SUPPORTED_MESH_EXTENSIONS)}"
        )
    if material is not None and not isinstance(material, Material):
        raise TypeError(f"load_mesh: material must be a Material, got {type(material).__name__}")
    ambient_light = np.asarray(ambient_light, dtype=np.float64)
    if ambient_light.shape not in ((), (3,)):
        raise ValueError(
            f"load_mesh: ambient_light must be a scalar or (3,), got {ambient_light.shape}"
        )

    if path.stat().st_size == 0:
        raise ValueError(f"load_mesh: {path} is empty")
    import trimesh  # here, not at the top: ``import render`` stays ~1.1 s faster

    source: Any = str(path)
    resolver = None
    if ext == ".obj":
        text = check_obj(path)  # clear errors for what trimesh would misread or crash on
        source, resolver = io.StringIO(text), trimesh.resolvers.FilePathResolver(str(path))
    elif ext == ".ply":
        check_ascii_ply(path)  # trimesh reads a wrong count as "no triangles"
    try:
        loaded = trimesh.load_scene(
            source, file_type=ext[1:], resolver=resolver, process=False, group_material=True
        )
    except Exception as err:  # trimesh raises many different types for bad input
        raise ValueError(f"load_mesh: cannot parse {path}: {err}") from err

    mtl = _read_obj_materials(path) if ext == ".obj" else {}
    meshes = []
    for geom_name, _node, transform, geom in _instances(loaded):
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue  # polylines (OBJ `l`), point clouds, empty groups
        vertices = np.asarray(geom.vertices, dtype=np.float64)
        normals = _file_normals(geom)
        uvs = _file_uvs(geom)
        if not np.allclose(transform, np.eye(4)):
            vertices, normals = _transform(vertices, normals, transform)

        if material is not None:
            mat = material
        elif ext == ".obj":
            mat = _obj_material(geom, mtl, ambient_light, path)
        else:
            mat = _trimesh_material(geom, ambient_light)
        if mat.texture is not None and uvs is None:
            warnings.warn(
                f"load_mesh: {path}: material of {geom_name!r} has a texture but the mesh "
                "has no UVs; using its albedo instead",
                stacklevel=2,
            )
            mat = Material(mat.albedo, mat.specular, mat.shininess, mat.ambient)
        meshes.append(Mesh(vertices, np.asarray(geom.faces), mat, normals=normals, uvs=uvs))

    if not meshes:
        raise ValueError(f"load_mesh: {path} contains no triangles")
    return meshes


def check_ascii_ply(path: Path) -> None:
    """For an ASCII PLY file: ValueError if the header's element counts (vertices, faces,
    ...) do not add up to the data lines that follow it. Binary PLY files are left to
    trimesh, which checks their sizes itself."""
    with open(path, "rb") as f:
        head = f.read(4096)
    if not head.startswith(b"ply") or b"format ascii" not in head.split(b"end_header")[0]:
        return
    text = read_text(path)
    header, _, body = text.partition("end_header")
    counts = {}
    for line in header.splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == "element":
            try:
                counts[words[1]] = int(words[2])
            except ValueError:
                raise ValueError(
                    f"load_mesh: {path}: the header's count of {words[1]!r} is not an integer: "
                    f"{words[2]!r}"
                ) from None
    rows = sum(1 for line in body.splitlines() if line.strip())
    if rows != sum(counts.values()):
        declared = ", ".join(f"{n} {name}" for name, n in counts.items())
        raise ValueError(
            f"load_mesh: {path}: the header declares {declared} ({sum(counts.values())} data "
            f"lines) but {rows} follow it"
        )


def read_text(path: Path) -> str:
    """A text file's content: UTF-8, or Latin-1 if it is not valid UTF-8 (one accented
    byte in a comment is common in the wild; Latin-1 decodes any byte)."""
    data = path.read_bytes()
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _obj_number(token: str, path: Path, line_no: int, what: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise ValueError(
            f"load_mesh: {path}, line {line_no}: {what} must be a number, got {token!r}"
        ) from None
    if not np.isfinite(value):
        raise ValueError(f"load_mesh: {path}, line {line_no}: {what} is {token!r}")
    return value


def _obj_index(token: str, count: int, path: Path, line_no: int, what: str) -> None:
    """Check one OBJ index: a non-zero integer, 1-based from the start or negative from
    the end, referring to one of the ``count`` entries defined so far."""
    try:
        index = int(token)
    except ValueError:
        raise ValueError(
            f"load_mesh: {path}, line {line_no}: {what} index must be an integer, got {token!r}"
        ) from None
    if index == 0:
        raise ValueError(
            f"load_mesh: {path}, line {line_no}: {what} index 0 is invalid (OBJ indices "
            "start at 1; negative ones count from the end)"
        )
    if index > count or index < -count:
        raise ValueError(
            f"load_mesh: {path}, line {line_no}: {what} index {index} refers past the "
            f"{count} defined so far"
        )


def check_obj(path: Path) -> str:
    """Read an OBJ file's text and check the lines that trimesh would silently misread:
    vertices need three numbers, faces at least three corners whose indices are non-zero
    integers within range. Raises ValueError naming the file, the line and the problem.
    (A file cut in the middle of its last index that still leaves a valid index cannot be
    told from a complete one: many valid OBJ files have no final newline.) Returns the
    text (see ``read_text``)."""
    text = read_text(path)
    counts = {"v": 0, "vt": 0, "vn": 0}
    for line_no, raw in enumerate(text.splitlines(), start=1):
        tokens = raw.split("#", 1)[0].split()
        if not tokens:
            continue
        key, args = tokens[0], tokens[1:]
        if key in counts:
            needed = {"v": 3, "vt": 1, "vn": 3}[key]
            if len(args) < needed:
                raise ValueError(
                    f"load_mesh: {path}, line {line_no}: {key} needs {needed} numbers, "
                    f"got {raw.strip()!r}"
                )
            for token in args[: {"v": 3, "vt": 2, "vn": 3}[key]]:
                _obj_number(token, path, line_no, f"a {key} coordinate")
            counts[key] += 1
        elif key == "f":
            if len(args) < 3:
                raise ValueError(
                    f"load_mesh: {path}, line {line_no}: a face needs 3 corners, got "
                    f"{raw.strip()!r}"
                )
            for corner in args:
                parts = corner.split("/")
                if len(parts) > 3 or parts[0] == "":
                    raise ValueError(
                        f"load_mesh: {path}, line {line_no}: bad face corner {corner!r}"
                    )
                for part, kind in zip(parts, ("v", "vt", "vn"), strict=False):
                    if part != "":
                        _obj_index(part, counts[kind], path, line_no, kind)
    return text


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------


def _instances(scene: trimesh.Scene) -> list[tuple[str, str, np.ndarray, Any]]:
    """(geometry name, node name, 4x4 world transform, geometry) for each placed geometry."""
    result = []
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry[geom_name]
        result.append((str(geom_name), str(node), np.asarray(transform), geom))
    result.sort(key=lambda item: (item[0], item[1]))
    return result


def _file_normals(geom: trimesh.Trimesh) -> np.ndarray | None:
    """Vertex normals read from the file, or None.

    ``geom.vertex_normals`` would *compute* normals when the file has none, so we look in
    trimesh's cache, where loaders put the normals they read (and nothing else has run yet
    since the mesh was built with process=False).
    """
    cached = geom._cache["vertex_normals"]  # None if absent (no public "was it given?")
    if cached is None:
        return None
    normals = np.asarray(cached, dtype=np.float64)
    if normals.shape != geom.vertices.shape or not np.isfinite(normals).all():
        return None
    return normals


def _file_uvs(geom: trimesh.Trimesh) -> np.ndarray | None:
    uv = getattr(geom.visual, "uv", None)
    if uv is None:
        return None
    uv = np.asarray(uv, dtype=np.float64)
    if uv.shape != (len(geom.vertices), 2) or not np.isfinite(uv).all():
        return None
    return uv


def _transform(
    vertices: np.ndarray, normals: np.ndarray | None, matrix: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None]:
    """Apply a 4x4 node transform (GLB scene graphs); normals use the inverse transpose."""
    vertices = vertices @ matrix[:3, :3].T + matrix[:3, 3]
    if normals is not None:
        normals = normals @ np.linalg.inv(matrix[:3, :3])  # == (inv(M).T @ n.T).T
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.where(length > 0, length, 1.0)
    return vertices, normals


# --------------------------------------------------------------------------------------
# Materials
# --------------------------------------------------------------------------------------


@dataclass
class _MtlEntry:
    """One ``newmtl`` block of an MTL file (only the fields we use)."""

    kd: tuple[float, ...] = DEFAULT_ALBEDO
    ks: tuple[float, ...] = (0.0, 0.0, 0.0)
    ka: tuple[float, ...] = (0.0, 0.0, 0.0)
    ns: float = 32.0
    map_kd: Path | None = None
    map_ks: Path | None = None
    map_ka: Path | None = None


def _obj_directives(path: Path, keyword: str) -> list[str]:
    """The argument text of every ``keyword ...`` line of a text file."""
    result = []
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            parts = line.strip().split(maxsplit=1)
            if len(parts) == 2 and parts[0] == keyword:
                result.append(parts[1].strip())
    return result


def _read_obj_materials(obj_path: Path) -> dict[str, _MtlEntry]:
    """Parse every ``mtllib`` of an OBJ file; missing MTL files only warn (common in the wild)."""
    materials: dict[str, _MtlEntry] = {}
    for name in _obj_directives(obj_path, "mtllib"):
        mtl_path = obj_path.parent / name.replace("\\", "/")
        if not mtl_path.is_file():
            warnings.warn(
                f"load_mesh: {obj_path}: material file {mtl_path} not found", stacklevel=3
            )
            continue
        materials.update(_parse_mtl(mtl_path))
    return materials


def _floats(values: list[str], mtl_path: Path, key: str) -> tuple[float, ...]:
    try:
        numbers = tuple(float(v) for v in values)
    except ValueError as err:
        raise ValueError(f"load_mesh: {mtl_path}: bad {key} values {values}") from err
    if len(numbers) == 1:  # "Kd 0.5" means grey
        numbers = numbers * 3
    if len(numbers) < 3:
        raise ValueError(f"load_mesh: {mtl_path}: {key} needs 1 or 3 values, got {values}")
    return numbers[:3]


#: MTL keys that change a rendering but that we do not model, with what they mean; a
#: value saying "no effect" (d 1, Tr 0, Ke 0 0 0) is not reported.
_UNMODELLED = {
    "d": "dissolve (transparency)",
    "tr": "transparency",
    "ke": "emission",
    "tf": "transmission filter",
    "illum": "illumination model",
    "map_d": "dissolve map",
    "map_ke": "emission map",
    "map_ns": "shininess map",
    "map_bump": "bump map",
    "bump": "bump map",
    "norm": "normal map",
    "disp": "displacement map",
    "decal": "decal map",
    "refl": "reflection map",
}


def _has_effect(key: str, values: list[str]) -> bool:
    """Whether an unmodelled MTL statement would change the image."""
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        return True
    if key == "d":
        return numbers[0] != 1.0
    if key in ("tr", "ke"):
        return any(numbers)
    if key == "tf":
        return any(n != 1.0 for n in numbers)
    if key == "illum":
        return numbers[0] > 2  # 0-2: colour, ambient, highlight (what we model)
    return True


def _parse_mtl(mtl_path: Path) -> dict[str, _MtlEntry]:
    """Kd, Ks, Ka, Ns, map_Kd, map_Ks and map_Ka of each material in an MTL file; one
    warning naming what the file asks for that we do not model."""
    materials: dict[str, _MtlEntry] = {}
    current: _MtlEntry | None = None
    ignored: dict[str, str] = {}
    with open(mtl_path, encoding="utf-8", errors="replace") as f:
        for line in f:
            parts = line.split()
            if len(parts) < 2 or parts[0].startswith("#"):
                continue
            key = parts[0].lower()
            if key == "newmtl":
                current = materials[" ".join(parts[1:])] = _MtlEntry()
            elif current is None:
                continue
            elif key in ("kd", "ks", "ka"):
                # Skip "Kd spectral ..." / "Kd xyz ..." variants: not plain RGB.
                if parts[1].lower() not in ("spectral", "xyz"):
                    setattr(current, key, _floats(parts[1:], mtl_path, key))
            elif key == "ns":
                current.ns = _floats(parts[1:2], mtl_path, key)[0]
            elif key in ("map_kd", "map_ks", "map_ka"):
                path = _texture_path(mtl_path, line.strip()[len(parts[0]) :].strip())
                setattr(current, key, path)
            elif key in _UNMODELLED and _has_effect(key, parts[1:]):
                ignored.setdefault(f"{parts[0]} {' '.join(parts[1:])}", _UNMODELLED[key])
    if ignored:
        listed = "; ".join(f"{text!r} ({meaning})" for text, meaning in ignored.items())
        warnings.warn(
            f"load_mesh: {mtl_path}: not modelled, ignored: {listed}. A mirror is "
            "Material(reflectance=...), set by you (MTL 'd' is not read as reflection)",
            stacklevel=4,
        )
    return materials


def _texture_path(mtl_path: Path, argument: str) -> Path:
    """Resolve a ``map_Kd`` argument relative to the MTL file.

    The argument may start with options (``-s 1 1 1 tex.png``); the file name is then its
    last word (file names with spaces and options together are not supported).
    """
    argument = argument.replace("\\", "/")
    candidate = mtl_path.parent / argument
    if candidate.is_file() or not argument.startswith("-"):
        return candidate
    return mtl_path.parent / argument.split()[-1]


def _obj_material(
    geom: trimesh.Trimesh, mtl: dict[str, _MtlEntry], ambient_light: np.ndarray, path: Path
) -> Material:
    """Material of one OBJ material group: trimesh tells its name, our MTL parse the values."""
    name = getattr(getattr(geom.visual, "material", None), "name", None)
    entry = mtl.get(name) if name is not None else None
    if entry is None:
        return Material(albedo=DEFAULT_ALBEDO)

    return Material(
        albedo=entry.kd,
        specular=entry.ks,
        shininess=entry.ns if entry.ns > 0 else 1.0,
        ambient=np.asarray(entry.ka) * ambient_light,
        texture=_texture(entry.map_kd, path),
        specular_texture=_texture(entry.map_ks, path),
        ambient_texture=_texture(entry.map_ka, path),
    )


def _texture(file: Path | None, obj_path: Path) -> np.ndarray | None:
    """A texture map's image, or None (with a warning if the file named is missing)."""
    if file is None:
        return None
    if not file.is_file():
        warnings.warn(f"load_mesh: {obj_path}: texture {file} not found", stacklevel=4)
        return None
    return load_image(file)


def _trimesh_material(geom: trimesh.Trimesh, ambient_light: np.ndarray) -> Material:
    """Material from trimesh's visual (GLB PBR base colour/texture, simple materials)."""
    import trimesh  # already imported by ``load_mesh``, its caller

    mat = getattr(geom.visual, "material", None)
    if mat is None:
        return Material(albedo=DEFAULT_ALBEDO)
    if isinstance(mat, trimesh.visual.material.PBRMaterial):
        factor = mat.baseColorFactor
        albedo = DEFAULT_ALBEDO if factor is None else np.asarray(factor[:3]) / 255.0
        image = mat.baseColorTexture
        texture = None if image is None else _pil_to_float(image)
        return Material(albedo=albedo, texture=texture)
    if isinstance(mat, trimesh.visual.material.SimpleMaterial):
        image = mat.image
        return Material(
            albedo=np.asarray(mat.diffuse[:3]) / 255.0,
            specular=np.asarray(mat.specular[:3]) / 255.0,
            shininess=max(float(mat.glossiness or 0.0), 1.0),
            ambient=np.asarray(mat.ambient[:3]) / 255.0 * ambient_light,
            texture=None if image is None else _pil_to_float(image),
        )
    return Material(albedo=DEFAULT_ALBEDO)


def _pil_to_float(image: Any) -> np.ndarray:
    """A PIL image as (H, W, 3) float64 in [0, 1] (alpha dropped)."""
    return np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
