"""Mesh files that are broken in the ways users' files are: each loads correctly or fails
with a ValueError naming the file (and, for OBJ text, the line) — never another exception,
never a silently wrong mesh."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from render.scene.meshio import load_mesh

GOOD = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"


def write(tmp_path, name: str, content: bytes | str):
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode("utf-8"))
    return path


@pytest.mark.parametrize(
    "text, message",
    [
        (GOOD + "f 0 1 2\n", r"line 5: v index 0 is invalid"),
        (GOOD + "f 1 2 9\n", r"line 5: v index 9 refers past the 4"),
        (GOOD + "f 1.5 2 3\n", r"line 5: v index must be an integer, got '1.5'"),
        ("v a b c\n" + GOOD + "f 1 2 3\n", r"line 1: a v coordinate must be a number"),
        (GOOD + "f 1 2\n", r"line 5: a face needs 3 corners"),
        (GOOD + "f 1 2 -7\n", r"refers past"),
    ],
)
def test_broken_obj_lines_name_the_file_and_line(tmp_path, text, message):
    path = write(tmp_path, "m.obj", text)
    with pytest.raises(ValueError, match=message) as caught:
        load_mesh(path)
    assert str(path) in str(caught.value)


def test_a_latin1_comment_loads(tmp_path):
    path = write(tmp_path, "m.obj", b"# caf\xe9\n" + GOOD.encode() + b"f 1 2 3\nf 1 3 4\n")
    (mesh,) = load_mesh(path)
    assert mesh.num_faces == 2


@pytest.mark.parametrize("name", ["empty.off", "empty.glb", "empty.obj", "empty.stl"])
def test_empty_files(tmp_path, name):
    path = write(tmp_path, name, b"")
    with pytest.raises(ValueError, match="is empty"):
        load_mesh(path)


# --------------------------------------------------------------------------------------
# Generated OBJ text against a reference parse
# --------------------------------------------------------------------------------------


def reference_triangles(text: str):
    """Independent reading of the subset of OBJ the generator writes: the corner
    positions (F, 3, 3) of the faces, or None if the text is invalid."""
    vertices, triangles = [], []
    for raw in text.splitlines():
        tokens = raw.split("#", 1)[0].split()
        if not tokens:
            continue
        if tokens[0] == "v":
            try:
                xyz = [float(t) for t in tokens[1:4]]
            except ValueError:
                return None
            if len(xyz) < 3 or not np.isfinite(xyz).all():
                return None
            vertices.append(xyz)
        elif tokens[0] == "f":
            if len(tokens) != 4:
                return None
            ids = []
            for t in tokens[1:]:
                try:
                    i = int(t)
                except ValueError:
                    return None
                if i == 0 or i > len(vertices) or i < -len(vertices):
                    return None
                ids.append(i - 1 if i > 0 else len(vertices) + i)
            triangles.append([vertices[i] for i in ids])
        else:
            return None  # the generator writes nothing else but comments
    return np.array(triangles, dtype=np.float64).reshape(-1, 3, 3)


line = st.one_of(
    st.tuples(st.just("v"), st.lists(st.integers(-9, 9), min_size=3, max_size=3)).map(
        lambda t: "v " + " ".join(map(str, t[1]))
    ),
    st.lists(st.integers(-6, 8), min_size=3, max_size=3).map(
        lambda ids: "f " + " ".join(map(str, ids))
    ),
    st.sampled_from(["# comment", "v a b c", "f 1.5 2 3", "f 1 2", "v 1 2", "f 0 1 2", ""]),
)


@settings(max_examples=60)
@given(
    lines=st.lists(line, min_size=1, max_size=12),
    cut=st.integers(0, 3),
    latin1=st.booleans(),
)
def test_generated_obj_loads_as_the_reference_says_or_fails_clearly(tmp_path_factory, lines,
                                                                      cut, latin1):  # fmt: skip
    text = "\n".join(lines) + "\n"
    text = text[: len(text) - cut] if cut else text  # truncation
    data = text.encode("utf-8") + (b"# \xe9\n" if latin1 else b"")
    path = tmp_path_factory.mktemp("obj") / "g.obj"
    path.write_bytes(data)
    expected = reference_triangles(data.decode("latin-1"))
    try:
        meshes = load_mesh(path)
    except ValueError as err:
        assert str(path) in str(err)
        # Refused: the reference must also find it invalid, or find no triangle in it.
        assert expected is None or len(expected) == 0, f"refused a valid file: {err}"
        return
    assert expected is not None, "loaded a file the reference parse rejects"
    loaded = np.concatenate([m.triangles() for m in meshes])
    key = lambda t: sorted(map(tuple, np.round(t.reshape(-1, 3, 3).tolist(), 9)))  # noqa: E731
    assert sorted(map(key, loaded)) == sorted(map(key, expected))
