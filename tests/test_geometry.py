import igl
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxdeform.errors import ConnectivityError
from jaxdeform.mesh import build_topology, cot_laplacian, cotangent_weights, face_areas, vertex_normals
from jaxdeform.mesh.geometry import corner_cotangents, zero_area_faces


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_topology_sizes_and_rings(sphere):
    v, f = sphere
    t = build_topology(f, len(v))
    assert t.n_edges == len(f) * 3 // 2  # closed manifold
    assert int(t.degree.sum()) == 2 * t.n_edges
    assert not bool(t.boundary_vertex.any())
    # each neighbor list holds exactly the vertices sharing an edge
    e = set(map(tuple, np.asarray(t.edges).tolist()))
    nb, mask = np.asarray(t.neighbors), np.asarray(t.mask)
    for i in (0, 17, 100):
        ring = set(nb[i][mask[i]].tolist())
        assert ring == {j for (a, j) in e if a == i} | {a for (a, j) in e if j == i}


def test_open_mesh_boundary_flags():
    f = np.array([[0, 1, 2], [1, 3, 2]])
    t = build_topology(f)
    assert bool(t.boundary_vertex.all())
    assert t.n_edges == 5


@pytest.mark.parametrize(
    "faces, match",
    [
        (np.array([[0, 1, 1]]), "repeats"),
        (np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]]), "non-manifold"),
        (np.array([[0, 1, 3]]), "belongs to no face"),
    ],
)
def test_bad_topology(faces, match):
    with pytest.raises(ConnectivityError, match=match):
        build_topology(faces, 5 if match != "belongs to no face" else 4)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_cot_laplacian_matches_libigl(sphere, dtype):
    v, f = sphere
    t = build_topology(f, len(v))
    lap = cot_laplacian(jnp.asarray(v.astype(dtype)), t).toarray()
    ref = -igl.cotmatrix(v, f.astype(np.int64)).toarray()
    tol = 1e-5 if dtype == np.float32 else 1e-10
    np.testing.assert_allclose(lap, ref, atol=tol)
    np.testing.assert_allclose(lap @ np.ones(len(v)), 0, atol=tol)  # L 1 = 0


def test_areas_and_normals(sphere):
    v, f = sphere
    t = build_topology(f, len(v))
    areas = np.asarray(face_areas(jnp.asarray(v), t))
    np.testing.assert_allclose(areas, igl.doublearea(v, f.astype(np.int64)).ravel() / 2, rtol=1e-10)
    n = np.asarray(vertex_normals(jnp.asarray(v), t))
    # on a sphere centred at the origin normals point along the position
    assert np.min(np.sum(n * v / np.linalg.norm(v, axis=1, keepdims=True), axis=1)) > 0.99


def test_degenerate_face_gives_finite_cotangents():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [1, 1, 0]], float)  # face 0 is collinear
    f = np.array([[0, 1, 2], [0, 2, 3]])
    t = build_topology(f, 4)
    cot = np.asarray(corner_cotangents(jnp.asarray(v), t))
    assert np.all(np.isfinite(cot)) and np.all(cot[0] == 0)
    w = np.asarray(cotangent_weights(jnp.asarray(v), t))
    assert np.all(np.isfinite(w))
    g = jax.grad(lambda x: jnp.sum(cotangent_weights(x, t)))(jnp.asarray(v))
    assert np.all(np.isfinite(np.asarray(g)))


def test_zero_area_faces_are_the_faces_without_cotangents():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [1, 1, 0]], np.float64)
    f = np.array([[0, 1, 2], [0, 3, 1], [1, 4, 2]])  # face 1: three collinear corners
    np.testing.assert_array_equal(zero_area_faces(v, f), [1])
    cot = np.asarray(corner_cotangents(jnp.asarray(v), build_topology(f, 5)))
    np.testing.assert_array_equal(np.flatnonzero(np.all(cot == 0, axis=1)), [1])
