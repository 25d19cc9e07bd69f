"""ACAP features files (.npz), as ``jaxdeform acap encode`` writes them and ``jaxdeform acap decode`` reads them.

Arrays: ``log_r`` (N, V, 3, 3), ``s`` (N, V, 3, 3), ``features`` (N, V, 9), ``scaled`` (N, V, 9), ``scaler``
(:meth:`Scaler.to_array`), ``faces`` (F, 3) int32, ``reference`` (V, 3), and the 0-d strings ``consistency`` and
``weighting``. A file with ``scaled`` and ``scaler`` but no ``features`` is read by inverse scaling.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jaxdeform.errors import ConnectivityError, JaxDeformError, MeshFormatError

WEIGHTINGS = ("official", "cotangent")


def _not_finite_reason(vertices, reference, features) -> str:
    """One sentence on why encoded features are not finite: a scale the dtype cannot hold, or collapsed faces."""
    frames = np.asarray(vertices)
    bad = np.flatnonzero(~np.isfinite(np.asarray(features)).reshape(len(features), -1).all(axis=1))
    k = int(bad[0]) if bad.size else 0
    dtype = np.asarray(reference).dtype
    sizes = [float(np.linalg.norm(np.ptp(np.asarray(x, np.float64), axis=0))) for x in (reference, frames[k])]
    tiny, huge = float(np.finfo(dtype).tiny) ** 0.25, float(np.finfo(dtype).max) ** 0.25
    if any(not tiny < size < huge for size in sizes):
        return (
            f"the features of frame {k} are not finite: the reference spans {sizes[0]:.3g} and the frame "
            f"{sizes[1]:.3g}, beyond what {dtype.name} features hold ({tiny:.1g} to {huge:.1g}); rescale the meshes"
            f"{' or encode in float64' if dtype == np.float32 else ''}; nothing was written."
        )
    return (
        f"the features of frame {k} are not finite: the frame or the reference has collapsed (zero-area or "
        "zero-length) faces; nothing was written."
    )


def encode_arrays(
    vertices: np.ndarray,
    reference: np.ndarray,
    faces: np.ndarray,
    consistency: str = "spatial",
    weighting: str = "official",
) -> dict[str, np.ndarray]:
    """The arrays of a features file (module docstring), computed in the vertices' dtype.

    **Arguments:**

    - `vertices`: frames `(N, V, 3)` sharing `faces` with `reference`.
    - `reference`: reference positions `(V, 3)`.
    - `faces`: triangles `(F, 3)`.
    - `consistency`: "spatial", "temporal" or "none".
    - `weighting`: "official" or "cotangent".

    **Returns:**

    A dict of the file's arrays by name.

    **Raises:**

    `JaxDeformError` when the features are not finite; the errors of :func:`prepare` and
    :meth:`Acap.encode_parts`.
    """
    from jaxdeform.acap.features import Scaler, features_from, log_matrices, prepare

    acap = prepare(reference, faces, weighting=weighting)
    v, s = acap.encode_parts(vertices, consistency)
    v, s = np.asarray(v), np.asarray(s)
    features = np.asarray(features_from(v, s))
    scaler = Scaler.fit(features)
    scaled = np.asarray(scaler.transform(features))
    log_r = np.asarray(log_matrices(v))
    if not (np.all(np.isfinite(features)) and np.all(np.isfinite(scaled))):
        raise JaxDeformError(_not_finite_reason(vertices, reference, features))
    return {
        "log_r": log_r,
        "s": s,
        "features": features,
        "scaled": scaled,
        "scaler": scaler.to_array(),
        "faces": np.asarray(faces, dtype=np.int32),
        "reference": reference,
        "consistency": np.array(consistency),
        "weighting": np.array(weighting),
    }


def rotation_angles(log_r: np.ndarray) -> np.ndarray:
    """The rotation angles of skew log matrices.

    **Arguments:**

    - `log_r`: skew matrices `(..., 3, 3)`.

    **Returns:**

    Angles in radians `(...)`: the norms of their axis-angle vectors.
    """
    return np.linalg.norm(np.stack([log_r[..., 2, 1], log_r[..., 0, 2], log_r[..., 1, 0]], axis=-1), axis=-1)


def save_features(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    """Write arrays as one .npz file, atomically (through a temporary sibling).

    **Arguments:**

    - `path`: the file to write.
    - `arrays`: the arrays by name (e.g. from :func:`encode_arrays`).
    """
    from jaxdeform.mesh.io import atomic_path

    with atomic_path(Path(path)) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def _string(data: dict, key: str, default: str, allowed: tuple[str, ...], path: Path) -> str:
    if key not in data:
        return default
    value = data[key]
    if value.ndim != 0 or value.dtype.kind not in "US":
        raise MeshFormatError(f"{path}: '{key}' must be a 0-d string array.")
    text = str(value.item().decode() if value.dtype.kind == "S" else value.item())
    if text not in allowed:
        raise MeshFormatError(f"{path}: '{key}' is {text!r}; expected one of {', '.join(allowed)}.")
    return text


def _features_array(data: dict, path: Path) -> np.ndarray:
    from jaxdeform.acap.features import Scaler

    if "features" in data:
        return data["features"]
    if "scaled" in data and "scaler" in data:
        scaled, scaler = data["scaled"], data["scaler"]
        if scaler.size < 4 or scaler.dtype.kind not in "iuf":
            raise MeshFormatError(f"{path}: 'scaler' must hold 4 numbers (rot_min, rot_max, s_min, s_max).")
        if scaled.ndim not in (2, 3) or scaled.shape[-1] != 9 or scaled.dtype.kind != "f":
            raise MeshFormatError(
                f"{path}: 'scaled' must be a float (N, V, 9) array, got {scaled.dtype} {scaled.shape}."
            )
        return np.asarray(Scaler.from_array(scaler).inverse(scaled))
    raise MeshFormatError(f"{path}: holds neither 'features' nor 'scaled' with 'scaler'.")


def read_features(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Read and check a features file.

    **Arguments:**

    - `path`: the .npz file.

    **Returns:**

    `(features, reference, faces, weighting)`: features `(N, V, 9)` and reference `(V, 3)` in a common float
    dtype (at least float32), faces `(F, 3)` int32 and the weighting name.

    **Raises:**

    `MeshFormatError` or `ConnectivityError`, one sentence naming `path`, for anything wrong.
    """
    from jaxdeform.mesh.io import read_npz_arrays

    path = Path(path)
    data = read_npz_arrays(path)
    features = _features_array(data, path)
    for key in ("reference", "faces"):
        if key not in data:
            raise MeshFormatError(f"{path}: the array '{key}' is missing.")
    reference, faces = data["reference"], data["faces"]
    if features.ndim == 2:
        features = features[None]
    if features.ndim != 3 or features.shape[-1] != 9 or features.dtype.kind != "f":
        raise MeshFormatError(
            f"{path}: features must be a float (N, V, 9) array, got {features.dtype} {features.shape}."
        )
    if features.shape[0] == 0:
        raise MeshFormatError(f"{path}: the features hold no frames (N = 0).")
    if reference.ndim != 2 or reference.shape[1] != 3 or reference.dtype.kind != "f":
        raise MeshFormatError(
            f"{path}: 'reference' must be a float (V, 3) array, got {reference.dtype} {reference.shape}."
        )
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu" or faces.shape[0] == 0:
        raise MeshFormatError(
            f"{path}: 'faces' must be a non-empty integer (F, 3) array, got {faces.dtype} {faces.shape}."
        )
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
