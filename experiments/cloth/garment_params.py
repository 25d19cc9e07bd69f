"""Which fabric makes a garment's paired data learnable: one garment scenario simulated with several physics.

    python -m experiments.cloth.garment_params [--kind skirt] [--index 2] [--frames 165] \\
        [--variants default damped stiff-damped] [--json OUT.json]

For each variant (:data:`VARIANTS`: overrides of the scenario's :class:`ClothParams`, the same at both
resolutions) the coarse and the fine cloth are simulated (``scenarios.simulate_pair``) and the fine one again from a
start perturbed by 0.1 mm (``scenarios.simulate_fine``). Printed and written per variant: the Loop-upsampled coarse
cloth's RMSE against the fine one, its share at the coarse mesh's scale (``evaluate.coarse_level_split``: how far
the two resolutions agree at the coarse scale), the perturbed fine cloth's RMSE (the floor) and its ratio to the
upsampled coarse RMSE (issue 55's bar: at most 0.2), the largest edge strains and penetrations, and seconds per
frame.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from jaxdeform.cloth import evaluate as ceval
from jaxdeform.cloth import scenarios

#: name -> ClothParams overrides (both resolutions)
VARIANTS = {
    "default": {},
    "damped": {"damping": 2.0},
    "stiff-damped": {"bend_stiffness": 1.0e-4, "damping": 2.0},
    "stiff-damped-untethered": {"bend_stiffness": 1.0e-4, "damping": 2.0, "tethers": False},
}


def measure(kind: str, index: int, frames: int, overrides: dict) -> dict:
    sc = scenarios.scenario(kind, index, n_frames=frames)
    sc = dataclasses.replace(sc, params=sc.params.replace(**overrides))
    t0 = time.perf_counter()
    pair = scenarios.simulate_pair(sc, progress=False)
    again = scenarios.simulate_fine(sc, perturbation=1e-4)
    ups = ceval.Upsampler(pair["coarse_faces"], pair["coarse"].shape[1], pair["fine_faces"])
    fine = pair["fine"].astype(np.float64)
    gap = fine - ups(pair["coarse"])
    low, high = ceval.coarse_level_split(ups, gap)
    up_rmse = float(np.sqrt(np.mean(np.sum(gap**2, -1))))
    floor = float(np.sqrt(np.mean(np.sum((again - fine) ** 2, -1))))
    m = pair["meta"]
    return {
        "overrides": overrides,
        "upsampled_coarse_rmse": up_rmse,
        "coarse_scale_share": float(np.sum(low**2) / np.sum(gap**2)),
        "finer_rmse": float(np.sqrt(np.mean(np.sum(high**2, -1)))),
        "perturbed_fine_rmse": floor,
        "floor_ratio": floor / up_rmse,
        "strain_max": [m["coarse_strain_max"], m["fine_strain_max"]],
        "penetration_max_m": [m["coarse_max_penetration"], m["fine_max_penetration"]],
        "seconds_per_frame": [m["coarse_seconds_per_frame"], m["fine_seconds_per_frame"]],
        "wall_seconds": time.perf_counter() - t0,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kind", default="skirt", choices=scenarios.GARMENT_KINDS)
    ap.add_argument("--index", type=int, default=2)
    ap.add_argument("--frames", type=int, default=scenarios.GARMENT_FRAMES)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    out = {"kind": args.kind, "index": args.index, "frames": args.frames, "variants": {}}
    for name in args.variants:
        r = measure(args.kind, args.index, args.frames, VARIANTS[name])
        out["variants"][name] = r
        print(
            f"{args.kind} {args.index} {name}: upsampled coarse {r['upsampled_coarse_rmse']:.4f} m "
            f"({100 * r['coarse_scale_share']:.1f}% at the coarse scale), perturbed fine {r['perturbed_fine_rmse']:.4f} m "
            f"= {r['floor_ratio']:.2f}x; strain {r['strain_max']}, penetration {r['penetration_max_m']}",
            flush=True,
        )
        if args.json:
            Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
