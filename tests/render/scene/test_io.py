"""Tests for render.scene.image (files, mse, psnr) and render.scene.meshio (mesh files)."""

import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

import minidiff
from render.scene.image import linear_to_srgb, load_image, mse, psnr, save_image, srgb_to_linear
from render.scene.meshio import load_mesh
from render.scene.scene import Material, Mesh

MESHES = Path(__file__).parents[2] / "data" / "raytracerjl" / "meshes"
TEXTURES = Path(__file__).parents[2] / "data" / "raytracerjl" / "textures"

# --- images ----------------------------------------------------------------------------


@pytest.fixture
def rgb() -> np.ndarray:
    return np.random.default_rng(0).uniform(0.0, 1.0, size=(7, 5, 3))


def test_save_load_round_trip(tmp_path, rgb):
    path = save_image(rgb, tmp_path / "sub" / "dir" / "img.png")  # parents are created
    assert path == tmp_path / "sub" / "dir" / "img.png" and path.is_file()
    back = load_image(path)
    assert back.shape == (7, 5, 3) and back.dtype == np.float64
    np.testing.assert_allclose(back, rgb, atol=0.5 / 255 + 1e-12)  # 8-bit rounding


def test_save_tensor_grey_and_clipping(tmp_path):
    img = minidiff.tensor(np.array([[-1.0, 0.25], [2.0, np.inf]]))
    back = load_image(save_image(img, tmp_path / "grey.png"))
    assert back.shape == (2, 2, 3)
    np.testing.assert_allclose(back[..., 0], [[0.0, 64 / 255], [1.0, 1.0]])
    np.testing.assert_array_equal(back[..., 0], back[..., 2])


def test_srgb_round_trip(tmp_path, rgb):
    x = np.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    assert linear_to_srgb(np.array(0.5)) == pytest.approx(0.7353569830524495)
    back = load_image(save_image(rgb, tmp_path / "s.png", srgb=True), srgb=True)
    # 8-bit rounding happens in the encoded domain; decoding amplifies it by at most 2.28x.
    np.testing.assert_allclose(back, rgb, atol=2.5 * 0.5 / 255)
    raw = load_image(tmp_path / "s.png")  # not decoded: brighter than linear mid-tones
    assert raw.mean() > rgb.mean()


def test_jpeg(tmp_path):
    flat = np.full((16, 16, 3), 0.5)
    back = load_image(save_image(flat, tmp_path / "a.JPG"))
    np.testing.assert_allclose(back, 0.5, atol=3 / 255)


def test_load_converts_modes(tmp_path):
    rgba = np.zeros((3, 4, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 255, 10
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    np.testing.assert_array_equal(load_image(tmp_path / "rgba.png")[0, 0], [1, 0, 0])
    Image.fromarray(np.full((2, 2), 51, np.uint8)).convert("P").save(tmp_path / "p.png")
    np.testing.assert_allclose(load_image(tmp_path / "p.png"), 0.2)
    Image.fromarray(np.full((2, 2), 65535, np.uint16)).save(tmp_path / "i16.png")
    np.testing.assert_allclose(load_image(tmp_path / "i16.png"), 1.0)


def test_texture_loads_with_size():
    img = load_image(TEXTURES / "wood_osb.jpg")
    with Image.open(TEXTURES / "wood_osb.jpg") as im:
        assert img.shape == (im.height, im.width, 3)
    assert 0.0 <= img.min() and img.max() <= 1.0


def test_image_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.png"):
        load_image(tmp_path / "nope.png")
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage garbage")
    with pytest.raises(ValueError, match="corrupt.png"):
        load_image(tmp_path / "corrupt.png")
    (tmp_path / "text.png").write_text("not an image")
    with pytest.raises(ValueError, match="text.png"):
        load_image(tmp_path / "text.png")
    with pytest.raises(ValueError, match=r"shape \(H, W, 3\) or \(H, W\), got \(2, 2, 4\)"):
        save_image(np.zeros((2, 2, 4)), tmp_path / "x.png")
    with pytest.raises(ValueError, match="got \\(5,\\)"):
        save_image(np.zeros(5), tmp_path / "x.png")
    with pytest.raises(ValueError, match="NaN"):
        save_image(np.full((2, 2, 3), np.nan), tmp_path / "x.png")
    with pytest.raises(ValueError, match="unsupported extension '.bmp'"):
        save_image(np.zeros((2, 2, 3)), tmp_path / "x.bmp")
    assert not (tmp_path / "x.png").exists()


def test_mse_psnr_closed_forms():
    a = np.zeros((4, 4, 3))
    b = np.full((4, 4, 3), 0.1)
    assert isinstance(mse(a, b), float)
    assert mse(a, b) == pytest.approx(0.01)
    assert psnr(a, b) == pytest.approx(20.0)  # 10 log10(1 / 0.01)
    assert psnr(a, b, peak=2.0) == pytest.approx(20.0 + 20 * math.log10(2.0))
    assert psnr(b, b) == math.inf and mse(b, b) == 0.0
    c = a.copy()
    c[0, 0, 0] = 1.0  # one wrong value out of 48
    assert mse(c, a) == pytest.approx(1 / 48)
    with pytest.raises(ValueError, match="shapes differ"):
        mse(a, np.zeros((4, 4)))
    with pytest.raises(ValueError, match="shapes differ"):
        psnr(a, np.zeros((3, 4, 3)))


@settings(max_examples=25, deadline=None)
@given(st.floats(-2, 2), st.floats(-2, 2))
def test_mse_constant_images(x, y):
    assert mse(np.full((3, 2, 3), x), np.full((3, 2, 3), y)) == pytest.approx((x - y) ** 2)


def test_mse_tensor_is_differentiable():
    rng = np.random.default_rng(1)
    target = rng.uniform(size=(3, 4, 3))
    image = minidiff.tensor(rng.uniform(size=(3, 4, 3)), requires_grad=True)
    loss = mse(image, target)
    assert isinstance(loss, minidiff.Tensor) and loss.shape == ()
    assert float(loss.data) == pytest.approx(mse(image.data, target))
    loss.backward()
    np.testing.assert_allclose(image.grad, 2 * (image.data - target) / target.size)
    # Tensor target with array image: same value.
    assert float(mse(target, image).data) == pytest.approx(float(loss.data))


# --- meshes ------------------------------------------------------------------------------


def test_teapot_obj_triangulated():
    (mesh,) = load_mesh(MESHES / "teapot_rtjl.obj")
    assert mesh.num_faces == 2256 and mesh.num_vertices >= 1202
    assert mesh.normals is not None and mesh.uvs is None and not mesh.smooth
    np.testing.assert_array_equal(mesh.material.albedo.data, [0.8, 0.8, 0.8])  # no MTL


def test_tree_materials_from_mtl():
    meshes = load_mesh(MESHES / "tree.obj", ambient_light=0.5)
    assert len(meshes) == 2
    mats = {tuple(m.material.albedo.data): m.material for m in meshes}
    bark = mats[(0.207595, 0.138513, 0.055181)]
    tree = mats[(0.029850, 0.106291, 0.017666)]
    np.testing.assert_array_equal(bark.specular.data, [0, 0, 0])
    assert float(bark.shininess.data) == pytest.approx(254.901961)
    np.testing.assert_array_equal(tree.specular.data, [0.085514, 0.355277, 0.074845])
    assert float(tree.shininess.data) == pytest.approx(96.078431)
    np.testing.assert_array_equal(tree.ambient.data, [0, 0, 0])  # Ka = 0
    assert sum(m.num_faces for m in meshes) == 37
    # Deterministic order.
    again = load_mesh(MESHES / "tree.obj")
    assert [m.num_faces for m in again] == [m.num_faces for m in meshes]


def test_sign_textures_and_uvs():
    meshes = load_mesh(MESHES / "sign_yield.obj", ambient_light=0.25)
    assert len(meshes) == 3  # the `l` polyline object is skipped
    textured = [m for m in meshes if m.material.texture is not None]
    assert len(textured) == 2
    sizes = set()
    for m in textured:
        assert m.uvs is not None and m.uvs.shape == (m.num_vertices, 2)
        tex = m.material.texture.data
        assert tex.ndim == 3 and tex.shape[2] == 3 and 0 <= tex.min() and tex.max() <= 1
        sizes.add(tex.shape[:2])
    expected = set()
    for name in ("sign_yield.png", "wood_osb.jpg"):
        with Image.open(TEXTURES / name) as im:
            expected.add((im.height, im.width))
    assert sizes == expected
    for m in meshes:  # Ka = 1 everywhere in this MTL
        np.testing.assert_allclose(m.material.ambient.data, [0.25] * 3)
        np.testing.assert_allclose(m.material.specular.data, [0.5] * 3)
    green = [m for m in meshes if m.material.texture is None][0]
    np.testing.assert_array_equal(green.material.albedo.data, [0.239216, 0.6, 0.239216])


def test_material_override():
    mat = Material((0.1, 0.2, 0.3))
    meshes = load_mesh(MESHES / "sign_yield.obj", material=mat)
    assert all(m.material is mat for m in meshes)


@pytest.mark.parametrize("ext", [".ply", ".stl", ".off", ".glb"])
def test_round_trip_formats(tmp_path, ext):
    box = trimesh.creation.box()
    path = tmp_path / f"box{ext}"
    box.export(path)
    meshes = load_mesh(path)
    assert sum(m.num_faces for m in meshes) == len(box.faces) == 12
    assert all(isinstance(m, Mesh) for m in meshes)
    if ext != ".stl":  # STL stores unshared corners
        assert sum(m.num_vertices for m in meshes) == len(box.vertices)
    for m in meshes:
        lo, hi = m.vertices.data.min(axis=0), m.vertices.data.max(axis=0)
        np.testing.assert_allclose([lo, hi], [[-0.5] * 3, [0.5] * 3])


def test_glb_texture(tmp_path):
    quad = trimesh.Trimesh(
        vertices=[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]],
        faces=[[0, 1, 2], [0, 2, 3]],
        process=False,
    )
    image = Image.fromarray(np.full((4, 6, 3), [255, 0, 0], np.uint8))
    quad.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=image)
    quad.export(tmp_path / "quad.glb")
    (mesh,) = load_mesh(tmp_path / "quad.glb")
    assert mesh.num_faces == 2 and mesh.uvs is not None
    assert mesh.material.texture.shape == (4, 6, 3)
    np.testing.assert_allclose(mesh.material.texture.data[0, 0], [1, 0, 0])


def test_quads_are_triangulated(tmp_path):
    obj = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\nf 1 2 3 4\nf 2 5 6 3\n"
    (tmp_path / "quads.obj").write_text(obj)
    (mesh,) = load_mesh(tmp_path / "quads.obj")
    assert mesh.num_faces == 4 and mesh.num_vertices == 6
    np.testing.assert_array_equal(mesh.vertices.data[:, 0], [0, 1, 1, 0, 2, 2])  # order kept


def test_missing_mtl_and_texture_warn(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl red\nKd 1 0 0\nmap_Kd missing.png\n")
    obj = "mtllib m.mtl\nmtllib gone.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"
    (tmp_path / "t.obj").write_text(obj + "usemtl red\nf 1/1 2/2 3/3\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        (mesh,) = load_mesh(tmp_path / "t.obj")
    text = " ".join(str(w.message) for w in caught)
    assert "gone.mtl" in text and "missing.png" in text
    np.testing.assert_array_equal(mesh.material.albedo.data, [1, 0, 0])
    assert mesh.material.texture is None


TRIANGLE_WITH_UVS = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"


def test_specular_and_ambient_texture_maps(tmp_path):
    """map_Ks and map_Ka become specular_texture and ambient_texture (each its own size),
    read like map_Kd; Ks and Ka keep multiplying them."""
    shutil.copy(TEXTURES / "sign_yield.png", tmp_path / "kd.png")
    ks = np.random.default_rng(1).uniform(0, 1, (3, 5, 3))
    ka = np.random.default_rng(2).uniform(0, 1, (6, 2, 3))
    save_image(ks, tmp_path / "ks.png", srgb=False)
    save_image(ka, tmp_path / "ka.png", srgb=False)
    mtl = "newmtl m\nKd 1 1 1\nKs 0.5 0.5 0.5\nKa 0.2 0.2 0.2\n"
    mtl += "map_Kd kd.png\nmap_Ks -s 1 1 1 ks.png\nmap_Ka ka.png\nillum 2\nd 1\nKe 0 0 0\n"
    (tmp_path / "m.mtl").write_text(mtl)
    (tmp_path / "t.obj").write_text(
        "mtllib m.mtl\n" + TRIANGLE_WITH_UVS + "usemtl m\nf 1/1 2/2 3/3\n"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing unmodelled in this file
        (mesh,) = load_mesh(tmp_path / "t.obj", ambient_light=2.0)
    material = mesh.material
    assert material.texture.shape == load_image(tmp_path / "kd.png").shape
    np.testing.assert_allclose(material.specular_texture.data, ks, atol=0.5 / 255)
    np.testing.assert_allclose(material.ambient_texture.data, ka, atol=0.5 / 255)
    np.testing.assert_allclose(material.specular.data, [0.5, 0.5, 0.5])
    np.testing.assert_allclose(material.ambient.data, [0.4, 0.4, 0.4])


def test_what_an_mtl_asks_for_and_we_do_not_model_is_named_in_one_warning(tmp_path):
    mtl = "newmtl glass\nKd 1 1 1\nd 0.5\nillum 3\nmap_Bump n.png\nKe 0 0 0\nNi 1.5\n"
    mtl += "newmtl other\nKd 1 1 1\nd 0.5\nTr 0\n"
    (tmp_path / "m.mtl").write_text(mtl)
    (tmp_path / "t.obj").write_text(
        "mtllib m.mtl\n" + TRIANGLE_WITH_UVS + "usemtl glass\nf 1 2 3\n"
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        (mesh,) = load_mesh(tmp_path / "t.obj")
    messages = [str(w.message) for w in caught]
    assert len(messages) == 1, messages
    for named in ("'d 0.5'", "'illum 3'", "'map_Bump n.png'", "reflectance"):
        assert named in messages[0]
    assert "Ke" not in messages[0] and "Tr" not in messages[0] and "Ni" not in messages[0]
    assert not mesh.material.reflective  # d is not read as a reflection coefficient


def test_the_raytracerjl_mtl_files_load_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_mesh(MESHES / "sign_yield.obj")
        load_mesh(MESHES / "tree.obj")


def test_mesh_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.obj"):
        load_mesh(tmp_path / "nothing.obj")
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    with pytest.raises(ValueError, match=r"unsupported file type '.xyz'.*\.obj, \.ply"):
        load_mesh(tmp_path / "a.xyz")
    (tmp_path / "lines.obj").write_text("v 0 0 0\nv 1 0 0\nl 1 2\n")
    with pytest.raises(ValueError, match="lines.obj contains no triangles"):
        load_mesh(tmp_path / "lines.obj")
    (tmp_path / "junk.obj").write_bytes(b"\x00\xff garbage \x01 not an obj")
    with pytest.raises(ValueError, match="junk.obj"):
        load_mesh(tmp_path / "junk.obj")
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat nonsense\n\x00\x01\x02")
    with pytest.raises(ValueError, match="junk.ply"):
        load_mesh(tmp_path / "junk.ply")
    (tmp_path / "junk.glb").write_bytes(b"glTF not really")
    with pytest.raises(ValueError, match="junk.glb"):
        load_mesh(tmp_path / "junk.glb")
    with pytest.raises(TypeError, match="material must be a Material"):
        load_mesh(MESHES / "tree.obj", material="red")


def test_load_image_bad_inputs_say_what_is_wrong(tmp_path):
    with pytest.raises(TypeError, match="path must be a str or Path"):
        load_image(None)
    nan_tiff = tmp_path / "nan.tif"
    Image.fromarray(np.array([[0.5, np.nan], [np.inf, 0.1]], np.float32), mode="F").save(nan_tiff)
    with pytest.raises(ValueError, match="2 pixels that are NaN or inf"):
        load_image(nan_tiff)
    big = tmp_path / "big.png"
    Image.new("L", (200, 200)).save(big)
    limit = Image.MAX_IMAGE_PIXELS
    try:
        Image.MAX_IMAGE_PIXELS = 100  # 40,000 pixels is then "more than twice the limit"
        with pytest.raises(ValueError, match="safety limit"):
            load_image(big)
    finally:
        Image.MAX_IMAGE_PIXELS = limit


PLY_HEADER = """ply
format ascii 1.0
element vertex {n}
property float x
property float y
property float z
element face 1
property list uchar int vertex_indices
end_header
"""


@pytest.mark.parametrize("declared", [2, 4, 5])
def test_an_ascii_ply_whose_counts_do_not_match_its_data_says_so(tmp_path, declared):
    """trimesh read a wrong vertex count as a file with "no triangles"."""
    path = tmp_path / "bad.ply"
    path.write_text(PLY_HEADER.format(n=declared) + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(ValueError, match=f"declares {declared} vertex, 1 face .* but 4 follow"):
        load_mesh(path)
    path.write_text(PLY_HEADER.format(n=3) + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert load_mesh(path)[0].num_faces == 1


@pytest.mark.parametrize("path", [None, 42, b"mesh.obj", ["a.obj"]])
def test_load_mesh_names_a_path_of_the_wrong_type(path):
    with pytest.raises(TypeError, match="load_mesh: path must be a str or pathlib.Path"):
        load_mesh(path)


@pytest.mark.parametrize("ext", [".stl", ".off"])
def test_garbage_stl_and_off_files_are_a_clear_error(tmp_path, ext):
    path = tmp_path / f"garbage{ext}"
    path.write_bytes(b"garbage\x00\x01 not a mesh\n" * 3)
    with pytest.raises(ValueError, match=f"load_mesh: (cannot parse )?{path}"):
        load_mesh(path)
