"""Command-line interface: acap encode/decode round trip, render, and one-line errors with nothing written."""

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from jaxdeform.cli import main
from jaxdeform.data.synthetic import bending_tube_sequence
from jaxdeform.mesh.io import save_mesh

# 32 rings rather than 16: at the full 1.15-turn bend, 16 rings turn the tangent by ~0.48 rad per ring, and
# ACAP's plain least-squares reconstruction (edges mapped by the averaged gradients (T_i + T_j) / 2) then
# shrinks the tube by ~4%: 2.2% of the bbox diagonal at the last frame (0.76% with one refinement step).
# With 32 rings it stays under 0.6% even without refinement, so the 1% tolerance below has a margin.
N_FRAMES, N_AROUND, N_ALONG = 4, 8, 32
NV = N_AROUND * N_ALONG


@pytest.fixture(scope="module")
def tube():
    return bending_tube_sequence(n_frames=N_FRAMES, n_around=N_AROUND, n_along=N_ALONG)


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory, tube):
    """A folder frame0.obj .. frame3.obj (natural order) of the small bending tube."""
    vertices, faces = tube
    d = tmp_path_factory.mktemp("seq")
    for k in range(N_FRAMES):
        save_mesh(d / f"frame{k}.obj", vertices[k], faces)
    return d


@pytest.fixture(scope="module")
def encoded(tmp_path_factory, seq_dir):
    """Features of the tube, encoded once (temporal consistency) for the tests that read them."""
    out = tmp_path_factory.mktemp("enc") / "f.npz"
    assert (
        main(
            [
                "acap",
                "encode",
                str(seq_dir),
                "--reference",
                str(seq_dir / "frame0.obj"),
                "--out",
                str(out),
                "--consistency",
                "temporal",
            ]
        )
        == 0
    )
    return out


def centred(x):
    return x - x.mean(axis=-2, keepdims=True)


def diag(x):
    return float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))


def assert_one_line_error(capsys, rc, *absent):
    """rc 2, exactly one non-empty 'jaxdeform: error: ...' line on stderr, and none of ``absent`` exists."""
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and len(err.strip().splitlines()) == 1, err
    assert lines[0].startswith("jaxdeform: error: ") and len(lines[0]) > len("jaxdeform: error: ") + 5, err
    for path in absent:
        assert not Path(path).exists(), path
        leftovers = [p.name for p in Path(path).parent.iterdir() if p.name.startswith(f".{Path(path).name}.")]
        assert not leftovers, leftovers
    return lines[0]


# ------------------------------------------------------------------------------------------ success


def test_encode_writes_every_array(encoded, tube, capsys):
    vertices, faces = tube
    with np.load(encoded, allow_pickle=False) as d:
        data = {k: d[k] for k in d.files}
    assert data["log_r"].shape == (N_FRAMES, NV, 3, 3)
    assert data["s"].shape == (N_FRAMES, NV, 3, 3)
    assert data["features"].shape == (N_FRAMES, NV, 9)
    assert data["scaled"].shape == (N_FRAMES, NV, 9)
    assert data["scaler"].shape == (4,)
    assert data["faces"].shape == faces.shape and data["faces"].dtype == np.int32
    np.testing.assert_array_equal(data["faces"], faces)
    np.testing.assert_allclose(data["reference"], vertices[0], atol=1e-8)
    assert data["consistency"].shape == () and str(data["consistency"]) == "temporal"
    assert data["weighting"].shape == () and str(data["weighting"]) == "official"
    assert np.all(np.abs(data["scaled"]) <= 0.95)
    # log R is skew and matches the feature layout (logR_01, logR_02, logR_12).
    log_r = data["log_r"]
    np.testing.assert_allclose(log_r, -np.swapaxes(log_r, -1, -2), atol=1e-12)
    np.testing.assert_allclose(data["features"][..., :3], log_r[..., [0, 0, 1], [1, 2, 2]], atol=1e-12)
    # The rest frame has identity deformation: no rotation, S = I.
    np.testing.assert_allclose(data["s"][0], np.broadcast_to(np.eye(3), (NV, 3, 3)), atol=1e-6)
    np.testing.assert_allclose(log_r[0], 0.0, atol=1e-6)


def test_encode_prints_one_summary_line(seq_dir, tmp_path, capsys):
    out = tmp_path / "g.npz"
    files = [str(seq_dir / f"frame{k}.obj") for k in range(N_FRAMES)]
    rc = main(
        ["acap", "encode", *files, "--reference", files[0], "--out", str(out), "--float32", "--consistency", "spatial"]
    )
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    lines = captured.out.strip().splitlines()
    assert len(lines) == 1 and "rad" in lines[0] and str(out) in lines[0]
    with np.load(out) as d:
        assert d["features"].dtype == np.float32 and d["features"].shape == (N_FRAMES, NV, 9)
        assert str(d["consistency"]) == "spatial"


def test_encode_warns_of_zero_area_reference_faces(tube, tmp_path, capsys):
    """A reference with a zero-area face encodes with one warning line naming the face as the file counts it."""
    vertices, faces = tube
    ref = vertices[0].copy()
    a, b, c = faces[6]
    ref[c] = 0.5 * (ref[a] + ref[b])  # face 6 (the file's 7th) collapses onto its edge a-b
    save_mesh(tmp_path / "ref.npz", ref, faces)  # exact: an OBJ would round the collapsed vertex off the edge
    save_mesh(tmp_path / "f1.obj", vertices[1], faces)
    out = tmp_path / "f.npz"
    assert (
        main(["acap", "encode", str(tmp_path / "f1.obj"), "--reference", str(tmp_path / "ref.npz"), "--out", str(out)])
        == 0
    )
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("warning: ") and "face 7, counting from 1" in err[0], err
    assert out.is_file()


def test_decode_round_trip(encoded, tube, tmp_path, capsys):
    vertices, faces = tube
    out = tmp_path / "dec"
    assert main(["acap", "decode", str(encoded), "--out", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [".jaxdeform"] + [f"{k:03d}.obj" for k in range(N_FRAMES)]  # the frames and the output marker
    names = names[1:]
    from jaxdeform.mesh.io import load_mesh

    for k, name in enumerate(names):
        v, f = load_mesh(out / name)
        np.testing.assert_array_equal(f, faces)
        err = np.linalg.norm(centred(v) - centred(vertices[k]), axis=-1).max()
        assert err < 1e-2 * diag(vertices[k]), (k, err)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_decode_refuses_absurd_features(encoded, tmp_path, capsys):
    """Features scaled by 1e30 decode to coordinates of 1e30: refused (one sentence), nothing written."""
    with np.load(encoded) as d:
        data = {k: d[k] for k in d.files}
    data["features"] = data["features"] * 1e30
    huge = tmp_path / "huge.npz"
    np.savez(huge, **data)
    out = tmp_path / "dec"
    line = assert_one_line_error(capsys, main(["acap", "decode", str(huge), "--out", str(out)]), out)
    assert "reference sizes away" in line and "nothing was written" in line


def test_decode_from_scaled_with_anchors(encoded, tube, tmp_path, capsys):
    """Without 'features' the decoder inverse-scales 'scaled' with 'scaler'; anchors (two vertices of the fixed
    end ring, which never moves) are held at their reference positions."""
    vertices, _ = tube
    with np.load(encoded) as d:
        data = {k: d[k] for k in d.files if k != "features"}
    scaled_only = tmp_path / "scaled.npz"
    np.savez(scaled_only, **data)
    out = tmp_path / "dec"
    assert main(["acap", "decode", str(scaled_only), "--out", str(out), "--anchors", "0", "3", "--refine", "0"]) == 0
    from jaxdeform.mesh.io import load_mesh

    v, _ = load_mesh(out / "003.obj")
    err = np.linalg.norm(centred(v) - centred(vertices[3]), axis=-1).max()
    assert err < 1e-2 * diag(vertices[3])
    np.testing.assert_allclose(v[[0, 3]], vertices[3][[0, 3]], atol=1e-3 * diag(vertices[3]))


def test_decode_two_components_anchors_each(tube, tmp_path, capfd):
    """A mesh of two disjoint tubes decodes with one anchor per component chosen automatically (and says so);
    anchors that leave a component free are refused in one sentence naming --anchors, with nothing on stdout."""
    vertices, faces = tube
    shift = np.array([0.0, 0.0, 3.0])
    both = np.concatenate([vertices, vertices[:, ::-1] * 0.7 + shift], axis=1)  # the copy bends the other way
    two_faces = np.concatenate([faces, faces + NV])
    seq = tmp_path / "seq"
    for k in range(N_FRAMES):
        save_mesh(seq / f"f{k}.obj", both[k], two_faces)
    enc = tmp_path / "f.npz"
    assert main(["acap", "encode", str(seq), "--reference", str(seq / "f0.obj"), "--out", str(enc)]) == 0
    capfd.readouterr()
    out = tmp_path / "dec"
    assert main(["acap", "decode", str(enc), "--out", str(out)]) == 0
    said = capfd.readouterr().out
    assert f"2 connected components, one anchored at its lowest vertex: 0 {NV}" in said
    from jaxdeform.mesh.io import load_mesh

    for k in range(N_FRAMES):
        v, _ = load_mesh(out / f"{k:03d}.obj")
        for part in (slice(0, NV), slice(NV, 2 * NV)):  # each component's shape, up to its translation
            err = np.abs(centred(v[part]) - centred(both[k][part])).max()
            assert err < 1e-2 * diag(both[k][part]), (k, err)
    bad = tmp_path / "bad"
    rc = main(["acap", "decode", str(enc), "--out", str(bad), "--anchors", "0", "5"])
    captured = capfd.readouterr()
    lines = [ln for ln in captured.err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and "--anchors" in lines[0] and "2 connected components" in lines[0], lines
    assert captured.out == "" and not bad.exists()


def test_decode_refuses_non_empty_folder_unless_forced(encoded, tmp_path, capsys):
    """A non-empty --out needs --force, and --force replaces only a folder jaxdeform wrote (it holds the marker):
    a folder of the user's own files survives it, subfolder included."""
    out = tmp_path / "dec"
    (out / "sub").mkdir(parents=True)
    (out / "keep.txt").write_text("mine")
    (out / "sub" / "notes.txt").write_text("mine too")
    rc = main(["acap", "decode", str(encoded), "--out", str(out)])
    assert_one_line_error(capsys, rc)
    rc = main(["acap", "decode", str(encoded), "--out", str(out), "--force"])
    assert "did not write" in assert_one_line_error(capsys, rc)
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt", "sub"]
    assert (out / "sub" / "notes.txt").read_text() == "mine too"
    ours = tmp_path / "ours"
    assert main(["acap", "decode", str(encoded), "--out", str(ours)]) == 0
    (ours / "000.obj").write_text("stale")
    assert main(["acap", "decode", str(encoded), "--out", str(ours), "--force"]) == 0  # jaxdeform's own: replaced
    assert sorted(p.name for p in ours.iterdir()) == [".jaxdeform"] + [f"{k:03d}.obj" for k in range(N_FRAMES)]
    assert (ours / "000.obj").read_text() != "stale"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dec", "ours"]
    # An existing empty folder is fine without --force.
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["acap", "decode", str(encoded), "--out", str(empty)]) == 0
    assert len(list(empty.iterdir())) == N_FRAMES + 1


def test_render_plain_and_with_scalar(seq_dir, tmp_path, capsys):
    mesh = seq_dir / "frame3.obj"
    plain = tmp_path / "plain.png"
    assert main(["render", str(mesh), "--out", str(plain), "--width", "160", "--height", "120"]) == 0
    with Image.open(plain) as im:
        assert im.size == (160, 120)
        rgb = np.asarray(im.convert("RGB")).reshape(-1, 3)
    assert len(np.unique(rgb, axis=0)) > 2  # background plus shaded mesh

    scalar = tmp_path / "s.npy"
    np.save(scalar, np.linspace(0.0, 1.0, NV))
    coloured = tmp_path / "coloured.png"
    assert (
        main(
            [
                "render",
                str(mesh),
                "--scalar",
                str(scalar),
                "--out",
                str(coloured),
                "--width",
                "200",
                "--height",
                "150",
                "--azimuth",
                "0",
                "--elevation",
                "30",
                "--cmap",
                "coolwarm",
                "--label",
                "t",
            ]
        )
        == 0
    )
    with Image.open(coloured) as im:
        assert im.size == (200, 150)
        rgb = np.asarray(im.convert("RGB")).astype(int)
    # coolwarm: both bluish and reddish pixels appear.
    assert np.any((rgb[..., 2] - rgb[..., 0]) > 60) and np.any((rgb[..., 0] - rgb[..., 2]) > 60)


# ------------------------------------------------------------------------------------------- errors


def _obj_text(vertices, faces):
    return "".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in vertices) + "".join(
        f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces
    )


@pytest.fixture
def bad_inputs(tmp_path, tube):
    """Named broken inputs, each a list of encode INPUT paths (good frames plus one bad file)."""
    vertices, faces = tube
    good = [tmp_path / f"good{k}.obj" for k in range(2)]
    for k, p in enumerate(good):
        save_mesh(p, vertices[k], faces)
    text = _obj_text(vertices[1], faces)
    cases = {}

    def add(name, filename, content):
        p = tmp_path / filename
        p.write_text(content)
        cases[name] = [*map(str, good), str(p)]

    changed = faces.copy()
    changed[0] = changed[0, ::-1]  # one triangle flipped: same counts, different faces
    add("changed_faces", "changed.obj", _obj_text(vertices[1], changed))
    v_small, f_small = bending_tube_sequence(n_frames=2, n_around=N_AROUND, n_along=N_ALONG - 1)
    add("vertex_count", "fewer.obj", _obj_text(v_small[1], f_small))
    lines = text.splitlines(keepends=True)
    add("nan", "nan.obj", "v nan 0 0\n" + "".join(lines[1:]))
    add("empty", "empty.obj", "")
    add("blank", "blank.obj", "\n  \n")
    add("unknown_ext", "mesh.xyz", text)
    vblock_end = text.index("f ")
    add("cut_vertex_block", "cut_v.obj", text[: vblock_end // 2])
    mid = len(lines) // 4  # a vertex line: keep 'v x y' of it (cut before the third number)
    assert lines[mid].startswith("v ")
    add("cut_vertex_line", "cut_vl.obj", "".join(lines[:mid]) + " ".join(lines[mid].split()[:3]))
    last_face = text.rindex("\nf ") + 1
    first, second = text[last_face:].split()[1:3]
    add("cut_face_line", "cut_f.obj", text[:last_face] + f"f {first} {second}")
    add("not_numeric", "junk.obj", text.replace("v ", "v abc ", 1))
    cases["missing"] = [*map(str, good), str(tmp_path / "missing.obj")]
    cases["missing_folder"] = [*map(str, good), str(tmp_path / "no_such_folder")]
    return cases, good


@pytest.mark.parametrize(
    "case",
    [
        "changed_faces",
        "vertex_count",
        "nan",
        "empty",
        "blank",
        "unknown_ext",
        "cut_vertex_block",
        "cut_vertex_line",
        "cut_face_line",
        "not_numeric",
        "missing",
        "missing_folder",
    ],
)
def test_encode_bad_input(bad_inputs, tmp_path, capsys, case):
    cases, good = bad_inputs
    out = tmp_path / "out.npz"
    rc = main(["acap", "encode", *cases[case], "--reference", str(good[0]), "--out", str(out)])
    line = assert_one_line_error(capsys, rc, out)
    if case in ("missing", "missing_folder", "unknown_ext", "changed_faces", "vertex_count", "nan"):
        assert Path(cases[case][-1]).name in line, line


def test_encode_bad_reference(bad_inputs, tmp_path, tube, capsys):
    cases, good = bad_inputs
    out = tmp_path / "out.npz"
    # A reference whose connectivity differs from the (consistent) inputs.
    for ref in (cases["changed_faces"][-1], cases["vertex_count"][-1]):
        rc = main(["acap", "encode", *map(str, good), "--reference", ref, "--out", str(out)])
        line = assert_one_line_error(capsys, rc, out)
        assert "reference" in line and Path(ref).name in line, line
    # A broken or missing reference.
    for ref in (cases["nan"][-1], cases["empty"][-1], str(tmp_path / "nope.obj")):
        rc = main(["acap", "encode", *map(str, good), "--reference", ref, "--out", str(out)])
        assert_one_line_error(capsys, rc, out)


def test_encode_out_is_a_folder(bad_inputs, tmp_path, capsys):
    _, good = bad_inputs
    folder = tmp_path / "adir"
    folder.mkdir()
    rc = main(["acap", "encode", *map(str, good), "--reference", str(good[0]), "--out", str(folder)])
    assert_one_line_error(capsys, rc)
    assert folder.is_dir() and not list(folder.iterdir())


def test_decode_bad_input(encoded, tmp_path, capsys):
    out = tmp_path / "dec"
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip archive")
    with np.load(encoded) as d:
        data = {k: d[k] for k in d.files}
    no_features = tmp_path / "nofeat.npz"
    np.savez(no_features, reference=data["reference"], faces=data["faces"])
    wrong_v = tmp_path / "wrongv.npz"
    np.savez(wrong_v, features=data["features"][:, :-1], reference=data["reference"], faces=data["faces"])
    nan = tmp_path / "nan.npz"
    feats = data["features"].copy()
    feats[1, 3, 4] = np.nan
    np.savez(nan, features=feats, reference=data["reference"], faces=data["faces"])
    for path in (tmp_path / "missing.npz", junk, no_features, wrong_v, nan):
        rc = main(["acap", "decode", str(path), "--out", str(out)])
        assert_one_line_error(capsys, rc, out)
    rc = main(["acap", "decode", str(encoded), "--out", str(out), "--anchors", str(NV)])
    assert_one_line_error(capsys, rc, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["junk.npz", "nofeat.npz", "wrongv.npz", "nan.npz"])


def test_render_bad_input(seq_dir, tmp_path, capsys):
    mesh = seq_dir / "frame1.obj"
    out = tmp_path / "r.png"
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.zeros(NV - 1))
    nan = tmp_path / "nan.npy"
    s = np.zeros(NV)
    s[5] = np.nan
    np.save(nan, s)
    text = tmp_path / "text.npy"
    text.write_text("hello")
    for extra in (
        ["--scalar", str(wrong)],
        ["--scalar", str(nan)],
        ["--scalar", str(text)],
        ["--scalar", str(tmp_path / "none.npy")],
    ):
        rc = main(["render", str(mesh), "--out", str(out), "--width", "64", "--height", "48", *extra])
        assert_one_line_error(capsys, rc, out)
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    for m in (empty, tmp_path / "missing.obj", tmp_path / "m.xyz"):
        rc = main(["render", str(m), "--out", str(out)])
        assert_one_line_error(capsys, rc, out)
    rc = main(["render", str(mesh), "--out", str(out), "--width", "0"])
    assert_one_line_error(capsys, rc, out)
    rc = main(["render", str(mesh), "--out", str(out), "--width", "200000", "--height", "200000"])
    assert "at most" in assert_one_line_error(capsys, rc, out)


def test_output_files_never_replace_an_input(seq_dir, encoded, tmp_path, capsys):
    """An output file equal to an input, added to an input folder, or in another format is refused untouched."""
    mesh = tmp_path / "m.obj"
    mesh.write_bytes((seq_dir / "frame1.obj").read_bytes())
    copy = tmp_path / "f.npz"
    copy.write_bytes(encoded.read_bytes())
    before = {p: p.read_bytes() for p in (mesh, copy)}
    ref = ["--reference", str(seq_dir / "frame0.obj")]
    cases = {
        "encode over its input": ["acap", "encode", str(copy), *ref, "--out", str(copy)],
        "encode over its reference": ["acap", "encode", str(seq_dir), "--reference", str(mesh), "--out", str(mesh)],
        "encode into its input folder": ["acap", "encode", str(seq_dir), *ref, "--out", str(seq_dir / "x.npz")],
        "encode to another format": ["acap", "encode", str(seq_dir), *ref, "--out", str(tmp_path / "x.obj")],
        "render over its mesh": ["render", str(mesh), "--out", str(mesh)],
        "render to jpeg": ["render", str(mesh), "--out", str(tmp_path / "x.jpg")],
    }
    for name, argv in cases.items():
        rc = main(argv)
        line = assert_one_line_error(capsys, rc)
        assert "--out" in line, (name, line)
    assert {p: p.read_bytes() for p in (mesh, copy)} == before
    assert not (seq_dir / "x.npz").exists() and not (tmp_path / "x.jpg").exists()
    assert not (tmp_path / "x.obj").exists()


def test_decode_bad_frames_and_scaled(encoded, tmp_path, capsys):
    """No frames, or a 'scaled' array of the wrong type or width, gets one sentence naming the file."""
    with np.load(encoded) as d:
        data = {k: d[k] for k in d.files}
    base = {"reference": data["reference"], "faces": data["faces"]}
    cases = {
        "no_frames.npz": {"features": data["features"][:0], **base},
        "text_scaled.npz": {"scaled": data["scaled"].astype(str), "scaler": data["scaler"], **base},
        "narrow_scaled.npz": {"scaled": data["scaled"][..., :5], "scaler": data["scaler"], **base},
    }
    out = tmp_path / "dec"
    for name, arrays in cases.items():
        np.savez(tmp_path / name, **arrays)
        rc = main(["acap", "decode", str(tmp_path / name), "--out", str(out)])
        assert name in assert_one_line_error(capsys, rc, out)


def test_encode_refuses_a_sequence_without_shapes(seq_dir, tmp_path, tube, capsys):
    _, faces = tube
    empty = tmp_path / "none.npz"
    np.savez(empty, vertices=np.zeros((0, NV, 3)), faces=faces)
    out = tmp_path / "e.npz"
    rc = main(["acap", "encode", str(empty), "--reference", str(seq_dir / "frame0.obj"), "--out", str(out)])
    assert "no shapes" in assert_one_line_error(capsys, rc, out)


def test_out_folder_under_a_file(encoded, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("keep")
    rc = main(["acap", "decode", str(encoded), "--out", str(blocker / "sub")])
    assert "is a file, not a folder" in assert_one_line_error(capsys, rc)
    assert blocker.read_text() == "keep"


def test_render_refuses_a_non_finite_angle(seq_dir, tmp_path, capsys):
    out = tmp_path / "r.png"
    rc = main(["render", str(seq_dir / "frame1.obj"), "--out", str(out), "--azimuth", "nan"])
    line = assert_one_line_error(capsys, rc, out)
    assert "azimuth" in line and "np.float64" not in line, line


def test_usage_errors_exit_2(capsys):
    for argv in (
        [],
        ["acap"],
        ["acap", "encode", "x.obj"],
        ["render"],
        ["acap", "encode", "a.obj", "--reference", "a.obj", "--out", "f.npz", "--consistency", "sometimes"],
    ):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
    assert "usage:" in capsys.readouterr().err


def test_console_script_and_module():
    exe = Path(sys.executable).with_name("jaxdeform")
    cmd = [str(exe), "--help"] if exe.exists() else [sys.executable, "-m", "jaxdeform", "--help"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "acap" in res.stdout and "render" in res.stdout


def test_help_imports_no_jax_or_numpy_and_names_every_method():
    """--help (top-level and per method) in a fresh process imports neither JAX nor NumPy, and the top-level
    description names the six methods."""
    methods = ("acap", "render", "parts", "components", "handles", "cloth")
    code = textwrap.dedent(f"""
        import contextlib, io, sys
        from jaxdeform.cli import main
        top = io.StringIO()
        with contextlib.redirect_stdout(top), contextlib.suppress(SystemExit):
            main(["--help"])
        for method in {methods!r}:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
                main([method, "--help"])
        heavy = [m for m in sys.modules if m.split(".")[0] in ("jax", "jaxlib", "jaxtyping", "numpy", "scipy", "flax")]
        assert not heavy, sorted(set(m.split(".")[0] for m in heavy))
        print(top.getvalue())
    """)
    res = subprocess.run(
        [sys.executable, "-c", code],
        cwd=Path(__file__).resolve().parents[1],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    description = " ".join(res.stdout.split("positional arguments:")[0].split())
    for method in methods:
        assert f"{method} (" in description, (method, description)
