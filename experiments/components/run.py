"""Seed 000 experiments: Table 2 (methods x data sets), Table 4 (attention x joint training), Table 5 (number of
levels) and Fig. 6 (editing error against the number of control points).

    python -m experiments.components.run table2|table4|table5|fig6 [--config default|test] [--data DIR]
                                          [--out OUT] [--datasets NAME ...] [--methods M ...]
                                          [--runs CONFIG ...] [--epochs N] [--split every10|half|all]
                                          [--force] [--trained-only] [--no-figures]

Every experiment trains through :mod:`jaxdeform.components.run` (the same code as ``jaxdeform components
train``) into OUT/<experiment>/<data set>/<run>, evaluates the generalization protocol of Sec. 5.1 (every 10th
shape of a sequence trains, a seeded random half of a pose set) and writes OUT/<experiment>/results.json and
results.md (atomically), plus the component figures of the multiscale runs. Existing runs are reused when their
run.json holds what the named configuration trains now (``components.run.stale_reason``; otherwise they are
retrained); ``--force`` retrains; ``--trained-only`` trains nothing and tabulates the runs that
exist (for example runs trained by separate invocations); ``--no-figures`` skips the component figures (a
three-level model has 61 blocks to draw). The table names the hardware: the CPU, or the accelerator of JAX's
default backend.

``--split`` trains table2/4/5 on another split than each data set's protocol, into OUT/<experiment>-<split>;
``--split all`` trains on every shape and reports the whole data set as "test" (Table 5 read as the
representation error "in the whole dataset").

``--config test`` runs the same code paths in seconds: every method's "test" configuration on a small synthetic
bending-tube sequence (written to OUT/data/tube), so CI exercises each experiment.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from experiments.components import editing
from experiments.components.common import BUILDERS, SPLITS, hardware, write_text
from jaxdeform.components import run as crun
from jaxdeform.components.edit import OBJECTIVES
from jaxdeform.mesh.io import save_mesh

TABLE2_METHODS = ("multiscale", "tan", "pca", "pca-xyz", "splocs")
TABLE4_CONFIGS = ("default", "no-attention", "separate", "no-attention-separate")
TABLE5_CONFIGS = ("levels1", "default", "levels3", "paper-kz-levels1", "paper-kz")
#: the data sets of each table without --datasets (fig6: horse-gallop); horse-49 is Table 1's Horse, built by
#: experiments.components.common.horse49 into OUT/data
DEFAULT_DATASETS = {
    "table2": ["horse-gallop", "horse-49", "samba", "cactus"],
    "table4": ["horse-gallop", "horse-49"],
    "table5": ["horse-gallop", "horse-49"],
}
PAPER = {  # seed 000's published figures (horse), for the tables
    "table2": {"multiscale": (6.9246, 0.0336), "tan": (12.9605, 0.04004), "splocs": (7.37, 0.0807)},
    "table4": {"default": 6.9246, "no-attention": 20.8894, "separate": 11.5899, "no-attention-separate": 17.4221},
    "table5": {
        "levels1": 0.1219,
        "default": 0.005491,
        "levels3": 0.003567,
        "paper-kz-levels1": 0.1219,
        "paper-kz": 0.005491,
    },
}


def synthetic_tube(out: Path) -> Path:
    from jaxdeform.data.synthetic import bending_tube_sequence

    d = out / "data" / "tube"
    if not (d / "f11.obj").is_file():
        d.mkdir(parents=True, exist_ok=True)
        vertices, faces = bending_tube_sequence(n_frames=12, n_around=8, n_along=16)
        for k in range(vertices.shape[0]):
            save_mesh(d / f"f{k}.obj", vertices[k], faces)
    return d


def train_and_evaluate(
    data: Path,
    folder: Path,
    method: str,
    config: str,
    split: str,
    epochs,
    force: bool,
    train: bool = True,
    figures: bool = True,
) -> dict | None:
    """Train (or reuse) one run and evaluate it; returns the evaluation with the run's timing. With
    ``train=False`` a run that does not exist yet is not trained: None. ``figures=False`` skips the component
    figures of the autoencoder runs."""
    if force and folder.exists():
        shutil.rmtree(folder)
    if (folder / "run.json").is_file():
        try:
            reason = crun.stale_reason(crun.read_record(folder), method, config, epochs, split)
        except crun.RunError as exc:  # an unreadable record: retrain
            reason = str(exc)
        if reason is not None and not train:
            print(f"   not what {method}/{config} trains now ({reason}): {folder} (left out)", flush=True)
            return None
        if reason is not None:
            print(f"   retraining {folder}: {reason}", flush=True)
            shutil.rmtree(folder)
    if not (folder / "run.json").is_file():
        if not train:
            print(f"   not trained yet: {folder} (left out)", flush=True)
            return None
        crun.fit(data, config, folder, method=method, epochs=epochs, split=split, progress=True)  # replaces folder
    loaded = crun.load(folder)
    result = crun.evaluate(loaded, data)
    result["timing"] = loaded.record.get("timing", {})
    result["run"] = str(folder)
    shown = folder / "figures" / "components.json"
    if figures and method in crun.AUTOENCODERS and not (folder / "figures" / "components.png").is_file():
        crun.show(loaded, folder / "figures")
    if method in crun.AUTOENCODERS and shown.is_file():
        result["kept_per_level"] = kept_per_level(json.loads(shown.read_text()))
    return result


def kept_per_level(info: dict) -> list[int]:
    """Components kept by the redundant-component removal, per level, from a components.json of
    ``jaxdeform components show`` (its ``kept`` maps "level/block" to the kept indices)."""
    counts: dict[int, int] = {}
    for key, kept in info["kept"].items():
        level = int(key.split("/")[0])
        counts[level] = counts.get(level, 0) + len(kept)
    return [counts.get(level, 0) for level in range(max(counts, default=-1) + 1)]


def _root(args, experiment: str) -> Path:
    """OUT/<experiment>, or OUT/<experiment>-<split> under --split: runs of another protocol never replace the
    protocol's runs (which fig6 reuses)."""
    return Path(args.out) / (experiment if not getattr(args, "split", None) else f"{experiment}-{args.split}")


def _split(args, name: str) -> str:
    """The split of data set ``name``: ``--split`` when given, else its protocol of Sec. 5.1 (SPLITS)."""
    return getattr(args, "split", None) or SPLITS.get(name, "every10")


def _datasets(args) -> list[tuple[str, Path]]:
    if args.config == "test":
        return [("tube", synthetic_tube(Path(args.out)))]
    names = args.datasets or DEFAULT_DATASETS.get(args.experiment, ["horse-gallop"])
    out = []
    for name in names:
        if name in BUILDERS:
            out.append((name, BUILDERS[name](Path(args.data), Path(args.out))))
            continue
        path = Path(args.data) / name
        if not path.is_dir():
            raise SystemExit(f"data set {name} not found at {path} (../shared/data beside the repository).")
        out.append((name, path))
    return out


def table2(args) -> dict:
    rows = {}
    for name, path in _datasets(args):
        for method in args.methods or TABLE2_METHODS:
            folder = _root(args, "table2") / name / method
            print(f"== table 2: {name} / {method}", flush=True)
            rows[f"{name}/{method}"] = train_and_evaluate(
                path,
                folder,
                method,
                args.config,
                _split(args, name),
                args.epochs,
                args.force,
                train=not args.trained_only,
                figures=not args.no_figures,
            )
    return {k: v for k, v in rows.items() if v is not None}


def _multiscale_table(args, experiment: str, configs) -> dict:
    """One multiscale run per named configuration (the test variant "test-<name>" under --config test)."""
    rows = {}
    for name, path in _datasets(args):
        for cfg in [c for c in configs if not args.runs or c in args.runs]:
            folder = _root(args, experiment) / name / cfg
            print(f"== {experiment}: {name} / {cfg}", flush=True)
            config = cfg if args.config != "test" else ("test" if cfg == "default" else f"test-{cfg}")
            rows[f"{name}/{cfg}"] = train_and_evaluate(
                path,
                folder,
                "multiscale",
                config,
                _split(args, name),
                args.epochs,
                args.force,
                train=not args.trained_only,
                figures=not args.no_figures,
            )
    return {k: v for k, v in rows.items() if v is not None}


def table4(args) -> dict:
    return _multiscale_table(args, "table4", TABLE4_CONFIGS)


def table5(args) -> dict:
    return _multiscale_table(args, "table5", TABLE5_CONFIGS)


def _fmt(x, digits=4) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


def _erms_cells(r: dict) -> str:
    """Test Erms under the paper's reading (unit-radius ball) and the group's scalemodel.m (diameter 1, the first
    shape's centre and radius), then the kept components per level ("-" for linear models)."""
    by = r["test"].get("erms_by_normalization", {})
    kept = r.get("kept_per_level")
    return f"{_fmt(by.get('radius'))} | {_fmt(by.get('diameter-first-shape'))} | {'/'.join(map(str, kept)) if kept else '-'}"


def markdown(experiment: str, rows: dict, hardware: str, split: str | None = None) -> str:
    """The results table; ``split`` as given to --split (None: each data set's protocol of Sec. 5.1)."""
    what = {
        None: "generalization to unseen shapes",
        "all": "every shape trains: 'test' is the whole data set, no unseen shape",
    }.get(split, f"split {split}")
    lines = [f"# Seed 000, {experiment} ({what})", "", f"Hardware: {hardware}.", ""]
    if experiment in ("table2", "table4"):
        lines += [
            "| data / run | test Erms | test Erms, diameter 1 | kept per level | test STED | paper Erms | paper STED | "
            "train Erms | train time (s) |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for key, r in rows.items():
            run_name = key.split("/")[-1]
            paper = PAPER[experiment].get(run_name) if key.startswith(("horse-gallop/", "horse-49/")) else None
            pe, ps = (paper if isinstance(paper, tuple) else (paper, None)) if paper is not None else (None, None)
            t = r.get("timing", {})
            secs = t.get("run_s", t.get("fit_s"))
            lines.append(
                f"| {key} | {_erms_cells(r)} | {_fmt(r['test']['sted'])} | {_fmt(pe)} | {_fmt(ps)} | "
                f"{_fmt(r['train']['erms'])} | {_fmt(secs, 3)} |"
            )
    elif experiment == "table5":
        lines += [
            "| data / levels | max rel. squared error (test) | (train) | paper (horse) | test Erms | "
            "test Erms, diameter 1 | kept per level |",
            "|---|---|---|---|---|---|---|",
        ]
        for key, r in rows.items():
            paper = PAPER["table5"].get(key.split("/")[-1]) if key.startswith(("horse-gallop/", "horse-49/")) else None
            lines.append(
                f"| {key} | {_fmt(r['test'].get('max_relative_squared_error'))} | "
                f"{_fmt(r['train'].get('max_relative_squared_error'))} | {_fmt(paper)} | {_erms_cells(r)} |"
            )
    lines.append("")
    return "\n".join(lines)


EXPERIMENTS = {"table2": table2, "table4": table4, "table5": table5}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("experiment", choices=sorted(EXPERIMENTS) + ["fig6"])
    parser.add_argument("--config", choices=("default", "test"), default="default")
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2].parent / "shared" / "data"))
    parser.add_argument("--out", default="out/experiments/components")
    parser.add_argument("--datasets", nargs="+")
    parser.add_argument("--methods", nargs="+", choices=TABLE2_METHODS, help="table2: a subset of the methods")
    parser.add_argument(
        "--runs",
        nargs="+",
        choices=sorted(set(TABLE4_CONFIGS + TABLE5_CONFIGS)),
        help="table4/table5: a subset of their configurations (the others are left out)",
    )
    parser.add_argument("--epochs", type=int, help="override the training epochs of every run")
    parser.add_argument(
        "--split",
        choices=crun.SPLITS,
        help="table2/table4/table5: train every run on this split instead of the data set's protocol "
        "(Sec. 5.1); 'all' trains on every shape and reports the whole data set as 'test' "
        "(Table 5 read as the representation error); runs and results go to OUT/<experiment>-<split>",
    )
    parser.add_argument("--force", action="store_true", help="retrain runs that exist")
    parser.add_argument(
        "--trained-only",
        action="store_true",
        help="table2/table4/table5: evaluate the runs that exist and leave the others out (no training)",
    )
    parser.add_argument("--no-figures", action="store_true", help="skip the component figures (PNGs) of the runs")
    parser.add_argument(
        "--controls",
        nargs="+",
        type=int,
        metavar="N",
        help="fig6: these control-point counts instead of the configuration's (5 10 20 40)",
    )
    parser.add_argument(
        "--edit-objective",
        choices=OBJECTIVES,
        default="deformation",
        help="fig6: how the methods on ACAP features edit (jaxdeform.components.edit): 'deformation' "
        "(default: the controls held, the codes minimise the deformation energy, the paper's "
        "data-driven deformation) or 'controls' (the decoded mesh fitted to the controls)",
    )
    parser.add_argument(
        "--skip-one-stage",
        action="store_true",
        help="fig6: leave out the multiscale model's one-stage edit (the ablation row)",
    )
    args = parser.parse_args(argv)
    if args.trained_only and args.force:
        parser.error("--trained-only evaluates existing runs; it cannot be combined with --force.")
    if args.experiment == "fig6" and args.split:
        parser.error("fig6 edits toward unseen shapes on each data set's own split; --split is for table2/4/5.")
    if args.controls and min(args.controls) < 1:
        parser.error("--controls takes positive control-point counts.")
    t0 = time.perf_counter()
    if args.experiment == "fig6":
        rows = editing.fig6(args, _datasets(args), train_and_evaluate)
    else:
        rows = EXPERIMENTS[args.experiment](args)
    result = {
        "experiment": args.experiment,
        "config": args.config,
        "hardware": hardware(),
        "split": args.split or "protocol",
        "seconds": round(time.perf_counter() - t0, 1),
        "rows": rows,
    }
    out = _root(args, args.experiment)
    write_text(out / "results.json", json.dumps(result, indent=2, default=float))
    if args.experiment != "fig6":
        write_text(out / "results.md", markdown(args.experiment, rows, hardware(), args.split))
    print(f"wrote {out}/results.json" + ("" if args.experiment == "fig6" else " and results.md"))
    return result


if __name__ == "__main__":
    main()
