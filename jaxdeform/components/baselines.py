"""Linear baselines of seed 000's evaluation (Sec. 5.1, Table 2): PCA and SPLOCS (Neumann et al. 2013).

Both methods produce a :class:`LinearModel`, a mean shape plus K components,

    x(w) = mean + scale * sum_k w_k C_k            (decode; pure JAX, differentiable, jittable),

over either ACAP features (c = 9, ``domain="acap"``; positions come from the ACAP reconstruction elsewhere)
or vertex coordinates (c = 3, ``domain="xyz"``). :func:`project` gives the least-squares weights of unseen
shapes (``w = pinv(C) (x - mean) / scale``), :func:`reconstruct` is decode after project.

PCA (:func:`fit_pca`): the data are centred on their mean and flattened to (N, V c); the components are the
first K right singular vectors of that matrix (orthonormal, sign fixed so the entry of largest magnitude is
positive), ``scale = 1``, so training weights are the principal coordinates. K = min(n_components, N - 1,
V c): centred data of N shapes have rank at most N - 1.

SPLOCS (:func:`fit_splocs`, Neumann, Varanasi, Wenger, Wacker, Magnor, Theobalt, "Sparse localized
deformation components", ACM TOG 32(6), 2013) on Euclidean coordinates. The variant implemented here:

* Preprocessing: X = (vertices - mean shape) / s with s = std(vertices - mean) over all entries, so the data
  have unit standard deviation; ``scale = s`` is stored and decoding multiplies by it.
* Problem (F frames, K components, C_k,i in R^3 the displacement of vertex i in component k):

      min_{W, C}  1/2 ||X - W C||_F^2 + Omega(C),     Omega(C) = sum_k sum_i Lambda_ki ||C_k,i||_2,
      subject to  -1 <= W_fk <= 1,

  with the support-map weights Lambda_ki = lambda * clip((d(c_k, i) - d_min) / (d_max - d_min), 0, 1),
  d the normalized geodesic distance and c_k the vertex of largest ||C_k,i|| (recomputed every outer
  iteration). The paper states the weight constraint as max |W_:,k| = 1, which removes the scale ambiguity
  between W and C; we use its convex relaxation, the box |W_fk| <= 1 (the bound is active at the optimum of
  every non-zero component, because shrinking C_k while growing W_:,k lowers Omega). The factor 1/2 on the
  data term is the scaling under which the public code's defaults (lambda = 2, rho = 10) act (its ADMM
  solves this problem, as we read it); the paper's ||X - W C||_F^2 + Omega is the same problem with lambda doubled.
* Initialisation by deflation, K times: the vertex i of largest residual energy sum_f ||R_f,i||^2 becomes the
  centre; the weights w are the leading left singular vector (times its singular value) of that vertex's
  (F, 3) residual, normalized so that max |w| = 1 (largest entry +1); the component is the least-squares
  one for w restricted softly to the support, C_k = (1 - Lambda_k / lambda) (w^T R) / (w^T w); R -= w C_k.
  When the residual is exhausted the remaining components stay zero.
* Outer iterations (``outer``, default 10): (i) W by one sweep of block coordinate descent over the columns:
  w_k = clip((R + w_k C_k) C_k^T / ||C_k||^2, -1, 1), the exact minimiser over the box given the other
  columns (a column whose component vanished is set to 0); (ii) re-centre the support maps;
  (iii) C by ``inner`` (default 10) ADMM iterations on the convex group-lasso problem (split C = Z, scaled
  dual U carried over between outer iterations, Boyd et al. 2011):

      C <- (W^T W + rho I)^-1 (W^T X + rho (Z - U)),
      Z <- prox_{Omega / rho}(C + U)   (per vertex group shrinkage: v * max(0, 1 - Lambda_ki / (rho ||v||))),
      U <- U + C - Z,

  and C is set to Z afterwards (exactly sparse, as the public code does).
* K stays as requested (default 50) even with few training shapes: localized components are not limited by
  the rank of the data (each restricts the training displacements to a different region), which is what
  lets SPLOCS generalise to unseen poses; components the deflation cannot fill stay exactly zero and decode
  to nothing.

Distances: pass the normalized geodesic distance matrix (V, V), or a callable ``dist_rows(indices) ->
(len(indices), V)`` so that only the rows of support centres are computed (a full matrix of an 8431-vertex
mesh is 284 MB in float32); rows are cached. Neumann et al. scale each mesh into the box [-0.5, 0.5]^3 and
use geodesic distances in those units; the multiscale paper (and :mod:`jaxdeform.mesh.geodesic`) divides by
the largest distance instead: which normalization to use is the caller's choice.

Fitting runs in NumPy/SciPy (float64) on the host; :func:`decode`, :func:`project` and :func:`reconstruct`
are pure JAX. :func:`save` / :func:`load` use an orbax checkpoint folder (:mod:`jaxdeform.nn.archive`), written
atomically.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla
from jaxtyping import Array, Float, Int

from jaxdeform.errors import ConnectivityError, JaxDeformError, MeshFormatError

#: Channels per vertex of each domain.
DOMAINS = {"acap": 9, "xyz": 3}
#: Format and version written into saved models' records.
FORMAT = "jaxdeform-linear-model"
FORMAT_VERSION = 1
#: Relative singular-value cut-off of the pseudo-inverse in :func:`project`, in units of the dtype's eps.
PINV_RTOL_EPS = 1000.0

DistanceLike = np.ndarray | Callable[[np.ndarray], np.ndarray]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LinearModel:
    """Mean shape + K linear components (a pytree); ``decode(w) = mean + scale * w @ components``."""

    mean: Float[Array, "v c"]
    components: Float[Array, "k v c"]
    scale: Float[Array, ""] | float
    domain: str = dataclasses.field(metadata=dict(static=True))
    method: str = dataclasses.field(metadata=dict(static=True))

    @property
    def n_components(self) -> int:
        return self.components.shape[0]

    @property
    def n_vertices(self) -> int:
        return self.components.shape[1]

    @property
    def channels(self) -> int:
        return self.components.shape[2]


# ------------------------------------------------------------------------------------------ checks


def _check_data(data, what: str = "data", domain: str | None = None) -> tuple[np.ndarray, str]:
    """Training data as a float array (N, V, c) with N >= 2, finite, c matching ``domain``."""
    if isinstance(data, (list, tuple)):
        shapes = {np.shape(item) for item in data}
        if len(shapes) > 1:
            raise ConnectivityError(f"{what}: the shapes do not share one array shape (found {sorted(shapes)}).")
    x = np.asarray(data)
    if x.ndim != 3 or x.shape[1] == 0:
        raise MeshFormatError(f"{what} must be an (N, V, c) array of N shapes, got shape {x.shape}.")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise MeshFormatError(f"{what} must hold numbers, got dtype {x.dtype}.")
    if domain is None:
        domain = {c: d for d, c in DOMAINS.items()}.get(x.shape[2])
        if domain is None:
            raise MeshFormatError(
                f"{what} has {x.shape[2]} channels per vertex; expected 3 (coordinates) or 9 (ACAP features)."
            )
    elif domain not in DOMAINS:
        raise JaxDeformError(f"domain must be one of {', '.join(DOMAINS)}, got {domain!r}.")
    elif x.shape[2] != DOMAINS[domain]:
        raise MeshFormatError(
            f"{what} must have {DOMAINS[domain]} channels per vertex for domain {domain!r}, got {x.shape[2]}."
        )
    if x.shape[0] < 2:
        raise JaxDeformError(f"{what} holds {x.shape[0]} shape(s); fitting a linear model needs at least 2.")
    if not np.all(np.isfinite(x)):
        bad = int(np.argwhere(~np.isfinite(x))[0, 0])
        raise MeshFormatError(f"{what}: shape {bad} holds NaN or infinite values.")
    return x, domain


def _out_dtype(x: np.ndarray):
    return x.dtype if np.issubdtype(x.dtype, np.floating) else np.float64


def _check_batch(model: LinearModel, data) -> None:
    """Static shape check of a (B, V, c) batch against the model (works on tracers)."""
    shape = tuple(jnp.shape(data))
    if len(shape) != 3 or shape[2] != model.channels:
        raise MeshFormatError(
            f"data must be a (B, V, {model.channels}) array for this {model.domain} model, got shape {shape}."
        )
    if shape[1] != model.n_vertices:
        raise ConnectivityError(f"data has {shape[1]} vertices but the model was fitted on {model.n_vertices}.")


# ------------------------------------------------------------------------------------------ model use


def decode(model: LinearModel, weights: Float[Array, "b k"]) -> Float[Array, "b v c"]:
    """Shapes = mean + scale * weights @ components (pure JAX).

    **Arguments:**

    - ``model``: the linear model.
    - ``weights``: ``(B, K)``.

    **Returns:**

    Shapes ``(B, V, c)``.

    **Raises:**

    ``JaxDeformError`` if ``weights`` is not ``(B, K)``.
    """
    if jnp.ndim(weights) != 2 or jnp.shape(weights)[1] != model.n_components:
        raise JaxDeformError(
            f"weights must be a (B, {model.n_components}) array for this model, got shape {jnp.shape(weights)}."
        )
    offsets = jnp.einsum("bk,kvc->bvc", weights, model.components)
    return model.mean[None] + model.scale * offsets


def _pinv_rows(components: Float[Array, "k d"]) -> Float[Array, "d k"]:
    rtol = PINV_RTOL_EPS * jnp.finfo(components.dtype).eps
    return jnp.linalg.pinv(components, rtol=rtol)


def project(model: LinearModel, data: Float[Array, "b v c"]) -> Float[Array, "b k"]:
    """Least-squares weights of shapes: argmin_w ||mean + scale w C - x||, minimum norm.

    Unconstrained (SPLOCS's training box |w| <= 1 is not imposed on unseen shapes); zero or linearly
    dependent components are handled by the pseudo-inverse (cut-off PINV_RTOL_EPS * eps relative).

    **Arguments:**

    - ``model``: the linear model.
    - ``data``: shapes ``(B, V, c)``.

    **Returns:**

    The weights ``(B, K)``.
    """
    _check_batch(model, data)
    b = jnp.shape(data)[0]
    x = (jnp.asarray(data) - model.mean[None]).reshape(b, -1) / model.scale
    return x @ _pinv_rows(model.components.reshape(model.n_components, -1))


def reconstruct(model: LinearModel, data: Float[Array, "b v c"]) -> Float[Array, "b v c"]:
    """The model's closest shapes to ``data``: decode(project(data)).

    **Arguments:**

    - ``model``: the linear model.
    - ``data``: shapes ``(B, V, c)``.

    **Returns:**

    Shapes ``(B, V, c)``.
    """
    return decode(model, project(model, data))


# ------------------------------------------------------------------------------------------ persistence


def save(model: LinearModel, path: str | os.PathLike) -> None:
    """Write the model as an orbax checkpoint folder (:func:`jaxdeform.nn.archive.save_tree`), atomically.

    **Arguments:**

    - ``model``: the linear model.
    - ``path``: the checkpoint folder (replaced if it exists).

    **Returns:**

    Nothing.
    """
    from jaxdeform.nn.archive import save_tree

    arrays = {"mean": np.asarray(model.mean), "components": np.asarray(model.components)}
    record = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "scale": float(model.scale),
        "domain": str(model.domain),
        "method": str(model.method),
    }
    save_tree(path, arrays, record)


def load(path: str | os.PathLike) -> LinearModel:
    """Read a model written by :func:`save`.

    **Arguments:**

    - ``path``: the checkpoint folder.

    **Returns:**

    The :class:`LinearModel`.

    **Raises:**

    ``FileNotFoundError`` for a missing path; ``MeshFormatError`` for anything but a linear model checkpoint
    (damaged included, or one holding NaN, infinite or non-positive values where they are not allowed).
    """
    from jaxdeform.nn.archive import read_tree

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such linear model checkpoint.")
    record, arrays = read_tree(path, "linear model", FORMAT, FORMAT_VERSION, error=MeshFormatError)
    for key in ("mean", "components"):
        if key not in arrays:
            raise MeshFormatError(f"{path}: the array '{key}' is missing; not a linear model checkpoint.")
    mean, comps = arrays["mean"], arrays["components"]
    domain, method, scale = record.get("domain"), record.get("method"), record.get("scale")
    if domain not in DOMAINS:
        raise MeshFormatError(f"{path}: domain is {domain!r}; expected one of {', '.join(DOMAINS)}.")
    if not isinstance(method, str) or isinstance(scale, bool) or not isinstance(scale, (int, float)):
        raise MeshFormatError(f"{path}: its record needs a text 'method' and a number 'scale'.")
    c = DOMAINS[domain]
    if mean.ndim != 2 or mean.shape[1] != c or comps.ndim != 3 or comps.shape[1:] != mean.shape:
        raise MeshFormatError(
            f"{path}: mean {mean.shape} and components {comps.shape} are not (V, {c}) and (K, V, {c})."
        )
    if mean.dtype.kind != "f" or comps.dtype.kind != "f":
        raise MeshFormatError(f"{path}: mean and components must be float arrays.")
    scale = float(scale)
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(comps)) and np.isfinite(scale) and scale > 0):
        raise MeshFormatError(f"{path}: the model holds NaN, infinite or non-positive values.")
    return LinearModel(jnp.asarray(mean), jnp.asarray(comps), scale, domain, method)


# ------------------------------------------------------------------------------------------ PCA


def pca_components(x: Float[np.ndarray, "n d"], k: int) -> Float[np.ndarray, "k d"]:
    """First k right singular vectors of a centred (N, D) matrix, each signed so its largest entry is > 0."""
    _, _, vt = np.linalg.svd(x, full_matrices=False)
    vt = vt[:k]
    big = np.argmax(np.abs(vt), axis=1)
    return vt * np.sign(vt[np.arange(vt.shape[0]), big])[:, None]


def fit_pca(data: Float[np.ndarray, "n v c"], n_components: int = 50, *, domain: str | None = None) -> LinearModel:
    """PCA of N shapes; K = min(n_components, N - 1, V c).

    **Arguments:**

    - ``data``: ACAP features ``(N, V, 9)`` or coordinates ``(N, V, 3)``.
    - ``n_components``: the most components (at least 1).
    - ``domain``: defaults to "xyz" for c = 3 and "acap" for c = 9.

    **Returns:**

    The :class:`LinearModel` (mean, K components, scale, domain).

    **Raises:**

    ``JaxDeformError`` for ``n_components < 1``; ``MeshFormatError`` or ``ConnectivityError`` for data that is not an
    ``(N, V, c)`` array of numbers.
    """
    if int(n_components) < 1:
        raise JaxDeformError(f"n_components must be at least 1, got {n_components}.")
    x, domain = _check_data(data, domain=domain)
    n, v, c = x.shape
    dtype = _out_dtype(x)
    x = x.astype(np.float64)
    mean = x.mean(axis=0)
    k = min(int(n_components), n - 1, v * c)
    comps = pca_components((x - mean).reshape(n, -1), k).reshape(k, v, c)
    return LinearModel(jnp.asarray(mean, dtype), jnp.asarray(comps, dtype), 1.0, domain, "pca")


# ------------------------------------------------------------------------------------------ SPLOCS


class DistanceRows:
    """Rows of the normalized geodesic distance matrix, from a (V, V) array or a callable, cached per vertex."""

    def __init__(self, dist: DistanceLike, n_vertices: int):
        self.n_vertices = n_vertices
        self._cache: dict[int, np.ndarray] = {}
        if callable(dist):
            self._fn = dist
        else:
            d = np.asarray(dist)
            if d.shape != (n_vertices, n_vertices):
                raise ConnectivityError(
                    f"the distance matrix has shape {d.shape} but the meshes have {n_vertices} vertices."
                )
            self._fn = lambda idx: d[idx]

    def __call__(self, indices: np.ndarray) -> Float[np.ndarray, "s v"]:
        indices = np.asarray(indices, dtype=np.int64)
        missing = np.unique([i for i in indices.tolist() if i not in self._cache]).astype(np.int64)
        if missing.size:
            rows = np.asarray(self._fn(missing), dtype=np.float64)
            if rows.shape != (missing.size, self.n_vertices):
                raise ConnectivityError(
                    f"the distance function returned shape {rows.shape} for {missing.size} rows; "
                    f"expected ({missing.size}, {self.n_vertices})."
                )
            if np.any(np.isnan(rows)) or np.any(rows < 0):
                raise MeshFormatError("the geodesic distances hold NaN or negative values.")
            self._cache.update(zip(missing.tolist(), rows))
        return np.stack([self._cache[i] for i in indices.tolist()])


def support_weights(dist_rows: Float[np.ndarray, "k v"], d_min: float, d_max: float) -> Float[np.ndarray, "k v"]:
    """clip((d - d_min) / (d_max - d_min), 0, 1): 0 near the centre, 1 beyond d_max (inf -> 1)."""
    return np.clip((dist_rows - d_min) / (d_max - d_min), 0.0, 1.0)


def group_shrink(v: Float[np.ndarray, "k v 3"], threshold: Float[np.ndarray, "k v"]) -> Float[np.ndarray, "k v 3"]:
    """prox of sum_ki t_ki ||v_ki||_2: every 3-vector shrunk towards 0 by its threshold (zero if shorter)."""
    norm = np.sqrt(np.einsum("...i,...i->...", v, v))
    factor = np.maximum(0.0, 1.0 - threshold / np.maximum(norm, 1e-300))
    return v * factor[..., None]


def splocs_objective(x, w, c, lam) -> tuple[float, float]:
    """(1/2 ||X - W C||_F^2, sum_ki Lambda_ki ||C_k,i||) of the problem above."""
    r = x - np.tensordot(w, c, axes=(1, 0))
    return 0.5 * float(np.sum(r * r)), float(np.sum(lam * np.linalg.norm(c, axis=-1)))


def component_centres(c: Float[np.ndarray, "k v 3"], previous: np.ndarray) -> np.ndarray:
    """Vertex of largest displacement of each component (the previous centre for a zero component)."""
    norms = np.sum(c * c, axis=-1)
    return np.where(norms.max(axis=1) > 0, np.argmax(norms, axis=1), previous)


def splocs_init(x: Float[np.ndarray, "f v 3"], k: int, rows: DistanceRows, d_min: float, d_max: float):
    """Greedy deflation: (W (F, K), C (K, V, 3), centres (K,)), see the module docstring."""
    f, v, _ = x.shape
    r = x.copy()
    w = np.zeros((f, k))
    c = np.zeros((k, v, 3))
    centres = np.zeros(k, dtype=np.int64)
    floor = 1e-24 * max(float(np.sum(x * x)), 1e-300)
    for j in range(k):  # loop over components
        energy = np.sum(r * r, axis=(0, 2))
        idx = int(np.argmax(energy))
        if energy[idx] <= floor:
            break  # residual exhausted: the remaining components stay zero
        u, s, _ = np.linalg.svd(r[:, idx, :], full_matrices=False)
        wj = u[:, 0] * s[0]
        wj = wj / wj[np.argmax(np.abs(wj))]  # max |w| = 1, largest entry +1
        mask = 1.0 - support_weights(rows([idx]), d_min, d_max)[0]
        cj = mask[:, None] * np.tensordot(wj, r, axes=(0, 0)) / float(wj @ wj)
        r -= wj[:, None, None] * cj[None]
        w[:, j], c[j], centres[j] = wj, cj, idx
    return w, c, centres


def update_weights(x: Float[np.ndarray, "f v 3"], w, c) -> Float[np.ndarray, "f k"]:
    """One sweep of block coordinate descent on the columns of W with the box |W| <= 1 (exact per column)."""
    f, k = w.shape
    w = w.copy()
    cf = c.reshape(k, -1)
    r = x.reshape(f, -1) - w @ cf
    for j in range(k):  # loop over components
        norm2 = float(cf[j] @ cf[j])
        r += np.outer(w[:, j], cf[j])
        w[:, j] = 0.0 if norm2 <= 1e-300 else np.clip(r @ cf[j] / norm2, -1.0, 1.0)
        r -= np.outer(w[:, j], cf[j])
    return w


def admm_components(x, w, c, u, lam, rho: float, iterations: int):
    """``iterations`` ADMM steps on min_C 1/2 ||X - W C||^2 + sum Lambda ||C_k,i||; returns (C = Z, U)."""
    f, k = w.shape
    shape = c.shape
    factor = sla.cho_factor(w.T @ w + rho * np.eye(k))
    base = sla.cho_solve(factor, w.T @ x.reshape(f, -1))  # (W^T W + rho I)^-1 W^T X
    step = rho * sla.cho_solve(factor, np.eye(k))  # rho (W^T W + rho I)^-1, one small matrix product per step
    z = c.copy()
    for _ in range(iterations):  # loop over ADMM iterations
        c = (base + step @ (z - u).reshape(k, -1)).reshape(shape)
        z = group_shrink(c + u, lam / rho)
        u = u + c - z
    return z, u


class SplocsResult(NamedTuple):
    weights: np.ndarray  # (F, K) training weights, |W| <= 1
    components: np.ndarray  # (K, V, 3) in the scaled units
    centres: np.ndarray  # (K,) support centres of the last iteration
    objectives: list  # objective after initialisation, then after every outer iteration


def splocs_solve(
    x: Float[np.ndarray, "f v 3"],
    rows: DistanceRows,
    k: int,
    *,
    sparsity: float,
    d_min: float,
    d_max: float,
    rho: float,
    outer: int,
    inner: int,
    progress: Callable[[int, float], None] | None = None,
) -> SplocsResult:
    """Sparse localized components of centred, scaled data X (F, V, 3) (NumPy, float64)."""
    w, c, centres = splocs_init(x, k, rows, d_min, d_max)
    lam = sparsity * support_weights(rows(centres), d_min, d_max)
    objectives = [sum(splocs_objective(x, w, c, lam))]
    u = np.zeros_like(c)
    for it in range(outer):  # loop over outer iterations
        w = update_weights(x, w, c)
        centres = component_centres(c, centres)
        lam = sparsity * support_weights(rows(centres), d_min, d_max)
        c, u = admm_components(x, w, c, u, lam, rho, inner)
        objectives.append(sum(splocs_objective(x, w, c, lam)))
        if progress is not None:
            progress(it, objectives[-1])
    return SplocsResult(w, c, centres, objectives)


def _check_splocs_args(n_components, sparsity, d_min, d_max, rho, outer, inner) -> None:
    if int(n_components) < 1:
        raise JaxDeformError(f"n_components must be at least 1, got {n_components}.")
    if not (0.0 <= d_min < d_max):
        raise JaxDeformError(f"the support range needs 0 <= d_min < d_max, got d_min={d_min}, d_max={d_max}.")
    if not (sparsity >= 0 and rho > 0):
        raise JaxDeformError(f"sparsity must be >= 0 and rho > 0, got sparsity={sparsity}, rho={rho}.")
    if int(outer) < 0 or int(inner) < 1:
        raise JaxDeformError(f"outer must be >= 0 and inner >= 1, got outer={outer}, inner={inner}.")


def fit_splocs(
    vertices: Float[np.ndarray, "n v 3"],
    dist: DistanceLike,
    n_components: int = 50,
    sparsity: float = 2.0,
    d_min: float = 0.1,
    d_max: float = 0.7,
    rho: float = 10.0,
    outer: int = 10,
    inner: int = 10,
    progress: Callable[[int, float], None] | None = None,
) -> LinearModel:
    """SPLOCS on coordinates with the public code's defaults; see the module docstring.

    **Arguments:**

    - ``vertices``: shapes ``(N, V, 3)``.
    - ``dist``: normalized geodesic distances, a ``(V, V)`` array or a callable ``rows(indices) -> (len, V)``.
    - ``n_components``: K.
    - ``sparsity``, ``d_min``, ``d_max``, ``rho``, ``outer``, ``inner``: the sparsity weight, the support's distance
        ramp, the ADMM penalty, and the outer and ADMM iterations (module docstring).
    - ``progress``: ``progress(iteration, objective)`` is called after every outer iteration.

    **Returns:**

    The :class:`LinearModel`.
    """
    return fit_splocs_detailed(vertices, dist, n_components, sparsity, d_min, d_max, rho, outer, inner, progress)[0]


def fit_splocs_detailed(
    vertices,
    dist: DistanceLike,
    n_components: int = 50,
    sparsity: float = 2.0,
    d_min: float = 0.1,
    d_max: float = 0.7,
    rho: float = 10.0,
    outer: int = 10,
    inner: int = 10,
    progress=None,
) -> tuple[LinearModel, SplocsResult]:
    """:func:`fit_splocs` that also returns the solver's result (training weights, centres, objectives)."""
    _check_splocs_args(n_components, sparsity, d_min, d_max, rho, outer, inner)
    x, _ = _check_data(vertices, "vertices", domain="xyz")
    dtype = _out_dtype(x)
    x = x.astype(np.float64)
    rows = DistanceRows(dist, x.shape[1])
    mean = x.mean(axis=0)
    xc = x - mean
    scale = float(np.std(xc))
    if not scale > 1e-12 * float(np.abs(x).max()):
        raise JaxDeformError("every training shape is identical; there is no deformation to decompose.")
    result = splocs_solve(
        xc / scale,
        rows,
        int(n_components),
        sparsity=float(sparsity),
        d_min=float(d_min),
        d_max=float(d_max),
        rho=float(rho),
        outer=int(outer),
        inner=int(inner),
        progress=progress,
    )
    model = LinearModel(jnp.asarray(mean, dtype), jnp.asarray(result.components, dtype), scale, "xyz", "splocs")
    return model, result


# --------------------------------------------------------------------------------- regional projection


def geodesic_regions(dist: Float[np.ndarray, "v v"], n_regions: int, start: int = 0) -> Int[np.ndarray, " v"]:
    """Region label (V,) of every vertex: furthest-point sampling of ``n_regions`` centres on the (normalized)
    geodesic distances, each vertex to its nearest centre (ties: the earlier centre)."""
    dist = np.asarray(dist)
    if dist.ndim != 2 or dist.shape[0] != dist.shape[1]:
        raise ValueError(f"dist must be a square (V, V) matrix, got shape {dist.shape}.")
    if not 1 <= n_regions <= dist.shape[0]:
        raise ValueError(f"n_regions must be in 1..{dist.shape[0]}, got {n_regions}.")
    centres = [int(start)]
    nearest = dist[start].copy()
    for _ in range(n_regions - 1):
        centres.append(int(nearest.argmax()))
        nearest = np.minimum(nearest, dist[centres[-1]])
    return dist[np.asarray(centres)].argmin(axis=0)


def regional_projection(
    train: Float[np.ndarray, "n v c"], test: Float[np.ndarray, "m v c"], labels: Int[np.ndarray, " v"]
) -> Float[np.ndarray, "m v c"]:
    """Each test shape, region by region, replaced by its least-squares fit in the span of the training
    shapes' deviations from their mean, restricted to that region.

    This is the best any model can do that reconstructs every region as a linear combination of the training
    shapes' deviations there (independently per region): a ceiling for localized linear components learned
    from these training shapes, and the reference point of the ``ceiling`` experiment.
    """
    train, test = np.asarray(train, np.float64), np.asarray(test, np.float64)
    if train.ndim != 3 or test.ndim != 3 or train.shape[1:] != test.shape[1:]:
        raise ValueError(f"train {train.shape} and test {test.shape} must be (N, V, c) with the same V and c.")
    labels = np.asarray(labels)
    if labels.shape != (train.shape[1],):
        raise ValueError(f"labels must have one entry per vertex ({train.shape[1]}), got shape {labels.shape}.")
    mean = train.mean(axis=0)
    out = np.empty_like(test)
    for r in np.unique(labels):
        idx = np.flatnonzero(labels == r)
        basis = (train[:, idx] - mean[idx]).reshape(train.shape[0], -1)  # (N, n_r c)
        target = (test[:, idx] - mean[idx]).reshape(test.shape[0], -1)
        coef = np.linalg.lstsq(basis.T, target.T, rcond=None)[0]  # (N, M)
        out[:, idx] = (coef.T @ basis).reshape(test.shape[0], idx.size, -1) + mean[idx]
    return out
