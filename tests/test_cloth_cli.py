"""`jaxdeform cloth train|synthesize|evaluate` on a tiny dataset, and their one-sentence refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxdeform.cli import main
from jaxdeform.cloth import data as cdata
from jaxdeform.cloth import obstacles as obst
from test_cloth_data import grid  # noqa: E402  (tests/ is on sys.path under pytest)

igl = pytest.importorskip("igl")


def wave(v, t, k):
    """A travelling bend of the flat sheet (y up), phase k."""
    y = 0.05 * np.sin(6.0 * v[:, 0] + 0.3 * t + k) * v[:, 2]
    return np.c_[v[:, 0], y, v[:, 2]]


def pair(k: int, frames: int = 6, n: int = 5):
    cv, cf = grid(n, 0.5)
    fv, ff = igl.loop(cv, cf)
    track = obst.static_track(obst.make(spheres=[((0.25, -0.3, 0.25), 0.2)]), frames)
    return {"coarse": np.stack([wave(cv, t, k) for t in range(frames)]),
            "fine": np.stack([wave(fv, t, k) for t in range(frames)]),
            "coarse_rest": cv, "fine_rest": fv, "coarse_faces": cf, "fine_faces": ff,
            "obstacles": obst.to_dict(track), "meta": {"kind": "sheet", "index": k, "params": {"thickness": 0.005}}}


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
    assert {p.name for p in run.iterdir()} == {"model.npz", "representation.npz", "run.json"}
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
    syn = tmp_path / "syn"
    code, out, err = run_cli(["cloth", "synthesize", str(run), "--coarse", str(data), "--split", "test",
                              "--out", str(syn)], capsys)
    assert code == 0, err
    arr = np.load(syn / "seq_002.npz")
    assert arr["vertices"].shape == (6, 81, 3) and np.all(np.isfinite(arr["vertices"]))


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


def test_bad_paths_are_one_sentence(tmp_path, capsys):
    code, _, err = run_cli(["cloth", "train", str(tmp_path / "nope"), "--out", str(tmp_path / "run")], capsys)
    assert code == 2 and err.count("\n") == 1 and "no such dataset folder" in err
    code, _, err = run_cli(["cloth", "evaluate", str(tmp_path), "--data", str(tmp_path), "--json", "x.json"], capsys)
    assert code == 2 and err.count("\n") == 1 and "not a cloth run" in err


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
    assert r["data"]["penetration"]["fine_max_over_edge"] <= 0.01
    assert set(r["jumps"]) == {"ts-acap", "acap"} and r["jumps"]["acap"]["count"] > 0
    fl = r["floor"]  # one test scenario re-simulated from a perturbed start: it moved, and only a little
    assert len(fl["sequences"]) == 1 and 0 < fl["perturbed_fine_rmse"] < 10 * fl["perturbation_m"]
    assert (tmp_path / "results.md").is_file() and r["figures"] and (tmp_path / r["figures"][0]).is_file()


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
