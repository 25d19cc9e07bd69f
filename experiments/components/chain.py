"""The fine-tuning chain of the README, one command: train the multiscale model, fine-tune it for its vertices (the
position term after the Kabsch rotation, ``--rigid``), then rounds that add meshes its own model generates; every
stage scored by the unchanged generalization protocol.

    python -m experiments.components.chain DATA --out DIR [--from RUN] [--config default|test] [--epochs N]
        [--first-steps 3000] [--rounds 4] [--round-steps 1000] [--generated 400] [--mixes 400] [--seed 0] [--quiet]

Stages, each a run folder under DIR made by the CLI (so each is what a user gets from the same commands):

- ``base``: ``jaxdeform components train DATA --config CONFIG`` (with ``--from RUN``: that run, read in place);
- ``rigid``: ``jaxdeform components finetune base --steps FIRST --rigid --mixes M``;
- ``round1`` .. ``roundR``: ``jaxdeform components finetune PREVIOUS --steps ROUND --rigid --mixes M --generated N``
  (the N meshes decoded by PREVIOUS's model; ``finetune.generated_meshes``).

After each stage its scores (``components.run.evaluate``: train and test Erms, STED, relative squared error) go into
DIR/results.json and DIR/results.md (written atomically), so a chain cut off keeps what it finished, and a rerun
skips every stage whose folder and scores are there (a stage folder without scores, or a changed option, is an
error: one sentence, exit 2).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from experiments.components.common import hardware, write_text


def stage_plan(args) -> list[tuple[str, list[str]]]:
    """(name, CLI argv) for each stage, in order; a resumed stage must have been made by the same argv."""
    out = Path(args.out)
    plan = []
    if args.from_run is None:
        argv = ["components", "train", str(args.data), "--out", str(out / "base"), "--config", args.config]
        if args.epochs is not None:
            argv += ["--epochs", str(args.epochs)]
        plan.append(("base", argv))
    prev = str(out / "base") if args.from_run is None else str(args.from_run)
    common = ["--data", str(args.data), "--mixes", str(args.mixes), "--rigid", "--seed", str(args.seed)]
    plan.append(
        (
            "rigid",
            ["components", "finetune", prev, "--out", str(out / "rigid"), "--steps", str(args.first_steps)] + common,
        )
    )
    prev = str(out / "rigid")
    for r in range(1, args.rounds + 1):
        name = f"round{r}"
        plan.append(
            (
                name,
                [
                    "components",
                    "finetune",
                    prev,
                    "--out",
                    str(out / name),
                    "--steps",
                    str(args.round_steps),
                    "--generated",
                    str(args.generated),
                ]
                + common,
            )
        )
        prev = str(out / name)
    return plan


def markdown(results: dict) -> str:
    lines = [
        f"# Fine-tuning chain on {results['data']}",
        "",
        f"{results['hardware']}; {results['date']}. Each stage is scored by `jaxdeform components evaluate` "
        "(encode, decode, ACAP reconstruction of the unseen shapes).",
        "",
        "| stage | test Erms | test STED | max eq. 8 | train Erms | seconds |",
        "|---|---|---|---|---|---|",
    ]
    for name, st in results["stages"].items():
        te, tr = st["evaluate"]["test"], st["evaluate"]["train"]
        lines.append(
            f"| {name} | {te['erms']:.2f} | {te['sted']:.4f} | {te['max_relative_squared_error']:.4f} | "
            f"{tr['erms']:.2f} | {st['seconds']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="mesh folder (or file) the chain trains and scores on")
    parser.add_argument("--out", "-o", type=Path, required=True, help="folder for the stage runs and results")
    parser.add_argument(
        "--from",
        dest="from_run",
        type=Path,
        default=None,
        help="start from this multiscale run instead of training one",
    )
    parser.add_argument("--config", default="default", help="training configuration of the base run")
    parser.add_argument("--epochs", type=int, default=None, help="override the base run's epochs")
    parser.add_argument("--first-steps", type=int, default=3000, help="--rigid steps before the rounds (3000)")
    parser.add_argument("--rounds", type=int, default=4, help="rounds with generated meshes (4)")
    parser.add_argument("--round-steps", type=int, default=1000, help="steps per round (1000)")
    parser.add_argument("--generated", type=int, default=400, help="generated meshes per round (400)")
    parser.add_argument("--mixes", type=int, default=400, help="regional mixes of the training shapes (400)")
    parser.add_argument("--seed", type=int, default=0, help="fine-tuning seed: mixes, generated codes, batches (0)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    for flag, value, least in (
        ("--first-steps", args.first_steps, 1),
        ("--rounds", args.rounds, 0),
        ("--round-steps", args.round_steps, 1),
        ("--generated", args.generated, 1),
        ("--mixes", args.mixes, 0),
        ("--seed", args.seed, 0),
    ):
        if value < least:
            parser.exit(2, f"chain: {flag} must be at least {least}, got {value}.\n")
    if not args.data.exists():
        parser.exit(2, f"chain: no data at {args.data}.\n")

    from jaxdeform.cli import main as cli_main
    from jaxdeform.components import run as crun

    out = args.out
    path = out / "results.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    if results and results.get("data") != str(args.data):
        parser.exit(2, f"chain: {path} holds a chain on {results.get('data')}, not on {args.data}.\n")
    results.setdefault("data", str(args.data))
    results.setdefault("stages", {})
    for name, cli_argv in stage_plan(args):
        done = results["stages"].get(name)
        folder = out / name
        if done is not None:
            if done["command"] != cli_argv:
                parser.exit(2, f"chain: stage {name} in {path} was made with other options; choose another --out.\n")
            print(f"{name}: done (test Erms {done['evaluate']['test']['erms']:.2f})")
            continue
        if folder.exists():
            parser.exit(2, f"chain: {folder} exists but has no scores in {path}; remove it or choose another --out.\n")
        print("jaxdeform " + " ".join(cli_argv), flush=True)
        t0 = time.perf_counter()
        code = cli_main(cli_argv + ["--quiet"] * args.quiet)
        seconds = time.perf_counter() - t0
        if code != 0:
            parser.exit(code, f"chain: stage {name} failed (exit {code}).\n")
        run = crun.load(folder)
        evaluated = crun.evaluate(run, args.data)
        results["stages"][name] = {
            "folder": str(folder),
            "command": cli_argv,
            "seconds": round(seconds, 1),
            "evaluate": evaluated,
        }
        results["hardware"] = hardware()
        results["date"] = time.strftime("%Y-%m-%d")
        write_text(path, json.dumps(results, indent=1))
        write_text(out / "results.md", markdown(results))
        te = evaluated["test"]
        print(f"{name}: test Erms {te['erms']:.4f}, STED {te['sted']:.4f} ({seconds:.0f} s)", flush=True)
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
