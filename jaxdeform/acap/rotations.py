"""Batched 3x3 algebra in closed form: inverse, polar decomposition, rotation log/exp.

Layout. Per-matrix LAPACK calls dominate batched 3x3 work on CPU (jnp.linalg.svd is far slower than the closed
forms here), and so do XLA's small matrix products and reductions over a trailing axis of size 3. The
kernels here therefore work "component-major": a matrix is a ``(3, 3, *batch)`` array and a vector a
``(3, *batch)`` array, so that every operation is an elementwise loop over the (long, contiguous) batch
that XLA fuses. The functions named ``*_cm`` take and return that layout; the public functions without the
suffix take the usual ``(..., 3, 3)`` / ``(..., 3)`` layout and move the axes around the same kernels.

Numerics
- ``polar``: scaled Newton iteration X <- (g X + (g X)^-T) / 2 (fixed count, differentiable), giving the
  orthogonal polar factor Q and P = sym(Q^T T). When det T < 0 the official ACAP convention is followed:
  the direction of the smallest singular value is reflected so that R is a proper rotation and S = R^T T
  carries the negative singular value.
- ``log_rotation``: theta = atan2(|w|, (tr R - 1)/2) with w = vee(R - R^T)/2 = sin(theta) axis, which is
  accurate at every angle; below 120 degrees log = w theta / sin(theta) (series at 0), above it the axis is
  read from the symmetric part (R + R^T)/2 - cos(theta) I = (1 - cos(theta)) a a^T, signed by w. Values
  and gradients are finite at the identity and at 180 degrees.
- ``exp_rotation``: Rodrigues with Taylor series near 0; valid for any angle (the consistent angles
  run past pi and past 2 pi).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

NEWTON_STEPS = 7
# gathered reflection fixes for up to 1/256 or 1/16 of the entries; beyond that the whole batch is fixed
REFLECTION_SHARES = (256, 16)

# ------------------------------------------------------------------------------- layout conversion


def to_cm(a: jax.typing.ArrayLike, rank: int = 2) -> Array:
    """Move the trailing matrix or vector axes to the front (component-major layout).

    **Arguments:**

    - `a`: an array `(..., 3, 3)` (rank 2) or `(..., 3)` (rank 1).
    - `rank`: 2 for matrices, 1 for vectors.

    **Returns:**

    The same entries as `(3, 3, ...)` or `(3, ...)`.
    """
    return jnp.moveaxis(a, tuple(range(a.ndim - rank, a.ndim)), tuple(range(rank)))


def from_cm(a: Array, rank: int = 2) -> Array:
    """Inverse of :func:`to_cm`.

    **Arguments:**

    - `a`: a component-major array `(3, 3, ...)` or `(3, ...)`.
    - `rank`: 2 for matrices, 1 for vectors.

    **Returns:**

    The same entries as `(..., 3, 3)` or `(..., 3)`.
    """
    return jnp.moveaxis(a, tuple(range(rank)), tuple(range(a.ndim - rank, a.ndim)))


# ------------------------------------------------------------------------ component-major kernels


def eye_cm(batch: tuple, dtype) -> Array:
    """The identity matrix, component-major, broadcast over a batch.

    **Arguments:**

    - `batch`: the batch shape.
    - `dtype`: the dtype.

    **Returns:**

    An array `(3, 3, *batch)`.
    """
    eye = jnp.eye(3, dtype=dtype).reshape((3, 3) + (1,) * len(batch))
    return jnp.broadcast_to(eye, (3, 3) + tuple(batch))


def mv_cm(a: Array, v: Array) -> Array:
    """Matrix-vector product, component-major, written out entry by entry (XLA fuses it into one loop).

    **Arguments:**

    - `a`: matrices `(3, 3, *batch)`.
    - `v`: vectors `(3, *batch)`.

    **Returns:**

    `a @ v`, shape `(3, *batch)`.
    """
    return jnp.stack([a[i, 0] * v[0] + a[i, 1] * v[1] + a[i, 2] * v[2] for i in range(3)])


def mm_cm(a: Array, b: Array) -> Array:
    """Matrix product, component-major, entry by entry.

    **Arguments:**

    - `a`, `b`: matrices `(3, 3, *batch)`.

    **Returns:**

    `a @ b`, shape `(3, 3, *batch)`.
    """
    return jnp.stack([mv_cm(a, b[:, k]) for k in range(3)], axis=1)


def t_cm(a: Array) -> Array:
    """Transpose of component-major matrices `(3, 3, *batch)`; returns the same shape."""
    return jnp.swapaxes(a, 0, 1)


def outer_cm(u: Array, v: Array) -> Array:
    """Outer product u v^T of component-major vectors `(3, *batch)`; returns `(3, 3, *batch)`."""
    return u[:, None] * v[None]


def cross_cm(u: Array, v: Array) -> Array:
    """Cross product of component-major vectors `(3, *batch)`; returns `(3, *batch)`."""
    return jnp.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def det_cm(a: Array) -> Array:
    """Determinant of component-major matrices `(3, 3, *batch)`; returns `(*batch)`."""
    return (
        a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
        - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
        + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])
    )


def adjugate_cm(a: Array) -> Array:
    """The adjugate adj(A): its rows are the cross products of pairs of columns of A.

    **Arguments:**

    - `a`: component-major matrices `(3, 3, *batch)`.

    **Returns:**

    adj(A), shape `(3, 3, *batch)`.
    """
    c0, c1, c2 = a[:, 0], a[:, 1], a[:, 2]
    return jnp.stack([cross_cm(c1, c2), cross_cm(c2, c0), cross_cm(c0, c1)])


def inv_cm(a: Array) -> Array:
    """Inverse adj(A) / det(A) of component-major matrices `(3, 3, *batch)` (not finite where det A = 0)."""
    return adjugate_cm(a) / det_cm(a)


def _sum3(x: Array) -> Array:
    """x[0] + x[1] + x[2]: a sum over a leading axis of size 3 as elementwise adds (XLA on CPU runs short
    reductions and argmaxes much slower than the same arithmetic written out)."""
    return x[0] + x[1] + x[2]


def frob_cm(a: Array) -> Array:
    """Frobenius norm of component-major matrices `(3, 3, *batch)`; returns `(*batch)`."""
    return jnp.sqrt(_sum3(_sum3(a * a)))


def sym_cm(a: Array) -> Array:
    """Symmetric part (A + A^T) / 2 of component-major matrices `(3, 3, *batch)`."""
    return 0.5 * (a + t_cm(a))


def _smallest_eigvec_cm(p: Array) -> Array:
    """Eigenvector of the smallest eigenvalue of an SPD matrix (repeated squaring of adj(P))."""

    def square(_, m):
        m = mm_cm(m, m)
        return m / jnp.maximum(frob_cm(m), 1e-30)

    # eigenvalues of adj(P): s2 s3, s1 s3, s1 s2; the largest belongs to the smallest of P
    m = jax.lax.fori_loop(0, 6, square, adjugate_cm(p))
    norms = _sum3(m * m)  # (3, *batch): squared column norms
    first = (norms[0] >= norms[1]) & (norms[0] >= norms[2])  # argmax, written out (see _sum3)
    second = ~first & (norms[1] >= norms[2])
    col = jnp.where(first, m[:, 0], jnp.where(second, m[:, 1], m[:, 2]))
    return col / jnp.sqrt(jnp.maximum(_sum3(col * col), 1e-30))


def polar_cm(t: Array, steps: int = NEWTON_STEPS) -> tuple[Array, Array]:
    """Polar decomposition T = R S, component-major, with R a proper rotation and S symmetric.

    **Arguments:**

    - `t`: matrices `(3, 3, *batch)`.
    - `steps`: number of scaled Newton steps.

    **Returns:**

    `(r, s)`, both `(3, 3, *batch)`; official sign convention when det T < 0 (module docstring).
    """

    def newton(_, x):
        xinv = inv_cm(x)
        g = jnp.sqrt(frob_cm(xinv) / frob_cm(x))
        return 0.5 * (g * x + t_cm(xinv) / g)

    # A loop, not unrolled: unrolled, XLA on CPU fuses the steps and recomputes shared terms.
    x = jax.lax.fori_loop(0, steps, newton, t)
    p = sym_cm(mm_cm(t_cm(x), t))
    neg = det_cm(t) < 0
    batch = t.shape[2:]
    n = math.prod(batch)

    def house(p):
        v = _smallest_eigvec_cm(p)
        return eye_cm(v.shape[1:], t.dtype) - 2.0 * outer_cm(v, v)

    def reflect_all(x, p):
        h = house(jnp.where(neg, p, eye_cm(batch, t.dtype)))
        return jnp.where(neg, mm_cm(x, h), x), jnp.where(neg, mm_cm(h, p), p)

    def reflect_few(cap, x, p):
        # gather the (rare) reflected entries, fix them, scatter back; padding indices n are dropped
        idx = jnp.nonzero(neg.reshape(n), size=cap, fill_value=n)[0]
        xf, pf = x.reshape(3, 3, n), p.reshape(3, 3, n)
        xs, ps = xf[:, :, idx], pf[:, :, idx]  # out-of-range indices are clamped (and dropped below)
        h = house(ps)
        xf = xf.at[:, :, idx].set(mm_cm(xs, h), mode="drop")
        pf = pf.at[:, :, idx].set(mm_cm(h, ps), mode="drop")
        return xf.reshape(x.shape), pf.reshape(p.shape)

    # Reflections are rare (a small fraction of vertex-frames): fix only those entries when they are few,
    # with a gathered batch of one of a few static capacities.
    caps = sorted({max(1, n // share) for share in REFLECTION_SHARES})
    count = jnp.sum(neg.astype(jnp.int32))
    branch = jnp.sum(jnp.asarray([count > c for c in caps], jnp.int32)) + jnp.where(count > 0, 1, 0)
    branches = [lambda x, p: (x, p)] + [functools.partial(reflect_few, c) for c in caps] + [reflect_all]
    return jax.lax.switch(branch, branches, x, p)


def skew_cm(v: Array) -> Array:
    """Skew matrices `(3, 3, *batch)` of component-major vectors `(3, *batch)` (K u = v x u)."""
    z = jnp.zeros_like(v[0])
    x, y, w = v[0], v[1], v[2]
    return jnp.stack([jnp.stack([z, -w, y]), jnp.stack([w, z, -x]), jnp.stack([-y, x, z])])


def vee_cm(k: Array) -> Array:
    """The vector (K_21, K_02, K_10) of a skew matrix (antisymmetric part taken first).

    **Arguments:**

    - `k`: component-major matrices `(3, 3, *batch)`.

    **Returns:**

    Vectors `(3, *batch)`.
    """
    return 0.5 * jnp.stack([k[2, 1] - k[1, 2], k[0, 2] - k[2, 0], k[1, 0] - k[0, 1]])


def _safe_norm0(v: Array) -> Array:
    """|v| over axis 0 with value 0 and a finite gradient at zero vectors."""
    sq = _sum3(v * v)
    ok = sq > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def log_rotation_cm(r: Array) -> Array:
    """Rotation log as axis-angle vectors, component-major.

    **Arguments:**

    - `r`: rotations `(3, 3, *batch)`.

    **Returns:**

    Axis-angle vectors `(3, *batch)` with theta in [0, pi]; values and gradients finite at 0 and pi.
    """
    w = vee_cm(r)
    sin = _safe_norm0(w)
    c = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)
    theta = jnp.arctan2(sin, c)
    # Small and medium angles: theta / sin(theta) * w.
    small = sin < 1e-4
    ratio = jnp.where(small, 1.0 + sin * sin / 6.0, theta / jnp.where(small, 1.0, sin))
    v_mid = w * ratio
    # Large angles: axis from the symmetric part.
    one_minus_c = jnp.maximum(1.0 - c, 0.5)  # only used where c < -0.5
    aat = (sym_cm(r) - c * eye_cm(r.shape[2:], r.dtype)) / one_minus_c
    diag = jnp.stack([aat[0, 0], aat[1, 1], aat[2, 2]])
    first = (diag[0] >= diag[1]) & (diag[0] >= diag[2])
    second = ~first & (diag[1] >= diag[2])
    col = jnp.where(first, aat[:, 0], jnp.where(second, aat[:, 1], aat[:, 2]))
    dk = jnp.where(first, diag[0], jnp.where(second, diag[1], diag[2]))
    axis = col / jnp.sqrt(jnp.maximum(dk, 1e-12))
    sign = jnp.where(_sum3(axis * w) < 0, -1.0, 1.0).astype(r.dtype)
    return jnp.where(c < -0.5, axis * (sign * theta), v_mid)


def exp_rotation_cm(v: Array) -> Array:
    """Rodrigues' formula, component-major, for any angle.

    **Arguments:**

    - `v`: axis-angle vectors `(3, *batch)`.

    **Returns:**

    Rotations `(3, 3, *batch)`.
    """
    th2 = _sum3(v * v)
    small = th2 < 1e-6
    th2s = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2s)
    a = jnp.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - jnp.cos(th)) / th2s)
    # K^2 = v v^T - theta^2 I, so R = (1 - b theta^2) I + a K + b v v^T.
    return (1.0 - b * th2) * eye_cm(v.shape[1:], v.dtype) + a * skew_cm(v) + b * outer_cm(v, v)


# ------------------------------------------------------------------------------ public (..., 3, 3)


def det3(a: Float[jax.typing.ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch"]:
    """Determinant of 3x3 matrices in closed form.

    **Arguments:**

    - `a`: matrices `(..., 3, 3)`.

    **Returns:**

    Determinants `(...)`.
    """
    return det_cm(to_cm(a))


def adjugate3(a: Float[jax.typing.ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3 3"]:
    """Adjugate of 3x3 matrices in closed form.

    **Arguments:**

    - `a`: matrices `(..., 3, 3)`.

    **Returns:**

    adj(A), shape `(..., 3, 3)`.
    """
    return from_cm(adjugate_cm(to_cm(a)))


def inv3(a: Float[jax.typing.ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3 3"]:
    """Inverse of 3x3 matrices in closed form (adjugate over determinant).

    **Arguments:**

    - `a`: matrices `(..., 3, 3)`.

    **Returns:**

    A^-1, shape `(..., 3, 3)`; not finite where det A = 0.
    """
    return from_cm(inv_cm(to_cm(a)))


def sym(a: jax.typing.ArrayLike) -> Array:
    """Symmetric part (A + A^T) / 2.

    **Arguments:**

    - `a`: matrices `(..., n, n)`.

    **Returns:**

    The symmetric part, same shape.
    """
    return 0.5 * (a + jnp.swapaxes(a, -1, -2))


def polar(
    t: Float[jax.typing.ArrayLike, "*batch 3 3"], steps: int = NEWTON_STEPS
) -> tuple[Float[Array, "*batch 3 3"], Float[Array, "*batch 3 3"]]:
    """Polar decomposition T = R S with R a proper rotation and S symmetric.

    **Arguments:**

    - `t`: matrices `(..., 3, 3)`.
    - `steps`: number of scaled Newton steps.

    **Returns:**

    `(r, s)`, both `(..., 3, 3)`; official ACAP sign convention when det T < 0. Differentiable.
    """
    r, s = polar_cm(to_cm(t), steps)
    return from_cm(r), from_cm(s)


def skew(v: Float[jax.typing.ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Skew matrices of vectors (K u = v x u).

    **Arguments:**

    - `v`: vectors `(..., 3)`.

    **Returns:**

    Skew matrices `(..., 3, 3)`.
    """
    return from_cm(skew_cm(to_cm(v, 1)))


def vee(k: Float[jax.typing.ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Inverse of :func:`skew` (antisymmetric part taken first).

    **Arguments:**

    - `k`: matrices `(..., 3, 3)`.

    **Returns:**

    Vectors (K_21, K_02, K_10), shape `(..., 3)`.
    """
    return from_cm(vee_cm(to_cm(k)), 1)


def rotation_angle(r: Float[jax.typing.ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch"]:
    """Rotation angles of rotation matrices.

    **Arguments:**

    - `r`: rotations `(..., 3, 3)`.

    **Returns:**

    Angles in [0, pi], shape `(...)`.
    """
    rc = to_cm(r)
    c = 0.5 * (rc[0, 0] + rc[1, 1] + rc[2, 2] - 1.0)
    return jnp.arctan2(_safe_norm0(vee_cm(rc)), c)


def log_rotation(r: Float[jax.typing.ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Rotation log as axis-angle vectors theta * axis.

    **Arguments:**

    - `r`: rotations `(..., 3, 3)`.

    **Returns:**

    Axis-angle vectors `(..., 3)` with theta in [0, pi]; values and gradients finite at 0 and pi.
    """
    return from_cm(log_rotation_cm(to_cm(r)), 1)


def exp_rotation(v: Float[jax.typing.ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rodrigues' formula for the rotation of axis-angle vectors (any angle).

    **Arguments:**

    - `v`: axis-angle vectors `(..., 3)`.

    **Returns:**

    Rotations `(..., 3, 3)`.
    """
    return from_cm(exp_rotation_cm(to_cm(v, 1)))
