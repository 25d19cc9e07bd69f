"""``jaxdeform cloth simulate|train|synthesize|evaluate``: coarse-to-fine cloth detail synthesis
(:mod:`jaxdeform.cloth`).

``simulate --scenario S --out DIR`` writes a paired coarse/fine dataset; ``train DATA --out RUN`` a run folder;
``synthesize RUN --coarse DIR|SEQ --out DIR`` one .npz sequence per coarse sequence (folders built beside
``--out`` and renamed at the end); ``evaluate RUN --data DATA --json OUT.json`` the metrics.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxdeform.cli import common


def cmd_cloth_simulate(args: argparse.Namespace) -> int:
    from jaxdeform.cloth.run import generate

    out = Path(args.out)
    common.check_out_folder(out, args.force)
    for name, n in (("sequences", args.sequences), ("frames", args.frames)):
        if n is not None and n < 2:
            raise ValueError(f"--{name} must be at least 2, got {n}.")
    if args.seed < 0:
        raise ValueError(f"--seed must be a whole number >= 0, got {args.seed}.")
    from jaxdeform.cloth.garments import motion_choices

    motions = motion_choices(args.scenario, args.motions)  # before any work: one sentence for a malformed motion
    with common.staged_folder(out) as tmp:
        record = generate(
            args.scenario,
            tmp,
            n_sequences=args.sequences,
            n_frames=args.frames,
            seed=args.seed,
            progress=not args.quiet,
            motions=motions,
        )
    pen = record["penetration"]
    print(
        f"simulated {args.sequences} {args.scenario} sequences of {record['frames_per_sequence']} frames "
        f"(coarse {record['vertices']['coarse']} / fine {record['vertices']['fine']} vertices); max obstacle "
        f"penetration {100 * pen['coarse_max_over_edge']:.2f}% / {100 * pen['fine_max_over_edge']:.2f}% of the mean "
        f"edge (at the vertices and on the order-{pen['samples_per_edge']} grid of every triangle); wrote {out}"
    )
    return 0


def _cloth_configs(args: argparse.Namespace):
    from dataclasses import replace

    from jaxdeform.cloth.model import ModelConfig
    from jaxdeform.cloth.train import TrainConfig

    mcfg = ModelConfig(kind=args.model, skip=args.skip)
    if args.seed is not None and args.seed < 0:
        raise ValueError(f"--seed must be a whole number >= 0, got {args.seed}.")
    if args.seed is not None:
        mcfg = replace(mcfg, seed=args.seed)
    if not 0.0 <= args.self_feed <= 1.0:
        raise ValueError(f"--self-feed is a probability and must lie in [0, 1], got {args.self_feed}.")
    tcfg = TrainConfig(
        position_weight=0.0 if args.position_weight is None else args.position_weight, self_feed=args.self_feed
    )
    return mcfg, common.steps_seed(tcfg, args)


def cmd_cloth_train(args: argparse.Namespace) -> int:
    from jaxdeform.cloth import data as cdata
    from jaxdeform.cloth import run as crun

    out = Path(args.out)
    common.check_out_folder(out, args.force, [args.data])
    ds = cdata.load_dataset(args.data)
    mcfg, tcfg = _cloth_configs(args)
    config = crun.Config(mcfg, tcfg, representation=args.representation, residual=args.target == "residual")
    with common.keeping_checkpoints(out), common.writing(out):
        run = crun.fit(ds, config, out, progress=not args.quiet, resume=args.resume)
    print(
        f"trained a {args.model} on {len(ds.subset('train'))} {ds.scenario} sequences ({args.representation}) in "
        f"{run.record['train_seconds']:.1f} s, final loss {run.record['final_loss']:.5f}; wrote {out}"
    )
    return 0


def cmd_cloth_synthesize(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxdeform.cloth import data as cdata
    from jaxdeform.cloth.run import Run, check_meshes, synthesize_timed
    from jaxdeform.mesh.io import save_sequence

    run = Run.load(args.run)
    out = Path(args.out)
    common.check_out_folder(out, args.force, [args.run, args.coarse])
    src = Path(args.coarse)
    if src.is_file():
        seq, shared = cdata.read_sequence(src)
        seqs = [seq]
    else:
        ds = cdata.load_dataset(src)
        seqs = ds.subset(args.split) if args.split else ds.sequences
        shared = {"coarse_faces": ds.coarse_faces, "coarse_rest": ds.coarse_rest}
    check_meshes(run, src, (shared["coarse_rest"], np.asarray(shared["coarse_faces"], np.int64)))
    with common.staged_folder(out) as tmp:
        for s in seqs:
            fine, timing = synthesize_timed(run, s.coarse, s.obstacles, refine=not args.no_refine, pins=s.pins)
            save_sequence(tmp / s.name, fine, run.rep.fine_faces)
    print(f"synthesised {len(seqs)} fine sequence(s) of {run.rep.fine_rest.shape[0]} vertices; wrote {out}")
    return 0


def cmd_cloth_evaluate(args: argparse.Namespace) -> int:
    import json

    from jaxdeform.cloth import data as cdata
    from jaxdeform.cloth.run import RUN_FILES, Run, check_dataset, evaluate_run

    out = Path(args.json)
    common.check_out_file(
        out, (".json",), [args.data], "metrics", "--json", protect=[args.run] + [Path(args.run) / f for f in RUN_FILES]
    )
    run = Run.load(args.run)
    ds = cdata.load_dataset(args.data)
    check_dataset(run, ds, args.data, args.run)
    part = args.split
    res = evaluate_run(run, ds, part=part, progress=not args.quiet)
    with common.atomic_file(out) as tmp:
        tmp.write_text(json.dumps(res, indent=1) + "\n")
    t = res[part]
    print(
        f"{part}: rmse {t['rmse']:.5f} m, hausdorff {t['hausdorff']:.5f} m, sted {t['sted']:.4g} "
        f"(upsampled coarse rmse {res['upsampled_coarse'][part]['rmse']:.5f}); wrote {out}"
    )
    return 0


def _add_simulate_train(cloth_sub) -> None:
    csim = cloth_sub.add_parser(
        "simulate",
        help="Simulate paired coarse/fine sequences of a scenario.",
        description="SHEET (81 / 4225 vertices), DISK (148 / 7729), or a SKIRT (128 / 7296) or PANTS (225 / 13455) "
        "on an animated body: coarse and fine sequences, simulated separately.",
    )
    csim.add_argument("--scenario", required=True, choices=("sheet", "disk", "skirt", "pants"))
    common.add_out(csim, "DIR", "dataset folder to write")
    csim.add_argument("--sequences", type=int, default=10, metavar="N", help="sequences (default 10)")
    csim.add_argument("--frames", type=int, metavar="T", help="frames per sequence (default 120; garments 165)")
    csim.add_argument(
        "--motions",
        nargs="+",
        metavar="M",
        help="garments: the body's motions to draw from, each KIND or KIND:NAME=VALUE,... (walk, run, jump, turn, "
        "kick, sway; e.g. run:speed=3; default: all, random parameters)",
    )
    common.add_seed(csim, default=0)
    common.add_force(csim, "replace a non-empty --out")
    common.add_quiet(csim)
    csim.set_defaults(func=cmd_cloth_simulate)
    ctr = cloth_sub.add_parser(
        "train",
        help="Train a detail model on a dataset's training split.",
        description="TS-ACAP features -> DeformTransformer, self-fed with probability 0.5 (--self-feed).",
    )
    ctr.add_argument("data", metavar="DATA", help="dataset folder written by 'cloth simulate'")
    common.add_out(ctr, "RUN", "run folder to write")
    ctr.add_argument("--model", default="transformer", choices=("transformer", "lstm", "none"))
    ctr.add_argument("--representation", default="ts-acap", choices=("ts-acap", "acap", "coords"))
    ctr.add_argument(
        "--target",
        default="residual",
        choices=("residual", "direct"),
        help="residual (default): learn the fine features as a residual over the Loop-upsampled "
        "coarse cloth's; direct: map coarse to fine features as the paper does",
    )
    ctr.add_argument(
        "--skip",
        action="store_true",
        help="the fine decoder also reads the coarse features interpolated to the fine mesh",
    )
    ctr.add_argument(
        "--position-weight",
        type=float,
        metavar="W",
        help="add W x the decoded positions' squared error (in fine edge lengths) to the loss "
        "(needs the scenario's pins; default 0: feature MSE only, as the paper)",
    )
    ctr.add_argument(
        "--self-feed",
        type=float,
        default=0.5,
        metavar="P",
        help="train windows on the model's own earlier predictions with probability P (ramped up over the "
        "first half), as synthesis feeds them (default 0.5; 0: the paper's teacher forcing)",
    )
    common.add_steps(ctr, "training steps (default: the TrainConfig's)")
    common.add_seed(ctr)
    common.add_force(ctr, "replace a non-empty --out")
    common.add_resume(ctr)
    common.add_quiet(ctr)
    ctr.set_defaults(func=cmd_cloth_train)


def _add_synthesize_evaluate(cloth_sub) -> None:
    csyn = cloth_sub.add_parser(
        "synthesize",
        help="Fine cloth from coarse sequences with a trained run.",
        description="Writes one .npz sequence (vertices, faces) per coarse sequence.",
    )
    csyn.add_argument("run", metavar="RUN")
    csyn.add_argument("--coarse", required=True, metavar="DIR|SEQ", help="dataset folder or one sequence file")
    csyn.add_argument("--split", choices=("train", "test"), help="only this split of a dataset folder")
    common.add_out(csyn, "DIR", None)
    csyn.add_argument("--no-refine", action="store_true", help="skip the collision refinement")
    common.add_force(csyn, "replace a non-empty --out")
    csyn.set_defaults(func=cmd_cloth_synthesize)
    cev = cloth_sub.add_parser(
        "evaluate",
        help="RMSE, Hausdorff and STED on the test (or training) split against the fine simulation.",
        description="Also reports the upsampled-coarse baseline.",
    )
    cev.add_argument("run", metavar="RUN")
    cev.add_argument("--data", required=True, metavar="DATA")
    common.add_json(cev, required=True)
    cev.add_argument(
        "--split",
        choices=("test", "train"),
        default="test",
        help="the run's split to evaluate (default test; train tells fitting from generalising)",
    )
    common.add_quiet(cev)
    cev.set_defaults(func=cmd_cloth_evaluate)


def register(sub) -> None:
    """Add ``cloth simulate|train|synthesize|evaluate`` to the top-level subparsers ``sub``."""
    cloth = sub.add_parser(
        "cloth",
        help="Coarse-to-fine cloth detail synthesis (seed 002): simulate, train, synthesize, evaluate.",
        description="Paired cloth simulation data, TS-ACAP features and the DeformTransformer.",
    )
    cloth_sub = cloth.add_subparsers(dest="cloth_command", metavar="ACTION", required=True)
    _add_simulate_train(cloth_sub)
    _add_synthesize_evaluate(cloth_sub)
