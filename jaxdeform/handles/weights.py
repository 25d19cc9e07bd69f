"""DFD weights from per-vertex features, anchors, locality, symmetry and linear blending (seed 004).

Everything from unit-norm features ``Z`` (V, C) (``Z = Phi(V)``, the distilled feature field at the vertices) to
deformed vertices. Paper: Deep Feature Deformation weights, Sec. 3.1, 3.3 (eqs. 1, 4-9) and App. I (eq. 10).

Weights (eqs. 4-6). For handle vertices ``h_1..h_K``::

    W_ik = max(1 - ||z_i - z_{h_k}||_2, 0)

For unit features ``||a - b||^2 = 2 - 2 a.b``, so the whole (V, K) matrix is one matmul ``Z @ Z[h].T`` followed by
an elementwise ``max(1 - sqrt(max(2 - 2 d, 0)), 0)``: linear in V and in K (the paper's point). The handle's own
weight is set to exactly 1 (the formula gives 1 - O(sqrt(eps)) there in floating point). The features must be
unit-norm (this is not checked, it would cost as much as a one-handle rebind); :class:`Deformer` normalises them.

Anchors (eq. 7), fixed vertices ``a_1..a_A``: ``W_ik <- max(W_ik - max_a F_ia, 0)`` with ``F_ia`` the feature
weight between vertex i and anchor a (the same formula as above). An anchor's own row becomes 0 and no weight
grows. As in the paper, the handle's own weight is *not* rescaled afterwards (it drops below 1 when the handle's
features resemble an anchor's).

Locality (eq. 8): ``W_ik <- W_ik (1 - G_ik)^lam`` with ``G[:, k]`` the heat-method geodesic distance from handle k
divided by its largest value (so per handle G lies in [0, 1], 0 at the handle); then each column is divided by
its maximum, which for DFD weights is the handle's own weight (1, at G = 0), so the handle keeps weight exactly 1
(``lam = 0`` is a no-op); the result is clipped to [0, 1]. Vertices unreachable from a handle (another connected
component) get G = 1, i.e. weight 0 for ``lam > 0``.

Blending (eq. 1) with per-handle affine transforms ``D_k = [A_k | t_k]`` (3 x 4), written in displacement form
so that zero motion returns the input exactly::

    V'_i = V_i + sum_k W_ik (D_k [V_i; 1] - V_i) = V_i + B_i [V_i; 1],   B_i = sum_k W_ik (D_k - [I | 0])

``B = W @ M`` is one (V, K) x (K, 12) matmul against the stacked displacement matrices ``M_k = D_k - [I | 0]``
(computed entrywise, so an identity transform gives exactly 0), followed by one fused elementwise pass over
the (V, 3) vertices; float32 for speed (any float dtype works). Layout (V, 3) kept: the (3, V) layout was not
reliably faster here. A translation-only edit is the special case ``A_k = I`` (no separate code path).
benchmarks/handles.py measures the per-frame cost (655k vertices, 10 handles: interactive rates on a CPU for blend,
symmetric_blend and pou, and through :class:`Deformer`, whose weights are padded to 16 columns). The CPU matmul
kernel is several times slower with 13+ output columns than with 12, so nothing (such as a column of ones for the
row sums) is appended to M.

Partition of unity (App. I, eq. 10, ``pou=True``): a simulated control point with transform ``D0`` (identity
unless given) and weight ``w0 = max(1 - sum_k W_ik, 0)``; the weights (w0, W_i1..W_iK) are divided by their sum
(which is >= 1) so they sum to exactly 1 per vertex, and ``V'_i = V_i + sum_j w^_ij (D_j [V_i; 1] - V_i)`` = the
affine combination ``sum_j w^_ij D_j [V_i; 1]`` (still exact for zero motion). With ``sum_k W_ik > 1`` the paper's
eq. 10 alone would not be an affine combination; the renormalisation makes it one. ``blend(pou=True)`` computes
the per-vertex factors 1 / (w0 + s) and w0 / (w0 + s) in one more pass over W each call (a separate jitted call:
fused into one program with the matmul it ran ~2x slower on this CPU); :class:`Deformer` normalises its weights
once per rebind, so its pou frames cost the same as plain ones.

Symmetry (eq. 9). Candidate planes have normals along the coordinate axes x, y, z (the paper's "primary axes")
and, in addition, the principal axes (PCA) of the vertices where they differ from the coordinate axes: the normal
of a mirror-symmetric vertex set is always an eigenvector of its covariance (for distinct eigenvalues), so these
find the plane of a shape that is not aligned with the coordinate frame (at most three more field evaluations;
``pca=False`` gives the paper's candidates only). All planes pass through the vertex centroid. Score::

    s(P) = (1/|V|) sum_i ||Phi(v_i) - Phi(R_P v_i)||_2        (symmetric when s < eps = 0.1)

(the sum over V+ and V- of eq. 9 is the sum over all vertices), estimated on at most ``max_points`` vertices
drawn at random (seed 0) for large meshes. Symmetric blending: vertex i takes ``D_k`` from handles on its own side
of the plane and the reflected transform ``S D_k S`` (S the affine reflection, S S = I) from handles on the other
side; points on the plane count as the positive side (n . x - offset >= 0). Implementation with the same single
12-column matmul: with M_k the displacements seen from the positive side (``S D_k S - [I|0]`` for a handle on the
negative side, ``= [R L R | R L c + R t]`` for ``D_k - [I|0] = [L | t]``, R = I - 2 n n^T, c = 2 offset n), a
negative-side vertex applies ``S M_k S`` and ``(S M S)[v; 1] = R (M [S v; 1])`` (the last row of M is 0): mirror
the negative-side vertices, blend, mirror the displacement back with R. Exact for zero motion.

Retracing: the weight functions pad K (and the anchor count A) to a power-of-two bucket (1, 2, 4, 8, ...) and
mask the padded columns to 0, so a new handle count compiles only when it crosses a bucket (K = 100 runs as 128,
about 6% slower than unpadded; one handle runs unpadded). ``blend`` compiles once per (V, K, dtype) (padding W
there would copy V x K every frame); :class:`Deformer` keeps its weights padded to the bucket (zero columns,
identity transforms), so interactive use never recompiles within a bucket.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxdeform.errors import JaxDeformError

#: Symmetry threshold of eq. 9 (the paper uses 0.1 for all results).
SYMMETRY_EPS = 0.1

#: detect_symmetry estimates each score on at most this many vertices (random subset, seed 0).
SYMMETRY_MAX_POINTS = 20_000

_COORD_AXES = (("x", (1.0, 0.0, 0.0)), ("y", (0.0, 1.0, 0.0)), ("z", (0.0, 0.0, 1.0)))


class NoSymmetryError(JaxDeformError):
    """A symmetric deformation was asked for but no symmetry plane is known for the shape."""


# ----------------------------------------------------------------------------------------------- helpers


def bucket(k: int) -> int:
    """The padded column count used for k handles.

    **Arguments:**

    - ``k``: the number of handles.

    **Returns:**

    The next power of two (0 and 1 stay as they are).
    """
    return k if k <= 1 else 1 << (k - 1).bit_length()


def _index_array(idx, n: int, what: str) -> np.ndarray:
    a = np.atleast_1d(np.asarray(idx))
    if a.ndim != 1:
        raise ValueError(f"{what} must be a 1-D sequence of vertex indices, got shape {a.shape}.")
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{what} must be integer vertex indices, got dtype {a.dtype}.")
    if a.size and (a.min() < 0 or a.max() >= n):
        bad = int(a.max()) if a.max() >= n else int(a.min())
        raise ValueError(f"{what} index {bad} is out of range for {n} vertices.")
    return a.astype(np.int32)


def _pad_indices(a: np.ndarray, size: int) -> np.ndarray:
    """Pads with the first index (a repeated index changes neither a max over anchors nor masked columns)."""
    if a.size == size:
        return a
    return np.concatenate([a, np.full(size - a.size, a[0] if a.size else 0, dtype=a.dtype)])


def _float_dtype(x) -> jnp.dtype:
    return jnp.promote_types(jnp.asarray(x).dtype, jnp.float32)


# ----------------------------------------------------------------------------------------------- weights


def _feature_weights(Z: Float[Array, "v c"], idx: Int[Array, " k"]) -> Float[Array, "v k"]:
    """max(1 - ||z_i - z_j||, 0) for every vertex i and j in idx (unit features: one matmul), own weight 1."""
    d2 = jnp.maximum(2.0 - 2.0 * (Z @ Z[idx].T), 0.0)
    return jnp.maximum(1.0 - jnp.sqrt(d2), 0.0)


@jax.jit
def _dfd_padded(Z: Float[Array, "v c"], handles: Int[Array, " kp"], k) -> Float[Array, "v kp"]:
    cols = jnp.arange(handles.shape[0])
    valid = cols < k
    W = jnp.where(valid, _feature_weights(Z, handles), 0.0)
    return W.at[handles, cols].set(valid.astype(W.dtype))


@jax.jit
def _anchor_padded(W: Float[Array, "v kp"], Z: Float[Array, "v c"], anchors: Int[Array, " ap"]) -> Float[Array, "v kp"]:
    Wa = _feature_weights(Z, anchors)
    Wa = Wa.at[anchors, jnp.arange(anchors.shape[0])].set(1.0)
    return jnp.maximum(W - jnp.max(Wa, axis=1, keepdims=True).astype(W.dtype), 0.0)


@jax.jit
def _locality_padded(W: Float[Array, "v kp"], G: Float[Array, "v kp"], lam) -> Float[Array, "v kp"]:
    G = jnp.clip(G.astype(W.dtype), 0.0, 1.0)
    Wl = W * jnp.power(1.0 - G, jnp.asarray(lam, W.dtype))
    top = jnp.max(Wl, axis=0)
    Wl = Wl / jnp.where(top > 0, top, 1.0)
    return jnp.clip(Wl, 0.0, 1.0)


def _slice_cols(W: Array, k: int) -> Array:
    return W if W.shape[1] == k else jax.lax.slice_in_dim(W, 0, k, axis=1)


def dfd_weights(Z: Float[Array, "v c"], handles: Int[Array, " k"]) -> Float[Array, "v k"]:
    """DFD weights (eq. 6): W_ik = max(1 - ||z_i - z_{h_k}||_2, 0) for unit-norm features Z, W[h_k, k] = 1.

    One matmul, jitted; K is padded to :func:`bucket` (K) inside, so new handle counts rarely recompile.

    **Arguments:**

    - ``Z``: unit-norm features ``(V, C)``; the weights are computed in its dtype (float32 recommended: the rebind
        reads Z once, it is memory-bound).
    - ``handles``: the handle vertices ``(K,)``.

    **Returns:**

    The weights ``(V, K)`` in [0, 1], 1 at each handle's own vertex; ``(V, 0)`` without handles.

    **Raises:**

    ``ValueError`` if ``handles`` is not 1-D integer vertex indices in range, or ``Z`` is not ``(V, C)``.
    """
    Z = jnp.asarray(Z)
    if Z.ndim != 2:
        raise ValueError(f"Z must be a (V, C) feature array, got shape {Z.shape}.")
    h = _index_array(handles, Z.shape[0], "handles")
    k = h.size
    if k == 0:
        return jnp.zeros((Z.shape[0], 0), Z.dtype)
    W = _dfd_padded(Z, jnp.asarray(_pad_indices(h, bucket(k))), k)
    return _slice_cols(W, k)


def anchor_weights(W: Float[Array, "v k"], Z: Float[Array, "v c"], anchors: Int[Array, " a"]) -> Float[Array, "v k"]:
    """Feature-space point constraints (eq. 7): W_ik <- max(W_ik - max_a F(z_i, z_a), 0), F the DFD weight.

    **Arguments:**

    - ``W``: weights ``(V, K)``.
    - ``Z``: unit-norm features ``(V, C)``.
    - ``anchors``: the anchor vertices ``(A,)``.

    **Returns:**

    The constrained weights ``(V, K)``: an anchor's own row becomes exactly 0; weights never increase. No
    anchors: ``W`` is returned unchanged.

    **Raises:**

    ``ValueError`` if ``W`` and ``Z`` do not have the same number of rows or ``anchors`` are not valid vertex indices.
    """
    W = jnp.asarray(W)
    Z = jnp.asarray(Z)
    if W.ndim != 2 or Z.ndim != 2 or W.shape[0] != Z.shape[0]:
        raise ValueError(f"W (V, K) and Z (V, C) must have the same number of rows, got {W.shape} and {Z.shape}.")
    a = _index_array(anchors, Z.shape[0], "anchors")
    if a.size == 0 or W.shape[1] == 0:
        return W
    k = W.shape[1]
    Wp = W if bucket(k) == k else jnp.pad(W, ((0, 0), (0, bucket(k) - k)))
    out = _anchor_padded(Wp, Z, jnp.asarray(_pad_indices(a, bucket(a.size))))
    return _slice_cols(out, k)


def handle_geodesics(geo, handles) -> np.ndarray:
    """Per-handle normalised geodesic distances: column k = heat-method distance from handle k / its max.

    **Arguments:**

    - ``geo``: a :class:`jaxdeform.mesh.geodesic.HeatGeodesics`.
    - ``handles``: the handle vertices ``(K,)``.

    **Returns:**

    ``(V, K)`` float64 in [0, 1], 0 at the handle; vertices unreachable from the handle (another connected
    component) are set to 1.

    **Raises:**

    ``ValueError`` if ``handles`` are not valid vertex indices.
    """
    h = _index_array(handles, geo.n_vertices, "handles")
    if h.size == 0:
        return np.zeros((geo.n_vertices, 0))
    d = np.asarray(geo(h), dtype=np.float64)  # (K, V)
    finite = np.isfinite(d)
    top = np.where(finite, d, 0.0).max(axis=1, keepdims=True)
    d = np.where(finite, d / np.where(top > 0, top, 1.0), 1.0)
    return np.ascontiguousarray(np.clip(d, 0.0, 1.0).T)


def locality_weights(W: Float[Array, "v k"], G: Float[Array, "v k"], lam: float) -> Float[Array, "v k"]:
    """Locality weighting (eq. 8): W (1 - G)^lam, each column rescaled so its maximum (the handle's weight) is 1.

    **Arguments:**

    - ``W``: weights ``(V, K)``.
    - ``G``: per-handle normalised geodesic distance in [0, 1] ``(V, K)`` (:func:`handle_geodesics`).
    - ``lam``: the exponent, >= 0; ``lam = 0`` returns W unchanged (for DFD weights, whose handle weight is 1);
        larger ``lam`` suppresses far vertices more.

    **Returns:**

    The weights ``(V, K)``.

    **Raises:**

    ``ValueError`` if ``lam`` is not a finite number >= 0 or ``W`` and ``G`` are not ``(V, K)`` arrays of one shape.
    """
    if not (np.isfinite(lam) and lam >= 0):
        raise ValueError(f"the locality exponent must be a finite number >= 0, got {lam}.")
    W = jnp.asarray(W)
    G = jnp.asarray(G)
    if W.shape != G.shape or W.ndim != 2:
        raise ValueError(f"W and G must both be (V, K) arrays of one shape, got {W.shape} and {G.shape}.")
    k = W.shape[1]
    if k == 0:
        return W
    if bucket(k) != k:
        pad = ((0, 0), (0, bucket(k) - k))
        W, G = jnp.pad(W, pad), jnp.pad(G, pad)
    return _slice_cols(_locality_padded(W, G, float(lam)), k)


# ----------------------------------------------------------------------------------------------- blending


def _identity34(dtype) -> Array:
    return jnp.eye(3, 4, dtype=dtype)


def _displacement(u: Float[Array, "v 3"], B: Float[Array, "v 12"]) -> Float[Array, "v 3"]:
    """B_i [u_i; 1] with B_i the (3, 4) blended displacement matrix of vertex i (elementwise, fused)."""
    B = B.reshape(-1, 3, 4)
    return B[:, :, 0] * u[:, 0:1] + B[:, :, 1] * u[:, 1:2] + B[:, :, 2] * u[:, 2:3] + B[:, :, 3]


def _row_sums(W: Float[Array, "v k"]) -> Float[Array, "v 1"]:
    """sum_k W_ik as K elementwise adds: XLA fuses them into the consumer's pass over W, where jnp.sum would be
    one more kernel (and on a busy machine with few cores every extra parallel kernel can wait a scheduler time
    slice)."""
    s = jnp.zeros((W.shape[0], 1), W.dtype)
    for k in range(W.shape[1]):
        s = s + W[:, k : k + 1]
    return s


def _pou_weights(W: Float[Array, "v k"]) -> tuple[Float[Array, "v 1"], Float[Array, "v 1"]]:
    """Eq. 10: w0 = max(1 - sum_k W_ik, 0) and the normaliser w0 + sum_k W_ik (>= 1)."""
    s = _row_sums(W)
    w0 = jnp.maximum(1.0 - s, 0.0)
    return w0, w0 + s


@jax.jit
def _blend_core(v, W, T):
    """V + B [V; 1] with B = W @ (T - [I|0]) (V, 12): the matmul kernel is much faster at 12 columns than 13+."""
    return v + _displacement(v, W @ (T - _identity34(v.dtype)).reshape(-1, 12))


@jax.jit
def _pou_scales(W: Float[Array, "v k"]) -> tuple[Float[Array, "v 1"], Float[Array, "v 1"]]:
    """Per vertex 1 / (w0 + s) and w0 / (w0 + s) of eq. 10 (s = sum_k W_ik, w0 = max(1 - s, 0)).

    A separate jitted call on purpose: fused into the blend program (where it is independent of the matmul) the
    blend runs about twice as slow on a CPU as the two programs do."""
    w0, total = _pou_weights(W)
    r = 1.0 / total
    return r, w0 * r


@jax.jit
def _blend_pou(v, W, T, d0, r, w0r):
    """V'_i = V_i + r_i B_i [V_i; 1] + w0r_i (D0 - [I|0]) [V_i; 1]: the normalised eq. 10, multiplications only."""
    eye = _identity34(v.dtype)
    d = _displacement(v, W @ (T - eye).reshape(-1, 12)) * r
    return v + (d + w0r * _displacement(v, (d0 - eye).reshape(1, 12)))


@jax.jit
def _pou_fill(W: Float[Array, "v kp"], k) -> Float[Array, "v kp"]:
    """The normalised eq.-10 weights [W_i1..W_iK, w0_i, 0..] / (w0_i + sum_k W_ik), w0 in the first padding
    column k (W has zero columns from k on, k < Kp). Blending them (pou=False) with identity transforms in the
    padding columns is the pou blend with D0 = identity; :class:`Deformer` computes them once per rebind."""
    w0, total = _pou_weights(W)
    return jnp.where(jnp.arange(W.shape[1]) == k, w0, W) / total


def _check_blend(vertices, W, transforms):
    v = jnp.asarray(vertices)
    dt = _float_dtype(v)
    v = v.astype(dt)
    W = jnp.asarray(W).astype(dt)
    T = jnp.asarray(transforms).astype(dt)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be a (V, 3) array, got shape {v.shape}.")
    if W.ndim != 2 or W.shape[0] != v.shape[0]:
        raise ValueError(f"W must be a (V, K) array with V = {v.shape[0]}, got shape {W.shape}.")
    if T.shape != (W.shape[1], 3, 4):
        raise ValueError(f"transforms must have shape (K, 3, 4) with K = {W.shape[1]}, got {T.shape}.")
    return v, W, T


def blend(
    vertices: Float[Array, "v 3"],
    W: Float[Array, "v k"],
    transforms: Float[Array, "k 3 4"],
    *,
    pou: bool = False,
    d0: Float[Array, "3 4"] | None = None,
) -> Float[Array, "v 3"]:
    """Linear blending of per-handle affine transforms (eq. 1), jitted and differentiable.

    Default: ``V'_i = V_i + sum_k W_ik (D_k [V_i; 1] - V_i)`` (zero motion returns the input exactly).
    ``pou=True`` (eq. 10): weights (w0 = max(1 - sum_k W_ik, 0), W_i1..W_iK) renormalised to sum to 1 per vertex,
    ``V'_i = w0 D0 [V_i; 1] + sum_k W_ik D_k [V_i; 1]``. Computed in the floating dtype of ``vertices`` (W and the
    transforms are cast to it); compiles once per (V, K, dtype, pou). With ``pou`` the normalisation is a separate
    jitted call (faster here, see _pou_scales).

    **Arguments:**

    - ``vertices``: rest positions ``(V, 3)``.
    - ``W``: weights ``(V, K)``.
    - ``transforms``: per-handle affine maps ``(K, 3, 4)``.
    - ``pou``: the partition-of-unity extension (eq. 10).
    - ``d0``: the ``(3, 4)`` transform of the rest weight w0 (default None: the identity); used only with ``pou``.

    **Returns:**

    The deformed positions ``(V, 3)``.

    **Raises:**

    ``ValueError`` for arrays of the wrong shapes.
    """
    v, W, T = _check_blend(vertices, W, transforms)
    if not pou:
        return _blend_core(v, W, T)
    d0 = _identity34(v.dtype) if d0 is None else jnp.asarray(d0).astype(v.dtype)
    if d0.shape != (3, 4):
        raise ValueError(f"d0 must be a (3, 4) affine transform, got shape {d0.shape}.")
    return _blend_pou(v, W, T, d0, *_pou_scales(W))


# ----------------------------------------------------------------------------------------------- symmetry


@dataclass(frozen=True, eq=False)  # eq=False: numpy normals make field-wise == ambiguous
class Plane:
    """The plane {x : normal . x = offset} (unit normal), its symmetry score (eq. 9) and whether score < eps."""

    normal: np.ndarray
    offset: float
    score: float = float("nan")
    symmetric: bool = False
    source: str = ""  # which candidate: "x", "y", "z" (coordinate axes) or "pca0".."pca2" (principal axes)


def _plane_arrays(plane: Plane) -> tuple[np.ndarray, float]:
    n = np.asarray(plane.normal, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(n)
    if not (np.isfinite(norm) and norm > 0):
        raise ValueError(f"a plane's normal must be a non-zero finite 3-vector, got {plane.normal}.")
    return n / norm, float(plane.offset)


def reflect_points(plane: Plane, points) -> np.ndarray:
    """Mirror images R_P(p) = p - 2 (n . p - offset) n of points across the plane.

    **Arguments:**

    - ``plane``: the plane.
    - ``points``: ``(..., 3)``.

    **Returns:**

    The mirror images, same shape (float64).
    """
    n, d = _plane_arrays(plane)
    p = np.asarray(points, dtype=np.float64)
    return p - 2.0 * (p @ n - d)[..., None] * n


def reflection_matrix(plane: Plane) -> np.ndarray:
    """The affine reflection S across the plane; S S = I.

    **Arguments:**

    - ``plane``: the plane.

    **Returns:**

    S, ``(4, 4)`` homogeneous.
    """
    n, d = _plane_arrays(plane)
    S = np.eye(4)
    S[:3, :3] -= 2.0 * np.outer(n, n)
    S[:3, 3] = 2.0 * d * n
    return S


def reflect_transform(plane: Plane, D) -> np.ndarray:
    """R_P(D) = S D S: the transform D seen in the mirror (eq. 9).

    **Arguments:**

    - ``plane``: the plane.
    - ``D``: a ``(3, 4)`` affine map.

    **Returns:**

    The mirrored ``(3, 4)`` map.
    """
    D = np.asarray(D, dtype=np.float64)
    if D.shape != (3, 4):
        raise ValueError(f"D must be a (3, 4) affine transform, got shape {D.shape}.")
    S = reflection_matrix(plane)
    D4 = np.vstack([D, [0.0, 0.0, 0.0, 1.0]])
    return (S @ D4 @ S)[:3]


def _canonical_sign(n: np.ndarray) -> np.ndarray:
    return n if n[np.argmax(np.abs(n))] > 0 else -n


def candidate_planes(vertices, *, pca: bool = True) -> list[Plane]:
    """Unscored candidate planes through the vertex centroid: normals x, y, z, then new principal axes.

    **Arguments:**

    - ``vertices``: ``(V, 3)``.
    - ``pca``: add the principal axes not already among x, y, z (needs at least 3 vertices).

    **Returns:**

    The candidate planes (:class:`Plane`, unscored, each naming its ``source``).
    """
    v = np.asarray(vertices, dtype=np.float64)
    centroid = v.mean(axis=0)
    normals = [(name, np.asarray(axis)) for name, axis in _COORD_AXES]
    if pca and v.shape[0] >= 3:
        _, vecs = np.linalg.eigh(np.cov((v - centroid).T))
        for j in range(3):
            n = _canonical_sign(vecs[:, 2 - j] / np.linalg.norm(vecs[:, 2 - j]))
            if all(abs(float(n @ m)) < 1.0 - 1e-6 for _, m in normals):
                normals.append((f"pca{j}", n))
    return [Plane(normal=n, offset=float(n @ centroid), source=name) for name, n in normals]


def detect_symmetry(
    field_fn: Callable[[np.ndarray], np.ndarray],
    vertices,
    eps: float = SYMMETRY_EPS,
    *,
    pca: bool = True,
    max_points: int | None = SYMMETRY_MAX_POINTS,
) -> list[Plane]:
    """Semantic symmetry planes (eq. 9), every candidate scored.

    Candidates: see :func:`candidate_planes`. Score: mean over vertices of ||Phi(v) - Phi(R_P v)||_2;
    ``symmetric`` when < eps. The mean is estimated on a random subset (seed 0) of at most ``max_points`` vertices.

    **Arguments:**

    - ``field_fn``: ``field_fn(points (P, 3)) -> features (P, C)`` (unit-norm, e.g. the distilled field).
    - ``vertices``: the mesh's vertices ``(V, 3)``.
    - ``eps``: the score below which a plane is symmetric.
    - ``pca``: also try the principal planes (:func:`candidate_planes`).
    - ``max_points``: the most vertices scored (None: all).

    **Returns:**

    The candidate planes (:class:`Plane`, each with its score and ``symmetric`` flag), best (lowest score) first.

    **Raises:**

    ``ValueError`` if ``vertices`` is not a non-empty ``(V, 3)`` array.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must be a non-empty (V, 3) array, got shape {v.shape}.")
    pts = v
    if max_points is not None and v.shape[0] > max_points:
        pts = v[np.sort(np.random.default_rng(0).choice(v.shape[0], size=int(max_points), replace=False))]
    f0 = np.asarray(field_fn(pts), dtype=np.float64)
    if f0.ndim != 2 or f0.shape[0] != pts.shape[0]:
        raise ValueError(
            f"field_fn must map (P, 3) points to (P, C) features, got shape {f0.shape} for P = {pts.shape[0]}."
        )
    planes = []
    for cand in candidate_planes(v, pca=pca):
        f1 = np.asarray(field_fn(reflect_points(cand, pts)), dtype=np.float64)
        score = float(np.mean(np.linalg.norm(f0 - f1, axis=1)))
        planes.append(Plane(cand.normal, cand.offset, score, bool(score < eps), cand.source))
    return sorted(planes, key=lambda p: p.score)


def _dot3(a: Float[Array, "v 3"], n: Float[Array, " 3"]) -> Float[Array, " v"]:
    # written out: a (V, 3) @ (3,) would become a separate matmul kernel with its own pass over memory
    return a[:, 0] * n[0] + a[:, 1] * n[1] + a[:, 2] * n[2]


def _mirror(v: Float[Array, "v 3"], normal, offset) -> tuple[Float[Array, "v 3"], Array]:
    """(u, negative): u_i = v_i on the positive side (n . v - offset >= 0), its mirror image S v_i otherwise;
    negative (V, 1) is 1 on the negative side, 0 on the positive one (both elementwise, without selects)."""
    dist = (_dot3(v, normal) - offset)[:, None]
    return v - 2.0 * jnp.minimum(dist, 0.0) * normal, (dist < 0).astype(v.dtype)


def _positive_side_matrices(T, hpos, normal, offset) -> Float[Array, "k 12"]:
    """Displacements M_k = D_k - [I|0] as seen from the positive side: S D_k S - [I|0] for a handle on the other.

    S M S = [R L R | R L c + R t] for M = [L | t] (R = I - 2 n n^T, c = 2 offset n); written with broadcasts, these
    3 x 3 products would otherwise each become a matmul kernel call."""
    M = T - _identity34(T.dtype)
    R = jnp.eye(3, dtype=T.dtype) - 2.0 * normal[:, None] * normal[None, :]
    c = 2.0 * offset * normal
    L, t = M[:, :, :3], M[:, :, 3]
    RL = jnp.sum(R[None, :, :, None] * L[:, None, :, :], axis=2)
    RLR = jnp.sum(RL[:, :, :, None] * R[None, None, :, :], axis=2)
    tr = jnp.sum(RL * c[None, None, :], axis=2) + jnp.sum(R[None] * t[:, None, :], axis=2)
    Mr = jnp.concatenate([RLR, tr[:, :, None]], axis=2)
    positive = (jnp.sum(hpos * normal, axis=1) - offset >= 0)[:, None, None]
    return jnp.where(positive, M, Mr).reshape(-1, 12)


def _symmetric_from(v, u, negative, W, m_plus, normal):
    """Eq. 9 with one (V, K) x (K, 12) matmul: a vertex on the negative side applies S M_k S, and since the last
    row of M_k (as 4 x 4) is zero, (S M S)[v; 1] = R (M [S v; 1]). So the negative-side vertices are mirrored,
    blended with the positive-side matrices, and the displacement is mirrored back with R (exact 0 stays 0).
    Returns the displacement (V, 3)."""
    d = _displacement(u, W @ m_plus)
    return d - 2.0 * negative * _dot3(d, normal)[:, None] * normal


@jax.jit
def _symmetric_core(v, W, T, hpos, normal, offset):
    u, negative = _mirror(v, normal, offset)
    return v + _symmetric_from(v, u, negative, W, _positive_side_matrices(T, hpos, normal, offset), normal)


@jax.jit
def _symmetric_pou(v, W, T, hpos, normal, offset, r):
    """Symmetric blend with eq. 10 (D0 = identity): only the normalisation r = 1 / (w0 + s) remains."""
    u, negative = _mirror(v, normal, offset)
    return v + _symmetric_from(v, u, negative, W, _positive_side_matrices(T, hpos, normal, offset), normal) * r


@jax.jit
def _symmetric_premirrored(v, u, negative, W, T, hpos, normal, offset):
    return v + _symmetric_from(v, u, negative, W, _positive_side_matrices(T, hpos, normal, offset), normal)


_mirror_jit = jax.jit(_mirror)


def symmetric_blend(
    vertices: Float[Array, "v 3"],
    W: Float[Array, "v k"],
    transforms: Float[Array, "k 3 4"],
    handle_positions: Float[Array, "k 3"],
    plane: Plane,
    *,
    pou: bool = False,
) -> Float[Array, "v 3"]:
    """Symmetry-preserving blending (eq. 9): handles on the vertex's side of the plane apply D_k, the others S D_k S.

    Same displacement form (exact for zero motion), dtype rules and ``pou`` option (D0 = identity) as :func:`blend`.

    **Arguments:**

    - ``vertices``: rest positions ``(V, 3)``.
    - ``W``: weights ``(V, K)``.
    - ``transforms``: per-handle affine maps ``(K, 3, 4)``.
    - ``handle_positions``: the handles' positions ``(K, 3)`` (which side of the plane each lies on).
    - ``plane``: the symmetry plane.
    - ``pou``: the partition-of-unity extension (eq. 10).

    **Returns:**

    The deformed positions ``(V, 3)``.

    **Raises:**

    ``ValueError`` for arrays of the wrong shapes.
    """
    v, W, T = _check_blend(vertices, W, transforms)
    hp = jnp.asarray(handle_positions).astype(v.dtype)
    if hp.shape != (W.shape[1], 3):
        raise ValueError(f"handle_positions must have shape (K, 3) with K = {W.shape[1]}, got {hp.shape}.")
    n, d = _plane_arrays(plane)
    n, d = jnp.asarray(n, v.dtype), jnp.asarray(d, v.dtype)
    if not pou:
        return _symmetric_core(v, W, T, hp, n, d)
    return _symmetric_pou(v, W, T, hp, n, d, _pou_scales(W)[0])


# ----------------------------------------------------------------------------------------------- transforms


def make_transform(centre, translate=(0.0, 0.0, 0.0), axis=None, degrees: float = 0.0) -> np.ndarray:
    """The affine map x -> R (x - centre) + centre + translate, R the rotation by ``degrees`` about ``axis``.

    **Arguments:**

    - ``centre``: the rotation centre ``(3,)``.
    - ``translate``: the translation ``(3,)``.
    - ``axis``: the rotation axis ``(3,)`` (default None: no rotation).
    - ``degrees``: the rotation angle.

    **Returns:**

    The ``(3, 4)`` float64 map; ``axis=None`` or ``degrees=0`` gives R = I exactly (a pure translation).
    """
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    t = np.asarray(translate, dtype=np.float64).reshape(3)
    R = np.eye(3)
    if axis is not None and degrees != 0.0:
        a = np.asarray(axis, dtype=np.float64).reshape(3)
        norm = np.linalg.norm(a)
        if not (np.isfinite(norm) and norm > 0):
            raise ValueError(f"the rotation axis must be a non-zero finite 3-vector, got {axis}.")
        a = a / norm
        K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
        th = np.deg2rad(float(degrees))
        R = np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)
    return np.concatenate([R, (c - R @ c + t)[:, None]], axis=1)


# ----------------------------------------------------------------------------------------------- Deformer


class Deformer:
    """Weights and deformations of one mesh from its per-vertex features (for the CLI and the interactive page).

    ``Z`` (V, C): per-vertex features (rows are normalised to unit length here); if None, ``field_fn(vertices)``.
    ``field_fn`` (optional): the feature field, needed for symmetry detection. Everything runs in ``dtype``
    (float32 by default: rebinding is memory-bound on Z). The heat-method geodesics are factored on the first
    ``locality > 0`` request, symmetry planes on the first symmetric request. The weights of the last
    (handles, anchors, locality) are kept padded to :func:`bucket` (K) columns, so dragging handles only blends.
    Order of the weight steps: DFD weights, then locality (eq. 8), then anchors (eq. 7).
    """

    def __init__(
        self, vertices, faces, Z=None, *, field_fn: Callable[[np.ndarray], np.ndarray] | None = None, dtype=np.float32
    ):
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0 or not np.all(np.isfinite(v)):
            raise ValueError(f"vertices must be a non-empty finite (V, 3) array, got shape {v.shape}.")
        if Z is None:
            if field_fn is None:
                raise ValueError("give the per-vertex features Z or a field_fn to compute them.")
            Z = field_fn(v)
        self.dtype = np.dtype(dtype)
        z = np.asarray(Z, dtype=self.dtype)
        if z.ndim != 2 or z.shape[0] != v.shape[0]:
            raise ValueError(f"Z must be a (V, C) array with V = {v.shape[0]}, got shape {z.shape}.")
        norms = np.linalg.norm(z, axis=1, keepdims=True)
        z = z / np.where(norms > 0, norms, 1.0)
        self.vertices = v
        self.faces = np.asarray(faces, dtype=np.int64)
        self.field_fn = field_fn
        self._v = jnp.asarray(v.astype(self.dtype))
        self._z = jnp.asarray(z)
        self._geo = None
        self._geo_cols: dict[int, np.ndarray] = {}
        self._planes: list[Plane] | None = None
        self._mirrored = None  # (u, negative) of the vertices for the symmetry plane
        self._cached: tuple[tuple, Array] | None = None
        self._cached_pou: tuple[tuple, Array] | None = None

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[0]

    @property
    def geodesics(self):
        """The mesh's :class:`HeatGeodesics` (factored on first use)."""
        if self._geo is None:
            from jaxdeform.mesh.geodesic import HeatGeodesics

            self._geo = HeatGeodesics(self.vertices, self.faces)
        return self._geo

    def _geodesic_columns(self, h: np.ndarray, width: int) -> np.ndarray:
        missing = [int(i) for i in dict.fromkeys(h.tolist()) if int(i) not in self._geo_cols]
        if missing:
            G = handle_geodesics(self.geodesics, np.asarray(missing))
            for j, i in enumerate(missing):
                self._geo_cols[i] = G[:, j].astype(self.dtype)
        G = np.zeros((self.n_vertices, width), dtype=self.dtype)
        for j, i in enumerate(h.tolist()):
            G[:, j] = self._geo_cols[int(i)]
        return G

    def _padded_weights(self, handles, anchors, locality: float) -> tuple[Array, int]:
        h = _index_array(handles, self.n_vertices, "handles")
        a = _index_array(anchors, self.n_vertices, "anchors")
        locality = float(locality)
        if not (np.isfinite(locality) and locality >= 0):
            raise ValueError(f"locality must be a finite number >= 0, got {locality}.")
        key = (tuple(h.tolist()), tuple(a.tolist()), locality)
        if self._cached is not None and self._cached[0] == key:
            return self._cached[1], h.size
        kp = max(bucket(h.size), 1)
        W = _dfd_padded(self._z, jnp.asarray(_pad_indices(h, kp)), h.size)
        if locality > 0 and h.size:
            W = _locality_padded(W, jnp.asarray(self._geodesic_columns(h, kp)), locality)
        if a.size:
            W = _anchor_padded(W, self._z, jnp.asarray(_pad_indices(a, bucket(a.size))))
        self._cached = (key, W)
        return W, h.size

    def weights(self, handles, *, anchors=(), locality: float = 0.0) -> np.ndarray:
        """DFD weights of the handles, with optional anchors (eq. 7) and locality exponent (eq. 8).

        **Arguments:**

        - ``handles``: the handle vertices ``(K,)``.
        - ``anchors``: the anchor vertices.
        - ``locality``: the locality exponent lam (0: no locality weighting).

        **Returns:**

        The weights ``(V, K)``.

        **Raises:**

        ``ValueError`` for invalid vertex indices or a negative locality exponent.
        """
        W, k = self._padded_weights(handles, anchors, locality)
        return np.array(W[:, :k])

    def deform(
        self, handles, transforms, *, anchors=(), locality: float = 0.0, symmetric: bool = False, pou: bool = False
    ) -> np.ndarray:
        """Deformed vertices for one affine transform per handle (eq. 1, 9 or 10).

        The weights of the last request are reused (pou: their normalised eq.-10 form too), so a new frame of the
        same handles costs one blend: a (V, K) x (K, 12) matmul and one elementwise pass.

        **Arguments:**

        - ``handles``: the handle vertices ``(K,)``.
        - ``transforms``: one ``(3, 4)`` affine map per handle, ``(K, 3, 4)``.
        - ``anchors``, ``locality``: as :meth:`weights`.
        - ``symmetric``: symmetry-preserving blending (eq. 9) about the detected plane.
        - ``pou``: the partition-of-unity extension (eq. 10).

        **Returns:**

        The deformed vertices ``(V, 3)``.

        **Raises:**

        ``ValueError`` for transforms of another shape; ``NoSymmetryError`` for ``symmetric`` when no symmetry plane was
        detected (or no feature field was given).
        """
        W, k = self._padded_weights(handles, anchors, locality)
        T = np.asarray(transforms, dtype=self.dtype)
        if T.shape != (k, 3, 4):
            raise ValueError(f"transforms must have shape ({k}, 3, 4), one per handle, got {T.shape}.")
        if pou:
            key = self._cached[0]
            if self._cached_pou is None or self._cached_pou[0] != key:
                if k == W.shape[1]:  # no padding column left for w0
                    W = jnp.pad(W, ((0, 0), (0, bucket(k + 1) - k)))
                self._cached_pou = (key, _pou_fill(W, k))
            W = self._cached_pou[1]
        Tp = np.tile(np.eye(3, 4, dtype=self.dtype), (W.shape[1], 1, 1))  # identity: padding columns and D0
        Tp[:k] = T
        if not symmetric:
            return np.array(_blend_core(self._v, W, jnp.asarray(Tp)))
        plane = self.symmetry_plane()
        if plane is None:
            raise NoSymmetryError("no symmetry plane was detected for this shape (or no feature field was given).")
        n, d = _plane_arrays(plane)
        n, d = jnp.asarray(n, self.dtype), jnp.asarray(d, self.dtype)
        if self._mirrored is None:
            self._mirrored = _mirror_jit(self._v, n, d)
        hp = np.zeros((W.shape[1], 3), dtype=self.dtype)
        hp[:k] = self.vertices[np.asarray(handles, dtype=np.int64).reshape(-1)]
        out = _symmetric_premirrored(self._v, *self._mirrored, W, jnp.asarray(Tp), jnp.asarray(hp), n, d)
        return np.array(out)

    def symmetry_planes(self) -> list[Plane]:
        """Every scored candidate plane, best first (empty without a field_fn); computed once."""
        if self._planes is None:
            self._planes = [] if self.field_fn is None else detect_symmetry(self.field_fn, self.vertices)
        return self._planes

    def symmetry_plane(self) -> Plane | None:
        """The best detected plane if it is symmetric (score < 0.1), else None (always None without a field_fn)."""
        planes = self.symmetry_planes()
        return planes[0] if planes and planes[0].symmetric else None
