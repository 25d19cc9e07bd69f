"""Reconstruction of vertex positions from per-vertex deformation gradients (features -> positions).

Least squares (Gao et al. 2019; seed 002 Sec. 3.2): with T_i the gradients, q the reference and w the
same positive edge weights as the encoder,

    min_p  sum_(i,j in E) w_ij |(p_i - p_j) - (T_i + T_j)/2 (q_i - q_j)|^2  +  a sum_(k in anchors) |p_k - t_k|^2

solved by ``optimistix.least_squares`` (:class:`LinearLeastSquares`: the residual is affine in p, so one
Gauss-Newton step from any start is exact). J^T J is the normal matrix M = weighted graph Laplacian plus ``a``
on the anchors' diagonal. Three interchangeable solvers for M x = b, all behind one lineax solver
(:class:`NormalSolver`) that serves the Gauss-Newton step and, through ``optimistix.ImplicitAdjoint``, the
derivatives (forward and reverse mode):

- ``"host"`` (:class:`HostCholesky`): a sparse Cholesky factor of M on the host (cholespy, float64), reached
  through ``jax.pure_callback``;
- ``"dense"`` (:class:`DenseCholesky`): a dense XLA Cholesky factor of M built once (meshes up to about 20k
  vertices), solved on the device for all frames at once;
- ``"cg"`` (:class:`ConjugateGradient`): matrix-free Jacobi-preconditioned conjugate gradients with the
  edge-list product of M, batched over frames, any mesh size, started from the least squares' initial guess.

Derivatives are implicit (one more solve of the same system), hence exact with respect to the gradients T,
the anchor targets and the reference-side constants (edge vectors, weights, anchor weight): see
:meth:`Reconstructor.with_rest` for derivatives with respect to the reference positions.

Translation is free without anchors, so at least one anchor per connected component is always used: by default
the lowest vertex of each component (vertex 0 for a connected mesh) held at its
reference position. The anchor weight ``a`` is ANCHOR_WEIGHT times the mean edge weight: large enough that
anchors act as near-hard constraints, small enough to keep the factor well conditioned.
"""

from __future__ import annotations

import atexit
import itertools
import threading
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from jaxdeform.errors import DegenerateMeshError
from jaxdeform.mesh.topology import Topology
from jaxdeform.typing import Int

ANCHOR_WEIGHT = 1e3
#: largest mesh for which ``solver=None`` picks the dense factor on an accelerator
DENSE_MAX_VERTICES = 20_000
#: conjugate gradients: default relative residual tolerance per dtype, and default step limit
CG_RTOL = {np.dtype(np.float32): 1e-6, np.dtype(np.float64): 1e-12}
CG_MAX_STEPS = 20_000

Solver = Literal["host", "dense", "cg"]
SOLVERS = ("host", "dense", "cg")

# --------------------------------------------------------------------------------------------------
# host factors (cholespy), reached by a static integer key
# --------------------------------------------------------------------------------------------------

_FACTORS: dict[int, Any] = {}
_FACTOR_SIZES: dict[int, int] = {}
_KEYS = itertools.count()
_LOCK = threading.Lock()


_RELEASED = threading.Event()


@atexit.register
def _release_factors() -> None:
    """Free the host factors before interpreter teardown (nanobind objects must die first), after the
    computations still running (unread results of asynchronous dispatch, whose host solves need the factors)
    have finished. A solve that still comes afterwards gets NaN instead of a crash."""
    try:
        jax.block_until_ready(jax.live_arrays())
    except Exception:  # noqa: BLE001  (teardown: a failed computation has nobody left to report to)
        pass
    _RELEASED.set()
    _FACTORS.clear()


def register_factor(n: int, rows: np.ndarray, cols: np.ndarray, vals: np.ndarray) -> int:
    """Factor an SPD matrix given in COO form with cholespy (float64) and register the factor.

    **Arguments:**

    - `n`: the matrix size.
    - `rows`, `cols`: COO indices (both triangles).
    - `vals`: COO values.

    **Returns:**

    The factor's registry key (for :func:`solve_factor`).

    **Raises:**

    `DegenerateMeshError` for a non-finite value.
    """
    from cholespy import CholeskySolverD, MatrixType

    vals = np.asarray(vals, dtype=np.float64)
    if not np.all(np.isfinite(vals)):
        raise DegenerateMeshError("the reconstruction matrix has non-finite entries (degenerate reference mesh).")
    solver = CholeskySolverD(
        n, np.ascontiguousarray(rows, np.int32), np.ascontiguousarray(cols, np.int32), vals, MatrixType.COO
    )
    with _LOCK:
        key = next(_KEYS)
        _FACTORS[key] = solver
        _FACTOR_SIZES[key] = n
    return key


def solve_factor(key: int, b: np.ndarray) -> np.ndarray:
    """Host solve with a registered factor.

    **Arguments:**

    - `key`: the key from :func:`register_factor`.
    - `b`: right-hand sides `(n,)` or `(n, k)`.

    **Returns:**

    x of b's shape, float64 (NaN after the factors are released at interpreter exit).

    **Raises:**

    `KeyError` for an unregistered key.
    """
    b64 = np.require(b, dtype=np.float64, requirements=["C", "W"])  # nanobind rejects read-only views
    x = np.empty_like(b64)
    factor = _FACTORS.get(key)
    if factor is None:
        if _RELEASED.is_set():  # interpreter teardown: nobody reads this result
            return np.full_like(b64, np.nan)
        raise KeyError(f"no host factor {key} is registered.")
    factor.solve(b64, x)
    return x


def _callback_solve(key: int, rhs: Array) -> Array:
    """Solve M x = rhs through the host factor; rhs is vertex-major (n, ...) with any trailing shape."""
    n = _FACTOR_SIZES[key]

    def host_any(b):
        b = np.asarray(b)
        if b.shape[0] == n:  # unbatched: (n, ...)
            return solve_factor(key, b.reshape(n, -1)).reshape(b.shape).astype(b.dtype)
        # vmapped: (B..., n, ...) with the batch dims in front
        lead = b.shape[: b.ndim - rhs.ndim]
        cols = np.moveaxis(b.reshape(-1, *rhs.shape), 0, -1).reshape(n, -1)
        x = solve_factor(key, cols).reshape(*rhs.shape, -1)
        return np.moveaxis(x, -1, 0).reshape(*lead, *rhs.shape).astype(b.dtype)

    return jax.pure_callback(host_any, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), rhs, vmap_method="broadcast_all")


# --------------------------------------------------------------------------------------------------
# the normal matrix, matrix-free
# --------------------------------------------------------------------------------------------------


def _scatter_edges(values, i, j, n):
    """sum over edges e of values_e at i_e minus at j_e: (E, ...) -> (n, ...) (two segment sums)."""
    return jax.ops.segment_sum(values, i, n, indices_are_sorted=True) - jax.ops.segment_sum(values, j, n)


class NormalMatrix(eqx.Module):
    """M = sum_e w_e (e_i - e_j)(e_i - e_j)^T + a sum_(k in anchors) e_k e_k^T, applied matrix-free.

    ``mv(x)`` takes vertex-major x (V, ...) and returns M x of the same shape, in x's dtype.
    """

    sqrt_w: Float[ArrayLike, " e"]
    edge_i: Int[ArrayLike, " e"]
    edge_j: Int[ArrayLike, " e"]
    anchors: Int[ArrayLike, " a"]
    sqrt_a: Float[ArrayLike, ""]
    n: int = eqx.field(static=True)

    def mv(self, x):
        """The product M x.

        **Arguments:**

        - `x`: vertex-major `(V, ...)`.

        **Returns:**

        M x of the same shape, in x's dtype.
        """
        dtype = x.dtype
        w = (self.sqrt_w.astype(dtype) ** 2).reshape((-1,) + (1,) * (x.ndim - 1))
        out = _scatter_edges(w * (x[self.edge_i] - x[self.edge_j]), self.edge_i, self.edge_j, self.n)
        return out.at[self.anchors].add(self.sqrt_a.astype(dtype) ** 2 * x[self.anchors])

    def diagonal(self, dtype) -> Array:
        """The diagonal of M.

        **Arguments:**

        - `dtype`: the result's dtype.

        **Returns:**

        An array `(V,)`.
        """
        w = self.sqrt_w.astype(dtype) ** 2
        d = jax.ops.segment_sum(w, self.edge_i, self.n, indices_are_sorted=True) + jax.ops.segment_sum(
            w, self.edge_j, self.n
        )
        return d.at[self.anchors].add(self.sqrt_a.astype(dtype) ** 2)

    def dense(self, dtype) -> Array:
        """M as a dense array.

        **Arguments:**

        - `dtype`: the result's dtype.

        **Returns:**

        An array `(V, V)`.
        """
        w = self.sqrt_w.astype(dtype) ** 2
        m = jnp.zeros((self.n, self.n), dtype)
        m = m.at[self.edge_i, self.edge_j].add(-w).at[self.edge_j, self.edge_i].add(-w)
        m = m.at[self.edge_i, self.edge_i].add(w).at[self.edge_j, self.edge_j].add(w)
        return m.at[self.anchors, self.anchors].add(self.sqrt_a.astype(dtype) ** 2)


# --------------------------------------------------------------------------------------------------
# the three solvers of M x = b; each returns (x, converged, steps)
# --------------------------------------------------------------------------------------------------


class HostCholesky(eqx.Module):
    """Sparse Cholesky factor of M on the host (cholespy, float64), one per (reference, anchors).

    The factor belongs to the matrix it was built from: derivatives through :meth:`Reconstructor.with_rest`
    are exact at that reference, and solving a different matrix with it is refused (``eqx.error_if``).
    """

    key: int = eqx.field(static=True)

    @staticmethod
    def build(matrix: NormalMatrix) -> HostCholesky:
        """Factor a normal matrix on the host.

        **Arguments:**

        - `matrix`: the normal matrix; its arrays must be concrete (not traced).

        **Returns:**

        The :class:`HostCholesky`.

        **Raises:**

        `ValueError` when `matrix` is traced; `DegenerateMeshError` for non-finite entries.
        """
        if is_traced(matrix):
            raise ValueError(
                "the host factor of a new anchor set needs a concrete Acap: call acap.reconstructor(anchors) "
                "outside the trace, or pass the Acap closed over instead of as an argument."
            )
        w = np.asarray(matrix.sqrt_w, np.float64) ** 2
        e = np.stack([np.asarray(matrix.edge_i), np.asarray(matrix.edge_j)], axis=1)
        anchors = np.asarray(matrix.anchors)
        a = float(np.asarray(matrix.sqrt_a, np.float64)) ** 2
        rows = np.r_[e[:, 0], e[:, 1], e[:, 0], e[:, 1], anchors]
        cols = np.r_[e[:, 1], e[:, 0], e[:, 0], e[:, 1], anchors]
        vals = np.r_[-w, -w, w, w, np.full(anchors.size, a)]
        return HostCholesky(register_factor(matrix.n, rows, cols, vals))

    def solve(self, matrix: NormalMatrix, b, scale2=None):
        """Solve M x = b through the host factor (`matrix` and `scale2` are ignored).

        **Arguments:**

        - `matrix`: the normal matrix M.
        - `b`: right-hand sides, vertex-major `(V, ...)`.
        - `scale2`: squared right-hand-side norms for the stopping rule (used by :class:`ConjugateGradient` only).

        **Returns:**

        `(x, converged, steps)`: x in b's shape and dtype, a bool scalar and an int32 scalar.
        """
        del matrix, scale2
        return _callback_solve(self.key, b), jnp.array(True), jnp.array(1, jnp.int32)


class DenseCholesky(eqx.Module):
    """Dense lower Cholesky factor (V, V) of M, computed by XLA once; solves all frames in one pair of
    triangular solves in the factor's dtype (float64 where x64 is enabled and the reference is float64)."""

    chol: Float[Array, "v v"]

    @staticmethod
    def build(matrix: NormalMatrix, dtype) -> DenseCholesky:
        """Factor a normal matrix with XLA.

        **Arguments:**

        - `matrix`: the normal matrix.
        - `dtype`: the factor's dtype.

        **Returns:**

        The :class:`DenseCholesky`.

        **Raises:**

        `DegenerateMeshError` when M is not positive definite (checked when concrete).
        """
        chol = jax.jit(lambda m: jnp.linalg.cholesky(m.dense(dtype)))(matrix)
        if not is_traced(chol) and not bool(jnp.isfinite(chol[-1, -1])):
            raise DegenerateMeshError("the reconstruction matrix is not positive definite (degenerate reference mesh).")
        return DenseCholesky(chol)

    def solve(self, matrix: NormalMatrix, b, scale2=None):
        """Solve M x = b with the dense factor (`matrix` and `scale2` are ignored).

        **Arguments:**

        - `matrix`: the normal matrix M.
        - `b`: right-hand sides, vertex-major `(V, ...)`.
        - `scale2`: squared right-hand-side norms for the stopping rule (used by :class:`ConjugateGradient` only).

        **Returns:**

        `(x, converged, steps)`: x in b's shape and dtype, a bool scalar and an int32 scalar.
        """
        del matrix, scale2
        n = self.chol.shape[0]
        cols = b.reshape(n, -1).astype(self.chol.dtype)
        x = jax.scipy.linalg.cho_solve((self.chol, True), cols)
        return x.reshape(b.shape).astype(b.dtype), jnp.array(True), jnp.array(1, jnp.int32)


class ConjugateGradient(eqx.Module):
    """Matrix-free Jacobi-preconditioned conjugate gradients on M, every column (vertex-major b (V, ...):
    coordinate and frame) solved at once with its own step sizes.

    Starts from zero and stops when every column's residual satisfies |r|^2 <= rtol^2 max(|b|^2, scale2)
    (``rtol=None``: 1e-6 in float32, 1e-12 in float64; ``scale2``: the squared norms of the full right-hand
    side when b is the right-hand side of a correction from a warm start) or after ``max_steps``;
    ``converged`` says which.
    """

    rtol: float | None = eqx.field(static=True, default=None)
    max_steps: int = eqx.field(static=True, default=CG_MAX_STEPS)

    def solve(self, matrix: NormalMatrix, b, scale2=None):
        """Solve M x = b by conjugate gradients from zero (stopping rule in the class docstring).

        **Arguments:**

        - `matrix`: the normal matrix M.
        - `b`: right-hand sides, vertex-major `(V, ...)`.
        - `scale2`: squared right-hand-side norms for the stopping rule (used by :class:`ConjugateGradient` only).

        **Returns:**

        `(x, converged, steps)`: x in b's shape and dtype, a bool scalar and an int32 scalar.
        """
        dtype = b.dtype
        rtol = CG_RTOL[np.dtype(dtype)] if self.rtol is None else self.rtol
        inv_d = (1.0 / matrix.diagonal(dtype)).reshape((-1,) + (1,) * (b.ndim - 1))
        x = jnp.zeros_like(b)
        r = b
        z = inv_d * r
        norm2 = jnp.sum(b * b, axis=0)
        if scale2 is not None:
            norm2 = jnp.maximum(norm2, scale2.astype(dtype))
        bound = (rtol**2) * norm2

        def cond(state):
            _, r, _, _, _, k = state
            return (k < self.max_steps) & jnp.any(jnp.sum(r * r, axis=0) > bound)

        def body(state):
            x, r, z, p, rz, k = state
            mp = matrix.mv(p)
            pmp = jnp.sum(p * mp, axis=0)
            alpha = jnp.where(pmp > 0, rz / jnp.where(pmp > 0, pmp, 1.0), 0.0)
            x = x + alpha * p
            r = r - alpha * mp
            z = inv_d * r
            rz_new = jnp.sum(r * z, axis=0)
            beta = jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
            return x, r, z, z + beta * p, rz_new, k + 1

        rz = jnp.sum(r * z, axis=0)
        x, r, _, _, _, k = jax.lax.while_loop(cond, body, (x, r, z, z, rz, jnp.array(0, jnp.int32)))
        return x, jnp.all(jnp.sum(r * r, axis=0) <= bound), k


# --------------------------------------------------------------------------------------------------
# lineax / optimistix glue
# --------------------------------------------------------------------------------------------------


class EdgeJacobianT(eqx.Module):
    """J^T of the reconstruction residuals (edge rows (E, 3, B), anchor rows (A, 3, B)) -> (V, 3, B).

    Written as segment sums: the transpose JAX derives from the residuals' gathers is a generic
    scatter that XLA on CPU runs several times slower.
    """

    sqrt_w: ArrayLike
    edge_i: ArrayLike
    edge_j: ArrayLike
    anchors: ArrayLike
    sqrt_a: ArrayLike
    n: int = eqx.field(static=True)

    def __call__(self, residuals):
        r_edge, r_anchor = residuals
        sr = self.sqrt_w.astype(r_edge.dtype)[:, None, None] * r_edge
        out = _scatter_edges(sr, self.edge_i, self.edge_j, self.n)
        return out.at[self.anchors].add(self.sqrt_a.astype(r_anchor.dtype) * r_anchor)


class NormalSolver(lx.AbstractLinearSolver):
    """A lineax solver for operators whose normal matrix is M (:class:`NormalMatrix`), solved by ``method``.

    For a square (self-adjoint) operator A = M it returns M^-1 v; for a rectangular operator J with
    J^T J = M (the Gauss-Newton Jacobian) it returns the least-squares solution M^-1 J^T v. The operator is
    only used for J^T v, and not even for that when ``jt`` (an explicit J^T, :class:`EdgeJacobianT`) is
    given. ``options["scale2"]``, where given, is passed to the method (see :class:`ConjugateGradient`).
    Stats: ``{"steps": iterations of the method, "converged": bool}``.
    """

    method: Any
    matrix: NormalMatrix
    jt: Any = None

    def init(self, operator, options):
        del options
        return operator

    def compute(self, state, vector, options):
        operator = state
        scale2 = None if options is None else options.get("scale2")
        if operator.in_size() != operator.out_size():
            vector = operator.transpose().mv(vector) if self.jt is None else self.jt(vector)
        leaves, treedef = jax.tree_util.tree_flatten(vector)
        outs = [self.method.solve(self.matrix, leaf, scale2) for leaf in leaves]
        converged = jnp.all(jnp.stack([o[1] for o in outs]))
        steps = jnp.max(jnp.stack([o[2] for o in outs]))
        result = lx.RESULTS.where(converged, lx.RESULTS.successful, lx.RESULTS.max_steps_reached)
        return (
            jax.tree_util.tree_unflatten(treedef, [o[0] for o in outs]),
            result,
            {"steps": steps, "converged": converged},
        )

    def transpose(self, state, options):
        return state.transpose(), options

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True


class LinearLeastSquares(optx.AbstractLeastSquaresSolver):
    """Least squares for residuals that are affine in y: one exact Gauss-Newton step from y0, then stop.

    ``optx.GaussNewton`` needs a second step (and a second solve) only to notice that the first step
    already solved an affine problem; this solver takes that one step and terminates. Its result is the
    linear solve's (``max_steps_reached`` where an iterative solve stopped short), and its stats hold the
    linear solve's ``steps`` and ``converged``. With ``warm_start`` the linear solver is told the size of the
    problem's right-hand side from y = 0 (``options["scale2"]``), so that an iterative solve started from a
    good y0 stops at the same absolute accuracy as one started from zero.
    """

    linear_solver: NormalSolver
    warm_start: bool = eqx.field(static=True, default=False)
    rtol: float = 0.0
    atol: float = 0.0
    norm: object = eqx.field(static=True, default=optx.max_norm)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, y, args, options, f_struct, tags
        aux = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), aux_struct)
        return (
            jnp.array(False),
            aux,
            optx.RESULTS.successful,
            {"steps": jnp.array(0, jnp.int32), "converged": jnp.array(True)},
        )

    def step(self, fn, y, args, options, state, tags):
        del options, state
        residual_fn = lambda _y: fn(_y, args)[0]  # noqa: E731
        (residual, jvp) = jax.linearize(residual_fn, y)
        aux = fn(y, args)[1]
        operator = lx.FunctionLinearOperator(jvp, jax.eval_shape(lambda: y), tags)
        neg = jax.tree_util.tree_map(jnp.negative, residual)
        solve_options = {}
        if self.warm_start and self.linear_solver.jt is not None:
            zero = jax.tree_util.tree_map(jnp.zeros_like, y)
            b0 = self.linear_solver.jt(residual_fn(zero))
            solve_options["scale2"] = jnp.sum(b0 * b0, axis=0)
        sol = lx.linear_solve(operator, neg, self.linear_solver, options=solve_options, throw=False)
        y_new = jax.tree_util.tree_map(jnp.add, y, sol.value)
        stats = {"steps": sol.stats["steps"], "converged": sol.stats["converged"]}
        return y_new, (jnp.array(True), aux, optx.RESULTS.promote(sol.result), stats), aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        return state[0], state[2]

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, args, options, tags, result
        return y, aux, state[3]


def _residuals(y, args):
    """Residuals in the vertex-major layout: y (V, 3, B); edge rows (E, 3, B) and anchor rows (A, 3, B)."""
    target, targets, sqrt_w, i, j, anchors, sqrt_a = args
    r_edge = sqrt_w[:, None, None] * (y[i] - y[j]) - target
    r_anchor = sqrt_a * (y[anchors] - targets)
    return r_edge, r_anchor


def edge_targets(t_vm: Float[Array, "v 3 3 b"], rest_edges, sqrt_w, i, j) -> Float[Array, "e 3 b"]:
    """The edge targets sqrt(w_ij) (T_i + T_j)/2 (q_i - q_j) of vertex-major gradients.

    The 3x3 products are written out entry by entry: XLA on CPU runs small einsums far slower.

    **Arguments:**

    - `t_vm`: gradients `(V, 3, 3, B)`.
    - `rest_edges`: reference edge vectors q_i - q_j `(E, 3)`.
    - `sqrt_w`: square roots of the edge weights `(E,)`.
    - `i`, `j`: edge endpoints `(E,)`.

    **Returns:**

    Edge targets `(E, 3, B)`, linear in the gradients.
    """
    tsum = t_vm[i] + t_vm[j]  # (E, 3, 3, B): contiguous row gathers
    q = ((0.5 * sqrt_w)[:, None] * rest_edges)[:, :, None]  # (E, 3, 1)
    return tsum[:, :, 0] * q[:, None, 0] + tsum[:, :, 1] * q[:, None, 1] + tsum[:, :, 2] * q[:, None, 2]


class SolveInfo(eqx.Module):
    """How a reconstruction's linear solves went: ``converged`` (always True for the factored solvers) and
    ``steps`` (the most iterations any solve took; 1 for the factored solvers)."""

    converged: Bool[Array, ""]
    steps: Int[Array, ""]

    def merge(self, other: SolveInfo) -> SolveInfo:
        """Combine the diagnostics of two solves.

        **Arguments:**

        - `other`: the other solve's info.

        **Returns:**

        Converged where both converged, with the larger step count.
        """
        return SolveInfo(self.converged & other.converged, jnp.maximum(self.steps, other.steps))


def component_anchors(edges: Int[ArrayLike, "e 2"], n: int) -> tuple[np.ndarray, np.ndarray]:
    """The connected components of a mesh's edge graph and the default anchor of each.

    **Arguments:**

    - `edges`: the undirected edges `(E, 2)` (host values).
    - `n`: the number of vertices (a vertex on no edge is a component of its own).

    **Returns:**

    `(labels, anchors)`: the component of each vertex `(V,)`, numbered in the order of their lowest vertex, and
    that lowest vertex of each component `(K,)`, ascending.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    first = np.full(labels.max(initial=-1) + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n))
    order = np.argsort(first)
    relabel = np.empty_like(order)
    relabel[order] = np.arange(order.size)
    return relabel[labels], first[order]


def _check_anchors(anchors, n: int, edges=None) -> np.ndarray:
    """Concrete anchor indices, checked; None gives vertex 0, or (given the host `edges`) the lowest vertex of
    each connected component. Given `edges`, every component must hold an anchor (else the solve is singular)."""
    labels = firsts = None
    if edges is not None:
        labels, firsts = component_anchors(edges, n)
    if anchors is None:
        anchors = [0] if firsts is None else firsts
    anchors = np.atleast_1d(np.asarray(anchors, dtype=np.int64))
    if anchors.ndim != 1 or anchors.size == 0 or anchors.min() < 0 or anchors.max() >= n:
        raise ValueError(f"anchor indices must lie in [0, {n}).")
    if np.unique(anchors).size != anchors.size:
        raise ValueError("anchor indices must be distinct.")
    if labels is not None:
        free = np.setdiff1d(np.arange(firsts.size), labels[anchors])
        if free.size:
            raise ValueError(
                f"the mesh has {firsts.size} connected components and {free.size} of them hold no anchor (the "
                f"one of vertex {int(firsts[free[0]])}, ...); give one anchor per component (the CLI's --anchors), "
                "or none for the lowest vertex of each."
            )
    return anchors


def is_traced(*trees) -> bool:
    """Whether any leaf holds values the host cannot read now.

    **Arguments:**

    - `trees`: any pytrees.

    **Returns:**

    True where a leaf is a tracer or a global array with parts on other processes (multi-host). Such
    values are checked inside the computation, not on the host.
    """
    return any(
        isinstance(x, jax.core.Tracer) or (isinstance(x, jax.Array) and not x.is_fully_addressable)
        for x in jax.tree_util.tree_leaves(trees)
    )


@jax.jit
def all_finite(x: ArrayLike) -> Array:
    """Whether every entry of an array is finite.

    **Arguments:**

    - `x`: an array.

    **Returns:**

    A device bool scalar (an eager check reads one bool, not `x`).
    """
    return jnp.all(jnp.isfinite(x))


class Reconstructor(eqx.Module):
    """Positions from deformation gradients for one (reference, connectivity, anchors); build once, call many.

    ``__call__(t (..., V, 3, 3), targets (..., A, 3) | None) -> positions (..., V, 3)``: traces under jit,
    vmap, grad, jvp; differentiable in ``t``, ``targets`` and (through :meth:`with_rest`) the reference.
    """

    rest: Float[Array, "v 3"]
    rest_edges: Float[Array, "e 3"]
    sqrt_w: Float[Array, " e"]
    edge_i: Int[Array, " e"]
    edge_j: Int[Array, " e"]
    anchors: Int[ArrayLike, " a"]  # numpy after :meth:`with_anchors` of concrete indices
    sqrt_a: Float[Array, ""]
    method: HostCholesky | DenseCholesky | ConjugateGradient
    anchor_weight: float = eqx.field(static=True, default=ANCHOR_WEIGHT)

    @staticmethod
    def build(
        rest: Float[ArrayLike, "v 3"],
        topo: Topology,
        weights: Float[ArrayLike, " e"],
        anchors=None,
        anchor_weight: float = ANCHOR_WEIGHT,
        solver: Solver = "host",
        cg_rtol: float | None = None,
        cg_max_steps: int = CG_MAX_STEPS,
    ) -> Reconstructor:
        """Host-side construction: checks (positive weights, anchors) and the factor of `solver`.

        **Arguments:**

        - `rest`: reference positions `(V, 3)`, a jax or numpy array; its dtype is the problem's.
        - `topo`: the mesh topology.
        - `weights`: edge weights `(E,)`, a jax or numpy array; all positive.
        - `anchors`: vertex indices, a concrete sequence, one at least in each connected component (default:
          the lowest vertex of each component, :func:`component_anchors`; vertex 0 for a connected mesh).
        - `anchor_weight`: the anchor weight relative to the mean edge weight.
        - `solver`: "host", "dense" or "cg".
        - `cg_rtol`, `cg_max_steps`: conjugate-gradient settings (:class:`ConjugateGradient`).

        **Returns:**

        The :class:`Reconstructor`.

        **Raises:**

        `ValueError` for an unknown solver or bad anchors (out of range, repeated, none);
        `DegenerateMeshError` for a non-positive weight or a degenerate normal matrix.
        """
        if solver not in SOLVERS:
            raise ValueError(f"unknown solver '{solver}'; expected one of {', '.join(SOLVERS)}.")
        rest = jnp.asarray(rest)
        w_host = np.asarray(weights, dtype=np.float64)
        if not np.all(w_host > 0):
            raise DegenerateMeshError(
                "reconstruction needs positive edge weights; use weighting='official' for this mesh."
            )
        n = topo.n_vertices
        anchors = _check_anchors(anchors, n, np.asarray(topo.edges))
        a = float(anchor_weight * np.mean(w_host))
        weights = jnp.asarray(weights, dtype=rest.dtype)
        edges = jnp.asarray(topo.edges)
        rec = Reconstructor(
            rest=rest,
            rest_edges=rest[edges[:, 0]] - rest[edges[:, 1]],
            sqrt_w=jnp.sqrt(weights),
            edge_i=edges[:, 0],
            edge_j=edges[:, 1],
            anchors=jnp.asarray(anchors, dtype=jnp.int32),
            sqrt_a=jnp.asarray(np.sqrt(a), dtype=rest.dtype),
            method=ConjugateGradient(cg_rtol, cg_max_steps),
            anchor_weight=anchor_weight,
        )
        return rec.with_method(solver, cg_rtol, cg_max_steps)

    def with_method(
        self, solver: Solver, cg_rtol: float | None = None, cg_max_steps: int = CG_MAX_STEPS
    ) -> Reconstructor:
        """The same problem solved by another solver (factors are built now, on the host for "host").

        **Arguments:**

        - `solver`: "host", "dense" or "cg".
        - `cg_rtol`, `cg_max_steps`: conjugate-gradient settings.

        **Returns:**

        A new :class:`Reconstructor`.

        **Raises:**

        `ValueError` for an unknown solver.
        """
        if solver == "host":
            method = HostCholesky.build(self.matrix())
        elif solver == "dense":
            method = DenseCholesky.build(self.matrix(), self.rest.dtype)
        elif solver == "cg":
            method = ConjugateGradient(cg_rtol, cg_max_steps)
        else:
            raise ValueError(f"unknown solver '{solver}'; expected one of {', '.join(SOLVERS)}.")
        return eqx.tree_at(lambda r: r.method, self, method)

    @property
    def solver(self) -> Solver:
        """The solver's name: "host", "dense" or "cg"."""
        return {HostCholesky: "host", DenseCholesky: "dense", ConjugateGradient: "cg"}[type(self.method)]

    def matrix(self) -> NormalMatrix:
        """The normal matrix of this problem.

        **Returns:**

        The matrix-free :class:`NormalMatrix`.
        """
        return NormalMatrix(self.sqrt_w, self.edge_i, self.edge_j, self.anchors, self.sqrt_a, self.rest.shape[0])

    def with_anchors(self, anchors) -> Reconstructor:
        """The same reference with other anchors.

        **Arguments:**

        - `anchors`: vertex indices. The factored solvers need concrete indices
          (a new factor is built); conjugate gradients take traced ones too.

        **Returns:**

        A new :class:`Reconstructor`.

        **Raises:**

        `ValueError` for bad concrete anchors, or traced anchors with a factored solver.
        """
        if is_traced(anchors):
            if not isinstance(self.method, ConjugateGradient):
                raise ValueError("traced anchor indices need solver='cg'; the factored solvers need concrete indices.")
            return eqx.tree_at(lambda r: r.anchors, self, anchors.astype(jnp.int32))
        edges = None if is_traced(self.edge_i, self.edge_j) else np.stack([self.edge_i, self.edge_j], axis=1)
        idx = _check_anchors(anchors, self.rest.shape[0], edges).astype(np.int32)  # numpy: concrete in a trace too
        rec = eqx.tree_at(lambda r: r.anchors, self, idx)
        if isinstance(self.method, HostCholesky):
            return eqx.tree_at(lambda r: r.method, rec, HostCholesky.build(rec.matrix()))
        if isinstance(self.method, DenseCholesky):
            return eqx.tree_at(lambda r: r.method, rec, DenseCholesky.build(rec.matrix(), self.method.chol.dtype))
        return rec

    def with_rest(self, rest: Float[ArrayLike, "v 3"], weights: Float[ArrayLike, " e"]) -> Reconstructor:
        """The problem's reference-side constants recomputed from a new reference.

        Conjugate gradients solve the new matrix; a factored solver keeps its factor, which is exact only at
        the reference it was built for: there the derivatives are exact, elsewhere the solve is refused.

        **Arguments:**

        - `rest`: reference positions `(V, 3)`.
        - `weights`: its edge weights `(E,)` (which the caller derives from `rest`).

        **Returns:**

        A new :class:`Reconstructor` whose positions are differentiable in the reference. A factored solver
        refuses (`equinox.error_if`) a reference other than its own.
        """
        if not isinstance(self.method, ConjugateGradient):
            rest = eqx.error_if(
                rest,
                jnp.any(rest != self.rest.astype(rest.dtype)),
                "a factored solver reconstructs only at its own reference; use solver='cg' to move it.",
            )
        weights = weights.astype(rest.dtype)
        new = (
            rest,
            rest[self.edge_i] - rest[self.edge_j],
            jnp.sqrt(weights),
            jnp.sqrt(self.anchor_weight * jnp.mean(weights)),
        )
        return eqx.tree_at(lambda r: (r.rest, r.rest_edges, r.sqrt_w, r.sqrt_a), self, new)

    def __call__(self, t: Float[ArrayLike, "... v 3 3"], targets: Float[ArrayLike, "... a 3"] | None = None):
        """Positions from deformation gradients (see :meth:`solve_vm` for the fast layout).

        **Arguments:**

        - `t`: gradients `(..., V, 3, 3)`.
        - `targets`: anchor targets `(..., A, 3)`; None: the anchors' reference positions.

        **Returns:**

        Positions `(..., V, 3)` in t's dtype; differentiable in `t` and `targets`.
        """
        lead = t.shape[:-3]
        v = self.rest.shape[0]
        t_vm = jnp.moveaxis(t.reshape(-1, v, 3, 3), 0, -1)  # (V, 3, 3, B)
        y = self.solve_vm(t_vm, self.targets_vm(targets, lead, t.dtype))
        return jnp.moveaxis(y, -1, 0).reshape(*lead, v, 3)

    def normal_rhs(self) -> EdgeJacobianT:
        """J^T of this problem's residuals, for the solver.

        **Returns:**

        The :class:`EdgeJacobianT`.
        """
        return EdgeJacobianT(self.sqrt_w, self.edge_i, self.edge_j, self.anchors, self.sqrt_a, self.rest.shape[0])

    def targets_vm(
        self, targets: Float[ArrayLike, "... a 3"] | None, lead: tuple, dtype
    ) -> Float[Array, "a 3 b"] | None:
        """Anchor targets broadcast to a batch and laid out vertex-major.

        **Arguments:**

        - `targets`: anchor targets `(..., A, 3)` or None.
        - `lead`: the batch shape.
        - `dtype`: the result's dtype.

        **Returns:**

        Targets `(A, 3, B)` (B the batch size); None stays None.
        """
        if targets is None:
            return None
        a = self.anchors.shape[0]
        targets = jnp.broadcast_to(jnp.asarray(targets, dtype), (*lead, a, 3))
        return jnp.moveaxis(targets.reshape(-1, a, 3), 0, -1)

    def rest_targets_vm(self, b: int, dtype) -> Float[Array, "a 3 b"]:
        """The anchors' reference positions for a number of frames.

        **Arguments:**

        - `b`: the number of frames.
        - `dtype`: the result's dtype.

        **Returns:**

        Targets `(A, 3, B)`.
        """
        return jnp.broadcast_to(self.rest[self.anchors].astype(dtype)[:, :, None], (self.anchors.shape[0], 3, b))

    def edge_targets_vm(self, t_vm: Float[Array, "v 3 3 b"]) -> Float[Array, "e 3 b"]:
        """The residuals' edge targets of gradients.

        **Arguments:**

        - `t_vm`: gradients `(V, 3, 3, B)`.

        **Returns:**

        Edge targets `(E, 3, B)` in the gradients' dtype; linear in the gradients.
        """
        dtype = t_vm.dtype
        return edge_targets(t_vm, self.rest_edges.astype(dtype), self.sqrt_w.astype(dtype), self.edge_i, self.edge_j)

    def solve_vm(self, t_vm: Float[Array, "v 3 3 b"], targets_vm: Float[Array, "a 3 b"] | None = None):
        """Positions from vertex-major gradients.

        **Arguments:**

        - `t_vm`: gradients `(V, 3, 3, B)`.
        - `targets_vm`: anchor targets `(A, 3, B)`; None: the reference.

        **Returns:**

        Positions `(V, 3, B)`.
        """
        return self.solve_targets_vm(self.edge_targets_vm(t_vm), targets_vm)

    def solve_targets_vm(self, target: Float[Array, "e 3 b"], targets_vm: Float[Array, "a 3 b"] | None = None):
        """Positions from edge targets.

        **Arguments:**

        - `target`: edge targets `(E, 3, B)` (:meth:`edge_targets_vm`).
        - `targets_vm`: anchor targets `(A, 3, B)`; None: the reference.

        **Returns:**

        Positions `(V, 3, B)`.
        """
        return self.solve(target, targets_vm)[0]

    def solve(
        self,
        target: Float[Array, "e 3 b"],
        targets_vm: Float[Array, "a 3 b"] | None = None,
        y0: Float[Array, "v 3 b"] | None = None,
    ) -> tuple[Array, SolveInfo]:
        """Positions from edge and anchor targets, with the solve's diagnostics.

        **Arguments:**

        - `target`: edge targets `(E, 3, B)`.
        - `targets_vm`: anchor targets `(A, 3, B)`; None: the reference.
        - `y0`: the start `(V, 3, B)` (default zero; only conjugate gradients depend on the start, up to their
          tolerance).

        **Returns:**

        `(positions, info)`: positions `(V, 3, B)` in the targets' dtype and the :class:`SolveInfo`.
        Differentiable (implicit adjoint) in the targets and the reference-side constants.
        """
        dtype = target.dtype
        b = target.shape[-1]
        if targets_vm is None:
            targets_vm = self.rest_targets_vm(b, dtype)
        y0 = jnp.zeros((self.rest.shape[0], 3, b), dtype) if y0 is None else y0.astype(dtype)
        args = (
            target,
            targets_vm.astype(dtype),
            self.sqrt_w.astype(dtype),
            self.edge_i,
            self.edge_j,
            self.anchors,
            self.sqrt_a.astype(dtype),
        )
        # the solver holds primal values only: the derivatives come from the residuals' args (implicit adjoint)
        linsolve = jax.lax.stop_gradient(NormalSolver(self.method, self.matrix(), self.normal_rhs()))
        sol = optx.least_squares(
            _residuals,
            LinearLeastSquares(linear_solver=linsolve, warm_start=isinstance(self.method, ConjugateGradient)),
            y0,
            args,
            max_steps=2,
            adjoint=optx.ImplicitAdjoint(linear_solver=linsolve),
            throw=False,
        )
        return sol.value, SolveInfo(jnp.asarray(sol.stats["converged"]), jnp.asarray(sol.stats["steps"], jnp.int32))
