"""``jaxdeform acap encode|decode``: meshes to an ACAP features .npz (:mod:`jaxdeform.acap.files`) and back.

``encode INPUT... --reference REF --out F.npz`` writes one features file; ``decode F.npz --out DIR`` writes
``DIR/000.obj``, ``DIR/001.obj``, ... (one per frame), the folder built beside ``DIR`` and renamed at the end.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from jaxdeform.cli import checks, common
from jaxdeform.errors import ConnectivityError

CONSISTENCY_MODES = ("spatial", "temporal", "none")
WEIGHTINGS = ("official", "cotangent")


def _shape(a) -> str:
    import numpy as np

    return "x".join(str(d) for d in np.shape(a))


def cmd_encode(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxdeform.acap.files import encode_arrays, rotation_angles, save_features
    from jaxdeform.mesh.io import check_same_connectivity, load_mesh, load_sequence

    common.check_exists(list(args.inputs) + [args.reference])
    out = Path(args.out)
    common.check_out_file(out, (".npz",), list(args.inputs) + [args.reference], "features file")
    vertices, faces = load_sequence(list(args.inputs))
    ref_v, ref_f = load_mesh(args.reference)
    try:
        check_same_connectivity(ref_f, faces, ref_v.shape[0], vertices.shape[1], "the input meshes")
    except ConnectivityError:
        what = (
            f"{vertices.shape[1]} vertices against {ref_v.shape[0]}"
            if vertices.shape[1] != ref_v.shape[0]
            else "different faces"
        )
        raise ConnectivityError(
            f"the input meshes do not share the connectivity of the reference {args.reference} ({what})."
        ) from None
    dtype = np.float32 if args.float32 else np.float64
    vertices, ref_v = vertices.astype(dtype), ref_v.astype(dtype)
    from jaxdeform.mesh.geometry import zero_area_faces

    flat = zero_area_faces(ref_v, ref_f)
    if flat.size:
        print(
            f"warning: the reference {args.reference} has {flat.size} zero-area face(s) (the first is its face "
            f"{flat[0] + 1}, counting from 1); they add nothing to their vertices' deformation gradients, which are "
            "less accurate there, and decoding returns those vertices less exactly.",
            file=sys.stderr,
        )

    wait = (
        f"encoding {vertices.shape[0]} frames x {vertices.shape[1]} vertices ({args.consistency} consistency; "
        "the first call compiles)..."
    )
    t0 = time.perf_counter()
    with common.waiting(args, wait):
        arrays = encode_arrays(vertices, ref_v, ref_f, args.consistency, args.weighting)
    elapsed = time.perf_counter() - t0
    with common.writing(out):
        save_features(out, arrays)
    max_angle = float(rotation_angles(arrays["log_r"]).max())
    n, nv = arrays["features"].shape[:2]
    print(
        f"encoded {n} frames x {nv} vertices ({args.consistency} consistency, {args.weighting} weighting, "
        f"{np.dtype(dtype).name}) in {elapsed:.2f} s; max rotation angle {max_angle:.4f} rad; wrote {out} "
        f"(log_r {_shape(arrays['log_r'])}, s {_shape(arrays['s'])}, features {_shape(arrays['features'])}, "
        f"scaled {_shape(arrays['scaled'])}, faces {_shape(ref_f)})"
    )
    return 0


def cmd_decode(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxdeform.acap.features import prepare
    from jaxdeform.acap.files import read_features
    from jaxdeform.mesh.io import save_mesh

    path = Path(args.features)
    out = Path(args.out)
    common.check_out_folder(out, args.force, [path])
    features, reference, faces, weighting = read_features(path)
    n, nv = features.shape[:2]
    if args.refine is not None and not 0 <= args.refine <= 100:
        raise ValueError(f"--refine must be between 0 and 100, got {args.refine}.")
    anchors = None
    if args.anchors:
        anchors = np.asarray(args.anchors, dtype=np.int64)
        bad = anchors[(anchors < 0) | (anchors >= nv)]
        if bad.size:
            raise ValueError(f"anchor {int(bad[0])} is not a vertex index (the mesh has {nv} vertices).")
        anchors = np.unique(anchors)

    t0 = time.perf_counter()
    with common.waiting(args, f"decoding {n} frames x {nv} vertices (the first call compiles)..."):
        acap = prepare(reference, faces, weighting=weighting)
        extra = {} if args.refine is None else {"refine": args.refine}
        positions = np.asarray(acap.decode(features, anchors=anchors, **extra))
    elapsed = time.perf_counter() - t0
    checks.check_result(positions, reference, "decoded frame")

    width = max(3, len(str(n - 1)))
    with common.staged_folder(out) as tmp:
        for k in range(n):
            save_mesh(tmp / f"{k:0{width}d}.obj", positions[k], faces)
    if anchors is not None:
        held = "anchors " + " ".join(map(str, anchors.tolist()))
    elif np.asarray(acap.rec.anchors).size > 1:
        used = np.asarray(acap.rec.anchors).tolist()
        held = f"{len(used)} connected components, one anchored at its lowest vertex: {' '.join(map(str, used))}"
    else:
        held = "vertex 0 anchored"
    print(
        f"decoded {n} frames x {nv} vertices ({weighting} weighting, {held}"
        f"{'' if args.refine is None else f', {args.refine} refinement steps'}) "
        f"in {elapsed:.2f} s; wrote {out}/{0:0{width}d}.obj .. {n - 1:0{width}d}.obj"
    )
    return 0


def register(sub) -> None:
    """Add ``acap encode|decode`` to the top-level subparsers ``sub``."""
    acap = sub.add_parser(
        "acap",
        help="ACAP features: encode meshes, decode features.",
        description="ACAP features (Gao et al. 2019) and their temporal variant TS-ACAP.",
    )
    acap_sub = acap.add_subparsers(dest="acap_command", metavar="ACTION", required=True)

    enc = acap_sub.add_parser(
        "encode",
        help="Encode meshes to ACAP features (.npz).",
        description="Encode meshes sharing the reference's connectivity to ACAP features, written as one .npz "
        "with arrays log_r, s, features, scaled, scaler, faces, reference, consistency, weighting.",
    )
    enc.add_argument(
        "inputs",
        nargs="+",
        metavar="INPUT",
        help="mesh files (.obj, .ply, .off, .npz) or folders of them (natural order)",
    )
    enc.add_argument("--reference", "-r", required=True, metavar="REF", help="the reference (rest) mesh file")
    common.add_out(enc, "F.npz", "the .npz file to write")
    enc.add_argument(
        "--consistency",
        choices=CONSISTENCY_MODES,
        default="spatial",
        help="rotation-angle consistency: spatial (ACAP, default), temporal (TS-ACAP, frames in "
        "order) or none (angles in [0, pi])",
    )
    enc.add_argument(
        "--weighting", choices=WEIGHTINGS, default="official", help="one-ring edge weights (default: official)"
    )
    enc.add_argument("--float32", action="store_true", help="compute in float32 (default: float64)")
    common.add_quiet(enc, "no status line")
    enc.set_defaults(func=cmd_encode)

    dec = acap_sub.add_parser(
        "decode",
        help="Decode ACAP features (.npz) to OBJ meshes.",
        description="Decode the features of an .npz written by 'acap encode' (or one with 'scaled' and "
        "'scaler', inverse-scaled) to DIR/000.obj, DIR/001.obj, ...",
    )
    dec.add_argument("features", metavar="F.npz", help="features file written by 'jaxdeform acap encode'")
    common.add_out(dec, "DIR", "folder to create with one OBJ per frame")
    dec.add_argument(
        "--anchors",
        type=int,
        nargs="+",
        metavar="I",
        help="vertex indices held at their reference positions (default: vertex 0)",
    )
    dec.add_argument(
        "--refine",
        type=int,
        metavar="K",
        help="refinement steps after the least-squares solve (default: the library's)",
    )
    common.add_force(dec, "replace DIR if it exists and is not empty")
    common.add_quiet(dec, "no status line")
    dec.set_defaults(func=cmd_decode)
