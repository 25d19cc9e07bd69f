"""Error measures: analytic cases and invariances."""

import numpy as np
import pytest

from jaxdeform import metrics


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _sequence(n=4, seed=0):
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6), indexing="ij")
    base = np.stack([u.ravel(), v.ravel(), 0.2 * np.sin(3 * u.ravel())], 1)
    idx = np.arange(36).reshape(6, 6)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    frames = np.stack([base + 0.05 * rng.normal(size=base.shape) for _ in range(n)])
    return frames, faces


def test_erms_is_zero_for_rigid_copies_and_known_for_an_offset():
    ref, _ = _sequence()
    moved = np.stack([f @ _rot([1, 2, 3], 0.7 * k).T + k for k, f in enumerate(ref)])
    assert metrics.erms(ref, moved) == pytest.approx(0.0, abs=1e-9)
    assert metrics.erms(ref, moved, rotate=False) > 1.0  # without alignment the rotation counts
    # unnormalized: every coordinate off by 1 -> 1000 * sqrt(3 N V) / sqrt(3 N V)
    assert metrics.erms(np.zeros((2, 5, 3)), np.ones((2, 5, 3)), normalize=False) == pytest.approx(1000.0)


def test_erms_per_shape_splits_the_sequence_erms():
    rng = np.random.default_rng(3)
    ref = rng.normal(size=(4, 30, 3))
    rec = ref + rng.normal(scale=[[[0.0]], [[0.01]], [[0.02]], [[0.05]]], size=(4, 30, 3))
    per = metrics.erms_per_shape(ref, rec)
    assert per.shape == (4,) and per[0] == pytest.approx(0.0, abs=1e-9)
    assert np.all(np.diff(per) > 0)  # more noise, more error
    assert np.sqrt(np.mean(per**2)) == pytest.approx(metrics.erms(ref, rec), rel=1e-12)
    # a shape alone: the same as the sequence measure of that one shape without normalization
    assert metrics.erms_per_shape(ref, rec, normalize=False)[2] == pytest.approx(
        metrics.erms(ref[2:3], rec[2:3], normalize=False), rel=1e-12
    )


def test_erms_scales_into_the_unit_ball():
    ref, _ = _sequence()
    noisy = ref + 0.01 * np.random.default_rng(1).normal(size=ref.shape)
    a = metrics.erms(ref, noisy)
    b = metrics.erms(10 * ref, 10 * noisy)  # the same data in other units
    assert a == pytest.approx(b, rel=1e-12)


def _sphere_points(radius, n=40, seed=0):
    """n points on a sphere of the given radius about a random centre (their centroid is not the centre)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return radius * d / np.linalg.norm(d, axis=1, keepdims=True) + rng.normal(size=3)


def test_erms_normalizations_divide_by_their_analytic_factors():
    # a zero-mean displacement of length e on every vertex: raw Erms = 1000 e / sqrt(3) (no rotation fit)
    first = _sphere_points(2.0)
    ref = np.stack([first, 1.5 * _sphere_points(2.0, seed=1)])  # the second shape reaches further out
    e = 0.01
    d = np.zeros_like(ref)
    d[:, 0::2, 0], d[:, 1::2, 0] = e, -e
    rec = ref + d
    raw = metrics.erms(ref, rec, rotate=False, scale="raw")
    assert raw == pytest.approx(1000 * e / np.sqrt(3), rel=1e-12)
    centred = ref - ref.mean(axis=1, keepdims=True)
    reach = np.linalg.norm(centred, axis=-1).max()  # "radius": the whole reference inside the unit ball
    assert metrics.erms(ref, rec, rotate=False) == pytest.approx(raw / reach, rel=1e-12)
    r0 = np.linalg.norm(first - first.mean(axis=0), axis=-1).max()  # "diameter-first-shape": 2 r0 of shape 0
    assert metrics.erms(ref, rec, rotate=False, scale="diameter-first-shape") == pytest.approx(
        raw / (2 * r0), rel=1e-12
    )
    other = _sphere_points(5.0, seed=2)  # a given first shape (the data set's, not the evaluated set's)
    r1 = np.linalg.norm(other - other.mean(axis=0), axis=-1).max()
    per = metrics.erms_per_shape(ref, rec, rotate=False, scale="diameter-first-shape", first=other)
    assert np.sqrt(np.mean(per**2)) == pytest.approx(raw / (2 * r1), rel=1e-12)
    with pytest.raises(ValueError, match="unknown Erms normalization"):
        metrics.erms(ref, rec, scale="unit")
    with pytest.raises(ValueError, match="does not match"):
        metrics.erms(ref, rec, scale="diameter-first-shape", first=other[:10])


def test_relative_squared_error_of_a_scaled_copy():
    x = np.random.default_rng(2).normal(size=(3, 10, 9))
    np.testing.assert_allclose(metrics.relative_squared_error(x, 0.9 * x), 0.01, rtol=1e-12)
    with pytest.raises(ValueError):
        metrics.relative_squared_error(np.zeros((1, 2, 9)), np.zeros((1, 2, 9)))


def test_sted_vanishes_for_uniform_scaling_and_rigid_motion():
    ref, faces = _sequence()
    scaled = np.stack([1.3 * f @ _rot([0, 1, 1], 0.4).T for f in ref])
    assert metrics.sted(ref, scaled, faces, temporal=False)["sted_s"] == pytest.approx(0.0, abs=1e-12)
    assert metrics.sted(ref, ref, faces)["sted"] == pytest.approx(0.0, abs=1e-15)


def test_sted_spatial_on_one_stretched_triangle():
    ref = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    rec = np.array([[[0.0, 0, 0], [2, 0, 0], [0, 1, 0]]])  # x stretched by 2
    faces = np.array([[0, 1, 2]])
    l0 = np.array([1.0, np.sqrt(2), 1.0])  # edges (0,1), (1,2), (0,2)
    ed = np.array([1.0, (np.sqrt(5) - np.sqrt(2)) / np.sqrt(2), 0.0])
    incident = [(0, 2), (0, 1), (1, 2)]  # edges of vertices 0, 1, 2

    def wstd(ids):
        w, x = l0[list(ids)], ed[list(ids)]
        m = np.sum(w * x) / w.sum()
        return np.sqrt(np.sum(w * (x - m) ** 2) / w.sum())

    expected = np.mean([wstd(ids) for ids in incident])
    got = metrics.sted(ref, rec, faces, temporal=False)
    assert got["sted_s"] == pytest.approx(expected, rel=1e-12)
    # two rings cover the whole triangle at every vertex
    assert metrics.sted(ref, rec, faces, rings=2, temporal=False)["sted_s"] == pytest.approx(wstd((0, 1, 2)), rel=1e-12)


def test_sted_temporal_part():
    ref, faces = _sequence(n=5)
    out = metrics.sted(ref, ref + 0.3, faces)  # a constant shift keeps every temporal edge
    assert out["sted_t"] == pytest.approx(0.0, abs=1e-12)
    jitter = ref.copy()
    jitter[2] += 0.01
    assert metrics.sted(ref, jitter, faces)["sted_t"] > 0


def test_hausdorff():
    a = np.zeros((1, 3))
    b = np.array([[0.0, 0, 0], [3, 4, 0]])
    assert metrics.hausdorff(a, b) == pytest.approx(5.0)
