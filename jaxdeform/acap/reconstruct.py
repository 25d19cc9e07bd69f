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
    b64 = np.require(b, dtype=np.float64, requirements=["C", "W"])  # nanobind rejects read-only views
    x = np.empty_like(b64)
    _FACTORS[key].solve(b64, x)
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


class EdgeJacobianT(eqx.Module):
    """J^T of the reconstruction residuals (edge rows (E, 3, B), anchor rows (A, 3, B)) -> (V, 3, B).

    Written as segment sums: the transpose JAX derives from the residuals' gathers is a generic
    scatter that XLA on CPU runs about 5x slower (horse-gallop, 48 frames: 16 against 3 ms).
    """

    sqrt_w: Array
    edge_i: Array
    edge_j: Array
    anchors: Array
    sqrt_a: Array
    n: int = eqx.field(static=True)

    def __call__(self, residuals):
        r_edge, r_anchor = residuals
        sr = self.sqrt_w.astype(r_edge.dtype)[:, None, None] * r_edge
        out = jax.ops.segment_sum(sr, self.edge_i, self.n, indices_are_sorted=True)
        out = out - jax.ops.segment_sum(sr, self.edge_j, self.n)
        return out.at[self.anchors].add(self.sqrt_a.astype(r_anchor.dtype) * r_anchor)


class PrefactoredCholesky(lx.AbstractLinearSolver):
    """A lineax solver for operators whose normal matrix is a fixed, prefactored sparse SPD matrix M.

    For a square (self-adjoint) operator A = M it returns M^-1 v; for a rectangular operator J with
    J^T J = M (a Gauss-Newton Jacobian) it returns the least-squares solution M^-1 J^T v. The operator is
    only used for J^T v, and not even for that when ``jt`` (an explicit J^T, e.g. :class:`EdgeJacobianT`)
    is given; M itself is never built in JAX.
    """

    key: int = eqx.field(static=True)
    jt: Any = None

    def init(self, operator, options):
        del options
        return operator

    def compute(self, state, vector, options):
        del options
        operator = state
        if operator.in_size() != operator.out_size():
            vector = operator.transpose().mv(vector) if self.jt is None else self.jt(vector)
        leaves, treedef = jax.tree_util.tree_flatten(vector)
        sol = [_callback_solve(self.key, leaf) for leaf in leaves]
        return jax.tree_util.tree_unflatten(treedef, sol), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        return state.transpose(), options

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True


class LinearLeastSquares(optx.AbstractLeastSquaresSolver):
    """Least squares for residuals that are affine in y: one exact Gauss-Newton step, then stop.

    ``optx.GaussNewton`` needs a second step (and a second solve) only to notice that the first step
    already solved an affine problem; this solver takes that one step and terminates.
    """

    linear_solver: lx.AbstractLinearSolver
    rtol: float = 0.0
    atol: float = 0.0
    norm: object = eqx.field(static=True, default=optx.max_norm)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, y, args, options, f_struct, tags
        return (jnp.array(False), jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), aux_struct))

    def step(self, fn, y, args, options, state, tags):
        del options, state
        residual_fn = lambda _y: fn(_y, args)[0]  # noqa: E731
        (residual, jvp) = jax.linearize(residual_fn, y)
        aux = fn(y, args)[1]
        operator = lx.FunctionLinearOperator(jvp, jax.eval_shape(lambda: y), tags)
        neg = jax.tree_util.tree_map(jnp.negative, residual)
        sol = lx.linear_solve(operator, neg, self.linear_solver, throw=False)
        y_new = jax.tree_util.tree_map(jnp.add, y, sol.value)
        return y_new, (jnp.array(True), aux), aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        return state[0], optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, args, options, state, tags, result
        return y, aux, {}


def _residuals(y, args):
    """Residuals in the vertex-major layout: y (V, 3, B); edge rows (E, 3, B) and anchor rows (A, 3, B)."""
    target, targets, sqrt_w, i, j, anchors, sqrt_a = args
    r_edge = sqrt_w[:, None, None] * (y[i] - y[j]) - target
    r_anchor = sqrt_a * (y[anchors] - targets)
    return r_edge, r_anchor


def edge_targets(t_vm: Float[Array, "v 3 3 b"], rest_edges, sqrt_w, i, j) -> Float[Array, "e 3 b"]:
    """sqrt(w_ij) (T_i + T_j)/2 (q_i - q_j) per edge, from vertex-major gradients (V, 3, 3, B).

    The 3x3 products are written out entry by entry: XLA on CPU runs small einsums far slower.
    """
    tsum = t_vm[i] + t_vm[j]  # (E, 3, 3, B): contiguous row gathers
    q = ((0.5 * sqrt_w)[:, None] * rest_edges)[:, :, None]  # (E, 3, 1)
    return tsum[:, :, 0] * q[:, None, 0] + tsum[:, :, 1] * q[:, None, 1] + tsum[:, :, 2] * q[:, None, 2]


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
        """Positions (..., V, 3) from gradients (..., V, 3, 3) (see :meth:`solve_vm` for the fast layout)."""
        lead = t.shape[:-3]
        v = self.rest.shape[0]
        t_vm = jnp.moveaxis(t.reshape(-1, v, 3, 3), 0, -1)  # (V, 3, 3, B)
        y = self.solve_vm(t_vm, self.targets_vm(targets, lead, t.dtype))
        return jnp.moveaxis(y, -1, 0).reshape(*lead, v, 3)

    def normal_rhs(self) -> EdgeJacobianT:
        """J^T of this problem's residuals, for the solver."""
        return EdgeJacobianT(self.sqrt_w, self.edge_i, self.edge_j, self.anchors, self.sqrt_a, self.rest.shape[0])

    def targets_vm(self, targets: Float[Array, "... a 3"] | None, lead: tuple, dtype) -> Float[Array, "a 3 b"] | None:
        """Anchor targets broadcast to the batch ``lead`` and laid out vertex-major (A, 3, B); None stays None."""
        if targets is None:
            return None
        a = self.anchors.shape[0]
        targets = jnp.broadcast_to(jnp.asarray(targets, dtype), (*lead, a, 3))
        return jnp.moveaxis(targets.reshape(-1, a, 3), 0, -1)

    def edge_targets_vm(self, t_vm: Float[Array, "v 3 3 b"]) -> Float[Array, "e 3 b"]:
        """The residuals' edge targets (E, 3, B) of gradients (V, 3, 3, B); linear in the gradients."""
        dtype = t_vm.dtype
        return edge_targets(t_vm, self.rest_edges.astype(dtype), self.sqrt_w.astype(dtype), self.edge_i, self.edge_j)

    def solve_vm(self, t_vm: Float[Array, "v 3 3 b"], targets_vm: Float[Array, "a 3 b"] | None = None):
        """Positions (V, 3, B) from gradients (V, 3, 3, B) and anchor targets (A, 3, B) (default: rest)."""
        return self.solve_targets_vm(self.edge_targets_vm(t_vm), targets_vm)

    def solve_targets_vm(self, target: Float[Array, "e 3 b"], targets_vm: Float[Array, "a 3 b"] | None = None):
        """Positions (V, 3, B) from edge targets (E, 3, B) (:meth:`edge_targets_vm`) and anchor targets."""
        dtype = target.dtype
        b = target.shape[-1]
        if targets_vm is None:
            targets_vm = jnp.broadcast_to(self.rest[self.anchors].astype(dtype)[:, :, None], (self.anchors.shape[0], 3, b))
        # the residuals are affine in y, so the one Gauss-Newton step is exact from any start: start at 0
        y0 = jnp.zeros((self.rest.shape[0], 3, b), dtype)
        args = (target, targets_vm, self.sqrt_w.astype(dtype), self.edge_i, self.edge_j, self.anchors,
                self.sqrt_a.astype(dtype))
        linsolve = PrefactoredCholesky(self.key, self.normal_rhs())
        sol = optx.least_squares(
            _residuals,
            LinearLeastSquares(linear_solver=linsolve),
            y0,
            args,
            max_steps=2,
            adjoint=optx.ImplicitAdjoint(linear_solver=linsolve),
            throw=False,
        )
        return sol.value
