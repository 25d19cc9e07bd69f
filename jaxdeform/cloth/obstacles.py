"""Rigid obstacles of the cloth scenes (seed 002): spheres, capsules, vertical capped cylinders and a ground plane.

An :class:`Obstacles` value holds every shape at one instant; a *track* is the same pytree with a leading time
axis (T, ...) (one entry per stored frame). Any shape family may be empty (zero rows); the ground is always
present (put it at :data:`NO_GROUND` to disable it).

Signed distances (metres, negative inside), with the unit outward normal n = grad d:

- sphere (centre c, radius r):       d = |x - c| - r
- capsule (segment a-b, radius r):   d = |x - p| - r, p = a + s (b - a), s = clip((x - a).(b - a) / |b - a|^2, 0, 1)
- capped vertical cylinder (centre of the top cap c, radius r, height h, axis along y, bottom cap at c_y - h):
  with rho = |(x - c)_xz| (distance to the axis) and z = |x_y - (c_y - h/2)| (distance to the mid plane),
  q = (rho - r, z - h/2):   d = min(max(q_0, q_1), 0) + |max(q, 0)|   (exact, rims included: outside a rim the
  distance is to the rim circle, inside it is the distance to the nearest of side and caps). With rims rounded
  to radius e (``cylinder_rounding``, 0 <= e < min(r, h / 2)) the shape is the set of points within e of the
  sharp cylinder of radius r - e and height h - 2 e (top cap at c_y - e), so d = d_inner - e, exactly, with the
  inner cylinder's normal: the rims become quarter tori, and the smallest curvature radius of the surface is e
  instead of 0 (the contact points inside the cloth's triangles need one, :func:`jaxdeform.cloth.simulate.
  face_samples_for`).
- ground:                            d = x_y - ground, n = (0, 1, 0)

The combined field is the minimum over all shapes; its normal is the normal of the minimising shape.
Normals at the degenerate points (a sphere's centre, a cylinder's axis, a capsule's segment) fall back to +y.
Everything is jittable, float32 or float64.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

#: Height used for "no ground plane" (distances to it never win the minimum in practice).
NO_GROUND = -1.0e6

_UP = np.array([0.0, 1.0, 0.0])
_TINY = 1e-12


class Obstacles(NamedTuple):
    """All obstacle shapes at one instant (a pytree); with a leading (T,) axis on every leaf it is a track."""

    sphere_c: Float[Array, "s 3"]
    sphere_r: Float[Array, " s"]
    capsule_a: Float[Array, "c 3"]  # pole end points
    capsule_b: Float[Array, "c 3"]
    capsule_r: Float[Array, " c"]
    cylinder_c: Float[Array, "y 3"]  # centre of the top cap of a vertical (y-axis) capped cylinder
    cylinder_r: Float[Array, " y"]
    cylinder_h: Float[Array, " y"]  # extends down from the top cap by h
    cylinder_rounding: Float[Array, " y"]  # radius of the rounded rims (0: sharp)
    ground: Float[Array, ""]  # height of the ground plane y = ground


#: Fields a stored track may lack (tracks written before they existed), with the value they then take.
OPTIONAL_FIELDS = {"cylinder_rounding": "cylinder_r"}  # name -> field whose shape its zeros take


def check_rims(radius, height, rim, error=ValueError, where: str = "") -> None:
    """Refuse rim radii outside [0, min(radius, height / 2)) (arrays of any equal shape), with one sentence."""
    bad = ~((rim >= 0) & (rim < np.minimum(radius, 0.5 * height)))
    if np.any(bad):
        i = np.flatnonzero(bad.ravel())[0]
        raise error(
            f"{where}a cylinder's rim radius must lie in [0, min(radius, height / 2)), got "
            f"{rim.ravel()[i]:g} for radius {radius.ravel()[i]:g} and height {height.ravel()[i]:g}."
        )


def make(spheres=(), capsules=(), cylinders=(), ground: float = NO_GROUND, dtype=np.float32) -> Obstacles:
    """Obstacles from lists (host numpy).

    **Arguments:**

    - ``spheres``: ``[(centre, radius)]``.
    - ``capsules``: ``[(a, b, radius)]``.
    - ``cylinders``: ``[(top_centre, radius, height)]`` or ``[(top_centre, radius, height, rim_radius)]``.
    - ``ground``: the ground plane's height (default: disabled).
    - ``dtype``: the arrays' dtype.

    **Returns:**

    The :class:`Obstacles` of one instant.

    **Raises:**

    ``ValueError`` for a cylinder of another form or invalid rims (:func:`check_rims`).
    """
    s = list(spheres)
    c = list(capsules)
    if any(len(p) not in (3, 4) for p in cylinders):
        raise ValueError("a cylinder is (top_centre, radius, height) or (top_centre, radius, height, rim_radius).")
    y = [tuple(p) + (0.0,) * (4 - len(p)) for p in cylinders]
    check_rims(
        np.asarray([p[1] for p in y], np.float64),
        np.asarray([p[2] for p in y], np.float64),
        np.asarray([p[3] for p in y], np.float64),
        ValueError,
    )

    def vecs(rows):
        return np.asarray(rows, dtype).reshape(-1, 3)

    def scal(rows):
        return np.asarray(rows, dtype).reshape(-1)

    return Obstacles(
        sphere_c=vecs([p[0] for p in s]),
        sphere_r=scal([p[1] for p in s]),
        capsule_a=vecs([p[0] for p in c]),
        capsule_b=vecs([p[1] for p in c]),
        capsule_r=scal([p[2] for p in c]),
        cylinder_c=vecs([p[0] for p in y]),
        cylinder_r=scal([p[1] for p in y]),
        cylinder_h=scal([p[2] for p in y]),
        cylinder_rounding=scal([p[3] for p in y]),
        ground=np.asarray(ground, dtype),
    )


def empty(ground: float = NO_GROUND, dtype=np.float32) -> Obstacles:
    """No shapes at all, only the ground plane at ``ground`` (disabled by default)."""
    return make(ground=ground, dtype=dtype)


def static_track(obs: Obstacles, n_frames: int) -> Obstacles:
    """The track of obstacles that do not move: ``obs`` repeated ``n_frames`` times along a new leading axis."""
    return jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a)[None], n_frames, axis=0), obs)


def stack(frames: list[Obstacles]) -> Obstacles:
    """A track from a list of instants (all with the same shape counts)."""
    return jax.tree_util.tree_map(lambda *a: np.stack([np.asarray(x) for x in a]), *frames)


def obstacles_at(track: Obstacles, t) -> Obstacles:
    """The obstacles of frame ``t`` of a track (``t`` may be traced)."""
    return jax.tree_util.tree_map(lambda a: a[t], track)


def n_frames(track: Obstacles) -> int:
    """Number of frames of a track."""
    return int(np.shape(track.ground)[0])


def lerp(a: Obstacles, b: Obstacles, s) -> Obstacles:
    """Linear interpolation (1 - s) a + s b of every leaf (shapes move in straight lines between frames)."""
    return jax.tree_util.tree_map(lambda p, q: p + s * (q - p), a, b)


def to_dict(track: Obstacles) -> dict[str, np.ndarray]:
    """The track as a dict of host arrays (field name -> array), e.g. for ``np.savez``."""
    return {k: np.asarray(v) for k, v in track._asdict().items()}


def complete(d: dict) -> dict:
    """A stored track's fields with the :data:`OPTIONAL_FIELDS` it lacks filled in (zeros: sharp rims)."""
    out = dict(d)
    for name, like in OPTIONAL_FIELDS.items():
        if name not in out and like in out:
            out[name] = np.zeros_like(np.asarray(out[like]))
    return out


def from_dict(d: dict) -> Obstacles:
    """Inverse of :func:`to_dict` (tracks stored before an optional field existed get its default)."""
    d = complete(d)
    return Obstacles(**{k: np.asarray(d[k]) for k in Obstacles._fields})


def _unit_cols(v, fallback):
    """Columns ``v`` (3 arrays of the same shape) normalised, ``fallback`` (3,) where shorter than _TINY; and their
    lengths."""
    length = jnp.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    ok = length > _TINY
    safe = jnp.where(ok, length, 1.0)
    return [jnp.where(ok, v[i] / safe, float(fallback[i])) for i in range(3)], length


# The shape functions below work in a shapes-by-points layout: the points' coordinates are three (P,) rows, every
# result is (K, P) per component, so that the points run along the vectorised axis (the shapes are few).


def _spheres(obs, X):
    """Signed distances (s, P) and normal components to every sphere."""
    rel = [X[i][None] - obs.sphere_c[:, i, None] for i in range(3)]
    n, dist = _unit_cols(rel, _UP)
    return dist - obs.sphere_r[:, None], n


def _capsule_param(obs, X):
    """The closest-point parameter t in [0, 1] along every capsule's segment (c, P)."""
    a = obs.capsule_a
    ab = obs.capsule_b - a
    ab2 = jnp.maximum(jnp.sum(ab * ab, -1), _TINY)
    dot = sum((X[i][None] - a[:, i, None]) * ab[:, i, None] for i in range(3))
    return jnp.clip(dot / ab2[:, None], 0.0, 1.0)


def _capsules(obs, X, t):
    a = obs.capsule_a
    ab = obs.capsule_b - a
    rel = [X[i][None] - (a[:, i, None] + t * ab[:, i, None]) for i in range(3)]
    n, dist = _unit_cols(rel, _UP)
    return dist - obs.capsule_r[:, None], n


def _cylinders(obs, X):
    e = obs.cylinder_rounding[:, None]  # the sharp inner cylinder, offset by e
    c = obs.cylinder_c
    rel = [X[0][None] - c[:, 0, None], X[1][None] - (c[:, 1, None] - e), X[2][None] - c[:, 2, None]]
    rdir, rho = _unit_cols([rel[0], jnp.zeros_like(rel[0]), rel[2]], (1.0, 0.0, 0.0))
    half = 0.5 * obs.cylinder_h[:, None] - e
    ym = rel[1] + half  # height above the mid plane
    q0 = rho - (obs.cylinder_r[:, None] - e)
    q1 = jnp.abs(ym) - half
    sgn = jnp.where(ym >= 0, 1.0, -1.0).astype(q0.dtype)
    # outside (some q > 0): gradient of |max(q, 0)|
    o0 = jnp.maximum(q0, 0.0)
    o1 = jnp.maximum(q1, 0.0)
    out_len = jnp.sqrt(o0 * o0 + o1 * o1)
    inv = 1.0 / jnp.maximum(out_len, _TINY)
    out_n = [o0 * rdir[0] * inv, o1 * sgn * inv, o0 * rdir[2] * inv]
    # inside (both q <= 0): the nearer of side and caps
    side = q0 >= q1
    in_n = [jnp.where(side, rdir[0], 0.0), jnp.where(side, 0.0, sgn), jnp.where(side, rdir[2], 0.0)]
    outside = (q0 > 0) | (q1 > 0)
    d = jnp.where(outside, out_len, jnp.maximum(q0, q1)) - e
    return d, [jnp.where(outside, out_n[i], in_n[i]) for i in range(3)]


def _closest(obs: Obstacles, x):
    """The closest of the k = s + c + y + 1 shapes (spheres, capsules, cylinders, the ground last) to each point:
    (distance (P,), normal (P, 3), shape index (P,), capsule parameter per capsule (c, P))."""
    X = [x[:, i] for i in range(3)]
    t = _capsule_param(obs, X)
    parts = [_spheres(obs, X), _capsules(obs, X, t), _cylinders(obs, X)]
    up = [jnp.full((1, x.shape[0]), v, x.dtype) for v in _UP]
    d = jnp.concatenate([p[0] for p in parts] + [(X[1] - obs.ground)[None]], 0)
    k = jnp.argmin(d, axis=0)
    pick = lambda a: jnp.take_along_axis(a, k[None], 0)[0]  # noqa: E731
    n = jnp.stack([pick(jnp.concatenate([p[1][i] for p in parts] + [up[i]], 0)) for i in range(3)], -1)
    return pick(d), n, k, t


@jax.jit
def signed_distance(obs: Obstacles, x: Float[Array, "p 3"]) -> tuple[Float[Array, " p"], Float[Array, "p 3"]]:
    """Signed distance of each point to the union of all shapes, and the closest shape's normal.

    Jitted; computed in the dtype of ``x`` (the obstacles are cast to it).

    **Arguments:**

    - ``obs``: the obstacles of one instant.
    - ``x``: points ``(P, 3)``.

    **Returns:**

    ``(distance (P,), normal (P, 3))``, the distance negative inside.
    """
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    obs = jax.tree_util.tree_map(lambda a: jnp.asarray(a, x.dtype), obs)
    d, n, _, _ = _closest(obs, x)
    return d, n


def query(
    obs: Obstacles, prev: Obstacles, x: Float[Array, "p 3"]
) -> tuple[Float[Array, " p"], Float[Array, "p 3"], Float[Array, "p 3"], Int[Array, " p"]]:
    """Closest-shape query of points against the obstacles and their motion since ``prev``.

    **Arguments:**

    - ``obs``: the obstacles now.
    - ``prev``: the same obstacles at the previous instant.
    - ``x``: points ``(P, 3)``.

    **Returns:**

    ``(distance (P,), normal (P, 3), displacement (P, 3), shape (P,))``: the signed distance and normal of the
    closest shape, the displacement of its surface point since ``prev`` (shapes translate; a capsule's point moves
    with its end points blended at the closest-point parameter), and its index.
    """
    x = jnp.asarray(x)
    d, n, k, t = _closest(obs, x)
    # each shape's translation since prev at its two ends (one point for all but capsules), blended at the
    # winning capsule's parameter
    ground = ((obs.ground - prev.ground) * jnp.asarray(_UP, x.dtype))[None]
    ends = [obs.sphere_c - prev.sphere_c, None, obs.cylinder_c - prev.cylinder_c, ground]
    move_a = jnp.concatenate([e if e is not None else obs.capsule_a - prev.capsule_a for e in ends], 0)
    move_b = jnp.concatenate([e if e is not None else obs.capsule_b - prev.capsule_b for e in ends], 0)
    n_s, n_c = obs.sphere_r.shape[0], obs.capsule_r.shape[0]
    on_capsule = (k >= n_s) & (k < n_s + n_c)
    tc = jnp.take_along_axis(t, jnp.clip(k - n_s, 0, max(n_c - 1, 0))[None], 0)[0] if n_c else jnp.zeros_like(d)
    tw = jnp.where(on_capsule, tc, 0.0)[:, None]
    return d, n, (1.0 - tw) * move_a[k] + tw * move_b[k], k
