"""Seed 002 experiments: Tables 1, 2, 4 and 5 on generated SHEET, DISK, SKIRT and PANTS data, and PNG strips.

    python -m experiments.cloth.run [--config default|test] [--out DIR] [--datasets sheet disk]
                                    [--stages data train evaluate linear scale scaling jumps timing floor figures]
                                    [--sequences N] [--floor-sequences N] [--steps N] [--methods ours ...]
                                    [--force]

Stages (each dataset in turn; results merge into OUT/summary.json, markdown into OUT/results.md; ``--methods``
limits ``train`` and ``evaluate`` to some methods, merging their rows into the stored table):
- ``data``: simulate the paired dataset (``jaxdeform.cloth.run.generate``; cached in OUT/data/KIND unless
  ``--force``), recording the obstacle penetration and the coarse / fine simulation time per frame.
- ``train``: the methods of Tables 2, 4 and 5 on the training split, one run folder each in OUT/runs/KIND/NAME.
  Every learned method predicts the fine cloth as a residual over the Loop-upsampled coarse cloth (see
  ``jaxdeform.cloth.features``): a model that learns nothing then decodes to the upsampled coarse baseline,
  and the ablations differ from ``ours`` in one thing each. ``ours`` (DeformTransformer on TS-ACAP),
  ``ours_direct`` (the paper's direct coarse -> fine feature mapping, no residual), ``no_temporal``
  (encoder-decoder, no temporal module), ``lstm`` (an LSTM in place of the transformer), ``acap`` (the
  transformer on plain per-frame ACAP), ``coords`` (the transformer on vertex coordinates).
- ``evaluate``: RMSE, Hausdorff and STED of every method and of the Loop-upsampled coarse simulation on the
  test sequences (never seen in training).
- ``linear``: a closed-form reference beside them (``jaxdeform.cloth.evaluate.LinearResidual``: the upsampled
  coarse frame plus a ridge-regressed linear map of it onto the leading principal directions of the training
  residuals), added to the evaluation's table as ``linear_residual``, with its error on the training sequences
  (``train_rmse``: how much better it fits them than the unseen ones).
- ``scale``: where the upsampled coarse cloth's error lies: the part that upsampled coarse offsets can express (the
  coarse and the fine simulation moving the cloth differently at the coarse mesh's scale) and the finer rest
  (wrinkles), over the test and the training sequences (``jaxdeform.cloth.evaluate.coarse_level_split``).
- ``scaling``: does more data of the same kind help? The linear reference and the per-frame model
  (``no_temporal``) are trained again on every 4th and every 2nd training sequence (on all of them: the
  linear fit again, the ``train`` stage's stored per-frame run where there is one) and scored on the same test
  sequences, beside their error on the sequences they were trained on.
- ``jumps``: frame-to-frame changes of the fine TS-ACAP and ACAP features over all sequences (largest,
  percentiles, fraction above pi).
- ``timing``: Table 1: per frame, the coarse simulation, TS-ACAP extraction, synthesis, reconstruction and
  refinement against the fine simulation of the same scenario: the first test scenario is simulated again at
  both resolutions (30 frames, compilation excluded) and our pipeline runs on its coarse frames after a
  warm-up call, all in this process.
- ``floor``: how far the fine simulation is determined by its scenario: the fine cloth of the test scenarios
  (all of them by default, ``Settings.floor_sequences``) is simulated again from a start perturbed by 0.1 mm RMS
  (``scenarios.simulate_fine``) and compared with the stored fine run (RMSE and STED, pooled as the evaluation
  pools), beside the upsampled coarse cloth's errors on the same sequences. No method that sees the scenario can
  be expected below that RMSE, and the STED is that of a cloth as valid as the simulation's own.
- ``figures``: strips coarse (upsampled) | ours | fine simulation | error colour map for a few test frames, and
  the training loss curves of the stored runs (``loss_KIND.png``).

``--config test`` runs everything in about a minute on tiny datasets (3 short sequences, one Loop level from
coarse to fine, few steps), for CI.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import time
from pathlib import Path

import numpy as np

from jaxdeform.cloth import data as cdata
from jaxdeform.cloth import evaluate as ceval
from jaxdeform.cloth import features as cfeat
from jaxdeform.cloth import run as crun
from jaxdeform.mesh.io import atomic_path

METHODS = {  # name -> (model kind, representation, residual over the upsampled coarse features[, skip, position weight,
    #                 self-feeding probability])
    "ours": ("transformer", "ts-acap", True),
    "ours_direct": ("transformer", "ts-acap", False),
    "no_temporal": ("none", "ts-acap", True),
    "lstm": ("lstm", "ts-acap", True),
    "acap": ("transformer", "acap", True),
    "coords": ("transformer", "coords", True),
    "ours_self_fed": ("transformer", "ts-acap", True, False, 0.0, 0.5),
    "acap_self_fed": ("transformer", "acap", True, False, 0.0, 0.5),
    "coords_self_fed": ("transformer", "coords", True, False, 0.0, 0.5),
}


#: the ``scaling`` stage trains on every k-th training sequence for each k here
SCALING_EVERY = (4, 2, 1)

#: RMS of the start perturbation (m) of the ``floor`` stage.
FLOOR_PERTURBATION = 1e-4


@dataclasses.dataclass(frozen=True)
class Settings:
    sequences: dict  # per scenario kind
    frames: int | None
    steps: int
    batch: int
    figure_frames: int
    size: int
    timing_frames: int
    levels: int = 3  # Loop levels coarse -> fine
    floor_sequences: int | None = None  # test scenarios re-simulated by the ``floor`` stage (None: all of them)
    garment_frames: int | None = None  # frames of a garment sequence (None: scenarios.GARMENT_FRAMES)

    def frames_for(self, kind: str) -> int:
        """Frames per sequence of a scenario kind."""
        from jaxdeform.cloth import scenarios

        own = self.garment_frames if kind in scenarios.GARMENT_KINDS else self.frames
        return own or scenarios.default_frames(kind)


def settings(config: str) -> Settings:
    if config == "test":
        return Settings(
            sequences={"sheet": 3, "disk": 3, "skirt": 3, "pants": 3},
            frames=8,
            steps=5,
            batch=4,
            figure_frames=1,
            size=96,
            timing_frames=8,
            levels=1,
            floor_sequences=1,
            garment_frames=20,
        )
    # SHEET: 40 x 100 frames, the paper's 4,000; DISK: 20 x 100, the paper's 2,000 (16 / 4 sequences: its 1,600 / 400);
    # garments: 20 x 165 frames (16 / 4 sequences; the paper's 18 / 2 of 300-450 frames)
    return Settings(
        sequences={"sheet": 40, "disk": 20, "skirt": 20, "pants": 20},
        frames=100,
        steps=1000,
        batch=8,
        figure_frames=3,
        size=320,
        timing_frames=30,
    )


def upsampler(ds) -> ceval.Upsampler:
    """Loop subdivision from the dataset's coarse to its fine connectivity."""
    return ceval.Upsampler(ds.coarse_faces, ds.coarse_rest.shape[0], ds.fine_faces)


def _scenario_of(ds, x, n_frames: int):
    """The scenario that produced sequence ``x`` of ``ds`` (from its stored record), ``n_frames`` long."""
    from jaxdeform.cloth import scenarios

    meta = x.meta
    return scenarios.scenario(
        ds.scenario,
        int(meta["index"]),
        seed=int(meta.get("seed", 0)),
        n_frames=n_frames,
        n_sequences=len(ds.sequences),
        levels=int(meta.get("levels", 3)),
    )


def stage_data(out: Path, kind: str, s: Settings, force: bool) -> dict:
    root = out / "data" / kind
    if (root / "dataset.json").is_file() and not force:
        record = json.loads((root / "dataset.json").read_text())
        names = record.get("sequences", [])
        if len(names) == s.sequences[kind]:
            from jaxdeform.cloth import scenarios

            sc = scenarios.scenario(kind, 0, n_frames=s.frames_for(kind), n_sequences=len(names), levels=s.levels)
            if crun.holds_scenario(root / names[0], sc.meta):
                return record
            # the scenes changed since (e.g. DISK's rounded table rims): generate() simulates what no longer matches
            print(f"note: {root} holds scenes the current code no longer makes; simulating them again", flush=True)
    elif force and root.is_dir():
        shutil.rmtree(root)
    t0 = time.perf_counter()
    record = crun.generate(
        kind, root, n_sequences=s.sequences[kind], n_frames=s.frames_for(kind), progress=True, levels=s.levels
    )
    record["wall_seconds"] = time.perf_counter() - t0
    return record


def _features(ds, kind, residual, cache):
    if (kind, residual) not in cache:
        cache[kind, residual] = cfeat.fit_representation(
            kind, ds, [x.name for x in ds.subset("train")], progress=True, residual=residual
        )
    return cache[kind, residual]


def train_method(ds, name: str, s: Settings, cache: dict, seed: int = 0, progress: bool = True):
    """The run of method ``name`` on ``ds``'s training split; ``seed`` sets the parameter initialisation and the batch
    order (``ModelConfig.seed``, ``TrainConfig.seed``; 0 = their defaults, the experiment's runs)."""
    from jaxdeform.cloth.model import ModelConfig
    from jaxdeform.cloth.train import TrainConfig

    model_kind, rep_kind, residual, *extra = METHODS[name]
    skip, weight, feed = tuple(extra) + (False, 0.0, 0.0)[len(extra) :]
    return crun.train_run(
        ds,
        representation=rep_kind,
        model_cfg=ModelConfig(kind=model_kind, skip=skip, seed=seed),
        train_cfg=TrainConfig(steps=s.steps, batch_size=s.batch, position_weight=weight, self_feed=feed, seed=seed),
        features=_features(ds, rep_kind, residual, cache),
        progress=progress,
    )


def method_errors(run, test, faces, ups=None) -> list[dict]:
    """:func:`jaxdeform.cloth.evaluate.sequence_errors` of ``run``'s synthesis of every test sequence (with the detail
    measure when the upsampler ``ups`` is given)."""
    return [_errors(x, crun.synthesize_timed(run, x.coarse, x.obstacles, pins=x.pins)[0], faces, ups) for x in test]


def _errors(x, fine, faces, ups) -> dict:
    """:func:`jaxdeform.cloth.evaluate.sequence_errors` of fine frames of the sequence ``x`` with the largest obstacle
    penetration of their vertices (``max_penetration``, metres)."""
    from jaxdeform.cloth import obstacles, scenarios

    e = ceval.sequence_errors(x.fine, fine, faces, upsampler=ups)
    e["max_penetration"] = scenarios.max_penetration(fine, obstacles.from_dict(x.obstacles))
    return e


def stage_train(out: Path, ds, s: Settings, force: bool, cache: dict, methods=tuple(METHODS)) -> dict:
    res = {}
    for name in methods:
        model_kind, rep_kind, *_ = METHODS[name]
        root = out / "runs" / ds.scenario / name
        if (root / "run.json").is_file() and not force:
            res[name] = json.loads((root / "run.json").read_text())
            continue
        print(f"training {name} ({model_kind}, {rep_kind}) on {ds.scenario}", flush=True)
        run = train_method(ds, name, s, cache)
        crun.save_run(run, root)
        res[name] = run.record
    return {n: {k: r[k] for k in ("final_loss", "train_seconds", "compile_seconds")} for n, r in res.items()}


def stage_evaluate(out: Path, ds, cache: dict, names=tuple(METHODS)) -> dict:
    test = ds.subset("test")
    ups = upsampler(ds)
    methods = {"upsampled_coarse": ceval.pool([_errors(x, ups(x.coarse), ds.fine_faces, ups) for x in test])}
    for name in names:
        run = crun.load_run(out / "runs" / ds.scenario / name)
        methods[name] = ceval.pool(method_errors(run, test, ds.fine_faces, ups))
        print(f"{ds.scenario} {name}: rmse {methods[name]['rmse']:.5f} sted {methods[name]['sted']:.4f}", flush=True)
    return {"methods": methods, "test_sequences": [x.name for x in test]}


def stage_linear(ds, r: dict) -> None:
    """The ``linear`` stage: fit LinearResidual on the training split, add its test errors to ``r``'s tables."""
    ups = upsampler(ds)
    train = ds.subset("train")
    ref = ceval.LinearResidual(ups, [x.coarse for x in train], [x.fine for x in train])
    m = ceval.pool([ceval.sequence_errors(x.fine, ref(x.coarse), ds.fine_faces) for x in ds.subset("test")])
    m["ridge_lambda"] = ref.lam
    m["train_rmse"] = ceval.pooled_rmse((x.fine, ref(x.coarse)) for x in train)
    print(
        f"{ds.scenario} linear_residual: rmse {m['rmse']:.5f} sted {m['sted']:.4f} "
        f"(training sequences: {m['train_rmse']:.5f})",
        flush=True,
    )
    r.setdefault("evaluate", {}).setdefault("methods", {})["linear_residual"] = m
    for key in ("rmse", "hausdorff", "sted"):
        r.setdefault(key, {})["linear_residual"] = m[key]


def stage_scale(ds) -> dict:
    """The ``scale`` stage: the upsampled coarse cloth's error split into its coarse-mesh-scale part and the finer
    rest (``evaluate.coarse_level_split``), pooled over the test and over the training sequences."""
    ups = upsampler(ds)
    out = {}
    for part in ("test", "train"):
        low = high = count = 0.0
        for x in ds.subset(part):
            lo, hi = ceval.coarse_level_split(ups, x.fine.astype(np.float64) - ups(x.coarse))
            low, high, count = low + np.sum(lo**2), high + np.sum(hi**2), count + x.fine.shape[0] * x.fine.shape[1]
        out[part] = {
            "rmse": float(np.sqrt((low + high) / count)),
            "coarse_scale_rmse": float(np.sqrt(low / count)),
            "finer_rmse": float(np.sqrt(high / count)),
            "coarse_scale_share": float(low / (low + high)),
        }
        print(
            f"{ds.scenario} {part}: upsampled coarse error {out[part]['rmse']:.5f} m = coarse scale "
            f"{out[part]['coarse_scale_rmse']:.5f} + finer {out[part]['finer_rmse']:.5f} "
            f"({100 * out[part]['coarse_scale_share']:.1f}% of the squared error at the coarse scale)",
            flush=True,
        )
    return out


def stage_scaling(out: Path, ds, s: Settings) -> list[dict]:
    """The ``scaling`` stage (module docstring): per training subset, the linear reference's and the per-frame
    model's RMSE on the test sequences and on the subset itself. On the whole training split the per-frame model
    is the ``train`` stage's stored run when there is one (the same training)."""
    ups = upsampler(ds)
    train, test = ds.subset("train"), ds.subset("test")
    ups_test = ceval.pooled_rmse((x.fine, ups(x.coarse)) for x in test)
    stored = out / "runs" / ds.scenario / "no_temporal"
    rows, seen = [], set()
    for every in SCALING_EVERY:
        part = train[::every]
        if len(part) in seen:
            continue
        seen.add(len(part))
        ref = ceval.LinearResidual(ups, [x.coarse for x in part], [x.fine for x in part])
        if len(part) == len(train) and (stored / "run.json").is_file():
            run = crun.load_run(stored)
        else:
            sub = dataclasses.replace(ds, split={"train": [x.name for x in part], "test": [x.name for x in test]})
            run = train_method(sub, "no_temporal", s, {}, progress=False)
        row = {
            "every": every,
            "train_sequences": len(part),
            "upsampled_coarse": {"test": ups_test, "train": ceval.pooled_rmse((x.fine, ups(x.coarse)) for x in part)},
            "linear_residual": {
                "test": ceval.pooled_rmse((x.fine, ref(x.coarse)) for x in test),
                "train": ceval.pooled_rmse((x.fine, ref(x.coarse)) for x in part),
                "ridge_lambda": ref.lam,
            },
        }
        row["no_temporal"] = {
            p: ceval.pool(method_errors(run, xs, ds.fine_faces))["rmse"] for p, xs in (("test", test), ("train", part))
        }
        print(
            f"{ds.scenario} scaling, {len(part)} training sequences: linear {row['linear_residual']['test']:.5f} "
            f"(train {row['linear_residual']['train']:.5f}), per-frame {row['no_temporal']['test']:.5f} "
            f"(train {row['no_temporal']['train']:.5f}), upsampled coarse {row['upsampled_coarse']['test']:.5f}",
            flush=True,
        )
        rows.append(row)
    return rows


def stage_jumps(ds) -> dict:
    """Frame-to-frame changes of the fine TS-ACAP and ACAP features over every sequence of the dataset."""
    return {
        kind: cfeat.frame_change_stats(
            [cfeat.encode_sequence(kind, ds.fine_rest, ds.fine_faces, x.fine) for x in ds.sequences]
        )
        for kind in ("ts-acap", "acap")
    }


def _ours_run(out: Path, ds):
    """The run the timing and the figures show: the CLI's default training (self-fed) where it was trained, else
    the teacher-forced one."""
    root = out / "runs" / ds.scenario
    return crun.load_run(root / ("ours_self_fed" if (root / "ours_self_fed" / "run.json").is_file() else "ours"))


def stage_timing(out: Path, ds, s: Settings) -> dict:
    """Table 1: re-simulate a test scenario (coarse and fine) and run our pipeline on its coarse frames, now."""
    from jaxdeform.cloth import scenarios

    run = _ours_run(out, ds)
    sc = _scenario_of(ds, ds.subset("test")[0], s.timing_frames)
    pair = scenarios.simulate_pair(sc, progress=False)  # seconds per frame exclude compilation
    coarse, obstacles = pair["coarse"], pair["obstacles"]
    pins = {k: pair[k] for k in cdata.PINS if k in pair}
    crun.synthesize_timed(run, coarse, obstacles, pins=pins)  # warm-up: compile every stage for this length
    _, t = crun.synthesize_timed(run, coarse, obstacles, pins=pins)
    coarse_sim = float(pair["coarse_seconds_per_frame"])
    fine_sim = float(pair["fine_seconds_per_frame"])
    ours = coarse_sim + t["extraction"] + t["synthesis"] + t["reconstruction"] + t["refinement"]
    return {
        "coarse_simulation": coarse_sim,
        "extraction": t["extraction"],
        "synthesis": t["synthesis"],
        "reconstruction": t["reconstruction"],
        "refinement": t["refinement"],
        "ours_total": ours,
        "fine_simulation": fine_sim,
        "speedup": fine_sim / ours,
        "refined_frames": t["refined_frames"],
        "frames": int(coarse.shape[0]),
        "scenario": sc.meta.get("index"),
    }


def stage_floor(ds, s: Settings) -> dict:
    """The ``floor`` stage (module docstring): fine vs perturbed fine against fine vs upsampled coarse."""
    from jaxdeform.cloth import scenarios

    ups = upsampler(ds)
    per, errors = [], []
    for x in ds.subset("test")[: s.floor_sequences]:
        again = scenarios.simulate_fine(_scenario_of(ds, x, x.fine.shape[0]), perturbation=FLOOR_PERTURBATION)
        again_e = ceval.sequence_errors(x.fine, again, ds.fine_faces)
        up_e = ceval.sequence_errors(x.fine, ups(x.coarse), ds.fine_faces)
        errors.append((again_e, up_e))
        per.append(
            {
                "sequence": x.name,
                "perturbed_fine": again_e["rmse"],
                "upsampled_coarse": up_e["rmse"],
                "perturbed_fine_sted": again_e["sted"],
                "upsampled_coarse_sted": up_e["sted"],
            }
        )
        print(
            f"{ds.scenario} floor {x.name}: perturbed fine {again_e['rmse']:.5f} (STED {again_e['sted']:.4f}), "
            f"upsampled coarse {up_e['rmse']:.5f} (STED {up_e['sted']:.4f})",
            flush=True,
        )
    again_p, up_p = (ceval.pool([e[k] for e in errors]) for k in (0, 1))
    return {
        "perturbation_m": FLOOR_PERTURBATION,
        "sequences": per,
        "perturbed_fine_rmse": again_p["rmse"],
        "upsampled_coarse_rmse": up_p["rmse"],
        "perturbed_fine_sted": again_p["sted"],
        "upsampled_coarse_sted": up_p["sted"],
    }


def loss_figure(out: Path, scenario: str) -> str | None:
    """The training loss curves of the stored runs of ``scenario`` (OUT/runs/KIND/*/run.json with a
    ``loss_curve``) in one log-scale chart, ``loss_KIND.png``; None when no run has a curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = {}
    for path in sorted((out / "runs" / scenario).glob("*/run.json")):
        c = json.loads(path.read_text()).get("loss_curve")
        if c and c["mean"]:
            curves[path.parent.name] = c
    if not curves:
        return None
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, c in curves.items():
        ax.plot(c["every"] * (np.arange(len(c["mean"])) + 0.5), c["mean"], label=name)
    ax.set(xlabel="step", ylabel=f"training loss (mean of {next(iter(curves.values()))['every']} steps)", yscale="log")
    ax.set_title(f"{scenario.upper()}: training loss")
    ax.legend(fontsize=8)
    fig.tight_layout()
    name = f"loss_{scenario}.png"
    with atomic_path(out / name) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return name


def stage_figures(out: Path, ds, s: Settings) -> list[str]:
    run = _ours_run(out, ds)
    ups = upsampler(ds)
    x = ds.subset("test")[0]
    fine, _ = crun.synthesize_timed(run, x.coarse, x.obstacles, pins=x.pins)
    coarse_up = ups(x.coarse)
    n = x.coarse.shape[0]
    frames = np.linspace(n // 4, n - 1, s.figure_frames).astype(int)
    paths = []
    for t in frames:
        path = out / f"strip_{ds.scenario}_{x.name.removesuffix('.npz')}_f{t:03d}.png"
        scene = crun.body_scene(ds.scenario, x.obstacles, t)
        crun.strip_figure(coarse_up[t], fine[t], x.fine[t], ds.fine_faces, path, s.size, scene)
        paths.append(path.name)
    curve = loss_figure(out, ds.scenario)
    return paths + ([curve] if curve else [])


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    """Markdown table lines (header, rule, rows) and a blank line."""
    return (
        ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows] + [""]
    )


def _tested_at(samples_per_edge: int) -> str:
    if samples_per_edge:
        return f"tested at the vertices and on the order-{samples_per_edge} grid of every triangle"
    return "tested at the vertices only"


def _detail_cells(m: dict) -> list[str]:
    """The detail measure's cells of a method's pooled errors (blank where it was not measured)."""
    d = m.get("detail")
    return [f"{d['dihedral_w1']:.4f}", f"{d['fine_scale_rmse']:.5f}"] if d else ["", ""]


def _pen(m: dict) -> str:
    """The largest obstacle penetration of a method's frames at their vertices, in mm (blank if not measured)."""
    return f"{1e3 * m['max_penetration']:.2f}" if "max_penetration" in m else ""


def markdown(summary: dict) -> str:
    lines = [f"# Seed 002 results ({summary.get('machine', '')})", ""]
    for kind, r in summary.get("datasets", {}).items():
        d = r.get("data", {})
        lines += [f"## {kind.upper()}", ""]
        if d:
            v = d.get("vertices", {})
            pen = d.get("penetration", {})
            lines += [
                f"{len(d.get('sequences', []))} sequences x {d.get('frames_per_sequence')} frames; coarse "
                f"{v.get('coarse')} / fine {v.get('fine')} vertices; max obstacle penetration "
                f"{100 * pen.get('coarse_max_over_edge', float('nan')):.3f}% (coarse) / "
                f"{100 * pen.get('fine_max_over_edge', float('nan')):.3f}% (fine) of the mean edge length, "
                f"{_tested_at(pen.get('samples_per_edge', 0))}.",
                "",
            ]
        ev = r.get("evaluate")
        if ev:
            lines += _table(
                [
                    "method",
                    "RMSE (m)",
                    "Hausdorff (m)",
                    "STED",
                    "detail: dihedral W1 (rad)",
                    "fine-scale RMSE (m)",
                    "max penetration (mm)",
                ],
                [
                    [name, f"{m['rmse']:.5f}", f"{m['hausdorff']:.5f}", f"{m['sted']:.4f}", *_detail_cells(m), _pen(m)]
                    for name, m in ev["methods"].items()
                ],
            )
        j = r.get("jumps")
        if j:
            lines += _table(
                ["fine features", "largest frame-to-frame change", "99.9th pct", "99th pct", "changes above pi"],
                [
                    [
                        kind,
                        f"{st['max']:.2f}",
                        f"{st['p99_9']:.3f}",
                        f"{st['p99']:.3f}",
                        f"{100 * st['fraction_above_pi']:.3f}% of {st['count']:,}",
                    ]
                    for kind, st in j.items()
                ],
            )
        sc = r.get("scale")
        if sc:
            lines += _table(
                [
                    "upsampled coarse error",
                    "RMSE (m)",
                    "at the coarse mesh's scale",
                    "finer",
                    "share at the coarse scale",
                ],
                [
                    [
                        f"{part} sequences",
                        f"{e['rmse']:.5f}",
                        f"{e['coarse_scale_rmse']:.5f}",
                        f"{e['finer_rmse']:.5f}",
                        f"{100 * e['coarse_scale_share']:.1f}%",
                    ]
                    for part, e in sc.items()
                ],
            )
        sg = r.get("scaling")
        if sg:
            lines += _table(
                [
                    "training sequences",
                    "upsampled coarse: test / train RMSE (m)",
                    "linear reference",
                    "per-frame model",
                ],
                [
                    [str(g["train_sequences"])]
                    + [
                        f"{g[k]['test']:.5f} / {g[k]['train']:.5f}"
                        for k in ("upsampled_coarse", "linear_residual", "no_temporal")
                    ]
                    for g in sg
                ],
            )
        fl = r.get("floor")
        if fl:
            lines += [
                f"Fine simulation against itself from a start perturbed by {fl['perturbation_m'] * 1e3:.1f} mm: "
                f"RMSE {fl['perturbed_fine_rmse']:.5f} m over {len(fl['sequences'])} test sequences, where the "
                f"upsampled coarse cloth is {fl['upsampled_coarse_rmse']:.5f} m from it"
                + (
                    f"; STED {fl['perturbed_fine_sted']:.4f} (upsampled coarse {fl['upsampled_coarse_sted']:.4f})"
                    if "perturbed_fine_sted" in fl
                    else ""
                )
                + ".",
                "",
            ]
        tm = r.get("timing")
        if tm:
            lines += [
                "| coarse sim | TS-ACAP extraction | synthesis | reconstruction | refinement | ours total | "
                "fine sim | speedup |",
                "|---|---|---|---|---|---|---|---|",
                f"| {tm['coarse_simulation'] * 1e3:.1f} ms | {tm['extraction'] * 1e3:.1f} ms | "
                f"{tm['synthesis'] * 1e3:.1f} ms | {tm['reconstruction'] * 1e3:.1f} ms | "
                f"{tm['refinement'] * 1e3:.1f} ms | {tm['ours_total'] * 1e3:.1f} ms | "
                f"{tm['fine_simulation'] * 1e3:.1f} ms | {tm['speedup']:.1f}x |",
                "",
            ]
    return "\n".join(lines) + "\n"


def _merge(path: Path, summary: dict, kind: str, r: dict) -> dict:
    """Write this dataset's record into summary.json as it is NOW on disk (another process may run another
    dataset at the same time); returns the merged summary."""
    current = json.loads(path.read_text()) if path.is_file() else {}
    current.update({k: v for k, v in summary.items() if k != "datasets"})
    current.setdefault("datasets", {})[kind] = r
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(current, indent=1, default=float) + "\n")
    return current


STAGES = ("data", "train", "evaluate", "linear", "scale", "scaling", "jumps", "timing", "floor", "figures")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", choices=("default", "test"), default="default")
    ap.add_argument("--out")
    ap.add_argument("--datasets", nargs="+", default=["sheet", "disk"], choices=["sheet", "disk", "skirt", "pants"])
    ap.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    ap.add_argument("--force", action="store_true", help="redo cached data and runs")
    ap.add_argument("--sequences", type=int, metavar="N", help="sequences per dataset (default: the configuration's)")
    ap.add_argument("--floor-sequences", type=int, metavar="N", help="test scenarios the floor stage re-simulates")
    ap.add_argument("--steps", type=int, metavar="N", help="training steps per model (default: the configuration's)")
    ap.add_argument(
        "--methods", nargs="+", choices=list(METHODS), default=list(METHODS), help="methods to train and evaluate"
    )
    args = ap.parse_args(argv)
    root = Path(__file__).resolve().parent
    out = (
        Path(args.out)
        if args.out
        else (root / "results" if args.config == "default" else Path("out/experiments/cloth-test"))
    )
    out.mkdir(parents=True, exist_ok=True)
    s = settings(args.config)
    if args.sequences is not None:
        if args.sequences < 2:
            ap.error(f"--sequences must be at least 2, got {args.sequences}.")
        s = dataclasses.replace(s, sequences={k: args.sequences for k in s.sequences})
    if args.steps is not None:
        if args.steps < 1:
            ap.error(f"--steps must be at least 1, got {args.steps}.")
        s = dataclasses.replace(s, steps=args.steps)
    if args.floor_sequences is not None:
        s = dataclasses.replace(s, floor_sequences=max(args.floor_sequences, 1))
    path = out / "summary.json"
    summary = json.loads(path.read_text()) if path.is_file() else {}
    summary["machine"] = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, CPU only"
    summary["config"] = args.config
    for kind in args.datasets:
        r = summary.setdefault("datasets", {}).setdefault(kind, {})
        if "data" in args.stages or not (out / "data" / kind / "dataset.json").is_file():
            r["data"] = stage_data(out, kind, s, args.force)
        ds = cdata.load_dataset(out / "data" / kind)
        cache: dict = {}
        if "train" in args.stages:
            r["train"] = {**r.get("train", {}), **stage_train(out, ds, s, args.force, cache, args.methods)}
        if "evaluate" in args.stages:
            ev = stage_evaluate(out, ds, cache, args.methods)
            ev["methods"] = {**r.get("evaluate", {}).get("methods", {}), **ev["methods"]}
            r["evaluate"] = {**r.get("evaluate", {}), **ev}
            m = r["evaluate"]["methods"]
            r["rmse"] = {k: v["rmse"] for k, v in m.items()}
            r["hausdorff"] = {k: v["hausdorff"] for k, v in m.items()}
            r["sted"] = {k: v["sted"] for k, v in m.items()}
        if "linear" in args.stages:
            stage_linear(ds, r)
        if "scale" in args.stages:
            r["scale"] = stage_scale(ds)
        if "scaling" in args.stages:
            r["scaling"] = stage_scaling(out, ds, s)
        if "jumps" in args.stages:
            r["jumps"] = stage_jumps(ds)
            r.get("evaluate", {}).pop("largest_frame_change_fine", None)
        if "timing" in args.stages:
            r["timing"] = stage_timing(out, ds, s)
            r["speedup"] = r["timing"]["speedup"]
        if "floor" in args.stages:
            r["floor"] = stage_floor(ds, s)
        if "figures" in args.stages:
            r["figures"] = stage_figures(out, ds, s)
        summary = _merge(path, summary, kind, r)
    with atomic_path(out / "results.md") as tmp:
        tmp.write_text(markdown(summary))
    print(f"wrote {path} and {out / 'results.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
