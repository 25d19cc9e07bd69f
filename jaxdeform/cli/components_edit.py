"""``jaxdeform components edit``: move control vertices of a run's mesh; the run's components do the rest
(:mod:`jaxdeform.components.edit`).

``edit RUN --controls FILE --out MESH`` writes the edited mesh. Registered under ``components`` by
:mod:`jaxdeform.cli.components`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from jaxdeform.cli import checks, common


def cmd_components_edit(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxdeform.components import run
    from jaxdeform.mesh.io import save_mesh

    common.check_exists([args.run, args.controls])
    out = Path(args.out)
    common.check_out_file(out, common.MESH_OUT, [args.run, args.controls], "mesh file")
    loaded = run.load(args.run)
    controls, targets = run.read_controls(args.controls)
    checks.check_magnitude(targets, loaded.rest, f"the targets of {args.controls}")
    t0 = time.perf_counter()
    with common.waiting(args, f"editing with {controls.size} control points (the editor compiles first)..."):
        ed = run.editor(loaded)
        result = ed.edit(
            controls, targets, steps=args.steps, stages=None if args.one_stage else ed.stages, objective=args.objective
        )
        positions = np.asarray(result.positions)
    checks.check_result(positions, loaded.rest, "edited mesh")
    with common.writing(out):
        save_mesh(out, positions, loaded.faces)
    stages = "" if ed.stages is None or args.one_stage else f", coarse to fine over {len(ed.stages)} levels"
    print(
        f"edited {loaded.method} run with {controls.size} control points in {time.perf_counter() - t0:.2f} s "
        f"({int(result.steps)} steps{stages}); mean control residual {float(result.control_error):.3g}; wrote {out}"
    )
    if not bool(result.converged):
        print(
            f"warning: the optimiser stopped at the cap of {args.steps} iterations per stage before converging; "
            "a larger --steps may fit the controls better.",
            file=sys.stderr,
        )
    return 0


def register(comp_sub) -> None:
    """Add ``edit`` to the ``components`` subparsers ``comp_sub``."""
    cedit = comp_sub.add_parser(
        "edit",
        help="Move control vertices; the run's components do the rest.",
        description="Find the latent weights whose reconstructed mesh meets the targets "
        "at the control vertices (Sec. 5.4) and write the edited mesh.",
    )
    cedit.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform components train'")
    cedit.add_argument(
        "--controls",
        required=True,
        metavar="FILE",
        help='JSON {"indices": [...], "targets": [[x, y, z], ...]} or lines \'index x y z\'',
    )
    common.add_out(cedit, "MESH.obj", "edited mesh to write")
    common.add_steps(
        cedit, "optimiser iterations at most, per stage (default 500; BFGS stops once converged)", default=500
    )
    cedit.add_argument(
        "--objective",
        choices=("deformation", "controls"),
        default="deformation",
        help="runs on ACAP features: 'deformation' (default) holds the control vertices at their "
        "targets and finds the codes whose deformation fits them best (the data-driven "
        "deformation of seed 000's ref. [19]); 'controls' moves the decoded mesh as near the "
        "targets as the codes allow. Coordinate runs (pca-xyz, splocs) always do the latter.",
    )
    cedit.add_argument(
        "--one-stage",
        action="store_true",
        help="multiscale runs: optimise every level's codes at once instead of coarse to fine "
        "(one stage per level: level 0's codes first)",
    )
    common.add_quiet(cedit, "no status line")
    cedit.set_defaults(func=cmd_components_edit)
