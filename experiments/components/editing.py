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
from PIL import Image, ImageDraw, ImageFont

from jaxdeform.components import run as crun
from jaxdeform.mesh.io import atomic_path

METHODS = ("multiscale", "tan", "pca", "splocs")
CONTROLS = {"default": (5, 10, 20, 40), "test": (3, 6)}
SHAPES = {"default": 8, "test": 2}
COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14)]


def fig6(args, datasets, train_and_evaluate) -> dict:
    from experiments.components.run import SPLITS, _write, hardware

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
            variants = [("", ed.stages)] + ([(" (one stage)", None)]
                                            if ed.stages is not None and not args.skip_one_stage else [])
            for suffix, stages in variants:
                per_n = {}
                for n in controls:
                    t0 = time.perf_counter()
                    reports = [ed.edit_error(vertices[i], n, stages=stages, objective=args.edit_objective)
                               for i in pick]
                    per_n[str(n)] = {"mean_error": float(np.mean([r.mean_error for r in reports])),
                                     "control_error": float(np.mean([r.control_error for r in reports])),
                                     "shapes": [int(i) for i in pick], "stages": stages,
                                     "objective": args.edit_objective if ed.space == "features" else "controls",
                                     "iterations": [int(r.result.steps) for r in reports],
                                     "converged": int(sum(bool(r.result.converged) for r in reports)),
                                     "seconds_per_edit": round((time.perf_counter() - t0) / len(pick), 3)}
                    print(f"   {n} controls{suffix}: mean error {per_n[str(n)]['mean_error']:.4g} of the diagonal",
                          flush=True)
                rows[f"{name}/{method}{suffix}"] = per_n
    out = Path(args.out) / "fig6"
    _write(out / "results.md", markdown(rows, controls, hardware()))
    plot(rows, controls, out / "fig6.png")
    return rows


def markdown(rows: dict, controls, hw: str) -> str:
    head = "| data / method | " + " | ".join(f"{n} controls" for n in controls) + " |"
    lines = ["# Seed 000, Fig. 6: mean vertex error of edits toward unseen shapes (over the bbox diagonal)", "",
             f"Hardware: {hw}.", "", head, "|---|" + "---|" * len(controls)]
    for key, per_n in rows.items():
        lines.append(f"| {key} | " + " | ".join(f"{per_n[str(n)]['mean_error']:.4g}" for n in controls) + " |")
    return "\n".join(lines + [""])


def plot(rows: dict, controls, path: Path, size=(640, 420)) -> None:
    """A line chart (PIL): mean error against the number of control points, one polyline per run."""
    left, right, top, bottom = 70, max(170, 20 + 7 * max((len(k) for k in rows), default=0)), 20, 50
    w, h = size[0] + right - 170, size[1]  # the legend's column grows with the longest row name
    img = Image.new("RGB", (w, h), "white")
    d = ImageDraw.Draw(img)
    font = ImageFont.load_default()
    values = [v["mean_error"] for per_n in rows.values() for v in per_n.values()]
    ymax = max(values) * 1.1 if values and max(values) > 0 else 1.0
    xs = {n: left + (w - left - right) * (i / max(len(controls) - 1, 1)) for i, n in enumerate(controls)}

    def y(v):
        return top + (h - top - bottom) * (1 - v / ymax)

    d.line([(left, top), (left, h - bottom), (w - right, h - bottom)], fill="black")
    for n, x in xs.items():
        d.text((x - 6, h - bottom + 6), str(n), fill="black", font=font)
    for k in range(5):
        v = ymax * k / 4
        d.text((4, y(v) - 5), f"{v:.3g}", fill="black", font=font)
    d.text((left + 60, h - 20), "control points", fill="black", font=font)
    for i, (key, per_n) in enumerate(rows.items()):
        colour = COLOURS[i % len(COLOURS)]
        pts = [(xs[n], y(per_n[str(n)]["mean_error"])) for n in controls]
        d.line(pts, fill=colour, width=2)
        for p in pts:
            d.ellipse([p[0] - 3, p[1] - 3, p[0] + 3, p[1] + 3], fill=colour)
        d.text((w - right + 10, top + 16 * i), key, fill=colour, font=font)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        img.save(tmp, format="PNG")
