"""Per-vertex deformation gradients T_i from cot-weighted one-rings (Gao et al. 2019, eq. (1) of seed 002).

T_i = argmin_T  sum_j w_ij |e'_ij - T e_ij|^2  +  |s'_i n'_i - T s_i n_i|^2
    = (sum_j w_ij e'_ij e_ij^T + s'_i s_i n'_i n_i^T) (sum_j w_ij e_ij e_ij^T + s_i^2 n_i n_i^T)^-1

with e_ij = q_i - q_j on the reference, e'_ij = p_i - p_j on the deformed mesh, n the unit vertex normal and
s = 0.3 * (mean one-ring edge length) of each mesh separately (the official "normal row", which keeps
flat one-rings well posed).

Weighting (``weighting=``):
- ``"official"`` (default): w_ij = sexp(c_ij)^(1/4) multiplies the squared residual, with
  c_ij = (cot a + cot b)/2 on the reference and sexp(x) = e^x for x <= 0, 1 + x otherwise (a non-finite
  value or one above 1e5 becomes 1). Always positive. The exponent is calibrated on the official outputs
  in ../shared/data/acap-bar: with w = sexp(c) the 99th percentile of |S - S_GT| is 1.37e-2 (rotations
  8.6e-3), with sqrt(sexp(c)) 4.5e-3 (2.7e-3), with sexp(c)^(1/4) 1.05e-3 (7.0e-4), uniform weights
  4.1e-3 (3.1e-3); two builds of the official code differ by 4.5e-3.
- ``"cotangent"``: plain w_ij = c_ij. Negative on obtuse triangles, so the local fit can be indefinite on
  bad meshes; offered for comparison with papers that use plain cotangent weights.
Degenerate reference faces contribute no cotangent (see ``jaxdeform.mesh.geometry``), so weights and
features stay finite.

The reference-side quantities are computed once in :class:`RestFrame`; per-frame work is one pass over the
one-rings (slot by slot, see :class:`RingPlan`), batched over frames.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxdeform.acap.rotations import cross_cm, inv3
from jaxdeform.mesh.geometry import cotangent_weights
from jaxdeform.mesh.topology import Topology

Weighting = Literal["official", "cotangent"]
NORMAL_ROW_SCALE = 0.3
OFFICIAL_EXPONENT = 0.25


SEXP_FLOOR = -30.0  # the official weight map's smallest exponent: e^-30 ~ 1e-13, a normal float32


def sexp(x: Array) -> Array:
    """The official positive weight map.

    **Arguments:**

    - `x`: an array of any shape.

    **Returns:**

    e^x for x <= 0 (x held at -30 or above, so that a near-flat triangle's huge negative cotangent still gives
    a positive weight), 1 + x above; non-finite values or values above 1e5 become 1. Same shape, always positive.
    """
    y = jnp.where(x <= 0, jnp.exp(jnp.clip(x, SEXP_FLOOR, 0.0)), 1.0 + x)
    return jnp.where(jnp.isfinite(y) & (y <= 1e5), y, 1.0)


def edge_weights(
    rest: Float[jax.typing.ArrayLike, "v 3"], topo: Topology, weighting: Weighting = "official"
) -> Float[Array, " e"]:
    """Per-edge weights of the local fits (module docstring).

    **Arguments:**

    - `rest`: reference positions `(V, 3)`.
    - `topo`: the mesh topology.
    - `weighting`: "official" or "cotangent".

    **Returns:**

    Weights `(E,)`, one per undirected edge, finite.

    **Raises:**

    `ValueError` for an unknown weighting.
    """
    c = cotangent_weights(rest, topo)
    if weighting == "official":
        return sexp(c) ** OFFICIAL_EXPONENT
    if weighting == "cotangent":
        return jnp.where(jnp.isfinite(c), c, 0.0)
    raise ValueError(f"unknown weighting '{weighting}'; expected 'official' or 'cotangent'.")


def _vertex_faces(topo: Topology) -> tuple[np.ndarray, np.ndarray]:
    """Padded vertex -> incident faces table (V, L) and its mask (host, once)."""
    f = np.asarray(topo.faces).reshape(-1)
    face = np.repeat(np.arange(topo.n_faces), 3)
    order = np.argsort(f, kind="stable")
    f, face = f[order], face[order]
    count = np.bincount(f, minlength=topo.n_vertices)
    slot = np.arange(f.size) - np.r_[0, np.cumsum(count)[:-1]][f]
    table = np.zeros((topo.n_vertices, int(count.max())), np.int32)
    table[f, slot] = face
    mask = np.zeros(table.shape, bool)
    mask[f, slot] = True
    return table, mask


def _prefix_counts(counts: np.ndarray, slots: int) -> tuple[int, ...]:
    """For counts sorted in descending order: how many leading entries have more than k items, k < slots."""
    return tuple(int(np.count_nonzero(counts > k)) for k in range(slots))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RingPlan:
    """The one-rings laid out for the per-frame kernels (host-built, once per connectivity).

    Vertices are ordered by degree, highest first (``order``: position -> vertex, ``position``: its
    inverse), so that ring slot k concerns a prefix of ``ring_counts[k]`` vertices and the incident-face
    slot l a prefix of ``face_counts[l]``. The kernels then touch each half-edge and each vertex-face pair
    once, instead of padding every vertex to the largest degree (horse: 14 slots, mean degree 6).
    """

    order: Array  # (V,)
    position: Array  # (V,)
    neighbors: Array  # (V, K): one-ring of the vertex at each position (original vertex indices)
    degree: Array  # (V,) at each position
    faces: Array  # (V, L): incident faces at each position
    faces_mask: Array  # (V, L)
    ring_counts: tuple = dataclasses.field(metadata=dict(static=True))
    face_counts: tuple = dataclasses.field(metadata=dict(static=True))


def ring_plan(topo: Topology) -> RingPlan:
    """Lay out the one-rings for the per-frame kernels (host work, once per connectivity).

    **Arguments:**

    - `topo`: the mesh topology.

    **Returns:**

    The :class:`RingPlan`.
    """
    degree = np.asarray(topo.degree)
    order = np.argsort(-degree, kind="stable")
    position = np.empty_like(order)
    position[order] = np.arange(order.size)
    vf, vf_mask = _vertex_faces(topo)
    vf, vf_mask = vf[order], vf_mask[order]
    n_faces = vf_mask.sum(axis=1)
    # faces per vertex are not exactly sorted in degree order (boundary vertices have one fewer):
    # each face slot covers the prefix up to the last vertex that uses it, masked inside
    last = [int(np.flatnonzero(n_faces > k).max()) + 1 for k in range(vf.shape[1])]
    i32 = lambda a: jnp.asarray(a, jnp.int32)  # noqa: E731
    return RingPlan(
        order=i32(order),
        position=i32(position),
        neighbors=i32(np.asarray(topo.neighbors)[order]),
        degree=i32(degree[order]),
        faces=i32(vf),
        faces_mask=jnp.asarray(vf_mask),
        ring_counts=_prefix_counts(degree[order], topo.max_degree),
        face_counts=tuple(last),
    )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RestFrame:
    """Reference-side quantities of the local fits, computed once per (reference, connectivity).

    With B_i = sum_k w_ik e_ik e_ik^T + n_i n_i^T (reference side), the fit is
    T_i = (sum_k w_ik e'_ik e_ik^T + n'_i n_i^T) B_i^-1 = sum_k e'_ik c_ik^T + n'_i cn_i^T
    with the constants c_ik = B_i^-1 w_ik e_ik and cn_i = B_i^-1 n_i, stored component-major ((3, V, K),
    (3, V)) in the vertex order of ``plan`` for the per-frame kernel.
    """

    topo: Topology
    plan: RingPlan
    weights: Float[Array, " e"]  # per undirected edge
    c_ring: Float[Array, "3 v k"]
    c_normal: Float[Array, "3 v"]

    @property
    def dtype(self):
        """The dtype of the reference constants (that of the reference the frame was built from)."""
        return self.c_ring.dtype


def rest_frame(
    rest: Float[jax.typing.ArrayLike, "v 3"], topo: Topology, weighting: Weighting = "official"
) -> RestFrame:
    """Compute the reference-side constants of the local fits.

    **Arguments:**

    - `rest`: reference positions `(V, 3)`; the frame's dtype follows it.
    - `topo`: the mesh topology.
    - `weighting`: "official" or "cotangent".

    **Returns:**

    The :class:`RestFrame`.

    **Raises:**

    `ValueError` for an unknown weighting.
    """
    rest = jnp.asarray(rest)
    if weighting not in ("official", "cotangent"):
        raise ValueError(f"unknown weighting '{weighting}'; expected 'official' or 'cotangent'.")
    plan = ring_plan(topo)
    w, c_ring, c_normal = _rest_constants(rest, topo, plan, weighting)
    return RestFrame(topo=topo, plan=plan, weights=w, c_ring=c_ring, c_normal=c_normal)


@functools.partial(jax.jit, static_argnames=("weighting",))
def _rest_constants(rest, topo: Topology, plan: RingPlan, weighting: Weighting):
    """Edge weights and the fit constants c_ring (3, V, K), c_normal (3, V) (one compiled program: run
    op by op, the per-slot steps make the first call slow)."""
    w = edge_weights(rest, topo, weighting)
    # Weight of the half-edge i -> neighbors[i, k]: look up the undirected edge.
    ring_w = jnp.zeros(topo.mask.shape, rest.dtype)
    slot = jnp.arange(topo.n_half_edges) - jnp.cumsum(topo.degree)[topo.half_src] + topo.degree[topo.half_src]
    ring_w = ring_w.at[topo.half_src, slot].set(w[topo.half_edge])[plan.order]
    e = rest[plan.order][:, None, :] - rest[plan.neighbors]  # (V, K, 3) at plan positions; padding: 0
    _, nrow = _ring_pass(topo, plan, to_vertex_major(rest))
    nrow = nrow[:, :, 0].T  # (V, 3)
    b = jnp.einsum("vk,vka,vkb->vab", ring_w, e, e) + nrow[:, :, None] * nrow[:, None, :]
    # A tiny relative ridge keeps pathological one-rings (all faces degenerate) invertible.
    tr = jnp.trace(b, axis1=-2, axis2=-1)
    b = b + (1e-12 * tr)[:, None, None] * jnp.eye(3, dtype=rest.dtype)
    inv_b = inv3(b)
    return w, jnp.einsum("vab,vk,vkb->avk", inv_b, ring_w, e), jnp.einsum("vab,vb->av", inv_b, nrow)


def _ring_pass(topo: Topology, plan: RingPlan, x: Float[Array, "3 v b"], c_ring=None):
    """One pass over the one-rings of a batch of meshes (3, V, B), in the vertex order of ``plan``.

    Returns sum_k e'_ik c_ik^T (3, 3, V, B) when ``c_ring`` is given (else None) and the normal rows
    s_i n_i (3, V, B): the unit area-weighted vertex normal times 0.3 times the mean one-ring edge length
    (the official "normal row"), for the reference and each frame alike. Slot k updates only the prefix of
    vertices that have a k-th neighbour; components are summed explicitly (XLA on CPU is slow at short
    reductions).
    """
    xp = x[:, plan.order]
    acc = None if c_ring is None else jnp.zeros((3, 3) + xp.shape[1:], x.dtype)
    length = jnp.zeros(xp.shape[1:], x.dtype)
    for k, m in enumerate(plan.ring_counts):
        # edge vectors first (not x_i c0 - sum x_k c_k): no cancellation for meshes far from the origin
        d = xp[:, :m] - x[:, plan.neighbors[:m, k]]
        sq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        length = length.at[:m].add(jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0))
        if acc is not None:
            acc = acc.at[:, :, :m].add(d[:, None] * c_ring[None, :, :m, k, None])
    f = topo.faces
    p0 = x[:, f[:, 0]]
    cross = cross_cm(x[:, f[:, 1]] - p0, x[:, f[:, 2]] - p0)  # (3, F, B): twice the area times the unit normal
    normal = jnp.zeros_like(xp)
    for k, m in enumerate(plan.face_counts):
        normal = normal.at[:, :m].add(jnp.where(plan.faces_mask[:m, k, None], cross[:, plan.faces[:m, k]], 0.0))
    nsq = normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]
    scale = jnp.where(nsq > 0, jax.lax.rsqrt(jnp.where(nsq > 0, nsq, 1.0)), 0.0)
    mean_len = length / plan.degree[:, None].astype(x.dtype)
    return acc, (NORMAL_ROW_SCALE * mean_len * scale) * normal


def deformation_gradients_cm(frame: RestFrame, x: Float[Array, "3 v b"]) -> Float[Array, "3 3 v b"]:
    """Deformation gradients T_i of a batch of meshes, component-major and vertex-major.

    **Arguments:**

    - `frame`: the reference constants.
    - `x`: positions `(3, V, B)`.

    **Returns:**

    T of shape `(3, 3, V, B)`.
    """
    acc, n_def = _ring_pass(frame.topo, frame.plan, x, frame.c_ring)
    t = acc + n_def[:, None] * frame.c_normal[None, :, :, None]
    return t[:, :, frame.plan.position]


def to_vertex_major(vertices: Float[jax.typing.ArrayLike, "... v 3"]) -> Float[Array, "3 v b"]:
    """Flatten meshes into the vertex-major layout.

    **Arguments:**

    - `vertices`: positions `(..., V, 3)`.

    **Returns:**

    Positions `(3, V, B)` with the leading batch dimensions flattened into B.
    """
    v = vertices.shape[-2]
    return jnp.moveaxis(vertices.reshape(-1, v, 3), (0, 2), (2, 0))


def deformation_gradients(
    frame: RestFrame, vertices: Float[jax.typing.ArrayLike, "*batch v 3"]
) -> Float[Array, "*batch v 3 3"]:
    """Deformation gradients T_i of meshes relative to the reference of `frame`.

    **Arguments:**

    - `frame`: the reference constants (:func:`rest_frame`).
    - `vertices`: positions `(..., V, 3)`, cast to the frame's dtype.

    **Returns:**

    T of shape `(..., V, 3, 3)`; differentiable in the vertices.
    """
    vertices = jnp.asarray(vertices, dtype=frame.dtype)
    t = deformation_gradients_cm(frame, to_vertex_major(vertices))  # (3, 3, V, B)
    return jnp.moveaxis(t, (0, 1, 2, 3), (2, 3, 1, 0)).reshape(*vertices.shape[:-1], 3, 3)
