"""`jaxdeform cloth train|synthesize|evaluate` on a tiny dataset, and their one-sentence refusals."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from test_cloth_data import grid  # noqa: E402  (tests/ is on sys.path under pytest)

from jaxdeform.cli import main
from jaxdeform.cloth import data as cdata
from jaxdeform.cloth import evaluate as ceval
from jaxdeform.cloth import obstacles as obst

igl = pytest.importorskip("igl")


def wave(v, t, k):
    """A travelling bend of the flat sheet (y up), phase k."""
    y = 0.05 * np.sin(6.0 * v[:, 0] + 0.3 * t + k) * v[:, 2]
    return np.c_[v[:, 0], y, v[:, 2]]


def pair(k: int, frames: int = 6, n: int = 5):
    cv, cf = grid(n, 0.5)
    fv, ff = igl.loop(cv, cf)
    track = obst.static_track(obst.make(spheres=[((0.25, -0.3, 0.25), 0.2)]), frames)
    return {
        "coarse": np.stack([wave(cv, t, k) for t in range(frames)]),
        "fine": np.stack([wave(fv, t, k) for t in range(frames)]),
        "coarse_rest": cv,
        "fine_rest": fv,
        "coarse_faces": cf,
        "fine_faces": ff,
        "obstacles": obst.to_dict(track),
        "meta": {"kind": "sheet", "index": k, "params": {"thickness": 0.005}},
    }


def write(root, pairs):
    names = []
    for i, p in enumerate(pairs):
        names.append(f"seq_{i:03d}.npz")
        cdata.write_sequence(root / names[-1], p)
    cdata.write_index(root, "sheet", names)


def run_cli(args, capsys):
    code = main(args)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def test_train_synthesize_evaluate_round_trip(tmp_path, capsys):
    data = tmp_path / "data"
    write(data, [pair(k) for k in range(3)])
    run = tmp_path / "run"
    code, out, err = run_cli(["cloth", "train", str(data), "--out", str(run), "--steps", "3", "--quiet"], capsys)
    assert code == 0, err
    assert {p.name for p in run.iterdir()} == {".jaxdeform", "model", "representation.npz", "run.json"}
    rec = json.loads((run / "run.json").read_text())
    assert rec["representation"] == "ts-acap" and rec["split"]["test"] == ["seq_002.npz"]
    assert rec["residual"] is True  # default target: the residual over the Loop-upsampled coarse cloth
    js = tmp_path / "ev.json"
    code, out, err = run_cli(["cloth", "evaluate", str(run), "--data", str(data), "--json", str(js), "--quiet"], capsys)
    assert code == 0, err
    res = json.loads(js.read_text())
    for part in (res["test"], res["upsampled_coarse"]["test"]):
        assert {"rmse", "hausdorff", "sted"} <= set(part) and np.isfinite(part["rmse"])
    assert res["upsampled_coarse"]["test"]["rmse"] < 0.01  # Loop of the coarse wave is close to the fine wave
    jt = tmp_path / "ev_train.json"
    code, out, err = run_cli(
        ["cloth", "evaluate", str(run), "--data", str(data), "--json", str(jt), "--split", "train", "--quiet"], capsys
    )
    assert code == 0, err
    tr = json.loads(jt.read_text())
    assert set(tr) == {"train", "upsampled_coarse"} and out.startswith("train: rmse")
    ds = cdata.load_dataset(data)
    ups = ceval.Upsampler(ds.coarse_faces, ds.coarse_rest.shape[0], ds.fine_faces)
    direct = ceval.pool(
        [
            ceval.sequence_errors(x.fine, ups(x.coarse), ds.fine_faces)
            for x in ds.sequences
            if x.name in rec["split"]["train"]
        ]
    )
    assert tr["upsampled_coarse"]["train"]["frames"] == 12  # the two training sequences, not the test one
    assert tr["upsampled_coarse"]["train"]["rmse"] == pytest.approx(direct["rmse"], rel=1e-6)
    syn = tmp_path / "syn"
    code, out, err = run_cli(
        ["cloth", "synthesize", str(run), "--coarse", str(data), "--split", "test", "--out", str(syn)], capsys
    )
    assert code == 0, err
    arr = np.load(syn / "seq_002.npz")
    assert arr["vertices"].shape == (6, 81, 3) and np.all(np.isfinite(arr["vertices"]))


def test_train_self_feed_option(tmp_path, capsys):
    data = tmp_path / "data"
    write(data, [pair(k) for k in range(3)])
    code, _, err = run_cli(
        ["cloth", "train", str(data), "--out", str(tmp_path / "bad"), "--self-feed", "1.5", "--quiet"], capsys
    )
    assert code == 2 and err.count("\n") == 1 and "--self-feed is a probability" in err
    assert not (tmp_path / "bad").exists()
    run = tmp_path / "run"
    code, _, err = run_cli(["cloth", "train", str(data), "--out", str(run), "--steps", "2", "--quiet"], capsys)
    assert code == 0, err
    assert json.loads((run / "run.json").read_text())["train"]["self_feed"] == 0.5  # the CLI's default
    code, _, err = run_cli(
        ["cloth", "train", str(data), "--out", str(tmp_path / "paper"), "--self-feed", "0", "--steps", "2", "--quiet"],
        capsys,
    )
    assert code == 0, err
    assert json.loads((tmp_path / "paper" / "run.json").read_text())["train"]["self_feed"] == 0.0


def test_train_refuses_unequal_lengths(tmp_path, capsys):
    data = tmp_path / "data"
    p = pair(1)
    p["fine"] = p["fine"][:5]
    write(data, [pair(0), p])
    code, out, err = run_cli(["cloth", "train", str(data), "--out", str(tmp_path / "run"), "--quiet"], capsys)
    assert code == 2
    assert err.count("\n") == 1 and "coarse and fine sequences must have equal lengths" in err
    assert not (tmp_path / "run").exists()


def test_train_refuses_mixed_connectivity(tmp_path, capsys):
    data = tmp_path / "data"
    write(data, [pair(0, n=5), pair(1, n=6)])
    code, out, err = run_cli(["cloth", "train", str(data), "--out", str(tmp_path / "run"), "--quiet"], capsys)
    assert code == 2
    assert err.count("\n") == 1 and "must share one connectivity" in err
    assert not (tmp_path / "run").exists()


def _damage_data(data, case):
    """Rewrite the dataset folder ``data`` (3 sequences of :func:`pair`) with one defect."""
    pairs = [pair(k) for k in range(3)]
    index = None
    if case == "nan pin positions":
        pairs[1].update(fine_pins=np.array([0, 1]), fine_pin_positions=np.array([[0, 0, 0], [np.nan, 0, 0]]))
    elif case == "nan obstacle":
        pairs[1]["obstacles"]["sphere_r"] = np.full_like(pairs[1]["obstacles"]["sphere_r"], np.nan)
    elif case == "missing obstacle field":
        del pairs[1]["obstacles"]["ground"]
    elif case == "short obstacle track":
        pairs[1]["obstacles"]["sphere_c"] = pairs[1]["obstacles"]["sphere_c"][:2]
    elif case == "meta not an object":
        pairs[1]["meta"] = [1, 2]
    elif case == "zero-area rest face":
        f = pairs[0]["coarse_faces"][0]
        for p in pairs:
            p["coarse_rest"] = p["coarse_rest"].copy()
            p["coarse_rest"][f[1]] = p["coarse_rest"][f[0]]
    elif case in ("index a list", "sequences not names", "split not lists", "empty train part"):
        index = {
            "index a list": [],
            "sequences not names": {"sequences": [0, 1, 2]},
            "split not lists": {"split": ["seq_000.npz"]},
            "empty train part": {"split": {"train": [], "test": ["seq_002.npz"]}},
        }[case]
    write(data, pairs)
    if case == "text frames":
        with np.load(data / "seq_001.npz") as z:
            arrays = {k: z[k] for k in z.files}
        np.savez(data / "seq_001.npz", **{**arrays, "coarse": arrays["coarse"].astype(str)})
    if index is not None:
        rec = json.loads((data / "dataset.json").read_text())
        rec = index if isinstance(index, list) else {**rec, **index}
        (data / "dataset.json").write_text(json.dumps(rec))


@pytest.mark.parametrize(
    "case",
    [
        "nan pin positions",
        "nan obstacle",
        "missing obstacle field",
        "short obstacle track",
        "meta not an object",
        "text frames",
        "zero-area rest face",
        "index a list",
        "sequences not names",
        "split not lists",
        "empty train part",
        "negative seed",
    ],
)
def test_train_refuses_damaged_data(tmp_path, capsys, case):
    data = tmp_path / "data"
    _damage_data(data, case)
    extra = ["--seed", "-1"] if case == "negative seed" else []
    code, _, err = run_cli(
        ["cloth", "train", str(data), "--out", str(tmp_path / "run"), "--steps", "2", "--quiet", *extra], capsys
    )
    assert code == 2 and err.count("\n") == 1 and err.startswith("jaxdeform: error: "), err
    assert "Traceback" not in err and not (tmp_path / "run").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".run")]


def test_damaged_runs_and_outputs_over_inputs(tmp_path, capsys):
    """evaluate never writes its JSON over a file of the run or the data; a damaged run record, representation or
    split, and a coarse input with a NaN obstacle, get one sentence before any work."""
    data = tmp_path / "data"
    write(data, [pair(k) for k in range(3)])
    run = tmp_path / "run"
    assert run_cli(["cloth", "train", str(data), "--out", str(run), "--steps", "2", "--quiet"], capsys)[0] == 0
    kept = {p: p.read_bytes() for p in (run / "run.json", data / "dataset.json")}
    for target in kept:
        code, _, err = run_cli(
            ["cloth", "evaluate", str(run), "--data", str(data), "--json", str(target), "--quiet"], capsys
        )
        assert code == 2 and err.count("\n") == 1 and "--json" in err, err
    assert {p: p.read_bytes() for p in kept} == kept

    def damaged(name, edit):
        bad = tmp_path / name
        shutil.copytree(run, bad)
        edit(bad)
        return bad

    def record(change):
        def edit(bad):
            rec = json.loads((bad / "run.json").read_text())
            (bad / "run.json").write_text(json.dumps(change(rec)))

        return edit

    def drop_array(bad):
        with np.load(bad / "representation.npz") as z:
            arrays = {k: z[k] for k in z.files if k != "coarse_faces"}
        np.savez(bad / "representation.npz", **arrays)

    runs = {
        "a list": damaged("r1", record(lambda r: [])),
        "thickness": damaged("r2", record(lambda r: {**r, "thickness": "thick"})),
        "coarse_faces": damaged("r3", drop_array),
        "seq_007": damaged("r4", record(lambda r: {**r, "split": {"train": ["seq_000.npz"], "test": ["seq_007.npz"]}})),
        "damaged cloth model checkpoint": damaged("r5", lambda bad: (bad / "model" / "arrays" / "_METADATA").unlink()),
    }
    for expected, bad in runs.items():
        code, _, err = run_cli(
            ["cloth", "evaluate", str(bad), "--data", str(data), "--json", str(tmp_path / "e.json"), "--quiet"], capsys
        )
        assert code == 2 and err.count("\n") == 1 and (expected in err or "run record" in err), err
    p = pair(5)
    p["obstacles"]["sphere_r"] = np.full_like(p["obstacles"]["sphere_r"], np.nan)
    cdata.write_sequence(tmp_path / "coarse.npz", p)
    code, _, err = run_cli(
        ["cloth", "synthesize", str(run), "--coarse", str(tmp_path / "coarse.npz"), "--out", str(tmp_path / "syn")],
        capsys,
    )
    assert code == 2 and "obs_sphere_r" in err and not (tmp_path / "syn").exists()
    assert not (tmp_path / "e.json").exists()


def test_bad_paths_are_one_sentence(tmp_path, capsys):
    code, _, err = run_cli(["cloth", "train", str(tmp_path / "nope"), "--out", str(tmp_path / "run")], capsys)
    assert code == 2 and err.count("\n") == 1 and "no such dataset folder" in err
    code, _, err = run_cli(["cloth", "evaluate", str(tmp_path), "--data", str(tmp_path), "--json", "x.json"], capsys)
    assert code == 2 and err.count("\n") == 1 and "not a cloth run" in err


def test_loss_curve_is_block_means():
    from jaxdeform.cloth.run import loss_curve

    assert loss_curve([1.0, 2.0, 3.0, 4.0, 5.0], every=2) == {"every": 2, "mean": [1.5, 3.5, 5.0]}
    assert loss_curve([], every=3) == {"every": 3, "mean": []}


def test_experiment_test_config_writes_summary(tmp_path):
    """The CPU test configuration of experiments/cloth runs every stage on a tiny SHEET dataset."""
    from experiments.cloth import run as exp

    assert exp.main(["--config", "test", "--out", str(tmp_path), "--datasets", "sheet"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    r = summary["datasets"]["sheet"]
    assert set(r["rmse"]) == set(exp.METHODS) | {"upsampled_coarse", "linear_residual"}
    assert all(np.isfinite(v) for v in r["sted"].values()) and all(np.isfinite(v) for v in r["hausdorff"].values())
    t = r["timing"]
    assert {"coarse_simulation", "extraction", "synthesis", "reconstruction", "refinement", "fine_simulation"} <= set(t)
    assert r["speedup"] == pytest.approx(t["fine_simulation"] / t["ours_total"])
    pen = r["data"]["penetration"]  # inside the triangles too, at both resolutions
    assert pen["samples_per_edge"] == 12 and max(pen["coarse_max_over_edge"], pen["fine_max_over_edge"]) <= 0.01
    assert set(r["jumps"]) == {"ts-acap", "acap"} and r["jumps"]["acap"]["count"] > 0
    sc = r["scale"]["test"]  # the test split's upsampled-coarse error, split into two orthogonal parts
    assert sc["rmse"] == pytest.approx(r["rmse"]["upsampled_coarse"], rel=1e-5)
    assert sc["coarse_scale_rmse"] ** 2 + sc["finer_rmse"] ** 2 == pytest.approx(sc["rmse"] ** 2, rel=1e-9)
    assert np.isfinite(r["evaluate"]["methods"]["linear_residual"]["train_rmse"])
    details = {k: m["detail"] for k, m in r["evaluate"]["methods"].items() if k != "linear_residual"}
    assert set(details) == set(exp.METHODS) | {"upsampled_coarse"}
    assert details["upsampled_coarse"]["fine_scale_rms"] < 1e-6  # in the coarse Loop basis: no fine-scale part
    assert details["upsampled_coarse"]["fine_scale_rmse"] == pytest.approx(
        details["upsampled_coarse"]["fine_scale_rms_ref"], rel=1e-3
    )
    assert all(np.isfinite(d["dihedral_w1"]) and d["dihedral_w1"] >= 0 for d in details.values())
    assert "dihedral W1" in (tmp_path / "results.md").read_text()
    # refined frames (every learned method) keep their vertices within 1 mm of the obstacles' surface
    pens = {k: m["max_penetration"] for k, m in r["evaluate"]["methods"].items() if k != "linear_residual"}
    assert set(pens) == set(exp.METHODS) | {"upsampled_coarse"} and all(pens[k] <= 1e-3 for k in exp.METHODS)
    sg = {g["train_sequences"]: g for g in r["scaling"]}  # every 4th / 2nd / every training sequence: 1 and 2 here
    assert sorted(sg) == [1, 2]
    full = sg[2]  # the whole training split: the linear stage's fit again and the experiment's per-frame run
    assert full["upsampled_coarse"]["test"] == pytest.approx(r["rmse"]["upsampled_coarse"], rel=1e-6)
    assert full["linear_residual"]["test"] == pytest.approx(r["rmse"]["linear_residual"], rel=1e-6)
    assert full["linear_residual"]["train"] == pytest.approx(
        r["evaluate"]["methods"]["linear_residual"]["train_rmse"], rel=1e-6
    )
    assert full["no_temporal"]["test"] == pytest.approx(r["rmse"]["no_temporal"], rel=1e-4)
    assert sg[1]["upsampled_coarse"]["test"] == full["upsampled_coarse"]["test"]
    fl = r["floor"]  # one test scenario re-simulated from a perturbed start: it moved, and only a little
    assert len(fl["sequences"]) == 1 and 0 < fl["perturbed_fine_rmse"] < 10 * fl["perturbation_m"]
    # it covers the whole test split here (one sequence), so its upsampled-coarse errors are the evaluation's
    assert fl["upsampled_coarse_rmse"] == pytest.approx(r["rmse"]["upsampled_coarse"], rel=1e-9)
    assert fl["upsampled_coarse_sted"] == pytest.approx(r["sted"]["upsampled_coarse"], rel=1e-9)
    assert 0 < fl["perturbed_fine_sted"] < fl["upsampled_coarse_sted"]
    assert (tmp_path / "results.md").is_file() and r["figures"] and (tmp_path / r["figures"][0]).is_file()
    assert "loss_sheet.png" in r["figures"] and (tmp_path / "loss_sheet.png").stat().st_size > 0
    rec = json.loads((tmp_path / "runs" / "sheet" / "ours" / "run.json").read_text())
    assert len(rec["loss_curve"]["mean"]) == -(-exp.settings("test").steps // rec["loss_curve"]["every"])
    # one method evaluated again (its stored run) merges into the table: every other row stays, its own is the same
    argv = ["--config", "test", "--out", str(tmp_path), "--datasets", "sheet", "--stages", "train", "evaluate"]
    assert exp.main(argv + ["--methods", "ours"]) == 0
    again = json.loads((tmp_path / "summary.json").read_text())["datasets"]["sheet"]
    assert set(again["rmse"]) == set(r["rmse"]) and again["rmse"]["ours"] == pytest.approx(r["rmse"]["ours"], rel=1e-6)
    assert again["rmse"]["acap"] == r["rmse"]["acap"]

    # the seed spread reuses the stored seed-0 run (same figure as the experiment's) and trains another draw
    from experiments.cloth import seeds

    assert (
        seeds.main(
            ["--config", "test", "--out", str(tmp_path), "--dataset", "sheet", "--methods", "ours", "--seeds", "0", "1"]
        )
        == 0
    )
    rec = json.loads((tmp_path / "seeds_sheet.json").read_text())
    assert rec["upsampled_coarse"]["rmse"] == pytest.approx(r["rmse"]["upsampled_coarse"], rel=1e-9)
    assert rec["methods"]["ours"]["0"]["rmse"] == pytest.approx(r["rmse"]["ours"], rel=1e-6)
    assert rec["methods"]["ours"]["1"]["rmse"] != rec["methods"]["ours"]["0"]["rmse"]
    for per in rec["methods"]["ours"].values():  # equal-length test sequences: pooled RMSE = RMS of theirs
        assert per["rmse"] == pytest.approx(np.sqrt(np.mean(np.square(per["rmse_per_sequence"]))), rel=1e-9)
    assert "| ours, 1 |" in (tmp_path / "seeds_sheet.md").read_text()
    # a second invocation adds its methods to the record of the same seeds and test sequences
    assert (
        seeds.main(
            [
                "--config",
                "test",
                "--out",
                str(tmp_path),
                "--dataset",
                "sheet",
                "--methods",
                "no_temporal",
                "--seeds",
                "0",
                "1",
            ]
        )
        == 0
    )
    again = json.loads((tmp_path / "seeds_sheet.json").read_text())
    assert set(again["methods"]) == {"ours", "no_temporal"} and again["methods"]["ours"] == rec["methods"]["ours"]


def test_generate_keeps_matching_sequences_and_grows(tmp_path):
    """A second generation keeps the files whose stored scenario matches and simulates only the rest."""
    from jaxdeform.cloth import run as crun

    crun.generate("sheet", tmp_path, n_sequences=2, n_frames=3, progress=False, levels=1)
    first = (tmp_path / "seq_000.npz").stat().st_mtime_ns
    rec = crun.generate("sheet", tmp_path, n_sequences=3, n_frames=3, progress=False, levels=1)
    assert (tmp_path / "seq_000.npz").stat().st_mtime_ns == first
    assert rec["sequences"] == ["seq_000.npz", "seq_001.npz", "seq_002.npz"]
    assert cdata.load_dataset(tmp_path).sequences[2].coarse.shape[0] == 3
    crun.generate("sheet", tmp_path, n_sequences=2, n_frames=4, progress=False, levels=1)  # another scenario
    assert (tmp_path / "seq_000.npz").stat().st_mtime_ns != first
    assert cdata.load_dataset(tmp_path).sequences[0].fine.shape[0] == 4
