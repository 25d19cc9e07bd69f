"""``jaxdeform components train|evaluate|finetune|show|edit``: deformation components of a shape set
(:mod:`jaxdeform.components`).

``train DATA... --out RUN`` writes a run folder (built beside ``--out`` and renamed
at the end); ``evaluate RUN --data DATA...`` prints the metrics (or writes them with ``--json``); ``show RUN
--out DIR`` writes ``components.png``, ``similarity.png`` and ``components.json``; ``edit`` (the edited mesh) is
in :mod:`jaxdeform.cli.components_edit`, ``finetune`` in :mod:`jaxdeform.cli.components_finetune`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxdeform.cli import common

METHODS = ("multiscale", "tan", "pca", "pca-xyz", "splocs")


def cmd_components_train(args: argparse.Namespace) -> int:
    from jaxdeform.acap.features import check_quantile
    from jaxdeform.components import run

    common.check_exists(args.data)
    out = Path(args.out)
    common.check_out_folder(out, args.force, args.data)
    data = common.data_arg(args.data)
    run.resolve_config(args.method, args.config, args.epochs, args.seed)  # bad names fail before any work
    if args.split_seed < 0:
        raise ValueError(f"--split-seed must be a non-negative integer, got {args.split_seed}.")
    q = run.SCALE_QUANTILE if args.scale_quantile is None else args.scale_quantile
    check_quantile(q, "--scale-quantile")  # before any work (Scaler.fit checks it too, after encoding)
    loaded = run.load_data(data)  # fewer than 2 shapes or mixed connectivity: one sentence, nothing written
    kw = {k: getattr(args, k) for k in ("epochs", "seed", "split", "split_seed", "method")}
    what = "features" + (" and geodesic distances" if args.method in run.AUTOENCODERS else "")
    slow = args.method in run.ACAP_METHODS or args.method in run.AUTOENCODERS
    wait = f"computing the {what} of {loaded[0].shape[0]} shapes x {loaded[0].shape[1]} vertices..." if slow else None
    with common.keeping_checkpoints(out), common.writing(out), common.waiting(args, wait) as say:
        fitted = run.fit(
            data,
            args.config,
            out,
            progress=not args.quiet,
            scale_quantile=q,
            loaded=loaded,
            resume=args.resume,
            log=say,
            **kw,
        )
    record = fitted.record
    t = record["timing"]
    extra = ""
    if "run_s" in t:
        per = 1e3 * t["run_s"] / max(t.get("epochs_timed", 1), 1)
        extra = f"; compile {t['compile_s']:.1f} s, training {t['run_s']:.1f} s ({per:.1f} ms/epoch)"
    print(
        f"{args.method} ({args.config}) trained on {len(record['split']['train'])} of {record['n_shapes']} shapes "
        f"in {t['total_s']:.1f} s{extra}; wrote {out}"
    )
    return 0


def cmd_components_evaluate(args: argparse.Namespace) -> int:
    import json

    from jaxdeform.components import run

    common.check_exists([args.run] + list(args.data))
    if args.json:
        protect = [args.run] + [Path(args.run) / f for f in run.RUN_FILES]
        common.check_out_file(Path(args.json), (".json",), list(args.data), "metrics", "--json", protect=protect)
    loaded = run.load(args.run)
    n = loaded.record["n_shapes"]
    with common.waiting(args, f"evaluating the {loaded.method} run on {n} shapes (encode, reconstruct, compare)..."):
        result = run.evaluate(loaded, common.data_arg(args.data))
    text = json.dumps(result, indent=2)
    if args.json:
        with common.atomic_file(Path(args.json)) as tmp:
            Path(tmp).write_text(text)
    te = result["test"]
    rse = "max_relative_squared_error"
    rse = f", max relative squared error {te[rse]:.4g}" if rse in te else ""
    wrote = f"; wrote {args.json}" if args.json else ""
    print(f"{result['method']}: test Erms {te['erms']:.4g}, STED {te['sted']:.4g}{rse}{wrote}")
    if not args.json:
        print(text)
    return 0


def cmd_components_show(args: argparse.Namespace) -> int:
    from jaxdeform.components import run

    common.check_exists([args.run])
    out = Path(args.out)
    common.check_out_folder(out, args.force, [args.run])
    loaded = run.load(args.run)
    with common.waiting(args, f"drawing the {loaded.method} run's components..."), common.staged_folder(out) as tmp:
        info = run.show(loaded, tmp, up_axis=None if args.up == "auto" else args.up)
    print(
        f"{info['n_kept']} of {info['components']} components kept (eq. 7, eps2 = 0.01); wrote {out}/components.png, "
        f"similarity.png, components.json"
    )
    return 0


def _add_train_evaluate(comp_sub) -> None:
    ctrain = comp_sub.add_parser(
        "train",
        help="Train a method on the training split of a mesh folder.",
        description="Train on every 10th shape (or a random half) and write a run folder.",
    )
    ctrain.add_argument("data", nargs="+", metavar="DATA", help="mesh files or folders of them (at least 2 shapes)")
    common.add_out(ctrain, "RUN", "run folder to create")
    ctrain.add_argument(
        "--method",
        choices=METHODS,
        default="multiscale",
        help="multiscale (seed 000, default), tan (Tan et al. 2018), pca (ACAP features), "
        "pca-xyz (coordinates), splocs (Neumann et al. 2013)",
    )
    ctrain.add_argument(
        "--config",
        default="default",
        metavar="NAME",
        help="named configuration: default, test; multiscale also no-attention, separate, "
        "no-attention-separate, levels1, levels3, paper-kz (Kz = 10, 5), paper-kz-levels1, latent-tanh, mse",
    )
    ctrain.add_argument("--epochs", type=int, metavar="N", help="override the configuration's epochs")
    common.add_seed(ctrain, "override the training seed")
    ctrain.add_argument(
        "--split",
        choices=("every10", "half", "all"),
        default="every10",
        help="every10: shapes 0, 10, 20, ... train (sequences, default); half: a seeded random half; "
        "all: every shape trains and evaluate reports the whole data set as 'test'",
    )
    ctrain.add_argument("--split-seed", type=int, default=0, metavar="S", help="seed of the 'half' split (default 0)")
    ctrain.add_argument(
        "--scale-quantile",
        type=float,
        metavar="Q",
        help="ACAP methods: feature scaler bounds at the Q and 1 - Q quantiles of the training "
        "features, outliers clipped (default 1e-3; 0: the official min/max)",
    )
    common.add_quiet(ctrain, "no progress bar")
    common.add_force(ctrain, "replace RUN if it exists and is not empty")
    common.add_resume(ctrain)
    ctrain.set_defaults(func=cmd_components_train)
    ceval = comp_sub.add_parser(
        "evaluate",
        help="Erms, STED and relative squared error on the run's split.",
        description="Reconstruct the run's training and unseen shapes and report metrics.",
    )
    ceval.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform components train'")
    common.add_data(ceval, "the data the run was trained on", required=True)
    common.add_json(ceval, "write the metrics here")
    common.add_quiet(ceval, "no status line")
    ceval.set_defaults(func=cmd_components_evaluate)


def _add_show(comp_sub) -> None:
    cshow = comp_sub.add_parser(
        "show",
        help="Render the kept components and their similarity matrix.",
        description="Write components.png (AE0 row and AEk rows), similarity.png and "
        "components.json (strengths, kept and removed components).",
    )
    cshow.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform components train'")
    common.add_out(cshow, "DIR", "folder to create")
    cshow.add_argument("--up", choices=("auto", "y", "z"), default="auto", help="the meshes' vertical (or guessed)")
    common.add_force(cshow, "replace DIR if it exists and is not empty")
    common.add_quiet(cshow, "no status line")
    cshow.set_defaults(func=cmd_components_show)


def register(sub):
    """Add ``components train|evaluate|show`` to ``sub``; returns the ``components`` subparsers."""
    comp = sub.add_parser(
        "components",
        help="Multiscale deformation components (seed 000) and baselines.",
        description="Deformation components of a shape set: train, evaluate, finetune, show, edit.",
    )
    comp_sub = comp.add_subparsers(dest="components_command", metavar="ACTION", required=True)
    _add_train_evaluate(comp_sub)
    _add_show(comp_sub)
    return comp_sub
