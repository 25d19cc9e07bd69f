"""Axis/angle consistency of per-vertex rotations (ACAP, Gao et al. 2019) and its temporal variant (TS-ACAP).

A rotation with axis w and angle theta in [0, pi] is also (-w, -theta) and any of theta + 2 pi r. The
consistent representation picks, per vertex, an orientation o_i in {+1, -1} and a number of turns r_i,
giving the axis-angle vector (o_i theta_i + 2 pi r_i) w_i, so that neighbours agree:

1. orientation: maximize  sum_(i,j in E) o_i o_j s_ij  (+ sum_i o_t,i o_t-1,i s_i^time for TS-ACAP), with
   s = 0 where |w_i . w_j| <= EPS_DOT or either angle < EPS_ANGLE, else sign(w_i . w_j);
2. turns: minimize  sum_(i,j in E) (u_i - u_j)^2  (+ sum_i (u_t,i - u_t-1,i)^2), u = o theta + 2 pi r.

Fast path (default, jitted jnp, batched over frames; TS-ACAP scans over frames): a breadth-first tree from
the root of each connected component gives an initial solution by path products (orientation) and path
sums (turns) computed with pointer jumping over precomputed ancestor tables; then local improvement by
Gauss-Seidel sweeps over the colour classes of a graph colouring, each vertex taking its best value given
its neighbours, which never worsens the energy and stops when no vertex improves (or after MAX_SWEEPS).

Exact path (``method="milp"``, small meshes, one frame): both integer programs through
``scipy.optimize.milp`` (HiGHS): orientation as a max-cut with XOR variables; turns with a piecewise-linear
epigraph of each edge's convex integer cost (exact at integers) under |r_i - r_j| <= MILP_MAX_TURN_GAP.

The gauge is fixed by o = +1 and r = 0 at the root (vertex 0) of each component in a spatial solve; in the
temporal solve of frames after the first the previous frame fixes the gauge and the root is left free.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, Bool, Float
from scipy.sparse import csgraph

from jaxdeform.typing import Int

EPS_DOT = 1e-2
EPS_ANGLE = 1e-3
TWO_PI = 2.0 * np.pi
MAX_SWEEPS = 100
MILP_MAX_TURN_GAP = 3

Consistency = Literal["spatial", "temporal", "none"]


@dataclasses.dataclass(frozen=True)
class Graph:
    """Graph structures of one connectivity, built once on the host.

    ``edges`` serve the exact (MILP) path and the energies; ``rings`` is the device-side pytree of the fast
    path (padded one-rings, tree ancestors for pointer jumping, colour classes).
    """

    n: int
    edges: np.ndarray  # (E, 2)
    roots: np.ndarray  # (C,) one root per connected component
    rings: Rings


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Rings:
    """Static-size device arrays of the fast path (a pytree: jit compiles once per connectivity)."""

    nbr: Int[Array, "v k"]  # padded one-rings (padding = the vertex itself)
    mask: Bool[Array, "v k"]
    degree: Int[Array, " v"]
    parent: Int[Array, " v"]  # BFS parent; roots point to themselves
    is_root: Bool[Array, " v"]
    jumps: tuple  # ancestor tables parent, parent^2, parent^4, ... (pointer jumping)
    classes: tuple  # colour classes: independent vertex sets covering all vertices, each by degree (descending)
    class_slots: tuple = dataclasses.field(metadata=dict(static=True))  # per class: members with > k neighbours


def build_graph(edges: np.ndarray, n: int) -> Graph:
    """Build the graph structures of one connectivity on the host.

    **Arguments:**

    - `edges`: undirected edges `(E, 2)`, integer vertex indices.
    - `n`: the number of vertices.

    **Returns:**

    The :class:`Graph`, with one BFS root per connected component (its lowest vertex).
    """
    edges = np.asarray(edges, dtype=np.int64)
    e = edges.shape[0]
    src = np.r_[edges[:, 0], edges[:, 1]]
    dst = np.r_[edges[:, 1], edges[:, 0]]
    adj = sp.coo_matrix((np.ones(2 * e), (src, dst)), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    ncomp, labels = csgraph.connected_components(adj, directed=False)
    parent = np.arange(n)
    roots = np.array([np.flatnonzero(labels == c)[0] for c in range(ncomp)])
    for root in roots:
        order, pred = csgraph.breadth_first_order(adj, int(root), directed=False, return_predecessors=True)
        parent[order[1:]] = pred[order[1:]]
    jumps = [parent]
    while not np.array_equal(jumps[-1][jumps[-1]], jumps[-1]):
        jumps.append(jumps[-1][jumps[-1]])
    order = np.lexsort((dst, src))
    src_s, dst_s = src[order], dst[order]
    degree = np.bincount(src_s, minlength=n)
    kmax = int(degree.max()) if n else 0
    slot = np.arange(src_s.size) - np.r_[0, np.cumsum(degree)[:-1]][src_s]
    nbr = np.repeat(np.arange(n)[:, None], kmax, axis=1)
    nbr[src_s, slot] = dst_s
    mask = np.zeros((n, kmax), bool)
    mask[src_s, slot] = True
    is_root = np.zeros(n, bool)
    is_root[roots] = True
    # members of each colour class by degree, highest first: ring slot k of a class is then a prefix of it
    classes = [c[np.argsort(-degree[c], kind="stable")] for c in _colour_classes(nbr, mask)]
    i32 = lambda x: jnp.asarray(x, jnp.int32)  # noqa: E731
    rings = Rings(
        nbr=i32(nbr),
        mask=jnp.asarray(mask),
        degree=i32(degree),
        parent=i32(parent),
        is_root=jnp.asarray(is_root),
        jumps=tuple(i32(j) for j in jumps),
        classes=tuple(i32(c) for c in classes),
        class_slots=tuple(tuple(int(np.count_nonzero(degree[c] > k)) for k in range(kmax)) for c in classes),
    )
    return Graph(n=n, edges=edges, roots=roots, rings=rings)


def _colour_classes(nbr: np.ndarray, mask: np.ndarray) -> list[np.ndarray]:
    """A proper vertex colouring in few colours, vectorized (Jones-Plassmann rounds, smallest free colour).

    In each round the uncoloured vertices whose random priority beats every uncoloured neighbour take the
    smallest colour none of their neighbours has; colour classes are returned as index arrays.
    """
    n, k = nbr.shape
    prio = np.random.default_rng(0).permutation(n)
    colour = np.full(n, -1)
    palette = np.arange(k + 1)
    while (colour < 0).any():
        unc = colour < 0
        rival = np.where(mask & unc[nbr], prio[nbr], -1).max(axis=1, initial=-1)
        pick = np.flatnonzero(unc & (prio > rival))
        used = np.where(mask[pick], colour[nbr[pick]], -1)  # (P, K)
        free = ~(used[:, :, None] == palette[None, None, :]).any(axis=1)  # (P, K + 1)
        colour[pick] = np.argmax(free, axis=1)
    return [np.flatnonzero(colour == c) for c in range(colour.max() + 1)]


# ------------------------------------------------------------------------------ fast path (jitted jnp)


def _signs(d, angle_a, angle_b):
    ok = (jnp.abs(d) > EPS_DOT) & (angle_a >= EPS_ANGLE) & (angle_b >= EPS_ANGLE)
    return jnp.where(ok, jnp.sign(d), 0.0).astype(d.dtype)


def _pair_signs(axis_a, angle_a, axis_b, angle_b):
    """s between two vertex fields (axes (3, ...), angles (...)): sign of the axes' dot product, 0 when ill-defined."""
    return _signs(axis_a[0] * axis_b[0] + axis_a[1] * axis_b[1] + axis_a[2] * axis_b[2], angle_a, angle_b)


# The fast path works vertex-major and component-major: angles (V, N), axes (3, V, N), so that gathers over
# the one-rings and tree ancestors move whole contiguous rows (all frames of a vertex) at once, and no
# reduction runs over a short trailing axis (XLA on CPU is slow at both).


def _ring_signs(axis, angle, rings: Rings):
    """s_ij on the padded one-rings (V, K, N); 0 on padding."""
    nb = rings.nbr
    d = sum(axis[c][:, None] * axis[c][nb] for c in range(3))
    return jnp.where(rings.mask[:, :, None], _signs(d, angle[:, None], angle[nb]), 0.0)


def _path_combine(rel, rings: Rings, mul: bool):
    """Combine ``rel`` (V, N) along each vertex's tree path to its root (roots hold the identity)."""
    val = rel
    for anc in rings.jumps:
        val = val * val[anc] if mul else val + val[anc]
    return val


def _sweeps(step, x, max_sweeps: int = MAX_SWEEPS):
    """Repeat ``step(x) -> (x, changed)`` until nothing changes (at most ``max_sweeps`` times)."""

    def cond(state):
        return state[1] & (state[2] < max_sweeps)

    def body(state):
        x, _, it = state
        x, changed = step(x)
        return x, changed, it + 1

    return jax.lax.while_loop(cond, body, (x, jnp.array(True), jnp.array(0)))[0]


def _class_rings(rings: Rings) -> list[tuple[Array, Array, tuple]]:
    """Per colour class: (members, their one-rings (|c|, K), slot prefix lengths)."""
    return [(cls, rings.nbr[cls], slots) for cls, slots in zip(rings.classes, rings.class_slots)]


def _slot_sum(values_at, slots: tuple, shape, dtype) -> Array:
    """sum_k values_at(k, m_k) over the ring slots, where slot k covers the first m_k class members
    (members sorted by degree): no padding is touched, and the sum is K elementwise adds (fast on XLA CPU)."""
    total = jnp.zeros(shape, dtype)
    for k, m in enumerate(slots):
        if m:
            total = total.at[:m].add(values_at(k, m))
    return total


def _improve_orientation(o, s_ring, rings: Rings, fixed, s_time=None, o_prev=None):
    """Gauss-Seidel over colour classes: o_i <- sign(sum_j s_ij o_j [+ s_time_i o_prev_i])."""
    parts = _class_rings(rings)
    # signs per class and slot, gathered once outside the sweeps
    s_cls = [[s_ring[cls[:m], k] for k, m in enumerate(slots)] for cls, _, slots in parts]

    def step(o):
        changed = jnp.array(False)
        for (cls, nb, slots), s_c in zip(parts, s_cls):
            field = _slot_sum(lambda k, m: s_c[k] * o[nb[:m, k]], slots, (cls.shape[0],) + o.shape[1:], o.dtype)
            if s_time is not None:
                field = field + s_time[cls] * o_prev[cls]
            flip = (o[cls] * field < 0) & ~fixed[cls][:, None]
            o = o.at[cls].set(jnp.where(flip, -o[cls], o[cls]))
            changed = changed | jnp.any(flip)
        return o, changed

    return _sweeps(step, o)


def _improve_turns(phi, r, rings: Rings, fixed, u_prev=None):
    """Gauss-Seidel over colour classes: r_i <- the integer minimizing the vertex's quadratic terms."""
    deg = rings.degree.astype(phi.dtype) + (0.0 if u_prev is None else 1.0)
    tol = 1e-9 if phi.dtype == jnp.float64 else 1e-4
    parts = _class_rings(rings)

    def step(r):
        changed = jnp.array(False)
        u = phi + TWO_PI * r
        for cls, nb, slots in parts:
            total = _slot_sum(lambda k, m: u[nb[:m, k]], slots, (cls.shape[0],) + phi.shape[1:], phi.dtype)
            if u_prev is not None:
                total = total + u_prev[cls]
            mean = total / deg[cls][:, None]
            ph, cur = phi[cls], r[cls]
            best = jnp.round((mean - ph) / TWO_PI)
            # move only on a strict decrease (ties would let a vertex oscillate between equal choices)
            gain = (ph + TWO_PI * cur - mean) ** 2 - (ph + TWO_PI * best - mean) ** 2
            move = (best != cur) & (gain > tol) & ~fixed[cls][:, None]
            new = jnp.where(move, best, cur)
            r = r.at[cls].set(new)
            u = u.at[cls].set(ph + TWO_PI * new)
            changed = changed | jnp.any(move)
        return r, changed

    return _sweeps(step, r)


def _tree_orientation(axis, angle, rings: Rings):
    """Initial orientations: products of the parent signs along each vertex's BFS path (roots: +1)."""
    p = rings.parent
    rel = _pair_signs(axis, angle, axis[:, p], angle[p])
    rel = jnp.where((rel == 0) | rings.is_root[:, None], 1.0, rel).astype(angle.dtype)
    return _path_combine(rel, rings, mul=True)


def _tree_turns(phi, rings: Rings):
    """Initial turns: sums of the rounded parent differences along each vertex's BFS path (roots: 0)."""
    p = rings.parent
    d = jnp.where(rings.is_root[:, None], 0.0, jnp.round((phi[p] - phi) / TWO_PI)).astype(phi.dtype)
    return _path_combine(d, rings, mul=False)


def _spatial_orientation(axis, angle, rings: Rings):
    o = _tree_orientation(axis, angle, rings)
    return _improve_orientation(o, _ring_signs(axis, angle, rings), rings, fixed=rings.is_root)


def _spatial_turns(phi, rings: Rings):
    r = _improve_turns(phi, _tree_turns(phi, rings), rings, fixed=rings.is_root)
    return phi + TWO_PI * r


def _spatial_vm(axis, angle, rings: Rings):
    o = _spatial_orientation(axis, angle, rings)
    return _spatial_turns(o * angle, rings), o


def _temporal_vm(axis, angle, rings: Rings):
    phi0, o0 = _spatial_vm(axis[..., :1], angle[:, :1], rings)
    free = jnp.zeros_like(rings.is_root)

    def frame(carry, x):
        o_prev, u_prev = carry
        ax, an, ax_prev, an_prev = (a[..., None] for a in x)
        s_time = _pair_signs(ax, an, ax_prev, an_prev)
        o = jnp.where(s_time == 0, 1.0, s_time).astype(an.dtype) * o_prev
        o = _improve_orientation(o, _ring_signs(ax, an, rings), rings, free, s_time=s_time, o_prev=o_prev)
        phi = o * an
        r = _improve_turns(phi, jnp.round((u_prev - phi) / TWO_PI), rings, free, u_prev=u_prev)
        u = phi + TWO_PI * r
        return (o, u), (u[:, 0], o[:, 0])

    xs = (jnp.moveaxis(axis[:, :, 1:], 2, 0), angle[:, 1:].T, jnp.moveaxis(axis[:, :, :-1], 2, 0), angle[:, :-1].T)
    _, (phis, os_) = jax.lax.scan(frame, (o0, phi0), xs)
    return jnp.concatenate([phi0, phis.T], axis=1), jnp.concatenate([o0, os_.T], axis=1)


@jax.jit
def spatial_jax(axis, angle, rings: Rings):
    """Spatially consistent angles and orientations, each frame on its own, gauge fixed at the roots.

    **Arguments:**

    - `axis`: unit axes `(N, V, 3)`.
    - `angle`: angles `(N, V)` in [0, pi].
    - `rings`: the graph's :class:`Rings`.

    **Returns:**

    `(phi, o)`, both `(N, V)`.
    """
    phi, o = _spatial_vm(jnp.moveaxis(axis, (0, 1, 2), (2, 1, 0)), angle.T, rings)
    return phi.T, o.T


@jax.jit
def temporal_jax(axis, angle, rings: Rings):
    """TS-ACAP angles and orientations: frame 0 as in :func:`spatial_jax`; later frames also agree with their
    predecessor.

    **Arguments:**

    - `axis`: unit axes `(N, V, 3)`, frames in order.
    - `angle`: angles `(N, V)` in [0, pi].
    - `rings`: the graph's :class:`Rings`.

    **Returns:**

    `(phi, o)`, both `(N, V)`.
    """
    phi, o = _temporal_vm(jnp.moveaxis(axis, (0, 1, 2), (2, 1, 0)), angle.T, rings)
    return phi.T, o.T


def consistent_vectors(v: Float[Array, "n v 3"], g: Graph, mode: Consistency | None) -> Float[Array, "n v 3"]:
    """Consistent axis-angle vectors (phi * o) * axis from raw ones.

    **Arguments:**

    - `v`: raw axis-angle vectors `(N, V, 3)` with angles in [0, pi].
    - `g`: the :class:`Graph`.
    - `mode`: "spatial", "temporal", or "none"/None (returns `v`).

    **Returns:**

    Consistent vectors `(N, V, 3)`, a jnp array.

    **Raises:**

    `ValueError` for an unknown mode.
    """
    if mode in ("none", None):
        return v
    if mode not in ("spatial", "temporal"):
        raise ValueError(f"unknown consistency '{mode}'; expected 'spatial', 'temporal' or 'none'.")
    out = consistent_cm(jnp.moveaxis(v, (0, 1, 2), (2, 1, 0)), g.rings, mode)
    return jnp.moveaxis(out, (0, 1, 2), (2, 1, 0))


def _axis_angle_cm(v):
    sq = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    angle = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)
    return v / jnp.where(angle > 0, angle, 1.0), angle


# The spatial solve runs as separately jitted stages: compiled as one program, XLA on CPU chose layouts and
# fusions that made it several times slower than its parts.


@jax.jit
def _orientation_start(v, rings: Rings):
    """Axes, angles, tree-product orientations and the one-ring signs of raw vectors (3, V, N)."""
    axis, angle = _axis_angle_cm(v)
    return axis, angle, _tree_orientation(axis, angle, rings), _ring_signs(axis, angle, rings)


@jax.jit
def _orientation_sweeps(o, s_ring, rings: Rings):
    return _improve_orientation(o, s_ring, rings, fixed=rings.is_root)


@jax.jit
def _turns_start(o, angle, rings: Rings):
    phi = o * angle
    return phi, _tree_turns(phi, rings)


@jax.jit
def _turns_sweeps(phi, r, rings: Rings):
    return _improve_turns(phi, r, rings, fixed=rings.is_root)


def _with_turns(v, turns):
    """v + turns * axis(v): the raw vectors v (3, V, N) moved by ``turns`` (V, N) radians along their own
    axes. Differentiable in v (exactly v's derivative where turns = 0); ``turns`` is a constant."""
    if turns is None:
        return v
    axis, _ = _axis_angle_cm(v)
    return v + turns * axis


@jax.jit
def _vectors(v, r, o):
    # (o theta + 2 pi r) o w = theta w + 2 pi r o w, as o^2 = 1: the orientation acts only through the turns
    return _with_turns(v, TWO_PI * jax.lax.stop_gradient(r * o))


@jax.jit
def _temporal_cm(v, rings: Rings):
    axis, angle = _axis_angle_cm(jax.lax.stop_gradient(v))
    phi, o = _temporal_vm(axis, angle, rings)
    r = jnp.round((phi - o * angle) / TWO_PI)
    return _with_turns(v, TWO_PI * jax.lax.stop_gradient(r * o))


def consistent_cm(v: Float[Array, "3 v n"], rings: Rings, mode: str) -> Float[Array, "3 v n"]:
    """:func:`consistent_vectors` in the component-major, vertex-major layout (jitted stages).

    **Arguments:**

    - `v`: raw axis-angle vectors `(3, V, N)`.
    - `rings`: the graph's :class:`Rings`.
    - `mode`: "spatial" or "temporal".

    **Returns:**

    Consistent vectors `(3, V, N)`. Traces under jit, vmap, grad and jvp: the integer choices (orientations,
    turns) are made on `stop_gradient(v)`, so the derivative holds them fixed and equals v's own where no turn
    is added.

    **Raises:**

    `ValueError` for an unknown mode.
    """
    if mode == "temporal":
        return _temporal_cm(v, rings)
    if mode != "spatial":
        raise ValueError(f"unknown consistency '{mode}'; expected 'spatial' or 'temporal'.")
    _, angle, o, s_ring = _orientation_start(jax.lax.stop_gradient(v), rings)
    o = _orientation_sweeps(o, s_ring, rings)
    phi, r = _turns_start(o, angle, rings)
    return _vectors(v, _turns_sweeps(phi, r, rings), o)


#: the jitted stages of :func:`consistent_cm` (tests check that none retraces)
STAGES = (_orientation_start, _orientation_sweeps, _turns_start, _turns_sweeps, _vectors, _temporal_cm)


# ------------------------------------------------------------------------------ numpy-facing wrappers


def edge_signs(axis: np.ndarray, angle: np.ndarray, i: np.ndarray | slice, j: np.ndarray | slice) -> np.ndarray:
    """The edge signs s of eq. (3) of seed 002.

    **Arguments:**

    - `axis`: unit axes `(..., V, 3)`.
    - `angle`: angles `(..., V)`.
    - `i`, `j`: index arrays or slices along the vertex axis.

    **Returns:**

    Signs in {-1, 0, 1} between the (i) and (j) vertices: 0 where the axes are near-orthogonal or an angle
    is near 0.
    """
    d = np.sum(axis[..., i, :] * axis[..., j, :], axis=-1)
    ok = (np.abs(d) > EPS_DOT) & (angle[..., i] >= EPS_ANGLE) & (angle[..., j] >= EPS_ANGLE)
    return np.where(ok, np.sign(d), 0.0)


def orientation_energy(o: np.ndarray, s_edge: np.ndarray, g: Graph) -> np.ndarray | float:
    """The orientation objective sum_E o_i o_j s_ij (larger is more consistent).

    **Arguments:**

    - `o`: orientations `(..., V)`.
    - `s_edge`: edge signs `(..., E)`.
    - `g`: the :class:`Graph`.

    **Returns:**

    The energy per frame `(...)`.
    """
    return np.sum(o[..., g.edges[:, 0]] * o[..., g.edges[:, 1]] * s_edge, axis=-1)


def turn_energy(u: np.ndarray, g: Graph) -> np.ndarray | float:
    """The turn objective sum_E (u_i - u_j)^2.

    **Arguments:**

    - `u`: angles `(..., V)`.
    - `g`: the :class:`Graph`.

    **Returns:**

    The energy per frame `(...)`.
    """
    return np.sum((u[..., g.edges[:, 0]] - u[..., g.edges[:, 1]]) ** 2, axis=-1)


def spatial(axis: np.ndarray, angle: np.ndarray, g: Graph) -> tuple[np.ndarray, np.ndarray]:
    """Consistent angles and orientations, each frame on its own (numpy in and out).

    **Arguments:**

    - `axis`: unit axes `(N, V, 3)`.
    - `angle`: angles `(N, V)` in [0, pi].
    - `g`: the :class:`Graph`.

    **Returns:**

    `(phi, o)`, both `(N, V)`; the consistent axis-angle vector of vertex i is `phi_i * o_i * axis_i`.
    """
    phi, o = spatial_jax(jnp.asarray(axis), jnp.asarray(angle), g.rings)
    return np.asarray(phi), np.asarray(o)


_spatial_turns_jit = jax.jit(_spatial_turns)


def spatial_turns(phi: np.ndarray, g: Graph) -> np.ndarray:
    """Stage 2 of :func:`spatial`: integer turns made consistent.

    **Arguments:**

    - `phi`: signed angles `(N, V)`.
    - `g`: the :class:`Graph`.

    **Returns:**

    phi + 2 pi r, `(N, V)`.
    """
    return np.asarray(_spatial_turns_jit(jnp.asarray(phi).T, g.rings)).T


def temporal(axis: np.ndarray, angle: np.ndarray, g: Graph) -> tuple[np.ndarray, np.ndarray]:
    """TS-ACAP angles and orientations: frame 0 as in :func:`spatial`, each later frame also agrees with its
    predecessor (numpy in and out).

    **Arguments:**

    - `axis`: unit axes `(N, V, 3)`, frames in order.
    - `angle`: angles `(N, V)` in [0, pi].
    - `g`: the :class:`Graph`.

    **Returns:**

    `(phi, o)`, both `(N, V)`.
    """
    phi, o = temporal_jax(jnp.asarray(axis), jnp.asarray(angle), g.rings)
    return np.asarray(phi), np.asarray(o)


def consistent_angles(
    axis: np.ndarray, angle: np.ndarray, g: Graph, mode: Consistency
) -> tuple[np.ndarray, np.ndarray]:
    """Consistent angles and orientations for a mode.

    **Arguments:**

    - `axis`: unit axes `(N, V, 3)`.
    - `angle`: angles `(N, V)` in [0, pi].
    - `g`: the :class:`Graph`.
    - `mode`: "spatial", "temporal" or "none"/None (phi = angle, o = 1).

    **Returns:**

    `(phi, o)`, both `(N, V)`.

    **Raises:**

    `ValueError` for an unknown mode.
    """
    if mode == "spatial":
        return spatial(axis, angle, g)
    if mode == "temporal":
        return temporal(axis, angle, g)
    if mode in ("none", None):
        return angle.copy(), np.ones_like(angle)
    raise ValueError(f"unknown consistency '{mode}'; expected 'spatial', 'temporal' or 'none'.")


# --------------------------------------------------------------------------------------------------
# Exact reference for small meshes (one frame)
# --------------------------------------------------------------------------------------------------


def milp_orientation(axis: np.ndarray, angle: np.ndarray, g: Graph) -> np.ndarray:
    """Exact maximizer of sum_E o_i o_j s_ij with o = +1 at each component root (scipy.optimize.milp).

    **Arguments:**

    - `axis`: unit axes `(V, 3)` of one frame.
    - `angle`: angles `(V,)`.
    - `g`: the :class:`Graph`.

    **Returns:**

    Orientations `(V,)` in {-1, 1}.

    **Raises:**

    `RuntimeError` when the MILP fails.
    """
    from scipy.optimize import Bounds, LinearConstraint, milp

    s = edge_signs(axis, angle, g.edges[:, 0], g.edges[:, 1])
    act = np.flatnonzero(s != 0)
    i, j, sa = g.edges[act, 0], g.edges[act, 1], s[act]
    n, m = g.n, act.size
    # variables: x (n, binary; o = 2x - 1), z (m, binary; z = x_i xor x_j). maximize sum s (1 - 2z).
    c = np.r_[np.zeros(n), 2.0 * sa]
    rows, cols, vals, lo, hi = [], [], [], [], []
    k = 0
    pos, neg = np.flatnonzero(sa > 0), np.flatnonzero(sa < 0)
    for a, b in ((1.0, -1.0), (-1.0, 1.0)):  # z >= x_i - x_j and z >= x_j - x_i where s > 0
        e = pos
        cnt = e.size
        r = k + np.arange(cnt)
        rows += [r, r, r]
        cols += [n + e, i[e], j[e]]
        vals += [np.ones(cnt), -a * np.ones(cnt), -b * np.ones(cnt)]
        lo.append(np.zeros(cnt))
        hi.append(np.full(cnt, np.inf))
        k += cnt
    for sign in (+1.0, -1.0):  # z <= x_i + x_j ; z <= 2 - x_i - x_j
        e = neg
        cnt = e.size
        r = k + np.arange(cnt)
        rows += [r, r, r]
        cols += [n + e, i[e], j[e]]
        vals += [np.ones(cnt), -sign * np.ones(cnt), -sign * np.ones(cnt)]
        lo.append(np.full(cnt, -np.inf))
        hi.append(np.zeros(cnt) if sign > 0 else np.full(cnt, 2.0))
        k += cnt
    a_mat = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(k, n + m))
    lb = np.zeros(n + m)
    ub = np.ones(n + m)
    lb[g.roots] = 1.0
    res = milp(
        c,
        constraints=[LinearConstraint(a_mat, np.concatenate(lo), np.concatenate(hi))],
        integrality=np.ones(n + m),
        bounds=Bounds(lb, ub),
    )
    if not res.success:
        raise RuntimeError(f"milp orientation failed: {res.message}")
    return 2.0 * np.rint(res.x[:n]) - 1.0


def milp_turns(phi: np.ndarray, g: Graph) -> np.ndarray:
    """Exact integer turns r minimizing sum_E (phi_i + 2 pi r_i - phi_j - 2 pi r_j)^2, r = 0 at roots.

    **Arguments:**

    - `phi`: signed angles `(V,)` of one frame.
    - `g`: the :class:`Graph`.

    **Returns:**

    Integer-valued turns `(V,)` (float array).

    **Raises:**

    `RuntimeError` when the MILP fails.
    """
    from scipy.optimize import Bounds, LinearConstraint, milp

    n, e = g.n, g.edges.shape[0]
    i, j = g.edges[:, 0], g.edges[:, 1]
    cdiff = phi[i] - phi[j]
    gap = MILP_MAX_TURN_GAP
    ks = np.arange(-gap, gap)  # secants between k and k+1 of f(k) = (c + 2 pi k)^2
    rows, cols, vals, lo = [], [], [], []
    k0 = 0
    for kk in ks:
        fk = (cdiff + TWO_PI * kk) ** 2
        fk1 = (cdiff + TWO_PI * (kk + 1)) ** 2
        slope = fk1 - fk
        r = k0 + np.arange(e)
        # t_e - slope (r_i - r_j) >= fk - slope * kk
        rows += [r, r, r]
        cols += [n + np.arange(e), i, j]
        vals += [np.ones(e), -slope, slope]
        lo.append(fk - slope * kk)
        k0 += e
    a_mat = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(k0, n + e))
    d_rows = np.arange(e)
    d_mat = sp.csr_matrix((np.r_[np.ones(e), -np.ones(e)], (np.r_[d_rows, d_rows], np.r_[i, j])), shape=(e, n + e))
    lb = np.r_[np.full(n, -10.0), np.zeros(e)]
    ub = np.r_[np.full(n, 10.0), np.full(e, np.inf)]
    lb[g.roots] = ub[g.roots] = 0.0
    res = milp(
        np.r_[np.zeros(n), np.ones(e)],
        constraints=[LinearConstraint(a_mat, np.concatenate(lo), np.inf), LinearConstraint(d_mat, -gap, gap)],
        integrality=np.r_[np.ones(n), np.zeros(e)],
        bounds=Bounds(lb, ub),
    )
    if not res.success:
        raise RuntimeError(f"milp turns failed: {res.message}")
    return np.rint(res.x[:n])


def milp_spatial(axis: np.ndarray, angle: np.ndarray, g: Graph) -> tuple[np.ndarray, np.ndarray]:
    """Exact two-stage (orientation, then turns) solution for one frame.

    **Arguments:**

    - `axis`: unit axes `(V, 3)`.
    - `angle`: angles `(V,)`.
    - `g`: the :class:`Graph`.

    **Returns:**

    `(phi, o)`, both `(V,)`.

    **Raises:**

    `RuntimeError` when a MILP fails.
    """
    o = milp_orientation(axis, angle, g)
    phi = o * angle
    return phi + TWO_PI * milp_turns(phi, g), o


# --------------------------------------------------------------------------------------------------
# Consistency across shapes
# --------------------------------------------------------------------------------------------------
# The solves above make each shape (or each frame given its predecessor) consistent on its own, with the gauge
# fixed at the root. Two shapes whose region turns by nearly pi can still end on different branches there: the
# same physical rotation is theta w in one and (theta - 2 pi) w in the other (a jump of 2 pi in the features).
# On horse-gallop, relative to frame 0, 0.1 % of the vertex rotations of the 48 frames sit on a branch other
# than the one nearest the mean of the every-10th training shapes, all in the lower legs, and that costs a
# linear model on the features a third of its accuracy on the unseen frames (benchmarks in the README).


@jax.jit
def align_turns(v: Float[Array, "... v 3"], reference: Float[Array, "v 3"]) -> Float[Array, "... v 3"]:
    """Per vertex, the axis-angle vector of the same rotation, (theta + 2 pi k) w, nearest to a reference.

    ||(theta + 2 pi k) w - ref||^2 is a parabola in t = theta + 2 pi k with its minimum at t = w . ref, so
    k = round((w . ref - theta) / 2 pi).

    **Arguments:**

    - `v`: axis-angle vectors `(..., V, 3)`.
    - `reference`: reference vectors `(V, 3)`.

    **Returns:**

    Vectors `(..., V, 3)` of the same rotations. Vectors of zero angle (no axis) are left as they are.
    """
    sq = jnp.sum(v * v, axis=-1, keepdims=True)
    angle = jnp.sqrt(jnp.where(sq > 0, sq, 1.0))
    axis = v / angle
    k = jnp.round((jnp.sum(axis * reference, axis=-1, keepdims=True) - angle) / TWO_PI)
    return jnp.where(sq > 0, v + (TWO_PI * k) * axis, v)


@jax.jit
def turn_reference(v: Float[Array, "n v 3"], max_iterations: int = 20) -> Float[Array, "v 3"]:
    """A per-vertex reference for :func:`align_turns` from a set of shapes.

    **Arguments:**

    - `v`: axis-angle vectors `(N, V, 3)` of the shapes.
    - `max_iterations`: the most alignment rounds.

    **Returns:**

    The reference `(V, 3)`: the mean of the vectors, each shape aligned to the mean in turn, repeated until no
    vector changes branch (at most `max_iterations` times).
    """

    def cond(state):
        _, changed, it = state
        return changed & (it < max_iterations)

    def body(state):
        ref, _, it = state
        a = align_turns(v, ref)
        new = jnp.mean(a, axis=0)
        return new, jnp.any(jnp.abs(new - ref) > 0), it + 1

    ref0 = jnp.mean(v, axis=0)
    ref, _, _ = jax.lax.while_loop(cond, body, (ref0, jnp.array(True), jnp.array(0)))
    return ref
