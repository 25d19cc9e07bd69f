"""Tests of the synthetic mesh sequences (jaxdeform.data.synthetic)."""

import numpy as np
import pytest

from jaxdeform.data import synthetic

N_AROUND, N_ALONG, RADIUS, LENGTH = 24, 64, 0.12, 4.0


@pytest.fixture(scope="module")
def seq():
    return synthetic.bending_tube_sequence()


def _rings(verts, n_around=N_AROUND):
    """(..., V, 3) -> (..., n_along, n_around, 3)."""
    return verts.reshape(*verts.shape[:-2], -1, n_around, 3)


def _centres(verts, n_around=N_AROUND):
    return _rings(verts, n_around).mean(axis=-2)


def _face_normals(verts, faces):
    p = verts[..., faces, :]  # (..., F, 3, 3)
    return np.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])


def _rmf(points):
    """Rotation-minimizing frame along a polyline (double reflection, Wang et al. 2008).

    Starts from the rest frame of the tube (reference vector +y at ring 0); returns tangents and
    reference vectors at every point.
    """
    t = np.gradient(points, axis=0, edge_order=2)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    r = np.array([0.0, 1.0, 0.0])
    r = r - (r @ t[0]) * t[0]
    refs = [r / np.linalg.norm(r)]
    for i in range(len(points) - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        r_l = refs[-1] - (2.0 / c1) * (v1 @ refs[-1]) * v1
        t_l = t[i] - (2.0 / c1) * (v1 @ t[i]) * v1
        v2 = t[i + 1] - t_l
        c2 = v2 @ v2
        r_n = r_l - (2.0 / c2) * (v2 @ r_l) * v2 if c2 > 1e-30 else r_l
        refs.append(r_n / np.linalg.norm(r_n))
    return t, np.array(refs)


def _wrap(a):
    return np.angle(np.exp(1j * a))


def test_tube_layout_and_orientation():
    v, f = synthetic.tube()
    assert v.shape == (N_ALONG * N_AROUND, 3) and v.dtype == np.float64
    assert f.shape == (2 * (N_ALONG - 1) * N_AROUND, 3) and f.dtype == np.int32
    np.testing.assert_allclose(v[0], [0.0, RADIUS, 0.0])
    assert v[:, 0].min() == 0.0 and v[:, 0].max() == LENGTH
    np.testing.assert_allclose(np.hypot(v[:, 1], v[:, 2]), RADIUS)
    # Outward: each face normal points away from the x axis.
    n = _face_normals(v, f)
    c = v[f].mean(axis=1)
    c[:, 0] = 0.0
    assert np.all(np.einsum("fi,fi->f", n, c) > 0)
    # Every edge is shared by at most two faces, boundary edges are the two end rings only.
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert counts.max() == 2 and (counts == 1).sum() == 2 * N_AROUND
    # Consistent orientation: each interior directed edge appears once in each direction.
    d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len(np.unique(d, axis=0)) == len(d)


def test_shapes_dtypes_and_validity(seq):
    v, f = seq
    assert v.shape == (24, N_ALONG * N_AROUND, 3) and v.dtype == np.float64
    assert f.shape == (2 * (N_ALONG - 1) * N_AROUND, 3) and f.dtype == np.int32
    assert f.min() == 0 and f.max() == v.shape[1] - 1
    assert np.all(np.isfinite(v))
    areas = 0.5 * np.linalg.norm(_face_normals(v, f), axis=-1)
    rest_min = areas[0].min()
    assert rest_min > 1e-4
    assert areas.min() > 0.3 * rest_min


def test_outward_normals_every_frame(seq):
    v, f = seq
    rings = f // N_AROUND  # ring of each corner
    centres = _centres(v)  # (N, L, 3)
    face_axis = centres[:, rings, :].mean(axis=2)  # (N, F, 3): centre line point near each face
    out = v[:, f, :].mean(axis=2) - face_axis
    assert np.all(np.einsum("nfi,nfi->nf", _face_normals(v, f), out) > 0)


def test_deterministic():
    a, fa = synthetic.bending_tube_sequence(seed=3)
    b, fb = synthetic.bending_tube_sequence(seed=3)
    assert np.array_equal(a, b) and np.array_equal(fa, fb)
    c, _ = synthetic.bending_tube_sequence(seed=4)
    assert not np.allclose(a, c)
    # The seed only moves the bumps.
    a0, _ = synthetic.bending_tube_sequence(seed=3, bump_amplitude=0.0)
    c0, _ = synthetic.bending_tube_sequence(seed=4, bump_amplitude=0.0)
    assert np.array_equal(a0, c0)


def test_frame0_is_rest_tube_and_fixed_end(seq):
    v, f = seq
    rv, rf = synthetic.tube(N_AROUND, N_ALONG)
    assert np.array_equal(v[0], rv) and np.array_equal(f, rf)
    # The end at x = 0 (ring 0, vertex 0 included) stays in place in every frame.
    np.testing.assert_allclose(v[:, :N_AROUND], np.broadcast_to(rv[:N_AROUND], (24, N_AROUND, 3)), atol=1e-12)
    np.testing.assert_allclose(v[:, 0], np.broadcast_to([0.0, RADIUS, 0.0], (24, 3)), atol=1e-12)


def test_inextensible_centre_line(seq):
    step = LENGTH / (N_ALONG - 1)
    v, _ = seq
    d = np.linalg.norm(np.diff(_centres(v[-1]), axis=0), axis=-1)
    np.testing.assert_allclose(d, step, rtol=0.01)
    # Without bumps, every frame keeps the spacing (chord of the arc: well within 1%).
    v0, _ = synthetic.bending_tube_sequence(bump_amplitude=0.0)
    d0 = np.linalg.norm(np.diff(_centres(v0), axis=1), axis=-1)
    np.testing.assert_allclose(d0, step, rtol=0.01)


def test_total_turning_exceeds_full_turn(seq):
    v, _ = seq
    c = _centres(v[-1])[:, :2]  # projected on the x-y plane
    seg = np.diff(c, axis=0)
    heading = np.arctan2(seg[:, 1], seg[:, 0])
    turning = _wrap(np.diff(heading))
    total = turning.sum()
    assert total > 2.0 * np.pi
    # The polyline turns from the first to the last segment midpoints: 62/63 of the full angle.
    expected = 1.15 * 2.0 * np.pi * (N_ALONG - 2) / (N_ALONG - 1)
    assert abs(total - expected) < 0.02 * expected
    # It bends one way only, with bounded curvature (no kinks).
    assert np.all(turning > 0) and turning.max() < 0.2
    # Local rotation w.r.t. the rest pose at the far end exceeds pi (about 7 rad).
    t, _ = _rmf(_centres(v[-1]))
    assert np.all(turning.cumsum()[-5:] > np.pi) and abs(t[0] @ np.array([1.0, 0.0, 0.0]) - 1) < 1e-3


@pytest.mark.parametrize("twist_turns", [0.5, 0.3, -0.2])
def test_twist_about_centre_line(twist_turns):
    """The far ring's angular offset, measured in a numerically propagated rotation-minimizing frame
    (independent of the generator's analytic frame), equals the requested twist."""
    v, _ = synthetic.bending_tube_sequence(max_twist_turns=twist_turns)
    last = _rings(v[-1])
    centres = last.mean(axis=1)
    t, r = _rmf(centres)
    u, w = r[-1], np.cross(t[-1], r[-1])
    d = last[-1] - centres[-1]
    ang = np.arctan2(d @ w, d @ u)
    rest = 2.0 * np.pi * np.arange(N_AROUND) / N_AROUND
    offset = np.angle(np.mean(np.exp(1j * (ang - rest))))  # circular mean, robust to wrapping
    assert abs(_wrap(offset - twist_turns * 2.0 * np.pi)) < np.deg2rad(10.0)
    # Halfway along, half the twist.
    mid = N_ALONG // 2
    d = last[mid] - centres[mid]
    ang = np.arctan2(d @ np.cross(t[mid], r[mid]), d @ r[mid])
    offset = np.angle(np.mean(np.exp(1j * (ang - rest))))
    s_frac = mid / (N_ALONG - 1)
    assert abs(_wrap(offset - s_frac * twist_turns * 2.0 * np.pi)) < np.deg2rad(10.0)


def test_bumps(seq):
    amp = 0.04
    v, _ = seq
    rings = _rings(v)
    dev = np.abs(np.linalg.norm(rings - rings.mean(axis=2, keepdims=True), axis=-1) - RADIUS)
    per_frame = dev.reshape(len(v), -1).max(axis=1)
    assert per_frame[0] < 1e-12
    assert np.any((per_frame > 0.5 * amp) & (per_frame <= 1.5 * amp))
    assert per_frame.max() <= 1.5 * amp
    # Exact check against the same sequence without bumps: radial displacements of peak amp.
    v0, _ = synthetic.bending_tube_sequence(bump_amplitude=0.0)
    disp = np.linalg.norm(v - v0, axis=-1).max(axis=1)
    assert disp[0] == 0.0 and disp[-1] < 1e-12  # bumps appear and disappear
    assert np.any((disp > 0.9 * amp) & (disp <= amp + 1e-12))
    active = (disp > 1e-3 * amp).sum()
    assert 3 <= active < len(v) - 2


def test_no_self_intersection(seq):
    """Ring centres far apart along the tube stay farther apart than the tube diameter (bumps included).

    Rings a few apart are close on any tube (spacing 0.063 < 2 radius), so only pairs separated by more
    than 4 radius of arclength are compared; closer pairs cannot collide because the centre line's
    radius of curvature stays above the tube radius (checked via the turning per segment).
    """
    v, _ = seq
    step = LENGTH / (N_ALONG - 1)
    c = _centres(v)  # (N, L, 3)
    idx = np.arange(N_ALONG)
    far = np.abs(idx[:, None] - idx[None, :]) * step > 4.0 * RADIUS
    dist = np.linalg.norm(c[:, :, None, :] - c[:, None, :, :], axis=-1)
    assert dist[:, far].min() > 2.0 * (RADIUS + 0.04)
    seg = np.diff(c, axis=1)
    seg /= np.linalg.norm(seg, axis=-1, keepdims=True)
    bend = np.arccos(np.clip(np.einsum("nli,nli->nl", seg[:, 1:], seg[:, :-1]), -1.0, 1.0))
    assert np.all(step / np.maximum(bend, 1e-12) > RADIUS)


def test_invalid_arguments():
    with pytest.raises(ValueError):
        synthetic.tube(n_around=2)
    with pytest.raises(ValueError):
        synthetic.bending_tube_sequence(max_bend_turns=10.0)
    with pytest.raises(ValueError):
        synthetic.bending_tube_sequence(n_frames=0)


def test_twisted_bar_is_closed_outward_and_has_no_mirror_plane():
    import trimesh
    from scipy.spatial import cKDTree

    from jaxdeform.data.synthetic import twisted_bar

    v, f = twisted_bar()
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    # no coordinate plane through the centroid mirrors the surface onto itself: some reflected vertices lie
    # far from the surface compared to the bar's size
    tree = cKDTree(trimesh.sample.sample_surface_even(m, 6000, seed=0)[0])
    centre = v.mean(axis=0)
    diagonal = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    for axis in range(3):
        r = v.copy()
        r[:, axis] = 2 * centre[axis] - r[:, axis]
        assert np.max(tree.query(r)[0]) > 0.05 * diagonal, axis
