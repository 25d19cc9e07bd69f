"""Losses of the seed-000 autoencoder block (Sec. 4.1, eq. (2)): L = l1 L_recon + l2 Omega(C) + V(Z).

- ``reconstruction_loss``: the paper writes L_recon = (1/N) sum_m ||X_m - X_hat_m||_2^2, i.e. the squared
  norm over all V*9 entries summed per shape and averaged over shapes. That is the default
  (``reduction="shape"``); ``reduction="element"`` gives the plain element-wise mean (= the former / 9V).
- ``group_sparsity``: Omega(C) = (1/Kz) sum_k sum_i Lambda_ik ||C_k,i||_2 with the step mask of eq. (3),
  Lambda_ik = 0 if d(c_k, i) < d else 1, centre c_k = argmax_i ||C_k,i||_2 recomputed at every call;
  or Tan et al.'s clipped-linear mask clip((d(c_k, i) - 0.2) / (0.4 - 0.2), 0, 1) (``mask="linear"``).
- ``latent_bound``: V(Z) = (1/Kz) sum_k max(max_m |Z_mk| - theta, 0), theta = 5 (as in the paper).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jaxdeform.typing import Int

MU = 9

#: A float or a scalar array (a tracer where the caller jits over it).
FloatScalar = Float[ArrayLike, ""]


def reconstruction_loss(
    x: Float[ArrayLike, "b v 9"], x_hat: Float[ArrayLike, "b v 9"], reduction: str = "shape"
) -> Float[Array, ""]:
    """MSE reconstruction loss.

    **Arguments:**

    - `x`: features `(B, V, 9)`.
    - `x_hat`: reconstructions `(B, V, 9)`.
    - `reduction`: "shape" (paper): mean over shapes of the summed squared error; "element": mean over all entries.

    **Returns:**

    A scalar.

    **Raises:**

    `ValueError` for an unknown reduction.
    """
    sq = jnp.square(x - x_hat)
    if reduction == "shape":
        return jnp.mean(jnp.sum(sq.reshape(sq.shape[0], -1), axis=1))
    if reduction == "element":
        return jnp.mean(sq)
    raise ValueError(f"reduction must be 'shape' or 'element', got {reduction!r}.")


def _sqrt_or_zero(sq: Array) -> Array:
    """sqrt(sq) with a zero (finite) gradient where sq = 0."""
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def vertex_squared_norms(C: Float[ArrayLike, "kz nine_v"], n_vertices: int) -> Float[Array, "kz v"]:
    """Squared per-vertex norms ||C_k,i||_2^2 of every component.

    **Arguments:**

    - `C`: components `(Kz, 9V)`; rows are `(V, 9)` blocks, vertex-major.
    - `n_vertices`: V.

    **Returns:**

    `(Kz, V)`.
    """
    return jnp.sum(jnp.square(C.reshape(C.shape[0], n_vertices, MU)), axis=-1)


def vertex_norms(C: Float[ArrayLike, "kz nine_v"], n_vertices: int) -> Float[Array, "kz v"]:
    """Per-vertex norms ||C_k,i||_2 of every component.

    **Arguments:**

    - `C`: components `(Kz, 9V)`; rows are `(V, 9)` blocks, vertex-major.
    - `n_vertices`: V.

    **Returns:**

    `(Kz, V)`, with a finite (zero) gradient at zero norms.
    """
    return _sqrt_or_zero(vertex_squared_norms(C, n_vertices))


def component_centres(C: Float[ArrayLike, "kz nine_v"], n_vertices: int) -> Int[Array, " kz"]:
    """The component centres c_k = argmax_i ||C_k,i||_2.

    **Arguments:**

    - `C`: components `(Kz, 9V)`.
    - `n_vertices`: V.

    **Returns:**

    int32 vertex indices `(Kz,)` (first index on ties).
    """
    return _centres(vertex_squared_norms(C, n_vertices))


def _centres(sq: Float[Array, "kz v"]) -> Int[Array, " kz"]:
    return jnp.argmax(sq, axis=1).astype(jnp.int32)


def geodesic_step_mask(
    dist: Float[ArrayLike, "v v"], centres: Int[ArrayLike, " kz"], d: FloatScalar
) -> Float[Array, "kz v"]:
    """The step mask of eq. 3: Lambda_ik = 0 where the normalized geodesic distance dist[c_k, i] < d, else 1.

    **Arguments:**

    - `dist`: normalized geodesic distances `(V, V)`.
    - `centres`: component centres `(Kz,)`.
    - `d`: the cut-off.

    **Returns:**

    The mask `(Kz, V)` in dist's dtype.
    """
    return (dist[centres, :] >= d).astype(dist.dtype)


def geodesic_linear_mask(
    dist: Float[ArrayLike, "v v"], centres: Int[ArrayLike, " kz"], d_min: FloatScalar, d_max: FloatScalar
) -> Float[Array, "kz v"]:
    """Tan et al. (2018)'s mask: Lambda_ik = clip((dist[c_k, i] - d_min) / (d_max - d_min), 0, 1).

    **Arguments:**

    - `dist`: normalized geodesic distances `(V, V)`.
    - `centres`: component centres `(Kz,)`.
    - `d_min`, `d_max`: the ramp's ends.

    **Returns:**

    The mask `(Kz, V)` in dist's dtype.
    """
    return jnp.clip((dist[centres, :] - d_min) / (d_max - d_min), 0.0, 1.0).astype(dist.dtype)


def _sparsity_terms(C, dist, d, mask):
    """(Lambda, ||C_k,i||) of :func:`group_sparsity`, the mask without gradient."""
    # the squared vertex norms once, for the centres and the norms: computed apart, XLA on CPU reads C (15 MB on
    # level 1 of the horse model) once for each
    sq = vertex_squared_norms(C, dist.shape[0])
    centres = jax.lax.stop_gradient(_centres(sq))
    if mask == "step":
        lam = geodesic_step_mask(dist, centres, d)
    elif mask == "linear":
        lam = geodesic_linear_mask(dist, centres, *d)
    else:
        raise ValueError(f"mask must be 'step' or 'linear', got {mask!r}.")
    return jax.lax.stop_gradient(lam).astype(C.dtype), _sqrt_or_zero(sq)


def group_sparsity(
    C: Float[ArrayLike, "kz nine_v"],
    dist: Float[ArrayLike, "v v"],
    d: FloatScalar | tuple[FloatScalar, FloatScalar],
    mask: str = "step",
) -> Float[Array, ""]:
    """The group sparsity Omega(C) = (1/Kz) sum_k sum_i Lambda_ik ||C_k,i||_2, centres recomputed from C.

    **Arguments:**

    - `C`: components `(Kz, 9V)`.
    - `dist`: normalized geodesic distances `(V, V)`.
    - `d`: the cut-off for `mask="step"`; `(d_min, d_max)` for `mask="linear"`.
    - `mask`: "step" (seed 000, eq. 3) or "linear" (Tan et al.).

    **Returns:**

    A scalar; no gradient flows through the centres or the mask.

    **Raises:**

    `ValueError` for an unknown mask.
    """
    lam, norms = _sparsity_terms(C, dist, d, mask)
    return jnp.sum(lam * norms) / C.shape[0]


def latent_bound(z: Float[ArrayLike, "n kz"], theta: FloatScalar = 5.0) -> Float[Array, ""]:
    """The latent bound V(Z) = (1/Kz) sum_k max(max_m |Z_mk| - theta, 0).

    **Arguments:**

    - `z`: codes `(N, Kz)`.
    - `theta`: the bound.

    **Returns:**

    A scalar.
    """
    peak = jnp.max(jnp.abs(z), axis=0)
    return jnp.mean(jnp.maximum(peak - theta, 0.0))
