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

The reference-side quantities are computed once in :class:`RestFrame`; per-frame work is a gather and an
einsum over the padded one-rings, batched over frames.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxdeform.acap.rotations import inv3
from jaxdeform.mesh.geometry import cotangent_weights, safe_norm, vertex_normals
from jaxdeform.mesh.topology import Topology

Weighting = Literal["official", "cotangent"]
NORMAL_ROW_SCALE = 0.3
OFFICIAL_EXPONENT = 0.25


def sexp(x: Array) -> Array:
    """The official positive weight map: e^x for x <= 0, 1 + x above; non-finite or > 1e5 -> 1."""
    y = jnp.where(x <= 0, jnp.exp(jnp.minimum(x, 0.0)), 1.0 + x)
    return jnp.where(jnp.isfinite(y) & (y <= 1e5), y, 1.0)


def edge_weights(rest: Float[Array, "v 3"], topo: Topology, weighting: Weighting = "official") -> Float[Array, " e"]:
    c = cotangent_weights(rest, topo)
    if weighting == "official":
        return sexp(c) ** OFFICIAL_EXPONENT
    if weighting == "cotangent":
        return jnp.where(jnp.isfinite(c), c, 0.0)
    raise ValueError(f"unknown weighting '{weighting}'; expected 'official' or 'cotangent'.")


def _ring_vectors(x: Float[Array, "... v 3"], topo: Topology) -> Float[Array, "... v k 3"]:
    """e_ik = x_i - x_{neighbor k} on the padded one-rings (padding gives zero vectors)."""
    return x[..., :, None, :] - x[..., topo.neighbors, :]


def _normal_rows(x: Float[Array, "... v 3"], topo: Topology) -> Float[Array, "... v 3"]:
    """s_i n_i: unit vertex normal times 0.3 times the mean one-ring edge length."""
    e = _ring_vectors(x, topo)
    length = safe_norm(e)  # padding slots are zero vectors: keep their gradient finite
    mean_len = jnp.sum(jnp.where(topo.mask, length, 0.0), axis=-1) / topo.degree
    if x.ndim == 2:
        n = vertex_normals(x, topo)
    else:
        n = jax.vmap(vertex_normals, in_axes=(0, None))(x.reshape(-1, *x.shape[-2:]), topo).reshape(x.shape)
    return NORMAL_ROW_SCALE * mean_len[..., None] * n


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RestFrame:
    """Reference-side quantities of the local fits, computed once per (reference, connectivity)."""

    topo: Topology
    weights: Float[Array, " e"]  # per undirected edge
    ring_weights: Float[Array, "v k"]  # w on the padded one-rings (0 on padding)
    ring_edges: Float[Array, "v k 3"]  # reference e_ik
    normal_row: Float[Array, "v 3"]  # s_i n_i on the reference
    inv_b: Float[Array, "v 3 3"]  # (sum w e e^T + s^2 n n^T)^-1


def rest_frame(rest: Float[Array, "v 3"], topo: Topology, weighting: Weighting = "official") -> RestFrame:
    rest = jnp.asarray(rest)
    w = edge_weights(rest, topo, weighting)
    # Weight of the half-edge i -> neighbors[i, k]: look up the undirected edge.
    ring_w = jnp.zeros(topo.mask.shape, rest.dtype)
    slot = jnp.arange(topo.n_half_edges) - jnp.cumsum(topo.degree)[topo.half_src] + topo.degree[topo.half_src]
    ring_w = ring_w.at[topo.half_src, slot].set(w[topo.half_edge])
    e = _ring_vectors(rest, topo)
    nrow = _normal_rows(rest, topo)
    b = jnp.einsum("vk,vka,vkb->vab", ring_w, e, e) + nrow[:, :, None] * nrow[:, None, :]
    # A tiny relative ridge keeps pathological one-rings (all faces degenerate) invertible.
    tr = jnp.trace(b, axis1=-2, axis2=-1)
    b = b + (1e-12 * tr)[:, None, None] * jnp.eye(3, dtype=rest.dtype)
    return RestFrame(topo=topo, weights=w, ring_weights=ring_w, ring_edges=e, normal_row=nrow, inv_b=inv3(b))


def deformation_gradients(frame: RestFrame, vertices: Float[Array, "... v 3"]) -> Float[Array, "... v 3 3"]:
    """T_i for each frame (any leading batch shape) relative to the reference of ``frame``."""
    vertices = jnp.asarray(vertices, dtype=frame.ring_edges.dtype)
    e_def = _ring_vectors(vertices, frame.topo)
    nrow_def = _normal_rows(vertices, frame.topo)
    a = jnp.einsum("vk,...vka,vkb->...vab", frame.ring_weights, e_def, frame.ring_edges)
    a = a + nrow_def[..., :, None] * frame.normal_row[:, None, :]
    return a @ frame.inv_b
