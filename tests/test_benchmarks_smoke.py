"""Smoke run of the benchmark script (benchmarks/acap.py) on a tiny synthetic sequence, so it cannot rot.

This checks that the script runs and writes every field; it measures nothing (the real benchmark is
``make bench`` / ``python -m benchmarks.acap``, never part of the test suite).
"""

import json
import math

import numpy as np
import pytest

from benchmarks import acap as bench
from jaxdeform.data.synthetic import bending_tube_sequence
from jaxdeform.mesh import save_mesh

TIMING_KEYS = {"compile_s", "per_frame_ms_median", "per_frame_ms_min", "call_ms_median"}
RECORD_KEYS = {
    "case",
    "solver",
    "vertices",
    "faces",
    "frames",
    "dtype",
    "device",
    "cpu",
    "prepare_s",
    "prepare_cold_s",
    "solver_setup_s",
    "encode",
    "encode_local",
    "encode_temporal",
    "decode",
    "decode_plain",
    "cholespy_solve_3rhs_ms",
    "cholespy_solve_all_ms",
    "cholespy_factor_s",
    "decode_over_solve",
    "decode_over_solve_paired",
    "decode_plain_over_solve",
    "decode_plain_over_solve_paired",
    "cg_steps",
    "cg_converged",
    "roundtrip",
    "max_dev_from_host",
}


def test_benchmark_script_smoke(tmp_path):
    verts, faces = bending_tube_sequence(n_frames=3, n_around=8, n_along=12)
    data = tmp_path / "tube"
    for k, v in enumerate(verts):
        save_mesh(data / f"frame{k:02d}.obj", v, faces)
    out = tmp_path / "bench" / "nested" / "acap.json"

    # float32 only: each dtype pays JAX's cold compilation again (~5-10 s on a 2-core machine). No wall-clock bound
    # here (timings belong to the benchmarks): the records check below fails if the big case or a float64 pass
    # sneaks into the smoke run.
    payload = bench.main(["--data", str(data), "--json", str(out), "--skip-big", "--no-float64", "--repeats", "1"])

    assert out.is_file()
    on_disk = json.loads(out.read_text())
    assert on_disk == json.loads(json.dumps(payload))
    assert {"records", "date", "command", "solvers"} <= set(on_disk)
    assert not [p for p in out.parent.iterdir() if p.name != out.name]  # no temporary file left behind

    records = on_disk["records"]
    assert [(r["case"], r["dtype"], r["solver"]) for r in records] == [
        ("dataset", "float32", "host"),
        ("dataset", "float32", "dense"),
        ("dataset", "float32", "cg"),
    ]
    for r in records:
        assert "skipped" not in r
        assert RECORD_KEYS <= set(r), RECORD_KEYS - set(r)
        assert (r["vertices"], r["faces"], r["frames"]) == (verts.shape[1], faces.shape[0], 3)
        assert {"platform", "name"} <= set(r["device"])
        for key in ("encode", "encode_local", "encode_temporal", "decode", "decode_plain"):
            assert TIMING_KEYS <= set(r[key]), (key, r[key])
            assert all(math.isfinite(r[key][k]) and r[key][k] >= 0 for k in TIMING_KEYS)
        assert r["encode"]["consistency"] == "spatial"
        assert r["encode_local"]["consistency"] == "none"
        assert r["encode_temporal"]["consistency"] == "temporal"
        for key in ("decode", "decode_plain"):
            assert r[key]["solves"]["converged"] is True and r[key]["solves"]["steps"] >= 1
        assert r["cholespy_solve_3rhs_ms"] > 0 and r["cholespy_solve_all_ms"] > 0
        assert r["decode_over_solve"] > 0 and r["decode_over_solve_paired"] > 0
        assert r["decode_plain_over_solve"] > 0 and r["decode_plain_over_solve_paired"] > 0
        assert r["prepare_s"] > 0 and r["prepare_cold_s"] > 0 and r["cholespy_factor_s"] > 0
        rt = r["roundtrip"]
        assert np.isfinite(rt["mean_rel"]) and np.isfinite(rt["max_rel"]) and rt["max_rel"] >= rt["mean_rel"] >= 0
        # a smooth tube decodes close to itself: catches a broken pipeline, not a precision regression
        assert rt["max_rel"] < 0.1
    host, dense, cg = records
    assert host["solver_setup_s"] > 0 and dense["solver_setup_s"] > 0 and cg["solver_setup_s"] >= 0
    assert host["max_dev_from_host"] is None  # the reference
    # float32: the solvers agree with the host factor to float32 accuracy (1e-6 CG tolerance), not bit for bit
    assert 0 <= dense["max_dev_from_host"] < 1e-4 and 0 <= cg["max_dev_from_host"] < 1e-4
    assert host["decode"]["solves"]["steps"] == dense["decode"]["solves"]["steps"] == 1
    assert host["cg_steps"] is None and dense["cg_converged"] is None
    assert cg["cg_converged"] is True and cg["cg_steps"] == cg["decode"]["solves"]["steps"] > 1

    table = bench.format_table(records)
    assert "float32" in table and "dataset" in table and all(s in table for s in ("host", "dense", "cg"))


def test_benchmark_solver_selection_and_skips():
    """--solvers parsing and the recorded (not silent) skip of the dense solver on large meshes."""
    from jaxdeform.acap import reconstruct

    assert bench.parse_solvers("cg,host") == ["host", "cg"]
    with pytest.raises(ValueError):
        bench.parse_solvers("host,sparse")
    limit = reconstruct.DENSE_MAX_VERTICES
    assert bench.skip_reason("dense", limit) is None
    assert "DENSE_MAX_VERTICES" in bench.skip_reason("dense", limit + 1)
    assert bench.skip_reason("host", 10 * limit) is None and bench.skip_reason("cg", 10 * limit) is None
    skipped = {
        "case": "big",
        "solver": "dense",
        "dtype": "float32",
        "vertices": limit + 1,
        "frames": 2,
        "skipped": bench.skip_reason("dense", limit + 1),
    }
    assert "skipped" in bench.format_table([skipped])


def test_handles_benchmark_smoke(tmp_path):
    """benchmarks/handles.py (seed 004 rebind and pose timings) on a tiny mesh: every field is written."""
    import trimesh

    from benchmarks import handles as hbench

    m = trimesh.creation.icosphere(subdivisions=2)
    mesh = tmp_path / "ico.obj"
    save_mesh(mesh, np.asarray(m.vertices), np.asarray(m.faces))
    out = tmp_path / "bench" / "handles.json"
    payload = hbench.main(
        [
            "--mesh",
            str(mesh),
            "--json",
            str(out),
            "--channels",
            "8",
            "--handles",
            "1",
            "3",
            "--repeats",
            "2",
            "--pose-faces",
            "300",
            "--pose-handles",
            "3",
            "--pose-frames",
            "2",
        ]
    )
    on_disk = json.loads(out.read_text())
    assert on_disk == json.loads(json.dumps(payload))
    assert not [p for p in out.parent.iterdir() if p.name != out.name]
    assert (on_disk["vertices"], on_disk["faces"], on_disk["channels"]) == (len(m.vertices), len(m.faces), 8)
    assert [r["handles"] for r in on_disk["rebind"]] == [1, 3] and set(on_disk["rebind_ms"]) == {"1", "3"}
    for r in on_disk["rebind"]:
        assert {"bucket", "compile_s", "ms_median", "ms_min", "ms_host_median"} <= set(r)
        assert 0 <= r["ms_min"] <= r["ms_median"] and r["compile_s"] > 0
    assert on_disk["pose_mesh"]["faces"] >= 300 and on_disk["pose_mesh"]["handles"] == 3
    assert {r["variant"] for r in on_disk["pose"]} == {
        "affine",
        "translation",
        "pou",
        "symmetric",
        "deformer",
        "deformer_pou",
        "deformer_symmetric",
    }
    assert on_disk["pose_mesh"]["symmetry_plane"] == "x"
    assert all(r["fps_median"] > 0 and math.isfinite(r["fps_median"]) for r in on_disk["pose"])
    assert set(on_disk["pose_fps"]) == {r["variant"] for r in on_disk["pose"]}
    assert "rebind" in hbench.format_table(on_disk)
