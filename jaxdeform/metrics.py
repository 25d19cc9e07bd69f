"""Error measures between a reference sequence and its reconstruction (seed 000 Sec. 5; seed 002 evaluation).

- :func:`normalize_pair`: the seed-000 protocol "align all the models and scale them to fit within a unit
  ball": every shape is centred on its centroid, each reconstructed shape is rotated onto its reference by a
  proper Procrustes fit (optional), and both sequences are scaled by one factor. Three readings of that factor
  (:data:`NORMALIZATIONS`): ``"radius"`` puts the reference sequence inside the ball of radius 1 (the default);
  ``"diameter-first-shape"`` divides by twice the radius of the data set's first shape about its centroid (the
  group's ``scalemodel.m`` maps every mesh with the first mesh's centre and radius into a ball of diameter 1);
  ``"raw"`` keeps the data's units.
- :func:`erms`: 1000 * sqrt(sum over shapes and vertices |v - v'|^2) / sqrt(3 N V) (the group's ERMS.m);
  :func:`erms_per_shape` splits it by shape.
- :func:`relative_squared_error`: eq. (8) of seed 000, |X_i - X^_i|_F^2 / |X_i|_F^2 per shape (features).
- :func:`sted`: the spatial-temporal edge difference of Vasa and Skala (2011), as documented there in words
  (no public code exists); our choices are stated in its docstring.
- :func:`hausdorff`: symmetric Hausdorff distance between the vertex sets of two shapes.

Numpy in, floats out: these are evaluation functions, run once per experiment on the host.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from jaxdeform.mesh.topology import unique_edges


def _as_sequence(x) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"expected shapes (N, V, 3) or (V, 3), got {x.shape}.")
    return x


def _check_pair(ref, rec) -> tuple[np.ndarray, np.ndarray]:
    ref, rec = _as_sequence(ref), _as_sequence(rec)
    if ref.shape != rec.shape:
        raise ValueError(f"reference {ref.shape} and reconstruction {rec.shape} differ in shape.")
    return ref, rec


def proper_rotation(a: np.ndarray) -> np.ndarray:
    """The proper rotation R maximizing tr(R^T A) for each (3, 3) in a batch (numpy): with A = sum_i y_i x_i^T,
    the rotation that best maps the points x_i onto y_i (Kabsch)."""
    u, _, vt = np.linalg.svd(a)
    flip = np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)
    u = u.copy()
    u[..., :, 2] *= flip[..., None]
    return u @ vt


NORMALIZATIONS = ("radius", "diameter-first-shape", "raw")


def normalize_pair(
    ref, rec, *, rotate: bool = True, scale: str = "radius", first=None
) -> tuple[np.ndarray, np.ndarray]:
    """(reference, reconstruction) centred shape by shape, the reconstruction rigidly aligned to the reference
    shape by shape (``rotate``), and both divided by one factor.

    **Arguments:**

    - ``ref``, ``rec``: shapes ``(N, V, 3)`` (or one ``(V, 3)``).
    - ``rotate``: align each reconstructed shape to its reference by a proper rotation.
    - ``scale``: one of :data:`NORMALIZATIONS`: ``"radius"``: the factor is the largest distance of a centred
      reference vertex from the origin (the sequence fits the unit ball); ``"diameter-first-shape"``: twice the
      largest distance of ``first``'s vertices from its centroid; ``"raw"``: 1.
    - ``first``: the data set's first shape ``(V, 3)`` for ``"diameter-first-shape"``; None: ``ref[0]``.

    **Returns:**

    The normalized pair, float64 ``(N, V, 3)`` each.

    **Raises:**

    ``ValueError`` for shapes that differ, an unknown ``scale`` or a reference (or first shape) that collapses
    to a point.
    """
    ref, rec = _aligned(ref, rec, rotate)
    factor = _factor(ref, scale, first)
    return ref / factor, rec / factor


def _aligned(ref, rec, rotate: bool) -> tuple[np.ndarray, np.ndarray]:
    """The pair centred shape by shape, rec rotated onto ref shape by shape (``rotate``)."""
    ref, rec = _check_pair(ref, rec)
    ref = ref - ref.mean(axis=1, keepdims=True)
    rec = rec - rec.mean(axis=1, keepdims=True)
    if rotate:
        r = proper_rotation(np.einsum("nvx,nvy->nxy", ref, rec))  # maps rec onto ref
        rec = np.einsum("nxy,nvy->nvx", r, rec)
    return ref, rec


def _factor(ref: np.ndarray, scale: str, first) -> float:
    """The divisor of :func:`normalize_pair` for the centred reference ``ref`` (N, V, 3)."""
    if scale not in NORMALIZATIONS:
        raise ValueError(f"unknown Erms normalization {scale!r}; choose one of {', '.join(NORMALIZATIONS)}.")
    if scale == "raw":
        return 1.0
    if scale == "radius":
        factor = float(np.sqrt((ref**2).sum(axis=-1)).max())
    else:
        base = _as_sequence(ref[0] if first is None else first)[0]
        if base.shape != ref.shape[1:]:
            raise ValueError(f"the first shape {base.shape} does not match the shapes' {ref.shape[1:]}.")
        factor = 2.0 * float(np.sqrt(((base - base.mean(axis=0)) ** 2).sum(axis=-1)).max())
    if factor <= 0:
        raise ValueError("the reference shapes collapse to points.")
    return factor


def erms(ref, rec, *, normalize: bool = True, rotate: bool = True, scale: str = "radius", first=None) -> float:
    """1000 sqrt(sum |v - v'|^2) / sqrt(3 N V), after :func:`normalize_pair` (``rotate``, ``scale``, ``first``
    as there) unless ``normalize=False``."""
    ref, rec = normalize_pair(ref, rec, rotate=rotate, scale=scale, first=first) if normalize else _check_pair(ref, rec)
    n, v = ref.shape[:2]
    return float(1000.0 * np.sqrt(np.sum((ref - rec) ** 2)) / np.sqrt(3.0 * n * v))


def erms_per_shape(
    ref, rec, *, normalize: bool = True, rotate: bool = True, scale: str = "radius", first=None
) -> np.ndarray:
    """(N,) Erms of each shape under the sequence's normalization (:func:`normalize_pair` of the whole pair):
    their root mean square is :func:`erms` of the sequence."""
    ref, rec = normalize_pair(ref, rec, rotate=rotate, scale=scale, first=first) if normalize else _check_pair(ref, rec)
    return _per_shape(ref, rec)


def erms_per_shape_by_normalization(ref, rec, *, rotate: bool = True, first=None) -> dict[str, np.ndarray]:
    """:func:`erms_per_shape` under each of :data:`NORMALIZATIONS` (name -> (N,)), the pair aligned once."""
    ref, rec = _aligned(ref, rec, rotate)
    raw = _per_shape(ref, rec)
    return {scale: raw / _factor(ref, scale, first) for scale in NORMALIZATIONS}


def _per_shape(ref: np.ndarray, rec: np.ndarray) -> np.ndarray:
    """(N,) 1000 sqrt(sum over a shape's vertices |v - v'|^2) / sqrt(3 V)."""
    return 1000.0 * np.sqrt(np.sum((ref - rec) ** 2, axis=(1, 2))) / np.sqrt(3.0 * ref.shape[1])


def relative_squared_error(x, x_hat) -> np.ndarray:
    """Eq. (8) of seed 000 per shape: |X_i - X^_i|_F^2 / |X_i|_F^2 for features (N, V, C)."""
    x, x_hat = np.asarray(x, np.float64), np.asarray(x_hat, np.float64)
    if x.shape != x_hat.shape:
        raise ValueError(f"features {x.shape} and reconstruction {x_hat.shape} differ in shape.")
    axes = tuple(range(1, x.ndim))
    den = np.sum(x**2, axis=axes)
    if np.any(den == 0):
        raise ValueError("a shape has all-zero features; its relative error is undefined.")
    return np.sum((x - x_hat) ** 2, axis=axes) / den


def _neighbourhood_edges(edges: np.ndarray, n: int, rings: int) -> sp.csr_matrix:
    """(V, E) 0/1 matrix: edges with an end point within ``rings - 1`` hops of each vertex (rings >= 1:
    the edges incident to the vertex and, for rings = 2, those of its one-ring neighbours)."""
    m = edges.shape[0]
    inc = sp.csr_matrix(
        (np.ones(2 * m), (np.r_[edges[:, 0], edges[:, 1]], np.r_[np.arange(m), np.arange(m)])), shape=(n, m)
    )
    reach = sp.identity(n, format="csr")
    adj = (inc @ inc.T).tocsr()
    for _ in range(rings - 1):
        reach = ((reach @ adj) > 0).astype(np.float64).tocsr()
    return ((reach @ inc) > 0).astype(np.float64).tocsr()


def sted(ref, rec, faces, *, rings: int = 1, fps: float = 30.0, c: float = 1.0, temporal: bool = True) -> dict:
    """Spatial-temporal edge difference (Vasa and Skala 2011) of ``rec`` against ``ref`` (both (N, V, 3)).

    Spatial part: per edge and frame the relative edge-length difference ed = (|e'| - |e|) / |e|; per vertex
    the standard deviation of ed over the edges of its topological neighbourhood (``rings = 1``: the edges
    incident to the vertex; 2: also those of its neighbours), weighted by the reference edge lengths;
    STED_s = the mean of that over vertices and frames. A uniform scaling or a rigid motion of a frame gives
    STED_s = 0 (the deviation removes any common relative change).
    Temporal part (needs N >= 2): every vertex has a temporal edge between consecutive frames, of length
    sqrt(|v^(f+1) - v^f|^2 + (c dt)^2) with dt = 1/fps (time scaled into space by ``c``); its relative length
    difference, squared and averaged over vertices and frame pairs, gives STED_t^2.
    STED = sqrt(STED_s^2 + STED_t^2). The seed-000 tables report the spatial part on test shapes that are
    not a sequence; use ``temporal=False`` for those.
    """
    ref, rec = _check_pair(ref, rec)
    if rings < 1:
        raise ValueError("rings must be at least 1.")
    edges = unique_edges(faces)
    n, v = ref.shape[:2]
    if edges.max() >= v:
        raise ValueError("faces index vertices the shapes do not have.")
    ln = np.linalg.norm(ref[:, edges[:, 0]] - ref[:, edges[:, 1]], axis=-1)  # (N, E)
    ln2 = np.linalg.norm(rec[:, edges[:, 0]] - rec[:, edges[:, 1]], axis=-1)
    if np.any(ln <= 0):
        raise ValueError("the reference has zero-length edges; relative edge differences are undefined.")
    ed = (ln2 - ln) / ln
    hood = _neighbourhood_edges(edges, v, rings).tocoo()  # (V, E) membership
    rows, cols = hood.row, hood.col
    pick = sp.csr_matrix((np.ones(rows.size), (rows, np.arange(rows.size))), shape=(v, rows.size))
    w = ln[:, cols]  # (N, nnz): weights of the (vertex, edge) pairs
    wsum = pick @ w.T  # (V, N)
    mean = (pick @ (w * ed[:, cols]).T) / wsum
    # two-pass deviation (no cancellation: a uniform scaling gives exactly 0)
    dev = ed[:, cols] - mean.T[:, rows]
    std = np.sqrt((pick @ (w * dev**2).T) / wsum)
    sted_s = float(std.mean())
    out = {"sted_s": sted_s, "rings": rings}
    if temporal and n >= 2:
        dt2 = (c / fps) ** 2
        lt = np.sqrt(np.sum((ref[1:] - ref[:-1]) ** 2, axis=-1) + dt2)
        lt2 = np.sqrt(np.sum((rec[1:] - rec[:-1]) ** 2, axis=-1) + dt2)
        sted_t = float(np.sqrt(np.mean(((lt2 - lt) / lt) ** 2)))
        out |= {"sted_t": sted_t, "sted": float(np.hypot(sted_s, sted_t)), "fps": fps, "c": c}
    else:
        out["sted"] = sted_s
    return out


def hausdorff(a, b) -> float:
    """Symmetric Hausdorff distance between the vertex sets of two shapes (V, 3) and (W, 3)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max()))
