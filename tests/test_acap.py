import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import expm

from jaxdeform import acap
from jaxdeform.acap import consistency as cons
from jaxdeform.acap.rotations import exp_rotation
from jaxdeform.errors import ConnectivityError, DegenerateMeshError

IDENTITY_FEATURE = np.array([0, 0, 0, 1, 0, 0, 1, 0, 1.0])


def thin_tube(n_around=8, n_along=60, radius=0.05, length=6.0):
    ang = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    s = np.linspace(0, length, n_along)
    v = np.stack(
        [np.repeat(s, n_around), np.tile(radius * np.cos(ang), n_along), np.tile(radius * np.sin(ang), n_along)], 1
    )
    faces = []
    for i in range(n_along - 1):
        for j in range(n_around):
            a, b = i * n_around + j, i * n_around + (j + 1) % n_around
            c, d = a + n_around, b + n_around
            faces += [[a, b, d], [a, d, c]]
    return v, np.asarray(faces)


def bend(v, total_angle, length=6.0):
    """Bend along x into an arc in the x-y plane; the local rotation at arclength s is total*s/L about z."""
    radius = length / total_angle
    th = v[:, 0] / radius
    rr = radius - v[:, 1]
    return np.stack([rr * np.sin(th), radius - rr * np.cos(th), v[:, 2]], 1), th


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_identity_gives_identity_features(dtype):
    v, f = thin_tube()
    feats = np.asarray(acap.encode(v.astype(dtype), f, v[None].astype(dtype)))
    assert feats.dtype == dtype
    np.testing.assert_allclose(
        feats[0], np.broadcast_to(IDENTITY_FEATURE, feats[0].shape), atol=1e-5 if dtype == np.float32 else 1e-10
    )


def test_rigid_motion_gives_unit_stretch_and_constant_rotation():
    v, f = thin_tube()
    rvec = np.array([0.4, -1.0, 2.2])
    r = expm(np.array([[0, -rvec[2], rvec[1]], [rvec[2], 0, -rvec[0]], [-rvec[1], rvec[0], 0]]))
    moved = v @ r.T + [3.0, -1.0, 2.0]
    a = acap.prepare(v, f)
    vecs, s = a.encode_parts(moved[None], "spatial")
    np.testing.assert_allclose(np.asarray(s[0]), np.broadcast_to(np.eye(3), s[0].shape), atol=1e-9)
    np.testing.assert_allclose(np.asarray(vecs[0]), np.broadcast_to(rvec, vecs[0].shape), atol=1e-9)


def test_known_bend_angle_and_consistency_past_pi():
    v, f = thin_tube(n_around=16, n_along=80)
    total = 1.4 * 2 * np.pi
    bent, th = bend(v, total)
    a = acap.prepare(v, f)
    vec, _ = a.encode_parts(bent[None], "spatial")
    vec = np.asarray(vec[0])
    interior = (v[:, 0] > 0.2) & (v[:, 0] < 5.8)  # one-ring fits at the open ends see half a ring
    # The angle follows the bend continuously past pi and 2 pi. (Near 2 pi the rotation is close to the
    # identity and its axis ill-defined, so the axis direction is not compared there.)
    np.testing.assert_allclose(np.linalg.norm(vec[interior], axis=-1), th[interior], atol=4e-2)
    clear = interior & (np.abs(th - 2 * np.pi) > 0.5)
    np.testing.assert_allclose(vec[clear, 2], th[clear], atol=4e-2)
    assert vec[:, 2].max() > 2 * np.pi
    raw, _ = a.encode_parts(bent[None], "none")
    assert np.linalg.norm(np.asarray(raw), axis=-1).max() <= np.pi + 1e-9


def _angles(log_mats):
    return np.linalg.norm(np.stack([log_mats[..., 2, 1], log_mats[..., 0, 2], log_mats[..., 1, 0]], -1), axis=-1)


def test_acap_bar_matches_official_outputs(acap_bar):
    verts, faces, gt = acap_bar
    a = acap.prepare(verts[0], faces)
    vec, s = a.encode_parts(verts, "none")
    r_ours = np.asarray(exp_rotation(vec))
    r_gt = np.array([[expm(m) for m in frame] for frame in gt("LOGRNEW_GT.txt")])
    assert np.abs(r_ours - r_gt).max() <= 2e-2
    s_err = np.abs(np.asarray(s) - gt("S_GT.txt"))
    assert np.quantile(s_err, 0.99) <= 1e-2
    assert np.linalg.norm(np.asarray(vec), axis=-1).max() <= np.pi + 1e-9

    vec_c, _ = a.encode_parts(verts, "spatial")
    ang = np.linalg.norm(np.asarray(vec_c), axis=-1)
    ang_gt = _angles(gt("LOGRNEW_withopt_GT.txt"))
    assert np.quantile(np.abs(ang - ang_gt), 0.99) <= 2e-2
    assert ang.max() >= 5.9


def test_fast_consistency_equals_exact_milp_on_acap_bar(acap_bar):
    verts, faces, _ = acap_bar
    a = acap.prepare(verts[0], faces)
    vec, _ = a.local(verts[1:2])
    vec = np.asarray(vec[0], dtype=np.float64)
    angle = np.linalg.norm(vec, axis=-1)
    axis = vec / np.maximum(angle, 1e-300)[:, None]
    phi_fast, o_fast = cons.spatial(axis[None], angle[None], a.graph)
    phi_milp, o_milp = cons.milp_spatial(axis, angle, a.graph)
    s_edge = cons.edge_signs(axis, angle, a.graph.edges[:, 0], a.graph.edges[:, 1])
    assert cons.orientation_energy(o_fast[0], s_edge, a.graph) == pytest.approx(
        cons.orientation_energy(o_milp, s_edge, a.graph)
    )
    assert cons.turn_energy(phi_fast[0], a.graph) == pytest.approx(
        cons.turn_energy(phi_milp, a.graph), rel=1e-9, abs=1e-9
    )


def test_fast_consistency_is_optimal_on_random_small_meshes():
    """Given the same orientations, the fast turns reach the MILP optimum on a noisy bend past 2 pi."""
    v, f = thin_tube(n_around=6, n_along=25)
    bent, _ = bend(v, 2.3 * np.pi)
    rng = np.random.default_rng(3)
    bent = bent + 0.01 * rng.normal(size=bent.shape)
    a = acap.prepare(v, f)
    vec = np.asarray(a.local(bent[None])[0][0], dtype=np.float64)
    angle = np.linalg.norm(vec, axis=-1)
    axis = vec / np.maximum(angle, 1e-300)[:, None]
    o = cons.milp_orientation(axis, angle, a.graph)
    phi_fast = cons.spatial_turns((o * angle)[None], a.graph)[0]
    phi_milp = o * angle + 2 * np.pi * cons.milp_turns(o * angle, a.graph)
    assert np.abs(phi_milp).max() > 2 * np.pi
    assert cons.turn_energy(phi_fast, a.graph) <= cons.turn_energy(phi_milp, a.graph) + 1e-6


def test_temporal_consistency_is_continuous_in_time():
    v, f = thin_tube()
    frames = np.stack([bend(v, ang)[0] for ang in np.linspace(0.3, 2.6 * np.pi, 16)])
    a = acap.prepare(v, f)
    vec_t, _ = a.encode_parts(frames, "temporal")
    ang_t = np.linalg.norm(np.asarray(vec_t), axis=-1)  # (near 2 pi the axis itself is ill-defined)
    assert np.abs(np.diff(ang_t, axis=0)).max() < 0.6  # each step adds ~0.52 rad at the far end
    assert ang_t[-1].max() > 2 * np.pi


def test_align_turns_picks_the_nearest_branch_of_the_same_rotation():
    rng = np.random.default_rng(3)
    w = rng.normal(size=(50, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    theta = rng.uniform(0.1, 3.1, size=(50, 1))
    v = theta * w
    ref = (theta - 2 * np.pi + rng.uniform(-0.5, 0.5, size=(50, 1))) * w  # near the branch one turn down
    out = np.asarray(cons.align_turns(jnp.asarray(v), jnp.asarray(ref)))
    np.testing.assert_allclose(out, (theta - 2 * np.pi) * w, atol=1e-12)
    # the same rotations
    np.testing.assert_allclose(
        np.asarray(exp_rotation(jnp.asarray(out))), np.asarray(exp_rotation(jnp.asarray(v))), atol=1e-12
    )
    # no other branch is nearer, for random references; aligning again changes nothing
    ref = rng.normal(size=(50, 3)) * 6
    out = np.asarray(cons.align_turns(jnp.asarray(v), jnp.asarray(ref)))
    d_out = np.linalg.norm(out - ref, axis=1)
    for k in range(-3, 4):
        assert np.all(d_out <= np.linalg.norm((theta + 2 * np.pi * k) * w - ref, axis=1) + 1e-12)
    np.testing.assert_array_equal(np.asarray(cons.align_turns(jnp.asarray(out), jnp.asarray(ref))), out)
    # a zero rotation has no axis: it stays
    assert np.all(np.asarray(cons.align_turns(jnp.zeros((2, 3)), jnp.full((2, 3), 5.0))) == 0)


def test_turn_reference_brings_a_shape_off_by_a_turn_back():
    rng = np.random.default_rng(4)
    w = rng.normal(size=(30, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    theta = rng.uniform(2.8, 3.1, size=(6, 30, 1))  # near pi: where shapes' own solves may disagree
    v = theta * w
    off = v.copy()
    off[2, :10] = (theta[2, :10] - 2 * np.pi) * w[:10]  # shape 2: ten vertices one turn down
    feats = np.concatenate([off, np.ones((6, 30, 6))], axis=-1)
    ref = np.asarray(acap.turn_reference(jnp.asarray(feats)))
    np.testing.assert_allclose(ref, v.mean(0), atol=1e-12)
    aligned = np.asarray(acap.align_turns(jnp.asarray(feats), jnp.asarray(ref)))
    np.testing.assert_allclose(aligned[..., :3], v, atol=1e-12)
    np.testing.assert_array_equal(aligned[..., 3:], feats[..., 3:])


def test_scaler_range_and_inverse(acap_bar):
    verts, faces, _ = acap_bar
    feats = acap.encode(verts[0], faces, verts)
    sc = acap.Scaler.fit(feats)
    scaled = np.asarray(sc.transform(feats))
    assert scaled.min() >= -0.95 and scaled.max() <= 0.95
    assert scaled[..., :3].min() == pytest.approx(-0.95, abs=1e-5)
    np.testing.assert_allclose(np.asarray(sc.inverse(scaled)), np.asarray(feats), atol=1e-10)
    np.testing.assert_allclose(acap.Scaler.from_array(sc.to_array()).to_array(), sc.to_array())


def test_scaler_quantile_bounds_clip_outliers():
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(4, 500, 9))
    feats[0, 0, 4] = 40.0  # one outlier S entry
    full = acap.Scaler.fit(feats)
    robust = acap.Scaler.fit(feats, quantile=1e-3)
    assert full.s_max > 40 and robust.s_max < 4
    np.testing.assert_allclose(robust.s_max, np.quantile(feats[..., 3:], 1 - 1e-3) + 1e-6)
    scaled = np.asarray(robust.transform(feats))
    assert scaled.min() >= -0.95 - 1e-12 and scaled.max() <= 0.95 + 1e-12
    assert scaled[0, 0, 4] == pytest.approx(0.95, abs=1e-6)  # clipped to the bound
    inside = (feats[..., 3:] > robust.s_min) & (feats[..., 3:] < robust.s_max)
    back = np.asarray(robust.inverse(scaled))[..., 3:]
    np.testing.assert_allclose(back[inside], feats[..., 3:][inside], atol=1e-12)
    # stored with its quantile; four-entry arrays (older files) load as unclipped scalers
    assert acap.Scaler.from_array(robust.to_array()) == robust
    assert full.to_array().shape == (4,) and acap.Scaler.from_array(full.to_array()) == full
    with pytest.raises(ValueError, match="quantile"):
        acap.Scaler.fit(feats, quantile=0.5)


def test_round_trip_acap_bar(acap_bar):
    verts, faces, _ = acap_bar
    a = acap.prepare(verts[0], faces)
    out = np.asarray(a.decode(a.encode(verts)))
    diag = np.linalg.norm(np.ptp(verts[0], axis=0))
    err = np.linalg.norm((out - out.mean(1, keepdims=True)) - (verts - verts.mean(1, keepdims=True)), axis=-1) / diag
    assert err.mean() < 1e-3 and err.max() < 1e-2


@pytest.mark.slow
def test_round_trip_horse_gallop(horse):
    verts, faces = horse
    a = acap.prepare(verts[0], faces)
    out = np.asarray(a.decode(a.encode(verts, "spatial")))
    diag = np.linalg.norm(np.ptp(verts[0], axis=0))
    err = np.linalg.norm((out - out.mean(1, keepdims=True)) - (verts - verts.mean(1, keepdims=True)), axis=-1) / diag
    assert err.mean() <= 1e-3, err.mean()
    assert err.max() <= 1e-2, err.max()


@pytest.mark.slow
def test_aligned_turns_decode_to_the_same_horse(horse):
    verts, faces = horse
    a = acap.prepare(verts[0], faces)
    feats = a.encode(verts[::3])
    aligned = acap.align_turns(feats, acap.turn_reference(feats[::3]))
    assert np.abs(np.asarray(aligned) - np.asarray(feats)).max() > 6  # some leg vertices changed branch
    np.testing.assert_allclose(np.asarray(a.decode(aligned)), np.asarray(a.decode(feats)), atol=1e-9)


def test_decode_gradient_matches_finite_differences(acap_bar):
    verts, faces, _ = acap_bar
    a = acap.prepare(verts[0], faces)
    feats = a.encode(verts[1:2])
    w = jnp.asarray(np.random.default_rng(0).normal(size=(1, verts.shape[1], 3)))
    loss = lambda f: jnp.sum(w * a.decode(f)) + 0.1 * jnp.sum(a.decode(f) ** 2)  # noqa: E731
    g = jax.grad(loss)(feats)
    assert np.all(np.isfinite(np.asarray(g)))
    rng = np.random.default_rng(1)
    for _ in range(3):
        d = jnp.asarray(rng.normal(size=feats.shape))
        eps = 1e-5
        fd = (loss(feats + eps * d) - loss(feats - eps * d)) / (2 * eps)
        an = jnp.sum(g * d)
        assert abs(float(an - fd)) <= 1e-4 * abs(float(fd)), (float(an), float(fd))


def test_decode_gradient_finite_at_identity(acap_bar):
    verts, faces, _ = acap_bar
    a = acap.prepare(verts[0], faces)
    feats = jnp.broadcast_to(jnp.asarray(IDENTITY_FEATURE), (1, verts.shape[1], 9))
    g = jax.grad(lambda f: jnp.sum(a.decode(f) ** 2))(feats)
    assert np.all(np.isfinite(np.asarray(g)))
    np.testing.assert_allclose(np.asarray(a.decode(feats))[0], verts[0], atol=1e-8)


def test_anchors_hold_targets():
    v, f = thin_tube()
    bent, _ = bend(v, np.pi)
    a = acap.prepare(v, f)
    feats = a.encode(bent[None])
    anchors = [0, len(v) - 1]
    out = np.asarray(a.decode(feats, anchors=anchors, targets=bent[anchors]))
    np.testing.assert_allclose(out[0, anchors], bent[anchors], atol=1e-3)
    np.testing.assert_allclose(out[0], bent, atol=5e-3)


def test_jit_matches_no_jit_and_no_retracing(acap_bar):
    from jaxdeform.acap.features import (
        _decode_gradients,
        _defect_stage,
        _edge_stage,
        _features_cm,
        _gradients_stage,
        _output_stage,
        _polar_stage,
        _refit_stage,
        _solve_stage,
    )

    verts, faces, _ = acap_bar
    a = acap.prepare(verts[0], faces)
    vec_jit, s_jit = a.encode_parts(verts, "spatial")
    with jax.disable_jit():
        vec_eager, s_eager = a.encode_parts(verts, "spatial")
    np.testing.assert_allclose(np.asarray(vec_jit), np.asarray(vec_eager), atol=1e-10)
    np.testing.assert_allclose(np.asarray(s_jit), np.asarray(s_eager), atol=1e-10)
    feats = a.encode(verts)
    a.decode(feats)
    jitted = (
        _gradients_stage,
        _polar_stage,
        _output_stage,
        *cons.STAGES,
        _features_cm,
        _decode_gradients,
        _edge_stage,
        _solve_stage,
        _refit_stage,
        _defect_stage,
    )
    sizes = [f._cache_size() for f in jitted]
    a.encode(verts + 0.01)
    a.decode(feats * 1.001)
    assert [f._cache_size() for f in jitted] == sizes


def test_degenerate_faces_give_finite_features():
    v, f = thin_tube(n_around=6, n_along=10)
    v = v.copy()
    v[f[5, 2]] = 0.5 * (v[f[5, 0]] + v[f[5, 1]])  # collapse one face onto its edge
    feats = np.asarray(acap.encode(v, f, v[None] * 1.1))
    assert np.all(np.isfinite(feats))


def test_bad_inputs():
    v, f = thin_tube(n_around=6, n_along=10)
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(DegenerateMeshError, match="NaN"):
        acap.encode(v, f, bad[None])
    with pytest.raises(ConnectivityError):
        acap.encode(v, f, v[None, :-1])
    with pytest.raises(ValueError, match="consistency"):
        acap.encode(v, f, v[None], consistency="sideways")


def test_explicit_jacobian_transpose_equals_autodiff_transpose():
    """The solver's explicit J^T (segment sums) is the transpose JAX derives from the residuals."""
    from jaxdeform.acap.reconstruct import _residuals

    v, f = thin_tube(n_around=6, n_along=12)
    a = acap.prepare(v, f)
    rec = a.reconstructor(anchors=[0, 7, 40])
    rng = np.random.default_rng(2)
    b = 4
    e, n_anchor = rec.edge_i.shape[0], rec.anchors.shape[0]
    zero_args = (
        jnp.zeros((e, 3, b)),
        jnp.zeros((n_anchor, 3, b)),
        rec.sqrt_w,
        rec.edge_i,
        rec.edge_j,
        rec.anchors,
        rec.sqrt_a,
    )
    y = jnp.zeros((v.shape[0], 3, b))
    r = (jnp.asarray(rng.normal(size=(e, 3, b))), jnp.asarray(rng.normal(size=(n_anchor, 3, b))))
    (auto,) = jax.linear_transpose(lambda y: _residuals(y, zero_args), y)(r)
    np.testing.assert_allclose(np.asarray(rec.normal_rhs()(r)), np.asarray(auto), rtol=1e-12, atol=1e-12)


def test_default_solver_by_backend_and_size():
    from jaxdeform.acap.features import default_solver
    from jaxdeform.acap.reconstruct import DENSE_MAX_VERTICES

    assert default_solver(10**6, "cpu") == "host"
    assert default_solver(DENSE_MAX_VERTICES, "gpu") == "dense"
    assert default_solver(DENSE_MAX_VERTICES + 1, "gpu") == "cg"
    assert default_solver(100, "tpu") == "dense"
