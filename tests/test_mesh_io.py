import numpy as np
import pytest

from jaxdeform.errors import ConnectivityError, MeshFormatError
from jaxdeform.mesh import io

TRI = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]])
FACES = np.array([[0, 1, 2], [1, 3, 2]])


@pytest.mark.parametrize("suffix", [".obj", ".off", ".ply", ".npz"])
def test_save_load_round_trip(tmp_path, suffix):
    path = tmp_path / f"m{suffix}"
    io.save_mesh(path, TRI, FACES)
    v, f = io.load_mesh(path)
    np.testing.assert_allclose(v, TRI, atol=1e-7)
    np.testing.assert_array_equal(f, FACES)
    assert f.dtype == np.int32 and v.dtype == np.float64


def test_obj_polygons_are_fan_triangulated_and_slashes_ignored(tmp_path):
    p = tmp_path / "q.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1/1 2/1/1 3/1/1 4/1/1\n")
    v, f = io.load_mesh(p)
    np.testing.assert_array_equal(f, [[0, 1, 2], [0, 2, 3]])


def test_folder_loads_in_natural_order(tmp_path):
    for k in (10, 2, 1):
        io.save_mesh(tmp_path / f"frame{k}.obj", TRI + k, FACES)
    v, f = io.load_sequence(tmp_path)
    np.testing.assert_allclose(v[:, 0, 0], [1, 2, 10])


def test_sequence_npz_round_trip(tmp_path):
    seq = np.stack([TRI, TRI * 2])
    io.save_sequence(tmp_path / "s.npz", seq, FACES)
    v, f = io.load_sequence(tmp_path / "s.npz")
    np.testing.assert_allclose(v, seq)


def test_different_connectivity_is_rejected(tmp_path):
    io.save_mesh(tmp_path / "a.obj", TRI, FACES)
    io.save_mesh(tmp_path / "b.obj", TRI, FACES[:, ::-1])
    with pytest.raises(ConnectivityError, match="different faces"):
        io.load_sequence([tmp_path / "a.obj", tmp_path / "b.obj"])
    io.save_mesh(tmp_path / "c.obj", np.vstack([TRI, [[2, 2, 2]]]), np.vstack([FACES, [[3, 4, 2]]]))
    with pytest.raises(ConnectivityError, match="vertices"):
        io.load_sequence([tmp_path / "a.obj", tmp_path / "c.obj"])


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "empty"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
        ("v 0 0 0\nv 1 0 0\nv 0 1\n", "truncated"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "fewer than 3"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n", "truncated or corrupt"),
        ("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "NaN"),
        ("v a b c\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "not numeric"),
    ],
)
def test_bad_obj(tmp_path, text, match):
    p = tmp_path / "bad.obj"
    p.write_text(text)
    with pytest.raises(MeshFormatError, match=match):
        io.load_mesh(p)


def test_unknown_extension_and_missing_file(tmp_path):
    with pytest.raises(MeshFormatError, match="unknown mesh format"):
        io.load_mesh(tmp_path / "x.xyz")
    with pytest.raises(MeshFormatError, match="no such file"):
        io.load_mesh(tmp_path / "missing.obj")


@pytest.mark.parametrize(
    "text, match", [("OFF\n4 2 0\n0 0 0\n1 0 0\n", "truncated"), ("# only a comment\n# and another\n", "only comments")]
)
def test_bad_off(tmp_path, text, match):
    p = tmp_path / "t.off"
    p.write_text(text)
    with pytest.raises(MeshFormatError, match=match):
        io.load_mesh(p)


def test_failed_write_leaves_nothing(tmp_path):
    target = tmp_path / "out.obj"
    with pytest.raises(RuntimeError):
        with io.atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_truncated_ascii_ply(tmp_path):
    """trimesh reads a cut ASCII body without complaint; the header's counts catch it."""
    header = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    )
    body = "".join(" ".join(map(str, v)) + "\n" for v in TRI) + "".join(
        "3 " + " ".join(map(str, f)) + "\n" for f in FACES
    )
    whole, cut = tmp_path / "m.ply", tmp_path / "cut.ply"
    whole.write_text(header + body)
    cut.write_text(header + "".join(body.splitlines(keepends=True)[:-1]))  # the last face line dropped
    v, f = io.load_mesh(whole)
    np.testing.assert_array_equal(f, FACES)
    with pytest.raises(MeshFormatError, match="truncated"):
        io.load_mesh(cut)


def test_sequence_npz_without_shapes(tmp_path):
    p = tmp_path / "s.npz"
    np.savez(p, vertices=np.zeros((0, 4, 3)), faces=FACES)
    with pytest.raises(MeshFormatError, match="no shapes"):
        io.load_sequence(p)


def test_sequence_with_a_face_repeating_a_vertex_names_the_file(tmp_path):
    io.save_mesh(tmp_path / "a.obj", TRI, np.array([[0, 1, 2], [1, 3, 3]]))
    with pytest.raises(MeshFormatError, match="a.obj: a face joins the vertices 2, 4 and 4, one of them twice"):
        io.load_sequence(tmp_path)  # numbered as the OBJ file numbers its vertices, from 1


def test_obj_messages_number_vertices_as_the_file_does(tmp_path):
    """Out-of-range and duplicate faces are named in the file's own (1-based) vertex numbers."""
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 10000\n")
    with pytest.raises(MeshFormatError, match="bad.obj: a face refers to vertex 10000 .*numbered 1..3"):
        io.load_mesh(bad)
    dup = tmp_path / "dup.obj"
    dup.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\nf 3 1 2\n")
    with pytest.raises(MeshFormatError, match="dup.obj: two faces join the same vertices 1, 2 and 3"):
        io.load_mesh(dup)
