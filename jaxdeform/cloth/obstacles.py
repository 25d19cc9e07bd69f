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


def _safe_unit(v, fallback):
    n = jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))
    ok = n > _TINY
    return jnp.where(ok, v / jnp.where(ok, n, 1.0), fallback), n[..., 0]


def _spheres(obs, x):
    """(p, s) distances and normals to every sphere, plus the closest-point segment parameter (0)."""
    diff = x[:, None, :] - obs.sphere_c[None]  # (p, s, 3)
    n, dist = _safe_unit(diff, jnp.asarray(_UP, x.dtype))
    return dist - obs.sphere_r[None], n


def _capsule_param(obs, x):
    ab = obs.capsule_b - obs.capsule_a  # (c, 3)
    ab2 = jnp.sum(ab * ab, -1)
    t = jnp.sum((x[:, None, :] - obs.capsule_a[None]) * ab[None], -1) / jnp.maximum(ab2, _TINY)[None]
    return jnp.clip(t, 0.0, 1.0)  # (p, c)


def _capsules(obs, x):
    t = _capsule_param(obs, x)
    p = obs.capsule_a[None] + t[..., None] * (obs.capsule_b - obs.capsule_a)[None]
    n, dist = _safe_unit(x[:, None, :] - p, jnp.asarray(_UP, x.dtype))
    return dist - obs.capsule_r[None], n


def _cylinders(obs, x):
    e = obs.cylinder_rounding  # the sharp inner cylinder, offset by e
    rel = x[:, None, :] - (obs.cylinder_c - e[:, None] * jnp.asarray(_UP, x.dtype))[None]  # (p, y, 3)
    radial = rel * jnp.asarray([1.0, 0.0, 1.0], x.dtype)
    rdir, rho = _safe_unit(radial, jnp.asarray([1.0, 0.0, 0.0], x.dtype))
    half = 0.5 * obs.cylinder_h[None] - e[None]
    ym = rel[..., 1] + half  # height above the mid plane
    q0 = rho - (obs.cylinder_r - e)[None]
    q1 = jnp.abs(ym) - half
    sgn = jnp.where(ym >= 0, 1.0, -1.0).astype(x.dtype)
    up = jnp.asarray(_UP, x.dtype)
    axial = sgn[..., None] * up
    # outside (some q > 0): gradient of |max(q, 0)|
    o0 = jnp.maximum(q0, 0.0)
    o1 = jnp.maximum(q1, 0.0)
    out_len = jnp.sqrt(o0 * o0 + o1 * o1)
    out_dir = o0[..., None] * rdir + o1[..., None] * axial
    out_n = out_dir / jnp.maximum(out_len, _TINY)[..., None]
    # inside (both q <= 0): the nearer of side and caps
    in_n = jnp.where((q0 >= q1)[..., None], rdir, axial)
    outside = (q0 > 0) | (q1 > 0)
    d = jnp.where(outside, out_len, jnp.maximum(q0, q1)) - e[None]
    n = jnp.where(outside[..., None], out_n, in_n)
    return d, n


def _candidates(obs: Obstacles, x):
    """Distances (p, k) and normals (p, k, 3) to the k = s + c + y + 1 shapes, in that order (ground last)."""
    ds, ns = _spheres(obs, x)
    dc, nc = _capsules(obs, x)
    dy, ny = _cylinders(obs, x)
    dg = (x[:, 1] - obs.ground)[:, None]
    ng = jnp.broadcast_to(jnp.asarray(_UP, x.dtype), (x.shape[0], 1, 3))
    d = jnp.concatenate([ds, dc, dy, dg.astype(x.dtype)], axis=1)
    n = jnp.concatenate([ns, nc, ny, ng], axis=1)
    return d, n


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
    d, n = _candidates(obs, x)
    k = jnp.argmin(d, axis=1)
    return jnp.take_along_axis(d, k[:, None], 1)[:, 0], jnp.take_along_axis(n, k[:, None, None], 1)[:, 0]


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
    d, n = _candidates(obs, x)
    k = jnp.argmin(d, axis=1)
    t = _capsule_param(obs, x)  # (p, c)
    disp = jnp.concatenate(
        [
            jnp.broadcast_to((obs.sphere_c - prev.sphere_c)[None], (x.shape[0],) + obs.sphere_c.shape),
            (1.0 - t)[..., None] * (obs.capsule_a - prev.capsule_a)[None]
            + t[..., None] * (obs.capsule_b - prev.capsule_b)[None],
            jnp.broadcast_to((obs.cylinder_c - prev.cylinder_c)[None], (x.shape[0],) + obs.cylinder_c.shape),
            jnp.broadcast_to((obs.ground - prev.ground) * jnp.asarray(_UP, x.dtype), (x.shape[0], 1, 3)),
        ],
        axis=1,
    )
    pick = k[:, None]
    return (
        jnp.take_along_axis(d, pick, 1)[:, 0],
        jnp.take_along_axis(n, pick[..., None], 1)[:, 0],
        jnp.take_along_axis(disp, pick[..., None], 1)[:, 0],
        k,
    )
