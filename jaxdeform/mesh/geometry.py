"""Differentiable per-mesh geometry on a fixed :class:`Topology`: cotangents, areas, normals, Laplacian.

All functions are pure jnp, work in float32 and float64 (the dtype of ``vertices``), and use segment sums
over the static-size index arrays of the topology (no Python loops over elements).

Degenerate (zero-area) faces: their corner cotangents are defined as 0 (the face adds nothing to the
cotangent weights) instead of +-inf, so weights stay finite; normals of such faces are zero vectors.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxdeform.mesh.topology import Topology
from jaxdeform.typing import Int

#: A face whose doubled area is below this fraction of its squared longest edge counts as degenerate.
DEGENERATE_RELATIVE_AREA = 1e-10


def safe_norm(x: ArrayLike, axis: int = -1, keepdims: bool = False) -> Array:
    """Norm with value 0 and a finite (zero) gradient at zero vectors.

    **Arguments:**

    - `x`: an array.
    - `axis`: the axis to reduce.
    - `keepdims`: keep the reduced axis.

    **Returns:**

    |x| along `axis`.
    """
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    ok = sq > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def safe_normalize(x: ArrayLike, axis: int = -1) -> Array:
    """x / |x| with 0 for zero vectors and finite gradients everywhere.

    **Arguments:**

    - `x`: an array.
    - `axis`: the vector axis.

    **Returns:**

    An array of x's shape.
    """
    n = safe_norm(x, axis=axis, keepdims=True)
    return x / jnp.where(n > 0, n, 1.0)


def zero_area_faces(vertices: Float[ArrayLike, "v 3"], faces: Int[ArrayLike, "f 3"]) -> Int[np.ndarray, " bad"]:
    """The faces whose area is zero relative to their longest edge (host numpy, float64).

    **Arguments:**

    - `vertices`: positions `(V, 3)`.
    - `faces`: triangles `(F, 3)`.

    **Returns:**

    Their indices: the faces :func:`corner_cotangents` gives no cotangent.
    """
    p = np.asarray(vertices, np.float64)[np.asarray(faces)]
    u = np.roll(p, -1, axis=1) - p
    cross = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=-1)
    longest = np.max(np.sum(u * u, axis=-1), axis=1)
    return np.flatnonzero(cross <= DEGENERATE_RELATIVE_AREA * longest)


def face_cross(vertices: Float[ArrayLike, "v 3"], faces: Int[ArrayLike, "f 3"]) -> Float[Array, "f 3"]:
    """The face cross products (p1 - p0) x (p2 - p0).

    **Arguments:**

    - `vertices`: positions `(V, 3)`, float32 or float64 (the result's dtype).
    - `faces`: triangles `(F, 3)`.

    **Returns:**

    `(F, 3)`: normal direction with length twice the face area.
    """
    p = vertices[faces]
    return jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def face_areas(vertices: Float[ArrayLike, "v 3"], topo: Topology) -> Float[Array, " f"]:
    """Face areas.

    **Arguments:**

    - `vertices`: positions `(V, 3)`, float32 or float64 (the result's dtype).
    - `topo`: the mesh :class:`Topology`.

    **Returns:**

    Areas `(F,)`; differentiable.
    """
    return 0.5 * safe_norm(face_cross(vertices, topo.faces))


def face_normals(vertices: Float[ArrayLike, "v 3"], topo: Topology) -> Float[Array, "f 3"]:
    """Unit face normals.

    **Arguments:**

    - `vertices`: positions `(V, 3)`, float32 or float64 (the result's dtype).
    - `topo`: the mesh :class:`Topology`.

    **Returns:**

    Normals `(F, 3)`; zero vectors for degenerate faces.
    """
    return safe_normalize(face_cross(vertices, topo.faces))


def vertex_normals(vertices: Float[ArrayLike, "v 3"], topo: Topology) -> Float[Array, "v 3"]:
    """Area-weighted vertex normals.

    **Arguments:**

    - `vertices`: positions `(V, 3)`, float32 or float64 (the result's dtype).
    - `topo`: the mesh :class:`Topology`.

    **Returns:**

    Normals `(V, 3)`, unit length; zero only if every incident face is degenerate.
    """
    cross = face_cross(vertices, topo.faces)
    acc = jax.ops.segment_sum(jnp.repeat(cross, 3, axis=0), topo.faces.reshape(-1), topo.n_vertices)
    return safe_normalize(acc)


def corner_cotangents(vertices: Float[ArrayLike, "v 3"], topo: Topology) -> Float[Array, "f 3"]:
    """The cotangent of the angle at each corner k of each face.

    **Arguments:**

    - `vertices`: positions `(V, 3)`, float32 or float64 (the result's dtype).
    - `topo`: the mesh :class:`Topology`.

    **Returns:**

    Cotangents `(F, 3)`; 0 for degenerate faces.
    """
    p = vertices[topo.faces]
    u = jnp.roll(p, -1, axis=1) - p  # p[k+1] - p[k]
    w = jnp.roll(p, -2, axis=1) - p  # p[k+2] - p[k]
    dot = jnp.sum(u * w, axis=-1)
    cross = safe_norm(jnp.cross(u, w))
    longest = jnp.max(jnp.sum(u * u, axis=-1), axis=1, keepdims=True)
    ok = cross > DEGENERATE_RELATIVE_AREA * longest
    return jnp.where(ok, dot / jnp.where(ok, cross, 1.0), 0.0)


def cotangent_weights(vertices: Float[ArrayLike, "v 3"], topo: Topology) -> Float[Array, " e"]:
    """Cotangent weights c_ij = (cot a + cot b) / 2 per undirected edge.

    **Arguments:**

    - `vertices`: positions `(V, 3)`, float32 or float64 (the result's dtype).
    - `topo`: the mesh :class:`Topology`.

    **Returns:**

    Weights `(E,)` (one term on boundary edges); finite, differentiable.
    """
    cot = corner_cotangents(vertices, topo)
    return jax.ops.segment_sum(0.5 * cot.reshape(-1), topo.face_edge.reshape(-1), topo.n_edges)


def laplacian_coo(
    topo: Topology, weights: Float[ArrayLike, " e"]
) -> tuple[Int[np.ndarray, " nnz"], Int[np.ndarray, " nnz"], Float[Array, " nnz"]]:
    """Graph Laplacian L = D - W (positive semidefinite) in COO form.

    `(L p)_i = sum_j w_ij (p_i - p_j)`; with cotangent weights this is the negated libigl `cotmatrix`.

    **Arguments:**

    - `topo`: the mesh :class:`Topology`.
    - `weights`: edge weights `(E,)`.

    **Returns:**

    `(rows, cols, vals)`: row/col index arrays are numpy (host), values follow `weights`.
    """
    e = np.asarray(topo.edges)
    n = topo.n_vertices
    rows = np.concatenate([e[:, 0], e[:, 1], np.arange(n)])
    cols = np.concatenate([e[:, 1], e[:, 0], np.arange(n)])
    diag = jax.ops.segment_sum(
        jnp.concatenate([weights, weights]), jnp.concatenate([topo.edges[:, 0], topo.edges[:, 1]]), n
    )
    vals = jnp.concatenate([-weights, -weights, diag])
    return rows, cols, vals


def cot_laplacian(vertices: Float[ArrayLike, "v 3"], topo: Topology):
    """Cotangent Laplacian (PSD convention) on the host.

    **Arguments:**

    - `vertices`: positions `(V, 3)`, float32 or float64 (the result's dtype).
    - `topo`: the mesh :class:`Topology`.

    **Returns:**

    A `scipy.sparse.csr_matrix` `(V, V)`.
    """
    import scipy.sparse as sp

    rows, cols, vals = laplacian_coo(topo, cotangent_weights(vertices, topo))
    n = topo.n_vertices
    return sp.csr_matrix((np.asarray(vals), (rows, cols)), shape=(n, n))


def bounding_box_diagonal(vertices) -> float:
    """The length of the axis-aligned bounding box's diagonal.

    **Arguments:**

    - `vertices`: positions `(..., 3)`.

    **Returns:**

    A Python float.
    """
    v = np.asarray(vertices).reshape(-1, 3)
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
