"""Geodesic distances on a triangle mesh (libigl): exact (Mitchell-Mount-Papadimitriou) or heat method.

``geodesic_distances(vertices, faces, sources)`` returns one row of distances per source vertex. With
``normalize=True`` (the default) the whole result is divided by its largest entry, so every value lies in
[0, 1]: this is the *normalized geodesic distance* used by the sparse localized / multiscale deformation
components papers (distances divided by the largest one) to build the support maps of components.

Meshes with several connected components (or vertices that belong to no face) are handled one component at
a time: a vertex that cannot be reached from a source is at distance ``inf`` (normalization ignores these
and keeps them ``inf``). The heat method is an approximation (a few percent on fine, well-shaped meshes;
Crane et al. 2013); its small negative values near a source are clipped to 0.

This module is NumPy/libigl only (not differentiable) and imports nothing of jaxdeform but the errors.
"""

from __future__ import annotations

from collections.abc import Sequence

import igl
import numpy as np

from jaxdeform.errors import ConnectivityError, DegenerateMeshError, MeshFormatError
from jaxdeform.mesh.topology import vertex_components

#: ``method="auto"`` uses the exact algorithm up to this many vertices and this much work (sources x vertices;
#: the exact algorithm's cost per source grows with the mesh), the heat method above either.
AUTO_EXACT_MAX_VERTICES = 5000
AUTO_EXACT_MAX_WORK = 200_000

METHODS = ("auto", "exact", "heat")


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise MeshFormatError(f"vertices must be a non-empty (V, 3) array, got shape {v.shape}.")
    if not np.all(np.isfinite(v)):
        bad = int(np.argwhere(~np.isfinite(v))[0, 0])
        raise MeshFormatError(f"vertex {bad} has a NaN or infinite coordinate.")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise MeshFormatError(f"faces must be a non-empty (F, 3) array, got shape {f.shape}.")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshFormatError(f"faces must hold integer vertex indices, got dtype {f.dtype}.")
    if f.min() < 0 or f.max() >= v.shape[0]:
        bad = int(f.max()) if f.max() >= v.shape[0] else int(f.min())
        raise ConnectivityError(f"faces index vertex {bad} but the mesh has {v.shape[0]} vertices.")
    return np.ascontiguousarray(v), np.ascontiguousarray(f, dtype=np.int64)


def _check_sources(sources, n_vertices: int) -> np.ndarray:
    s = np.atleast_1d(np.asarray(sources))
    if s.ndim != 1 or s.size == 0:
        raise ValueError("sources must be a vertex index or a non-empty 1-D sequence of vertex indices.")
    if not np.issubdtype(s.dtype, np.integer):
        raise ValueError(f"sources must be integer vertex indices, got dtype {s.dtype}.")
    if s.min() < 0 or s.max() >= n_vertices:
        bad = int(s.max()) if s.max() >= n_vertices else int(s.min())
        raise ValueError(f"source vertex {bad} is out of range for a mesh of {n_vertices} vertices.")
    return s.astype(np.int64)


class _Components:
    """Connected components of the vertex graph, with each component's own (re-indexed) submesh."""

    def __init__(self, v: np.ndarray, f: np.ndarray):
        self.n_components, self.labels = vertex_components(f, v.shape[0])
        self.single = self.n_components == 1
        self._v, self._f = v, f
        self._face_labels = self.labels[f[:, 0]]
        self._cache: dict[int, tuple[np.ndarray, np.ndarray | None, np.ndarray | None]] = {}

    def submesh(self, label: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(global vertex ids, local vertices, local faces); faces are None for an isolated vertex."""
        if self.single:
            return np.arange(self._v.shape[0]), self._v, self._f
        if label not in self._cache:
            ids = np.flatnonzero(self.labels == label)
            faces = self._f[self._face_labels == label]
            if faces.shape[0] == 0:
                self._cache[label] = (ids, None, None)
            else:
                local = np.full(self._v.shape[0], -1, dtype=np.int64)
                local[ids] = np.arange(ids.size)
                self._cache[label] = (ids, np.ascontiguousarray(self._v[ids]), np.ascontiguousarray(local[faces]))
        return self._cache[label]

    def local_index(self, ids: np.ndarray, vertex: int) -> int:
        return vertex if self.single else int(np.searchsorted(ids, vertex))


def _finish_row(d: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(d)):
        raise DegenerateMeshError(
            f"the {what} produced non-finite distances; the mesh likely has zero-area or badly shaped faces."
        )
    return np.maximum(d, 0.0)


class HeatGeodesics:
    """Heat-method geodesic distances (Crane et al. 2013) with the factorization done once.

    `HeatGeodesics(vertices, faces)(sources)` returns raw (unnormalized) distances; repeated calls reuse the
    prefactored solvers (every component with faces is factored at construction).

    **Arguments:**

    - `vertices`: positions `(V, 3)`.
    - `faces`: triangles `(F, 3)`, integer.
    - `t`: the heat time, a positive number; None: libigl's default, the squared mean edge length.
    - `intrinsic_delaunay`: compute the Laplacian on an intrinsic Delaunay triangulation, which helps on
      meshes with obtuse triangles.

    **Raises:**

    `MeshFormatError` for vertices not a non-empty finite `(V, 3)` array or faces not a non-empty integer
    `(F, 3)` array; `ConnectivityError` for a face index out of range;
    `ValueError` for a non-positive or non-finite `t`.
    """

    def __init__(self, vertices, faces, *, t: float | None = None, intrinsic_delaunay: bool = False):
        v, f = _check_mesh(vertices, faces)
        if t is not None and not (np.isfinite(t) and t > 0):
            raise ValueError(f"the heat time t must be a positive number, got {t}.")
        self.n_vertices = v.shape[0]
        self._components = _Components(v, f)
        self._t = t
        self._intrinsic_delaunay = bool(intrinsic_delaunay)
        self._data: dict[int, igl.HeatGeodesicsData] = {}
        # Factor every component that has faces now, so that calls only do back-substitutions.
        for label in np.unique(self._components.labels):
            self._solver(int(label))

    def _solver(self, label: int):
        if label not in self._data:
            _, v, f = self._components.submesh(label)
            if f is None:
                self._data[label] = None
            else:
                data = igl.HeatGeodesicsData()
                data.use_intrinsic_delaunay = self._intrinsic_delaunay
                if self._t is None:
                    igl.heat_geodesics_precompute(v, f, data)
                else:
                    igl.heat_geodesics_precompute(v, f, float(self._t), data)
                self._data[label] = data
        return self._data[label]

    def __call__(self, sources: int | Sequence[int] | np.ndarray) -> np.ndarray:
        """Raw heat-method distances from each source.

        **Arguments:**

        - `sources`: a vertex index or a non-empty 1-D sequence of them.

        **Returns:**

        float64 distances `(S, V)`, one row per source, non-negative; `inf` for vertices in other components.

        **Raises:**

        `ValueError` for bad sources; `DegenerateMeshError` for non-finite distances (badly shaped faces).
        """
        s = _check_sources(sources, self.n_vertices)
        comps = self._components
        out = np.full((s.size, self.n_vertices), np.inf)
        for row, src in enumerate(s):
            label = int(comps.labels[src])
            ids, _, _ = comps.submesh(label)
            data = self._solver(label)
            if data is None:
                out[row, src] = 0.0
                continue
            gamma = np.array([comps.local_index(ids, int(src))], dtype=np.int64)
            d = _finish_row(np.asarray(igl.heat_geodesics_solve(data, gamma), dtype=np.float64), "heat method")
            d[gamma[0]] = 0.0
            out[row, ids] = d
        return out


def _exact(v: np.ndarray, f: np.ndarray, s: np.ndarray) -> np.ndarray:
    comps = _Components(v, f)
    out = np.full((s.size, v.shape[0]), np.inf)
    empty = np.zeros(0, dtype=np.int64)
    for row, src in enumerate(s):
        ids, vc, fc = comps.submesh(int(comps.labels[src]))
        if fc is None:
            out[row, src] = 0.0
            continue
        local = comps.local_index(ids, int(src))
        # Without explicit targets (VT) igl.exact_geodesic returns an empty array.
        d = igl.exact_geodesic(
            vc, fc, np.array([local], dtype=np.int64), empty, np.arange(vc.shape[0], dtype=np.int64), empty
        )
        d = _finish_row(np.asarray(d, dtype=np.float64), "exact geodesic algorithm")
        d[local] = 0.0
        out[row, ids] = d
    return out


def geodesic_distances(
    vertices,
    faces,
    sources: int | Sequence[int] | np.ndarray,
    *,
    method: str = "auto",
    normalize: bool = True,
) -> np.ndarray:
    """Geodesic distance from each source vertex to every vertex.

    For repeated heat-method queries on one mesh, use :class:`HeatGeodesics` directly.

    **Arguments:**

    - `vertices`: positions `(V, 3)`.
    - `faces`: triangles `(F, 3)`, integer.
    - `sources`: a vertex index or a non-empty 1-D sequence of them.
    - `method`: `"exact"` (libigl's exact MMP algorithm, one run per source), `"heat"` (heat method, factored
      once per call and reused for every source) or `"auto"` (exact up to :data:`AUTO_EXACT_MAX_VERTICES`
      vertices and :data:`AUTO_EXACT_MAX_WORK` sources x vertices, heat above: all pairs exact up to 447
      vertices, one source up to 5,000).
    - `normalize`: True divides the whole result by its largest finite entry (the "normalized geodesic
      distance" of the multiscale deformation components paper); False keeps the units of `vertices`.

    **Returns:**

    A float64 array `(S, V)`, one row per source: with `normalize=True` values lie in [0, 1] and the maximum
    is 1. Vertices unreachable from a source (another connected component) are `inf`.

    **Raises:**

    `MeshFormatError` for vertices not a non-empty finite `(V, 3)` array or faces not a non-empty integer
    `(F, 3)` array; `ConnectivityError` for a face index out of range;
    `ValueError` for an unknown method or bad sources; `DegenerateMeshError` for non-finite distances or
    (normalizing) when every reachable distance is zero.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}.")
    v, f = _check_mesh(vertices, faces)
    s = _check_sources(sources, v.shape[0])
    if method == "auto":
        small = v.shape[0] <= AUTO_EXACT_MAX_VERTICES and s.size * v.shape[0] <= AUTO_EXACT_MAX_WORK
        method = "exact" if small else "heat"
    d = _exact(v, f, s) if method == "exact" else HeatGeodesics(v, f)(s)
    if normalize:
        finite = d[np.isfinite(d)]
        largest = float(finite.max()) if finite.size else 0.0
        if not largest > 0.0:
            raise DegenerateMeshError("cannot normalize geodesic distances: every reachable distance is zero.")
        d = d / largest
    return d
