"""Smoke run of the benchmark script (benchmarks/acap.py) on a tiny synthetic sequence, so it cannot rot.

This checks that the script runs and writes every field; it measures nothing (the real benchmark is
``make bench`` / ``python -m benchmarks.acap``, never part of the test suite).
"""

import json
import math

import numpy as np

from benchmarks import acap as bench
from jaxdeform.data.synthetic import bending_tube_sequence
from jaxdeform.mesh import save_mesh

TIMING_KEYS = {"compile_s", "per_frame_ms_median", "per_frame_ms_min"}
RECORD_KEYS = {
    "case", "vertices", "faces", "frames", "dtype", "device", "cpu", "prepare_s", "encode", "encode_local",
    "encode_temporal", "decode", "decode_plain", "cholespy_solve_3rhs_ms", "cholespy_factor_s", "decode_over_solve", "roundtrip",
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
    assert {"records", "date", "command"} <= set(on_disk)
    assert not [p for p in out.parent.iterdir() if p.name != out.name]  # no temporary file left behind

    records = on_disk["records"]
    assert [(r["case"], r["dtype"]) for r in records] == [("dataset", "float32")]
    for r in records:
        assert RECORD_KEYS <= set(r), RECORD_KEYS - set(r)
        assert (r["vertices"], r["faces"], r["frames"]) == (verts.shape[1], faces.shape[0], 3)
        assert {"platform", "name"} <= set(r["device"])
        for key in ("encode", "encode_local", "encode_temporal", "decode", "decode_plain"):
            assert TIMING_KEYS <= set(r[key]), (key, r[key])
            assert all(math.isfinite(r[key][k]) and r[key][k] >= 0 for k in TIMING_KEYS)
        assert r["encode"]["consistency"] == "spatial"
        assert r["encode_local"]["consistency"] == "none"
        assert r["encode_temporal"]["consistency"] == "temporal"
        assert r["cholespy_solve_3rhs_ms"] > 0 and r["decode_over_solve"] > 0
        assert r["prepare_s"] > 0 and r["cholespy_factor_s"] is not None
        rt = r["roundtrip"]
        assert np.isfinite(rt["mean_rel"]) and np.isfinite(rt["max_rel"]) and rt["max_rel"] >= rt["mean_rel"] >= 0
        # a smooth tube decodes close to itself: catches a broken pipeline, not a precision regression
        assert rt["max_rel"] < 0.1

    table = bench.format_table(records)
    assert "float32" in table and "dataset" in table


def test_handles_benchmark_smoke(tmp_path):
    """benchmarks/handles.py (seed 004 rebind and pose timings) on a tiny mesh: every field is written."""
    import trimesh

    from benchmarks import handles as hbench

    m = trimesh.creation.icosphere(subdivisions=2)
    mesh = tmp_path / "ico.obj"
    save_mesh(mesh, np.asarray(m.vertices), np.asarray(m.faces))
    out = tmp_path / "bench" / "handles.json"
    payload = hbench.main(["--mesh", str(mesh), "--json", str(out), "--channels", "8", "--handles", "1", "3",
                           "--repeats", "2", "--pose-faces", "300", "--pose-handles", "3", "--pose-frames", "2"])
    on_disk = json.loads(out.read_text())
    assert on_disk == json.loads(json.dumps(payload))
    assert not [p for p in out.parent.iterdir() if p.name != out.name]
    assert (on_disk["vertices"], on_disk["faces"], on_disk["channels"]) == (len(m.vertices), len(m.faces), 8)
    assert [r["handles"] for r in on_disk["rebind"]] == [1, 3] and set(on_disk["rebind_ms"]) == {"1", "3"}
    for r in on_disk["rebind"]:
        assert {"bucket", "compile_s", "ms_median", "ms_min", "ms_host_median"} <= set(r)
        assert 0 <= r["ms_min"] <= r["ms_median"] and r["compile_s"] > 0
    assert on_disk["pose_mesh"]["faces"] >= 300 and on_disk["pose_mesh"]["handles"] == 3
    assert {r["variant"] for r in on_disk["pose"]} == {"affine", "translation", "pou", "symmetric", "deformer", "deformer_pou",
                                                     "deformer_symmetric"}
    assert on_disk["pose_mesh"]["symmetry_plane"] == "x"
    assert all(r["fps_median"] > 0 and math.isfinite(r["fps_median"]) for r in on_disk["pose"])
    assert set(on_disk["pose_fps"]) == {r["variant"] for r in on_disk["pose"]}
    assert "rebind" in hbench.format_table(on_disk)
