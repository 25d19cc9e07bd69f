"""Reconstruction of vertex positions from per-vertex deformation gradients (features -> positions).

Least squares (Gao et al. 2019; seed 002 Sec. 3.2): with T_i the gradients, q the reference and w the
same positive edge weights as the encoder,

    min_p  sum_(i,j in E) w_ij |(p_i - p_j) - (T_i + T_j)/2 (q_i - q_j)|^2  +  a sum_(k in anchors) |p_k - t_k|^2

solved by ``optimistix.least_squares`` with Gauss-Newton. The residual is linear in p, so J^T J is the
weighted graph Laplacian plus ``a`` on the anchors' diagonal: a fixed sparse matrix, factored once per
(reference, connectivity, anchors) with cholespy, and used through a lineax solver
(:class:`PrefactoredCholesky`) both for the Gauss-Newton step and, via ``optimistix.ImplicitAdjoint``, for
the backward pass. Gradients with respect to T, the reference-side constants and the anchor targets are
therefore exact (implicit differentiation), and cost one more solve.

Translation is free without anchors, so at least one anchor is always used: by default vertex 0 held at its
reference position. The anchor weight ``a`` is ANCHOR_WEIGHT times the mean edge weight: large enough that
anchors act as near-hard constraints, small enough to keep the float64 factor well conditioned.

The factor lives on the host (cholespy); jitted code reaches it through ``jax.pure_callback`` and a
registry key, so a compiled decoder never retraces for new features.
"""

from __future__ import annotations

import atexit
import itertools
import threading
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from jaxdeform.errors import DegenerateMeshError
from jaxdeform.mesh.topology import Topology

ANCHOR_WEIGHT = 1e3

_FACTORS: dict[int, Any] = {}
_FACTOR_SIZES: dict[int, int] = {}
_KEYS = itertools.count()
_LOCK = threading.Lock()


@atexit.register
def _release_factors() -> None:
    """Free the host factors before interpreter teardown (nanobind objects must die first)."""
    _FACTORS.clear()


def register_factor(n: int, rows: np.ndarray, cols: np.ndarray, vals: np.ndarray) -> int:
    """Factor the SPD matrix given in COO form with cholespy (float64); return its registry key."""
    from cholespy import CholeskySolverD, MatrixType

    vals = np.asarray(vals, dtype=np.float64)
    if not np.all(np.isfinite(vals)):
        raise DegenerateMeshError("the reconstruction matrix has non-finite entries (degenerate reference mesh).")
    solver = CholeskySolverD(n, np.ascontiguousarray(rows, np.int32), np.ascontiguousarray(cols, np.int32), vals, MatrixType.COO)
    with _LOCK:
        key = next(_KEYS)
        _FACTORS[key] = solver
        _FACTOR_SIZES[key] = n
    return key


def solve_factor(key: int, b: np.ndarray) -> np.ndarray:
    """Host solve with a registered factor; ``b`` is (n,) or (n, k)."""
    b64 = np.ascontiguousarray(b, dtype=np.float64)
    x = np.empty_like(b64)
    _FACTORS[key].solve(b64, x)
    return x


def _callback_solve(key: int, rhs: Array) -> Array:
    """Solve M x = rhs for rhs of shape (..., n, 3) through the host factor (any batch shape)."""
    n = _FACTOR_SIZES[key]

    def host(b):
        b = np.asarray(b)
        lead = b.shape[:-2]
        cols = np.moveaxis(b.reshape(-1, n, b.shape[-1]), 1, 0).reshape(n, -1)
        x = solve_factor(key, cols)
        out = np.moveaxis(x.reshape(n, -1, b.shape[-1]), 0, 1).reshape(*lead, n, b.shape[-1])
        return out.astype(b.dtype)

    return jax.pure_callback(host, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), rhs, vmap_method="broadcast_all")


class PrefactoredCholesky(lx.AbstractLinearSolver):
    """A lineax solver for operators whose normal matrix is a fixed, prefactored sparse SPD matrix M.

    For a square (self-adjoint) operator A = M it returns M^-1 v; for a rectangular operator J with
    J^T J = M (a Gauss-Newton Jacobian) it returns the least-squares solution M^-1 J^T v. The operator is
    only used for J^T v; M itself is never built in JAX.
    """

    key: int = eqx.field(static=True)

    def init(self, operator, options):
        del options
        return operator

    def compute(self, state, vector, options):
        del options
        operator = state
        if operator.in_size() != operator.out_size():
            vector = operator.transpose().mv(vector)
        leaves, treedef = jax.tree_util.tree_flatten(vector)
        sol = [_callback_solve(self.key, leaf) for leaf in leaves]
        return jax.tree_util.tree_unflatten(treedef, sol), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        return state.transpose(), options

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True


def _residuals(y, args):
    t, targets, rest_edges, sqrt_w, i, j, anchors, sqrt_a = args
    # (T_i + T_j)/2 (q_i - q_j) per edge and frame.
    guide = 0.5 * jnp.einsum("...eab,eb->...ea", t[..., i, :, :] + t[..., j, :, :], rest_edges)
    r_edge = sqrt_w[:, None] * ((y[..., i, :] - y[..., j, :]) - guide)
    r_anchor = sqrt_a * (y[..., anchors, :] - targets)
    return r_edge, r_anchor


class Reconstructor(eqx.Module):
    """Positions from deformation gradients for one (reference, connectivity, anchors); build once, call many.

    ``__call__(t (..., V, 3, 3), targets (..., A, 3) | None) -> positions (..., V, 3)``, jit-able and
    differentiable in ``t`` and ``targets``.
    """

    rest: Float[Array, "v 3"]
    rest_edges: Float[Array, "e 3"]
    sqrt_w: Float[Array, " e"]
    edge_i: Array
    edge_j: Array
    anchors: Array
    sqrt_a: Array
    key: int = eqx.field(static=True)
    rtol: float = eqx.field(static=True, default=1e-6)

    @staticmethod
    def build(rest, topo: Topology, weights, anchors=None, anchor_weight: float = ANCHOR_WEIGHT) -> "Reconstructor":
        rest = jnp.asarray(rest)
        weights = jnp.asarray(weights, dtype=rest.dtype)
        if not bool(jnp.all(weights > 0)):
            raise DegenerateMeshError(
                "reconstruction needs positive edge weights; use weighting='official' for this mesh."
            )
        n = topo.n_vertices
        anchors = np.atleast_1d(np.asarray([0] if anchors is None else anchors, dtype=np.int64))
        if anchors.size == 0 or anchors.min() < 0 or anchors.max() >= n:
            raise ValueError(f"anchor indices must lie in [0, {n}).")
        if np.unique(anchors).size != anchors.size:
            raise ValueError("anchor indices must be distinct.")
        a = float(anchor_weight * np.mean(np.asarray(weights)))
        e = np.asarray(topo.edges)
        w = np.asarray(weights, dtype=np.float64)
        rows = np.r_[e[:, 0], e[:, 1], e[:, 0], e[:, 1], anchors]
        cols = np.r_[e[:, 1], e[:, 0], e[:, 0], e[:, 1], anchors]
        vals = np.r_[-w, -w, w, w, np.full(anchors.size, a)]
        key = register_factor(n, rows, cols, vals)
        return Reconstructor(
            rest=rest,
            rest_edges=rest[topo.edges[:, 0]] - rest[topo.edges[:, 1]],
            sqrt_w=jnp.sqrt(weights),
            edge_i=topo.edges[:, 0],
            edge_j=topo.edges[:, 1],
            anchors=jnp.asarray(anchors, dtype=jnp.int32),
            sqrt_a=jnp.asarray(np.sqrt(a), dtype=rest.dtype),
            key=key,
        )

    def __call__(self, t: Float[Array, "... v 3 3"], targets: Float[Array, "... a 3"] | None = None):
        dtype = t.dtype
        if targets is None:
            targets = self.rest[self.anchors].astype(dtype)
        targets = jnp.broadcast_to(targets, (*t.shape[:-3], self.anchors.shape[0], 3)).astype(dtype)
        y0 = jnp.broadcast_to(self.rest.astype(dtype), (*t.shape[:-3], *self.rest.shape))
        args = (t, targets, self.rest_edges.astype(dtype), self.sqrt_w.astype(dtype), self.edge_i, self.edge_j,
                self.anchors, self.sqrt_a.astype(dtype))
        linsolve = PrefactoredCholesky(self.key)
        tol = self.rtol if dtype == jnp.float64 else 1e-4
        sol = optx.least_squares(
            _residuals,
            optx.GaussNewton(rtol=tol, atol=tol, linear_solver=linsolve),
            y0,
            args,
            max_steps=8,
            adjoint=optx.ImplicitAdjoint(linear_solver=linsolve),
            throw=False,
        )
        return sol.value
