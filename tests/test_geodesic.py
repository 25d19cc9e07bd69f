"""Geodesic distances: exact and heat method against known distances on a plane and a sphere."""

import numpy as np
import pytest
import trimesh

from jaxdeform.errors import MeshFormatError
from jaxdeform.mesh.geodesic import HeatGeodesics, geodesic_distances


def grid(n=21):
    x, y = np.meshgrid(np.linspace(0.0, 1.0, n), np.linspace(0.0, 1.0, n), indexing="ij")
    v = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    return v, f, idx


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.mark.parametrize("corner", [(0, 0), (-1, 0), (-1, -1)])
def test_flat_grid_exact_is_euclidean(corner):
    v, f, idx = grid()
    s = int(idx[corner])
    d = geodesic_distances(v, f, s, method="exact", normalize=False)
    e = np.linalg.norm(v - v[s], axis=1)
    assert d.shape == (1, len(v)) and d.dtype == np.float64
    np.testing.assert_allclose(d[0], e, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("corner", [(0, 0), (-1, 0)])
def test_flat_grid_heat_is_close(corner):
    v, f, idx = grid()
    s = int(idx[corner])
    d = geodesic_distances(v, f, s, method="heat", normalize=False)[0]
    e = np.linalg.norm(v - v[s], axis=1)
    assert d.min() >= 0.0 and d[s] == 0.0
    assert np.abs(d - e).max() < 0.05 * e.max()
    # The heat method smooths across the boundary; against the diagonals of the triangulation the error
    # reaches ~6 % of the local distance on this 21 x 21 grid.
    far = e > 0.3
    assert np.max(np.abs(d - e)[far] / e[far]) < 0.08


@pytest.mark.parametrize("method,tol", [("exact", 0.02), ("heat", 0.05)])
def test_sphere_antipodal_is_half_circumference(sphere, method, tol):
    v, f = sphere
    a = 0
    b = int(np.argmin(v @ v[a]))
    d = geodesic_distances(v, f, [a, b], method=method, normalize=False)
    assert d.shape == (2, len(v))
    assert d[0, b] == pytest.approx(np.pi * 2.0, rel=tol)
    assert d[1, a] == pytest.approx(np.pi * 2.0, rel=tol)
    assert d[0, a] == 0.0 and d[1, b] == 0.0


def test_exact_symmetry(sphere):
    v, f = sphere
    src = [0, 17, 100, 333]
    d = geodesic_distances(v, f, src, method="exact", normalize=False)
    sub = d[:, src]
    np.testing.assert_allclose(sub, sub.T, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(np.diag(sub), 0.0)


@pytest.mark.parametrize("method", ["auto", "exact", "heat"])
def test_normalized_in_unit_interval(sphere, method):
    v, f = sphere
    d = geodesic_distances(v, f, [0, 5, 9], method=method)
    assert d.min() >= 0.0 and d.max() == pytest.approx(1.0, abs=1e-15)
    raw = geodesic_distances(v, f, [0, 5, 9], method=method, normalize=False)
    np.testing.assert_allclose(d, raw / raw.max())


def test_heat_object_reuses_factorization(sphere):
    v, f = sphere
    heat = HeatGeodesics(v, f)
    a = heat([3, 4])
    b = heat(3)
    np.testing.assert_allclose(a[0], b[0])
    np.testing.assert_allclose(a, geodesic_distances(v, f, [3, 4], method="heat", normalize=False))


def test_disconnected_components_are_infinite():
    m1 = trimesh.creation.icosphere(subdivisions=1)
    m2 = m1.copy()
    m2.apply_translation([3.0, 0.0, 0.0])
    both = trimesh.util.concatenate([m1, m2])
    v, f = np.asarray(both.vertices), np.asarray(both.faces)
    n1 = len(m1.vertices)
    for method in ("exact", "heat"):
        d = geodesic_distances(v, f, [0, n1], method=method)
        assert np.all(np.isinf(d[0, n1:])) and np.all(np.isinf(d[1, :n1]))
        assert np.all(np.isfinite(d[0, :n1])) and np.nanmax(d[np.isfinite(d)]) == 1.0
    # a vertex that belongs to no face (libigl's heat method would crash on it)
    v2 = np.r_[np.asarray(m1.vertices), [[9.0, 9.0, 9.0]]]
    d = geodesic_distances(v2, np.asarray(m1.faces), 0, method="heat", normalize=False)
    assert np.isinf(d[0, -1]) and np.all(np.isfinite(d[0, :-1]))


def test_bad_input():
    v, f, _ = grid(5)
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(MeshFormatError):
        geodesic_distances(bad, f, 0)
    with pytest.raises(ValueError):
        geodesic_distances(v, f, len(v))
    with pytest.raises(ValueError):
        geodesic_distances(v, f, 0, method="dijkstra")
