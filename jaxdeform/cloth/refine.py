"""Collision refinement of synthesised cloth frames (seed 002, Sec. 3.3, Fig. 6; after Wang et al. 2019).

The network never sees the obstacles, so a synthesised fine frame may dip into them. For a frame with
positions ``P0`` (V, 3) and the obstacles' signed distance ``d(x)`` with outward normal ``n(x)``:

1. every penetrating vertex (``d(p_i) < 0``) gets a target on the outside, ``t_i = p_i + (margin - d(p_i))
   n(p_i)`` (the closest surface point pushed out by the margin, the simulation's cloth thickness); vertices
   resting within the margin but outside (cloth lying on a table) are left alone;
2. the frame is deformed to meet the targets while keeping its Laplacian detail, by the sparse least squares

       min_P  ||L (P - P0)||^2 + w sum_(i in C) ||p_i - t_i||^2 + eps ||P - P0||^2

   with ``L`` the uniform graph Laplacian of the connectivity (``(L p)_i = sum_j (p_i - p_j)``), ``C`` the
   constrained vertices of this and all earlier iterations (their targets kept), ``w = 100`` and ``eps =
   0.1`` (the Euclidean term of Wang et al.: keeps the push local; the diagonal of L^T L is ~ deg^2 + deg ~ 40). The normal matrix
   ``L^T L + w I_C + eps I`` is solved on the region the push can reach: the constrained vertices and those
   within ``rings`` (6) + 2 edges of them; every other vertex keeps its position exactly (a sparse solve of a
   few hundred to a few thousand unknowns per iteration, much cheaper than factorising the whole mesh in
   every iteration).
3. repeat from 1 on the result, at most ``iterations`` (3, the paper: "usually takes less than 3
   iterations") or until no vertex is inside.

By default (``exact=True``) the targets are met exactly: the constrained vertices are moved onto them and
eliminated (the limit w -> infinity), and the same normal matrix without the w term is solved for the others.
With the soft penalty (``exact=False``, the paper's form) the Laplacian term holds the deepest vertices back: on
synthesised SKIRT frames whose hem the model put 6.8 cm inside a thigh, 3-20 iterations leave vertices 1.1-1.3 cm
inside, where the exact form leaves none after 2.

Frames without collisions are returned unchanged, bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from jaxdeform.mesh.topology import unique_edges

SDF = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class RefineStats:
    iterations: int  # solves performed
    collided: int  # vertices constrained in total
    max_depth_before: float  # penetration depth max(-d, 0) over vertices, before
    max_depth_after: float


def uniform_laplacian(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """Graph Laplacian D - A of the edges of ``faces`` (positive semidefinite)."""
    e = unique_edges(np.asarray(faces, np.int64))
    a = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(a.sum(axis=1)).ravel()) - a).tocsr()


def _spd_solve(a: sp.csc_matrix, rhs: np.ndarray) -> np.ndarray:
    """Solve a sparse symmetric positive definite system: a symmetric fill-reducing order (minimum degree on
    A + A^T) with diagonal pivots, 1.6x faster on the DISK's contact regions than spsolve's default (COLAMD)."""
    from scipy.sparse.linalg import splu

    return splu(a, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True}).solve(rhs)


class Refiner:
    """Collision refinement for one connectivity (the Laplacian and its square are built once)."""

    def __init__(
        self,
        faces: np.ndarray,
        n_vertices: int,
        *,
        weight: float = 100.0,
        eps: float = 0.1,
        iterations: int = 3,
        rings: int = 6,
        exact: bool = True,
    ):
        if iterations < 1:
            raise ValueError("iterations must be at least 1.")
        if rings < 1:
            raise ValueError("rings must be at least 1.")
        self.n = int(n_vertices)
        lap = uniform_laplacian(faces, self.n)
        self.ltl = (lap.T @ lap).tocsr()
        adj = (lap != 0).astype(np.int8).tocsr()  # vertex and its one-ring
        self.adj = adj
        self.rings = int(rings)
        self.weight, self.eps, self.iterations = float(weight), float(eps), int(iterations)
        self.exact = bool(exact)

    def region(self, mask: np.ndarray) -> np.ndarray:
        """The vertices within ``rings`` + 2 edges of the masked ones (the solve's unknowns)."""
        grow = mask.astype(np.int8)
        for _ in range(self.rings + 2):  # + 2: L^T L couples vertices two edges apart
            grow = (self.adj @ grow > 0).astype(np.int8)
        return np.flatnonzero(grow)

    def _solve(self, p0: np.ndarray, mask: np.ndarray, targets: np.ndarray) -> np.ndarray:
        r = self.region(mask)
        m = mask[r]
        out = p0.copy()
        # unknown: displacement D = P - P0 on the region (0 outside)
        if self.exact:  # D = t - p0 on C; the rest solves (L^T L + eps I)_ff D_f = -(L^T L)_fc D_c
            free, held = r[~m], r[m]
            d_held = targets[held] - p0[held]
            out[held] += d_held
            if free.size:
                a = (self.ltl[free][:, free] + sp.diags(np.full(free.size, self.eps))).tocsc()
                out[free] += _spd_solve(a, -(self.ltl[free][:, held] @ d_held))
            return out
        a = (self.ltl[r][:, r] + sp.diags(self.eps + self.weight * m.astype(np.float64))).tocsc()
        rhs = np.zeros((r.size, 3))  # w (t - p0) on C, 0 elsewhere
        rhs[m] = self.weight * (targets[r][m] - p0[r][m])
        out[r] += _spd_solve(a, rhs)
        return out

    def __call__(self, p0: np.ndarray, sdf: SDF, margin: float) -> tuple[np.ndarray, RefineStats]:
        p0 = np.asarray(p0, np.float64)
        if p0.shape != (self.n, 3):
            raise ValueError(f"expected positions of shape ({self.n}, 3), got {p0.shape}.")
        d, nrm = (np.asarray(a, np.float64) for a in sdf(p0))
        depth0 = float(np.maximum(-d, 0.0).max())
        if depth0 <= 0.0:
            return p0, RefineStats(0, 0, 0.0, 0.0)
        mask = np.zeros(self.n, bool)
        targets = np.zeros((self.n, 3))
        p = p0
        its = 0
        for its in range(1, self.iterations + 1):  # noqa: B007  (read after the loop)
            hit = d < 0.0
            targets[hit] = p[hit] + (margin - d[hit])[:, None] * nrm[hit]
            mask |= hit
            p = self._solve(p0, mask, targets)
            d, nrm = (np.asarray(a, np.float64) for a in sdf(p))
            if not np.any(d < 0.0):
                break
        return p, RefineStats(its, int(mask.sum()), depth0, float(np.maximum(-d, 0.0).max()))
