"""Deterministic synthetic mesh sequences sharing one connectivity (no download needed).

The main generator, :func:`bending_tube_sequence`, is a small but demanding test case for deformation
representations such as ACAP / TS-ACAP: an open tube (radius 0.12, length 4) whose centre line bends into
a spiral of more than one full turn, so that local rotations with respect to the rest pose exceed pi
(about 7 rad at the far end), while its cross-sections twist about the centre line and small Gaussian
bumps appear and disappear on its surface. It is therefore multi-scale (large bend + twist, small bumps)
and exercises rotation-angle ambiguity, which naive per-frame rotation logs get wrong.

Every function returns NumPy arrays: vertices as float64, faces as int32 ``(F, 3)`` with outward normals
(counter-clockwise seen from outside) and no degenerate triangles. Vertex ``i * n_around + j`` is vertex
``j`` of ring ``i``; ring 0 sits at ``x = 0`` and vertex 0 is ``(0, radius, 0)``. All frames of a
sequence share the faces of :func:`tube`, and frame 0 is the rest tube.

Geometry of the sequence, frame ``t`` with progress ``f = t / (n_frames - 1)``:

* Centre line: a unit-speed helix ``c(s)``, ``s`` in ``[0, length]``, whose projection on the plane
  perpendicular to its axis turns by ``theta = f * max_bend_turns * 2 pi`` in total (constant
  curvature), and which rises along the axis by ``pitch = 1.5 * (2 radius)`` per full turn, so the
  coils never touch once the bend passes a full turn. Arclength is preserved exactly (an inextensible
  bend). The helix is rigidly rotated so that ring 0 keeps its rest position and orientation: the
  fixed end (``x = 0``, vertex 0 included) never moves, the start tangent stays ``+x`` and the helix axis
  is ``+z`` tilted by the small climb angle (``asin(pitch * theta / (2 pi length))`` <= 6 degrees at the
  defaults), i.e. the bend happens (nearly) in the x-y plane.
* Cross-sections stay perpendicular to the centre line; they are placed in the analytic
  rotation-minimizing frame of the helix (the Frenet frame rotated back by the accumulated torsion),
  so the only twist is the intended one: ``f * max_twist_turns * 2 pi * s / length`` about the tangent.
* Bumps: ``n_bumps`` Gaussian radial displacements of peak ``bump_amplitude`` and width ``bump_width``
  (standard deviation, as surface distance), centred on vertices drawn by
  ``np.random.default_rng(seed)`` away from both ends. Each lives over a random time window strictly
  inside the sequence (``sin^2`` envelope), so the first and last frames carry no bump.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bending_tube_sequence", "tube"]


def _check_counts(n_around: int, n_along: int) -> None:
    if int(n_around) < 3:
        raise ValueError(f"n_around must be at least 3, got {n_around}.")
    if int(n_along) < 2:
        raise ValueError(f"n_along must be at least 2, got {n_along}.")


def _tube_faces(n_around: int, n_along: int) -> np.ndarray:
    """Triangles of the open tube grid, outward oriented, diagonals alternating in a checkerboard."""
    i, j = np.meshgrid(np.arange(n_along - 1), np.arange(n_around), indexing="ij")
    i, j = i.ravel(), j.ravel()
    jn = (j + 1) % n_around
    a = i * n_around + j  # (i, j)
    b = i * n_around + jn  # (i, j+1)
    c = (i + 1) * n_around + jn  # (i+1, j+1)
    d = (i + 1) * n_around + j  # (i+1, j)
    even = ((i + j) % 2 == 0)[:, None]
    # Around-direction x along-direction points outward, hence the (a, b, .) ordering.
    t1 = np.where(even, np.stack([a, b, d], 1), np.stack([a, c, d], 1))
    t2 = np.where(even, np.stack([b, c, d], 1), np.stack([a, b, c], 1))
    faces = np.stack([t1, t2], axis=1).reshape(-1, 3)
    return faces.astype(np.int32)


def _ring_angles(n_around: int) -> np.ndarray:
    return 2.0 * np.pi * np.arange(n_around) / n_around


def tube(n_around: int = 24, n_along: int = 64, radius: float = 0.12, length: float = 4.0):
    """An open cylinder along +x, from ``x = 0`` to ``x = length``.

    It has ``n_along`` rings of ``n_around`` vertices; vertex ``i * n_around + j`` is
    ``(i * length / (n_along - 1), radius * cos(2 pi j / n_around), radius * sin(2 pi j / n_around))``,
    so vertex 0 is ``(0, radius, 0)`` on the end at ``x = 0``. Each quad is split into two triangles
    with diagonals alternating in a checkerboard. The tube has no caps: its two end rings are boundary
    loops (the surface is a topological annulus, genus 0 with 2 boundaries).

    **Arguments:**

    - ``n_around``: vertices per ring (at least 3).
    - ``n_along``: rings (at least 2).
    - ``radius``: the tube's radius (positive).
    - ``length``: the tube's length (positive).

    **Returns:**

    ``(vertices (n_along * n_around, 3) float64, faces (2 * (n_along - 1) * n_around, 3) int32)``
    with outward normals.

    **Raises:**

    ``ValueError`` for counts below the minimums or a non-positive radius or length.
    """
    _check_counts(n_around, n_along)
    if not (radius > 0 and length > 0):
        raise ValueError(f"radius and length must be positive, got radius={radius}, length={length}.")
    s = np.linspace(0.0, float(length), int(n_along))
    ang = _ring_angles(int(n_around))
    verts = np.empty((int(n_along), int(n_around), 3))
    verts[..., 0] = s[:, None]
    verts[..., 1] = radius * np.cos(ang)[None, :]
    verts[..., 2] = radius * np.sin(ang)[None, :]
    return verts.reshape(-1, 3), _tube_faces(int(n_around), int(n_along))


def _bump_field(rng, n_frames, n_around, n_along, n_bumps, amplitude, width, radius, length):
    """Radial displacement (N, n_along, n_around) of the time-windowed Gaussian bumps."""
    disp = np.zeros((n_frames, n_along, n_around))
    if n_bumps <= 0 or amplitude == 0.0:
        return disp
    s = np.linspace(0.0, length, n_along)
    ang = _ring_angles(n_around)
    # Centres: one per equal slot of [0.15, 0.9] * length (so bumps never overlap much), snapped to a
    # vertex so that the peak displacement is reached exactly on the mesh.
    lo, hi = 0.15 * length, 0.9 * length
    edges = np.linspace(lo, hi, n_bumps + 1)
    s_c = edges[:-1] + (edges[1:] - edges[:-1]) * rng.uniform(0.15, 0.85, size=n_bumps)
    ring_c = np.clip(np.rint(s_c / length * (n_along - 1)).astype(int), 1, n_along - 2)
    j_c = rng.integers(0, n_around, size=n_bumps)
    # Time windows strictly inside (0, 1): absent from the first and the last frame.
    dur = rng.uniform(0.3, 0.5, size=n_bumps)
    start = rng.uniform(0.05, 0.95 - dur)
    f = np.linspace(0.0, 1.0, n_frames) if n_frames > 1 else np.zeros(1)
    phase = (f[:, None] - start[None, :]) / dur[None, :]  # (N, B)
    env = np.where((phase > 0) & (phase < 1), np.sin(np.pi * np.clip(phase, 0.0, 1.0)) ** 2, 0.0)
    ds = s[None, :] - s[ring_c][:, None]  # (B, n_along)
    dang = np.angle(np.exp(1j * (ang[None, :] - ang[j_c][:, None])))  # (B, n_around), wrapped
    g = np.exp(-0.5 * (ds[:, :, None] ** 2 + (radius * dang[:, None, :]) ** 2) / width**2)  # (B, L, A)
    return amplitude * np.einsum("nb,bla->nla", env, g)


def _check_sequence(n_frames: int, max_bend_turns, bump_amplitude, radius, length, bump_width) -> tuple[float, float]:
    """Validate :func:`bending_tube_sequence`'s numbers; return ``(h, omega_max)`` of its helix.

    ``h`` = ``1.5 * 2 radius / (2 pi)`` is the rise per radian of turning and ``omega_max`` =
    ``max_bend_turns * 2 pi / length`` the projected turning per unit arclength of the last frame. Raises
    ValueError, in this order, unless ``n_frames`` >= 1; ``radius``, ``length`` and ``bump_width`` > 0;
    ``max_bend_turns`` >= 0; ``bump_amplitude`` in [0, ``radius``); and the coils stay looser than the tube
    (``omega_max * h < 1`` and ``omega_max * (radius + bump_amplitude) < 1``).
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be at least 1, got {n_frames}.")
    if not (radius > 0 and length > 0 and bump_width > 0):
        raise ValueError("radius, length and bump_width must be positive.")
    if max_bend_turns < 0:
        raise ValueError(f"max_bend_turns must be non-negative, got {max_bend_turns}.")
    if bump_amplitude < 0 or abs(bump_amplitude) >= radius:
        raise ValueError(f"bump_amplitude must be in [0, radius), got {bump_amplitude}.")

    h = 1.5 * (2.0 * radius) / (2.0 * np.pi)  # rise per radian of turning
    omega_max = max_bend_turns * 2.0 * np.pi / length  # projected turning per unit arclength
    if omega_max * h >= 1.0 or omega_max * (radius + bump_amplitude) >= 1.0:
        raise ValueError(
            f"max_bend_turns={max_bend_turns} is too large for a tube of length {length} and radius "
            f"{radius}: the coils would be tighter than the tube."
        )
    return h, omega_max


def _start_rotation(cos_a: np.ndarray, sin_a: np.ndarray) -> np.ndarray:
    """Per-frame rigid rotations ``(N, 3, 3)`` about y taking the helix start frame (T0, N0, B0) to (+x, +y, +z).

    ``cos_a``, ``sin_a`` (N,): cosine and sine of each frame's climb angle. Row-major: apply as ``q @ p``.
    """
    q = np.zeros((cos_a.shape[0], 3, 3))
    q[:, 0, 0] = cos_a
    q[:, 0, 2] = sin_a
    q[:, 1, 1] = 1.0
    q[:, 2, 0] = -sin_a
    q[:, 2, 2] = cos_a
    return q


def _centre_line_frames(f: np.ndarray, s: np.ndarray, omega_max: float, h: float):
    """The bent centre line and its rotation-minimizing cross-section axes, per frame and ring.

    ``f`` (N,): progress of each frame in [0, 1]; ``s`` (L,): arclength of each ring; ``omega_max``, ``h``: from
    :func:`_check_sequence`. Returns ``(centre, u, v)``, each ``(N, L, 3)``: the unit-speed helix of turning
    ``f * omega_max`` per unit arclength (a straight line at ``f = 0``) and two orthonormal axes perpendicular
    to its tangent, rigidly rotated so that ring 0 sits at the origin with tangent +x, ``u`` = +y, ``v`` = +z.
    """
    omega = f * omega_max  # (N,)
    sin_a = omega * h  # sine of the helix climb angle
    cos_a = np.sqrt(1.0 - sin_a**2)
    tau = omega * sin_a  # torsion of the unit-speed helix (curvature is omega * cos_a)

    x = omega[:, None] * s[None, :]  # (N, L) projected turning angle
    cx, sx = np.cos(x), np.sin(x)
    # Stable forms of sin(x)/omega and (1 - cos x)/omega (straight line at omega = 0).
    sin_over = s[None, :] * np.sinc(x / np.pi)
    one_minus_cos_over = s[None, :] * 0.5 * x * np.sinc(x / (2.0 * np.pi)) ** 2
    ca, sa = cos_a[:, None], sin_a[:, None]
    zeros = np.zeros_like(x)
    # Helix in its own frame: axis +z, start tangent (cos_a, 0, sin_a), start normal +y; its tangent
    # is (cos_a cos x, cos_a sin x, sin_a), normal (-sin x, cos x, 0), binormal = tangent x normal.
    centre = np.stack([ca * sin_over, ca * one_minus_cos_over, sa * s[None, :] + zeros], axis=-1)
    normal = np.stack([-sx, cx, zeros], axis=-1)
    binormal = np.stack([-sa * cx, -sa * sx, ca + zeros], axis=-1)
    # Rotation-minimizing frame: Frenet frame rotated by -tau * s about the tangent.
    rot = (tau[:, None] * s[None, :])[..., None]
    u = np.cos(rot) * normal - np.sin(rot) * binormal
    v = np.cos(rot) * binormal + np.sin(rot) * normal

    q = _start_rotation(cos_a, sin_a)
    centre, u, v = (np.einsum("nij,nlj->nli", q, a) for a in (centre, u, v))
    return centre, u, v


def bending_tube_sequence(
    n_frames: int = 24,
    *,
    n_around: int = 24,
    n_along: int = 64,
    max_bend_turns: float = 1.15,
    max_twist_turns: float = 0.5,
    bump_amplitude: float = 0.04,
    n_bumps: int = 3,
    seed: int = 0,
    radius: float = 0.12,
    length: float = 4.0,
    bump_width: float = 0.05,
):
    """A tube bending into a spiral past a full turn, twisting, with transient bumps.

    Frame 0 is exactly ``tube(n_around, n_along, radius, length)``. Over the frames (progress
    ``f = t / (n_frames - 1)``) the centre line bends, inextensibly, into a helix whose total projected
    tangent turning grows linearly to ``max_bend_turns * 2 pi`` (rising ``1.5 * 2 * radius`` per full
    turn so it never self-intersects), the cross-sections twist about the centre line (relative to a
    rotation-minimizing frame) by ``f * max_twist_turns * 2 pi * s / length`` at arclength ``s``, and
    ``n_bumps`` radial Gaussian bumps of peak ``bump_amplitude`` and width ``bump_width`` appear and
    vanish at places and times drawn by ``np.random.default_rng(seed)``. The fixed end (ring 0 at
    ``x = 0``, vertex 0 included) never moves. See the module docstring for details.

    **Arguments:**

    - ``n_frames``: frames (at least 1).
    - ``n_around``, ``n_along``, ``radius``, ``length``: the tube's (:func:`tube`).
    - ``max_bend_turns``: the total turning of the centre line at the last frame, in full turns.
    - ``max_twist_turns``: the twist of the far end at the last frame, in full turns.
    - ``bump_amplitude``, ``n_bumps``, ``bump_width``: the transient bumps (``bump_width`` positive).
    - ``seed``: the seed of the bumps' places and times.

    **Returns:**

    ``(vertices (n_frames, V, 3) float64, faces (F, 3) int32)``, the faces being those of :func:`tube`.

    **Raises:**

    ``ValueError`` for counts below the minimums or non-positive sizes.
    """
    _check_counts(n_around, n_along)
    n_frames, n_around, n_along = int(n_frames), int(n_around), int(n_along)
    h, omega_max = _check_sequence(n_frames, max_bend_turns, bump_amplitude, radius, length, bump_width)

    f = np.linspace(0.0, 1.0, n_frames) if n_frames > 1 else np.zeros(1)
    s = np.linspace(0.0, float(length), n_along)
    ang = _ring_angles(n_around)
    centre, u, v = _centre_line_frames(f, s, omega_max, h)

    twist = (f * max_twist_turns * 2.0 * np.pi)[:, None] / length * s[None, :]  # (N, L)
    phi = ang[None, None, :] + twist[:, :, None]  # (N, L, A)
    rng = np.random.default_rng(seed)
    r = radius + _bump_field(
        rng,
        n_frames,
        n_around,
        n_along,
        int(n_bumps),
        float(bump_amplitude),
        float(bump_width),
        float(radius),
        float(length),
    )
    verts = (
        centre[:, :, None, :]
        + (r * np.cos(phi))[..., None] * u[:, :, None, :]
        + (r * np.sin(phi))[..., None] * v[:, :, None, :]
    )
    verts = verts.reshape(n_frames, n_along * n_around, 3)
    # Frame 0 (f = 0, no bump) is the rest tube; make it so bit for bit, not just up to rounding.
    verts[0] = tube(n_around, n_along, radius, length)[0]
    return verts, _tube_faces(n_around, n_along)


def twisted_bar(
    n_along: int = 48,
    width: float = 1.0,
    depth: float = 0.3,
    length: float = 4.0,
    twist_turns: float = 0.375,
    bend: float = 0.6,
    n_width: int = 8,
    n_depth: int = 4,
):
    """A closed rectangular bar along ``y``, twisted about its axis and bent in ``x``: no mirror symmetry.

    The cross-section (``width`` x ``depth`` in ``x``, ``z``) at height ``y = s length`` (``s`` in [0, 1]) turns by
    ``2 pi twist_turns s`` about the axis, and the axis bends sideways by ``bend s^2`` in ``x``. The twist makes the
    bar chiral (a mirror image twists the other way) and the one-sided bend breaks the remaining planes, so it
    serves as the asymmetric case of symmetry detection (DFD eq. 9).

    **Arguments:**

    - ``n_along``: rings along the bar (at least 2).
    - ``width``, ``depth``, ``length``: the bar's size.
    - ``twist_turns``: the twist of the top end, in full turns.
    - ``bend``: the sideways bend of the top end.
    - ``n_width``, ``n_depth``: segments of the cross-section's sides (at least 1).

    **Returns:**

    ``(vertices (V, 3) float64, faces (F, 3) int32)``, outward-facing, capped at both ends.

    **Raises:**

    ``ValueError`` for ``n_along < 2`` or ``n_width``, ``n_depth < 1``.
    """
    if n_along < 2 or n_width < 1 or n_depth < 1:
        raise ValueError("twisted_bar needs n_along >= 2 and n_width, n_depth >= 1.")
    # the rectangle's boundary, counter-clockwise seen from +y, as one closed ring of points
    xs = np.linspace(-width / 2, width / 2, n_width + 1)
    zs = np.linspace(-depth / 2, depth / 2, n_depth + 1)
    ring = np.concatenate(
        [
            np.stack([xs[:-1], np.full(n_width, zs[-1])], 1),
            np.stack([np.full(n_depth, xs[-1]), zs[::-1][:-1]], 1),
            np.stack([xs[::-1][:-1], np.full(n_width, zs[0])], 1),
            np.stack([np.full(n_depth, xs[0]), zs[:-1]], 1),
        ]
    )
    m = ring.shape[0]
    s = np.linspace(0.0, 1.0, n_along)
    ang = 2 * np.pi * twist_turns * s
    c, sn = np.cos(ang)[:, None], np.sin(ang)[:, None]
    x = c * ring[None, :, 0] - sn * ring[None, :, 1] + bend * s[:, None] ** 2
    z = sn * ring[None, :, 0] + c * ring[None, :, 1]
    y = np.broadcast_to(length * s[:, None], x.shape)
    side = np.stack([x, y, z], -1).reshape(-1, 3)
    i = np.arange(n_along - 1)[:, None] * m
    j = np.arange(m)[None, :]
    a, b = i + j, i + (j + 1) % m
    quads = np.stack([a, b, b + m, a + m], -1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 2, 1]], quads[:, [0, 3, 2]]])
    # caps: a centre vertex at each end, fanned to its ring
    bottom = np.array([[bend * 0.0, 0.0, 0.0]])
    top = np.array([[bend * 1.0, length, 0.0]])
    vb, vt = side.shape[0], side.shape[0] + 1
    ring0 = np.arange(m)
    ring1 = (n_along - 1) * m + np.arange(m)
    cap0 = np.stack([np.full(m, vb), ring0, np.roll(ring0, -1)], 1)
    cap1 = np.stack([np.full(m, vt), np.roll(ring1, -1), ring1], 1)
    vertices = np.concatenate([side, bottom, top])
    faces = np.concatenate([faces, cap0, cap1]).astype(np.int32)
    # orient outward: flip everything if the signed volume is negative
    tri = vertices[faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    if volume < 0:
        faces = faces[:, ::-1].copy()
    return vertices, faces
