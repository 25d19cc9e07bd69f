"""DFD weights, anchors, locality, blending (eqs. 1, 10), symmetry (eq. 9): identities and direct NumPy references."""

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import grid_mesh
from jax.test_util import check_grads

from jaxdeform.handles import weights as hw
from jaxdeform.mesh.geodesic import HeatGeodesics


def unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def smooth_features(points, c=16, seed=0, scale=1.5):
    """A smooth unit feature field of the positions: nearby points get close features, far ones unrelated."""
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(c, 3)) * scale, rng.normal(size=c)
    return unit(np.tanh(np.asarray(points) @ a.T + b))


def numpy_dfd(Z, h):
    return np.maximum(1.0 - np.linalg.norm(Z[:, None, :] - Z[None, h, :], axis=2), 0.0)


def apply_np(D, v):
    return v @ D[:, :3].T + D[:, 3]


def random_affine(rng, n, scale=0.3):
    return np.eye(3, 4)[None] + scale * rng.normal(size=(n, 3, 4))


def rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(0)
    v = rng.uniform(-1.0, 1.0, size=(300, 3))
    return v, smooth_features(v)


# ------------------------------------------------------------------------------------------------ weights


@pytest.mark.parametrize("dtype,atol", [(np.float64, 1e-7), (np.float32, 2e-3)])
def test_dfd_weights_match_direct_numpy(cloud, dtype, atol):
    v, Z = cloud
    h = np.array([5, 17, 17, 250, 3])  # a repeated handle too; K = 5 runs padded to 8
    W = np.asarray(hw.dfd_weights(Z.astype(dtype), h))
    assert W.shape == (len(v), len(h)) and W.dtype == dtype
    assert W.min() >= 0.0 and W.max() <= 1.0
    assert np.all(W[h, np.arange(len(h))] == 1.0)
    ref = numpy_dfd(Z, h)
    # float32: the 2 - 2 a.b form loses ~sqrt(eps) near zero distance
    np.testing.assert_allclose(W, ref, atol=atol, rtol=0)
    assert 0.05 < np.mean(ref > 0) < 0.95  # the field gives a mix of related and unrelated vertices


def test_dfd_weights_do_not_retrace_within_a_bucket(cloud):
    _, Z = cloud
    Zj = jnp.asarray(Z.astype(np.float32))
    hw.dfd_weights(Zj, [1, 2, 3])
    size = hw._dfd_padded._cache_size()
    for h in ([4, 5, 6], [7, 8, 9, 10], [0, 1, 2]):  # K = 3 and 4 share the bucket 4
        hw.dfd_weights(Zj, h)
    assert hw._dfd_padded._cache_size() == size
    assert [hw.bucket(k) for k in (0, 1, 2, 3, 5, 100)] == [0, 1, 2, 4, 8, 128]


def test_anchors_zero_their_rows_and_never_increase(cloud):
    _, Z = cloud
    h, a = [5, 17, 250], [40, 41, 120]
    W = hw.dfd_weights(Z, h)
    Wa = np.asarray(hw.anchor_weights(W, Z, a))
    W = np.asarray(W)
    assert np.all(Wa[a] == 0.0)
    assert np.all(Wa <= W) and Wa.min() >= 0.0
    ref = np.maximum(W - numpy_dfd(Z, a).max(axis=1, keepdims=True), 0.0)
    np.testing.assert_allclose(Wa, ref, atol=1e-7, rtol=0)
    assert np.array_equal(np.asarray(hw.anchor_weights(W, Z, [])), W)


def test_locality_lambda_zero_noop_and_monotone_suppression():
    v, f = grid_mesh(15)
    Z = smooth_features(v, scale=0.6)  # broad weights, so that locality has something to cut
    h = [0, 112, 224]
    G = hw.handle_geodesics(HeatGeodesics(v, f), h)
    assert G.shape == (len(v), 3) and G.min() >= 0.0
    np.testing.assert_array_equal(G.max(axis=0), 1.0)
    assert np.all(G[h, np.arange(3)] == 0.0)
    W = np.asarray(hw.dfd_weights(Z, h))
    assert np.array_equal(np.asarray(hw.locality_weights(W, G, 0.0)), W)
    prev = W
    for lam in (0.5, 1.0, 2.0, 4.0):
        Wl = np.asarray(hw.locality_weights(W, G, lam))
        np.testing.assert_allclose(Wl, W * (1.0 - G) ** lam, atol=1e-12, rtol=0)
        assert np.all(Wl[h, np.arange(3)] == 1.0)
        assert np.all(Wl <= prev + 1e-12)
        prev = Wl
    far = G > 0.6
    assert W[far].max() > 0.2 and prev[far].max() < 0.4**4 + 1e-12


def test_locality_rescales_the_handle_weight_to_one():
    v, f = grid_mesh(9)
    Z = smooth_features(v, scale=0.6)
    h = [0, 40]
    G = 0.1 + 0.9 * hw.handle_geodesics(HeatGeodesics(v, f), h)  # distances that do not vanish at the handle
    W = np.asarray(hw.dfd_weights(Z, h))
    Wl = np.asarray(hw.locality_weights(W, G, 3.0))
    np.testing.assert_allclose(Wl[h, [0, 1]], 1.0, atol=1e-12)
    np.testing.assert_allclose(Wl, W * (1.0 - G) ** 3 / 0.9**3, atol=1e-12)


# ------------------------------------------------------------------------------------------------ blending


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("pou", [False, True])
def test_zero_motion_returns_input_exactly(cloud, dtype, pou):
    v, Z = cloud
    rng = np.random.default_rng(1)
    W = rng.uniform(0.0, 0.8, size=(len(v), 4)).astype(dtype)  # row sums both below and above 1
    T = np.tile(np.eye(3, 4), (4, 1, 1))
    vd = v.astype(dtype)
    out = np.asarray(hw.blend(vd, W, T, pou=pou))
    assert out.dtype == dtype and np.array_equal(out, vd)
    plane = hw.Plane(np.array([0.0, 0.6, 0.8]), 0.1)
    out = np.asarray(hw.symmetric_blend(vd, W, T, v[:4], plane, pou=pou))
    assert np.array_equal(out, vd)


def test_blend_matches_equation_1(cloud):
    v, Z = cloud
    rng = np.random.default_rng(2)
    h = [5, 17, 250]
    W = np.asarray(hw.dfd_weights(Z, h))
    T = random_affine(rng, 3)
    ref = v + sum(W[:, [k]] * (apply_np(T[k], v) - v) for k in range(3))
    np.testing.assert_allclose(np.asarray(hw.blend(v, W, T)), ref, atol=1e-12)
    # translation-only edits: the identity linear part, nothing else to do
    t = rng.normal(size=(3, 3))
    Tt = np.concatenate([np.tile(np.eye(3), (3, 1, 1)), t[:, :, None]], axis=2)
    np.testing.assert_allclose(np.asarray(hw.blend(v, W, Tt)), v + W @ t, atol=1e-12)


@pytest.mark.parametrize("dtype,tol", [(np.float32, 1e-5), (np.float64, 1e-12)])
def test_pou_common_rigid_motion_is_rigid(cloud, dtype, tol):
    v, Z = cloud
    rng = np.random.default_rng(3)
    W = rng.uniform(0.0, 0.9, size=(len(v), 5))
    D = np.concatenate([rotation(rng), rng.normal(size=(3, 1))], axis=1)
    out = np.asarray(hw.blend(v.astype(dtype), W.astype(dtype), np.tile(D, (5, 1, 1)), pou=True, d0=D))
    np.testing.assert_allclose(out, apply_np(D, v), atol=tol, rtol=0)


def test_pou_weights_sum_to_one(cloud):
    v, Z = cloud
    rng = np.random.default_rng(4)
    K = 4
    W = rng.uniform(0.0, 0.6, size=(len(v), K))  # row sums from ~0.3 to ~2.2
    s = W.sum(1, keepdims=True)
    w0 = np.maximum(1 - s, 0)
    expect = np.concatenate([w0, W], axis=1) / (w0 + s)
    eye = np.tile(np.eye(3, 4), (K, 1, 1))
    shift = np.array([1.0, 0.0, 0.0])
    got = []
    for j in range(K + 1):  # translate one control (D0 first) by e_x: the x displacement is its weight
        T, d0 = eye.copy(), np.eye(3, 4)
        (d0 if j == 0 else T[j - 1])[:, 3] = shift
        got.append((np.asarray(hw.blend(v, W, T, pou=True, d0=d0)) - v)[:, 0])
    got = np.stack(got, axis=1)
    np.testing.assert_allclose(got, expect, atol=1e-12)
    np.testing.assert_allclose(got.sum(1), 1.0, atol=1e-12)
    assert got.min() >= 0.0 and (s > 1).any() and (s < 1).any()


def test_pou_with_weight_sum_above_one_is_affine_combination(cloud):
    v, Z = cloud
    rng = np.random.default_rng(5)
    W = rng.uniform(0.5, 1.0, size=(len(v), 4))  # every row sums to > 1, so w0 = 0
    T = random_affine(rng, 4)
    what = W / W.sum(1, keepdims=True)
    ref = sum(what[:, [k]] * apply_np(T[k], v) for k in range(4))
    np.testing.assert_allclose(np.asarray(hw.blend(v, W, T, pou=True)), ref, atol=1e-12)


@pytest.mark.parametrize("pou", [False, True])
def test_blend_gradients_match_finite_differences(cloud, pou):
    v, Z = cloud
    rng = np.random.default_rng(6)
    W = np.asarray(hw.dfd_weights(Z, [5, 17, 250]))
    T = random_affine(rng, 3)
    plane = hw.Plane(np.array([1.0, 0.0, 0.0]), 0.05)

    def loss(T):
        return jnp.sum(jnp.sin(hw.blend(v, W, T, pou=pou))) + jnp.sum(
            jnp.cos(hw.symmetric_blend(v, W, T, v[[5, 17, 250]], plane, pou=pou))
        )

    check_grads(loss, (jnp.asarray(T),), order=1, modes=("rev",), atol=1e-6, rtol=1e-6)


def test_blend_does_not_retrace_with_same_k(cloud):
    v, Z = cloud
    rng = np.random.default_rng(7)
    vf = v.astype(np.float32)
    hw.blend(vf, rng.uniform(size=(len(v), 3)).astype(np.float32), random_affine(rng, 3))
    size = hw._blend_core._cache_size()
    for _ in range(3):
        hw.blend(vf, rng.uniform(size=(len(v), 3)).astype(np.float32), random_affine(rng, 3))
    assert hw._blend_core._cache_size() == size


def test_make_transform_rotates_about_centre():
    c = np.array([1.0, 2.0, 3.0])
    D = hw.make_transform(c, translate=(0.5, 0.0, 0.0), axis=(0, 0, 2), degrees=90)
    np.testing.assert_allclose(apply_np(D, c[None])[0], c + [0.5, 0, 0], atol=1e-12)
    np.testing.assert_allclose(apply_np(D, (c + [1, 0, 0])[None])[0], c + [0.5, 1, 0], atol=1e-12)
    T = hw.make_transform(c, translate=(1, 2, 3), axis=(1, 0, 0), degrees=0.0)
    assert np.array_equal(T, np.concatenate([np.eye(3), [[1], [2], [3]]], axis=1))


# ------------------------------------------------------------------------------------------------ symmetry

_A = np.random.default_rng(11).normal(size=(32, 3)) * 2.0
_B = np.random.default_rng(12).normal(size=32)


def mirrored_feature(q):
    return unit(np.tanh(q @ _A.T + _B))


def x_symmetric_shape(rotate=None):
    """A blob mirror-symmetric in x (vertex pairs i, i + n), with the field f(|x|, y, z); optionally rotated."""
    rng = np.random.default_rng(13)
    half = rng.uniform([0.0, -1.0, -0.5], [1.2, 1.0, 0.5], size=(400, 3))
    half[:, 1] += 0.3 * half[:, 0] ** 2
    pts = np.r_[half, half * [-1.0, 1.0, 1.0]]
    R = np.eye(3) if rotate is None else rotate

    def field(p):
        q = np.asarray(p) @ R  # back to the unrotated frame
        return mirrored_feature(np.c_[np.abs(q[:, 0]), q[:, 1], q[:, 2]])

    return pts @ R.T, field


def twisted_bar(twist_deg):
    u, w, z = (
        a.ravel()
        for a in np.meshgrid(
            np.linspace(-0.5, 0.5, 9), np.linspace(-0.15, 0.15, 5), np.linspace(-2, 2, 41), indexing="ij"
        )
    )
    k = np.deg2rad(twist_deg) / 4.0
    pts = np.c_[np.cos(k * z) * u - np.sin(k * z) * w, np.sin(k * z) * u + np.cos(k * z) * w, z]

    def field(p):  # features of the untwisted cross-section coordinates (|u|, |w|) and z
        th = k * p[:, 2]
        uu = np.cos(th) * p[:, 0] + np.sin(th) * p[:, 1]
        ww = -np.sin(th) * p[:, 0] + np.cos(th) * p[:, 1]
        return mirrored_feature(np.c_[2 * np.abs(uu), 2 * np.abs(ww), p[:, 2]])

    return pts, field


def test_detects_exact_mirror_symmetry_only_along_x():
    pts, field = x_symmetric_shape()
    planes = hw.detect_symmetry(field, pts)
    assert [p.score for p in planes] == sorted(p.score for p in planes)
    sym = [p for p in planes if p.symmetric]
    assert len(sym) == 1 and abs(sym[0].normal[0]) == pytest.approx(1.0) and sym[0].score < 1e-9
    assert sym[0].offset == pytest.approx(0.0, abs=1e-12)
    assert {p.source for p in planes} >= {"x", "y", "z"}
    assert all(p.score > 0.3 for p in planes if p.source in ("y", "z"))


def test_principal_axes_find_a_rotated_mirror_plane():
    R = hw.make_transform(np.zeros(3), axis=(0.3, 0.2, 1.0), degrees=35)[:, :3]
    pts, field = x_symmetric_shape(R)
    assert not any(p.symmetric for p in hw.detect_symmetry(field, pts, pca=False))
    sym = [p for p in hw.detect_symmetry(field, pts) if p.symmetric]
    assert len(sym) == 1 and sym[0].source.startswith("pca")
    assert abs(sym[0].normal @ R[:, 0]) == pytest.approx(1.0, abs=1e-9)


def test_twisted_bar_has_no_symmetry_plane():
    pts, field = twisted_bar(0.0)  # untwisted: the same field is mirror-symmetric in x and y
    assert {p.source for p in hw.detect_symmetry(field, pts) if p.symmetric} == {"x", "y"}
    pts, field = twisted_bar(120.0)
    planes = hw.detect_symmetry(field, pts)
    assert not any(p.symmetric for p in planes) and min(p.score for p in planes) > 0.2


def test_reflections_are_involutions():
    rng = np.random.default_rng(14)
    plane = hw.Plane(unit(rng.normal(size=3)), 0.7)
    p = rng.normal(size=(10, 3))
    np.testing.assert_allclose(hw.reflect_points(plane, hw.reflect_points(plane, p)), p, atol=1e-12)
    D = random_affine(rng, 1)[0]
    SDS = hw.reflect_transform(plane, D)
    np.testing.assert_allclose(hw.reflect_transform(plane, SDS), D, atol=1e-12)
    # S D S maps mirror images to mirror images
    np.testing.assert_allclose(
        apply_np(SDS, hw.reflect_points(plane, p)), hw.reflect_points(plane, apply_np(D, p)), atol=1e-12
    )


def test_symmetric_blend_matches_equation_9(cloud):
    v, Z = cloud
    rng = np.random.default_rng(15)
    h = [5, 17, 250, 3]
    W = np.asarray(hw.dfd_weights(Z, h))
    T = random_affine(rng, 4)
    plane = hw.Plane(unit(np.array([1.0, 0.5, 0.0])), 0.1)
    side = lambda p: p @ plane.normal - plane.offset >= 0  # noqa: E731
    ref = v.copy()
    for k in range(4):
        Dr = hw.reflect_transform(plane, T[k])
        same = side(v) == side(v[h[k]])
        moved = np.where(same[:, None], apply_np(T[k], v), apply_np(Dr, v))
        ref += W[:, [k]] * (moved - v)
    assert 0 < side(v[h]).sum() < 4  # handles on both sides
    np.testing.assert_allclose(np.asarray(hw.symmetric_blend(v, W, T, v[h], plane)), ref, atol=1e-12)


def test_symmetric_blend_gives_mirrored_deformations():
    pts, field = x_symmetric_shape()
    n = len(pts) // 2  # vertex i + n is the mirror image of vertex i
    Z = field(pts)
    plane = next(p for p in hw.detect_symmetry(field, pts) if p.symmetric)
    rng = np.random.default_rng(16)
    D = random_affine(rng, 1)[0]
    h = int(np.argmax(pts[:n, 0]))  # a handle on the positive side
    mirrored = lambda out: np.abs(out[n:] - hw.reflect_points(plane, out[:n])).max()  # noqa: E731

    # one handle moved: symmetric blending mirrors the edit, plain blending does not
    W1 = np.asarray(hw.dfd_weights(Z, [h]))
    assert mirrored(np.asarray(hw.symmetric_blend(pts, W1, D[None], pts[[h]], plane))) < 1e-12
    assert mirrored(np.asarray(hw.blend(pts, W1, D[None]))) > 1e-2
    # a mirrored handle pair with mirrored transforms
    W2 = np.asarray(hw.dfd_weights(Z, [h, h + n]))
    T2 = np.stack([D, hw.reflect_transform(plane, D)])
    for pou in (False, True):
        assert mirrored(np.asarray(hw.symmetric_blend(pts, W2, T2, pts[[h, h + n]], plane, pou=pou))) < 1e-12


# ------------------------------------------------------------------------------------------------ Deformer


def test_deformer_composes_the_public_functions():
    v, f = grid_mesh(12)
    v = v + [0.0, 0.0, 0.1] * np.sin(3 * v[:, :1])
    Z = smooth_features(v, scale=0.8)
    dfm = hw.Deformer(v, f, 3.0 * Z, dtype=np.float64)  # features are normalised by the Deformer
    h, a = [3, 70, 140], [100]
    G = hw.handle_geodesics(HeatGeodesics(v, f), h)
    ref = hw.anchor_weights(hw.locality_weights(hw.dfd_weights(Z, h), G, 2.0), Z, a)
    W = dfm.weights(h, anchors=a, locality=2.0)
    np.testing.assert_allclose(W, np.asarray(ref), atol=1e-12)
    rng = np.random.default_rng(17)
    for h in ([3, 70, 140], [3, 70, 140, 20]):  # K = 3 leaves a padding column for pou's w0, K = 4 does not
        W = dfm.weights(h, anchors=a, locality=2.0)
        T = random_affine(rng, len(h))
        for pou in (False, True):
            np.testing.assert_allclose(
                dfm.deform(h, T, anchors=a, locality=2.0, pou=pou), np.asarray(hw.blend(v, W, T, pou=pou)), atol=1e-12
            )
    with pytest.raises(hw.NoSymmetryError):
        dfm.deform(h, T, symmetric=True)
    assert dfm.symmetry_plane() is None


def test_deformer_float32_identity_and_no_retrace():
    pts, field = x_symmetric_shape()
    faces = np.zeros((1, 3), dtype=np.int64)  # unused: no locality asked for
    dfm = hw.Deformer(pts, faces, field_fn=field)
    assert dfm.symmetry_plane() is not None and abs(dfm.symmetry_plane().normal[0]) == pytest.approx(1.0)
    eye = np.tile(np.eye(3, 4), (3, 1, 1))
    out = dfm.deform([1, 2, 3], eye, symmetric=True)
    assert out.dtype == np.float32 and np.array_equal(out, pts.astype(np.float32))
    rng = np.random.default_rng(18)
    h, T = [1, 2, 500], random_affine(rng, 3)
    W = dfm.weights(h)
    plane = dfm.symmetry_plane()
    for pou in (False, True):
        ref = np.asarray(hw.symmetric_blend(pts, W.astype(np.float64), T, pts[h], plane, pou=pou))
        np.testing.assert_allclose(dfm.deform(h, T, symmetric=True, pou=pou), ref, atol=1e-5)
    dfm.deform([1, 2, 3], eye)
    sizes = hw._blend_core._cache_size(), hw._dfd_padded._cache_size()
    for h in ([4, 5, 6], [7, 8, 9, 10], [11, 12, 13]):  # K = 3, 4: one bucket
        out = dfm.deform(h, random_affine(rng, len(h)))
        assert np.all(np.isfinite(out))
    assert (hw._blend_core._cache_size(), hw._dfd_padded._cache_size()) == sizes
