"""Pose interpolation between two training shapes with a fitted rotation-constrained MFA (seed 003, Algorithm 2).

Given the part labels, the latent images z_i and the per-shape rigid motions (R_k^m, t_k^m) of the mixture
(``parts.mfa``), a pose between the source shape s and the target shape g is built part by part:

1. Part graph: parts a, b are adjacent when a triangle has vertices of both ("between" triangles carry more
   than one label). Every connected component of this graph gets its own root: the part with the smallest
   rotation angle of R_k^g (R_k^s)^T. A breadth-first search from the root gives every other part its parent.
2. Rotations: R_k(t) = Slerp(q(R_k^s), q(R_k^g), t), shortest arc, for every part.
3. Translations: the root is interpolated linearly, t_k(t) = (1 - t) t_k^s + t t_k^g. A child a of parent b
   is placed so that the joint point stays in contact when mapped through both parts (eq. 23):

       R_a(t) z_a(t) + t_a(t) = R_b(t) z_b(t) + t_b(t).

   Joint point c^m of (a, b) in shape m: the mass centre of the triangles that have vertices in both a and b.
   By default every such triangle carries the same mass (mass is conserved as the between triangles stretch),
   so c^m is the plain mean of their centroids; ``weighting="area"`` weights them by their area in shape m
   instead. On a bent synthetic chain the area weighting drifts off the joint by ~2% of the bounding-box
   diagonal (the stretched outer triangles dominate), the uniform one by ~0.15%. Its latent images
   are z_a^m = R_a^m^T (c^m - t_a^m) and z_b^m = R_b^m^T (c^m - t_b^m), taken in the two end shapes only and
   blended linearly, z_a(t) = (1 - t) z_a^s + t z_a^g (same for b) -- the same treatment as the residuals.
   With this choice the end poses are reproduced exactly for every part (not only the root), and contact
   holds at every t by construction.
4. Vertices (eq. 24): with the latent residuals e_i^m = R_k^m^T (p_i^m - t_k^m) - z_i of the end shapes,

       p_i(t) = R_k(t) (z_i + (1 - t) e_i^s + t e_i^g) + t_k(t),    k = labels[i],

   i.e. the non-rigid "muscle" residual is blended in the latent space and then posed by the part.

Vertices with label -1 (unassigned) are interpolated linearly between the two end shapes.
Everything is numpy float64 (K parts and a handful of t values: tiny algebra); loops run over parts only.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Sequence

import numpy as np

from jaxdeform.parts.mfa import MFA

#: Quaternion dot product above which slerp falls back to normalised linear interpolation.
SLERP_LINEAR_DOT = 1.0 - 1e-10

# ------------------------------------------------------------------------------------------ quaternions


def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternions of proper rotations (Shepperd's method).

    The largest of the four candidates 4w^2, 4x^2, 4y^2, 4z^2 (from the trace and the diagonal) is used as
    the pivot, so the division is always by a number >= 1 and the result is accurate for every angle.

    **Arguments:**

    - ``r``: proper rotations ``(..., 3, 3)``.

    **Returns:**

    Quaternions (w, x, y, z) ``(..., 4)``, unit, w >= 0.
    """
    r = np.asarray(r, np.float64)
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    tr = r00 + r11 + r22
    s21, d21 = r[..., 2, 1] + r[..., 1, 2], r[..., 2, 1] - r[..., 1, 2]
    s02, d02 = r[..., 0, 2] + r[..., 2, 0], r[..., 0, 2] - r[..., 2, 0]
    s10, d10 = r[..., 1, 0] + r[..., 0, 1], r[..., 1, 0] - r[..., 0, 1]
    piv = np.stack([1 + tr, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22], axis=-1)
    # unnormalised candidates: each row equals 4 * q_pivot * q (with q_pivot the pivot component)
    cands = np.stack(
        [
            np.stack([piv[..., 0], d21, d02, d10], axis=-1),
            np.stack([d21, piv[..., 1], s10, s02], axis=-1),
            np.stack([d02, s10, piv[..., 2], s21], axis=-1),
            np.stack([d10, s02, s21, piv[..., 3]], axis=-1),
        ],
        axis=-2,
    )  # (..., 4, 4)
    best = np.argmax(piv, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions.

    **Arguments:**

    - ``q``: quaternions (w, x, y, z) ``(..., 4)``; normalised first.

    **Returns:**

    ``(..., 3, 3)``.
    """
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = (q[..., j] for j in range(4))
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def slerp(q0: np.ndarray, q1: np.ndarray, t) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shortest arc (Lengyel 2001).

    q1 is negated when q0 . q1 < 0 (q and -q are the same rotation); nearly identical quaternions use
    normalised lerp.

    **Arguments:**

    - ``q0``, ``q1``: ``(..., 4)``.
    - ``t``: scalar or array, broadcast against the leading axes.

    **Returns:**

    Shape broadcast(t.shape + (1,), q.shape), e.g. t ``(T, 1)`` and q ``(K, 4)`` give ``(T, K, 4)``.
    """
    q0 = np.asarray(q0, np.float64)
    q1 = np.asarray(q1, np.float64)
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    t = np.asarray(t, np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    theta = np.arccos(dot)
    near = dot > SLERP_LINEAR_DOT
    sin_theta = np.where(near, 1.0, np.sin(theta))
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / sin_theta)
    w1 = np.where(near, t, np.sin(t * theta) / sin_theta)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def rotation_angle(r: np.ndarray) -> np.ndarray:
    """Rotation angle of rotation matrices, via the quaternion (accurate near 0).

    **Arguments:**

    - ``r``: ``(..., 3, 3)``.

    **Returns:**

    Angles ``(...)`` in [0, pi].
    """
    q = quat_from_matrix(r)
    return 2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), np.abs(q[..., 0]))


# ------------------------------------------------------------------------------------------ part graph


def between_faces(faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The "between" triangles: faces whose (assigned) vertices carry more than one label.

    **Arguments:**

    - ``faces``: ``(F, 3)``.
    - ``labels``: ``(V,)`` parts (-1: unassigned).

    **Returns:**

    A boolean mask ``(F,)``.
    """
    fl = np.asarray(labels)[np.asarray(faces)]  # (F, 3)
    ok = fl >= 0
    lo = np.where(ok, fl, np.iinfo(fl.dtype).max).min(axis=1)
    hi = np.where(ok, fl, -1).max(axis=1)
    return ok.any(axis=1) & (hi > lo)


def _face_label_pairs(faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(P, 2) pairs (a, b), a < b, of different non-negative labels on one face, with repeats (one per face edge)."""
    fl = np.asarray(labels)[np.asarray(faces)]
    pairs = np.concatenate([fl[:, [0, 1]], fl[:, [1, 2]], fl[:, [2, 0]]], axis=0)
    pairs = pairs[(pairs[:, 0] != pairs[:, 1]) & (pairs >= 0).all(axis=1)]
    return np.sort(pairs, axis=1)


def part_adjacency(faces: np.ndarray, labels: np.ndarray, k: int) -> list[set[int]]:
    """Part adjacency: ``adj[a]`` is the set of parts b != a such that some triangle has vertices of a and b.

    **Arguments:**

    - ``faces``: ``(F, 3)``.
    - ``labels``: ``(V,)`` parts; -1 (unassigned vertices) is ignored.
    - ``k``: K.

    **Returns:**

    A list of K sets.
    """
    adj: list[set[int]] = [set() for _ in range(k)]
    for a, b in np.unique(_face_label_pairs(faces, labels), axis=0):
        adj[int(a)].add(int(b))
        adj[int(b)].add(int(a))
    return adj


def bfs_tree(adjacency: Sequence[set[int]], angles: np.ndarray) -> tuple[list[int], np.ndarray, list[int]]:
    """Breadth-first spanning forest of the part graph (Algorithm 2).

    Each connected component is rooted at its part with the smallest rotation angle ``angles[k]`` (ties: the
    lowest index); neighbours are visited in increasing index order.

    **Arguments:**

    - ``adjacency``: :func:`part_adjacency`'s K sets.
    - ``angles``: ``(K,)`` rotation angles.

    **Returns:**

    ``(visit order, parent (K,) with -1 for roots, roots)``.
    """
    k = len(adjacency)
    parent = np.full(k, -1, np.int64)
    seen = np.zeros(k, bool)
    order: list[int] = []
    roots: list[int] = []
    for start in range(k):
        if seen[start]:
            continue
        comp, queue = [start], deque([start])  # collect the component first to pick its root
        seen[start] = True
        while queue:
            a = queue.popleft()
            for b in sorted(adjacency[a]):
                if not seen[b]:
                    seen[b] = True
                    comp.append(b)
                    queue.append(b)
        root = min(comp, key=lambda j: (float(angles[j]), j))
        roots.append(root)
        visited, queue = {root}, deque([root])
        while queue:
            a = queue.popleft()
            order.append(a)
            for b in sorted(adjacency[a]):
                if b not in visited:
                    visited.add(b)
                    parent[b] = a
                    queue.append(b)
    return order, parent, roots


# ------------------------------------------------------------------------------------------ joints


def joint_points(
    vertices_m: np.ndarray, faces: np.ndarray, labels: np.ndarray, pairs: np.ndarray, *, weighting: str = "uniform"
) -> np.ndarray:
    """Contact points of the part pairs ``pairs`` in one shape.

    The contact point of (a, b) is the mass centre of the triangles that have vertices in both a and b:
    ``weighting="uniform"`` (default) gives every triangle the same mass (plain mean of the triangle
    centroids); ``"area"`` weights each centroid by the triangle's area in this shape (falling back to the
    plain mean where the total area is ~0).

    **Arguments:**

    - ``vertices_m``: one shape ``(V, 3)``.
    - ``faces``: triangles ``(F, 3)``.
    - ``labels``: the part of every vertex ``(V,)``.
    - ``pairs``: part pairs ``(n, 2)``.
    - ``weighting``: ``"uniform"`` or ``"area"``.

    **Returns:**

    The contact points ``(n, 3)``; NaN for a pair that shares no triangle.

    **Raises:**

    ``ValueError`` if ``weighting`` is neither ``"uniform"`` nor ``"area"``.
    """
    if weighting not in ("uniform", "area"):
        raise ValueError(f"weighting must be 'uniform' or 'area', got {weighting!r}")
    v = np.asarray(vertices_m, np.float64)
    faces = np.asarray(faces)
    fl = np.asarray(labels)[faces]  # (F, 3)
    tri = v[faces]  # (F, 3, 3)
    cen = tri.mean(axis=1)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    out = np.full((len(pairs), 3), np.nan)
    for j, (a, b) in enumerate(pairs):  # loop over joints only
        sel = (fl == a).any(axis=1) & (fl == b).any(axis=1)
        if not sel.any():
            continue
        w = area[sel] if weighting == "area" else np.ones(int(sel.sum()))
        if w.sum() <= 1e-300:
            w = np.ones_like(w)
        out[j] = (w[:, None] * cen[sel]).sum(axis=0) / w.sum()
    return out


def joint_latents(
    params: MFA,
    labels: np.ndarray,
    faces: np.ndarray,
    vertices: np.ndarray,
    pairs: np.ndarray,
    shapes: Sequence[int],
    *,
    weighting: str = "uniform",
) -> tuple[np.ndarray, np.ndarray]:
    """Latent images of the joints of ``pairs`` = (a, b) in the given shapes, used by eq. (23).

    **Arguments:**

    - ``params``: the fitted mixture.
    - ``labels``: the part of every vertex ``(V,)``.
    - ``faces``: triangles ``(F, 3)``.
    - ``vertices``: the training shapes ``(M, V, 3)``.
    - ``pairs``: part pairs ``(n, 2)``.
    - ``shapes``: the indices of the shapes.
    - ``weighting``: the contact points' mass centre (:func:`joint_points`).

    **Returns:**

    ``(z_a, z_b)``, each ``(len(shapes), n, 3)``, with z_a^m = R_a^m^T (c^m - t_a^m), z_b^m = R_b^m^T (c^m - t_b^m)
    and c^m the contact point of (a, b) in shape m (:func:`joint_points`).
    """
    rot, mu = np.asarray(params.rot, np.float64), np.asarray(params.mu, np.float64)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    za, zb = [], []
    for m in shapes:
        c = joint_points(np.asarray(vertices)[m], faces, labels, pairs, weighting=weighting)  # (n, 3)
        a, b = pairs[:, 0], pairs[:, 1]
        za.append(np.einsum("nyx,ny->nx", rot[a, m], c - mu[a, m]))
        zb.append(np.einsum("nyx,ny->nx", rot[b, m], c - mu[b, m]))
    return np.stack(za), np.stack(zb)


# ------------------------------------------------------------------------------------------ the path


@dataclasses.dataclass(frozen=True)
class PosePath:
    """Interpolated rigid motions of every part (Algorithm 2).

    ``rot`` (T, K, 3, 3) and ``trans`` (T, K, 3) are R_k(t), t_k(t); ``parent`` (K,) the BFS parent (-1 for
    roots); ``joints`` (n, 2) the tree edges (child a, parent b) in visit order; ``joint_a`` / ``joint_b``
    (T, n, 3) the blended latent joint images z_a(t), z_b(t) used in eq. (23).
    """

    ts: np.ndarray
    rot: np.ndarray
    trans: np.ndarray
    order: list[int]
    parent: np.ndarray
    roots: list[int]
    joints: np.ndarray
    joint_a: np.ndarray
    joint_b: np.ndarray


def pose_path(
    params: MFA,
    labels: np.ndarray,
    faces: np.ndarray,
    vertices: np.ndarray,
    source: int,
    target: int,
    ts: Sequence[float],
    *,
    weighting: str = "uniform",
) -> PosePath:
    """Rotations (slerp) and translations (linear for roots, eq. (23) otherwise) of every part at every t.

    **Arguments:**

    - ``params``: the fitted mixture (:class:`~jaxdeform.parts.mfa.MFA`, data units).
    - ``labels``: the part of every vertex ``(V,)``.
    - ``faces``: triangles ``(F, 3)``.
    - ``vertices``: the training shapes ``(M, V, 3)``.
    - ``source``, ``target``: indices of the two end shapes among the training shapes.
    - ``ts``: the interpolation parameters (0: ``source``, 1: ``target``).
    - ``weighting``: the joint points' mass centre, ``"uniform"`` or ``"area"`` (:func:`joint_points`).

    **Returns:**

    A :class:`PosePath`; its rotations are exactly the end shapes' at t = 0 and t = 1.
    """
    rot = np.asarray(params.rot, np.float64)
    mu = np.asarray(params.mu, np.float64)
    k = rot.shape[0]
    labels = np.asarray(labels)
    faces = np.asarray(faces)
    ts = np.asarray(ts, np.float64).reshape(-1)
    r_s, r_g = rot[:, source], rot[:, target]  # (K, 3, 3)
    angles = rotation_angle(np.einsum("kxy,kzy->kxz", r_g, r_s))  # angle of R^g (R^s)^T
    order, parent, roots = bfs_tree(part_adjacency(faces, labels, k), angles)

    q = slerp(quat_from_matrix(r_s), quat_from_matrix(r_g), ts[:, None])  # (T, K, 4)
    r_t = matrix_from_quat(q)
    # exact endpoints (slerp at t = 0 / 1 reproduces R only up to round-off of the quaternion round trip)
    r_t = np.where((ts == 0.0)[:, None, None, None], r_s[None], r_t)
    r_t = np.where((ts == 1.0)[:, None, None, None], r_g[None], r_t)

    joints = np.array([(a, int(parent[a])) for a in order if parent[a] >= 0], np.int64).reshape(-1, 2)
    za, zb = joint_latents(params, labels, faces, vertices, joints, (source, target), weighting=weighting)
    w = ts[:, None, None]
    ja = (1.0 - w) * za[0][None] + w * za[1][None]  # (T, n, 3)
    jb = (1.0 - w) * zb[0][None] + w * zb[1][None]

    tr = (1.0 - ts)[:, None, None] * mu[None, :, source] + ts[:, None, None] * mu[None, :, target]  # (T, K, 3)
    row = {int(a): j for j, a in enumerate(joints[:, 0])}
    for a in order:  # BFS order: the parent is always placed before the child
        b = int(parent[a])
        if b < 0:
            continue
        j = row[a]
        # eq. (23): R_a(t) z_a(t) + t_a(t) = R_b(t) z_b(t) + t_b(t)
        tr[:, a] = (
            np.einsum("txy,ty->tx", r_t[:, b], jb[:, j]) + tr[:, b] - np.einsum("txy,ty->tx", r_t[:, a], ja[:, j])
        )
    return PosePath(ts, r_t, tr, order, parent, roots, joints, ja, jb)


def interpolate(
    params: MFA,
    labels: np.ndarray,
    latent: np.ndarray,
    faces: np.ndarray,
    vertices: np.ndarray,
    source: int,
    target: int,
    ts: Sequence[float],
    *,
    weighting: str = "uniform",
) -> np.ndarray:
    """Poses between training shapes ``source`` and ``target`` (Algorithm 2).

    Part motions come from :func:`pose_path` (slerp, eq. (23)); vertex i of part k is
    p_i(t) = R_k(t) (z_i + (1 - t) e_i^s + t e_i^g) + t_k(t) (eq. (24)) with the latent residuals
    e_i^m = R_k^m^T (p_i^m - t_k^m) - z_i. Vertices labelled -1 move linearly.

    **Arguments:**

    - ``params``: the fitted mixture (:class:`~jaxdeform.parts.mfa.MFA`, data units).
    - ``labels``: the part of every vertex ``(V,)``.
    - ``latent``: the latent images z_i ``(V, 3)`` (``mfa.latent_images``).
    - ``faces``: triangles ``(F, 3)``.
    - ``vertices``: the training shapes ``(M, V, 3)``.
    - ``source``, ``target``: indices of the two end shapes among the training shapes.
    - ``ts``: the interpolation parameters (0: ``source``, 1: ``target``).
    - ``weighting``: the joint points' mass centre, ``"uniform"`` or ``"area"`` (:func:`joint_points`).

    **Returns:**

    The poses ``(len(ts), V, 3)``. At t = 0 / 1 the source / target shape is reproduced (exactly up to round-off,
    since the joint latents are those of the end shapes).
    """
    rot = np.asarray(params.rot, np.float64)
    mu = np.asarray(params.mu, np.float64)
    labels = np.asarray(labels)
    z = np.asarray(latent, np.float64)
    verts = np.asarray(vertices, np.float64)
    path = pose_path(params, labels, faces, verts, source, target, ts, weighting=weighting)
    ts = path.ts
    lab = np.maximum(labels, 0)

    def residual(m: int) -> np.ndarray:  # e_i^m (V, 3) in the latent space of part labels[i]
        return np.einsum("vyx,vy->vx", rot[lab, m], verts[m] - mu[lab, m]) - z

    w = ts[:, None, None]
    e_t = (1.0 - w) * residual(source)[None] + w * residual(target)[None]  # (T, V, 3)
    out = np.einsum("tvxy,tvy->tvx", path.rot[:, lab], z[None] + e_t) + path.trans[:, lab]  # eq. (24)
    lin = (1.0 - w) * verts[source][None] + w * verts[target][None]
    return np.where((labels >= 0)[None, :, None], out, lin)


def contact_gaps(
    params: MFA,
    labels: np.ndarray,
    latent: np.ndarray,
    faces: np.ndarray,
    vertices: np.ndarray,
    source: int,
    target: int,
    ts: Sequence[float],
    *,
    weighting: str = "uniform",
) -> np.ndarray:
    """Contact gaps |R_a(t) z_a(t) + t_a(t) - (R_b(t) z_b(t) + t_b(t))| per tree edge.

    The joints are the BFS tree edges (child a, parent b) in visit order (``pose_path(...).joints``). Eq. (23)
    makes every gap zero up to round-off; the function reports it as a check.

    **Arguments:**

    - ``params``: the fitted mixture (:class:`~jaxdeform.parts.mfa.MFA`, data units).
    - ``labels``: the part of every vertex ``(V,)``.
    - ``latent``: the latent images z_i ``(V, 3)`` (``mfa.latent_images``); accepted for a signature parallel to
        :func:`interpolate` and unused (the joints' latent images come from the end shapes).
    - ``faces``: triangles ``(F, 3)``.
    - ``vertices``: the training shapes ``(M, V, 3)``.
    - ``source``, ``target``: indices of the two end shapes among the training shapes.
    - ``ts``: the interpolation parameters (0: ``source``, 1: ``target``).
    - ``weighting``: the joint points' mass centre, ``"uniform"`` or ``"area"`` (:func:`joint_points`).

    **Returns:**

    The gaps ``(len(ts), n_joints)`` (zero columns when the parts form no joint).
    """
    del latent
    path = pose_path(params, labels, faces, vertices, source, target, ts, weighting=weighting)
    if len(path.joints) == 0:
        return np.zeros((len(path.ts), 0))
    a, b = path.joints[:, 0], path.joints[:, 1]
    pa = np.einsum("tnxy,tny->tnx", path.rot[:, a], path.joint_a) + path.trans[:, a]
    pb = np.einsum("tnxy,tny->tnx", path.rot[:, b], path.joint_b) + path.trans[:, b]
    return np.linalg.norm(pa - pb, axis=-1)
