"""Topology: everything about one connectivity, built once on the host with static sizes.

A :class:`Topology` is a JAX pytree whose array leaves are int32/bool arrays and whose sizes are static
metadata, so jitted functions that take it compile once per connectivity and never retrace.

Conventions
- ``edges`` (E, 2): undirected edges with ``i < j``, sorted lexicographically.
- ``face_edge`` (F, 3): the undirected edge *opposite* corner k of each face, i.e. edge
  (f[k+1], f[k+2]); the cotangent of the angle at corner k belongs to that edge.
- half-edges ``half_src -> half_dst`` (2E,): both directions of every edge, sorted by source, so the
  one-ring of vertex i is the contiguous block ``half_src == i``; ``half_edge`` maps each to its edge.
- ``neighbors`` (V, K) padded one-rings with ``mask`` and ``degree``; padding index is the vertex itself.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool

from jaxdeform.errors import ConnectivityError
from jaxdeform.typing import Int, NonArrayLeaf


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Topology:
    """Everything about one connectivity (module docstring for the conventions), built by :func:`build_topology`."""

    faces: Int[ArrayLike, "f 3"] | NonArrayLeaf
    edges: Int[ArrayLike, "e 2"] | NonArrayLeaf
    face_edge: Int[ArrayLike, "f 3"] | NonArrayLeaf
    half_src: Int[ArrayLike, " h"] | NonArrayLeaf
    half_dst: Int[ArrayLike, " h"] | NonArrayLeaf
    half_edge: Int[ArrayLike, " h"] | NonArrayLeaf
    neighbors: Int[ArrayLike, "v k"] | NonArrayLeaf
    mask: Bool[ArrayLike, "v k"] | NonArrayLeaf
    degree: Int[ArrayLike, " v"] | NonArrayLeaf
    boundary_vertex: Bool[ArrayLike, " v"] | NonArrayLeaf
    n_vertices: int = dataclasses.field(metadata=dict(static=True))
    n_faces: int = dataclasses.field(metadata=dict(static=True))
    n_edges: int = dataclasses.field(metadata=dict(static=True))
    max_degree: int = dataclasses.field(metadata=dict(static=True))

    @property
    def n_half_edges(self) -> int:
        """The number of half-edges, 2E."""
        return 2 * self.n_edges

    def faces_numpy(self) -> np.ndarray:
        """The faces `(F, 3)` as a numpy array."""
        return np.asarray(self.faces)


def unique_edges(faces: Int[ArrayLike, "f 3"]) -> Int[np.ndarray, "e 2"]:
    """Undirected edges of a triangle list (numpy, no checks).

    **Arguments:**

    - `faces`: triangles `(F, 3)`.

    **Returns:**

    Edges `(E, 2)` int64 with `i < j`, sorted lexicographically.
    """
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


class HalfEdgeGroups(NamedTuple):
    """A triangle list's half-edges sorted by their undirected edge (:func:`half_edge_groups`)."""

    key: np.ndarray  # (3F, 2) the undirected edge of each half-edge, i < j, lexicographic order
    he: np.ndarray  # (3F, 2) the half-edges, as their triangles walk them
    opp: np.ndarray  # (3F,) the vertex opposite each half-edge in its triangle
    fid: np.ndarray  # (3F,) the triangle of each half-edge
    starts: np.ndarray  # (E,) the index of each unique edge's first half-edge
    counts: np.ndarray  # (E,) the half-edges (triangles) of each unique edge: 1 on the boundary, 2 inside


def half_edge_groups(faces: Int[ArrayLike, "f 3"]) -> HalfEdgeGroups:
    """The half-edges of a triangle list grouped by undirected edge (numpy, no checks): the unique edges are
    ``key[starts]`` (as :func:`unique_edges`), the triangles of edge ``e`` are ``fid[starts[e]:starts[e] +
    counts[e]]``."""
    f = np.asarray(faces, dtype=np.int64)
    he = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    opp = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    fid = np.tile(np.arange(len(f)), 3)
    key = np.sort(he, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, he, opp, fid = key[order], he[order], opp[order], fid[order]
    first = np.ones(len(key), bool)
    first[1:] = np.any(key[1:] != key[:-1], axis=1)
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, len(key)))
    return HalfEdgeGroups(key, he, opp, fid, starts, counts)


def repeated_vertex_face(faces: Int[ArrayLike, "f 3"]) -> int:
    """Find a face that names one vertex twice.

    **Arguments:**

    - `faces`: triangles `(F, 3)`.

    **Returns:**

    The index of the first such face, or -1 if every face has 3 distinct vertices.
    """
    f = np.asarray(faces)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    return int(np.argmax(repeated)) if repeated.any() else -1


def validate_faces(faces: ArrayLike, n_vertices: int | None = None) -> tuple[Int[np.ndarray, "f 3"], int]:
    """Check faces as every connectivity must pass.

    **Arguments:**

    - `faces`: triangles, a non-empty `(F, 3)` integer array.
    - `n_vertices`: the vertex count; None: the largest index plus one.

    **Returns:**

    `(faces, n)`: faces `(F, 3)` int64 and the vertex count.

    **Raises:**

    `ConnectivityError` unless faces is a non-empty `(F, 3)` integer array with indices in range, three
    distinct vertices per face and every vertex in some face.
    """
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ConnectivityError(f"faces must be a non-empty (F, 3) integer array, got shape {faces.shape}.")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ConnectivityError("faces must hold integer vertex indices.")
    faces = faces.astype(np.int64)
    n = int(faces.max()) + 1 if n_vertices is None else int(n_vertices)
    if faces.min() < 0 or faces.max() >= n:
        raise ConnectivityError(f"faces index vertex {int(faces.max())} but the mesh has {n} vertices.")
    bad = repeated_vertex_face(faces)
    if bad >= 0:
        raise ConnectivityError(f"face {bad} repeats a vertex index; faces must have 3 distinct vertices.")
    used = np.zeros(n, dtype=bool)
    used[faces.ravel()] = True
    if not used.all():
        raise ConnectivityError(
            f"vertex {int(np.argmin(used))} belongs to no face; remove unreferenced vertices first."
        )
    return faces, n


def vertex_components(elements: Int[ArrayLike, "m s"], n_vertices: int) -> tuple[int, Int[np.ndarray, " v"]]:
    """The connected components of the vertex graph of a simplex mesh.

    **Arguments:**

    - `elements`: triangles `(F, 3)` or tetrahedra `(T, 4)`.
    - `n_vertices`: the vertex count.

    **Returns:**

    `(count, labels)`: the number of components and a label per vertex `(V,)`; a vertex in no element is a
    component of its own.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.asarray(elements)
    s = e.shape[1]
    rows = np.concatenate([e[:, i] for i in range(s)])
    cols = np.concatenate([e[:, (i + 1) % s] for i in range(s)])
    graph = coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    count, labels = connected_components(graph, directed=False)
    return int(count), labels


def build_topology(faces: ArrayLike, n_vertices: int | None = None) -> Topology:
    """Build the :class:`Topology` of a triangle mesh on the host (numpy), once per connectivity.

    **Arguments:**

    - `faces`: triangles `(F, 3)`.
    - `n_vertices`: the vertex count; None: the largest index plus one.

    **Returns:**

    The :class:`Topology` (int32/bool arrays, static sizes).

    **Raises:**

    `ConnectivityError` for faces failing :func:`validate_faces` or a non-manifold edge (shared by more than
    two faces).
    """
    faces, n = validate_faces(faces, n_vertices)

    # Edge opposite corner k: (f[k+1], f[k+2]).
    a = faces[:, [1, 2, 0]].ravel()
    b = faces[:, [2, 0, 1]].ravel()
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keys = lo * n + hi
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    if counts.max() > 2:
        raise ConnectivityError("the mesh is non-manifold: an edge is shared by more than two faces.")
    edges = np.stack([uniq // n, uniq % n], axis=1)
    face_edge = inverse.reshape(-1, 3)
    boundary_edge = counts == 1
    boundary_vertex = np.zeros(n, dtype=bool)
    boundary_vertex[edges[boundary_edge].ravel()] = True

    n_edges = edges.shape[0]
    src = np.concatenate([edges[:, 0], edges[:, 1]])
    dst = np.concatenate([edges[:, 1], edges[:, 0]])
    hedge = np.concatenate([np.arange(n_edges), np.arange(n_edges)])
    order = np.lexsort((dst, src))
    src, dst, hedge = src[order], dst[order], hedge[order]
    degree = np.bincount(src, minlength=n)
    kmax = int(degree.max())
    start = np.concatenate([[0], np.cumsum(degree)[:-1]])
    slot = np.arange(src.shape[0]) - start[src]
    neighbors = np.repeat(np.arange(n)[:, None], kmax, axis=1)
    neighbors[src, slot] = dst
    mask = np.zeros((n, kmax), dtype=bool)
    mask[src, slot] = True

    i32 = lambda x: jnp.asarray(x, dtype=jnp.int32)  # noqa: E731
    return Topology(
        faces=i32(faces),
        edges=i32(edges),
        face_edge=i32(face_edge),
        half_src=i32(src),
        half_dst=i32(dst),
        half_edge=i32(hedge),
        neighbors=i32(neighbors),
        mask=jnp.asarray(mask),
        degree=i32(degree),
        boundary_vertex=jnp.asarray(boundary_vertex),
        n_vertices=n,
        n_faces=int(faces.shape[0]),
        n_edges=int(n_edges),
        max_degree=kmax,
    )
