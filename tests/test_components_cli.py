"""`jaxdeform components train|evaluate|show`: a whole run on a small synthetic sequence, and bad input."""

import json

import numpy as np
import pytest
from PIL import Image

from jaxdeform.cli import main
from jaxdeform.components import run
from jaxdeform.data.synthetic import bending_tube_sequence
from jaxdeform.mesh.io import save_mesh

N_FRAMES = 12


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    vertices, faces = bending_tube_sequence(n_frames=N_FRAMES, n_around=8, n_along=16)
    d = tmp_path_factory.mktemp("tube")
    for k in range(N_FRAMES):
        save_mesh(d / f"f{k}.obj", vertices[k], faces)
    return d


def _one_line_error(capsys, rc):
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("jaxdeform: error: "), err
    return lines[0]


@pytest.mark.parametrize("method", ["multiscale", "pca", "splocs"])
def test_train_evaluate_show(seq_dir, tmp_path, capsys, method):
    out = tmp_path / "run"
    assert (
        main(
            [
                "components",
                "train",
                str(seq_dir),
                "--out",
                str(out),
                "--method",
                method,
                "--config",
                "test",
                "--epochs",
                "20",
                "--quiet",
            ]
        )
        == 0
    )
    rec = json.loads((out / "run.json").read_text())
    assert rec["split"]["train"] == [0, 10] and len(rec["split"]["test"]) == N_FRAMES - 2
    assert main(["components", "evaluate", str(out), "--data", str(seq_dir), "--json", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    first = bending_tube_sequence(n_frames=N_FRAMES, n_around=8, n_along=16)[0][0]  # the data set's shape 0
    r0 = np.linalg.norm(first - first.mean(axis=0), axis=-1).max()
    for part in ("train", "test"):
        assert np.isfinite(m[part]["erms"]) and np.isfinite(m[part]["sted"]) and m[part]["erms"] >= 0
        by = m[part]["erms_by_normalization"]  # the three readings side by side, the headline one among them
        assert by["radius"] == pytest.approx(m[part]["erms"], rel=1e-12)
        assert by["diameter-first-shape"] == pytest.approx(by["raw"] / (2 * r0), rel=1e-6)
    if method != "splocs":
        assert 0 <= m["test"]["max_relative_squared_error"] < 10
    if method == "pca":  # PCA spans its training features exactly; positions then differ only by the ACAP solve
        assert m["train"]["max_relative_squared_error"] < 1e-8
        assert m["train"]["erms"] < 0.05 * m["test"]["erms"]
    assert main(["components", "show", str(out), "--out", str(tmp_path / "fig"), "--up", "z"]) == 0
    for name in ("components.png", "similarity.png"):
        with Image.open(tmp_path / "fig" / name) as im:
            assert im.size[0] > 50 and im.size[1] > 50
    info = json.loads((tmp_path / "fig" / "components.json").read_text())
    assert info["components"] >= info["n_kept"] >= 1 and info["up_axis"] == "z"
    loaded = run.load(out)
    assert loaded.method == method and loaded.rest.shape == (8 * 16, 3)
    if method != "splocs":  # ACAP methods: branch reference and clipped scaler stored, and used on new shapes
        assert loaded.turns.shape == (8 * 16, 3) and loaded.scaler.quantile == run.SCALE_QUANTILE
        shapes = run.load_data(seq_dir)[0][:3]
        from jaxdeform import acap

        feats = acap.align_turns(acap.encode(loaded.rest, loaded.faces, shapes), loaded.turns)
        np.testing.assert_allclose(
            np.asarray(run.scaled_features(loaded, shapes)),
            np.asarray(loaded.scaler.transform(np.asarray(feats, np.float32))),
            atol=1e-6,
        )
    # edit: pull three vertices to a test shape's positions; the control residual falls below the start's
    from jaxdeform.mesh.io import load_mesh

    target, _ = load_mesh(seq_dir / "f5.obj")
    idx = [0, 60, 127]
    (tmp_path / "c.json").write_text(json.dumps({"indices": idx, "targets": target[idx].tolist()}))
    assert (
        main(["components", "edit", str(out), "--controls", str(tmp_path / "c.json"), "--out", str(tmp_path / "e.obj")])
        == 0
    )
    edited, _ = load_mesh(tmp_path / "e.obj")
    assert edited.shape == loaded.rest.shape and np.all(np.isfinite(edited))
    if method in run.ACAP_METHODS:  # default objective "deformation": the controls are held at their targets
        diag = np.linalg.norm(np.ptp(loaded.rest, axis=0))
        assert np.linalg.norm(edited[idx] - target[idx], axis=1).max() < 1e-3 * diag
    if method == "pca":  # the other objective (one ACAP method suffices: the editor's compile is the cost)
        assert (
            main(
                [
                    "components",
                    "edit",
                    str(out),
                    "--controls",
                    str(tmp_path / "c.json"),
                    "--objective",
                    "controls",
                    "--out",
                    str(tmp_path / "e2.obj"),
                ]
            )
            == 0
        )
        fitted, _ = load_mesh(tmp_path / "e2.obj")
        assert np.all(np.isfinite(fitted)) and not np.allclose(fitted, edited)
    if method == "multiscale":  # two levels: coarse to fine by default, --one-stage edits every code at once
        assert "coarse to fine over 2 levels" in capsys.readouterr().out
        assert (
            main(
                [
                    "components",
                    "edit",
                    str(out),
                    "--controls",
                    str(tmp_path / "c.json"),
                    "--one-stage",
                    "--out",
                    str(tmp_path / "e1.obj"),
                ]
            )
            == 0
        )
        assert "coarse to fine" not in capsys.readouterr().out
        one, _ = load_mesh(tmp_path / "e1.obj")  # three controls: both orders can meet them, so meshes may agree
        assert one.shape == edited.shape and np.all(np.isfinite(one))


def test_latent_tanh_config_round_trips(seq_dir, tmp_path):
    out = tmp_path / "run"
    assert (
        main(
            [
                "components",
                "train",
                str(seq_dir),
                "--out",
                str(out),
                "--config",
                "test-latent-tanh",
                "--epochs",
                "10",
                "--quiet",
            ]
        )
        == 0
    )
    loaded = run.load(out)
    assert loaded.config.latent == "tanh" and loaded.config.kz == (3, 2)
    rec = run.reconstruct(loaded, run.load_data(seq_dir)[0][loaded.test_idx])
    assert np.all(np.isfinite(rec["positions"]))
    # the codes the run's model gives are tanh outputs
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn.graph_conv import rings_from_topology

    rings = rings_from_topology(build_topology(loaded.faces, loaded.rest.shape[0]))
    codes = loaded.model.encode(rec["scaled"].astype(np.float32), rings)
    assert all(float(np.abs(np.asarray(z)).max()) < 1.0 for z in codes)


def test_train_needs_two_shapes(seq_dir, tmp_path, capsys):
    out = tmp_path / "run"
    line = _one_line_error(capsys, main(["components", "train", str(seq_dir / "f0.obj"), "--out", str(out)]))
    assert "at least 2 shapes" in line
    assert not out.exists()


def test_train_refuses_mixed_connectivity(seq_dir, tmp_path, capsys):
    vertices, faces = bending_tube_sequence(n_frames=2, n_around=8, n_along=16)
    d = tmp_path / "mixed"
    d.mkdir()
    save_mesh(d / "a.obj", vertices[0], faces)
    save_mesh(d / "b.obj", vertices[1], faces[:, [0, 2, 1]])
    out = tmp_path / "run"
    _one_line_error(capsys, main(["components", "train", str(d), "--out", str(out), "--config", "test"]))
    assert not out.exists()


def test_bad_names_and_mismatched_data(seq_dir, tmp_path, capsys):
    out = tmp_path / "run"
    line = _one_line_error(capsys, main(["components", "train", str(seq_dir), "--out", str(out), "--config", "huge"]))
    assert "no config 'huge'" in line and not out.exists()
    line = _one_line_error(
        capsys, main(["components", "train", str(seq_dir), "--out", str(out), "--scale-quantile", "0.5"])
    )
    assert "--scale-quantile" in line and not out.exists()
    _one_line_error(capsys, main(["components", "evaluate", str(tmp_path), "--data", str(seq_dir)]))
    assert (
        main(["components", "train", str(seq_dir), "--out", str(out), "--method", "pca", "--config", "test", "--quiet"])
        == 0
    )
    capsys.readouterr()
    line = _one_line_error(
        capsys, main(["components", "evaluate", str(out), "--data", str(seq_dir / "f0.obj"), str(seq_dir / "f1.obj")])
    )
    assert "same data" in line


def _train_pca_xyz(seq_dir, out, capsys):
    """A quick pca-xyz run (test config) in ``out``; its output is read off."""
    assert (
        main(
            ["components", "train", str(seq_dir), "--out", str(out), "--method", "pca-xyz"]
            + ["--config", "test", "--quiet"]
        )
        == 0
    )
    capsys.readouterr()
    return out


def test_evaluate_refuses_other_data_and_damaged_records(seq_dir, tmp_path, capsys):
    """A run knows its data: the same count and connectivity but other shapes (all scaled by 1e-8, or one shape
    moved) are refused, naming what differs; a record with a split index out of range, a negative one, or an
    autoencoder method without its configuration is refused in one sentence."""
    from jaxdeform.mesh.io import load_mesh

    out = _train_pca_xyz(seq_dir, tmp_path / "run", capsys)
    for case, change in (("scaled", lambda k, v: v * 1e-8), ("moved", lambda k, v: v * (1.1 if k == 7 else 1.0))):
        other = tmp_path / case
        other.mkdir()
        for k in range(N_FRAMES):
            v, f = load_mesh(seq_dir / f"f{k}.obj")
            save_mesh(other / f"f{k}.obj", change(k, v), f)
        line = _one_line_error(capsys, main(["components", "evaluate", str(out), "--data", str(other)]))
        assert "not the data the run was fitted on" in line and ("shape 0" if case == "scaled" else "shape 7") in line
    # the data itself still evaluates
    assert main(["components", "evaluate", str(out), "--data", str(seq_dir)]) == 0
    capsys.readouterr()
    record = json.loads((out / "run.json").read_text())
    for damage, expect in (("test", "split.test holds 99"), ("train", "split.train holds -1"), ("method", "config")):
        bad = json.loads(json.dumps(record))
        if damage == "test":
            bad["split"]["test"].append(99)
        elif damage == "train":
            bad["split"]["train"][0] = -1
        else:
            bad["method"] = "multiscale"
        (out / "run.json").write_text(json.dumps(bad))
        for argv in (["evaluate", str(out), "--data", str(seq_dir)], ["show", str(out), "--out", str(tmp_path / "s")]):
            line = _one_line_error(capsys, main(["components", *argv]))
            assert expect in line and "run.json" in line, line
            assert not (tmp_path / "s").exists()


def test_edit_bad_controls(seq_dir, tmp_path, capsys):
    out = _train_pca_xyz(seq_dir, tmp_path / "run", capsys)
    (tmp_path / "bad.json").write_text(json.dumps({"indices": [0, 9999], "targets": [[0, 0, 0], [1, 1, 1]]}))
    _one_line_error(
        capsys,
        main(
            ["components", "edit", str(out), "--controls", str(tmp_path / "bad.json"), "--out", str(tmp_path / "e.obj")]
        ),
    )
    (tmp_path / "far.json").write_text(json.dumps({"indices": [0, 5], "targets": [[0, 0, 0], [0, 1e300, 0]]}))
    line = _one_line_error(
        capsys,
        main(
            ["components", "edit", str(out), "--controls", str(tmp_path / "far.json"), "--out", str(tmp_path / "e.obj")]
        ),
    )
    assert "far.json" in line and "mesh's size" in line and not (tmp_path / "e.obj").exists()
    (tmp_path / "bad.txt").write_text("0 1 2\n")
    _one_line_error(
        capsys,
        main(
            ["components", "edit", str(out), "--controls", str(tmp_path / "bad.txt"), "--out", str(tmp_path / "e.obj")]
        ),
    )
    # not vertex numbers: a string, a JSON true (numpy would read it as 1), a float beyond int64, an empty file
    for k, indices in enumerate((["a"], [True], [1e20])):
        (tmp_path / f"bad{k}.json").write_text(json.dumps({"indices": indices, "targets": [[0, 0, 0]]}))
        line = _one_line_error(
            capsys,
            main(
                [
                    "components",
                    "edit",
                    str(out),
                    "--controls",
                    str(tmp_path / f"bad{k}.json"),
                    "--out",
                    str(tmp_path / "e.obj"),
                ]
            ),
        )
        assert "indices" in line, line
    (tmp_path / "empty.txt").write_text("")
    line = _one_line_error(
        capsys,
        main(
            [
                "components",
                "edit",
                str(out),
                "--controls",
                str(tmp_path / "empty.txt"),
                "--out",
                str(tmp_path / "e.obj"),
            ]
        ),
    )
    assert "M >= 1" in line
    assert not (tmp_path / "e.obj").exists()
    # evaluate must not write its JSON over the run's own record; the run still loads afterwards
    line = _one_line_error(
        capsys, main(["components", "evaluate", str(out), "--data", str(seq_dir), "--json", str(out / "run.json")])
    )
    assert "would replace" in line and run.load(out).method == "pca-xyz"
    # ... but metrics written into the run folder may be written again
    for _ in range(2):
        assert main(["components", "evaluate", str(out), "--data", str(seq_dir), "--json", str(out / "m.json")]) == 0
    assert json.loads((out / "m.json").read_text())["method"] == "pca-xyz"
    # show must not replace the run folder it reads
    line = _one_line_error(capsys, main(["components", "show", str(out), "--out", str(out), "--force"]))
    assert "would replace the input" in line and (out / "run.json").is_file()


def test_train_refuses_to_replace_its_data(seq_dir, tmp_path, capsys):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(seq_dir, data)
    for out in (data, tmp_path):  # the data folder itself, or a folder holding it, with --force
        line = _one_line_error(
            capsys, main(["components", "train", str(data), "--out", str(out), "--force", "--method", "pca", "--quiet"])
        )
        assert "would replace the input" in line
    assert len(list(data.glob("*.obj"))) == N_FRAMES
    line = _one_line_error(
        capsys,
        main(["components", "train", str(data), "--out", str(tmp_path / "r"), "--split", "half", "--split-seed", "-1"]),
    )
    assert "--split-seed" in line and not (tmp_path / "r").exists()


def test_train_refuses_degenerate_meshes(tmp_path, capsys):
    vertices, faces = bending_tube_sequence(n_frames=3, n_around=8, n_along=16)
    a, b = faces[0, :2]
    vertices[:, b] = vertices[:, a]  # the two ends of an edge coincide in every shape
    d = tmp_path / "degenerate"
    d.mkdir()
    for k in range(3):
        save_mesh(d / f"f{k}.obj", vertices[k], faces)
    out = tmp_path / "run"
    line = _one_line_error(capsys, main(["components", "train", str(d), "--out", str(out), "--method", "pca"]))
    assert "zero-length edge" in line and f"vertices {a} and {b}" in line
    assert not out.exists() and not list(tmp_path.glob(".run*"))
    # a zero-area face with edges of positive length (three collinear corners) in the rest shape
    flat = np.array([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [1, 1, 0]]] * 2)
    with pytest.raises(run.DegenerateMeshError, match="zero-area face"):
        run.check_nondegenerate(flat, np.array([[0, 1, 3], [0, 2, 1]]), "flat")
    run.check_nondegenerate(flat, np.array([[0, 1, 3], [1, 2, 3]]), "fine")  # no error


def test_unreadable_run_records(seq_dir, tmp_path, capsys):
    out = _train_pca_xyz(seq_dir, tmp_path / "run", capsys)
    for text, expected in (
        ("", "not a readable run record"),
        ('{"data": "x"}', "lacks method"),
        ("[1, 2]", "not a components run record"),
    ):
        (out / "run.json").write_text(text)
        line = _one_line_error(capsys, main(["components", "evaluate", str(out), "--data", str(seq_dir)]))
        assert expected in line and "run.json" in line, line


def test_split_indices():
    tr, te = run.split_indices(48)
    assert tr.tolist() == [0, 10, 20, 30, 40] and len(te) == 43 and not set(tr) & set(te)
    tr2, te2 = run.split_indices(19, "half", seed=3)
    assert len(tr2) == 10 and len(te2) == 9 and sorted(tr2.tolist() + te2.tolist()) == list(range(19))
    assert run.split_indices(19, "half", seed=3)[0].tolist() == tr2.tolist()
    tr3, te3 = run.split_indices(7, "all")  # Table 5 as the whole data set's representation error
    assert tr3.tolist() == te3.tolist() == list(range(7))
    with pytest.raises(ValueError, match="at least 2"):
        run.split_indices(1)
    with pytest.raises(ValueError, match="unknown split"):
        run.split_indices(9, "thirds")


def test_stale_reason_compares_the_split():
    """A run trained on one split is not reused for another (experiments' --split)."""
    record = {
        "method": "pca",
        "split": {"mode": "every10"},
        "feature_turns": "aligned",
        "feature_scale_quantile": run.SCALE_QUANTILE,
    }
    assert run.stale_reason(record, "pca", "default") is None
    assert run.stale_reason(record, "pca", "default", split="every10") is None
    assert "every10 split, not all" in run.stale_reason(record, "pca", "default", split="all")


def test_split_all_reports_the_whole_data_set(seq_dir, tmp_path):
    """--split all: every shape trains, and the "test" metrics are the whole data set's, hence the train ones."""
    out = tmp_path / "run"
    assert (
        main(["components", "train", str(seq_dir), "--out", str(out), "--method", "pca", "--split", "all", "--quiet"])
        == 0
    )
    rec = json.loads((out / "run.json").read_text())
    assert rec["split"]["mode"] == "all" and rec["split"]["train"] == rec["split"]["test"] == list(range(N_FRAMES))
    assert main(["components", "evaluate", str(out), "--data", str(seq_dir), "--json", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["test"]["shapes"] == m["train"]["shapes"] == N_FRAMES
    for key in ("erms", "sted", "max_relative_squared_error"):
        assert m["test"][key] == pytest.approx(m["train"][key], rel=1e-9, abs=1e-12)
    # PCA with at least as many components as shapes spans every training feature: eq. 8 vanishes
    assert m["test"]["max_relative_squared_error"] < 1e-8


def test_stale_reason_reads_missing_model_fields_as_their_defaults():
    """A run written before a model option existed is the same run as today's default; another value is not."""
    import dataclasses

    cfg, tc = run.resolve_config("multiscale", "default", None)
    full = run._json_config(cfg)
    record = {
        "method": "multiscale",
        "split": {"mode": "every10"},
        "feature_turns": "aligned",
        "feature_scale_quantile": run.SCALE_QUANTILE,
        "config": full,
        "train_config": dataclasses.asdict(tc),
    }
    assert run.stale_reason(record, "multiscale", "default") is None
    older = {k: v for k, v in full.items() if k not in ("init", "init_std", "tie_conv", "decoder_tanh")}
    assert run.stale_reason({**record, "config": older}, "multiscale", "default") is None
    tied = {**full, "tie_conv": True}
    assert run.stale_reason({**record, "config": tied}, "multiscale", "default") == "its model configuration differs"
