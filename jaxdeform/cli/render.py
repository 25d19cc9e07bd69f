"""``jaxdeform render MESH [--scalar FILE.npy] [--out FILE.png]``: ray-cast one mesh to a PNG
(:mod:`jaxdeform.mesh.render`), optionally coloured by one value per vertex; the default output is MESH with a
.png suffix."""

from __future__ import annotations

import argparse
import time
import zipfile
from pathlib import Path

from jaxdeform.cli import common
from jaxdeform.errors import MeshFormatError

CMAPS = ("viridis", "coolwarm", "viridis_r", "coolwarm_r")


def _read_scalar(path: str, mesh: Path, n_vertices: int):
    """The per-vertex values of a .npy file, checked against the mesh's vertex count."""
    import numpy as np

    try:
        scalar = np.load(path, allow_pickle=False)
    except (ValueError, EOFError, zipfile.BadZipFile, NotImplementedError, RuntimeError) as exc:
        raise MeshFormatError(f"{path}: not a readable .npy array ({type(exc).__name__}).") from None
    if not isinstance(scalar, np.ndarray):
        scalar.close()
        raise MeshFormatError(f"{path}: is a .npz archive; give a .npy array of one value per vertex.")
    if scalar.dtype.kind not in "biuf":
        raise MeshFormatError(f"{path}: holds {scalar.dtype} values; expected numbers.")
    if scalar.size != n_vertices or scalar.squeeze().ndim > 1:
        raise MeshFormatError(
            f"{path}: holds {scalar.size} values of shape {scalar.shape} but {mesh} has "
            f"{n_vertices} vertices; expected one value per vertex."
        )
    return scalar


MAX_SIDE = 8192  # pixels: the largest image side render writes


def cmd_render(args: argparse.Namespace) -> int:
    from jaxdeform.mesh.io import load_mesh
    from jaxdeform.mesh.render import auto_camera, render, save_png

    mesh = Path(args.mesh)
    common.check_exists([args.mesh] + ([args.scalar] if args.scalar else []))
    out = Path(args.out) if args.out else mesh.with_suffix(".png")
    common.check_out_file(out, (".png",), [args.mesh] + ([args.scalar] if args.scalar else []), "image")
    vertices, faces = load_mesh(mesh)
    scalar = _read_scalar(args.scalar, mesh, vertices.shape[0]) if args.scalar else None
    if args.width < 1 or args.height < 1:
        raise ValueError(f"--width and --height must be positive, got {args.width} x {args.height}.")
    if args.width > MAX_SIDE or args.height > MAX_SIDE:
        raise ValueError(f"--width and --height must be at most {MAX_SIDE} pixels, got {args.width} x {args.height}.")
    camera = auto_camera(vertices, azimuth_deg=args.azimuth, elevation_deg=args.elevation, up_axis=args.up)
    t0 = time.perf_counter()
    image = render(
        vertices,
        faces,
        scalar=scalar,
        camera=camera,
        width=args.width,
        height=args.height,
        cmap=args.cmap,
        vmin=args.vmin,
        vmax=args.vmax,
        label=args.label,
    )
    with common.writing(out):
        save_png(image, out)
    print(
        f"rendered {mesh} ({vertices.shape[0]} vertices, {faces.shape[0]} faces"
        f"{', coloured by ' + str(args.scalar) if scalar is not None else ''}) at {args.width}x{args.height} "
        f"in {time.perf_counter() - t0:.2f} s; wrote {out}"
    )
    return 0


def register(sub) -> None:
    """Add ``render`` to the top-level subparsers ``sub``."""
    ren = sub.add_parser(
        "render",
        help="Render a mesh to PNG, optionally coloured by a per-vertex scalar.",
        description="Ray-cast a mesh to a PNG image (CPU, Embree).",
    )
    ren.add_argument("mesh", metavar="MESH", help="mesh file (.obj, .ply, .off, or a one-frame .npz)")
    ren.add_argument("--scalar", metavar="FILE.npy", help="per-vertex values (.npy, one per vertex) to colour by")
    common.add_out(ren, "FILE.png", "image to write (default: MESH with .png suffix)", required=False)
    ren.add_argument("--width", type=int, default=800, help="image width in pixels (default 800)")
    ren.add_argument("--height", type=int, default=600, help="image height in pixels (default 600)")
    ren.add_argument(
        "--azimuth",
        type=float,
        default=30.0,
        metavar="DEG",
        help="camera azimuth about the up axis in degrees (default 30)",
    )
    ren.add_argument(
        "--elevation", type=float, default=20.0, metavar="DEG", help="camera elevation in degrees (default 20)"
    )
    ren.add_argument("--up", choices=("y", "z"), default="y", help="the world's up axis (default y)")
    ren.add_argument("--cmap", choices=CMAPS, default="viridis", help="colormap for --scalar (default viridis)")
    ren.add_argument("--vmin", type=float, help="scalar value at the bottom of the colormap (default: min)")
    ren.add_argument("--vmax", type=float, help="scalar value at the top of the colormap (default: max)")
    ren.add_argument("--label", metavar="TEXT", help="label of the colour bar")
    ren.set_defaults(func=cmd_render)
