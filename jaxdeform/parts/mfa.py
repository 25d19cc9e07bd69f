"""Rotation-constrained mixtures of factor analyzers (seed 003): the model, AECM, labels, latent images.

Data: one vector per vertex, y_i = (p_i^1, ..., p_i^M) in R^{3M}, stored vertex-major as ``y`` (V, M, 3).
Part k is a factor analyzer

    y = mu_k + Lambda_k x + e,    x ~ N(0, I_3),    e ~ N(0, sigma_k^2 I_{3M}),
    Lambda_k = (R_k^1; ...; R_k^M) D_k,   mu_k = (t_k^1; ...; t_k^M),   D_k = diag(d_k) > 0,

with proper rotations R_k^m. Because Lambda^T Lambda = M D^2 is diagonal, every density and posterior has a
closed form with 3-vectors only (Woodbury): with r = y - mu, b = sum_m R_m^T r_m and c_j = sigma^2 + M d_j^2,

    log N(y | mu, Lambda Lambda^T + sigma^2 I) = -1/2 [3M log 2 pi + (3M - 3) log sigma^2 + sum_j log c_j
                                                      + (|r|^2 - sum_j d_j^2 b_j^2 / c_j) / sigma^2],
    E[x | y] = d * b / c,    Cov[x | y] = diag(sigma^2 / c).

AECM (McLachlan et al. 2003 with the rotation constraint of the paper), one iteration = two cycles:
- cycle 1: E-step (responsibilities tau), CM-step: pi_k = mean tau_ik, mu_k = tau-weighted mean of y;
- cycle 2: E-step with the new pi, mu (tau and the posterior moments of x), then three conditional
  maximizations of the expected complete-data log-likelihood, in order:
  R_k^m by Procrustes: the SVD U S V^T of A = sum_i tau_i r_im (d * E[x_i])^T gives R = U V^T, with the
  right-handed fix of Lemma 1 (negate the singular direction of the smallest singular value when
  det(U V^T) < 0) so R is always a proper rotation; then d_j (closed form given R); then sigma^2.
Every step maximizes its own objective exactly, so the observed log-likelihood never decreases (a
generalised EM); the paper's eigenvalue estimate of D (eq. 18) is used where parameters are initialised
from labels (:func:`init_from_weights`).

Vertex weights ``w`` (V,) in {0, 1} restrict a fit to a subset of vertices with static shapes, which is how
the hierarchy (``parts.hierarchy``) refines one part at a time without recompiling per subset.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

#: Lower bound of sigma^2 relative to the data's mean squared spread (keeps tiny parts from collapsing).
SIGMA2_FLOOR = 1e-9
#: Lower bound of the latent scales d_j relative to the data's spread.
D_FLOOR = 1e-6


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MFA:
    """Parameters of K rotation-constrained factor analyzers over M shapes (a pytree)."""

    log_pi: Float[Array, " k"]
    mu: Float[Array, "k m 3"]  # t_k^m
    rot: Float[Array, "k m 3 3"]  # R_k^m
    d: Float[Array, "k 3"]  # diagonal of D_k
    sigma2: Float[Array, " k"]

    @property
    def n_parts(self) -> int:
        return self.log_pi.shape[0]


# ------------------------------------------------------------------------------------------ algebra


def proper_procrustes(a: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """argmax over proper rotations R of tr(R^T A) (Lemma 1: flip the last singular direction if needed).

    **Arguments:**

    - ``a``: ``(..., 3, 3)``.

    **Returns:**

    Proper rotations ``(..., 3, 3)``.
    """
    u, _, vt = jnp.linalg.svd(a)
    det = jnp.linalg.det(u @ vt)
    flip = jnp.where(det < 0, -1.0, 1.0).astype(a.dtype)
    u = u.at[..., :, 2].multiply(flip[..., None])
    return u @ vt


def _projections(y, p: MFA):
    """b_ik = sum_m R_km^T (y_im - mu_km) (V, K, 3) and |y_i - mu_k|^2 (V, K), via matrix products."""
    v, m = y.shape[:2]
    yf = y.reshape(v, 3 * m)
    by = jnp.einsum("vn,knx->vkx", yf, p.rot.reshape(p.n_parts, 3 * m, 3))  # sum_m R^T y_m
    bmu = jnp.einsum("kmy,kmyx->kx", p.mu, p.rot)
    b = by - bmu[None]
    muf = p.mu.reshape(p.n_parts, 3 * m)
    r2 = jnp.sum(yf * yf, axis=1)[:, None] - 2.0 * yf @ muf.T + jnp.sum(muf * muf, axis=1)[None]
    return b, jnp.maximum(r2, 0.0)


def log_densities(y: Float[Array, "v m 3"], p: MFA) -> Float[Array, "v k"]:
    """log N(y_i | mu_k, Sigma_k) for every vertex and part.

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``p``: the mixture's parameters.

    **Returns:**

    ``(V, K)``.
    """
    m = y.shape[1]
    b, r2 = _projections(y, p)
    c = p.sigma2[:, None] + m * p.d**2  # (K, 3)
    maha = (r2 - jnp.sum((p.d**2 / c)[None] * b * b, axis=-1)) / p.sigma2[None]
    logdet = (3 * m - 3) * jnp.log(p.sigma2) + jnp.sum(jnp.log(c), axis=-1)
    return -0.5 * (3 * m * math.log(2 * math.pi) + logdet[None] + maha)


def e_step(y, w, p: MFA):
    """The E-step.

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``w``: per-vertex weights ``(V,)``.
    - ``p``: the mixture's parameters.

    **Returns:**

    ``(responsibilities (V, K), weighted log-likelihood sum_i w_i log sum_k pi_k N_ik)``.
    """
    lj = p.log_pi[None] + log_densities(y, p)
    lse = jax.scipy.special.logsumexp(lj, axis=1)
    return jnp.exp(lj - lse[:, None]), jnp.sum(w * lse)


def posterior(y, p: MFA):
    """The latent posterior of every vertex in every part.

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``p``: the mixture's parameters.

    **Returns:**

    ``(E[x | y_i, k] (V, K, 3), the diagonal of Cov[x | y, k] (K, 3))``.
    """
    m = y.shape[1]
    b, _ = _projections(y, p)
    c = p.sigma2[:, None] + m * p.d**2
    return (p.d / c)[None] * b, p.sigma2[:, None] / c


def log_likelihood(y, w, p: MFA) -> Array:
    """The weighted log-likelihood sum_i w_i log sum_k pi_k N_ik (:func:`e_step`'s second output).

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``w``: per-vertex weights ``(V,)``.
    - ``p``: the mixture's parameters.

    **Returns:**

    A scalar array.
    """
    return e_step(y, w, p)[1]


# ---------------------------------------------------------------------------------------------- AECM


def _scale_floor(y, w):
    """Mean squared distance of the (weighted) data vectors to their mean, per coordinate."""
    ww = w / jnp.sum(w)
    mean = jnp.einsum("v,vmx->mx", ww, y)
    return jnp.einsum("v,vmx->", ww, (y - mean) ** 2) / (3 * y.shape[1])


def cycle1(y, w, p: MFA) -> MFA:
    """The AECM's first cycle: mixing weights pi and translations mu from the responsibilities.

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``w``: per-vertex weights ``(V,)``.
    - ``p``: the mixture's parameters.

    **Returns:**

    ``p`` with new ``log_pi`` and ``mu``.
    """
    tau, _ = e_step(y, w, p)
    tw = tau * w[:, None]
    n = jnp.sum(tw, axis=0) + 1e-12
    mu = jnp.einsum("vk,vmx->kmx", tw, y) / n[:, None, None]
    log_pi = jnp.log(n / jnp.sum(n))
    return dataclasses.replace(p, log_pi=log_pi, mu=mu)


def cycle2(y, w, p: MFA, floor) -> MFA:
    """The AECM's second cycle: rotations R (Procrustes), scales d and noise sigma^2 from the latent posterior.

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``w``: per-vertex weights ``(V,)``.
    - ``p``: the mixture's parameters.
    - ``floor``: the data's scale floor; d and sigma^2 are kept above multiples of it.

    **Returns:**

    ``p`` with new ``rot``, ``d`` and ``sigma2``.
    """
    m = y.shape[1]
    tau, _ = e_step(y, w, p)
    tw = tau * w[:, None]
    n = jnp.sum(tw, axis=0) + 1e-12
    ex, cov = posterior(y, p)  # (V, K, 3), (K, 3)
    # R: Procrustes of A_km = sum_i tau_ik (y_im - mu_km) (d * E x_ik)^T
    dex = p.d[None] * ex
    s_ydx = jnp.einsum("vk,vmx,vky->kmxy", tw, y, dex)
    s_dx = jnp.einsum("vk,vky->ky", tw, dex)
    a = s_ydx - p.mu[..., :, None] * s_dx[:, None, None, :]
    rot = proper_procrustes(a)
    p = dataclasses.replace(p, rot=rot)
    # d: maximize sum_i tau [d.(b * Ex) - M/2 sum_j d_j^2 (Ex_j^2 + cov_j)] with the new R
    b, r2 = _projections(y, p)
    s_bx = jnp.einsum("vk,vkx->kx", tw, b * ex)
    s_xx = jnp.einsum("vk,vkx->kx", tw, ex * ex) + n[:, None] * cov
    d = jnp.maximum(s_bx / (m * s_xx), D_FLOOR * jnp.sqrt(floor))
    # sigma^2: mean expected squared residual per coordinate
    dbx = jnp.einsum("vk,vkx->k", tw, (d[None] * b) * ex)
    dxx = m * jnp.sum(d**2 * s_xx, axis=-1)
    sse = jnp.einsum("vk,vk->k", tw, r2) - 2.0 * dbx + dxx
    sigma2 = jnp.maximum(sse / (3 * m * n), SIGMA2_FLOOR * floor)
    return dataclasses.replace(p, d=d, sigma2=sigma2)


#: AECM stops when an iteration gains less than this fraction of |log-likelihood| (horse-poses: the
#: labels then differ from a 50-iteration run on ~0.1% of the vertices).
TOL = 1e-4
MAX_ITER = 100


@functools.partial(jax.jit, static_argnames=("max_iter",))
def aecm(y: Float[Array, "v m 3"], w: Float[Array, " v"], p0: MFA, *, max_iter: int = MAX_ITER, tol: float = TOL):
    """Run AECM from ``p0`` until an iteration gains less than ``tol`` times |log-likelihood|.

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``w``: per-vertex weights ``(V,)``.
    - ``p0``: the starting parameters.
    - ``max_iter``: the most iterations.
    - ``tol``: the relative gain below which the iteration stops.

    **Returns:**

    ``(parameters, history, iterations)``: the fitted :class:`MFA`, the log-likelihood history ``(max_iter + 1,)``
    with NaN after the last iteration (history[0] is the log-likelihood of ``p0``), and the iterations run.
    """
    floor = _scale_floor(y, w)
    scale = jnp.sum(w) * y.shape[1]  # a floor for |L| near 0 (one nat per weighted vertex and shape)
    hist0 = jnp.full((max_iter + 1,), jnp.nan, y.dtype).at[0].set(log_likelihood(y, w, p0))

    def cond(state):
        _, hist, it = state
        gain = (hist[it] - hist[jnp.maximum(it - 1, 0)]) / jnp.maximum(jnp.abs(hist[it]), scale)
        return (it < max_iter) & ((it == 0) | (gain > tol))

    def body(state):
        p, hist, it = state
        p = cycle2(y, w, cycle1(y, w, p), floor)
        hist = hist.at[it + 1].set(log_likelihood(y, w, p))
        return p, hist, it + 1

    p, hist, it = jax.lax.while_loop(cond, body, (p0, hist0, jnp.asarray(0)))
    return p, hist, it


# ------------------------------------------------------------------------------------ initialisation


def init_from_weights(y: Float[Array, "v m 3"], resp: Float[Array, "v k"], procrustes_iters: int = 4) -> MFA:
    """Parameters from (hard or soft) assignments: per-part generalised Procrustes alignment.

    mu_km = weighted centroid of part k in shape m; the latent cloud z starts as shape 0 and is re-estimated
    as the mean of the shapes rotated back; the latent frame is put on the principal axes of z, and D from
    the eigenvalues of z's covariance (paper eq. 18); sigma^2 from the residual.

    **Arguments:**

    - ``y``: normalised shapes ``(V, M, 3)``.
    - ``resp``: assignments ``(V, K)``.
    - ``procrustes_iters``: the alignment's iterations.

    **Returns:**

    The initial :class:`MFA`.
    """
    return _init_from_weights(jnp.asarray(y), jnp.asarray(resp, y.dtype), procrustes_iters)


@functools.partial(jax.jit, static_argnames=("procrustes_iters",))
def _init_from_weights(y, resp, procrustes_iters: int) -> MFA:
    v, m = y.shape[:2]
    n = jnp.sum(resp, axis=0) + 1e-12  # (K,)
    mu = jnp.einsum("vk,vmx->kmx", resp, y) / n[:, None, None]
    k = resp.shape[1]
    z = jnp.broadcast_to(y[:, None, 0, :] - mu[None, :, 0, :], (v, k, 3))  # latent: shape 0, centred

    def align(z):
        # A_km = sum_i resp_ik (y_im - mu_km) z_ik^T ; R = proper Procrustes ; z = mean_m R^T (y - mu)
        a = (
            jnp.einsum("vk,vmx,vky->kmxy", resp, y, z)
            - mu[..., :, None] * jnp.einsum("vk,vky->ky", resp, z)[:, None, None, :]
        )
        rot = proper_procrustes(a)
        zn = (jnp.einsum("vmx,kmxy->vky", y, rot) - jnp.einsum("kmx,kmxy->ky", mu, rot)[None]) / m
        return zn, rot

    rot = None
    for _ in range(procrustes_iters):
        z, rot = align(z)
    # principal axes of the latent cloud: z = E diag(lambda) E^T, descending, proper E
    cov = jnp.einsum("vk,vkx,vky->kxy", resp, z, z) / n[:, None, None]
    lam, vec = jnp.linalg.eigh(cov)
    lam, vec = lam[:, ::-1], vec[:, :, ::-1]
    vec = vec.at[:, :, 2].multiply(jnp.sign(jnp.linalg.det(vec))[:, None])
    rot = rot @ vec[:, None]
    z = jnp.einsum("vkx,kxy->vky", z, vec)
    floor = _scale_floor(y, jnp.minimum(jnp.sum(resp, axis=1), 1.0))  # the floor AECM uses on these vertices
    d = jnp.sqrt(jnp.maximum(lam, (D_FLOOR**2) * floor))
    # sum_m |y_m - mu_m - R_m z|^2 = |y - mu|^2 - 2 z.b + M |z|^2 (b = sum_m R_m^T (y_m - mu_m)): no (V, K, M, 3)
    b, r2 = _projections(y, MFA(log_pi=jnp.zeros(k, y.dtype), mu=mu, rot=rot, d=d, sigma2=jnp.ones(k, y.dtype)))
    sse = jnp.einsum("vk,vk->k", resp, r2 - 2.0 * jnp.sum(z * b, axis=-1) + m * jnp.sum(z * z, axis=-1))
    sigma2 = jnp.maximum(sse / (3 * m * n), SIGMA2_FLOOR * floor)
    return MFA(log_pi=jnp.log(n / jnp.sum(n)), mu=mu, rot=rot, d=d, sigma2=sigma2)


def kmeans_labels(y: np.ndarray, k: int, w: np.ndarray | None = None, *, seed: int = 0, iters: int = 30) -> np.ndarray:
    """k-means (k-means++ start, fixed seed) of the weighted vertices' trajectories.

    **Arguments:**

    - ``y``: shapes ``(V, M, 3)`` (each vertex's trajectory is one point).
    - ``k``: the number of clusters.
    - ``w``: per-vertex weights ``(V,)`` (default None: all ones); vertices of weight 0 are left out.
    - ``seed``: the seed of the k-means++ start.
    - ``iters``: Lloyd iterations.

    **Returns:**

    The labels ``(V,)``, -1 where w = 0.
    """
    x = np.asarray(y, np.float64).reshape(y.shape[0], -1)
    idx = np.flatnonzero(np.ones(len(x), bool) if w is None else np.asarray(w) > 0)
    xs = x[idx]
    rng = np.random.default_rng(seed)
    centres = [xs[rng.integers(len(xs))]]
    d2 = np.sum((xs - centres[0]) ** 2, axis=1)
    for _ in range(1, k):
        c = xs[rng.choice(len(xs), p=d2 / d2.sum())] if d2.sum() > 0 else xs[rng.integers(len(xs))]
        centres.append(c)
        d2 = np.minimum(d2, np.sum((xs - c) ** 2, axis=1))
    c = np.stack(centres)
    lab = np.zeros(len(xs), np.int64)
    for _ in range(iters):
        dist = np.sum(xs * xs, 1)[:, None] - 2 * xs @ c.T + np.sum(c * c, 1)[None]
        new = np.argmin(dist, axis=1)
        for j in range(k):
            sel = new == j
            if sel.any():
                c[j] = xs[sel].mean(axis=0)
        if np.array_equal(new, lab):
            break
        lab = new
    out = np.full(len(x), -1, np.int64)
    out[idx] = lab
    return out


def one_hot(labels: np.ndarray, k: int, dtype=np.float64) -> np.ndarray:
    """One-hot matrix of labels.

    **Arguments:**

    - ``labels``: ``(V,)`` in [0, K), or -1.
    - ``k``: K.
    - ``dtype``: the dtype of the result.

    **Returns:**

    ``(V, K)``; rows of -1 are all zero.
    """
    labels = np.asarray(labels)
    oh = np.zeros((labels.shape[0], k), dtype)
    ok = labels >= 0
    oh[np.flatnonzero(ok), labels[ok]] = 1.0
    return oh


# ----------------------------------------------------------------------------------- derived outputs


def labels_of(y, p: MFA) -> np.ndarray:
    """Maximum-responsibility part of every vertex (eq. 20).

    **Arguments:**

    - ``y``: shapes ``(V, M, 3)``.
    - ``p``: the mixture's parameters.

    **Returns:**

    The labels ``(V,)`` in [0, K).
    """
    tau, _ = jax.jit(e_step)(y, jnp.ones(y.shape[0], y.dtype), p)
    return np.asarray(jnp.argmax(tau, axis=1))


@jax.jit
def latent_images(y, p: MFA, labels) -> Float[Array, "v 3"]:
    """Latent image z_i = D_k E[x | y_i, k] of every vertex in its part k = labels[i] (eq. 21).

    **Arguments:**

    - ``y``: shapes ``(V, M, 3)``.
    - ``p``: the mixture's parameters.
    - ``labels``: the part of every vertex ``(V,)``.

    **Returns:**

    The latent images ``(V, 3)``.
    """
    ex, _ = posterior(y, p)
    z = p.d[None] * ex  # (V, K, 3)
    return jnp.take_along_axis(z, labels[:, None, None], axis=1)[:, 0]


@jax.jit
def reconstruct(p: MFA, labels, z) -> Float[Array, "m v 3"]:
    """Shape m, vertex i: R_k^m z_i + t_k^m with k = labels[i] (eq. 22).

    **Arguments:**

    - ``p``: the mixture's parameters.
    - ``labels``: the part of every vertex ``(V,)``.
    - ``z``: the latent images ``(V, 3)``.

    **Returns:**

    The reconstructed shapes ``(M, V, 3)``.
    """
    rot = p.rot[labels]  # (V, M, 3, 3)
    return jnp.einsum("vmxy,vy->mvx", rot, z) + jnp.swapaxes(p.mu[labels], 0, 1)
