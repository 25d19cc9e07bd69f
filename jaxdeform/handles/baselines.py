"""Classical handle-deformation baselines (libigl) for the timing comparison of DFD (Fig. 10, App. B).

Both baselines take the same input as DFD: a triangle mesh, handles given as vertex indices, and one 3x4
affine transform ``D_k`` per handle (translation-only or general affine). Each exposes the three timed phases
of the paper, measured with ``time.perf_counter`` into ``self.timings`` (seconds):

* ``preprocess`` -- mesh-only work that does not depend on the handles (done in the constructor);
* ``bind``       -- work that depends on the handle SET (:meth:`bind`);
* ``pose``       -- new handle transforms -> deformed vertices (:meth:`pose`).

**ARAP** (:class:`ARAPBaseline`; Sorkine & Alexa 2007) minimises
``E(V') = sum_i sum_{(j,k) in E_i} w_jk || (v'_j - v'_k) - R_i (v_j - v_k) ||^2`` over the positions ``V'`` and
one rotation ``R_i`` per vertex, with the handle vertices as hard positional constraints
``v'_h = D_k [v_h; 1]`` (and optional fixed vertices kept at rest). It alternates a local step
(``R_i = polar(S_i)``, ``S_i`` the cotangent-weighted edge covariance) and a global step (a cotangent-Laplacian
solve with the constrained rows eliminated, factored once). Choices: libigl's ``arap_precomputation`` /
``arap_solve`` with the *spokes-and-rims* edge sets ``E_i`` (all edges of the triangles around vertex i,
Chao et al. 2010; libigl's default for triangle meshes). libigl's pure *spokes* energy (the one-ring edges of
the 2007 paper) is not offered: on this libigl build it does not keep the rest pose when nothing moves (a 3 %
drift of the bounding box on armadillo after 10 iterations). A fixed iteration count (10 by default) is run
from the rest pose. Only the position ``D_k [v_h; 1]`` of a handle enters ARAP (point constraints), so the
linear part of an affine handle transform is ignored, as in every point-handle ARAP. Phase split: libigl
builds the Laplacian together with the constrained factorisation in ``arap_precomputation``, so ARAP's
``preprocess`` is only input checking and connectivity, and ``bind`` holds all the precomputation. libigl's
local step fits rotations in single precision, so even zero motion is reproduced only to ~1e-7 of the mesh
size (not to float64 round-off).

**Biharmonic weights + linear blend skinning** (:class:`BiharmonicBaseline`). Weights ``W`` (V x K) minimise
``trace(W^T Q W)`` with ``W[h_j, k] = delta_jk`` at the handle vertices (fixed vertices get a column of
their own, weight 1 there, which blends the identity). ``kind`` selects:

* ``"biharmonic"`` -- ``Q = L M^-1 L`` (cotangent Laplacian L, Voronoi mass matrix M; ``igl.harmonic`` with
  k = 2). Since ``L 1 = 0``, the weights sum to one (partition of unity) up to the solver's precision.
  Phase split: ``preprocess`` assembles Q, ``bind`` factors ``Q_uu`` on the unconstrained vertices and solves.
* ``"coordinates"`` -- biharmonic coordinates of Wang et al. 2015 (``igl.biharmonic_coordinates``; the
  paper's "Biharmonic" baseline): the squared-Laplacian energy with the boundary treatment that gives linear
  precision (``sum_k W_ik p_k = v_i`` on a volume mesh or a flat surface). libigl builds its operator inside
  the call, so all of it is ``bind``.
* ``"bounded"`` -- bounded biharmonic weights (Jacobson et al. 2011; ``igl.bbw``): the ``"biharmonic"`` energy
  with ``0 <= W <= 1``, one active-set QP per handle, then rows divided by their sums (libigl's recommended
  normalisation; not the PoU-constrained variant). All ``bind``. Slow: minutes at 25k vertices.

With ``volume=True`` the closed surface is first tetrahedralised with TetGen (``igl.copyleft.tetgen``, flags
``"pq1.414YQ"``: quality interior, no Steiner points on the surface, so the surface vertices keep their
indices) and the weights are solved on the tetrahedra, as the paper does with FTetWild; TetGen is part of
``preprocess`` and the weights are read back on the surface vertices. ``volume=False`` solves on the surface.

Pose (all kinds) is linear blend skinning in displacement form,
``V'_i = V_i + sum_k W_ik (D_k [V_i; 1] - V_i) = sum_k W_ik D_k [V_i; 1] + (1 - sum_k W_ik) V_i``,
computed by DFD's own :func:`jaxdeform.handles.weights.blend` (the same formula, so both methods pose alike).
It equals plain LBS when the weights sum to one and returns the input exactly when nothing moves. The
product is jitted JAX: NumPy's multithreaded OpenBLAS GEMM for this tall, thin
shape slows down by more than an order of magnitude whenever other processes keep the cores busy. It is
compiled once per handle count at the end of :meth:`BiharmonicBaseline.bind`, outside the timed window
(``compile_seconds``), so ``pose`` times the blend only, as for DFD.

The weight solves and ARAP are libigl's C++ on the CPU; nothing in this module is differentiable.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import igl
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Float, Int

from jaxdeform.errors import DegenerateMeshError, JaxDeformError, MeshFormatError
from jaxdeform.handles.weights import blend
from jaxdeform.mesh.topology import validate_faces, vertex_components

#: Methods of :func:`run_baseline`: ARAP and the three weight kinds of :class:`BiharmonicBaseline`.
METHODS = ("arap", "biharmonic", "coordinates", "bounded")
WEIGHT_KINDS = ("biharmonic", "coordinates", "bounded")
DEFAULT_ITERATIONS = 10
DEFAULT_TET_FLAGS = "pq1.414YQ"
PHASES = ("preprocess", "bind", "pose")


class HandleError(JaxDeformError, ValueError):
    """Handles, fixed vertices or transforms are inconsistent with the mesh or with each other."""


# ----------------------------------------------------------------------------------------- checks


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0 or not np.issubdtype(v.dtype, np.number):
        raise MeshFormatError(f"vertices must be a non-empty (V, 3) numeric array, got shape {v.shape}.")
    v = np.ascontiguousarray(v, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise MeshFormatError(f"vertex {int(np.argwhere(~np.isfinite(v))[0, 0])} has a NaN or infinite coordinate.")
    f = np.asarray(faces)
    if f.ndim == 2 and f.shape[0] == 0:
        raise DegenerateMeshError("the mesh has no faces; ARAP and biharmonic weights need a triangle mesh.")
    f, _ = validate_faces(f, v.shape[0])  # int64, in range, distinct corners, every vertex in a face
    return v, np.ascontiguousarray(f)


def _check_indices(indices, n_vertices: int, what: str, *, allow_empty: bool) -> np.ndarray:
    idx = np.atleast_1d(np.asarray(indices))
    if idx.size == 0:
        if not allow_empty:
            raise HandleError(f"at least one {what} vertex is needed.")
        return np.zeros(0, dtype=np.int64)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
        raise HandleError(
            f"{what} vertices must be a 1-D sequence of integer vertex indices, got {idx.dtype} {idx.shape}."
        )
    bad = idx[(idx < 0) | (idx >= n_vertices)]
    if bad.size:
        raise HandleError(f"{what} vertex {int(bad[0])} is out of range for a mesh of {n_vertices} vertices.")
    uniq, counts = np.unique(idx, return_counts=True)
    if np.any(counts > 1):
        raise HandleError(f"{what} vertex {int(uniq[np.argmax(counts > 1)])} is given more than once.")
    return idx.astype(np.int64)


def _check_constraints(handles, fixed, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    h = _check_indices(handles, n_vertices, "handle", allow_empty=False)
    x = _check_indices(fixed, n_vertices, "fixed", allow_empty=True)
    both = np.intersect1d(h, x)
    if both.size:
        raise HandleError(f"vertex {int(both[0])} is both a handle and a fixed vertex.")
    return h, x


def _check_transforms(transforms, n_handles: int) -> np.ndarray:
    d = np.asarray(transforms, dtype=np.float64)
    if d.shape != (n_handles, 3, 4):
        raise HandleError(f"transforms must have shape ({n_handles}, 3, 4), one per handle, got {d.shape}.")
    if not np.all(np.isfinite(d)):
        raise HandleError("transforms hold a NaN or infinite entry.")
    return d


def _check_every_component_constrained(labels: np.ndarray, constrained: np.ndarray) -> None:
    missing = np.setdiff1d(np.unique(labels), np.unique(labels[constrained]))
    if missing.size:
        vertex = int(np.argmax(labels == missing[0]))
        raise HandleError(
            f"the connected component containing vertex {vertex} has no handle or fixed vertex, so its "
            "deformation is undetermined; add a handle or fixed vertex there."
        )


def handle_targets(
    vertices: Float[np.ndarray, "v 3"], handles: Int[np.ndarray, " k"], transforms: Float[np.ndarray, "k 3 4"]
) -> Float[np.ndarray, "k 3"]:
    """Target position ``D_k [v_h; 1]`` of every handle vertex.

    **Arguments:**

    - ``vertices``: rest positions ``(V, 3)``.
    - ``handles``: the handle vertices ``(K,)``.
    - ``transforms``: per-handle affine maps ``(K, 3, 4)``.

    **Returns:**

    The targets ``(K, 3)`` float64.
    """
    p = np.asarray(vertices, dtype=np.float64)[np.asarray(handles)]
    d = np.asarray(transforms, dtype=np.float64)
    return np.einsum("kij,kj->ki", d[:, :, :3], p) + d[:, :, 3]


# ------------------------------------------------------------------------------------------- ARAP


class ARAPBaseline:
    """As-rigid-as-possible deformation with point handles (libigl; see the module docstring).

    ``ARAPBaseline(vertices, faces)`` checks the mesh (``timings["preprocess"]``); :meth:`bind` precomputes
    for a handle set (``timings["bind"]``); :meth:`pose` runs ``iterations`` local/global steps from the rest
    pose (``timings["pose"]``) and returns the deformed vertices, handle vertices exactly on their targets.
    """

    def __init__(self, vertices, faces, *, iterations: int = DEFAULT_ITERATIONS):
        if int(iterations) < 1:
            raise ValueError(f"iterations must be at least 1, got {iterations}.")
        t0 = time.perf_counter()
        self.vertices, self.faces = _check_mesh(vertices, faces)
        self._labels = vertex_components(self.faces, self.vertices.shape[0])[1]
        self.timings: dict[str, float] = {"preprocess": time.perf_counter() - t0}
        self.iterations = int(iterations)
        self.handles: np.ndarray | None = None
        self.fixed = np.zeros(0, dtype=np.int64)
        self._data: igl.ARAPData | None = None

    def bind(self, handles: Sequence[int] | np.ndarray, *, fixed: Sequence[int] | np.ndarray = ()) -> ARAPBaseline:
        """Precompute for this handle set (and vertices held at rest).

        **Arguments:**

        - ``handles``: the handle vertices ``(K,)``.
        - ``fixed``: vertices held at rest.

        **Returns:**

        ``self``.

        **Raises:**

        :class:`HandleError` for handles or fixed vertices inconsistent with the mesh or with each other.
        """
        h, x = _check_constraints(handles, fixed, self.vertices.shape[0])
        _check_every_component_constrained(self._labels, np.concatenate([h, x]))
        t0 = time.perf_counter()
        data = igl.ARAPData()
        data.energy = igl.ARAP_ENERGY_TYPE_SPOKES_AND_RIMS
        igl.arap_precomputation(self.vertices, self.faces, 3, np.concatenate([h, x]).astype(np.int32), data)
        self.timings["bind"] = time.perf_counter() - t0
        self.handles, self.fixed, self._data = h, x, data
        return self

    def pose(
        self,
        transforms: Float[np.ndarray, "k 3 4"],
        *,
        initial: np.ndarray | None = None,
        iterations: int | None = None,
    ) -> Float[np.ndarray, "v 3"]:
        """Deformed vertices for one transform per handle.

        **Arguments:**

        - ``transforms``: ``(K, 3, 4)`` affine maps.
        - ``initial``: the start of the ARAP iterations ``(V, 3)`` (default None: the rest pose).
        - ``iterations``: ARAP iterations, at least 1 (default None: the baseline's count).

        **Returns:**

        ``(V, 3)`` float64.

        **Raises:**

        :class:`HandleError` before :meth:`bind` or for an ``initial`` of another shape; ``ValueError`` for
        ``iterations < 1``; the transforms' checks.
        """
        if self._data is None or self.handles is None:
            raise HandleError("call bind(handles) before pose(transforms).")
        d = _check_transforms(transforms, self.handles.size)
        n_iter = self.iterations if iterations is None else int(iterations)
        if n_iter < 1:
            raise ValueError(f"iterations must be at least 1, got {iterations}.")
        u0 = self.vertices if initial is None else np.ascontiguousarray(initial, dtype=np.float64)
        if u0.shape != self.vertices.shape:
            raise HandleError(f"initial must have shape {self.vertices.shape}, got {u0.shape}.")
        t0 = time.perf_counter()
        bc = np.concatenate([handle_targets(self.vertices, self.handles, d), self.vertices[self.fixed]])
        self._data.max_iter = n_iter
        out = np.asarray(igl.arap_solve(bc, self._data, u0), dtype=np.float64)
        self.timings["pose"] = time.perf_counter() - t0
        return out


# ------------------------------------------------------------------------------------- biharmonic


def tetrahedralize(
    vertices: np.ndarray, faces: np.ndarray, flags: str = DEFAULT_TET_FLAGS
) -> tuple[np.ndarray, np.ndarray]:
    """TetGen volume mesh of a closed surface.

    **Arguments:**

    - ``vertices``, ``faces``: the closed surface.
    - ``flags``: TetGen's switches.

    **Returns:**

    ``(TV, TT)``: tet-mesh vertices, whose first V are the surface vertices, and tetrahedra.
    """
    import igl.copyleft.tetgen as tetgen

    try:
        tv, tt = tetgen.tetrahedralize(vertices, faces, flags=flags)[:2]
    except RuntimeError as err:
        raise DegenerateMeshError(
            f"TetGen could not tetrahedralize the surface ({err}); it must be closed and free of self-intersections."
        ) from None
    n = vertices.shape[0]
    if tv.shape[0] < n or not np.array_equal(tv[:n], vertices):
        raise DegenerateMeshError("TetGen moved or dropped surface vertices (duplicate vertices?); use volume=False.")
    return np.ascontiguousarray(tv, dtype=np.float64), np.ascontiguousarray(tt, dtype=np.int64)


class BiharmonicBaseline:
    """Biharmonic-type weights bound to handle vertices, posed by linear blend skinning (module docstring).

    ``BiharmonicBaseline(vertices, faces, kind=..., volume=...)`` runs the mesh-only work
    (``timings["preprocess"]``); :meth:`bind` solves the weights (``timings["bind"]``, ``self.weights`` is
    (V, K) over the surface vertices); :meth:`pose` blends the handle transforms (``timings["pose"]``).
    """

    def __init__(
        self, vertices, faces, *, kind: str = "biharmonic", volume: bool = False, tet_flags: str = DEFAULT_TET_FLAGS
    ):
        if kind not in WEIGHT_KINDS:
            raise ValueError(f"kind must be one of {', '.join(WEIGHT_KINDS)}, got {kind!r}.")
        t0 = time.perf_counter()
        self.vertices, self.faces = _check_mesh(vertices, faces)
        self.kind, self.volume = kind, bool(volume)
        if self.volume:
            self._domain_v, self._domain_e = tetrahedralize(self.vertices, self.faces, tet_flags)
        else:
            self._domain_v, self._domain_e = self.vertices, self.faces
        self._labels = vertex_components(self._domain_e, self._domain_v.shape[0])[1]
        self._Q = None
        if kind == "biharmonic":
            L = igl.cotmatrix(self._domain_v, self._domain_e)
            M = igl.massmatrix(self._domain_v, self._domain_e, igl.MASSMATRIX_TYPE_DEFAULT)
            self._Q = sp.csc_matrix(igl.harmonic_integrated_from_laplacian_and_mass(L, M, 2))
        self.timings: dict[str, float] = {"preprocess": time.perf_counter() - t0}
        self.handles: np.ndarray | None = None
        self.fixed = np.zeros(0, dtype=np.int64)
        self.weights: np.ndarray | None = None  # (V, K) weights of the handles on the surface vertices
        self.fixed_weights: np.ndarray | None = None  # (V, F) weights of the fixed vertices (identity columns)
        self._vertices_j = jnp.asarray(self.vertices)
        self.compile_seconds = 0.0  # jit compilation of the blend at bind, excluded from timings

    @property
    def n_domain_vertices(self) -> int:
        """Vertices the weights are solved on (surface, or surface + TetGen's interior points)."""
        return int(self._domain_v.shape[0])

    def _solve(self, b: np.ndarray) -> np.ndarray:
        """All-column weights (domain V x |b|) with ``W[b_j, k] = delta_jk``."""
        bc = np.eye(b.size)
        if self.kind == "biharmonic":
            data = igl.min_quad_with_fixed_data()
            igl.min_quad_with_fixed_precompute(A=self._Q, known=b, pd=True, data=data)
            zeros = np.zeros((self.n_domain_vertices, b.size))
            return igl.min_quad_with_fixed_solve(data, B=zeros, Y=bc)
        if self.kind == "coordinates":
            return igl.biharmonic_coordinates(self._domain_v, self._domain_e, [[int(i)] for i in b], 2)
        w = igl.bbw(self._domain_v, self._domain_e, b, bc, partition_unity=False)
        return w / np.maximum(w.sum(axis=1, keepdims=True), np.finfo(np.float64).tiny)

    def bind(
        self, handles: Sequence[int] | np.ndarray, *, fixed: Sequence[int] | np.ndarray = ()
    ) -> BiharmonicBaseline:
        """Solve the weights for this handle set (plus vertices held at rest).

        **Arguments:**

        - ``handles``: the handle vertices ``(K,)``.
        - ``fixed``: vertices held at rest.

        **Returns:**

        ``self``.

        **Raises:**

        :class:`HandleError` for handles or fixed vertices inconsistent with the mesh or with each other, or a
        connected component with neither.
        """
        h, x = _check_constraints(handles, fixed, self.vertices.shape[0])
        b = np.concatenate([h, x])
        _check_every_component_constrained(self._labels, b)
        t0 = time.perf_counter()
        w = np.asarray(self._solve(b), dtype=np.float64)[: self.vertices.shape[0]]
        wh = np.ascontiguousarray(w[:, : h.size])
        self._W = jnp.asarray(wh)
        self.timings["bind"] = time.perf_counter() - t0
        if not np.all(np.isfinite(w)):
            raise DegenerateMeshError(
                "the weight solve produced non-finite values; the mesh may have degenerate faces."
            )
        self.handles, self.fixed, self.weights, self.fixed_weights = h, x, wh, w[:, h.size :]
        # compile the jitted blend for this handle count now (JAX overhead, not part of the method's timings)
        t0 = time.perf_counter()
        blend(self._vertices_j, self._W, jnp.zeros((h.size, 3, 4))).block_until_ready()
        self.compile_seconds = time.perf_counter() - t0
        return self

    def pose(self, transforms: Float[np.ndarray, "k 3 4"]) -> Float[np.ndarray, "v 3"]:
        """Deformed vertices: displacement-form LBS of one transform per handle.

        **Arguments:**

        - ``transforms``: ``(K, 3, 4)`` affine maps.

        **Returns:**

        ``(V, 3)`` float64.

        **Raises:**

        :class:`HandleError` before :meth:`bind`; the transforms' checks.
        """
        if self.weights is None or self.handles is None:
            raise HandleError("call bind(handles) before pose(transforms).")
        d = _check_transforms(transforms, self.handles.size)
        t0 = time.perf_counter()
        out = np.array(blend(self._vertices_j, self._W, d), dtype=np.float64)
        self.timings["pose"] = time.perf_counter() - t0
        return out


# ------------------------------------------------------------------------------------ one-shot run


def make_baseline(method: str, vertices, faces, **options) -> ARAPBaseline | BiharmonicBaseline:
    """The preprocessed baseline ``method``.

    **Arguments:**

    - ``method``: one of :data:`METHODS`.
    - ``vertices``, ``faces``: the mesh, ``(V, 3)`` and ``(F, 3)``.
    - ``options``: passed to the baseline's constructor.

    **Returns:**

    An :class:`ARAPBaseline` or a :class:`BiharmonicBaseline`.

    **Raises:**

    ``ValueError`` for an unknown ``method``.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}.")
    if method == "arap":
        return ARAPBaseline(vertices, faces, **options)
    return BiharmonicBaseline(vertices, faces, kind=method, **options)


def run_baseline(
    method: str, vertices, faces, handles, transforms, *, fixed=(), **options
) -> tuple[Float[np.ndarray, "v 3"], dict[str, float]]:
    """Preprocess, bind and pose once.

    **Arguments:**

    - ``method``, ``vertices``, ``faces``, ``options``: as :func:`make_baseline`'s.
    - ``handles``: the handle vertices ``(K,)``.
    - ``transforms``: per-handle affine maps ``(K, 3, 4)``.
    - ``fixed``: vertices held at rest.

    **Returns:**

    ``(deformed vertices (V, 3) float64, {phase: seconds})``.

    **Raises:**

    As :func:`make_baseline`; :class:`HandleError` for handles, fixed vertices or transforms inconsistent with the
    mesh or with each other (a vertex both handle and fixed, a connected component with neither).
    """
    model = make_baseline(method, vertices, faces, **options)
    out = model.bind(handles, fixed=fixed).pose(transforms)
    return out, {phase: model.timings[phase] for phase in PHASES}
