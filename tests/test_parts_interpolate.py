"""Pose interpolation of seed 003 (Algorithm 2): quaternions, part graph, and an articulated synthetic chain."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxdeform.parts.interpolate import (
    between_faces,
    bfs_tree,
    contact_gaps,
    interpolate,
    joint_points,
    matrix_from_quat,
    part_adjacency,
    pose_path,
    quat_from_matrix,
    rotation_angle,
    slerp,
)
from jaxdeform.parts.mfa import MFA, latent_images, reconstruct


def rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def angle_by_trace(r):
    return np.arccos(np.clip((np.trace(r, axis1=-2, axis2=-1) - 1) / 2, -1, 1))


# ------------------------------------------------------------------------------------------ quaternions


def test_quaternion_round_trip_all_pivots():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(60, 3))
    angles = np.concatenate(
        [rng.uniform(0, np.pi, 50), [0.0, 1e-9, np.pi, np.pi - 1e-7, np.pi, np.pi, 2.0, 3.0, 0.5, 1.0]]
    )
    axes[-5:-2] = np.eye(3)  # half turns about the coordinate axes: the x / y / z pivots
    r = np.stack([rot(a, t) for a, t in zip(axes, angles)])
    q = quat_from_matrix(r)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(matrix_from_quat(q), r, atol=1e-12)
    np.testing.assert_allclose(rotation_angle(r), angles, atol=1e-7)
    # analytic: 90 degrees about z is (cos 45, 0, 0, sin 45)
    np.testing.assert_allclose(
        quat_from_matrix(rot([0, 0, 1], np.pi / 2)), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-15
    )


def test_slerp_analytic_endpoints_midpoint_shortest_arc():
    q0 = quat_from_matrix(np.eye(3))
    q1 = quat_from_matrix(rot([0, 0, 1], np.pi / 2))
    ts = np.array([0.0, 0.25, 0.5, 1.0])
    q = slerp(q0, q1, ts)  # (4,) times (4,) -> (4, 4)
    r = matrix_from_quat(q)
    np.testing.assert_allclose(r[0], np.eye(3), atol=1e-14)
    np.testing.assert_allclose(r[-1], rot([0, 0, 1], np.pi / 2), atol=1e-14)
    np.testing.assert_allclose(r[1], rot([0, 0, 1], np.pi / 8), atol=1e-14)
    np.testing.assert_allclose(r[2], rot([0, 0, 1], np.pi / 4), atol=1e-14)
    # -q1 is the same rotation: the shortest arc gives the same path
    np.testing.assert_allclose(matrix_from_quat(slerp(q0, -q1, 0.5)), rot([0, 0, 1], np.pi / 4), atol=1e-14)
    # 300 degrees about z the long way is 60 degrees the short way: the midpoint is -30 degrees
    q2 = quat_from_matrix(rot([0, 0, 1], 5 * np.pi / 3))
    np.testing.assert_allclose(matrix_from_quat(slerp(q0, q2, 0.5)), rot([0, 0, 1], -np.pi / 6), atol=1e-14)
    # (nearly) identical quaternions: no NaN, stays put
    qa = quat_from_matrix(rot([1, 2, 3], 0.7))
    qb = quat_from_matrix(rot([1, 2, 3], 0.7 + 1e-12))
    for qq in (qa, qb):
        out = slerp(qa, qq, np.linspace(0, 1, 7))
        assert np.all(np.isfinite(out))
        np.testing.assert_allclose(matrix_from_quat(out), np.broadcast_to(rot([1, 2, 3], 0.7), (7, 3, 3)), atol=1e-11)
    # batched: (T, 1) times (K, 4) -> (T, K, 4), constant angular speed
    qs = quat_from_matrix(np.stack([rot([0, 1, 0], 1.2), rot([1, 1, 0], 2.5)]))
    out = slerp(np.stack([q0, q0]), qs, np.linspace(0, 1, 5)[:, None])
    assert out.shape == (5, 2, 4)
    np.testing.assert_allclose(
        rotation_angle(matrix_from_quat(out)), np.linspace(0, 1, 5)[:, None] * [1.2, 2.5], atol=1e-12
    )


# ------------------------------------------------------------------------------------------ synthetic chain


def tube(n_rings=15, n_around=12, length=3.0, radius=0.3, offset=(0.0, 0.0, 0.0)):
    """Open cylinder along x, rings at cell centres (none on the integer joints x = 1, 2)."""
    x = (np.arange(n_rings) + 0.5) * length / n_rings
    a = 2 * np.pi * np.arange(n_around) / n_around
    xx, aa = np.meshgrid(x, a, indexing="ij")
    verts = np.stack([xx, radius * np.cos(aa), radius * np.sin(aa)], -1).reshape(-1, 3) + np.asarray(offset)
    i, j = np.meshgrid(np.arange(n_rings - 1), np.arange(n_around), indexing="ij")
    v00 = i * n_around + j
    v01 = i * n_around + (j + 1) % n_around
    v10 = v00 + n_around
    v11 = v01 + n_around
    faces = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)])
    labels = np.clip(np.floor(verts[:, 0] - offset[0]).astype(np.int64), 0, int(length) - 1)
    return verts, faces.astype(np.int64), labels


def chain_pose(rest, labels, local_rots, base):
    """Forward kinematics of the 3-segment chain with joints at x = 0, 1, 2: world (R_k, t_k) and the shape."""
    joints = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    rs, ts = [], []
    r_world, j_world = np.eye(3), np.asarray(base, float)
    for k, a in enumerate(local_rots):
        if k > 0:
            j_world = r_world @ (joints[k] - joints[k - 1]) + j_world
        r_world = r_world @ a
        rs.append(r_world)
        ts.append(j_world - r_world @ joints[k])
    rs, ts = np.stack(rs), np.stack(ts)
    return rs, ts, np.einsum("vxy,vy->vx", rs[labels], rest) + ts[labels]


@pytest.fixture(scope="module")
def chain():
    rest, faces, labels = tube()
    poses = [
        ([np.eye(3)] * 3, [0.0, 0, 0]),
        (
            [rot([0, 0, 1], np.radians(20)), rot([0, 1, 0], np.radians(50)), rot([0, 0, 1], np.radians(70))],
            [0.2, 0.1, 0.0],
        ),
        (
            [rot([1, 0, 0], np.radians(-10)), rot([1, 1, 0], np.radians(-60)), rot([0, 1, 1], np.radians(45))],
            [-0.1, 0.3, 0.2],
        ),
    ]
    rs, ts, verts = zip(*(chain_pose(rest, labels, lr, b) for lr, b in poses))
    rot_km = np.stack(rs, axis=1)  # (K, M, 3, 3)
    mu_km = np.stack(ts, axis=1)  # (K, M, 3)
    k = 3
    params = MFA(
        log_pi=jnp.full(k, -np.log(k)),
        mu=jnp.asarray(mu_km),
        rot=jnp.asarray(rot_km),
        d=jnp.ones((k, 3)),
        sigma2=jnp.full(k, 1e-6),
    )
    return params, labels, rest, faces, np.stack(verts)


def bbox_diag(verts):
    v = verts.reshape(-1, 3)
    return float(np.linalg.norm(v.max(0) - v.min(0)))


def test_chain_construction_and_graph(chain):
    params, labels, rest, faces, verts = chain
    np.testing.assert_allclose(
        np.asarray(reconstruct(params, jnp.asarray(labels), jnp.asarray(rest))), verts, atol=1e-12
    )
    assert part_adjacency(faces, labels, 3) == [{1}, {0, 2}, {1}]
    nb = between_faces(faces, labels)
    assert nb.sum() == 2 * 2 * 12  # two bands of 12 quads
    # the rest joint points lie on the axis at x = 1, 2
    c = joint_points(rest, faces, labels, np.array([[1, 0], [2, 1]]))
    np.testing.assert_allclose(c, [[1, 0, 0], [2, 0, 0]], atol=1e-12)


@pytest.mark.parametrize("source, target", [(0, 1), (2, 1), (1, 2)])
def test_chain_interpolation(chain, source, target):
    params, labels, rest, faces, verts = chain
    ts = np.linspace(0, 1, 5)
    out = interpolate(params, labels, rest, faces, verts, source, target, ts)
    assert out.shape == (5, len(rest), 3)
    np.testing.assert_allclose(out[0], verts[source], atol=1e-6)
    np.testing.assert_allclose(out[-1], verts[target], atol=1e-6)

    diag = bbox_diag(verts)
    gaps = contact_gaps(params, labels, rest, faces, verts, source, target, ts)
    assert gaps.shape == (5, 2)
    assert np.all(gaps <= 1e-6 * diag)

    # root = smallest rotation between the end shapes (computed here independently, by the trace)
    rk = np.asarray(params.rot)
    angles = angle_by_trace(np.einsum("kxy,kzy->kxz", rk[:, target], rk[:, source]))
    path = pose_path(params, labels, faces, verts, source, target, ts)
    root = int(np.argmin(angles))
    assert path.roots == [root]
    assert path.parent[root] == -1 and sorted(path.order) == [0, 1, 2]
    # at t = 0.5 the root's rotation is the half-angle rotation about the same axis: H = R_s^T R(0.5), H^2 = R_s^T R_g
    h = rk[root, source].T @ path.rot[2, root]
    np.testing.assert_allclose(h @ h, rk[root, source].T @ rk[root, target], atol=1e-12)
    assert np.isclose(angle_by_trace(h), angles[root] / 2, atol=1e-9)
    # ... and the root's translation is linear, the vertices of the root are posed rigidly by (R(t), t(t))
    np.testing.assert_allclose(
        path.trans[2, root], 0.5 * (np.asarray(params.mu)[root, source] + np.asarray(params.mu)[root, target])
    )
    sel = labels == root
    np.testing.assert_allclose(out[2, sel], rest[sel] @ path.rot[2, root].T + path.trans[2, root], atol=1e-12)

    # every part stays rigid (edges inside a part keep their length) at every t
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    inner = labels[e[:, 0]] == labels[e[:, 1]]
    rest_len = np.linalg.norm(rest[e[inner, 0]] - rest[e[inner, 1]], axis=-1)
    for p in out:
        np.testing.assert_allclose(np.linalg.norm(p[e[inner, 0]] - p[e[inner, 1]], axis=-1), rest_len, atol=1e-12)

    # the joint point of the interpolated mesh (centre of the between triangles) stays at the constrained joint
    pairs, a, b = path.joints, path.joints[:, 0], path.joints[:, 1]
    for t_i, p in enumerate(out):
        c = joint_points(p, faces, labels, pairs)
        through_a = np.einsum("nxy,ny->nx", path.rot[t_i, a], path.joint_a[t_i]) + path.trans[t_i, a]
        assert np.all(np.linalg.norm(c - through_a, axis=-1) <= 0.01 * diag)
    # the true (rest) joints x = 1, 2 mapped through both parts stay within 1% of the diagonal
    true_joint = np.stack([np.maximum(a, b), 0 * a, 0 * a], -1).astype(float)
    pa = np.einsum("tnxy,ny->tnx", path.rot[:, a], true_joint) + path.trans[:, a]
    pb = np.einsum("tnxy,ny->tnx", path.rot[:, b], true_joint) + path.trans[:, b]
    assert np.all(np.linalg.norm(pa - pb, axis=-1) <= 0.01 * diag)

    # area-weighted joint points: same guarantees by construction (ends exact, constrained gaps ~0)
    out_area = interpolate(params, labels, rest, faces, verts, source, target, ts, weighting="area")
    np.testing.assert_allclose(out_area[0], verts[source], atol=1e-6)
    np.testing.assert_allclose(out_area[-1], verts[target], atol=1e-6)
    assert np.all(contact_gaps(params, labels, rest, faces, verts, source, target, ts, weighting="area") <= 1e-6 * diag)


def test_chain_with_residuals_and_mfa_latents(chain):
    """Non-rigid residuals (eq. 24) and the MFA's own latent images: the ends are still reproduced."""
    params, labels, rest, faces, verts = chain
    rng = np.random.default_rng(3)
    noisy = verts + 0.01 * rng.normal(size=verts.shape)
    y = jnp.asarray(noisy.transpose(1, 0, 2))
    z = np.asarray(latent_images(y, params, jnp.asarray(labels)))
    assert np.abs(z - rest).max() < 0.05
    ts = np.linspace(0, 1, 5)
    out = interpolate(params, labels, z, faces, noisy, 2, 1, ts)
    np.testing.assert_allclose(out[0], noisy[2], atol=1e-6)
    np.testing.assert_allclose(out[-1], noisy[1], atol=1e-6)
    gaps = contact_gaps(params, labels, z, faces, noisy, 2, 1, ts)
    assert np.all(gaps <= 1e-6 * bbox_diag(noisy))
    # the residual is blended: the midpoint lies between the rigid poses' noise levels (no blow-up)
    clean = interpolate(params, labels, rest, faces, verts, 2, 1, ts)
    assert np.abs(out[2] - clean[2]).max() < 0.05


def test_disconnected_components_get_own_roots():
    v1, f1, l1 = tube(n_rings=10, length=2.0)
    v2, f2, l2 = tube(n_rings=10, length=2.0, offset=(0.0, 2.0, 0.0))
    rest = np.concatenate([v1, v2])
    faces = np.concatenate([f1, f2 + len(v1)])
    labels = np.concatenate([l1, l2 + 2])
    adj = part_adjacency(faces, labels, 4)
    assert adj == [{1}, {0}, {3}, {2}]
    # part 1 turns less than part 0, part 2 less than part 3
    order, parent, roots = bfs_tree(adj, np.array([0.5, 0.1, 0.2, 0.9]))
    assert roots == [1, 2] and parent.tolist() == [1, -1, -1, 2] and order == [1, 0, 2, 3]

    # two shapes: rest and every part rotated rigidly about its own joint (x = 1 in each tube)
    k, m = 4, 2
    rot_km = np.stack([[np.eye(3)] * m for _ in range(k)])
    mu_km = np.zeros((k, m, 3))
    for part, (ang, piv) in enumerate([(0.3, (0, 0, 0)), (0.8, (1, 0, 0)), (0.6, (0, 2, 0)), (0.2, (1, 2, 0))]):
        r = rot([0, 0, 1], ang)
        rot_km[part, 1] = r
        mu_km[part, 1] = np.asarray(piv, float) - r @ np.asarray(piv, float)
    params = MFA(jnp.full(k, -np.log(k)), jnp.asarray(mu_km), jnp.asarray(rot_km), jnp.ones((k, 3)), jnp.full(k, 1e-6))
    verts = np.asarray(reconstruct(params, jnp.asarray(labels), jnp.asarray(rest)))
    ts = np.linspace(0, 1, 5)
    path = pose_path(params, labels, faces, verts, 0, 1, ts)
    assert path.roots == [0, 3]  # smallest rotation in each component
    out = interpolate(params, labels, rest, faces, verts, 0, 1, ts)
    np.testing.assert_allclose(out[0], verts[0], atol=1e-6)
    np.testing.assert_allclose(out[-1], verts[1], atol=1e-6)
    gaps = contact_gaps(params, labels, rest, faces, verts, 0, 1, ts)
    assert gaps.shape == (5, 2) and np.all(gaps <= 1e-6 * bbox_diag(verts))
