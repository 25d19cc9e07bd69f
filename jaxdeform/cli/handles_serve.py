"""``jaxdeform handles serve MESH [--field FIELD]``: an interactive page on 127.0.0.1 for live Deep Feature
Deformation (:mod:`jaxdeform.handles.server`) until Ctrl-C. Registered under ``handles`` by
:func:`jaxdeform.cli.build_parser`.
"""

from __future__ import annotations

import argparse
import sys

from jaxdeform.cli import handles


def cmd_handles_serve(args: argparse.Namespace) -> int:
    from jaxdeform.handles import server

    if not 0 <= args.port < 65536:
        raise ValueError(f"--port must be in 0 .. 65535, got {args.port}.")
    from jaxdeform.handles.field import evaluate_field
    from jaxdeform.handles.pipeline import field_features

    vertices, faces = handles.load_mesh(args.mesh)
    if args.field:
        fitted, Z = field_features(args.field, args.mesh, vertices, faces, args.remap)
    else:
        from jaxdeform.handles.pipeline import distill_mesh

        print(f"no --field given: distilling {args.mesh} first (about a minute on a CPU)", file=sys.stderr)
        fitted = distill_mesh(vertices, faces, progress=True).field
        Z = evaluate_field(fitted, vertices)
    field_fn = lambda p: evaluate_field(fitted, p)  # noqa: E731
    server.serve(
        vertices,
        faces,
        Z,
        field_fn=field_fn,
        port=args.port,
        block=True,
        announce=_announce,
    )
    return 0


def _announce(url: str) -> None:
    """Say where the page is; from here the command waits on its user, so no status line follows."""
    from jaxdeform.cli import feedback

    feedback.settle()
    print(f"serving {url} (Ctrl-C stops)", flush=True)


def register(hand_sub) -> None:
    """Add ``serve`` to the ``handles`` subparsers ``hand_sub``."""
    hserve = hand_sub.add_parser(
        "serve",
        help="Interactive page on 127.0.0.1: click a vertex, drag to deform.",
        description="Serve a local page for live DFD deformation (Ctrl-C stops it).",
    )
    handles.add_mesh(hserve, with_field=False)
    hserve.add_argument("--field", metavar="FIELD", help="field written by 'handles distill' (else distil first)")
    hserve.add_argument("--port", type=int, default=8765, metavar="P", help="port on 127.0.0.1 (default 8765)")
    hserve.set_defaults(func=cmd_handles_serve)
