"""Demo: ACAP / TS-ACAP round trip on the synthetic bending tube (``python -m jaxdeform.demo --out out/demo``).

Generates :func:`~jaxdeform.data.synthetic.bending_tube_sequence` (24 frames: a tube bending into a spiral past
a full turn, twisting, with transient bumps), encodes it with each rotation-consistency mode (none, spatial,
temporal), decodes the features back to positions and prints, per mode: the largest rotation angle |v| of the
(consistent) axis-angle vectors, the mean and max round-trip vertex error as a fraction of each frame's
bounding-box diagonal (after removing each frame's mean translation: features carry none), and encode and
decode times per frame after a warm-up call (median of a few repeats).

Writes to OUT: ``reference.png`` (the rest tube), ``deformed.png`` (the last frame), ``error.png`` (the last
frame as decoded from spatial-ACAP features, coloured by its per-vertex round-trip error), ``rotation_angle.png``
(the last frame coloured by the per-vertex TS-ACAP rotation angle |v| in rad) and ``summary.json`` (the
table's numbers and the set-up). Small enough to run in under a minute on a CPU.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import numpy as np

from jaxdeform.acap.features import DEFAULT_REFINE, features_from, prepare
from jaxdeform.data.synthetic import bending_tube_sequence

MODES = ("none", "spatial", "temporal")
REPEATS = 3
WIDTH, HEIGHT = 800, 600
# The tube bends (nearly) in the x-y plane: look at it from +z, a little from above.
VIEW = dict(azimuth_deg=0.0, elevation_deg=25.0)


def _timed(fn, repeats: int = REPEATS) -> tuple[object, float]:
    """Run ``fn`` once to warm up (compile), then ``repeats`` times; (last result, median seconds)."""
    jax.block_until_ready(fn())
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return result, statistics.median(times)


def round_trip_errors(original: np.ndarray, decoded: np.ndarray) -> np.ndarray:
    """Per-vertex error after removing each frame's mean translation, over each frame's bbox diagonal.

    **Arguments:**

    - ``original``: the frames ``(N, V, 3)``.
    - ``decoded``: their round trip ``(N, V, 3)``.

    **Returns:**

    The relative errors ``(N, V)``.
    """
    a = original - original.mean(axis=1, keepdims=True)
    b = decoded - decoded.mean(axis=1, keepdims=True)
    diag = np.linalg.norm(original.max(axis=1) - original.min(axis=1), axis=-1)  # (N,)
    return np.linalg.norm(a - b, axis=-1) / diag[:, None]


def format_table(rows: list[dict]) -> str:
    """The demo's result rows as a plain-text table.

    **Arguments:**

    - ``rows``: one dict per consistency mode (consistency, angles, errors, encode / decode times).

    **Returns:**

    The table as one string.
    """
    headers = [
        "consistency",
        "max angle (rad)",
        "mean err / diag",
        "max err / diag",
        "encode ms/frame",
        "decode ms/frame",
    ]
    cells = [
        [
            r["consistency"],
            f"{r['max_angle_rad']:.4f}",
            f"{r['mean_error']:.3e}",
            f"{r['max_error']:.3e}",
            f"{r['encode_ms_per_frame']:.2f}",
            f"{r['decode_ms_per_frame']:.2f}",
        ]
        for r in rows
    ]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(headers)]

    def line(items):
        return "  ".join(s.ljust(w) if i == 0 else s.rjust(w) for i, (s, w) in enumerate(zip(items, widths)))

    return "\n".join([line(headers), line(["-" * w for w in widths])] + [line(c) for c in cells])


def _round_trips(acap, vertices) -> tuple[list, dict, dict, dict]:
    """Encode and decode ``vertices`` (n, V, 3) with ``acap`` once per consistency mode of ``MODES``, in order.

    Returns ``(rows, decoded_by_mode, v_by_mode, err_by_mode)``: one result row per mode (angles, errors,
    median ms per frame) and, per mode, the decoded positions, rotation vectors and per-vertex errors.
    """
    n = vertices.shape[0]
    rows, decoded_by_mode, v_by_mode, err_by_mode = [], {}, {}, {}
    for mode in MODES:
        (v, s), enc_s = _timed(lambda: acap.encode_parts(vertices, mode))
        features = features_from(v, s)
        decoded, dec_s = _timed(lambda: acap.decode(features))
        v, decoded = np.asarray(v), np.asarray(decoded)
        err = round_trip_errors(vertices, decoded)
        decoded_by_mode[mode], v_by_mode[mode], err_by_mode[mode] = decoded, v, err
        rows.append(
            {
                "consistency": mode,
                "max_angle_rad": float(np.linalg.norm(v, axis=-1).max()),
                "mean_error": float(err.mean()),
                "max_error": float(err.max()),
                "encode_ms_per_frame": 1e3 * enc_s / n,
                "decode_ms_per_frame": 1e3 * dec_s / n,
            }
        )
    return rows, decoded_by_mode, v_by_mode, err_by_mode


def _images(rest, faces, vertices, decoded_by_mode, v_by_mode, err_by_mode) -> dict:
    """Render the demo's four images of the last frame (reference, deformed, spatial-mode error, temporal-mode
    rotation angle). Returns ``{file name: image}`` in the order they are saved; writes nothing."""
    from jaxdeform.mesh.render import auto_camera, render

    n = vertices.shape[0]
    last = n - 1
    return {
        "reference.png": render(rest, faces, camera=auto_camera(rest, **VIEW), width=WIDTH, height=HEIGHT),
        "deformed.png": render(
            vertices[last], faces, camera=auto_camera(vertices[last], **VIEW), width=WIDTH, height=HEIGHT
        ),
        "error.png": render(
            decoded_by_mode["spatial"][last],
            faces,
            camera=auto_camera(decoded_by_mode["spatial"][last], **VIEW),
            scalar=err_by_mode["spatial"][last],
            vmin=0.0,
            width=WIDTH,
            height=HEIGHT,
            cmap="viridis",
            label="error / bbox diag",
        ),
        "rotation_angle.png": render(
            vertices[last],
            faces,
            camera=auto_camera(vertices[last], **VIEW),
            scalar=np.linalg.norm(v_by_mode["temporal"][last], axis=-1),
            vmin=0.0,
            width=WIDTH,
            height=HEIGHT,
            cmap="viridis",
            label="|v| (rad)",
        ),
    }


def _write_summary(out: Path, n, nv, faces, rows, prepare_s, compute_s, render_s) -> Path:
    """Write out/summary.json (data, normalisation, timings, images, environment and the result ``rows``)
    atomically through a hidden temporary file. Returns its path."""
    summary = {
        "data": {
            "generator": "bending_tube_sequence",
            "n_frames": int(n),
            "n_vertices": int(nv),
            "n_faces": int(faces.shape[0]),
        },
        "error_normalisation": "per-vertex distance after removing each frame's mean translation, divided by "
        "that frame's bounding-box diagonal",
        "decode_refine_steps": DEFAULT_REFINE,
        "timing": {
            "repeats": REPEATS,
            "statistic": "median after one warm-up call",
            "prepare_s": prepare_s,
            "compute_s": compute_s,
            "render_s": render_s,
        },
        "images": {
            "error.png": "spatial consistency, last frame",
            "rotation_angle.png": "temporal consistency, last frame",
        },
        "environment": {
            "jax": jax.__version__,
            "backend": jax.default_backend(),
            "python": platform.python_version(),
            "machine": platform.machine(),
        },
        "results": rows,
    }
    summary_path = out / "summary.json"
    tmp = summary_path.with_name(f".{summary_path.name}.tmp")
    tmp.write_text(json.dumps(summary, indent=2) + "\n")
    tmp.replace(summary_path)
    return summary_path


def run(out: Path, n_frames: int = 24) -> dict:
    """Run the demo: ACAP round trips of a bending tube, figures and a summary.

    **Arguments:**

    - ``out``: the folder for the PNGs and summary.json (created if needed).
    - ``n_frames``: frames of the bending tube sequence.

    **Returns:**

    A dict: ``rows`` (one per consistency mode), ``paths`` (the files written), ``n``, ``nv``, ``nf`` (frames, vertices,
    faces) and the seconds ``prepare_s``, ``compute_s``, ``render_s``, ``total_s``.
    """
    from jaxdeform.mesh.render import save_png

    t_start = time.perf_counter()
    vertices, faces = bending_tube_sequence(n_frames)
    n, nv = vertices.shape[:2]
    rest = vertices[0]

    t0 = time.perf_counter()
    acap = prepare(rest, faces)
    prepare_s = time.perf_counter() - t0

    rows, decoded_by_mode, v_by_mode, err_by_mode = _round_trips(acap, vertices)
    compute_s = time.perf_counter() - t_start

    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    images = _images(rest, faces, vertices, decoded_by_mode, v_by_mode, err_by_mode)
    paths = [save_png(img, out / name) for name, img in images.items()]
    render_s = time.perf_counter() - t0

    summary_path = _write_summary(out, n, nv, faces, rows, prepare_s, compute_s, render_s)
    return {
        "rows": rows,
        "paths": paths + [summary_path],
        "n": n,
        "nv": nv,
        "nf": faces.shape[0],
        "prepare_s": prepare_s,
        "compute_s": compute_s,
        "render_s": render_s,
        "total_s": time.perf_counter() - t_start,
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point (``python -m jaxdeform.demo``).

    **Arguments:**

    - ``argv``: the arguments (default None: ``sys.argv[1:]``); ``--out`` folder, ``--frames`` (at least 2).

    **Returns:**

    The exit status, 0.
    """
    parser = argparse.ArgumentParser(prog="python -m jaxdeform.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/demo", help="folder for the PNGs and summary.json (default out/demo)")
    parser.add_argument("--frames", type=int, default=24, help="number of frames (default 24)")
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error("--frames must be at least 2.")
    res = run(Path(args.out), args.frames)
    print(
        f"bending tube: {res['n']} frames, {res['nv']} vertices, {res['nf']} faces "
        f"(jax {jax.__version__}, {jax.default_backend()}); prepare {res['prepare_s']:.2f} s"
    )
    print(format_table(res["rows"]))
    print(
        f"errors: after removing each frame's mean translation, over the frame's bbox diagonal; times: median of "
        f"{REPEATS} after a warm-up call"
    )
    print(f"compute {res['compute_s']:.1f} s, render {res['render_s']:.1f} s, total {res['total_s']:.1f} s")
    print(f"wrote {len(res['paths'])} files to {Path(args.out)}/: " + ", ".join(p.name for p in res["paths"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
