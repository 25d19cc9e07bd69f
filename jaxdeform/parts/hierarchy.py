"""Hierarchical fitting of rotation-constrained MFAs (seed 003, Algorithm 1), labels, latent images, runs.

Algorithm 1, as implemented here (shapes first scaled into the unit box, as in the paper):

1. coarse: AECM with ``initial_parts`` factor analyzers, started from k-means of the vertex trajectories;
2. refine: every coarse part is split on its own (AECM restricted to its vertices with 2, 3, ... analyzers)
   while its *average variance* (mean squared distance, per vertex and shape, between the real positions and
   the images of the vertices' latent points, eq. 22) is above ``threshold`` and still falls (a candidate
   split whose AECM does not converge within REFINE_MAX_ITER iterations is rejected);
3. the refined labels are split into connected regions of the mesh (a rigid part is one region; islands of
   fewer than ``min_part_vertices`` vertices join the neighbouring part they share most edges with);
4. final: AECM with all refined parts, started from those labels; labels by maximum responsibility
   (eq. 20); parts left without vertices are dropped.

Everything returned is in data units (:func:`to_data_units` undoes the normalisation of the parameters).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from jaxdeform.errors import DegenerateMeshError
from jaxdeform.mesh.topology import unique_edges, validate_faces
from jaxdeform.parts import mfa
from jaxdeform.parts.mfa import MFA

#: Average variance (unit-box units squared) below which a part is not split further: an RMS residual of
#: about 0.5% of the box. Calibrated on horse-poses (the paper's threshold value was lost in extraction).
THRESHOLD = 2.5e-5
MAX_SPLIT = 6
#: A candidate split whose AECM has not converged after this many iterations is rejected (its analyzers
#: compete for one motion and can run for a hundred iterations without settling).
REFINE_MAX_ITER = 20
MIN_PART_VERTICES = 20
INITIAL_PARTS = 8


@dataclasses.dataclass
class PartsFit:
    """A fitted hierarchy: parameters, labels, latent images and reconstruction, all in data units."""

    params: MFA
    labels: np.ndarray  # (V,) in [0, K)
    latent: np.ndarray  # (V, 3): D_k E[x | y_i, k] of each vertex in its part (eq. 21)
    reconstruction: np.ndarray  # (M, V, 3): R_k^m z_i + t_k^m (eq. 22)
    stages: list[dict]
    seconds: float
    disconnected_parts: list[int]  # parts that are not one connected region of the mesh

    @property
    def n_parts(self) -> int:
        return int(self.params.n_parts)


# ------------------------------------------------------------------------------------------- helpers


def check_shapes(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """Shapes and faces of a parts fit, checked.

    **Arguments:**

    - ``vertices``: shapes ``(M, V, 3)``, ``M >= 2``.
    - ``faces``: triangles ``(F, 3)`` over the ``V`` vertices.

    **Returns:**

    ``(vertices, faces)``: the shapes as float64 and the validated faces.

    **Raises:**

    ``ValueError`` if ``vertices`` is not ``(M, V, 3)`` or ``M < 2``; ``DegenerateMeshError`` if a coordinate is NaN or
    infinite; the errors of :func:`~jaxdeform.mesh.topology.validate_faces` for bad faces.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices must be (M, V, 3), got {vertices.shape}.")
    if vertices.shape[0] < 2:
        raise ValueError(f"a parts fit needs at least 2 shapes, got {vertices.shape[0]}.")
    if not np.all(np.isfinite(vertices)):
        raise DegenerateMeshError("a vertex coordinate is NaN or infinite.")
    faces, _ = validate_faces(faces, vertices.shape[1])
    return vertices, faces


def normalize(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Shapes in the unit box, as the fit works on them.

    **Arguments:**

    - ``vertices``: shapes ``(M, V, 3)``.

    **Returns:**

    ``(y (V, M, 3) in the unit box, offset (3,), scale)``: data = y * scale + offset.

    **Raises:**

    ``DegenerateMeshError`` if all shapes collapse to a single point.
    """
    lo = vertices.min(axis=(0, 1))
    scale = float((vertices.max(axis=(0, 1)) - lo).max())
    if scale <= 0:
        raise DegenerateMeshError("all shapes collapse to a single point.")
    return ((vertices - lo) / scale).transpose(1, 0, 2), lo, scale


def to_data_units(p: MFA, offset: np.ndarray, scale: float) -> MFA:
    """Parameters of the same mixture for data = y * scale + offset.

    **Arguments:**

    - ``p``: parameters fitted to normalised shapes.
    - ``offset``, ``scale``: :func:`normalize`'s.

    **Returns:**

    The :class:`MFA` in data units.
    """
    return MFA(
        log_pi=p.log_pi, mu=p.mu * scale + jnp.asarray(offset), rot=p.rot, d=p.d * scale, sigma2=p.sigma2 * scale**2
    )


def components_of_labels(labels: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Connected-component id of every vertex in the graph of edges whose ends share a label.

    **Arguments:**

    - ``labels``: ``(V,)``.
    - ``edges``: the mesh's edges ``(E, 2)``.

    **Returns:**

    ``(V,)`` component ids.
    """
    n = labels.shape[0]
    same = labels[edges[:, 0]] == labels[edges[:, 1]]
    e = edges[same]
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return csgraph.connected_components(adj, directed=False)[1]


def split_regions(labels: np.ndarray, edges: np.ndarray, min_size: int) -> np.ndarray:
    """Relabel so that every part is one connected region.

    Islands smaller than ``min_size`` join the neighbouring region they share most edges with.

    **Arguments:**

    - ``labels``: ``(V,)``.
    - ``edges``: the mesh's edges ``(E, 2)``.
    - ``min_size``: the fewest vertices of a region that stays on its own.

    **Returns:**

    Labels ``(V,)`` renumbered 0..K-1.
    """
    labels = labels.copy()
    for _ in range(10):  # merging can create new small regions only rarely; a few passes settle it
        comp = components_of_labels(labels, edges)
        sizes = np.bincount(comp)
        small = sizes < min_size
        if not small[comp].any() or small.all():
            break
        # for each small component, the label across its boundary edges that is most frequent
        a, b = comp[edges[:, 0]], comp[edges[:, 1]]
        cross = a != b
        src = np.r_[a[cross], b[cross]]
        dst_lab = np.r_[labels[edges[cross, 1]], labels[edges[cross, 0]]]
        keep = small[src] & ~small[np.r_[b[cross], a[cross]]]
        if not keep.any():
            break
        votes = sp.coo_matrix(
            (np.ones(keep.sum()), (src[keep], dst_lab[keep])), shape=(len(sizes), labels.max() + 1)
        ).toarray()
        has = votes.sum(axis=1) > 0
        target = np.argmax(votes, axis=1)
        move = small[comp] & has[comp]
        labels[move] = target[comp[move]]
    comp = components_of_labels(labels, edges)
    return np.unique(comp, return_inverse=True)[1]


def average_variance(y, p: MFA, labels: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean over (masked) vertices and shapes of |y_im - (R_k^m z_i + t_k^m)|^2 with k = labels[i].

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``p``: the mixture's parameters.
    - ``labels``: ``(V,)`` parts.
    - ``mask``: ``(V,)`` bool, the vertices to average over (default None: all).

    **Returns:**

    The mean as a float.
    """
    lab = jnp.asarray(labels)
    rec = mfa.reconstruct(p, lab, mfa.latent_images(y, p, lab))  # (M, V, 3)
    err = np.sum((np.asarray(rec) - np.asarray(y).transpose(1, 0, 2)) ** 2, axis=-1)  # (M, V)
    return float(err[:, mask].mean() if mask is not None else err.mean())


def fit_from_labels(y, labels: np.ndarray, k: int, w=None, max_iter: int = mfa.MAX_ITER):
    """AECM started from hard labels.

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``labels``: ``(V,)`` in [-1, k) (-1: outside the fit).
    - ``k``: the number of parts.
    - ``w``: per-vertex weights ``(V,)`` (default None: ones).
    - ``max_iter``: the AECM's iteration cap.

    **Returns:**

    ``(params, history, iters)``: the fitted :class:`MFA`, the log-likelihood per iteration and the number of
    iterations.
    """
    w = jnp.ones(y.shape[0], y.dtype) if w is None else jnp.asarray(w, y.dtype)
    p0 = mfa.init_from_weights(y, jnp.asarray(mfa.one_hot(labels, k)))
    p, hist, it = mfa.aecm(y, w, p0, max_iter=max_iter)
    hist = np.asarray(hist)
    return p, hist[~np.isnan(hist)], int(it)


def _labels_masked(y, p: MFA, mask: np.ndarray) -> np.ndarray:
    lab = mfa.labels_of(y, p)
    return np.where(mask, lab, -1)


# ------------------------------------------------------------------------------------------ Algorithm 1


def _refine_parts(y, y_np, p: MFA, coarse, k0: int, threshold, max_split, min_part_vertices, seed):
    """Step 2 of Algorithm 1: split every coarse part on its own into 2..``max_split`` parts while that lowers
    its average variance (and it is above ``threshold``, the part large enough and the AECM converged).

    Takes the normalised shapes (``y`` on device, ``y_np`` on host), the coarse fit ``p`` and its labels
    ``coarse`` over ``k0`` parts. Returns ``(refined, n_parts, refine_log)``: labels (-1 for vertices of no
    part), consecutive per coarse part; their count; one log record per non-empty coarse part.
    """
    n = y.shape[0]
    refined = np.full(n, -1, np.int64)
    next_label = 0
    refine_log = []
    for k in range(k0):
        mask = coarse == k
        if not mask.any():
            continue
        sub = np.zeros(n, np.int64)
        var = average_variance(y, p, coarse, mask)
        splits, iters = 1, []
        for m in range(2, max_split + 1):
            if var <= threshold or mask.sum() < m * min_part_vertices:
                break
            init = mfa.kmeans_labels(y_np, m, w=mask, seed=seed + k)
            q, _, q_it = fit_from_labels(y, init, m, w=mask, max_iter=REFINE_MAX_ITER + 1)
            q_lab = _labels_masked(y, q, mask)
            q_var = average_variance(y, q, np.maximum(q_lab, 0), mask)
            iters.append(q_it)
            if q_var >= var or q_it > REFINE_MAX_ITER:  # the variance ceased to decrease, or no convergence
                break
            sub, var, splits = q_lab, q_var, m
        refined[mask] = next_label + sub[mask]
        next_label += splits
        refine_log.append({"part": k, "split_into": splits, "average_variance": var, "iterations": iters})
    return refined, next_label, refine_log


def fit(
    vertices,
    faces,
    *,
    initial_parts: int = INITIAL_PARTS,
    threshold: float = THRESHOLD,
    max_split: int = MAX_SPLIT,
    min_part_vertices: int = MIN_PART_VERTICES,
    seed: int = 0,
    log: Callable[[str], None] = lambda s: None,
) -> PartsFit:
    """Fit the hierarchy of Algorithm 1 to shapes sharing ``faces``; see the module docstring.

    **Arguments:** ``vertices`` ``(M, V, 3)``, ``M >= 2``; ``faces`` ``(F, 3)``; ``initial_parts`` (>= 1),
    ``threshold``, ``max_split``, ``min_part_vertices``, ``seed``: Algorithm 1's parameters; ``log``: one line a stage.

    **Returns:** a :class:`PartsFit` in data units; parts that lost all their vertices are dropped (relabelled).

    **Raises:** ``ValueError`` (``initial_parts < 1``, :func:`check_shapes`); ``DegenerateMeshError``.
    """
    t0 = time.perf_counter()
    vertices, faces = check_shapes(vertices, faces)
    if initial_parts < 1:
        raise ValueError("initial_parts must be at least 1.")
    y_np, offset, scale = normalize(vertices)
    y = jnp.asarray(y_np)
    n = y.shape[0]
    edges = unique_edges(faces)
    stages: list[dict] = []

    # 1. coarse
    k0 = min(initial_parts, n)
    lab = mfa.kmeans_labels(y_np, k0, seed=seed)
    p, hist, it = fit_from_labels(y, lab, k0)
    coarse = mfa.labels_of(y, p)
    stages.append({"stage": "coarse", "parts": k0, "iterations": it, "loglik": hist.tolist()})
    log(f"coarse: {k0} parts, {it} AECM iterations, average variance {average_variance(y, p, coarse):.3e}")

    # 2. refine every coarse part on its own
    refined, next_label, refine_log = _refine_parts(
        y, y_np, p, coarse, k0, threshold, max_split, min_part_vertices, seed
    )
    accepted = [r["iterations"][r["split_into"] - 2] for r in refine_log if r["split_into"] > 1]
    stages.append(
        {"stage": "refine", "parts": int(next_label), "iterations": max(accepted, default=0), "per_part": refine_log}
    )
    log(f"refine: {next_label} parts (splits {[r['split_into'] for r in refine_log]})")

    # 3. one connected region per part
    regions = split_regions(refined, edges, min_part_vertices)
    k1 = int(regions.max()) + 1

    # 4. final AECM from the refined labels
    p, hist, it = fit_from_labels(y, regions, k1)
    labels = mfa.labels_of(y, p)
    used = np.unique(labels)
    if used.size < k1:  # drop parts that lost all their vertices
        log_pi = p.log_pi[used] - jax.scipy.special.logsumexp(p.log_pi[used])  # weights sum to 1 again
        p = MFA(log_pi=log_pi, mu=p.mu[used], rot=p.rot[used], d=p.d[used], sigma2=p.sigma2[used])
        labels = np.searchsorted(used, labels)
    stages.append({"stage": "final", "parts": int(used.size), "iterations": it, "loglik": hist.tolist()})
    log(f"final: {used.size} parts, {it} AECM iterations")

    p_data = to_data_units(p, offset, scale)
    y_data = jnp.asarray(vertices.transpose(1, 0, 2))
    lab_j = jnp.asarray(labels)
    latent = mfa.latent_images(y_data, p_data, lab_j)
    rec = np.asarray(mfa.reconstruct(p_data, lab_j, latent))
    comp = components_of_labels(labels, edges)
    n_regions = np.array([np.unique(comp[labels == k]).size for k in range(used.size)])
    return PartsFit(
        params=p_data,
        labels=labels,
        latent=np.asarray(latent),
        reconstruction=rec,
        stages=stages,
        seconds=time.perf_counter() - t0,
        disconnected_parts=np.flatnonzero(n_regions > 1).tolist(),
    )


def rmse(vertices: np.ndarray, reconstruction: np.ndarray) -> float:
    """Root mean square per-vertex distance over all shapes and vertices (data units).

    **Arguments:**

    - ``vertices``: shapes ``(M, V, 3)``.
    - ``reconstruction``: their reconstruction ``(M, V, 3)``.

    **Returns:**

    The RMS distance as a float.
    """
    return float(np.sqrt(np.mean(np.sum((np.asarray(vertices) - np.asarray(reconstruction)) ** 2, axis=-1))))


def bbox_diagonal(vertices: np.ndarray) -> float:
    """The bounding-box diagonal of the first shape.

    **Arguments:**

    - ``vertices``: shapes ``(M, V, 3)``.

    **Returns:**

    Its length as a float.
    """
    v = np.asarray(vertices)[0]
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))


# ------------------------------------------------------------------------------------------------ runs


def summary(fit_: PartsFit, vertices: np.ndarray) -> dict:
    """The summary record of a fit.

    **Arguments:**

    - ``fit_``: the fit.
    - ``vertices``: the shapes it was fitted to ``(M, V, 3)``.

    **Returns:**

    A dict: parts, iterations and parts per stage, rmse (also over the first shape's bounding-box diagonal),
    seconds, shapes, vertices, disconnected parts, the range of the rotations' determinants, and whether every
    stage's log-likelihood is monotone.
    """
    err = rmse(vertices, fit_.reconstruction)
    dets = np.linalg.det(np.asarray(fit_.params.rot))
    return {
        "parts": fit_.n_parts,
        "iterations": {s["stage"]: s["iterations"] for s in fit_.stages},
        "parts_per_stage": {s["stage"]: s["parts"] for s in fit_.stages},
        "rmse": err,
        "rmse_over_diagonal": err / bbox_diagonal(vertices),
        "seconds": round(fit_.seconds, 3),
        "shapes": int(np.asarray(vertices).shape[0]),
        "vertices": int(np.asarray(vertices).shape[1]),
        "disconnected_parts": fit_.disconnected_parts,
        "rotation_det_range": [float(dets.min()), float(dets.max())],
        "loglik_monotone": all(
            bool(np.all(np.diff(s["loglik"]) >= -1e-9 * np.abs(s["loglik"][-1]))) for s in fit_.stages if "loglik" in s
        ),
    }
