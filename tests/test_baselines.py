"""Linear baselines of seed 000 (PCA and SPLOCS): exactness of PCA, locality and convergence of SPLOCS on a
synthetic grid with two bumps, the JAX model interface (jit, grad, save/load) and input errors."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdeform.components import baselines as B
from jaxdeform.errors import ConnectivityError, JaxDeformError, MeshFormatError
from jaxdeform.nn.archive import save_tree

BUMP_CENTRES = np.array([[0.25, 0.25], [0.75, 0.75]])


def _random(n=6, v=10, c=3, seed=0):
    return np.random.default_rng(seed).normal(size=(n, v, c))


def _grid_bumps(n=12, shapes=20, seed=0):
    """n x n grid in [0, 1]^2, two Gaussian bumps (sigma 0.08) moving along fixed directions with random
    amplitudes; Euclidean distances divided by their maximum stand in for normalized geodesics."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    rest = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
    bumps = np.exp(-np.sum((rest[None, :, :2] - BUMP_CENTRES[:, None]) ** 2, -1) / (2 * 0.08**2))
    dirs = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]) / np.array([[1.0], [np.sqrt(2)]])
    amp = np.random.default_rng(seed).normal(size=(shapes, 2)) * 0.1
    verts = rest[None] + np.einsum("nb,bv,bd->nvd", amp, bumps, dirs)
    dist = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
    return verts, dist / dist.max(), rest


def _rel(a, b, ref):
    return np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(ref)


# ------------------------------------------------------------------------------- regional projection


def test_geodesic_regions_on_a_line():
    """Points on a segment: two regions split it at the middle (centres at both ends), V regions isolate every
    point, one region holds all."""
    v = 9
    pos = np.arange(v, dtype=float)
    dist = np.abs(pos[:, None] - pos[None]) / (v - 1)
    np.testing.assert_array_equal(B.geodesic_regions(dist, 2), [0, 0, 0, 0, 0, 1, 1, 1, 1])  # tie -> earlier
    assert sorted(B.geodesic_regions(dist, v)) == list(range(v))
    assert set(B.geodesic_regions(dist, 1)) == {0}
    with pytest.raises(ValueError, match="n_regions"):
        B.geodesic_regions(dist, 0)


def test_regional_projection_recombines_regions_of_training_shapes():
    """A test shape made of shape 1 on one half and shape 2 on the other is outside the span of the training
    shapes (one region fails) but exact region by region; a training shape is reproduced by any partition, and
    one region is PCA with every component kept."""
    train = _random(n=4, v=10, c=3, seed=3)
    labels = np.repeat([0, 1], 5)
    mixed = np.where(labels[:, None] == 0, train[1], train[2])[None]
    np.testing.assert_allclose(B.regional_projection(train, mixed, labels), mixed, atol=1e-10)
    one = B.regional_projection(train, mixed, np.zeros(10, int))
    assert _rel(one, mixed, mixed - train.mean(0)) > 0.1
    np.testing.assert_allclose(B.regional_projection(train, train[2:3], np.arange(10) % 3), train[2:3], atol=1e-10)
    pca = B.fit_pca(train, n_components=50)
    np.testing.assert_allclose(one, np.asarray(B.reconstruct(pca, jnp.asarray(mixed))), atol=1e-8)
    with pytest.raises(ValueError, match="labels"):
        B.regional_projection(train, mixed, labels[:-1])


# ------------------------------------------------------------------------------------------ PCA


def test_pca_reconstructs_training_data_and_is_orthonormal():
    x = _random()
    m = B.fit_pca(x)
    assert (m.n_components, m.domain, m.method, m.scale) == (5, "xyz", "pca", 1.0)
    cf = np.asarray(m.components).reshape(5, -1)
    np.testing.assert_allclose(cf @ cf.T, np.eye(5), atol=1e-12)
    np.testing.assert_allclose(np.asarray(B.reconstruct(m, x)), x, atol=1e-12)
    np.testing.assert_allclose(np.asarray(m.mean), x.mean(0), atol=1e-14)


def test_pca_matches_numpy_svd_and_projects_span_exactly():
    x = _random(n=12, v=7, c=9, seed=3)
    m = B.fit_pca(x, n_components=4)
    assert m.domain == "acap" and m.components.shape == (4, 7, 9)
    xc = (x - x.mean(0)).reshape(12, -1)
    _, s, vt = np.linalg.svd(xc, full_matrices=False)
    cf = np.asarray(m.components).reshape(4, -1)
    np.testing.assert_allclose(np.abs(np.sum(cf * vt[:4], axis=1)), 1.0, atol=1e-10)
    # training weights are the principal coordinates
    np.testing.assert_allclose(np.linalg.norm(np.asarray(B.project(m, x)), axis=0), s[:4], rtol=1e-10)
    w = np.random.default_rng(4).normal(size=(3, 4))
    shapes = B.decode(m, jnp.asarray(w))
    np.testing.assert_allclose(np.asarray(B.project(m, shapes)), w, atol=1e-10)


def test_pca_caps_k_and_keeps_float32():
    x = _random(n=4, v=5).astype(np.float32)
    m = B.fit_pca(x, n_components=50)
    assert m.n_components == 3 and m.components.dtype == jnp.float32 and m.mean.dtype == jnp.float32
    assert B.fit_pca(x, n_components=2).n_components == 2
    assert B.fit_pca(_random(n=30, v=2, c=3), n_components=50).n_components == 6  # V c = 6


# ------------------------------------------------------------------------------------------ SPLOCS


@pytest.fixture(scope="module")
def bumps():
    verts, dist, rest = _grid_bumps()
    calls = []
    model, result = B.fit_splocs_detailed(verts, dist, n_components=10, progress=lambda it, e: calls.append((it, e)))
    return verts, dist, rest, model, result, calls


def test_splocs_reconstructs_training_data(bumps):
    verts, _, _, model, result, _ = bumps
    ref = verts - verts.mean(0)
    assert model.method == "splocs" and model.domain == "xyz" and model.components.shape == (10, 144, 3)
    assert model.scale == pytest.approx(np.std(ref))
    assert _rel(B.decode(model, jnp.asarray(result.weights)), verts, ref) < 0.05
    assert _rel(B.reconstruct(model, verts), verts, ref) < 0.05


def test_splocs_leading_components_are_localized_on_one_bump_each(bumps):
    _, _, rest, model, result, _ = bumps
    c = np.asarray(model.components)
    energy = np.sum(c * c, axis=-1)  # (K, V)
    contribution = np.linalg.norm(result.weights, axis=0) * np.sqrt(energy.sum(1))
    near = np.linalg.norm(rest[None, :, :2] - BUMP_CENTRES[:, None], axis=-1) < 0.3  # (2, V)
    found = set()
    for k in np.argsort(-contribution)[:2]:
        fraction = (near.astype(float) @ energy[k]) / energy[k].sum()
        assert fraction.max() > 0.9, fraction
        found.add(int(np.argmax(fraction)))
    assert found == {0, 1}


def test_splocs_objective_decreases_and_weights_are_bounded(bumps):
    _, _, _, _, result, calls = bumps
    e = np.asarray(result.objectives)
    assert len(e) == 11 and e[-1] < 0.5 * e[0]
    assert np.all(e[1:] <= e[:-1] * 1.02)
    assert [it for it, _ in calls] == list(range(10))
    np.testing.assert_allclose([v for _, v in calls], e[1:])
    w = result.weights
    assert np.all(np.abs(w) <= 1.0 + 1e-12)
    # the bound is active for the components that carry the data (the scale ambiguity is fixed by it)
    lead = np.argsort(-np.linalg.norm(result.components.reshape(10, -1), axis=1))[:2]
    np.testing.assert_allclose(np.abs(w[:, lead]).max(axis=0), 1.0, atol=1e-3)


def test_splocs_distance_callable_matches_matrix_and_fetches_few_rows(bumps):
    verts, dist, _, model, _, _ = bumps
    asked = []

    def rows(idx):
        asked.extend(np.asarray(idx).tolist())
        return dist[idx]

    other = B.fit_splocs(verts, rows, n_components=10)
    np.testing.assert_allclose(np.asarray(other.components), np.asarray(model.components), atol=1e-12)
    assert len(asked) == len(set(asked)) < 144  # cached, and only support centres


def test_splocs_keeps_k_beyond_the_data_rank():
    verts, dist, _ = _grid_bumps(n=8, shapes=3)
    model, result = B.fit_splocs_detailed(verts, dist, n_components=50, outer=3)
    assert model.components.shape == (50, 64, 3)
    zero = np.all(result.components == 0, axis=(1, 2))
    assert np.all(result.weights[:, zero] == 0)
    assert np.all(np.isfinite(np.asarray(B.reconstruct(model, verts))))


def test_splocs_support_weights_and_shrinkage():
    lam = B.support_weights(np.array([[0.0, 0.1, 0.4, 0.7, 0.9, np.inf]]), 0.1, 0.7)
    np.testing.assert_allclose(lam, [[0.0, 0.0, 0.5, 1.0, 1.0, 1.0]])
    v = np.array([[[3.0, 4.0, 0.0], [0.3, 0.4, 0.0]]])
    np.testing.assert_allclose(B.group_shrink(v, np.array([[1.0, 1.0]])), [[[2.4, 3.2, 0.0], [0, 0, 0]]])


# ------------------------------------------------------------------------------------------ JAX interface


def test_decode_and_project_jit_and_grad(bumps):
    verts, _, _, model, _, _ = bumps
    w = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, size=(2, model.n_components)))
    np.testing.assert_allclose(np.asarray(jax.jit(B.decode)(model, w)), np.asarray(B.decode(model, w)), atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(jax.jit(B.project)(model, verts[:3])), np.asarray(B.project(model, verts[:3])), atol=1e-10
    )
    g = jax.grad(lambda a: jnp.sum(B.decode(model, a)))(w)
    expected = model.scale * np.asarray(model.components).sum(axis=(1, 2))
    np.testing.assert_allclose(np.asarray(g), np.broadcast_to(expected, g.shape), rtol=1e-10)
    target = jnp.asarray(verts[5])
    gx = jax.grad(lambda x: jnp.sum((B.reconstruct(model, x) - target) ** 2))(jnp.asarray(verts[:2]))
    gm = jax.grad(lambda m: jnp.sum(B.decode(m, w) ** 2))(model)
    assert np.all(np.isfinite(np.asarray(gx))) and np.all(np.isfinite(np.asarray(gm.components)))


def test_save_load_round_trip(tmp_path, bumps):
    model = bumps[3]
    path = tmp_path / "splocs"
    B.save(model, path)
    B.save(model, path)  # overwrite in place
    back = B.load(path)
    assert (back.domain, back.method, back.scale) == (model.domain, model.method, pytest.approx(model.scale))
    np.testing.assert_array_equal(np.asarray(back.components), np.asarray(model.components))
    np.testing.assert_array_equal(np.asarray(back.mean), np.asarray(model.mean))
    assert os.listdir(tmp_path) == ["splocs"] and path.is_dir()
    pca = B.fit_pca(_random(v=4, c=9).astype(np.float32))
    B.save(pca, tmp_path / "pca.ckpt")  # any name: written exactly there
    back = B.load(tmp_path / "pca.ckpt")
    assert back.domain == "acap" and back.components.dtype == jnp.float32


# ------------------------------------------------------------------------------------------ errors


def test_bad_training_data_raises():
    x = _random()
    for fit in (B.fit_pca, lambda d: B.fit_splocs(d, np.zeros((10, 10)))):
        with pytest.raises(JaxDeformError, match="at least 2"):
            fit(x[:1])
        bad = x.copy()
        bad[2, 3, 1] = np.nan
        with pytest.raises(MeshFormatError, match="shape 2 holds NaN"):
            fit(bad)
        with pytest.raises(ConnectivityError, match="do not share"):
            fit([x[0], x[1, :9]])
        with pytest.raises(MeshFormatError, match=r"\(N, V, c\)"):
            fit(x[0])
    with pytest.raises(MeshFormatError, match="channels"):
        B.fit_pca(_random(c=4))
    with pytest.raises(MeshFormatError, match="3 channels"):
        B.fit_splocs(_random(c=9), np.zeros((10, 10)))
    with pytest.raises(JaxDeformError, match="identical"):
        B.fit_splocs(np.repeat(x[:1], 3, axis=0), np.zeros((10, 10)))


def test_bad_distances_and_parameters_raise():
    x = _random()
    with pytest.raises(ConnectivityError, match="distance matrix"):
        B.fit_splocs(x, np.zeros((11, 11)))
    with pytest.raises(ConnectivityError, match="returned shape"):
        B.fit_splocs(x, lambda idx: np.zeros((len(idx), 9)))
    with pytest.raises(MeshFormatError, match="NaN"):
        B.fit_splocs(x, np.full((10, 10), np.nan))
    with pytest.raises(JaxDeformError, match="d_min < d_max"):
        B.fit_splocs(x, np.zeros((10, 10)), d_min=0.7, d_max=0.1)
    with pytest.raises(JaxDeformError, match="n_components"):
        B.fit_pca(x, n_components=0)


def test_bad_model_inputs_raise(tmp_path):
    m = B.fit_pca(_random())
    with pytest.raises(ConnectivityError, match="11 vertices"):
        B.project(m, _random(n=2, v=11))
    with pytest.raises(MeshFormatError, match=r"\(B, V, 3\)"):
        B.project(m, _random(n=2, c=9))
    with pytest.raises(JaxDeformError, match=r"\(B, 5\)"):
        B.decode(m, jnp.zeros((2, 4)))
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not an archive")
    with pytest.raises(MeshFormatError, match="not a linear model checkpoint"):
        B.load(bad)
    with pytest.raises(FileNotFoundError):
        B.load(tmp_path / "absent")
    record = {"format": B.FORMAT, "version": B.FORMAT_VERSION, "scale": 1.0, "domain": "xyz", "method": "pca"}
    save_tree(tmp_path / "partial", {"mean": np.zeros((3, 3))}, record)
    with pytest.raises(MeshFormatError, match="'components' is missing"):
        B.load(tmp_path / "partial")
    save_tree(tmp_path / "nan", {"mean": np.zeros((3, 3)), "components": np.full((2, 3, 3), np.nan)}, record)
    with pytest.raises(MeshFormatError, match="NaN"):
        B.load(tmp_path / "nan")
    save_tree(
        tmp_path / "domain", {"mean": np.zeros((3, 3)), "components": np.ones((2, 3, 3))}, record | {"domain": "uv"}
    )
    with pytest.raises(MeshFormatError, match="domain"):
        B.load(tmp_path / "domain")
    B.save(m, tmp_path / "damaged")
    (tmp_path / "damaged" / "arrays" / "_METADATA").unlink()
    with pytest.raises(MeshFormatError, match="damaged linear model checkpoint"):
        B.load(tmp_path / "damaged")
