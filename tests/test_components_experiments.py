"""The seed-000 experiments and the training benchmark run end to end on their test configuration (synthetic
tube, a few epochs): the code paths of Tables 2, 4, 5 and the JSON/markdown they write. They measure nothing."""

import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.components import run as exp


@pytest.mark.parametrize("experiment, rows", [("table2", 5), ("table4", 4), ("table5", 5)])
def test_experiment_test_config(tmp_path, experiment, rows):
    result = exp.main([experiment, "--config", "test", "--out", str(tmp_path), "--epochs", "3"])
    assert len(result["rows"]) == rows
    on_disk = json.loads((tmp_path / experiment / "results.json").read_text())
    assert on_disk["experiment"] == experiment and len(on_disk["rows"]) == rows
    table = (tmp_path / experiment / "results.md").read_text()
    assert table.count("| tube/") == rows and "diameter 1" in table
    for row in result["rows"].values():
        assert row["test"]["erms"] >= 0 and row["test"]["shapes"] == 10
        per = np.asarray(row["test"]["erms_per_shape"])  # rounded to 4 decimals
        assert per.shape == (10,) and np.sqrt(np.mean(per**2)) == pytest.approx(row["test"]["erms"], abs=1e-3)
        by = row["test"]["erms_by_normalization"]
        assert by["radius"] == pytest.approx(row["test"]["erms"]) and by["diameter-first-shape"] > 0
        if row["run"].split("/")[-1] in ("multiscale", "default", "levels1", "levels3"):  # autoencoders: kept counts
            assert len(row["kept_per_level"]) >= 1 and all(k >= 0 for k in row["kept_per_level"])
    if experiment == "table5":  # relative squared errors of every level count
        assert all("max_relative_squared_error" in r["test"] for r in result["rows"].values())


def test_experiment_runs_subset(tmp_path):
    result = exp.main(
        [
            "table4",
            "--config",
            "test",
            "--out",
            str(tmp_path),
            "--epochs",
            "2",
            "--runs",
            "separate",
            "no-attention",
            "--no-figures",
        ]
    )
    assert set(result["rows"]) == {"tube/separate", "tube/no-attention"}
    runs = tmp_path / "table4" / "tube"
    assert sorted(p.name for p in runs.iterdir()) == ["no-attention", "separate"]
    assert not any((runs / r / "figures").exists() for r in ("no-attention", "separate"))
    # --trained-only tabulates the two runs that exist, trains none of the others, and gives the same figures
    # (and draws the component figures the first call left out)
    again = exp.main(["table4", "--config", "test", "--out", str(tmp_path), "--trained-only"])
    assert set(again["rows"]) == {"tube/separate", "tube/no-attention"}
    assert sorted(p.name for p in runs.iterdir()) == ["no-attention", "separate"]
    assert all((runs / r / "figures" / "components.png").is_file() for r in ("no-attention", "separate"))
    if jax.default_backend() == "cpu":  # the table names the accelerator when one trained
        assert again["hardware"].endswith("cores, CPU only")
    for key, row in again["rows"].items():
        assert row["test"]["erms"] == pytest.approx(result["rows"][key]["test"]["erms"], rel=1e-6)
    assert (tmp_path / "table4" / "results.md").read_text().count("| tube/") == 2
    with pytest.raises(SystemExit):
        exp.main(["table4", "--config", "test", "--out", str(tmp_path), "--trained-only", "--force"])


def test_split_all_goes_to_its_own_folder_and_says_so(tmp_path):
    """--split all: runs and results under OUT/table2-all (the protocol's runs, which fig6 reuses, stay), the split
    recorded in results.json, the table not titled as generalization, and every "test" shape a training shape."""
    result = exp.main(["table2", "--config", "test", "--out", str(tmp_path), "--methods", "pca-xyz", "--split", "all"])
    assert result["split"] == "all" and not (tmp_path / "table2").exists()
    row = result["rows"]["tube/pca-xyz"]
    assert row["test"]["shapes"] == row["train"]["shapes"] == 12
    assert json.loads((tmp_path / "table2-all" / "results.json").read_text())["split"] == "all"
    title = (tmp_path / "table2-all" / "results.md").read_text().splitlines()[0]
    assert "no unseen shape" in title and "generalization" not in title
    rec = json.loads((tmp_path / "table2-all" / "tube" / "pca-xyz" / "run.json").read_text())
    assert rec["split"]["mode"] == "all"
    with pytest.raises(SystemExit):  # fig6 edits toward unseen shapes: no --split there
        exp.main(["fig6", "--config", "test", "--out", str(tmp_path), "--split", "all"])


def test_runs_of_another_configuration_are_not_reused(tmp_path):
    """A run whose run.json holds another training configuration than the named one trains now (say an older
    learning-rate decay) is left out by --trained-only and retrained otherwise; a field added since (clip_norm)
    is compared with its default, so its absence alone does not make a run stale."""
    args = [
        "table4",
        "--config",
        "test",
        "--out",
        str(tmp_path),
        "--epochs",
        "2",
        "--runs",
        "separate",
        "no-attention",
        "--no-figures",
    ]
    first = exp.main(args)
    runs = tmp_path / "table4" / "tube"
    for name, decay in (("separate", 0.96), ("no-attention", None)):
        record = json.loads((runs / name / "run.json").read_text())
        del record["train_config"]["clip_norm"]
        if decay is not None:
            record["train_config"]["decay_rate"] = decay
        (runs / name / "run.json").write_text(json.dumps(record))
    kept = exp.main(
        [
            "table4",
            "--config",
            "test",
            "--out",
            str(tmp_path),
            "--runs",
            "separate",
            "no-attention",
            "--trained-only",
            "--no-figures",
        ]
    )
    assert set(kept["rows"]) == {"tube/no-attention"}
    assert kept["rows"]["tube/no-attention"]["test"]["erms"] == pytest.approx(
        first["rows"]["tube/no-attention"]["test"]["erms"]
    )
    again = exp.main(args)
    assert set(again["rows"]) == {"tube/separate", "tube/no-attention"}
    retrained = json.loads((runs / "separate" / "run.json").read_text())
    assert retrained["train_config"]["decay_rate"] != 0.96 and "clip_norm" in retrained["train_config"]
    assert "clip_norm" not in json.loads((runs / "no-attention" / "run.json").read_text())["train_config"]  # reused


def test_fig6_test_config(tmp_path):
    result = exp.main(
        ["fig6", "--config", "test", "--out", str(tmp_path), "--epochs", "3", "--methods", "multiscale", "pca-xyz"]
    )
    rows = result["rows"]
    # the two-level model edits coarse to fine (its level-0 code count, then all), with the one-stage ablation
    assert set(rows) == {"tube/multiscale", "tube/multiscale (one stage)", "tube/pca-xyz"}
    assert tuple(rows["tube/multiscale"]["3"]["stages"]) == (3, 3 + 3 * 2)  # test config kz = (3, 2)
    assert rows["tube/multiscale (one stage)"]["3"]["stages"] is None
    for per_n in rows.values():
        assert set(per_n) == {"3", "6"}
        for v in per_n.values():
            assert 0 <= v["mean_error"] < 1 and 0 <= v["control_error"] < 1
            assert len(v["iterations"]) == len(v["shapes"]) and 0 <= v["converged"] <= len(v["shapes"])
    assert (tmp_path / "fig6" / "fig6.png").is_file() and (tmp_path / "fig6" / "results.md").is_file()
    # a subset of the control counts, without the one-stage ablation row
    sub = exp.main(
        [
            "fig6",
            "--config",
            "test",
            "--out",
            str(tmp_path),
            "--epochs",
            "3",
            "--methods",
            "multiscale",
            "--controls",
            "4",
            "--skip-one-stage",
        ]
    )["rows"]
    assert set(sub) == {"tube/multiscale"} and set(sub["tube/multiscale"]) == {"4"}
    with pytest.raises(SystemExit):
        exp.main(["fig6", "--config", "test", "--out", str(tmp_path), "--controls", "0"])


def test_training_benchmark_smoke(tmp_path):
    from benchmarks import components as bench
    from jaxdeform.data.synthetic import bending_tube_sequence
    from jaxdeform.mesh import save_mesh

    verts, faces = bending_tube_sequence(n_frames=11, n_around=8, n_along=12)
    for k, v in enumerate(verts):
        save_mesh(tmp_path / "tube" / f"f{k:02d}.obj", v, faces)
    out = tmp_path / "b.json"
    payload = bench.main(
        [
            "--data",
            str(tmp_path / "tube"),
            "--json",
            str(out),
            "--repeats",
            "2",
            "--cases",
            "multiscale:test",
            "tan:test",
            "--breakdown",
            "--loop",
            "3",
        ]
    )
    assert json.loads(out.read_text()) == json.loads(json.dumps(payload))
    for rec in payload["records"]:
        assert {"compile_s", "step_ms_median", "step_ms_min", "projected_training_min"} <= set(rec)
        assert rec["loss_finite"] and rec["shapes"] == 2
        assert ("breakdown" in rec) == (rec["method"] == "multiscale")  # the parts of the multiscale step only
        assert rec["loop_steps"] == 3 and rec["loop_ms_per_step"] > 0 and rec["loop_cpu_ms_per_step"] > 0
    parts = payload["records"][0]["breakdown"]
    assert set(parts) == {
        "forward_ms",
        "loss_and_gradient_ms",
        "adam_ms",
        "sparsity_and_gradient_ms",
        "level0_loss_and_gradient_ms",
    }
    assert all(v > 0 for v in parts.values())


def test_sweep_inside_fraction_analytic():
    from experiments.components.sweep import inside_fraction

    dist = np.array([[0.0, 0.1, 0.5, 0.9], [0.1, 0.0, 0.4, 0.8], [0.5, 0.4, 0.0, 0.4], [0.9, 0.8, 0.4, 0.0]])
    c = np.zeros((2, 4 * 9))
    c[0, :9] = 1.0  # all of component 0 at vertex 0: perfectly localized
    c[1, :] = 0.5  # component 1 spread out, largest at vertex 0 (its centre); vertices 0 and 1 lie within 0.3
    c[1, :9] = 0.6
    per = [inside_fraction(c[k : k + 1], dist, 0.3) for k in range(2)]
    norms1 = np.array([0.6, 0.5, 0.5, 0.5]) * 3.0
    assert per[0] == pytest.approx(1.0)
    assert per[1] == pytest.approx(norms1[:2].sum() / norms1.sum())


def test_sweep_runs_on_a_tube(tmp_path):
    from experiments.components import sweep
    from jaxdeform.components import run as crun
    from jaxdeform.data.synthetic import bending_tube_sequence
    from jaxdeform.mesh import save_mesh

    verts, faces = bending_tube_sequence(n_frames=12, n_around=8, n_along=12)
    for k, v in enumerate(verts):
        save_mesh(tmp_path / "tube" / f"f{k:02d}.obj", v, faces)
    out = tmp_path / "s.jsonl"
    res = sweep.main(
        [
            "--data",
            str(tmp_path / "tube"),
            "--kz",
            "3,2",
            "--epochs",
            "150",
            "--jsonl",
            str(out),
            "--decay-rate",
            "0.5",
            "--clip-norm",
            "2",
        ]
    )
    assert json.loads(out.read_text()) == json.loads(json.dumps(res))
    assert res["config"]["turns"] == "aligned" and res["config"]["scale_quantile"] == crun.SCALE_QUANTILE
    assert res["config"]["decay_rate"] == 0.5 and res["config"]["clip_norm"] == 2.0
    # windows of 100 epochs, the last one short: [last loss, largest loss] of each
    assert len(res["loss_per_100"]) == 2 and res["loss_per_100"][-1][0] == res["final_loss"]
    assert all(top >= last for last, top in res["loss_per_100"])
    assert res["loss_per_100"][0][1] > res["loss_per_100"][1][0]  # the loss falls (the first window holds epoch 0)
    assert res["train_shapes"] == 2 and res["test_shapes"] == 10
    for key in ("train_erms", "test_erms", "level0_train_erms", "level0_test_erms"):
        assert np.isfinite(res[key]) and res[key] >= 0
    assert len(res["inside_fraction"]) == 2 and all(0 <= f <= 1 for f in res["inside_fraction"])
    # the redundant-component removal per level: 3 components at level 0, 3 x 2 at level 1, strongest first
    comps = res["components"]
    assert [comps[f"level{i}"]["components"] for i in (0, 1)] == [3, 6]
    for level in comps.values():
        top = level["strongest"]
        assert 0 <= level["kept"] <= level["components"] and top == sorted(top, reverse=True)
        assert level["kept"] <= sum(t >= 0.01 for t in top)  # eps2, then near duplicates; all listed here (<= 8)
    # eq. 8 per shape, its maximum and mean; with every shape training the test keys repeat the train ones
    assert 0 <= res["train_mean_rse"] <= res["train_max_rse"] and 0 <= res["test_mean_rse"] <= res["test_max_rse"]
    res_all = sweep.main(
        [
            "--data",
            str(tmp_path / "tube"),
            "--kz",
            "3,2",
            "--epochs",
            "100",
            "--split",
            "all",
            "--eval-every",
            "50",
            "--curve",
            "features",
            "--jsonl",
            str(tmp_path / "all.jsonl"),
        ]
    )
    assert res_all["train_shapes"] == res_all["test_shapes"] == 12 and res_all["split"] == "all"
    assert res_all["config"]["augment"] == 0 and "mix_sigma" not in res_all["config"]
    res_aug = sweep.main(
        [
            "--data",
            str(tmp_path / "tube"),
            "--kz",
            "3,2",
            "--epochs",
            "20",
            "--augment",
            "6",
            "--batch",
            "4",
            "--mix-regions",
            "1,2",
        ]
    )
    assert res_aug["config"]["augment"] == 6 and res_aug["config"]["batch"] == 4
    assert res_aug["config"]["mix_regions"] == "1,2" and res_aug["train_shapes"] == 2  # errors of the real shapes
    assert np.isfinite(res_aug["test_erms"])
    # a reference variant: the sweep with the variant's model options, named in the result line
    from experiments.components import reference_variants as rv

    res_tie = rv.main(["--variant", "init-tie", "--data", str(tmp_path / "tube"), "--kz", "3,2", "--epochs", "2"])
    assert res_tie["config"]["variant"] == "init-tie" and res_tie["config"]["tie_conv"] is True
    assert res_tie["config"]["init"] == "normal" and res_tie["config"]["decoder_tanh"] is True
    assert np.isfinite(res_tie["test_erms"]) and res["config"]["tie_conv"] is False
    assert "components" not in res_tie  # the tied decoder has no extractable components
    assert res_all["test_max_rse"] == res_all["train_max_rse"] and res_all["test_erms"] == res_all["train_erms"]
    assert [p["epoch"] for p in res_all["curve"]] == [50, 100]
    assert set(res_all["curve"][0]) == {"epoch", "seconds", "train_feature_mse", "train_max_rse", "train_mean_rse"}
    assert res_all["curve"][-1]["train_max_rse"] == pytest.approx(res_all["train_max_rse"], rel=1e-5)
    # the learning-curve table and figure of Table 5 from that line
    from experiments.components import curves

    rows = curves.main([f"two={tmp_path / 'all.jsonl'}", "--out", str(tmp_path / "curves")])
    assert rows["two"]["levels"] == 2 and rows["two"]["paper_max_relative_squared_error"] == curves.PAPER[2]
    assert [p["max_rse"] for p in rows["two"]["curve"]] == [p["train_max_rse"] for p in res_all["curve"]]
    md = (tmp_path / "curves" / "results.md").read_text()
    assert f"| 100 | {res_all['curve'][-1]['train_max_rse']:.4g} |" in md
    assert json.loads((tmp_path / "curves" / "results.json").read_text())["rows"]["two"]["epochs"] == 100
    from PIL import Image

    from experiments import charts

    assert Image.open(tmp_path / "curves" / "curves.png").size == charts.SIZE
    with pytest.raises(SystemExit, match="LABEL=FILE"):
        curves.main([str(tmp_path / "all.jsonl"), "--out", str(tmp_path / "c2")])
    with pytest.raises(SystemExit, match="no learning curve"):
        curves.main([f"plain={out}", "--out", str(tmp_path / "c3")])
    # a result line without Erms (a run whose final reconstruction did not happen) is tabled as "not measured"
    line = json.loads((tmp_path / "all.jsonl").read_text().splitlines()[-1])
    del line["test_erms"], line["train_erms"]
    (tmp_path / "no_erms.jsonl").write_text(json.dumps(line) + "\n")
    rows = curves.main([f"two={tmp_path / 'no_erms.jsonl'}", "--out", str(tmp_path / "c4")])
    assert rows["two"]["erms"] is None
    assert "| not measured |" in (tmp_path / "c4" / "results.md").read_text()


def test_table5_script_on_a_tube(tmp_path):
    """experiments/components/table5_all.sh: the two- and three-level sweeps side by side, their logs and result
    lines, and the curves over both."""
    import subprocess
    import sys

    data = exp.synthetic_tube(tmp_path)
    bindir = tmp_path / "bin"
    bindir.mkdir()
    shim = bindir / "python3"  # the script calls python3: make it this interpreter
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    shim.chmod(0o755)
    env = {
        **os.environ,
        "PATH": f"{bindir}{os.pathsep}{os.environ['PATH']}",
        "PYTHONPATH": str(Path(__file__).resolve().parents[1]),
    }
    out = tmp_path / "t5"
    proc = subprocess.run(
        ["bash", "experiments/components/table5_all.sh", str(data), str(out), "250", "0", "test host"],
        cwd=Path(__file__).resolve().parents[1],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert "two: exit 0" in proc.stdout and "three: exit 0" in proc.stdout
    res = json.loads((out / "results.json").read_text())
    assert res["hardware"] == "test host"
    assert {lab: r["levels"] for lab, r in res["rows"].items()} == {"two": 2, "three": 3}
    assert all(r["split"] == "all" and r["epochs"] == 250 for r in res["rows"].values())
    # the log keeps the curve point that the result line repeats
    three = json.loads((out / "three.jsonl").read_text().splitlines()[-1])
    assert f'"epoch": 250, "seconds": {three["curve"][0]["seconds"]}' in (out / "three.log").read_text()


def test_ceiling_on_the_tube(tmp_path):
    """The regional-projection experiment on the synthetic tube: one region in coordinates is the PCA-on-
    coordinates baseline's reconstruction, and it writes its tables."""
    from experiments.components import ceiling
    from jaxdeform import metrics
    from jaxdeform.components import baselines
    from jaxdeform.components import run as crun

    data = exp.synthetic_tube(tmp_path)
    result = ceiling.main(["--data", str(data), "--regions", "1,4", "--out", str(tmp_path / "ceiling")])
    assert [r["regions"] for r in result["rows"]] == [1, 4]
    vertices, _ = crun.load_data(data)
    tr, te = crun.split_indices(vertices.shape[0])
    pca = baselines.fit_pca(vertices[tr], n_components=50)
    expected = metrics.erms(vertices[te], np.asarray(baselines.reconstruct(pca, vertices[te])))
    assert result["rows"][0]["xyz"]["erms"] == pytest.approx(expected, rel=1e-6)
    assert all(np.isfinite(r["acap"]["erms"]) for r in result["rows"])
    assert "| 4 |" in (tmp_path / "ceiling" / "results.md").read_text()
    assert result["turns"] == "aligned" and "branches aligned" in (tmp_path / "ceiling" / "results.md").read_text()
    assert result["scale_quantile"] == 0.0  # the ceiling of the features, not of the runs' clipping
    own = ceiling.main(["--data", str(data), "--regions", "1", "--out", str(tmp_path / "own"), "--turns", "per-shape"])
    assert own["turns"] == "per-shape" and own["rows"][0]["xyz"] == result["rows"][0]["xyz"]  # coordinates: the same


def test_projection_fits_codes_back_to_a_decoder_output():
    """A shape the decoders can produce is found again from perturbed codes."""
    from experiments.components.projection import fit_codes
    from jaxdeform.components import model
    from jaxdeform.data.synthetic import bending_tube_sequence
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn.graph_conv import rings_from_topology

    verts, faces = bending_tube_sequence(n_frames=2, n_around=8, n_along=12)
    rings = rings_from_topology(build_topology(faces, verts.shape[1]))
    config = model.Config(kz=(3, 2), d=(0.5, 0.3))
    params = model.Model(verts.shape[1], config, key=jax.random.PRNGKey(0), dtype=jnp.float32)
    keys = jax.random.split(jax.random.PRNGKey(1), 4)
    # codes per level: (blocks, shapes, kz)
    target = (jax.random.normal(keys[0], (1, 2, 3), jnp.float32), jax.random.normal(keys[1], (3, 2, 2), jnp.float32))
    x = params.decode_latents(target, rings)
    start = tuple(t + 0.5 * jax.random.normal(k, t.shape, jnp.float32) for t, k in zip(target, keys[2:]))
    codes, losses = fit_codes(params, rings, x, start, steps=400, lr=0.02)
    final = float(jnp.sum((params.decode_latents(codes, rings) - x) ** 2))
    assert losses.shape == (400,) and losses[0] > 0
    assert final < 1e-3 * losses[0]


def test_projection_encoder_row_is_the_protocol(tmp_path):
    """The experiment's encoder-code row scores exactly what `components evaluate` reports for the test split."""
    from experiments.components import projection
    from jaxdeform.components import run as crun

    data = exp.synthetic_tube(tmp_path)
    (tmp_path / "run").mkdir()
    crun.fit(data, "test", tmp_path / "run", method="multiscale", epochs=3, progress=False, log=lambda s: None)
    result = projection.main([str(tmp_path / "run"), "--steps", "3", "--json", str(tmp_path / "p.json")])
    expected = crun.evaluate(crun.load(tmp_path / "run"), data)["test"]
    for key in ("erms", "sted", "max_relative_squared_error"):
        assert result["encoder"][key] == pytest.approx(expected[key], rel=1e-6)
    assert json.loads((tmp_path / "p.json").read_text())["fitted"]["shapes"] == expected["shapes"]


def test_projection_in_positions_finds_a_decodable_shape_again(tmp_path):
    """Position-space fitting through the ACAP reconstruction recovers a mesh the run can produce (moved by a
    translation, which the fit leaves free) from perturbed codes; the experiment records the space it fitted in."""
    from experiments.components import projection
    from jaxdeform import acap
    from jaxdeform.components import run as crun
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn.graph_conv import rings_from_topology

    data = exp.synthetic_tube(tmp_path)
    (tmp_path / "run").mkdir()
    crun.fit(data, "test", tmp_path / "run", method="multiscale", epochs=3, progress=False, log=lambda s: None)
    run = crun.load(tmp_path / "run")
    vertices, faces = crun.run_data(run, data)
    rings = rings_from_topology(build_topology(faces, run.rest.shape[0]))
    codes = run.model.encode(crun.scaled_features(run, vertices[run.test_idx][:2]), rings)
    features = run.scaler.inverse(run.model.decode_latents(codes, rings)).astype(jnp.float64)
    target = np.asarray(acap.cached(run.rest, run.faces).decode(features, refine=0)) + np.array([0.3, -0.2, 0.1])
    keys = jax.random.split(jax.random.PRNGKey(2), len(codes))
    start = tuple(c + 0.3 * jax.random.normal(k, c.shape, c.dtype) for c, k in zip(codes, keys))
    _, losses = projection.fit_positions(run.model, rings, run, target, start, iterations=200)
    assert losses[-1] < 1e-3 * losses[0], (losses[0], losses[-1])
    result = projection.main([str(tmp_path / "run"), "--space", "positions", "--steps", "2"])
    assert result["space"] == "positions" and result["fitted"]["erms"] <= result["encoder"]["erms"] * 1.0001


def test_feature_transform_aligns_then_scales():
    """components.run.fit_feature_transform / apply_feature_transform, shared by runs, the sweep and the ceiling:
    a shape whose rotation vectors sit one turn off is scaled as the shape itself once aligned, not otherwise;
    and the scaler is the one fitted on the aligned training features."""
    from jaxdeform import acap
    from jaxdeform.components import run as crun

    rng = np.random.default_rng(7)
    w = rng.normal(size=(20, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    theta = rng.uniform(2.8, 3.1, size=(5, 20, 1))
    v = theta * w
    feats = np.concatenate([v, rng.uniform(0.8, 1.2, size=(5, 20, 6))], axis=-1)
    off = feats.copy()
    off[3, :8, :3] = (theta[3, :8] - 2 * np.pi) * w[:8]  # one turn down, the same rotations
    turns, scaler = crun.fit_feature_transform(off, 0.0)
    np.testing.assert_allclose(turns, v.mean(0), atol=1e-9)
    x = crun.apply_feature_transform(off, turns, scaler)
    np.testing.assert_allclose(x, np.asarray(acap.Scaler.fit(feats).transform(feats)), atol=1e-9)
    none, plain = crun.fit_feature_transform(off, 0.0, align=False)
    assert none is None
    x_own = crun.apply_feature_transform(off, None, plain)
    assert np.abs(x_own[3, :8, :3] - x[3, :8, :3]).max() > 0.1  # per-shape branches: shape 3 scaled elsewhere
    assert crun.apply_feature_transform(off.astype(np.float32), turns, scaler).dtype == np.float32


def test_chain_scores_each_stage_and_resumes(tmp_path, capsys):
    """The fine-tuning chain on the synthetic tube: base, rigid and a generated round, each a run the CLI wrote
    from the previous one with the stated options and each scored by the protocol; a rerun trains nothing; another
    option, or a stage folder without scores, is refused with one sentence and exit 2."""
    from experiments.components import chain
    from experiments.components.run import synthetic_tube
    from jaxdeform.components import run as crun

    data = synthetic_tube(tmp_path)
    out = tmp_path / "chain"
    argv = [
        str(data),
        "--out",
        str(out),
        "--config",
        "test",
        "--epochs",
        "3",
        "--first-steps",
        "2",
        "--rounds",
        "1",
        "--round-steps",
        "1",
        "--generated",
        "2",
        "--mixes",
        "3",
        "--quiet",
    ]
    results = chain.main(argv)
    assert list(results["stages"]) == ["base", "rigid", "round1"]
    prev = out / "base"
    for name in ("rigid", "round1"):
        rec = json.loads((out / name / "run.json").read_text())["finetune"]
        assert rec["source"] == str(prev) and rec["rigid"] is True and rec["mixes"] == 3
        assert rec["generated"] == (0 if name == "rigid" else 2) and rec["steps"] == (2 if name == "rigid" else 1)
        prev = out / name
    again = crun.evaluate(crun.load(out / "round1"), data)  # the protocol's own scores
    for part in ("train", "test"):
        got = results["stages"]["round1"]["evaluate"][part]
        assert {k: v for k, v in got.items() if k != "seconds"} == {
            k: v for k, v in again[part].items() if k != "seconds"
        }
    md = (out / "results.md").read_text()
    assert md.count("\n| ") == 1 + 3 and "| round1 |" in md
    assert json.loads((out / "results.json").read_text()) == results
    stamp = (out / "round1" / "run.json").stat().st_mtime_ns
    capsys.readouterr()
    assert chain.main(argv) == results
    assert "round1: done" in capsys.readouterr().out
    assert (out / "round1" / "run.json").stat().st_mtime_ns == stamp
    other = list(argv)
    other[other.index("--first-steps") + 1] = "4"
    with pytest.raises(SystemExit) as err:
        chain.main(other)
    assert err.value.code == 2 and "other options" in capsys.readouterr().err
    assert json.loads((out / "results.json").read_text()) == results
    (tmp_path / "fresh" / "rigid").mkdir(parents=True)
    with pytest.raises(SystemExit) as err:
        chain.main([str(data), "--out", str(tmp_path / "fresh"), "--from", str(out / "base"), "--quiet"])
    assert err.value.code == 2 and "has no scores" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "fresh").iterdir()) == ["rigid"]


def test_reference_variants_are_model_options():
    """Tan et al.'s block, detail by detail, as options of model.Config (init/init_std, tie_conv, decoder_tanh)."""
    import dataclasses

    import jax

    from experiments.components import reference_variants as rv
    from jaxdeform.components import model, train
    from jaxdeform.data.synthetic import bending_tube_sequence
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn import graph_conv
    from jaxdeform.nn.graph_conv import rings_from_topology

    verts, faces = bending_tube_sequence(n_frames=3, n_around=8, n_along=6)
    n = verts.shape[1]
    rings = rings_from_topology(build_topology(faces, n))
    base = model.Config(kz=(3, 2), d=(0.5, 0.3))
    dist = jnp.zeros((n, n), jnp.float32)
    key = jax.random.PRNGKey(0)
    x = jax.random.uniform(jax.random.PRNGKey(1), (2, n, 9), minval=-0.9, maxval=0.9)
    assert rv.variant_config(base, "init-tie") == dataclasses.replace(
        base, init="normal", init_std=rv.TAN_STD, tie_conv=True
    )
    assert rv.variant_config(base, "linear-fc") == dataclasses.replace(base, decoder_tanh=False)
    with pytest.raises(ValueError, match="variant"):
        rv.variant_config(base, "nope")
    with pytest.raises(ValueError, match="init"):
        model.Config(init="uniform")
    with pytest.raises(ValueError, match="init_std"):
        model.Config(init="normal", init_std=0.0)
    plain = model.Model(n, base, key=key)

    # init: the Glorot draw's weights redrawn from N(0, 0.02^2), one key of split(key) per array, level by level in
    # the order of the arrays' sorted names (the draw of the earlier runs in results/reference_variants.jsonl); the
    # biases stay zero
    drawn = model.Model(n, rv.variant_config(base, "init"), key=key)
    names = ("C", "conv_dec/W_neighbor", "conv_dec/W_point", "conv_dec/b", "conv_enc/W_neighbor", "conv_enc/W_point")
    names = names + ("conv_enc/b",)
    keys = jax.random.split(key, len(names) * len(plain.levels))

    def array(m, level, name):
        obj = m.levels[level]
        for part in name.split("/"):
            obj = getattr(obj, part)
        return obj[...]

    for level in range(len(plain.levels)):
        for j, name in enumerate(names):
            ref = array(plain, level, name)
            k = keys[level * len(names) + j]
            want = ref if name.endswith("/b") else (rv.TAN_STD * jax.random.normal(k, ref.shape)).astype(ref.dtype)
            np.testing.assert_array_equal(array(drawn, level, name), want)
    assert abs(np.asarray(drawn.levels[0].C[...]).std() - rv.TAN_STD) < 0.15 * rv.TAN_STD

    # tie: no decoder weights of its own; the decoders read their encoders' (the bias their own)
    tie = rv.variant_config(base, "tie")
    tied = model.Model(n, tie, key=key)
    assert all(p.conv_dec.W_point is None and p.conv_dec.W_neighbor is None for p in tied.levels)
    for p, q in zip(tied.levels, plain.levels):  # the other arrays are the untied model's
        np.testing.assert_array_equal(p.C[...], q.C[...])
        np.testing.assert_array_equal(p.conv_enc.W_point[...], q.conv_enc.W_point[...])
    untied = model.Model(n, base, key=key)
    for p, q in zip(untied.levels, tied.levels):
        p.conv_dec.W_point.set_value(q.conv_enc.W_point[...])
        p.conv_dec.W_neighbor.set_value(q.conv_enc.W_neighbor[...])
    np.testing.assert_allclose(
        train.reconstruct(tied, x, rings), train.reconstruct(untied, x, rings), rtol=1e-6, atol=1e-7
    )
    loss = lambda q: q(x, rings, dist).loss  # noqa: E731  (the training path)
    assert loss(tied) == pytest.approx(float(loss(untied)), rel=1e-6)
    g_tied, g_untied = jax.grad(loss)(tied), jax.grad(loss)(untied)
    for level in (0, 1):  # the encoder's weights get the gradient of both uses
        for w in ("W_point", "W_neighbor"):
            np.testing.assert_allclose(
                getattr(g_tied.levels[level].conv_enc, w)[...],
                getattr(g_untied.levels[level].conv_enc, w)[...] + getattr(g_untied.levels[level].conv_dec, w)[...],
                rtol=1e-4,
                atol=1e-6,
            )
    out = tied(x, rings, dist)
    with pytest.raises(ValueError, match="no weights of its own"):
        tied.levels[0].conv_dec.weights()  # a tied decoder alone has no weights to read
    np.testing.assert_allclose(tied.decode_latents(out.latents, rings), out.reconstruction, rtol=1e-5, atol=1e-6)
    trained, history = train.train(x[:1], rings, dist, tie, train.TrainConfig(epochs=2))
    assert all(p.conv_dec.W_point is None for p in trained.levels) and np.all(np.isfinite(history))

    # linear-fc: no tanh on z C before the decoder's convolution
    linear = rv.variant_config(base, "linear-fc")
    plain_linear = model.Model(n, linear, key=key)  # the same arrays as plain's
    p0 = jax.tree_util.tree_map(lambda a: a[0], plain.levels[0])
    z = graph_conv.ae_encode(p0, x, rings)
    conv = graph_conv.mesh_conv(
        p0.conv_dec.weights(), graph_conv.ae_decode_pre(p0, z), rings.neighbors, rings.mask, rings.degree
    )
    np.testing.assert_allclose(model.decode_block(p0, z, rings, linear), np.tanh(conv), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(model.decode_block(p0, z, rings), graph_conv.ae_decode(p0, z, rings))
    out = plain_linear(x, rings, dist)  # the last level on its masked inputs
    np.testing.assert_allclose(out.reconstruction, plain_linear.reconstruction(x, rings), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(
        plain_linear.decode_latents(out.latents, rings), out.reconstruction, rtol=1e-5, atol=1e-6
    )
    assert not np.allclose(out.reconstruction, plain(x, rings, dist).reconstruction)


def test_similarity_onto_undoes_a_similarity_transform():
    from experiments.components.common import similarity_onto

    rng = np.random.default_rng(3)
    dst = rng.normal(size=(40, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))  # a proper rotation
    src = 2.7 * dst @ q.T + np.array([5.0, -1.0, 0.5])
    np.testing.assert_allclose(similarity_onto(src, dst), dst, atol=1e-10)


def test_horse49_is_the_reference_then_the_gallop(tmp_path):
    from conftest import data_dir

    from experiments.components.common import horse49, similarity_onto
    from jaxdeform.mesh import load_mesh, load_sequence

    gallop, poses = data_dir("horse-gallop"), data_dir("horse-poses")
    folder = horse49(gallop.parent, tmp_path)
    shapes, faces = load_sequence(folder)
    frames, gallop_faces = load_sequence(gallop)
    ref, _ = load_mesh(poses / "horse_ref.obj")
    assert shapes.shape == (49, *frames.shape[1:]) and np.array_equal(faces, gallop_faces)
    np.testing.assert_allclose(shapes[1:], frames, atol=1e-5)  # the OBJ text round trip
    # the reference at the gallop's size and place: RMS radius and centroid of the first frame
    radius = lambda v: np.sqrt(((v - v.mean(axis=0)) ** 2).sum(axis=1).mean())  # noqa: E731
    assert radius(shapes[0]) == pytest.approx(radius(frames[0]), rel=1e-5)
    np.testing.assert_allclose(shapes[0].mean(axis=0), frames[0].mean(axis=0), atol=1e-5)
    np.testing.assert_allclose(shapes[0], similarity_onto(ref, frames[0]), atol=1e-5)
    # Table 1's split: every 10th from the reference trains, 5 of 49
    from jaxdeform.components.run import split_indices

    train, test = split_indices(49, "every10")
    assert train.tolist() == [0, 10, 20, 30, 40] and len(test) == 44
    assert horse49(gallop.parent, tmp_path) == folder  # built once
