"""Fig. 6 of seed 000: editing error against the number of control points, per method.

For every method's Table-2 run (trained when missing): control vertices by furthest point sampling on the
reference shape, targets = an unseen shape's positions there, one edit from the reference shape's code
(:class:`jaxdeform.components.run.Editor`; the methods on ACAP features by the data-driven deformation of the
paper's ref. [19], ``--edit-objective deformation``, the coordinate methods by fitting their decoded mesh to the
controls), mean vertex error of the whole edited mesh against the unseen shape
over the bounding-box diagonal; averaged over a fixed subset of the unseen shapes. The multiscale model edits
coarse to fine, one stage per level (level-0 codes first: Sec. 5.4's editing order); its edit of every code at
once is shown as the "(one stage)" row. Writes results.md and fig6.png (one curve per row) next to results.json.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from matplotlib.ticker import NullLocator

from experiments import charts
from experiments.components.common import SPLITS, hardware, write_text
from jaxdeform.components import run as crun

METHODS = ("multiscale", "tan", "pca", "splocs")
CONTROLS = {"default": (5, 10, 20, 40), "test": (3, 6)}
SHAPES = {"default": 8, "test": 2}
ONE_STAGE = " (one stage)"  # suffix of the multiscale model's one-stage row


def fig6(args, datasets, train_and_evaluate) -> dict:
    """Fig. 6 over ``datasets`` ((name, path) pairs); ``train_and_evaluate``: the run experiment's
    (:func:`experiments.components.run.train_and_evaluate`), which trains a missing Table-2 run."""
    rows = {}
    controls = tuple(args.controls) if args.controls else CONTROLS[args.config]
    for name, path in datasets:
        for method in args.methods or METHODS:
            folder = Path(args.out) / "table2" / name / method
            print(f"== fig 6: {name} / {method}", flush=True)
            train_and_evaluate(path, folder, method, args.config, SPLITS.get(name, "every10"), args.epochs, False)
            loaded = crun.load(folder)
            vertices, _ = crun.load_data(path)
            test = loaded.test_idx
            pick = test[np.linspace(0, test.size - 1, min(SHAPES[args.config], test.size)).round().astype(int)]
            ed = crun.editor(loaded)
            # a model of several levels edits coarse to fine (the run's default); its one-stage edit (every code
            # at once) is the ablation row
            variants = [("", ed.stages)] + (
                [(ONE_STAGE, None)] if ed.stages is not None and not args.skip_one_stage else []
            )
            for suffix, stages in variants:
                per_n = {}
                for n in controls:
                    t0 = time.perf_counter()
                    reports = [
                        ed.edit_error(vertices[i], n, stages=stages, objective=args.edit_objective) for i in pick
                    ]
                    per_n[str(n)] = {
                        "mean_error": float(np.mean([r.mean_error for r in reports])),
                        "control_error": float(np.mean([r.control_error for r in reports])),
                        "shapes": [int(i) for i in pick],
                        "stages": stages,
                        "objective": args.edit_objective if ed.space == "features" else "controls",
                        "iterations": [int(r.result.steps) for r in reports],
                        "converged": int(sum(bool(r.result.converged) for r in reports)),
                        "seconds_per_edit": round((time.perf_counter() - t0) / len(pick), 3),
                    }
                    print(
                        f"   {n} controls{suffix}: mean error {per_n[str(n)]['mean_error']:.4g} of the diagonal",
                        flush=True,
                    )
                rows[f"{name}/{method}{suffix}"] = per_n
    out = Path(args.out) / "fig6"
    write_text(out / "results.md", markdown(rows, controls, hardware()))
    plot(rows, controls, out / "fig6.png")
    return rows


def markdown(rows: dict, controls, hw: str) -> str:
    head = "| data / method | " + " | ".join(f"{n} controls" for n in controls) + " |"
    lines = [
        "# Seed 000, Fig. 6: mean vertex error of edits toward unseen shapes (over the bbox diagonal)",
        "",
        f"Hardware: {hw}.",
        "",
        head,
        "|---|" + "---|" * len(controls),
    ]
    for key, per_n in rows.items():
        lines.append(f"| {key} | " + " | ".join(f"{per_n[str(n)]['mean_error']:.4g}" for n in controls) + " |")
    return "\n".join(lines + [""])


def plot(rows: dict, controls, path: Path, size=charts.SIZE) -> Path:
    """A line chart of ``size`` pixels at ``path`` (PNG): mean vertex error (percent of the bounding-box
    diagonal) against the number of control points (log axis, ticks at ``controls``), one line per row; a
    one-stage row is dashed in the colour of its coarse-to-fine row."""
    fig, ax = charts.figure(size)
    colour = {}
    for key, per_n in rows.items():
        base = key.removesuffix(ONE_STAGE)
        c = colour.setdefault(base, f"C{len(colour) % 10}")
        ys = [100.0 * per_n[str(n)]["mean_error"] for n in controls]
        ax.plot(
            controls,
            ys,
            color=c,
            linestyle="--" if key.endswith(ONE_STAGE) else "-",
            marker="o",
            markersize=4,
            linewidth=1.6,
            label=key,
        )
    ax.set_xscale("log")
    ax.set_xticks(list(controls), [str(n) for n in controls])
    ax.xaxis.set_minor_locator(NullLocator())
    if len(controls) == 1:
        ax.set_xlim(controls[0] / 1.5, controls[0] * 1.5)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("control points (vertices held at the target's positions)")
    ax.set_ylabel("mean vertex error (% of bounding-box diagonal)")
    charts.title(ax, "Seed 000, Fig. 6: editing error toward unseen shapes")
    if rows:
        fig.legend(loc="outside right upper", fontsize="small", title="data / method")
    return charts.save(fig, path)
