"""Garment meshes for the body of :mod:`jaxdeform.cloth.body` (seed 002): SKIRT and PANTS.

Each garment is a coarse triangle mesh built around the body's rest pose (metres, y up, facing +z), with the
vertices of its waistband (the ring the body holds it by). The fine mesh is the coarse one Loop-subdivided
(:func:`jaxdeform.cloth.scenarios.loop_subdivide`), as in the paper; its waistband is the fine boundary loop that
subdivides the coarse one. Every face is oriented with its normal pointing away from the body.

- SKIRT: a flared tube of :data:`SKIRT_AROUND` x :data:`SKIRT_RINGS` vertices (128; the paper's 127), elliptical
  rings from the waist (y = 1.02, around the torso) past the hips down to the knees; 3 Loop levels give 7,296
  fine vertices (the paper's 6,812).
- PANTS: a tube from the waist to the crotch that splits into two leg tubes down to the shins; the legs share a
  seam across the crotch (:func:`pants`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxdeform.mesh.topology import half_edge_groups, vertex_components

SKIRT_AROUND = 16
SKIRT_RINGS = 8
#: (height, semi-axis along x, semi-axis along z) of the skirt's rings at the waist, the hips and the hem; the
#: rings between are interpolated linearly in height.
SKIRT_PROFILE = ((1.02, 0.165, 0.165), (0.89, 0.27, 0.20), (0.50, 0.40, 0.34))
#: PANTS: vertices around the waist (even), rings from the waist to the crotch, rings of each leg below it.
PANTS_AROUND = 16
PANTS_UPPER_RINGS = 4
#: (height, semi-axis along x, along z) of the pants' waist tube at the waist, below the hips and at the crotch.
PANTS_PROFILE = ((1.02, 0.175, 0.17), (0.92, 0.25, 0.19), (0.72, 0.25, 0.19))
PANTS_LEG_RINGS = 8


class Garment(NamedTuple):
    """A coarse garment mesh: vertices ``(V, 3)``, faces ``(F, 3)`` and the waistband's vertex indices."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    waist: np.ndarray


def _strip(lower: np.ndarray, upper: np.ndarray, closed: bool = True) -> np.ndarray:
    """Triangles joining two rings of equal length (indices), two per quad, with outward normals for rings that run
    from the front (+z) towards +x around a vertical axis, ``upper`` above ``lower``."""
    n = len(lower)
    k = np.arange(n if closed else n - 1)
    k1 = (k + 1) % n
    a, b, c, d = lower[k], lower[k1], upper[k1], upper[k]
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _ellipse(centre, ax: float, az: float, n: int) -> np.ndarray:
    """``n`` points of an ellipse about the vertical through ``centre``, from the front (+z) towards +x."""
    th = 2.0 * np.pi * np.arange(n) / n
    return np.asarray(centre, np.float64) + np.stack([ax * np.sin(th), np.zeros(n), az * np.cos(th)], 1)


def skirt(n_around: int = SKIRT_AROUND, n_rings: int = SKIRT_RINGS) -> Garment:
    """The SKIRT garment (module docstring): rings from the waist down, the waistband the top ring."""
    (y0, a0, b0), (y1, a1, b1), (y2, a2, b2) = SKIRT_PROFILE
    ys = np.linspace(y0, y2, n_rings)
    ax = np.interp(-ys, [-y0, -y1, -y2], [a0, a1, a2])
    az = np.interp(-ys, [-y0, -y1, -y2], [b0, b1, b2])
    verts = np.concatenate([_ellipse([0.0, y, 0.0], a, b, n_around) for y, a, b in zip(ys, ax, az)])
    rings = np.arange(n_rings * n_around).reshape(n_rings, n_around)
    faces = np.concatenate([_strip(rings[k + 1], rings[k]) for k in range(n_rings - 1)])
    return Garment("skirt", verts, faces.astype(np.int64), rings[0].copy())


def pants(
    n_around: int = PANTS_AROUND, upper_rings: int = PANTS_UPPER_RINGS, leg_rings: int = PANTS_LEG_RINGS
) -> Garment:
    """The PANTS garment: a waist tube of ``upper_rings`` rings of ``n_around`` vertices (front centre first,
    counter-clockwise from above: towards the body's left), down to the crotch ring; one seam vertex at the crotch's
    centre; each leg a tube of ``leg_rings`` rings of ``n_around // 2 + 2`` vertices below. A leg's top loop is its
    half of the crotch ring closed by the seam vertex, so the two legs share the seam's edges and the surface stays
    a manifold with three boundary loops (waist and two hems)."""
    if n_around % 2 or n_around < 8:
        raise ValueError(f"pants need an even number of at least 8 vertices around the waist, got {n_around}.")
    m = n_around // 2
    (y_waist, a0, b0), (y1, a1, b1), (y_crotch, a2, b2) = PANTS_PROFILE
    y_hem = 0.12
    ys = np.linspace(y_waist, y_crotch, upper_rings)
    ax = np.interp(-ys, [-y_waist, -y1, -y_crotch], [a0, a1, a2])
    az = np.interp(-ys, [-y_waist, -y1, -y_crotch], [b0, b1, b2])
    verts = [_ellipse([0.0, y, 0.0], a, b, n_around) for y, a, b in zip(ys, ax, az)]
    rings = np.arange(upper_rings * n_around).reshape(upper_rings, n_around)
    faces = [_strip(rings[k + 1], rings[k]) for k in range(upper_rings - 1)]
    seam = upper_rings * n_around
    verts.append(np.array([[0.0, y_crotch, 0.0]]))
    crotch = rings[-1]
    nxt = seam + 1
    leg_n = m + 2
    allv = np.concatenate(verts)
    for side in (1, -1):  # left (+x), then right
        # the leg's top loop, in the leg rings' order (counter-clockwise from above, from the front centre): the
        # left leg goes front, outer half of the crotch ring, back, seam; the right one front, seam, back, outer half
        if side > 0:
            top = np.append(crotch[: m + 1], seam)
        else:
            top = np.concatenate([[crotch[0], seam], crotch[m:]])
        cx = 0.105 * side
        rel = allv[top] - [cx, 0.0, 0.0]
        angles = np.unwrap(np.arctan2(rel[:, 0], rel[:, 2]))  # each leg ring at its top loop's angles
        ys_leg = np.linspace(y_crotch - 0.08, y_hem, leg_rings)
        ax_leg = np.interp(-ys_leg, [-(y_crotch - 0.08), -y_hem], [0.105, 0.085])
        az_leg = np.interp(-ys_leg, [-(y_crotch - 0.08), -y_hem], [0.115, 0.09])
        leg = np.arange(nxt, nxt + leg_rings * leg_n).reshape(leg_rings, leg_n)
        for y, a, b in zip(ys_leg, ax_leg, az_leg):
            verts.append(np.stack([cx + a * np.sin(angles), np.full(leg_n, y), b * np.cos(angles)], 1))
        faces.append(_strip(leg[0], top))
        faces.extend(_strip(leg[k + 1], leg[k]) for k in range(leg_rings - 1))
        nxt += leg_rings * leg_n
    return Garment("pants", np.concatenate(verts), np.concatenate(faces).astype(np.int64), rings[0].copy())


GARMENTS = {"skirt": skirt, "pants": pants}


def motion_choices(kind: str, texts) -> list | None:
    """The body motions a request names (``KIND`` or ``KIND:NAME=VALUE,...`` each,
    :func:`jaxdeform.cloth.body.parse_motion`) for the scenario ``kind``: None for none; ``ValueError`` (one
    sentence) for motions asked of a scene without a body or a malformed motion."""
    if not texts:
        return None
    if kind not in GARMENTS:
        raise ValueError(f"motions apply to the garment scenarios ({', '.join(GARMENTS)}), not to '{kind}'.")
    from jaxdeform.cloth.body import parse_motion

    return [parse_motion(m) for m in texts]


def fine_waist(coarse_waist: np.ndarray, fine_faces: np.ndarray) -> np.ndarray:
    """The fine waistband: the fine mesh's boundary loop through the coarse waistband's vertices (Loop subdivision
    keeps the coarse vertices first, at the same indices), as sorted indices."""
    g = half_edge_groups(fine_faces)
    boundary = g.key[g.starts[g.counts == 1]]
    start = int(coarse_waist[0])
    if start not in boundary:
        raise ValueError("the coarse waistband is not on the fine mesh's boundary.")
    _, labels = vertex_components(boundary, int(np.asarray(fine_faces).max()) + 1)
    loop = np.flatnonzero(labels == labels[start])  # the boundary component that holds the first waist vertex
    if not np.isin(coarse_waist, loop).all():
        raise ValueError("the coarse waistband's vertices do not lie on one fine boundary loop.")
    return loop


def motion_track(rng: np.random.Generator, n_frames: int, fps: float, motions=None):
    """A random body animation for a garment sequence and what the waistband follows.

    **Arguments:**

    - ``rng``: the generator of the program (:func:`jaxdeform.cloth.body.random_program`).
    - ``n_frames``: frames, the 15 intro frames from the rest pose included.
    - ``fps``: frames per second.
    - ``motions``: the motions to draw from, ``(kind, fixed parameters)`` pairs (:func:`jaxdeform.cloth.body.
        parse_motion`); default None: every kind of :data:`jaxdeform.cloth.body.MOTIONS`, no parameter fixed.

    **Returns:**

    ``(track, rotation (T, 3, 3), translation (T, 3), meta)``: the body's capsules per frame; the pelvis's rigid
    motion from the rest pose, so that a waistband vertex at rest position x is held at ``R_t x + t_t``; and the
    program as a JSON-ready record.
    """
    from jaxdeform.cloth import body

    program = body.random_program(rng, n_frames / fps, tuple(motions) if motions else tuple(body.MOTIONS))
    anim = body.animate(program, n_frames, fps)
    rest_pos, _ = body.rest_pose()
    rot = anim.frames[:, body.J["pelvis"]]
    trans = anim.positions[:, body.J["pelvis"]] - rot @ rest_pos[body.J["pelvis"]]
    meta = {
        "program": [{"kind": m.kind, "seconds": m.seconds, "params": m.resolved()} for m in program],
        "intro_frames": body.INTRO_FRAMES,
        "capsules": {name: r for name, _, _, r in body.CAPSULES},
    }
    return body.track(anim), rot, trans, meta
