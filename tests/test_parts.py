"""Seed 003 parts: rotation-constrained MFA (AECM), the hierarchy of Algorithm 1, and the `parts` CLI."""

import json
import shutil

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import data_dir

from jaxdeform.cli import main
from jaxdeform.mesh.io import save_mesh
from jaxdeform.mesh.topology import unique_edges
from jaxdeform.nn.archive import read_tree, save_tree
from jaxdeform.parts import hierarchy, mfa
from jaxdeform.parts import run as prun


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _grid(n=12, offset=(0.0, 0.0, 0.0)):
    """A flat triangulated n x n patch (vertices (n*n, 3), faces)."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), 0.1 * np.sin(3 * u.ravel()) * np.cos(2 * v.ravel())], 1) + offset
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return verts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _two_rigid_parts(m=4, seed=0):
    """Shapes (M, V, 3) of two rigid patches, each moved by its own random rotation and translation."""
    rng = np.random.default_rng(seed)
    v0, f0 = _grid(offset=(0, 0, 0))
    v1, f1 = _grid(offset=(1.5, 0, 0))
    rest = np.concatenate([v0, v1])
    faces = np.concatenate([f0, f1 + len(v0)])
    labels = np.r_[np.zeros(len(v0), int), np.ones(len(v1), int)]
    shapes = []
    for _ in range(m):
        out = np.empty_like(rest)
        for k in (0, 1):
            r = _rot(rng.normal(size=3), rng.uniform(0.2, 2.0))
            out[labels == k] = rest[labels == k] @ r.T + rng.normal(size=3)
        shapes.append(out)
    return np.stack(shapes), faces, labels


def test_proper_procrustes_fixes_a_mirrored_configuration():
    """Plain Procrustes of a mirrored configuration returns a reflection; Lemma 1's fix a proper rotation,
    the best one: the reflection's last singular direction flipped."""
    rng = np.random.default_rng(1)
    q, p = _rot(rng.normal(size=3), 1.1), _rot(rng.normal(size=3), 2.3)
    a = q @ np.diag([3.0, 2.0, -1.0]) @ p.T  # cross-covariance of a mirrored point set
    u, _, vt = np.linalg.svd(a)
    assert np.linalg.det(u @ vt) < 0  # plain Procrustes: a reflection
    r = np.asarray(mfa.proper_procrustes(jnp.asarray(a)))
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(r, q @ p.T, atol=1e-10)
    # no proper rotation does better (random search)
    best = np.trace(r.T @ a)
    for _ in range(500):
        assert np.trace(_rot(rng.normal(size=3), rng.uniform(0, np.pi)).T @ a) <= best + 1e-9


def test_aecm_on_mirrored_shapes_returns_proper_rotations_and_monotone_loglik():
    shapes, faces, labels = _two_rigid_parts(m=3)
    shapes = np.concatenate([shapes, shapes[:1] * np.array([-1.0, 1.0, 1.0])])  # a mirror image of shape 0
    y = jnp.asarray(shapes.transpose(1, 0, 2))
    p, hist, it = hierarchy.fit_from_labels(y, labels, 2)
    assert np.all(np.abs(np.linalg.det(np.asarray(p.rot)) - 1.0) < 1e-9)
    assert np.all(np.diff(hist) >= -1e-9 * np.abs(hist[-1]))


def test_rigid_parts_are_recovered_exactly():
    shapes, faces, labels = _two_rigid_parts(m=4)
    y = jnp.asarray(shapes.transpose(1, 0, 2))
    p, hist, it = hierarchy.fit_from_labels(y, labels, 2)
    lab = mfa.labels_of(y, p)
    assert np.array_equal(lab, labels)
    rec = np.asarray(mfa.reconstruct(p, jnp.asarray(lab), mfa.latent_images(y, p, jnp.asarray(lab))))
    assert hierarchy.rmse(shapes, rec) < 1e-6 * hierarchy.bbox_diagonal(shapes)
    assert it < 20


def test_split_regions_makes_each_part_connected():
    v0, f0 = _grid()
    v1, f1 = _grid(offset=(2, 0, 0))
    faces = np.concatenate([f0, f1 + len(v0)])
    labels = np.zeros(len(v0) + len(v1), int)  # one label on two islands
    labels[:5] = 1  # and a 5-vertex island of label 1 inside the first patch
    out = hierarchy.split_regions(labels, unique_edges(faces), min_size=20)
    assert np.unique(out).size == 2  # the small island joined its surroundings, the two patches separated
    assert np.unique(out[: len(v0)]).size == 1 and out[0] != out[-1]


def test_horse_poses_fit_meets_the_bar():
    """Each AECM stage converges in < 20 iterations, the log-likelihood never decreases, rotations are
    proper, the part count is near the paper's 23, and the fit takes <= 30 s."""
    from jaxdeform.mesh import load_sequence

    verts, faces = load_sequence(data_dir("horse-poses"))
    fit = hierarchy.fit(verts, faces)
    info = hierarchy.summary(fit, verts)
    assert all(it < 20 for it in info["iterations"].values()), info["iterations"]
    assert info["loglik_monotone"]
    for stage in fit.stages:
        if "loglik" in stage:
            assert np.all(np.diff(stage["loglik"]) >= -1e-9 * abs(stage["loglik"][-1]))
    assert np.all(np.abs(np.linalg.det(np.asarray(fit.params.rot)) - 1.0) < 1e-9)
    assert 15 <= info["parts"] <= 35
    assert info["rmse_over_diagonal"] < 1e-2


def _write_shapes(folder, shapes, faces):
    folder.mkdir()
    for k, s in enumerate(shapes):
        save_mesh(folder / f"{k:02d}.obj", s, faces)
    return folder


def test_cli_parts_fit_show_interpolate(tmp_path):
    shapes, faces, _ = _two_rigid_parts(m=4)
    data = _write_shapes(tmp_path / "data", shapes, faces)
    run = tmp_path / "run"
    assert main(["parts", "fit", str(data), "--out", str(run), "--initial-parts", "2"]) == 0
    info = json.loads((run / "summary.json").read_text())
    for key in ("parts", "iterations", "rmse", "rmse_over_diagonal", "seconds"):
        assert key in info
    assert info["rmse_over_diagonal"] < 1e-4
    assert main(["parts", "show", str(run), "--out", str(tmp_path / "show")]) == 0
    assert (tmp_path / "show" / "segmentation.png").stat().st_size > 0
    out = tmp_path / "interp"
    assert (
        main(["parts", "interpolate", str(run), "--source", "0", "--target", "2", "--steps", "4", "--out", str(out)])
        == 0
    )
    assert len(list(out.glob("*.obj"))) == 4 and (out / "strip.png").is_file()
    gaps = json.loads((out / "gaps.json").read_text())
    assert gaps["max_gap_over_diagonal"] <= 1e-2
    for flag in ("--source", "--target"):  # negative indices are refused, not read from the end
        argv = ["parts", "interpolate", str(run), "--source", "0", "--target", "2", "--out", str(tmp_path / "neg")]
        argv[argv.index(flag) + 1] = "-1"
        assert main(argv) == 2 and not (tmp_path / "neg").exists()
    assert main(["parts", "show", str(run), "--shape", "-1", "--out", str(tmp_path / "neg")]) == 2


@pytest.mark.parametrize("case", ["one shape", "different connectivity", "more parts than vertices"])
def test_cli_parts_fit_bad_input(tmp_path, capsys, case):
    shapes, faces, _ = _two_rigid_parts(m=3)
    data = tmp_path / "data"
    if case == "one shape":
        _write_shapes(data, shapes[:1], faces)
    elif case == "more parts than vertices":
        _write_shapes(data, shapes, faces)
    else:
        _write_shapes(data, shapes, faces)
        save_mesh(data / "02.obj", shapes[2], faces[::-1])  # same vertices, other triangles
    run = tmp_path / "run"
    extra = ["--initial-parts", str(shapes.shape[1] + 1)] if case == "more parts than vertices" else []
    assert main(["parts", "fit", str(data), "--out", str(run), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxdeform: error:")
    assert not run.exists() and not any(p.name.startswith(".run") for p in tmp_path.iterdir())


def test_experiment_runs_on_a_small_config(tmp_path):
    """The experiments' code path (fit, figures, interpolation strip, optional Dem Bones, results table)."""
    from experiments.parts import run

    shapes, faces, _ = _two_rigid_parts(m=4)
    _write_shapes(tmp_path / "two-parts", shapes, faces)
    results = run.main(["--data", str(tmp_path), "--out", str(tmp_path / "out"), "--datasets", "two-parts"])
    ours = results[0]["ours"]
    assert ours["rmse_over_diagonal"] < 1e-4 and ours["max_joint_gap_over_diagonal"] <= 1e-2
    assert abs(ours["rotation_det_range"][0] - 1) < 1e-9 and abs(ours["rotation_det_range"][1] - 1) < 1e-9
    for png in ("segmentation.png", "error.png", "interpolation.png"):
        assert (tmp_path / "out" / "two-parts" / png).is_file()
    assert (tmp_path / "out" / "results.md").read_text().startswith("| data |")


@pytest.mark.parametrize(
    "damage",
    [
        "truncated",
        "not a checkpoint",
        "missing array",
        "float labels",
        "faces out of range",
        "nan vertices",
        "summary not an object",
    ],
)
def test_cli_parts_show_on_a_damaged_run(tmp_path, capsys, damage):
    shapes, faces, _ = _two_rigid_parts(m=3)
    run = tmp_path / "run"
    assert (
        main(
            [
                "parts",
                "fit",
                str(_write_shapes(tmp_path / "data", shapes, faces)),
                "--out",
                str(run),
                "--initial-parts",
                "2",
            ]
        )
        == 0
    )
    model = run / "model"
    if damage == "truncated":
        for data in (model / "arrays" / "d").iterdir():
            data.write_bytes(data.read_bytes()[:200])
    elif damage == "summary not an object":
        (run / "summary.json").write_text("[1, 2]")
    elif damage == "not a checkpoint":
        shutil.rmtree(model)
        model.mkdir()
    else:
        record, arrays = read_tree(model, "parts model", prun.MODEL_FORMAT, prun.MODEL_VERSION)
        if damage == "missing array":
            del arrays["rot"]
        if damage == "float labels":
            arrays["labels"] = arrays["labels"].astype(float)
        elif damage == "faces out of range":
            arrays["faces"] = arrays["faces"].copy()
            arrays["faces"][0, 0] = 9999
        elif damage == "nan vertices":
            arrays["vertices"] = arrays["vertices"].copy()
            arrays["vertices"][1, 2, 0] = np.nan
        save_tree(model, arrays, record)
    capsys.readouterr()
    for argv in (
        ["show", str(run), "--out", str(tmp_path / "show")],
        ["interpolate", str(run), "--source", "0", "--target", "1", "--steps", "2", "--out", str(tmp_path / "show")],
    ):
        assert main(["parts", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and ("summary.json" if damage.startswith("summary") else "model") in err[0], err
        assert not (tmp_path / "show").exists()
