"""Axis/angle consistency of per-vertex rotations (ACAP, Gao et al. 2019) and its temporal variant (TS-ACAP).

A rotation with axis w and angle theta in [0, pi] is also (-w, -theta) and any of theta + 2 pi r. The
consistent representation picks, per vertex, an orientation o_i in {+1, -1} and a number of turns r_i,
giving the axis-angle vector (o_i theta_i + 2 pi r_i) w_i, so that neighbours agree:

1. orientation: maximize  sum_(i,j in E) o_i o_j s_ij  (+ sum_i o_t,i o_t-1,i s_i^time for TS-ACAP), with
   s = 0 where |w_i . w_j| <= EPS_DOT or either angle < EPS_ANGLE, else sign(w_i . w_j);
2. turns: minimize  sum_(i,j in E) (u_i - u_j)^2  (+ sum_i (u_t,i - u_t-1,i)^2), u = o theta + 2 pi r.

Fast path (default, all numpy, vectorized over vertices and frames): a breadth-first tree from the root of
each connected component gives an initial solution by path products (orientation) and path sums (turns)
computed with pointer jumping; then local improvement by Gauss-Seidel sweeps over colour classes of a
greedy graph colouring, each vertex taking its best value given its neighbours, which never increases the
energy and stops when no vertex improves.

Exact path (``method="milp"``, small meshes, one frame): both integer programs through
``scipy.optimize.milp`` (HiGHS): orientation as a max-cut with XOR variables; turns with a piecewise-linear
epigraph of each edge's convex integer cost (exact at integers) under |r_i - r_j| <= MILP_MAX_TURN_GAP.

The gauge is fixed by o = +1 and r = 0 at the root (vertex 0) of each component in a spatial solve; in the
temporal solve of frames after the first the previous frame fixes the gauge and the root is left free.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

EPS_DOT = 1e-2
EPS_ANGLE = 1e-3
TWO_PI = 2.0 * np.pi
MAX_SWEEPS = 100
MILP_MAX_TURN_GAP = 3

Consistency = Literal["spatial", "temporal", "none"]


@dataclasses.dataclass(frozen=True)
class Graph:
    """Host-side graph structures of one connectivity (built once)."""

    n: int
    edges: np.ndarray  # (E, 2)
    adjacency: sp.csr_matrix  # (V, V) 0/1
    degree: np.ndarray  # (V,)
    parent: np.ndarray  # BFS parent, roots point to themselves
    roots: np.ndarray  # (C,) one root per connected component
    colour_classes: tuple[np.ndarray, ...]
    out_edges: sp.csr_matrix  # (V, 2E): 1 at (src_h, h), sums directed-edge values per source vertex
    src: np.ndarray  # (2E,) directed edges
    dst: np.ndarray
    hedge: np.ndarray


def build_graph(edges: np.ndarray, n: int) -> Graph:
    edges = np.asarray(edges, dtype=np.int64)
    e = edges.shape[0]
    adj = sp.coo_matrix((np.ones(2 * e), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    ncomp, labels = csgraph.connected_components(adj, directed=False)
    parent = np.arange(n)
    roots = np.array([np.flatnonzero(labels == c)[0] for c in range(ncomp)])
    for root in roots:
        order, pred = csgraph.breadth_first_order(adj, int(root), directed=False, return_predecessors=True)
        parent[order[1:]] = pred[order[1:]]
    src = np.r_[edges[:, 0], edges[:, 1]]
    dst = np.r_[edges[:, 1], edges[:, 0]]
    hedge = np.r_[np.arange(e), np.arange(e)]
    out_edges = sp.coo_matrix((np.ones(2 * e), (src, np.arange(2 * e))), shape=(n, 2 * e)).tocsr()
    return Graph(
        n=n, edges=edges, adjacency=adj, degree=np.asarray(adj.sum(axis=1)).ravel(), parent=parent, roots=roots,
        colour_classes=_colour_classes(src, dst, n), out_edges=out_edges, src=src, dst=dst, hedge=hedge,
    )


def _colour_classes(src: np.ndarray, dst: np.ndarray, n: int) -> tuple[np.ndarray, ...]:
    """Independent sets covering all vertices (Jones-Plassmann rounds with fixed random priorities)."""
    prio = np.random.default_rng(0).permutation(n)
    uncoloured = np.ones(n, dtype=bool)
    classes = []
    while uncoloured.any():
        nbr = np.full(n, -1)
        live = uncoloured[dst] & uncoloured[src]
        np.maximum.at(nbr, src[live], prio[dst[live]])
        chosen = uncoloured & (prio > nbr)
        classes.append(np.flatnonzero(chosen))
        uncoloured &= ~chosen
    return tuple(classes)


def _jump(rel: np.ndarray, parent: np.ndarray, mul: bool) -> np.ndarray:
    """Combine ``rel`` along each vertex's tree path to its root (pointer jumping).

    Roots must have the identity element in ``rel`` (1 for products, 0 for sums).
    """
    val = rel.copy()
    anc = parent.copy()
    while True:
        val = val * val[..., anc] if mul else val + val[..., anc]
        nxt = anc[anc]
        if np.array_equal(nxt, anc):
            return val
        anc = nxt


def edge_signs(axis: np.ndarray, angle: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """s of eq. (3) of seed 002 between (i) and (j) (index arrays or slices along the vertex axis)."""
    d = np.sum(axis[..., i, :] * axis[..., j, :], axis=-1)
    ok = (np.abs(d) > EPS_DOT) & (angle[..., i] >= EPS_ANGLE) & (angle[..., j] >= EPS_ANGLE)
    return np.where(ok, np.sign(d), 0.0)


def _pair_signs(axis_a, angle_a, axis_b, angle_b) -> np.ndarray:
    d = np.sum(axis_a * axis_b, axis=-1)
    ok = (np.abs(d) > EPS_DOT) & (angle_a >= EPS_ANGLE) & (angle_b >= EPS_ANGLE)
    return np.where(ok, np.sign(d), 0.0)


def orientation_energy(o: np.ndarray, s_edge: np.ndarray, g: Graph) -> np.ndarray:
    return np.sum(o[..., g.edges[:, 0]] * o[..., g.edges[:, 1]] * s_edge, axis=-1)


def turn_energy(u: np.ndarray, g: Graph) -> np.ndarray:
    return np.sum((u[..., g.edges[:, 0]] - u[..., g.edges[:, 1]]) ** 2, axis=-1)


def _neighbour_sum(x: np.ndarray, g: Graph) -> np.ndarray:
    """sum_j x_j over neighbours, for x of shape (N, V)."""
    return np.asarray((g.adjacency @ x.T).T)


def _signed_neighbour_sum(o: np.ndarray, s_edge: np.ndarray, g: Graph) -> np.ndarray:
    """sum_j s_ij o_j for o (N, V), s_edge (N, E)."""
    vals = s_edge[:, g.hedge] * o[:, g.dst]  # (N, 2E)
    return np.asarray((g.out_edges @ vals.T).T)


def _improve_orientation(o, s_edge, g: Graph, s_time=None, o_prev=None, fixed=None):
    """Gauss-Seidel over colour classes: o_i <- sign(sum_j s_ij o_j [+ s_time_i o_prev_i])."""
    for _ in range(MAX_SWEEPS):
        changed = False
        for cls in g.colour_classes:
            field = _signed_neighbour_sum(o, s_edge, g)
            if s_time is not None:
                field += s_time * o_prev
            f = field[:, cls]
            flip = (o[:, cls] * f) < 0
            if fixed is not None:
                flip &= ~fixed[cls]
            if flip.any():
                o[:, cls] = np.where(flip, -o[:, cls], o[:, cls])
                changed = True
        if not changed:
            break
    return o


def _improve_turns(phi, r, g: Graph, u_prev=None, fixed=None):
    """Gauss-Seidel over colour classes: r_i <- argmin over integers of the vertex's quadratic terms."""
    deg = g.degree + (1 if u_prev is not None else 0)
    for _ in range(MAX_SWEEPS):
        changed = False
        for cls in g.colour_classes:
            u = phi + TWO_PI * r
            total = _neighbour_sum(u, g)
            if u_prev is not None:
                total = total + u_prev
            best = np.rint((total[:, cls] / deg[cls] - phi[:, cls]) / TWO_PI)
            cur = r[:, cls]
            # Move only on a strict decrease (ties would let a vertex oscillate between equal choices).
            mean = total[:, cls] / deg[cls]
            gain = (phi[:, cls] + TWO_PI * cur - mean) ** 2 - (phi[:, cls] + TWO_PI * best - mean) ** 2
            move = (best != cur) & (gain > 1e-9)
            if fixed is not None:
                move &= ~fixed[cls]
            if move.any():
                r[:, cls] = np.where(move, best, cur)
                changed = True
        if not changed:
            break
    return r


def spatial(axis: np.ndarray, angle: np.ndarray, g: Graph) -> tuple[np.ndarray, np.ndarray]:
    """Consistent (phi, o) for axes (N, V, 3) and angles (N, V) in [0, pi], each frame on its own.

    The consistent axis-angle vector of vertex i is ``phi_i * o_i * axis_i``.
    """
    roots = np.zeros(g.n, dtype=bool)
    roots[g.roots] = True
    p = g.parent
    # 1. orientation: sign relative to the BFS parent, multiplied along the path to the root.
    rel = _pair_signs(axis, angle, axis[:, p], angle[:, p])
    rel = np.where(rel == 0, 1.0, rel)
    rel[:, roots] = 1.0
    o = _jump(rel, p, mul=True)
    s_edge = edge_signs(axis, angle, g.edges[:, 0], g.edges[:, 1])
    o = _improve_orientation(o, s_edge, g, fixed=roots)
    return spatial_turns(o * angle, g), o


def spatial_turns(phi: np.ndarray, g: Graph) -> np.ndarray:
    """Stage 2 of :func:`spatial`: phi + 2 pi r with the integer turns r made consistent (N, V)."""
    roots = np.zeros(g.n, dtype=bool)
    roots[g.roots] = True
    p = g.parent
    # whole turns relative to the BFS parent, summed along the path to the root, then local improvement
    d = np.rint((phi[:, p] - phi) / TWO_PI)
    d[:, roots] = 0.0
    r = _jump(d, p, mul=False)
    r = _improve_turns(phi, r, g, fixed=roots)
    return phi + TWO_PI * r


def temporal(axis: np.ndarray, angle: np.ndarray, g: Graph) -> tuple[np.ndarray, np.ndarray]:
    """TS-ACAP: frame 0 as in :func:`spatial`; each later frame adds the terms to its previous frame."""
    phi_out = np.empty_like(angle)
    o_out = np.empty_like(angle)
    phi_out[:1], o_out[:1] = spatial(axis[:1], angle[:1], g)
    for t in range(1, axis.shape[0]):  # each frame depends on its predecessor: sequential by nature
        cur = slice(t, t + 1)
        o_prev, u_prev = o_out[t - 1 : t], phi_out[t - 1 : t]
        s_time = _pair_signs(axis[cur], angle[cur], axis[t - 1 : t], angle[t - 1 : t])
        o = np.where(s_time == 0, 1.0, s_time) * o_prev
        s_edge = edge_signs(axis[cur], angle[cur], g.edges[:, 0], g.edges[:, 1])
        o = _improve_orientation(o, s_edge, g, s_time=s_time, o_prev=o_prev)
        phi = o * angle[cur]
        r = np.rint((u_prev - phi) / TWO_PI)
        r = _improve_turns(phi, r, g, u_prev=u_prev)
        phi_out[t], o_out[t] = (phi + TWO_PI * r)[0], o[0]
    return phi_out, o_out


def consistent_angles(axis: np.ndarray, angle: np.ndarray, g: Graph, mode: Consistency) -> tuple[np.ndarray, np.ndarray]:
    """(phi, o) for ``mode`` in spatial / temporal / none (none: phi = angle, o = 1)."""
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
    """Exact maximizer of sum_E o_i o_j s_ij with o = +1 at each component root (scipy.optimize.milp)."""
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
    res = milp(c, constraints=[LinearConstraint(a_mat, np.concatenate(lo), np.concatenate(hi))],
               integrality=np.ones(n + m), bounds=Bounds(lb, ub))
    if not res.success:
        raise RuntimeError(f"milp orientation failed: {res.message}")
    return 2.0 * np.rint(res.x[:n]) - 1.0


def milp_turns(phi: np.ndarray, g: Graph) -> np.ndarray:
    """Exact integer turns r minimizing sum_E (phi_i + 2 pi r_i - phi_j - 2 pi r_j)^2, r = 0 at roots."""
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
    """Exact two-stage solution for one frame: axis (V, 3), angle (V,) -> (phi (V,), o (V,))."""
    o = milp_orientation(axis, angle, g)
    phi = o * angle
    return phi + TWO_PI * milp_turns(phi, g), o
