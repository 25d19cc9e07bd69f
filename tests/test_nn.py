"""Tests of jaxdeform.nn: mesh convolution (seed 000 eq. 1), AE block, group sparsity and latent bound."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import (
    AEBlock,
    MeshConv,
    Rings,
    ae_decode,
    ae_decode_pre,
    ae_encode,
    ae_forward,
    ae_forward_error,
    init_ae_block,
    init_mesh_conv,
    mesh_conv,
    rings_from_topology,
)
from jaxdeform.nn.losses import (
    component_centres,
    geodesic_linear_mask,
    geodesic_step_mask,
    group_sparsity,
    latent_bound,
    reconstruction_loss,
)

# Eager dispatch compiles every primitive separately (slow on small CPUs): the tests call the jitted
# entry points, and test_jit_matches_eager checks that jit does not change the values.
eager_forward = ae_forward
mesh_conv = jax.jit(mesh_conv)
ae_decode = jax.jit(ae_decode)
ae_decode_pre = jax.jit(ae_decode_pre)
ae_forward = jax.jit(ae_forward)
component_centres = jax.jit(component_centres, static_argnums=1)
raw_group_sparsity = group_sparsity
group_sparsity = jax.jit(group_sparsity)
latent_bound = jax.jit(latent_bound)


def grid_faces(n: int = 4) -> np.ndarray:
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


@pytest.fixture(scope="module")
def grid():
    faces = grid_faces(4)
    topo = build_topology(faces, 16)
    return faces, topo, rings_from_topology(topo)


def dense_adjacency(faces: np.ndarray, n: int) -> np.ndarray:
    A = np.zeros((n, n))
    for f in faces:
        for k in range(3):
            A[f[k], f[(k + 1) % 3]] = A[f[(k + 1) % 3], f[k]] = 1.0
    return A


def grid_dist(n: int = 4) -> np.ndarray:
    """Normalized Euclidean distances between grid points (a stand-in for geodesics)."""
    p = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2).astype(float)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    return d / d.max()


def test_mesh_conv_matches_dense_reference(grid):
    faces, _, rings = grid
    rng = np.random.default_rng(0)
    params = {
        k: jnp.asarray(v)
        for k, v in dict(
            W_point=rng.normal(size=(5, 7)), W_neighbor=rng.normal(size=(5, 7)), b=rng.normal(size=7)
        ).items()
    }
    x = rng.normal(size=(3, 16, 5))
    y = mesh_conv(params, jnp.asarray(x), *rings)
    assert y.dtype == jnp.float64 and y.shape == (3, 16, 7)
    A = dense_adjacency(faces, 16)
    P = A / A.sum(1, keepdims=True)
    ref = x @ np.asarray(params["W_point"]) + np.einsum("ij,bjc->bic", P, x) @ np.asarray(params["W_neighbor"])
    ref = ref + np.asarray(params["b"])
    np.testing.assert_allclose(np.asarray(y), ref, rtol=1e-12, atol=1e-12)


def test_mesh_conv_pointwise_and_constant(grid):
    _, _, rings = grid
    p = init_mesh_conv(jax.random.PRNGKey(0), 4, 3, jnp.float64).weights()
    p = dict(p, b=jnp.array([0.5, -1.0, 2.0]))
    x = jnp.asarray(np.random.default_rng(1).normal(size=(2, 16, 4)))
    y = mesh_conv(dict(p, W_neighbor=jnp.zeros_like(p["W_neighbor"])), x, *rings)
    np.testing.assert_allclose(y, x @ p["W_point"] + p["b"], rtol=1e-12, atol=1e-12)
    # constant input with W_point = -W_neighbor gives exactly the bias
    xc = jnp.broadcast_to(jnp.array([1.0, -2.0, 0.3, 4.0]), (2, 16, 4))
    yc = mesh_conv(dict(p, W_neighbor=-p["W_point"]), xc, *rings)
    np.testing.assert_allclose(yc, jnp.broadcast_to(p["b"], yc.shape), atol=1e-12)


def test_init_shapes_and_dtype():
    conv = init_mesh_conv(jax.random.PRNGKey(0), 9, 9, jnp.float32)
    assert isinstance(conv, MeshConv) and isinstance(conv.W_point, nnx.Param)
    p = conv.weights()
    assert p["W_point"].shape == (9, 9) and p["W_neighbor"].shape == (9, 9) and p["b"].shape == (9,)
    assert p["W_point"].dtype == jnp.float32
    assert float(jnp.max(jnp.abs(p["W_point"]))) <= np.sqrt(6 / 18) + 1e-6


def test_ae_block_shapes_and_tied_weights(grid):
    _, _, rings = grid
    params = init_ae_block(jax.random.PRNGKey(0), 16, 5, jnp.float32)
    assert params.C[...].shape == (5, 9 * 16)
    x = jnp.asarray(0.5 * np.random.default_rng(1).normal(size=(4, 16, 9)), jnp.float32)
    z, xh = ae_forward(params, x, rings)
    assert z.shape == (4, 5) and xh.shape == (4, 16, 9) and xh.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(xh))) < 1.0
    # the decoder uses C (row k for z = e_k), the encoder C^T
    eye = jnp.eye(5, dtype=jnp.float32)
    pre = ae_decode_pre(params, eye)
    np.testing.assert_allclose(pre, params.C[...].reshape(5, 16, 9), rtol=0, atol=0)
    h = jnp.tanh(mesh_conv(params.conv_enc.weights(), x, *rings)).reshape(4, -1)
    np.testing.assert_allclose(z, h @ params.C[...].T, rtol=1e-5, atol=1e-6)
    # decoder conv has its own weights and is applied after tanh(z @ C)
    ref = jnp.tanh(mesh_conv(params.conv_dec.weights(), jnp.tanh(pre), *rings))
    np.testing.assert_allclose(ae_decode(params, eye, rings), ref, rtol=1e-6, atol=1e-6)
    assert not np.allclose(params.conv_enc.weights()["W_point"], params.conv_dec.weights()["W_point"])


def test_reconstruction_loss():
    x = jnp.zeros((2, 3, 9))
    xh = jnp.ones((2, 3, 9)) * jnp.array([1.0, 2.0])[:, None, None]
    assert float(reconstruction_loss(x, xh)) == pytest.approx((27 * 1 + 27 * 4) / 2)
    assert float(reconstruction_loss(x, xh, "element")) == pytest.approx(2.5)


def test_group_sparsity_step_mask():
    V, d = 16, 0.4
    dist = jnp.asarray(grid_dist(4))
    C = np.zeros((2, V, 9))
    # component 0 centred at vertex 0 with mass inside radius d; component 1 at vertex 15
    C[0, 0] = 3.0
    C[0, 1] = 0.5  # dist 1/sqrt(18) ~ 0.236 < 0.4
    C[1, 15] = -2.0
    C[1, 14, 4] = 1.0
    Cf = jnp.asarray(C.reshape(2, -1))
    np.testing.assert_array_equal(component_centres(Cf, V), [0, 15])
    assert float(group_sparsity(Cf, dist, d)) == 0.0
    lam = geodesic_step_mask(dist, jnp.array([0, 15]), d)
    assert lam.shape == (2, V)
    np.testing.assert_array_equal(lam, (np.asarray(dist)[[0, 15]] >= d).astype(float))
    assert float(lam[0, 0]) == 0.0 and float(lam[0, 15]) == 1.0
    # move a vector of norm 1.5 outside the radius (vertex 3: dist 3/sqrt(18) ~ 0.707)
    v = np.array([0.0, 0.9, 0, 1.2, 0, 0, 0, 0, 0])
    C2 = C.copy()
    C2[0, 3] = v
    got = float(group_sparsity(jnp.asarray(C2.reshape(2, -1)), dist, d))
    assert got == pytest.approx(1.5 / 2, rel=1e-12)
    # the centre follows the largest row: moving the peak elsewhere changes the mask
    C3 = C.copy()
    C3[0, 15] = 10.0
    assert int(component_centres(jnp.asarray(C3.reshape(2, -1)), V)[0]) == 15


def test_group_sparsity_linear_mask_of_tan_et_al():
    V = 16
    dist = jnp.asarray(grid_dist(4))
    C = np.zeros((1, V, 9))
    C[0, 0] = 3.0  # centre: vertex 0
    C[0, 1, 2] = 0.5  # dist ~0.236: inside the ramp, weight (0.236 - 0.2) / 0.2
    C[0, 3, 0] = -2.0  # dist ~0.707: weight 1
    d01, d03 = float(dist[0, 1]), float(dist[0, 3])
    assert 0.2 < d01 < 0.4 and d03 > 0.4
    expected = 0.5 * (d01 - 0.2) / 0.2 + 2.0 * 1.0
    got = float(
        jax.jit(lambda c, dd: raw_group_sparsity(c, dd, (0.2, 0.4), "linear"))(jnp.asarray(C.reshape(1, -1)), dist)
    )
    assert got == pytest.approx(expected, rel=1e-9)
    lam = np.asarray(geodesic_linear_mask(dist, jnp.array([0]), 0.2, 0.4))
    assert lam.min() == 0.0 and lam.max() == 1.0 and lam[0, 0] == 0.0
    with pytest.raises(ValueError, match="mask must be"):
        raw_group_sparsity(jnp.asarray(C.reshape(1, -1)), dist, 0.4, "gaussian")


def test_latent_bound():
    z = jnp.array([[1.0, -4.0, 0.0], [-5.0, 2.0, 3.0]])
    assert float(latent_bound(z)) == 0.0
    z2 = jnp.array([[7.0, -4.0, 0.0], [-5.0, -8.5, 3.0], [1.0, 0.0, 4.5]])
    assert float(latent_bound(z2)) == pytest.approx((2.0 + 3.5 + 0.0) / 3)
    g = jax.grad(latent_bound)(z2)
    np.testing.assert_allclose(g, np.array([[1, 0, 0], [0, -1, 0], [0, 0, 0]]) / 3)


def test_group_sparsity_grad_finite_with_zero_rows():
    dist = jnp.asarray(grid_dist(4))
    C = np.zeros((3, 16, 9))
    C[0, 0] = 1.0
    C[0, 15, 2] = 5.0
    # component 1 has zero rows at some vertices, component 2 is all zero
    C[1, 5, 0] = 1.0
    g = jax.grad(group_sparsity)(jnp.asarray(C.reshape(3, -1)), dist, 0.4)
    assert np.all(np.isfinite(np.asarray(g)))
    g = np.asarray(g).reshape(3, 16, 9)
    # gradient of ||v|| is v/||v|| / Kz on masked vertices, zero inside the radius and at zero rows
    # centre of component 0 is vertex 15 (largest norm), so vertex 0 lies outside the radius
    np.testing.assert_allclose(g[0, 0], np.ones(9) / 3 / 3)
    np.testing.assert_allclose(g[0, 15], 0.0)
    np.testing.assert_allclose(g[2], 0.0)


def test_jit_matches_eager(grid):
    _, _, rings = grid
    params = init_ae_block(jax.random.PRNGKey(2), 16, 4, jnp.float64)
    x = jnp.asarray(0.3 * np.random.default_rng(3).normal(size=(3, 16, 9)))
    dist = jnp.asarray(grid_dist(4))

    def loss(p, x, rings, dist):
        z, xh = eager_forward(p, x, rings)
        return (10 * reconstruction_loss(x, xh) + group_sparsity(p.C[...], dist, 0.4) + latent_bound(z, 0.01), z, xh)

    eager = loss(params, x, rings, dist)
    jitted = jax.jit(loss)(params, x, rings, dist)
    for a, b in zip(eager, jitted):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    gj = jax.jit(jax.grad(lambda p: loss(p, x, rings, dist)[0]))(params)
    assert all(np.all(np.isfinite(np.asarray(a))) for a in jax.tree_util.tree_leaves(gj))
    assert isinstance(rings, Rings)
    np.testing.assert_allclose(jax.jit(ae_encode)(params, x, rings), eager[1], rtol=1e-12)


def test_ring_mean_gradient_is_the_dense_transpose(grid):
    """The reverse-mode derivative of the one-ring mean (the transpose of its custom JVP) equals P^T applied to
    the cotangent (P row-normalized adjacency), under vmap too."""
    from jaxdeform.nn.graph_conv import ring_mean

    faces, _, rings = grid
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.normal(size=(2, 3, 16, 5)))  # (blocks, B, V, C)
    w = rng.normal(size=(2, 3, 16, 5))
    loss = lambda a: jnp.sum(jnp.asarray(w) * jax.vmap(lambda b: ring_mean(b, *rings))(a))  # noqa: E731
    g = np.asarray(jax.jit(jax.grad(loss))(x))
    A = dense_adjacency(faces, 16)
    P = A / A.sum(1, keepdims=True)
    np.testing.assert_allclose(g, np.einsum("ji,nbjc->nbic", P, w), rtol=1e-12, atol=1e-12)


def test_train_reports_the_step_temporaries(tmp_path):
    """train() compiles each stage's step ahead and records the largest XLA temporary buffer."""
    from jaxdeform.components import model, train
    from jaxdeform.data.synthetic import bending_tube_sequence
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn.graph_conv import rings_from_topology

    verts, faces = bending_tube_sequence(n_frames=3, n_around=6, n_along=5)
    rings = rings_from_topology(build_topology(faces, verts.shape[1]))
    x = jax.random.normal(jax.random.PRNGKey(0), (3, verts.shape[1], 9), jnp.float32) * 0.1
    dist = jnp.ones((verts.shape[1], verts.shape[1]), jnp.float32) * 0.5
    timing: dict = {}
    cfg = model.Config(kz=(2, 2), d=(0.5, 0.3))
    train.train(x, rings, dist, cfg, train.TrainConfig(epochs=3, joint=False), timing=timing)
    assert 0 < timing["step_temp_bytes"] < 1_000_000  # kilobytes of temporaries for this tiny tube
    assert timing["epochs_timed"] == 2 * 2 and timing["compile_s"] > 0


def test_host_scalars_keeps_values_and_order():
    from jaxdeform.nn.host import host_scalars, recent_mean

    xs = [jnp.asarray(v, jnp.float32) for v in (0.5, -2.0, 3.25, 7.0)]
    got = host_scalars(xs)
    assert got.dtype == np.float32 and got.shape == (4,)
    np.testing.assert_array_equal(got, [0.5, -2.0, 3.25, 7.0])
    assert host_scalars([]).shape == (0,)
    assert recent_mean(xs, 2) == pytest.approx(5.125)
    assert recent_mean(xs, 10) == pytest.approx(8.75 / 4)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_decoder_error_matches_the_squared_difference(dtype):
    """ae_forward_error's per-shape error and its gradients agree with the plain sum of (x_hat - x)^2 over the
    composed layers (mesh convolutions, tanh, products with C): the loss and the gradients of x and of every
    parameter, three vmapped blocks of 7 shapes on 361 vertices, with x_hat also used outside the error."""
    n = 19
    rings = rings_from_topology(build_topology(grid_faces(n), n * n))
    p = jax.vmap(lambda k: init_ae_block(k, n * n, 4, dtype))(jax.random.split(jax.random.PRNGKey(0), 3))
    x = jax.random.uniform(jax.random.PRNGKey(1), (3, 7, n * n, 9), dtype, -0.9, 0.9)

    def reference(q, xx):
        h = jnp.tanh(mesh_conv(q.conv_enc.weights(), xx, *rings))
        z = h.reshape(h.shape[0], -1) @ q.C[...].T
        g = jnp.tanh((z @ q.C[...]).reshape(xx.shape))
        xh = jnp.tanh(mesh_conv(q.conv_dec.weights(), g, *rings))
        return z, xh, jnp.sum(jnp.square(xh - xx), axis=(-2, -1))

    def make(block):
        def loss(p, x):
            z, xh, err = jax.vmap(block)(p, x)
            return jnp.sum(err * jnp.arange(1, 8)) + jnp.sum(jnp.sin(xh) * x) + jnp.sum(jnp.cos(z))

        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))

    (v1, g1), (v2, g2) = make(lambda q, xx: ae_forward_error(q, xx, rings))(p, x), make(reference)(p, x)
    tol = 2e-6 if dtype == jnp.float32 else 1e-13
    assert abs(float(v1 - v2)) <= tol * abs(float(v2))
    for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g2)):
        assert float(jnp.max(jnp.abs(a - b))) <= tol * float(jnp.max(jnp.abs(b)))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_masked_blocks_match_the_blocks_on_their_inputs(dtype):
    """masked_blocks_error gives the values and gradients of the vmapped blocks (ae_forward_error) run on the
    formed inputs am[j, m] x[j]: 2 parents x 3 children, 4 shapes, 361 vertices."""
    from jaxdeform.nn.graph_conv import masked_blocks_error

    n = 19
    rings = rings_from_topology(build_topology(grid_faces(n), n * n))
    keys = jax.random.split(jax.random.PRNGKey(0), 6).reshape(2, 3, -1)
    p = jax.vmap(jax.vmap(lambda k: init_ae_block(k, n * n, 5, dtype)))(keys)
    x = jax.random.uniform(jax.random.PRNGKey(1), (2, 4, n * n, 9), dtype, -0.9, 0.9)
    am = jax.random.uniform(jax.random.PRNGKey(2), (2, 3, n * n), dtype)

    def formed(p, x):
        inputs = am[..., None, :, None] * x[:, None]
        return jax.vmap(jax.vmap(lambda q, xin: ae_forward_error(q, xin, rings, "linear")))(p, inputs)

    def make(blocks):
        def loss(p, x):
            z, xh, err = blocks(p, x)
            return jnp.sum(err * jnp.arange(1, 5)) + 0.3 * jnp.sum(jnp.sin(xh)) + jnp.sum(jnp.cos(z))

        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))

    (v1, g1) = make(lambda p, x: masked_blocks_error(p, x, am, rings))(p, x)
    (v2, g2) = make(formed)(p, x)
    tol = 2e-6 if dtype == jnp.float32 else 1e-13
    assert abs(float(v1 - v2)) <= tol * abs(float(v2))
    for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g2)):
        assert float(jnp.max(jnp.abs(a - b))) <= tol * float(jnp.max(jnp.abs(b)))


def test_masked_blocks_jacobian_under_vmap():
    """jax.jacrev of masked_blocks_error (its adjoint mapped over the cotangents) equals that of the blocks on the
    formed inputs, for x and a block's C."""
    from jaxdeform.nn.graph_conv import masked_blocks_error

    n = 5
    rings = rings_from_topology(build_topology(grid_faces(n), n * n))
    p = jax.vmap(jax.vmap(lambda k: init_ae_block(k, n * n, 3, jnp.float64)))(
        jax.random.split(jax.random.PRNGKey(3), 4).reshape(1, 4, -1)
    )
    x = jax.random.uniform(jax.random.PRNGKey(4), (1, 2, n * n, 9), jnp.float64, -0.9, 0.9)
    am = jax.random.uniform(jax.random.PRNGKey(5), (1, 4, n * n), jnp.float64)

    def masked(x, c):
        z, xh, err = masked_blocks_error(AEBlock(p.conv_enc, p.conv_dec, c), x, am, rings)
        return jnp.concatenate([err.ravel(), xh[..., :3, :].ravel()])

    def formed(x, c):
        inputs = am[..., None, :, None] * x[:, None]
        z, xh, err = jax.vmap(jax.vmap(lambda q, xin: ae_forward_error(q, xin, rings)))(
            AEBlock(p.conv_enc, p.conv_dec, c), inputs
        )
        return jnp.concatenate([err.ravel(), xh[..., :3, :].ravel()])

    got = jax.jit(jax.jacrev(masked, argnums=(0, 1)))(x, p.C[...])
    want = jax.jit(jax.jacrev(formed, argnums=(0, 1)))(x, p.C[...])
    for a, b in zip(got, want):
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-12 * float(jnp.max(jnp.abs(b)))


def _central_difference(f, x, v, h=1e-5):
    """(f(x + h v) - f(x - h v)) / 2h over a pytree of outputs (error O(h^2) for smooth f)."""
    plus = f(jax.tree_util.tree_map(lambda a, b: a + h * b, x, v))
    minus = f(jax.tree_util.tree_map(lambda a, b: a - h * b, x, v))
    return jax.tree_util.tree_map(lambda p, m: (p - m) / (2 * h), plus, minus)


def _assert_close(got, want, rtol):
    """Every leaf of ``got`` finite and within rtol of ``want``, relative to the largest entry of ``want``."""
    want = [np.asarray(b) for b in jax.tree_util.tree_leaves(want)]
    scale = max(float(np.max(np.abs(b))) for b in want)
    for a, b in zip(jax.tree_util.tree_leaves(got), want):
        a = np.asarray(a)
        assert np.all(np.isfinite(a))
        assert np.max(np.abs(a - b)) <= rtol * scale, np.max(np.abs(a - b)) / scale


def _random_like(tree, seed):
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
    return treedef.unflatten([jax.random.normal(k, a.shape, a.dtype) for k, a in zip(keys, leaves)])


def test_mesh_conv_forward_mode_matches_central_differences(grid):
    """jax.jvp of the mesh convolution (in x and the weights, under vmap over blocks) matches central
    differences in float64, and jax.jacfwd of the one-ring mean is the row-normalized adjacency P (each channel
    apart), as jax.jacrev's."""
    from jaxdeform.nn.graph_conv import ring_mean

    faces, _, rings = grid
    params = jax.vmap(lambda k: init_mesh_conv(k, 9, 9, jnp.float64))(jax.random.split(jax.random.PRNGKey(0), 2))
    x = jax.random.uniform(jax.random.PRNGKey(1), (2, 3, 16, 9), jnp.float64, -1, 1)

    def f(args):
        p, xx = args
        return jnp.sin(jax.vmap(lambda q, a: mesh_conv(q.weights(), a, *rings))(p, xx))

    v = _random_like((params, x), 2)
    _, tangent = jax.jit(lambda a, t: jax.jvp(f, (a,), (t,)))((params, x), v)
    _assert_close(tangent, _central_difference(f, (params, x), v), 1e-8)

    x1 = x[0, :1, :, :2]  # (1, V, 2)
    mean = lambda a: ring_mean(a, *rings)  # noqa: E731
    jf, jr = jax.jit(jax.jacfwd(mean))(x1), jax.jit(jax.jacrev(mean))(x1)
    A = dense_adjacency(faces, 16)
    P = A / A.sum(1, keepdims=True)
    want = np.einsum("ij,cd->icjd", P, np.eye(2))[None, :, :, None]
    np.testing.assert_allclose(jf, want, rtol=0, atol=1e-15)
    np.testing.assert_allclose(jr, want, rtol=0, atol=1e-15)


def _hessian_vector_check(loss, x, v, rtol):
    """grad of <grad loss, v> (reverse over reverse: H v) against central differences of the gradient along v,
    and grad of |grad loss|^2 finite."""
    grad = jax.grad(loss)
    hv = jax.jit(
        jax.grad(
            lambda a: sum(
                jnp.vdot(g, t) for g, t in zip(jax.tree_util.tree_leaves(grad(a)), jax.tree_util.tree_leaves(v))
            )
        )
    )(x)
    _assert_close(hv, _central_difference(jax.jit(grad), x, v), rtol)
    gg = jax.jit(jax.grad(lambda a: sum(jnp.sum(g**2) for g in jax.tree_util.tree_leaves(grad(a)))))(x)
    assert all(np.all(np.isfinite(np.asarray(a))) for a in jax.tree_util.tree_leaves(gg))


def test_second_order_through_the_mesh_convolution(grid):
    """Grad-of-grad through the mesh convolution (x and weights) gives H v as central differences of the gradient."""
    _, _, rings = grid
    params = init_mesh_conv(jax.random.PRNGKey(3), 9, 5, jnp.float64)
    x = jax.random.uniform(jax.random.PRNGKey(4), (2, 16, 9), jnp.float64, -1, 1)
    loss = lambda a: jnp.sum(jnp.tanh(mesh_conv(a[0].weights(), a[1], *rings)) ** 3)  # noqa: E731
    _hessian_vector_check(loss, (params, x), _random_like((params, x), 5), 1e-7)


def test_second_order_through_the_autoencoder_block(grid):
    """Grad-of-grad through a whole autoencoder block's loss (encoder, decoder, squared error; vmapped blocks on
    masked inputs) gives H v as central differences of the gradient, for the parameters and the input."""
    from jaxdeform.nn.graph_conv import masked_blocks_error

    _, _, rings = grid
    p = jax.vmap(jax.vmap(lambda k: init_ae_block(k, 16, 3, jnp.float64)))(
        jax.random.split(jax.random.PRNGKey(6), 2).reshape(1, 2, -1)
    )
    x = jax.random.uniform(jax.random.PRNGKey(7), (1, 2, 16, 9), jnp.float64, -0.9, 0.9)
    am = jax.random.uniform(jax.random.PRNGKey(8), (1, 2, 16), jnp.float64)

    def loss(a):
        z, xh, err = masked_blocks_error(a[0], a[1], am, rings)
        return jnp.sum(err) + jnp.sum(jnp.sin(z))

    _hessian_vector_check(loss, (p, x), _random_like((p, x), 9), 1e-6)


def test_second_order_through_the_transformer():
    """Grad-of-grad through the transformer (parameters and inputs) gives H v as central differences of the
    gradient, and jax.jvp matches central differences of its output."""
    from flax import nnx

    from jaxdeform.nn.transformer import Transformer

    model = Transformer(8, heads=2, blocks=1, ffn=16, rngs=nnx.Rngs(0))
    graphdef, state = nnx.split(model)
    state = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), state)
    src = jax.random.normal(jax.random.PRNGKey(1), (2, 5, 8), jnp.float64)
    tgt = jax.random.normal(jax.random.PRNGKey(2), (2, 4, 8), jnp.float64)

    def out(a):
        return nnx.merge(graphdef, a[0])(a[1], a[2])

    args = (state, src, tgt)
    v = _random_like(args, 3)
    _, tangent = jax.jit(lambda a, t: jax.jvp(out, (a,), (t,)))(args, v)
    _assert_close(tangent, _central_difference(out, args, v), 1e-7)
    _hessian_vector_check(lambda a: jnp.sum(jnp.tanh(out(a)) ** 2), args, v, 1e-6)
