"""Runs of seed 003 (rigid parts of a shape population) through the run-folder API of :mod:`jaxdeform.runs`.

A run folder holds

    run.json      kind "parts", the configuration, the data it was fitted to and the fit's summary
                  (:func:`jaxdeform.parts.hierarchy.summary`: parts, iterations per stage, rmse, seconds)
    summary.json  the same summary with the per-stage records (parts, iterations, log-likelihoods)
    model         the fitted parameters, labels, latent images, shapes, faces and reconstruction
                  (an orbax checkpoint, :func:`save_run`)

The algorithm (:mod:`jaxdeform.parts.hierarchy`, :mod:`jaxdeform.parts.mfa`) holds no I/O; :func:`save_run` and
:func:`load_run` read and write the fit.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxdeform import runs
from jaxdeform.errors import JaxDeformError, MeshFormatError
from jaxdeform.mesh.fingerprint import RTOL, fingerprint
from jaxdeform.mesh.io import atomic_path, check_same_connectivity, load_sequence, staged_folder
from jaxdeform.nn.archive import read_tree, save_tree
from jaxdeform.parts import hierarchy
from jaxdeform.parts.mfa import MFA

KIND = "parts"


@dataclasses.dataclass(frozen=True)
class Config:
    """Algorithm 1's parameters (:func:`jaxdeform.parts.hierarchy.fit`); defaults: the paper's where it gives one."""

    initial_parts: int = hierarchy.INITIAL_PARTS
    threshold: float = hierarchy.THRESHOLD
    max_split: int = hierarchy.MAX_SPLIT
    min_part_vertices: int = hierarchy.MIN_PART_VERTICES
    seed: int = 0

    def __post_init__(self):
        if self.initial_parts < 1:
            raise ValueError(f"initial_parts must be at least 1, got {self.initial_parts}.")
        if not self.threshold > 0:
            raise ValueError(f"threshold must be positive, got {self.threshold}.")
        if self.max_split < 2 or self.min_part_vertices < 1:
            raise ValueError("max_split must be at least 2 and min_part_vertices at least 1.")


#: the fields of a parts run.json and their JSON types (:func:`jaxdeform.runs.check_fields`)
RECORD_FIELDS = {
    "config": ("object",),
    "data": ("string", "list", "null"),
    "summary": ("object",),
    "fingerprint": ("object",),
}
#: named configurations: the library defaults and a CPU-sized one (fewer coarse parts, coarser threshold)
CONFIGS = {"default": Config(), "test": Config(initial_parts=2, threshold=1e-3, max_split=2)}


@dataclasses.dataclass
class Run:
    """A parts run: the fit, the shapes and faces it was fitted to, its record and folder."""

    path: Path | None
    record: dict
    fit: hierarchy.PartsFit
    vertices: np.ndarray  # (M, V, 3)
    faces: np.ndarray  # (F, 3)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Run:
        """Read a parts run folder.

        **Arguments:**

        - ``path``: a folder written by :func:`fit`.

        **Returns:**

        The :class:`Run`.

        **Raises:**

        :class:`~jaxdeform.runs.RunFolderError` if ``path`` is not a run folder or is another method's;
        one-sentence errors of :func:`load_run` for a damaged model.
        """
        path = Path(path)
        record = runs.read_record(path, KIND)
        where = path / runs.RECORD
        runs.check_fields(where, record, RECORD_FIELDS, optional=("data", "summary", "fingerprint"))
        try:
            Config(**record["config"])
        except (TypeError, ValueError) as exc:
            raise runs.RunFolderError(f"{where}: its config is not a parts configuration ({exc}).") from None
        fit_, vertices, faces = load_run(path)
        runs.check_fingerprint(where, record, vertices, faces, f"{path / 'model'}")
        return cls(path, record, fit_, vertices, faces)


def save_run(
    path, fit_: hierarchy.PartsFit, vertices: np.ndarray, faces: np.ndarray, extra: dict | None = None
) -> dict:
    """Write RUN/model (an orbax checkpoint folder: parameters, labels, latent, shapes, faces) and RUN/summary.json.

    Both are written under temporary names and renamed, so an interrupted run leaves nothing half-written.

    **Arguments:**

    - ``path``: the run folder (created if needed).
    - ``fit_``: the fit.
    - ``vertices``, ``faces``: the shapes ``(M, V, 3)`` and faces ``(F, 3)`` it was fitted to.
    - ``extra``: more entries for the summary.

    **Returns:**

    The summary written (:func:`jaxdeform.parts.hierarchy.summary`, ``extra`` and the stages).
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    p = fit_.params
    arrays = {
        "log_pi": p.log_pi,
        "mu": p.mu,
        "rot": p.rot,
        "d": p.d,
        "sigma2": p.sigma2,
        "labels": fit_.labels,
        "latent": fit_.latent,
        "vertices": vertices,
        "faces": faces,
        "reconstruction": fit_.reconstruction,
    }
    record = {"format": MODEL_FORMAT, "version": MODEL_VERSION}
    save_tree(path / "model", {k: np.asarray(v) for k, v in arrays.items()}, record)
    info = hierarchy.summary(fit_, vertices) | (extra or {})
    info["stages"] = fit_.stages
    with atomic_path(path / "summary.json") as tmp:
        tmp.write_text(json.dumps(info, indent=2))
    return info


#: the record of a parts model checkpoint (RUN/model)
MODEL_FORMAT = "jaxdeform-parts-model"
MODEL_VERSION = 1
_RUN_ARRAYS = ("log_pi", "mu", "rot", "d", "sigma2", "labels", "latent", "vertices", "faces", "reconstruction")


def _read_summary(path: Path) -> dict:
    """The run's summary.json as a dict ({} where there is none), or one :class:`MeshFormatError` sentence."""
    if not path.is_file():
        return {}
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise MeshFormatError(f"{path}: not valid JSON.") from None
    if not isinstance(info, dict):
        raise MeshFormatError(f"{path}: not a parts-run summary (a JSON object).")
    return info


def load_run(path) -> tuple[hierarchy.PartsFit, np.ndarray, np.ndarray]:
    """The fit, shapes and faces of a run folder written by :func:`save_run`.

    **Arguments:**

    - ``path``: the run folder.

    **Returns:**

    ``(fit, vertices (M, V, 3), faces)``.

    **Raises:**

    ``FileNotFoundError`` if the model checkpoint is missing; a damaged run gets one :class:`MeshFormatError`
    sentence.
    """
    path = Path(path)
    model = path / "model"
    if not model.exists():
        raise FileNotFoundError(f"{path} is not a parts run: {model.name} is missing.")
    a = read_tree(model, "parts model", MODEL_FORMAT, MODEL_VERSION, error=MeshFormatError)[1]
    missing = [k for k in _RUN_ARRAYS if k not in a]
    if missing:
        raise MeshFormatError(f"{model}: not a parts model (missing {', '.join(missing)}).")
    k = a["log_pi"].shape[0] if a["log_pi"].ndim == 1 else -1
    m, v = a["vertices"].shape[:2] if a["vertices"].ndim == 3 else (-1, -1)
    shapes = {
        "mu": (k, m, 3),
        "rot": (k, m, 3, 3),
        "d": (k, 3),
        "sigma2": (k,),
        "labels": (v,),
        "latent": (v, 3),
        "vertices": (m, v, 3),
        "reconstruction": (m, v, 3),
    }
    bad = [n for n, s in shapes.items() if a[n].shape != s or -1 in s]
    if bad or a["faces"].ndim != 2 or a["faces"].shape[1] != 3:
        raise MeshFormatError(f"{model}: inconsistent array shapes ({', '.join(bad) or 'faces'}).")
    if a["labels"].dtype.kind not in "iu" or a["faces"].dtype.kind not in "iu":
        raise MeshFormatError(
            f"{model}: labels and faces must be integer arrays, got {a['labels'].dtype} and {a['faces'].dtype}."
        )
    if a["labels"].min() < 0 or a["labels"].max() >= k:
        raise MeshFormatError(f"{model}: labels outside the model's {k} parts.")
    if a["faces"].size == 0 or a["faces"].min() < 0 or a["faces"].max() >= v:
        raise MeshFormatError(f"{model}: faces index vertices outside the model's {v}.")
    floats = [
        n
        for n in ("log_pi", "mu", "rot", "d", "sigma2", "latent", "vertices", "reconstruction")
        if a[n].dtype.kind != "f" or not np.all(np.isfinite(a[n]))
    ]
    if floats:
        raise MeshFormatError(f"{model}: {', '.join(floats)} must hold finite floats.")
    info = _read_summary(path / "summary.json")
    p = MFA(**{n: jnp.asarray(a[n]) for n in ("log_pi", "mu", "rot", "d", "sigma2")})
    fit_ = hierarchy.PartsFit(
        params=p,
        labels=a["labels"],
        latent=a["latent"],
        reconstruction=a["reconstruction"],
        stages=info.get("stages", []),
        seconds=float(info.get("seconds", 0.0)),
        disconnected_parts=list(info.get("disconnected_parts", [])),
    )
    return fit_, a["vertices"], a["faces"]


def load_data(data) -> tuple[np.ndarray, np.ndarray]:
    """Shapes and faces of a parts fit: a folder, a list of mesh files or one .npz sequence of at least two shapes.

    **Arguments:**

    - ``data``: the shapes (as :func:`jaxdeform.mesh.io.load_sequence` reads them) or ``(vertices, faces)``.

    **Returns:**

    ``(vertices (M, V, 3), faces (F, 3))``, checked by :func:`jaxdeform.parts.hierarchy.check_shapes`.
    """
    if isinstance(data, tuple) and len(data) == 2 and not isinstance(data[0], (str, os.PathLike)):
        vertices, faces = data
    else:
        vertices, faces = load_sequence(data if isinstance(data, (str, os.PathLike)) or len(data) > 1 else data[0])
    return hierarchy.check_shapes(vertices, faces)


def _data_name(data) -> str | list[str] | None:
    if isinstance(data, (str, os.PathLike)):
        return str(data)
    if isinstance(data, (list, tuple)) and all(isinstance(d, (str, os.PathLike)) for d in data):
        return [str(d) for d in data]
    return None


def fit(
    data,
    config: str | Config = "default",
    out: str | os.PathLike | None = None,
    *,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> Run:
    """Fit Algorithm 1 to a shape population and write the run folder ``out``.

    **Arguments:**

    - ``data``: the shapes (:func:`load_data`).
    - ``config``: a name of :data:`CONFIGS` or a :class:`Config`.
    - ``out``: the run folder (built beside it, renamed at the end); None: nothing is written.
    - ``progress``: print one line per stage (where ``log`` is None).
    - ``log``: receives the per-stage lines (default: ``print`` when ``progress``).

    **Returns:**

    The :class:`Run`.

    **Raises:**

    ``ValueError`` for fewer than two shapes or more initial parts than vertices; the loaders' one-sentence errors
    for bad meshes.
    """
    cfg = runs.config(KIND, config, Config)
    vertices, faces = load_data(data)
    if cfg.initial_parts > vertices.shape[1]:
        raise ValueError(f"initial_parts {cfg.initial_parts} exceeds the {vertices.shape[1]} vertices of the meshes.")
    if log is None:
        log = (lambda line: print(line, flush=True)) if progress else (lambda line: None)
    fit_ = hierarchy.fit(vertices, faces, **dataclasses.asdict(cfg), log=log)
    record = {"kind": KIND, "config": dataclasses.asdict(cfg), "data": _data_name(data)}
    record["fingerprint"] = fingerprint(vertices, faces)
    record["summary"] = hierarchy.summary(fit_, vertices)
    run = Run(None, record, fit_, vertices, faces)
    if out is not None:
        out = Path(out)
        with staged_folder(out) as tmp:
            save_run(tmp, fit_, vertices, faces, extra={"data": record["data"]})
            with atomic_path(tmp / runs.RECORD) as t:
                t.write_text(json.dumps(record, indent=1) + "\n")
        run.path = out
    return run


def evaluate(run: Run, data=None) -> dict:
    """Reconstruction errors of the run's parts on its shapes.

    **Arguments:**

    - ``run``: the run.
    - ``data``: the shapes to compare with (None: the shapes of the run); they must be the run's own shapes (the
        same number, connectivity and positions within :data:`jaxdeform.mesh.fingerprint.RTOL` of their size, as
        another file format of them reads back), since a fit's parts and rotations are per shape.

    **Returns:**

    ``{"parts", "rmse", "rmse_over_diagonal", "max_vertex_rmse_over_diagonal", "per_shape_rmse"}``.

    **Raises:**

    ``JaxDeformError`` for data of another population.
    """
    vertices = run.vertices
    if data is not None:
        vertices, faces = load_data(data)
        where = str(_data_name(data) or "the data")
        check_same_connectivity(run.faces, faces, run.vertices.shape[1], vertices.shape[1], where)
        if vertices.shape[0] != run.vertices.shape[0]:
            raise JaxDeformError(
                f"{where} holds {vertices.shape[0]} shapes but the run was fitted to {run.vertices.shape[0]}."
            )
        size = hierarchy.bbox_diagonal(run.vertices) or 1.0
        off = np.abs(np.asarray(vertices, np.float64) - run.vertices).max(axis=(1, 2))
        bad = np.flatnonzero(~(off <= RTOL * size))
        if bad.size:
            k = int(bad[0])
            raise JaxDeformError(
                f"{where} is not the data the run was fitted on: its shape {k} lies up to {off[k]:.3g} from the "
                f"run's ({off[k] / size:.3g} of the shapes' size); pass the run's own data."
            )
    diff = np.sum((vertices - run.fit.reconstruction) ** 2, axis=-1)  # (M, V)
    diag = hierarchy.bbox_diagonal(vertices)
    rmse = float(np.sqrt(diff.mean()))  # hierarchy.rmse, from the squared distances already at hand
    return {
        "parts": run.fit.n_parts,
        "rmse": rmse,
        "rmse_over_diagonal": rmse / diag,
        "max_vertex_rmse_over_diagonal": float(np.sqrt(diff.mean(axis=0)).max() / diag),
        "per_shape_rmse": np.sqrt(diff.mean(axis=1)).tolist(),
    }


def show(run: Run, out: str | os.PathLike, shape: int = 0) -> dict:
    """Write segmentation.png, error.png and reconstruction.png of the run into the folder ``out``.

    **Arguments:**

    - ``run``: the run.
    - ``out``: the folder (created if needed; each figure replaces a file of its name, atomically).
    - ``shape``: the shape the parts and the error are drawn on.

    **Returns:**

    ``{"parts", "shape", "files"}``.

    **Raises:**

    ``ValueError`` for a shape index outside the run's shapes.
    """
    from jaxdeform.parts import figures

    n = run.vertices.shape[0]
    if not -n <= shape < n:
        raise ValueError(f"shape {shape} is not a shape of the run (it has {n} shapes: 0..{n - 1}).")
    shape %= n
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    error = np.sqrt(np.mean(np.sum((run.vertices - run.fit.reconstruction) ** 2, axis=-1), axis=0))
    files = ["segmentation.png", "error.png", "reconstruction.png"]
    figures.segmentation_figure(run.vertices[shape], run.faces, run.fit.labels, out / files[0])
    label = "RMS reconstruction error over the shapes"
    figures.error_figure(run.vertices[shape], run.faces, error, out / files[1], label=label)
    figures.strip_figure(run.fit.reconstruction, run.faces, out / files[2], labels=run.fit.labels)
    return {"parts": run.fit.n_parts, "shape": shape, "files": files}
