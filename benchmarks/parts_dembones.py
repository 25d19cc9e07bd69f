"""Peer comparison: Dem Bones (SSDR, through ``py_dem_bones``) with rigid skinning on a mesh sequence.

    python -m benchmarks.parts_dembones --data ../shared/data/horse-gallop --bones 23 --json out/bench/dembones.json

Dem Bones (Le & Deng 2012, Smooth Skinning Decomposition with Rigid Bones) fits ``--bones`` bone transforms
per frame and sparse convex vertex weights; here with ``nnz = 1`` (at most one influence per vertex, i.e. a
rigid segmentation, the setting comparable to a part decomposition). The rest pose is frame 0 and every frame
(frame 0 included) is an animated pose. Every frame is then reconstructed by linear blend skinning from the
rest pose with the learned weights and transforms,

    p_t,v = sum_b w_b,v  M_t,b [u_v; 1],

and the RMSE (root mean square per-vertex distance over all frames and vertices, data units) and the RMSE
divided by the bounding-box diagonal of frame 0 are reported. ``--ours RUN_SUMMARY_JSON`` copies that file's
contents unchanged under ``"ours"`` so both results land in one JSON. The JSON is written atomically (temp
file + ``os.replace``); its fields are described in benchmarks/README.md. Not a test: pytest never runs it.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.acap import cpu_info, write_json_atomic


def _import_dem_bones():
    try:
        import py_dem_bones
        from py_dem_bones._py_dem_bones import DemBones
    except ImportError:
        return None, None
    return py_dem_bones, DemBones


def run_dem_bones(
    DemBones,
    frames: np.ndarray,
    faces: np.ndarray,
    *,
    bones: int,
    nnz: int,
    n_iters: int,
    n_init_iters: int,
    n_trans_iters: int,
    n_weights_iters: int,
):
    """Fit Dem Bones; returns (weights (B, V), transforms (T, B, 4, 4) column-vector, seconds, solver)."""
    rest = np.ascontiguousarray(frames[0], dtype=np.float64)
    n_frames, n_vertices = frames.shape[:2]
    solver = DemBones()
    solver.nV = n_vertices
    solver.nF = n_frames
    solver.nS = 1  # one subject
    solver.nB = int(bones)
    solver.nnz = int(nnz)
    solver.nIters = int(n_iters)
    solver.nInitIters = int(n_init_iters)
    solver.nTransIters = int(n_trans_iters)
    solver.nWeightsIters = int(n_weights_iters)
    solver.fStart = np.array([0, n_frames], dtype=np.int32)
    solver.subjectID = np.zeros(n_frames, dtype=np.int32)
    solver.u = np.ascontiguousarray(rest.T)  # (3 * nS, V)
    solver.v = np.ascontiguousarray(frames.transpose(0, 2, 1).reshape(3 * n_frames, n_vertices))  # (3 T, V)
    solver.fv = np.asarray(faces, dtype=np.int64).tolist()
    t0 = time.perf_counter()
    solver.compute()
    seconds = time.perf_counter() - t0
    n_bones = int(solver.nB)
    weights = np.asarray(solver.get_weights(), dtype=np.float64)
    if weights.shape != (n_bones, n_vertices):
        raise RuntimeError(f"Dem Bones returned weights of shape {weights.shape}, expected ({n_bones}, {n_vertices}).")
    blocks = np.asarray(solver.m, dtype=np.float64)  # (4 T, 4 B): frame t, bone b at [4t:4t+4, 4b:4b+4]
    if blocks.shape != (4 * n_frames, 4 * n_bones):
        raise RuntimeError(f"Dem Bones returned transforms of shape {blocks.shape}.")
    transforms = blocks.reshape(n_frames, 4, n_bones, 4).transpose(0, 2, 1, 3)
    return weights, transforms, seconds, solver


def skin(rest: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Linear blend skinning: (T, V, 3) from rest (V, 3), weights (B, V), transforms (T, B, 4, 4)."""
    per_bone = np.einsum("tbij,vj->tbvi", transforms[:, :, :3, :3], rest) + transforms[:, :, None, :3, 3]
    return np.einsum("bv,tbvi->tvi", weights, per_bone)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m benchmarks.parts_dembones", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--data", required=True, help="folder (or .npz) of meshes sharing one connectivity; rest pose = first"
    )
    p.add_argument("--bones", type=int, required=True, help="number of bones to ask Dem Bones for")
    p.add_argument("--json", required=True, help="output JSON path (parent folders are created)")
    p.add_argument("--ours", default=None, help="a run-summary JSON to copy under 'ours' in the output")
    p.add_argument("--nnz", type=int, default=1, help="max influences per vertex (1 = rigid skinning)")
    p.add_argument("--iters", type=int, default=30, help="Dem Bones nIters (global iterations)")
    p.add_argument("--init-iters", type=int, default=10, help="Dem Bones nInitIters (clustering initialisation)")
    p.add_argument("--trans-iters", type=int, default=5, help="Dem Bones nTransIters (per global iteration)")
    p.add_argument("--weights-iters", type=int, default=3, help="Dem Bones nWeightsIters (per global iteration)")
    return p.parse_args(argv)


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    py_dem_bones, DemBones = _import_dem_bones()
    if DemBones is None:
        print(
            "py_dem_bones is not importable: install it with `.venv/bin/pip install py-dem-bones==0.13.1`.",
            file=sys.stderr,
        )
        raise SystemExit(2)
    if args.bones < 1:
        raise SystemExit("--bones must be at least 1.")
    ours = None
    if args.ours is not None:
        try:
            ours = json.loads(Path(args.ours).read_text())
        except (OSError, ValueError) as exc:
            raise SystemExit(f"--ours {args.ours}: cannot read it as JSON ({exc}).") from None

    from jaxdeform.mesh import load_sequence

    frames, faces = load_sequence(args.data)
    frames = np.asarray(frames, dtype=np.float64)
    n_frames, n_vertices = frames.shape[:2]
    print(f"data: {args.data}: {n_frames} frames, {n_vertices} vertices, {faces.shape[0]} faces")

    load_before = os.getloadavg()[0]
    weights, transforms, seconds, solver = run_dem_bones(
        DemBones,
        frames,
        faces,
        bones=args.bones,
        nnz=args.nnz,
        n_iters=args.iters,
        n_init_iters=args.init_iters,
        n_trans_iters=args.trans_iters,
        n_weights_iters=args.weights_iters,
    )
    recon = skin(frames[0], weights, transforms)
    dist = np.linalg.norm(recon - frames, axis=-1)  # (T, V)
    rmse = float(np.sqrt(np.mean(dist**2)))
    diag = float(np.linalg.norm(frames[0].max(axis=0) - frames[0].min(axis=0)))
    per_frame = np.sqrt(np.mean(dist**2, axis=1))
    influences = (weights > 0).sum(axis=0)
    used = int(np.count_nonzero(weights.sum(axis=1) > 0))

    dem = {
        "bones_requested": int(args.bones),
        "bones_returned": int(weights.shape[0]),
        "bones_used": used,
        "nnz": int(args.nnz),
        "nIters": int(args.iters),
        "nInitIters": int(args.init_iters),
        "nTransIters": int(args.trans_iters),
        "nWeightsIters": int(args.weights_iters),
        "seconds": round(seconds, 3),
        "rmse": rmse,
        "rmse_over_diag": rmse / diag,
        "max_error_over_diag": float(dist.max() / diag),
        "worst_frame": int(np.argmax(per_frame)),
        "worst_frame_rmse_over_diag": float(per_frame.max() / diag),
        "dembones_rmse": float(solver.rmse()),
        "max_influences_per_vertex": int(influences.max()),
        "weights_sum_min": float(weights.sum(axis=0).min()),
        "weights_sum_max": float(weights.sum(axis=0).max()),
    }
    payload = {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": "python -m benchmarks.parts_dembones " + shlex.join(argv),
        "data": str(args.data),
        "frames": int(n_frames),
        "vertices": int(n_vertices),
        "faces": int(faces.shape[0]),
        "bbox_diag_frame0": diag,
        "py_dem_bones_version": getattr(py_dem_bones, "__version__", None),
        "dem_bones_version": getattr(py_dem_bones, "__dem_bones_version__", None),
        "cpu": cpu_info(),
        "load_avg_1m": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "python": platform.python_version(),
        "dembones": dem,
    }
    if ours is not None:
        payload["ours"] = ours
    write_json_atomic(Path(args.json), payload)
    print(
        f"Dem Bones: {dem['bones_returned']} bones ({used} used) of {args.bones} asked, nnz={args.nnz}, "
        f"{seconds:.2f} s; RMSE {rmse:.6g} (data units), RMSE/diag {rmse / diag:.5f}"
    )
    print(f"wrote {args.json}")
    return payload


if __name__ == "__main__":
    main()
