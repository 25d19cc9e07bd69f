"""``jaxdeform parts fit|interpolate|show``: rigid parts of a shape population (:mod:`jaxdeform.parts`).

``fit DATA... --out RUN`` writes ``RUN/run.json``, ``RUN/summary.json`` and ``RUN/model`` (orbax);
``interpolate RUN --source A --target B --out DIR`` writes OBJ frames, ``strip.png`` and ``gaps.json``; ``show RUN
--out DIR`` writes ``segmentation.png``, ``error.png`` and ``reconstruction.png``. Output folders are built beside ``--out`` and
renamed at the end.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from jaxdeform.cli import common


def cmd_parts_fit(args: argparse.Namespace) -> int:
    from jaxdeform.parts import run as prun

    common.check_exists(args.data)
    out = Path(args.out)
    common.check_out_folder(out, args.force, args.data)
    if args.initial_parts < 1:
        raise ValueError(f"--initial-parts must be at least 1, got {args.initial_parts}.")
    if not args.threshold > 0:
        raise ValueError(f"--threshold must be positive, got {args.threshold}.")
    config = prun.Config(initial_parts=args.initial_parts, threshold=args.threshold)
    with common.writing(out):
        run = prun.fit(args.data if len(args.data) > 1 else args.data[0], config, out)
    info = run.record["summary"]
    print(
        f"{info['parts']} parts from {info['shapes']} shapes x {info['vertices']} vertices in "
        f"{info['seconds']:.1f} s (AECM iterations {info['iterations']}); rmse {info['rmse']:.4g} "
        f"({info['rmse_over_diagonal']:.2e} of the bbox diagonal); wrote {out}/run.json, summary.json, model"
    )
    return 0


def _shape_index(value: int, n: int, name: str) -> int:
    """``value`` checked to index one of ``n`` shapes (negative indices are refused, not counted from the end)."""
    if not 0 <= value < n:
        raise ValueError(f"--{name} {value} is not a shape of the run (it has {n} shapes: 0..{n - 1}).")
    return value


def cmd_parts_interpolate(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from jaxdeform.mesh.io import save_mesh
    from jaxdeform.parts import figures, hierarchy, interpolate
    from jaxdeform.parts import run as prun

    common.check_exists([args.run])
    out = Path(args.out)
    common.check_out_folder(out, args.force, [args.run])
    if args.steps < 2:
        raise ValueError(f"--steps must be at least 2 (the two end shapes), got {args.steps}.")
    run = prun.Run.load(args.run)
    fit, vertices, faces = run.fit, run.vertices, run.faces
    n = vertices.shape[0]
    a, b = _shape_index(args.source, n, "source"), _shape_index(args.target, n, "target")
    ts = np.linspace(0.0, 1.0, args.steps)
    t0 = time.perf_counter()
    frames = interpolate.interpolate(fit.params, fit.labels, fit.latent, faces, vertices, a, b, ts)
    gaps = interpolate.contact_gaps(fit.params, fit.labels, fit.latent, faces, vertices, a, b, ts)
    elapsed = time.perf_counter() - t0
    diag = hierarchy.bbox_diagonal(vertices)
    width = max(3, len(str(args.steps - 1)))
    worst = float(np.max(gaps)) / diag if np.size(gaps) else 0.0
    with common.staged_folder(out) as tmp:
        for k in range(args.steps):
            save_mesh(tmp / f"{k:0{width}d}.obj", frames[k], faces)
        figures.strip_figure(frames, faces, tmp / "strip.png", labels=fit.labels)
        (tmp / "gaps.json").write_text(
            json.dumps(
                {
                    "source": a,
                    "target": b,
                    "t": ts.tolist(),
                    "joints": int(np.shape(gaps)[1]) if np.ndim(gaps) == 2 else 0,
                    "max_gap": float(np.max(gaps)) if np.size(gaps) else 0.0,
                    "max_gap_over_diagonal": worst,
                    "gaps": np.asarray(gaps).tolist(),
                    "seconds": round(elapsed, 4),
                },
                indent=2,
            )
        )
    print(
        f"interpolated shape {a} -> {b} in {args.steps} steps ({elapsed:.2f} s); largest joint gap "
        f"{worst:.2e} of the bbox diagonal; wrote {out}/000.obj.., strip.png, gaps.json"
    )
    return 0


def cmd_parts_show(args: argparse.Namespace) -> int:
    from jaxdeform.parts import run as prun

    common.check_exists([args.run])
    out = Path(args.out)
    common.check_out_folder(out, args.force, [args.run])
    run = prun.Run.load(args.run)
    shape = _shape_index(args.shape, run.vertices.shape[0], "shape")
    with common.staged_folder(out) as tmp:
        prun.show(run, tmp, shape=shape)
    print(f"{run.fit.n_parts} parts; wrote {out}/segmentation.png, error.png, reconstruction.png")
    return 0


def register(sub) -> None:
    """Add ``parts fit|interpolate|show`` to the top-level subparsers ``sub``."""
    parts = sub.add_parser(
        "parts",
        help="Rigid parts of a shape population (mixtures of factor analyzers).",
        description="Pose variations by rotation-constrained mixtures of factor analyzers "
        "(seed 003): fit, interpolate, show.",
    )
    parts_sub = parts.add_subparsers(dest="parts_command", metavar="ACTION", required=True)
    pfit = parts_sub.add_parser(
        "fit",
        help="Fit the hierarchy of part analyzers to shapes sharing one connectivity.",
        description="Fit Algorithm 1 and write RUN/run.json, RUN/summary.json and RUN/model (orbax).",
    )
    pfit.add_argument("data", nargs="+", metavar="DATA", help="mesh files or folders of them (at least 2 shapes)")
    common.add_out(pfit, "RUN", "run folder to create")
    pfit.add_argument("--initial-parts", type=int, default=8, metavar="N", help="parts of the coarse stage (default 8)")
    pfit.add_argument(
        "--threshold",
        type=float,
        default=2.5e-5,
        metavar="X",
        help="average variance (unit-box units squared) under which a part is not split (default 2.5e-5)",
    )
    common.add_force(pfit, "replace RUN if it exists and is not empty")
    pfit.set_defaults(func=cmd_parts_fit)
    pint = parts_sub.add_parser(
        "interpolate",
        help="Interpolate the pose between two shapes of a run.",
        description="Algorithm 2: slerp of part rotations, joints kept in contact.",
    )
    pint.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform parts fit'")
    pint.add_argument("--source", type=int, required=True, metavar="A", help="index of the first shape")
    pint.add_argument("--target", type=int, required=True, metavar="B", help="index of the last shape")
    common.add_steps(pint, "frames including both ends (default 8)", default=8)
    common.add_out(pint, "DIR", "folder to create (OBJ frames, strip.png, gaps.json)")
    common.add_force(pint, "replace DIR if it exists and is not empty")
    pint.set_defaults(func=cmd_parts_interpolate)
    pshow = parts_sub.add_parser(
        "show",
        help="Render the segmentation and the reconstruction error of a run.",
        description="Write segmentation.png (three views), error.png, reconstruction.png.",
    )
    pshow.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform parts fit'")
    common.add_out(pshow, "DIR", "folder to create")
    pshow.add_argument("--shape", type=int, default=0, metavar="M", help="shape to draw the parts on (default 0)")
    common.add_force(pshow, "replace DIR if it exists and is not empty")
    pshow.set_defaults(func=cmd_parts_show)
