"""Seed 003 experiments: rigid parts of horse-poses, horse-gallop and cactus, against Dem Bones (rigid).

    python -m experiments.parts.run [--data ../shared/data] [--out out/experiments/parts] [--datasets ...]

For each data set: Algorithm 1 (``jaxdeform.parts.hierarchy.fit``) with the library defaults; parts per stage,
AECM iterations per stage, reconstruction RMSE and seconds; the run folder (model, summary.json), the
segmentation, error and reconstruction figures, and an interpolation strip between two shapes with the joint
gaps. Then, in the same process, Dem Bones (py-dem-bones, optional: ``pip install py-dem-bones==0.13.1``) with
one influence per vertex and as many bones as we found parts, on the same shapes. Everything lands in
OUT/results.json and OUT/results.md (written atomically).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from jaxdeform.mesh.io import atomic_path
from jaxdeform.parts import figures, hierarchy, interpolate
from jaxdeform.parts import run as prun

# (data set, source, target) of the interpolation strip
DATASETS = {"horse-poses": (0, 5), "horse-gallop": (0, 24), "cactus": (0, 10)}


def dem_bones(frames, faces, bones: int) -> dict:
    try:  # py-dem-bones: the optional `bench` extra
        from py_dem_bones import DemBones

        from benchmarks.parts_dembones import run_dem_bones, skin
    except ImportError:
        return {"available": False}
    weights, transforms, seconds, _ = run_dem_bones(
        DemBones, frames, faces, bones=bones, nnz=1, n_iters=30, n_init_iters=10, n_trans_iters=5, n_weights_iters=3
    )
    rec = skin(frames[0], weights, transforms)
    err = hierarchy.rmse(frames, rec)
    return {
        "available": True,
        "bones_asked": bones,
        "bones_used": int((weights.max(axis=1) > 0).sum()),
        "rmse": err,
        "rmse_over_diagonal": err / hierarchy.bbox_diagonal(frames),
        "seconds": round(seconds, 3),
    }


def run_one(name: str, data: Path, out: Path) -> dict:
    result = prun.fit(data / name, "default", out / name, log=lambda s: print(f"  {s}", flush=True))
    run, fit, frames, faces = out / name, result.fit, result.vertices, result.faces
    info = result.record["summary"]
    err = np.sqrt(np.mean(np.sum((frames - fit.reconstruction) ** 2, axis=-1), axis=0))
    figures.segmentation_figure(frames[0], faces, fit.labels, run / "segmentation.png")
    figures.error_figure(frames[0], faces, err, run / "error.png", label="RMS reconstruction error")
    a, b = DATASETS.get(name, (0, frames.shape[0] // 2))
    b = min(b, frames.shape[0] - 1)
    ts = np.linspace(0, 1, 6)
    strip = interpolate.interpolate(fit.params, fit.labels, fit.latent, faces, frames, a, b, ts)
    gaps = interpolate.contact_gaps(fit.params, fit.labels, fit.latent, faces, frames, a, b, ts)
    figures.strip_figure(strip, faces, run / "interpolation.png", labels=fit.labels)
    ours = {
        k: info[k]
        for k in (
            "parts",
            "iterations",
            "parts_per_stage",
            "rmse",
            "rmse_over_diagonal",
            "seconds",
            "disconnected_parts",
            "loglik_monotone",
            "rotation_det_range",
        )
    }
    ours["max_joint_gap_over_diagonal"] = (
        float(np.max(gaps)) / hierarchy.bbox_diagonal(frames) if np.size(gaps) else 0.0
    )
    ours["interpolation"] = [a, b]
    peer = dem_bones(frames, faces, info["parts"])
    return {
        "dataset": name,
        "shapes": int(frames.shape[0]),
        "vertices": int(frames.shape[1]),
        "ours": ours,
        "dem_bones_rigid": peer,
    }


def table(results: list[dict]) -> str:
    rows = [
        "| data | shapes | parts (coarse/refined/final) | AECM iterations (coarse/refine/final) | ours RMSE / diag | "
        "ours s | Dem Bones rigid, same bones: RMSE / diag | Dem Bones s | max joint gap / diag |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        o, d = r["ours"], r["dem_bones_rigid"]
        pps, its = o["parts_per_stage"], o["iterations"]
        peer = (
            f"{d['rmse_over_diagonal']:.5f} ({d['bones_used']} bones used)" if d.get("available") else "not installed"
        )
        rows.append(
            f"| {r['dataset']} | {r['shapes']} | {pps['coarse']}/{pps['refine']}/{pps['final']} | "
            f"{its['coarse']}/{its['refine']}/{its['final']} | {o['rmse_over_diagonal']:.5f} | {o['seconds']:.1f} | "
            f"{peer} | {d.get('seconds', '-')} | {o['max_joint_gap_over_diagonal']:.1e} |"
        )
    return "\n".join(rows)


def _write(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(prog="python -m experiments.parts.run", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default="../shared/data")
    p.add_argument("--out", default="out/experiments/parts")
    p.add_argument(
        "--datasets", nargs="+", default=list(DATASETS), help="folders under --data (default: the three of the study)"
    )
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for name in args.datasets:
        print(f"{name}:", flush=True)
        if not (Path(args.data) / name).exists():
            raise SystemExit(f"{Path(args.data) / name}: no such data set.")
        results.append(run_one(name, Path(args.data), out))
        print(
            f"  {json.dumps(results[-1]['ours'])}\n  dem bones: {json.dumps(results[-1]['dem_bones_rigid'])}",
            flush=True,
        )
    md = table(results)
    _write(
        out / "results.json",
        json.dumps(
            {
                "python": platform.python_version(),
                "cpu_count": os.cpu_count(),
                "date": time.strftime("%Y-%m-%d"),
                "results": results,
            },
            indent=2,
        ),
    )
    _write(out / "results.md", md + "\n")
    print(md)
    return results


if __name__ == "__main__":
    main()
