"""``jaxdeform components finetune``: train a run further for its vertices, through the differentiable ACAP
reconstruction (:mod:`jaxdeform.components.finetune`).

``finetune RUN --out RUN2`` writes a new run folder (built beside ``--out`` and renamed at the end). Registered under
``components`` by :mod:`jaxdeform.cli`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxdeform.cli import common

#: the finetune options passed by name to finetune.check_options and finetune.fit
FINETUNE_OPTIONS = (
    "mixes",
    "steps",
    "batch",
    "position_weight",
    "lr",
    "seed",
    "lr_final",
    "generated",
    "code_noise",
    "solver",
)


def cmd_components_finetune(args: argparse.Namespace) -> int:
    from jaxdeform.components import finetune, run

    common.check_exists([args.run] + list(args.data or []))
    out = Path(args.out)
    common.check_out_folder(out, args.force, [args.run] + list(args.data or []))
    opts = {k: getattr(args, k) for k in FINETUNE_OPTIONS}
    finetune.check_options(**opts)
    loaded = run.load(args.run)
    finetune.check_run(loaded)
    data = None if not args.data else common.data_arg(args.data)
    wait = f"preparing {args.mixes} regional mixes and the features of the training shapes..."
    with common.staged_folder(out) as tmp, common.waiting(args, wait):
        rec = finetune.fit(loaded, tmp, data, progress=not args.quiet, rigid=args.rigid, **opts)
    first, last = rec["first_terms"], rec["last_terms"]
    extra = f" and {args.generated} generated meshes" if args.generated else ""
    print(
        f"fine-tuned {args.run} for {args.steps} steps on {args.mixes} mixes{extra} in {rec['seconds']:.0f} s (model loss "
        f"{first[0]:.4g} -> {last[0]:.4g}, position term {first[1]:.3g} -> {last[1]:.3g}); wrote {out}"
    )
    return 0


def register(comp_sub) -> None:
    """Add ``finetune`` to the ``components`` subparsers ``comp_sub``."""
    cfine = comp_sub.add_parser(
        "finetune",
        help="Train a run further for its vertices, on regional mixes of its training shapes.",
        description="Adds w x the squared vertex error of the ACAP reconstruction to the model's loss and trains "
        "on the training shapes and regional mixes of them (jaxdeform.components.finetune); writes a "
        "new run folder.",
    )
    cfine.add_argument("run", metavar="RUN", help="a multiscale or tan run written by 'jaxdeform components train'")
    common.add_out(cfine, "RUN2", "run folder to create")
    common.add_data(cfine, "the data the run was trained on (default: its folder)")
    cfine.add_argument("--mixes", type=int, default=400, metavar="N", help="regional mixes (default 400; 0: none)")
    common.add_steps(cfine, "Adam steps (default 1000)", default=1000)
    cfine.add_argument("--batch", type=int, default=8, metavar="B", help="shapes per step (default 8)")
    cfine.add_argument(
        "--position-weight", type=float, default=1e5, metavar="W", help="weight w of the position term (default 1e5)"
    )
    cfine.add_argument("--lr", type=float, default=2e-4, help="Adam's learning rate (default 2e-4)")
    cfine.add_argument(
        "--lr-final",
        type=float,
        metavar="LR",
        help="learning rate at the last step, reached from --lr along a half cosine (default: --lr throughout)",
    )
    cfine.add_argument(
        "--generated",
        type=int,
        default=0,
        metavar="N",
        help="also train on N meshes that RUN's model decodes from its codes of further mixes, moved by "
        "--code-noise (default 0: none)",
    )
    cfine.add_argument(
        "--code-noise",
        type=float,
        default=1.0,
        metavar="S",
        help="Gaussian move of each code entry, in standard deviations of the mixes' codes (default 1)",
    )
    cfine.add_argument(
        "--rigid",
        action="store_true",
        help="compare the vertices after rotating each reconstruction onto its target, as Erms does "
        "(default: translation only)",
    )
    cfine.add_argument(
        "--solver",
        choices=("host", "dense", "cg"),
        help="the reconstruction's linear solver (jaxdeform.acap.prepare; default: by backend and mesh size)",
    )
    common.add_seed(cfine, "mixes and batch order (default 0)", default=0)
    common.add_quiet(cfine, "no progress bar")
    common.add_force(cfine, "replace RUN2 if it exists and is not empty")
    cfine.set_defaults(func=cmd_components_finetune)
