"""Seed spread of the seed-002 methods: retrain some of them with other seeds and compare per test sequence.

    python -m experiments.cloth.seeds [--dataset disk] [--methods ours acap coords no_temporal] [--seeds 0 1 2]
                                      [--out experiments/cloth/results]

One training of a detail model is one draw: its parameter initialisation and its batch order both come from a
seed (``ModelConfig.seed``, ``TrainConfig.seed``). On a few test sequences, one of which may be chaotic (a
tablecloth flipping up in a gust), the autoregressive synthesis of one draw can drift where another does not,
and a single training then decides the order of the methods. This script trains each method with each seed
(both seeds set to it; seed 0 is the run that ``experiments.cloth.run`` trains, reused from
OUT/runs/KIND/NAME when it is there and stored there when not), synthesizes every test sequence and writes

- OUT/seeds_KIND.json: per method and seed, the pooled RMSE / STED and the RMSE of each test sequence;
- OUT/seeds_KIND.md: the table of pooled RMSE and STED per seed, their mean, and the per-sequence RMSE.

Methods of an earlier OUT/seeds_KIND.json with the same seeds and test sequences are kept (the ones named again
are replaced), so methods can be added one invocation at a time.

The dataset and the training settings are those of ``experiments.cloth.run`` (OUT/data/KIND must exist: run its
``data`` stage first).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments.cloth import run as xrun
from jaxdeform.cloth import data as cdata
from jaxdeform.cloth import evaluate as ceval
from jaxdeform.cloth import run as crun
from jaxdeform.mesh.io import atomic_path


def train_seed(out: Path, ds, name: str, seed: int, s: xrun.Settings, cache: dict):
    """The run of ``name`` with ``seed`` (seed 0: the experiment's stored run when present; else it is trained
    and stored there, as the experiment's ``train`` stage would have trained it)."""
    stored = out / "runs" / ds.scenario / name
    if seed == 0 and (stored / "run.json").is_file():
        return crun.load_run(stored)
    print(f"training {name} seed {seed} on {ds.scenario}", flush=True)
    run = xrun.train_method(ds, name, s, cache, seed=seed, progress=False)
    if seed == 0:
        crun.save_run(run, stored)
    return run


def evaluate(run, test, faces) -> dict:
    per = xrun.method_errors(run, test, faces)
    pooled = ceval.pool(per)
    return {"rmse": pooled["rmse"], "sted": pooled["sted"], "rmse_per_sequence": [r["rmse"] for r in per]}


def markdown(record: dict) -> str:
    seeds = record["seeds"]
    names = record["test_sequences"]
    lines = [
        f"# Seed spread on {record['dataset']} ({len(names)} test sequences: {', '.join(names)})",
        "",
        "Pooled test RMSE (m) / STED per training seed; the upsampled coarse cloth needs no training.",
        "",
        "| method | " + " | ".join(f"seed {s}" for s in seeds) + " | mean RMSE | RMSE / upsampled coarse |",
        "|---|" + "---|" * (len(seeds) + 2),
    ]
    base = record["upsampled_coarse"]["rmse"]
    lines.append(
        f"| upsampled_coarse | {base:.4f} / {record['upsampled_coarse']['sted']:.4f}"
        + " |" * len(seeds)
        + f" {base:.4f} | 1.00x |"
    )
    for name, per_seed in record["methods"].items():
        cells = [f"{per_seed[str(s)]['rmse']:.4f} / {per_seed[str(s)]['sted']:.4f}" for s in seeds]
        mean = float(np.mean([per_seed[str(s)]["rmse"] for s in seeds]))
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {mean:.4f} | {mean / base:.2f}x |")
    lines += [
        "",
        "RMSE (m) of each test sequence:",
        "",
        "| method, seed | " + " | ".join(names) + " |",
        "|---|" + "---|" * len(names),
        "| upsampled_coarse | "
        + " | ".join(f"{v:.4f}" for v in record["upsampled_coarse"]["rmse_per_sequence"])
        + " |",
    ]
    for name, per_seed in record["methods"].items():
        for s in seeds:
            lines.append(
                f"| {name}, {s} | " + " | ".join(f"{v:.4f}" for v in per_seed[str(s)]["rmse_per_sequence"]) + " |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", choices=("sheet", "disk"), default="disk")
    ap.add_argument(
        "--methods", nargs="+", choices=list(xrun.METHODS), default=["ours", "acap", "coords", "no_temporal"]
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--config", choices=("default", "test"), default="default")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    root = out / "data" / args.dataset
    if not (root / "dataset.json").is_file():
        raise SystemExit(
            f"no {args.dataset} dataset in {root}: run `python -m experiments.cloth.run --datasets "
            f"{args.dataset} --stages data` first."
        )
    s = xrun.settings(args.config)
    ds = cdata.load_dataset(root)
    test = ds.subset("test")
    ups = xrun.upsampler(ds)
    base = [ceval.sequence_errors(x.fine, ups(x.coarse), ds.fine_faces) for x in test]
    pooled = ceval.pool(base)
    record = {
        "dataset": args.dataset,
        "seeds": args.seeds,
        "test_sequences": [x.name for x in test],
        "upsampled_coarse": {
            "rmse": pooled["rmse"],
            "sted": pooled["sted"],
            "rmse_per_sequence": [r["rmse"] for r in base],
        },
        "methods": {},
    }
    old_path = out / f"seeds_{args.dataset}.json"
    if old_path.is_file():
        old = json.loads(old_path.read_text())
        if old.get("seeds") == record["seeds"] and old.get("test_sequences") == record["test_sequences"]:
            record["methods"] = {k: v for k, v in old.get("methods", {}).items() if k not in args.methods}
    cache: dict = {}
    for name in args.methods:
        record["methods"][name] = {}
        for seed in args.seeds:
            r = evaluate(train_seed(out, ds, name, seed, s, cache), test, ds.fine_faces)
            record["methods"][name][str(seed)] = r
            print(
                f"{args.dataset} {name} seed {seed}: rmse {r['rmse']:.5f} sted {r['sted']:.4f} per sequence "
                + " ".join(f"{v:.4f}" for v in r["rmse_per_sequence"]),
                flush=True,
            )
    with atomic_path(out / f"seeds_{args.dataset}.json") as tmp:
        tmp.write_text(json.dumps(record, indent=1) + "\n")
    with atomic_path(out / f"seeds_{args.dataset}.md") as tmp:
        tmp.write_text(markdown(record))
    print(f"wrote {out / f'seeds_{args.dataset}.json'} and {out / f'seeds_{args.dataset}.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
