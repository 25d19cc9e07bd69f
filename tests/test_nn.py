"""Tests of jaxdeform.nn: mesh convolution (seed 000 eq. 1), AE block, group sparsity and latent bound."""

import inspect
import os
import platform
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import (
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
    group_sparsity_gradient,
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
    params = {k: jnp.asarray(v) for k, v in dict(
        W_point=rng.normal(size=(5, 7)), W_neighbor=rng.normal(size=(5, 7)), b=rng.normal(size=7)).items()}
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
    p = init_mesh_conv(jax.random.PRNGKey(0), 4, 3, jnp.float64)
    p = dict(p, b=jnp.array([0.5, -1.0, 2.0]))
    x = jnp.asarray(np.random.default_rng(1).normal(size=(2, 16, 4)))
    y = mesh_conv(dict(p, W_neighbor=jnp.zeros_like(p["W_neighbor"])), x, *rings)
    np.testing.assert_allclose(y, x @ p["W_point"] + p["b"], rtol=1e-12, atol=1e-12)
    # constant input with W_point = -W_neighbor gives exactly the bias
    xc = jnp.broadcast_to(jnp.array([1.0, -2.0, 0.3, 4.0]), (2, 16, 4))
    yc = mesh_conv(dict(p, W_neighbor=-p["W_point"]), xc, *rings)
    np.testing.assert_allclose(yc, jnp.broadcast_to(p["b"], yc.shape), atol=1e-12)


def test_init_shapes_and_dtype():
    p = init_mesh_conv(jax.random.PRNGKey(0), 9, 9, jnp.float32)
    assert p["W_point"].shape == (9, 9) and p["W_neighbor"].shape == (9, 9) and p["b"].shape == (9,)
    assert p["W_point"].dtype == jnp.float32
    assert float(jnp.max(jnp.abs(p["W_point"]))) <= np.sqrt(6 / 18) + 1e-6


def test_ae_block_shapes_and_tied_weights(grid):
    _, _, rings = grid
    params = init_ae_block(jax.random.PRNGKey(0), 16, 5, jnp.float32)
    assert params["C"].shape == (5, 9 * 16)
    x = jnp.asarray(0.5 * np.random.default_rng(1).normal(size=(4, 16, 9)), jnp.float32)
    z, xh = ae_forward(params, x, rings)
    assert z.shape == (4, 5) and xh.shape == (4, 16, 9) and xh.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(xh))) < 1.0
    # the decoder uses C (row k for z = e_k), the encoder C^T
    eye = jnp.eye(5, dtype=jnp.float32)
    pre = ae_decode_pre(params, eye)
    np.testing.assert_allclose(pre, params["C"].reshape(5, 16, 9), rtol=0, atol=0)
    h = jnp.tanh(mesh_conv(params["conv_enc"], x, *rings)).reshape(4, -1)
    np.testing.assert_allclose(z, h @ params["C"].T, rtol=1e-5, atol=1e-6)
    # decoder conv has its own weights and is applied after tanh(z @ C)
    ref = jnp.tanh(mesh_conv(params["conv_dec"], jnp.tanh(pre), *rings))
    np.testing.assert_allclose(ae_decode(params, eye, rings), ref, rtol=1e-6, atol=1e-6)
    assert not np.allclose(params["conv_enc"]["W_point"], params["conv_dec"]["W_point"])


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
    got = float(jax.jit(lambda c, dd: raw_group_sparsity(c, dd, (0.2, 0.4), "linear"))(jnp.asarray(C.reshape(1, -1)), dist))
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
        return (10 * reconstruction_loss(x, xh) + group_sparsity(p["C"], dist, 0.4) + latent_bound(z, 0.01), z, xh)

    eager = loss(params, x, rings, dist)
    jitted = jax.jit(loss)(params, x, rings, dist)
    for a, b in zip(eager, jitted):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    gj = jax.jit(jax.grad(lambda p: loss(p, x, rings, dist)[0]))(params)
    assert all(np.all(np.isfinite(np.asarray(a))) for a in jax.tree_util.tree_leaves(gj))
    assert isinstance(rings, Rings)
    np.testing.assert_allclose(jax.jit(ae_encode)(params, x, rings), eager[1], rtol=1e-12)


def test_ring_mean_gradient_is_the_dense_transpose(grid):
    """The hand-written backward of the one-ring mean equals P^T applied to the cotangent (P row-normalized
    adjacency), under vmap too."""
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


def _conv_pair_losses(rings, shared: bool):
    """Sum of sin(conv) under vmap over blocks (own or shared weights), native and pure-JAX."""
    from jaxdeform.nn.graph_conv import mesh_conv_reference
    from jaxdeform.nn.graph_conv import mesh_conv as conv

    def make(fn):
        def loss(p, x):
            if shared:
                y = jax.vmap(lambda xx: fn(p, xx, *rings))(x)
            else:
                y = jax.vmap(lambda q, xx: fn(q, xx, *rings))(p, x)
            return jnp.sum(jnp.sin(y) * jnp.cos(jnp.sum(x, axis=-1, keepdims=True)))
        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))

    return make(conv), make(mesh_conv_reference)


def test_native_kernels_build_where_a_compiler_exists():
    """The kernel source compiles wherever a C++ compiler is found: the tests of the native kernels skip only
    where there is none (or the backend is not the CPU), never because the source is broken."""
    import os
    import shutil

    from jaxdeform.nn import native

    if jax.default_backend() != "cpu" or os.environ.get("JAXDEFORM_NATIVE", "1") == "0":
        pytest.skip("the native kernels serve the CPU backend only")
    if not (os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")):
        pytest.skip("no C++ compiler here")
    assert native.build().is_file()
    assert native.available()


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("channels", [(9, 9), (5, 7)])
def test_native_mesh_conv_matches_pure_jax(dtype, shared, channels):
    """The native CPU kernels (forward and hand-written adjoint) agree with the pure-JAX definition, values
    and gradients of every parameter, for vmapped blocks with their own or with shared weights: the 9-channel
    kernels of seed 000 (49 vertices: one whole tile of the adjoint's weight-gradient sums and a partial one)
    and the generic ones."""
    from jaxdeform.nn import native

    if not native.available():
        pytest.skip("native mesh convolution unavailable here (no C++ compiler or not on CPU)")
    rings = rings_from_topology(build_topology(grid_faces(7), 49))
    cin, cout = channels
    keys = jax.random.split(jax.random.PRNGKey(5), 3)
    p = init_mesh_conv(keys[0], cin, cout, dtype)
    p = dict(p, b=jnp.linspace(-0.5, 0.5, cout, dtype=dtype))
    if not shared:
        p = jax.tree_util.tree_map(lambda a: jnp.stack([a, 0.5 * a, -a]), p)
    x = jax.random.normal(keys[1], (3, 4, 49, cin), dtype)
    nat, ref = _conv_pair_losses(rings, shared)
    (vn, gn), (vr, gr) = nat(p, x), ref(p, x)
    tol = 1e-11 if dtype == jnp.float64 else 2e-4
    np.testing.assert_allclose(vn, vr, rtol=tol)
    for a, b in zip(jax.tree_util.tree_leaves(gn), jax.tree_util.tree_leaves(gr)):
        assert a.dtype == dtype and a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=tol, atol=tol)


def test_native_mesh_conv_gradient_matches_finite_differences(grid):
    """Central differences of the native forward in float64 agree with its adjoint kernel."""
    from jaxdeform.nn import native

    if not native.available():
        pytest.skip("native mesh convolution unavailable here (no C++ compiler or not on CPU)")
    _, _, rings = grid
    from jaxdeform.nn.graph_conv import mesh_conv as conv

    rng = np.random.default_rng(6)
    p = {k: jnp.asarray(rng.normal(size=s)) for k, s in (("W_point", (9, 9)), ("W_neighbor", (9, 9)), ("b", (9,)))}
    x = jnp.asarray(rng.normal(size=(2, 16, 9)))
    def loss(p, x):
        return jnp.sum(jnp.tanh(conv(p, x, *rings)) ** 2)

    f = jax.jit(loss)
    gp, gx = jax.jit(jax.grad(loss, argnums=(0, 1)))(p, x)
    eps = 1e-6
    for _ in range(3):
        dp = {k: jnp.asarray(rng.normal(size=v.shape)) for k, v in p.items()}
        dx = jnp.asarray(rng.normal(size=x.shape))
        plus = f({k: p[k] + eps * dp[k] for k in p}, x + eps * dx)
        minus = f({k: p[k] - eps * dp[k] for k in p}, x - eps * dx)
        fd = (plus - minus) / (2 * eps)
        an = sum(jnp.vdot(gp[k], dp[k]) for k in p) + jnp.vdot(gx, dx)
        assert abs(float(fd - an)) <= 1e-6 * max(1.0, abs(float(an)))


def _block_losses(rings, shared: bool, kz: int):
    """A loss through both fused block halves under vmap over blocks (own or shared parameters, a tanh
    between them as in the latent-tanh configuration), native and from the pure-JAX layers."""
    from jaxdeform.nn.graph_conv import mesh_conv_reference

    def enc_ref(p, x):
        h = jnp.tanh(mesh_conv_reference(p["conv_enc"], x, *rings))
        return h.reshape(h.shape[0], -1) @ p["C"].T

    def dec_ref(p, z):
        g = jnp.tanh((z @ p["C"]).reshape(z.shape[0], -1, 9))
        return jnp.tanh(mesh_conv_reference(p["conv_dec"], g, *rings))

    def make(enc, dec):
        def loss(p, x):
            if shared:
                z = jax.vmap(lambda xx: enc(p, xx))(x)
                xh = jax.vmap(lambda zz: dec(p, jnp.tanh(zz)))(z)
            else:
                z = jax.vmap(enc)(p, x)
                xh = jax.vmap(lambda q, zz: dec(q, jnp.tanh(zz)))(p, z)
            return jnp.sum(jnp.sin(3 * xh) * x) + jnp.sum(jnp.cos(z))
        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))

    return (make(lambda p, x: ae_encode(p, x, rings), lambda p, z: ae_decode(p, z, rings)),
            make(enc_ref, dec_ref))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("shapes", [5, 6, 7])
def test_native_fused_block_matches_pure_jax(dtype, shared, shapes):
    """The fused encoder and decoder calls (forward and adjoint) agree with the block built from the pure-JAX
    layers: values and the gradients of x and of every parameter (C, both convolutions), for three vmapped
    blocks with their own or shared parameters. 441 vertices: several vertex tiles of 64, a partial last
    one of 57 (the kernels' vertex groups of 8 or 16: a partial last group either way), and a split over
    threads where the machine has two or more cores. 5, 6 and 7 shapes per block: the
    kernels sum the rings of up to 4 shapes at once, then of the 1, 2 or 3 left over."""
    from jaxdeform.nn import native

    if not native.available():
        pytest.skip("native kernels unavailable here (no C++ compiler or not on CPU)")
    n = 21
    rings = rings_from_topology(build_topology(grid_faces(n), n * n))
    kz = 5
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    p = jax.vmap(lambda k: init_ae_block(k, n * n, kz, dtype))(keys)
    p["C"] = 3 * p["C"]  # large enough to reach tanh's tails
    p["conv_enc"]["b"] = jnp.linspace(-0.3, 0.3, 27, dtype=dtype).reshape(3, 9)
    p["conv_dec"]["b"] = jnp.linspace(0.2, -0.4, 27, dtype=dtype).reshape(3, 9)
    if shared:
        p = jax.tree_util.tree_map(lambda a: a[1], p)
    x = 0.5 * jax.random.normal(jax.random.PRNGKey(1), (3, shapes, n * n, 9), dtype)
    nat, ref = _block_losses(rings, shared, kz)
    (vn, gn), (vr, gr) = nat(p, x), ref(p, x)
    tol = 1e-11 if dtype == jnp.float64 else 1e-4
    np.testing.assert_allclose(vn, vr, rtol=tol)
    for a, b in zip(jax.tree_util.tree_leaves(gn), jax.tree_util.tree_leaves(gr)):
        assert a.dtype == dtype and a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=tol, atol=tol * float(jnp.max(jnp.abs(b))))


def test_native_fused_block_8_lane_build_matches_pure_jax():
    """On an AVX-512 CPU the fused kernels run on groups of 16 vertices (float32); elsewhere, the AVX2 machines
    included, on groups of 8. The 8-lane build (JAXDEFORM_NATIVE_CFLAGS=-mno-avx512f, its own cached library)
    passes the same float32 comparisons with the pure-JAX blocks (plain and masked), in a fresh process."""
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    from jaxdeform.nn import native

    if not native.available():
        pytest.skip("native kernels unavailable here (no C++ compiler or not on CPU)")
    if not {"avx512f", "avx512dq"} <= set(native._cpu_tag().split()):  # the kernels' condition for 16 lanes
        pytest.skip("no AVX-512 F and DQ here: the default build is the 8-lane one, tested above")
    env = dict(os.environ, JAXDEFORM_NATIVE_CFLAGS="-mno-avx512f")
    script = ("from jaxdeform.nn import native; assert native.available(); print(native.build().name)")
    lib = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert lib.returncode == 0, lib.stderr[-2000:]
    assert lib.stdout.strip() != native.build().name  # another library than this process's
    tests = "(test_native_fused_block_matches_pure_jax or test_masked_blocks_match_the_blocks) and float32"
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", __file__, "-k", tests],
                          env=env, capture_output=True, text=True, timeout=900, cwd=Path(__file__).parent.parent)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert re.search(r"\b7 passed", proc.stdout), proc.stdout[-2000:]


def test_native_fused_block_gradient_matches_finite_differences(grid):
    """Central differences of the fused encoder and decoder in float64 agree with their adjoint calls
    (unbatched: no vmap), for every input."""
    from jaxdeform.nn import native

    if not native.available():
        pytest.skip("native kernels unavailable here (no C++ compiler or not on CPU)")
    _, _, rings = grid
    rng = np.random.default_rng(7)
    p = jax.tree_util.tree_map(lambda a: jnp.asarray(rng.normal(size=a.shape)),
                               init_ae_block(jax.random.PRNGKey(0), 16, 3, jnp.float64))
    x = jnp.asarray(rng.normal(size=(2, 16, 9)))

    def loss(p, x):
        z = ae_encode(p, x, rings)
        return jnp.sum(jnp.sin(ae_decode(p, 0.3 * z, rings)) * x) + jnp.sum(z ** 2)

    f = jax.jit(loss)
    gp, gx = jax.jit(jax.grad(loss, argnums=(0, 1)))(p, x)
    eps = 1e-6
    for _ in range(3):
        dp = jax.tree_util.tree_map(lambda a: jnp.asarray(rng.normal(size=a.shape)), p)
        dx = jnp.asarray(rng.normal(size=x.shape))
        step = lambda s: jax.tree_util.tree_map(lambda a, d: a + s * eps * d, p, dp)  # noqa: E731
        fd = (f(step(1), x + eps * dx) - f(step(-1), x - eps * dx)) / (2 * eps)
        an = sum(jnp.vdot(g, d) for g, d in zip(jax.tree_util.tree_leaves(gp), jax.tree_util.tree_leaves(dp)))
        an = an + jnp.vdot(gx, dx)
        assert abs(float(fd - an)) <= 1e-6 * max(1.0, abs(float(an)))


def test_native_fused_block_jacobians_match_pure_jax(grid):
    """Jacobians through the fused halves (jax.jacrev: a vmap over cotangents whose primal arguments are not
    batched, nested in the vmap over blocks, so C and the primals broadcast against the cotangents' batch)
    equal those of the pure-JAX layers."""
    from jaxdeform.nn import native
    from jaxdeform.nn.graph_conv import ae_decode_reference, ae_encode_reference

    if not native.available():
        pytest.skip("native kernels unavailable here (no C++ compiler or not on CPU)")
    _, _, rings = grid
    n_v = rings.neighbors.shape[0]
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    p = jax.vmap(lambda k: init_ae_block(k, n_v, 3, jnp.float64))(keys)
    p = jax.tree_util.tree_map(lambda a: 3 * a, p)
    x = jax.random.normal(jax.random.PRNGKey(4), (2, 1, n_v, 9), jnp.float64)
    rows = np.arange(0, n_v * 9, 7)

    def make(enc, dec):
        def f(z, x):  # (2, 1, 3), (2, 1, V, 9) -> a few output rows of both halves per block
            xh = jax.vmap(lambda q, zz: dec(q, zz, rings))(p, z)
            zz = jax.vmap(lambda q, xx: enc(q, xx, rings))(p, x)
            return jnp.concatenate([xh.reshape(2, -1)[:, rows], zz.reshape(2, -1)], axis=1)
        return jax.jit(jax.jacrev(f, argnums=(0, 1)))

    z = jax.random.normal(jax.random.PRNGKey(5), (2, 1, 3), jnp.float64)
    fused = make(ae_encode, ae_decode)
    got = fused(z, x)
    want = make(ae_encode_reference, ae_decode_reference)(z, x)
    for a, b in zip(got, want):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(b))))
    assert "ae_encoder_bwd" in fused.lower(z, x).as_text()


_ALLOCATOR_PROBE = """
import resource, sys, threading
import numpy as np
from jaxdeform.nn import native
applied = native.tune_host_allocator() if sys.argv[1] == "1" else False
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt  # noqa: E731
res = []
def work():  # as XLA's worker threads do: large buffers, allocated and freed again in another thread
    bufs = [np.ones(2_000_000) for _ in range(8)]; del bufs  # 8 x 16 MB, written and freed once
    f0 = faults()
    for _ in range(3):
        bufs = [np.ones(2_000_000) for _ in range(8)]; del bufs
    res.append(faults() - f0)
t = threading.Thread(target=work); t.start(); t.join()
print(int(applied), res[0])
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="tune_host_allocator sets glibc malloc options")
def test_tune_host_allocator_reuses_freed_buffers():
    """Once tuned, buffers freed by a worker thread are reused by its next allocations without new pages;
    untuned, glibc returns some of them to the system and the rewrites fault pages in again (about 9,000
    faults on the project's VM)."""
    out = {}
    for flag, tuned in (("1", "0"), ("1", "1"), ("0", "1")):  # (JAXDEFORM_HOST_ALLOCATOR, call the tuning)
        proc = subprocess.run([sys.executable, "-c", _ALLOCATOR_PROBE, tuned], capture_output=True, text=True,
                              env={**os.environ, "JAXDEFORM_HOST_ALLOCATOR": flag}, check=True)
        out[flag, tuned] = tuple(map(int, proc.stdout.split()))
    assert out["1", "1"][0] == 1 and out["1", "0"][0] == 0
    assert out["0", "1"][0] == 0  # the opt-out
    assert out["1", "1"][1] < 50 and out["1", "1"][1] < out["1", "0"][1]


_FIT_PROBE = """
import sys
import numpy as np
from jaxdeform.nn import native
rss = lambda: int(open("/proc/self/statm").read().split()[1]) * 4096  # noqa: E731  (resident bytes)
before = native.fit_host_allocator(2 << 30)  # not tuned yet: nothing to fit
tuned = native.tune_host_allocator()
assert native.fit_host_allocator(None) is False  # size unknown: the tuned heap stays
fitted = native.fit_host_allocator(native.LARGE_PROGRAM_BYTES + int(sys.argv[1]))  # + 0: at the limit
again = native.fit_host_allocator(2 << 30) if fitted else False  # no change after a switch
bufs = np.ones(8_000_000)  # a 64 MB buffer, written
r0 = rss(); del bufs
print(int(before), int(tuned), int(fitted), int(again), (r0 - rss()) // 2**20, native.host_allocator())
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="fit_host_allocator sets glibc malloc options")
def test_fit_host_allocator_maps_large_blocks_only_for_large_programs():
    """A program with more than LARGE_PROGRAM_BYTES of temporaries switches the tuned heap to mmap for blocks
    above 32 MiB: a freed 64 MB buffer then leaves the resident set at once; at the limit the tuned heap stays
    and keeps it for reuse."""
    out = {}
    for extra in ("0", "1"):
        proc = subprocess.run([sys.executable, "-c", _FIT_PROBE, extra], capture_output=True, text=True,
                              check=True, env={**os.environ, "JAXDEFORM_HOST_ALLOCATOR": "1"})
        *flags, released_mib, state = proc.stdout.split(maxsplit=5)
        out[extra] = (list(map(int, flags)), int(released_mib), state.strip())
    assert out["0"][0] == [0, 1, 0, 0] and out["0"][2] == "tuned" and out["0"][1] < 8
    assert out["1"][0] == [0, 1, 1, 0] and out["1"][2] == "large blocks by mmap" and out["1"][1] >= 60


def test_train_reports_the_step_temporaries(tmp_path):
    """train() compiles each stage's step ahead and records the largest XLA temporary buffer (what
    fit_host_allocator decides on)."""
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


_THREADS_PROBE = r"""
import hashlib, sys
import jax, jax.numpy as jnp, numpy as np
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn import native
from jaxdeform.nn.graph_conv import (ae_decode, ae_encode, init_ae_block, masked_blocks_error, mesh_conv,
                                     rings_from_topology)
n = 48  # 2304 vertices: 36 tiles of 64, cut into several chunks by every kernel
rings = rings_from_topology(build_topology(grid_faces(n), n * n))  # grid_faces: this test module's, prepended
assert native.available()
p = jax.vmap(lambda k: init_ae_block(k, n * n, 4, jnp.float32))(jax.random.split(jax.random.PRNGKey(0), 3))
x = jax.random.uniform(jax.random.PRNGKey(1), (3, 5, n * n, 9), jnp.float32, -0.9, 0.9)
def loss(p, x):
    z = jax.vmap(lambda q, xx: ae_encode(q, xx, rings))(p, x)
    xh = jax.vmap(lambda q, zz: ae_decode(q, zz, rings))(p, z)
    y = jax.vmap(lambda q, xx: mesh_conv(q["conv_enc"], xx, *rings))(p, x)
    q = jax.tree_util.tree_map(lambda a: a[None], p)  # one parent, 3 children on masked inputs
    zm, xm, em = masked_blocks_error(q, x[:1], jnp.abs(x[None, :, 0, :, 0]), rings)
    return (jnp.sum(jnp.sin(3 * xh) * x) + jnp.sum(jnp.cos(z)) + jnp.sum(y * y) + jnp.sum(em)
            + jnp.sum(jnp.cos(zm)) + jnp.sum(jnp.sin(xm)))
val, grads = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(p, x)
h = hashlib.sha256(np.asarray(val).tobytes())
for leaf in jax.tree_util.tree_leaves(grads):
    h.update(np.asarray(leaf).tobytes())
print(h.hexdigest())
"""


def test_native_results_do_not_depend_on_the_thread_count():
    """The kernels cut their work into chunks fixed by the sizes and add per-chunk partial sums in chunk order:
    the loss and every gradient of the fused block halves and of the convolution are the same bit for bit with
    JAXDEFORM_NATIVE_THREADS 1, 2 and 3 (threads in all: at most as many as XLA's pool has, so 3 runs as 2 on a
    two-core machine)."""
    from jaxdeform.nn import native

    if not native.available():
        pytest.skip("native kernels unavailable here (no C++ compiler or not on CPU)")
    probe = "import numpy as np\n" + inspect.getsource(grid_faces) + _THREADS_PROBE
    digests = {}
    for threads in ("1", "2", "3"):
        proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True,
                              env={**os.environ, "JAXDEFORM_NATIVE_THREADS": threads})
        digests[threads] = proc.stdout.strip()
    assert len(digests["1"]) == 64 and len(set(digests.values())) == 1, digests


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_decoder_error_matches_the_squared_difference(dtype):
    """ae_forward_error's per-shape error (summed inside the native decoder on CPU) and its adjoint agree with
    the plain sum of (x_hat - x)^2 through the pure-JAX layers: the loss and the gradients of x and of every
    parameter, three vmapped blocks of 7 shapes on 361 vertices (a last group of 1 vertex past a whole tile, whose
    lanes beyond the mesh must not count), with x_hat also used outside the error."""
    from jaxdeform.nn.graph_conv import ae_decode_reference, ae_encode_reference

    n = 19
    rings = rings_from_topology(build_topology(grid_faces(n), n * n))
    p = jax.vmap(lambda k: init_ae_block(k, n * n, 4, dtype))(jax.random.split(jax.random.PRNGKey(0), 3))
    x = jax.random.uniform(jax.random.PRNGKey(1), (3, 7, n * n, 9), dtype, -0.9, 0.9)

    def reference(q, xx):
        z = ae_encode_reference(q, xx, rings)
        xh = ae_decode_reference(q, z, rings)
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


@pytest.mark.parametrize("mask, d", [("step", 0.4), ("linear", (0.2, 0.4))])
def test_group_sparsity_gradient_in_closed_form(mask, d):
    """group_sparsity_gradient's value is Omega(C) and w C (w per vertex row) is autodiff's gradient of Omega,
    zero rows (zero gradient) included."""
    dist = jnp.asarray(grid_dist(4))
    C = np.random.default_rng(3).normal(size=(3, 16, 9))
    C[1, 4:9] = 0.0
    C[2, 0] = 0.0
    Cf = jnp.asarray(C.reshape(3, -1))
    value, w = jax.jit(lambda c: group_sparsity_gradient(c, dist, d, mask))(Cf)
    want = jax.jit(jax.value_and_grad(lambda c: raw_group_sparsity(c, dist, d, mask)))(Cf)
    assert w.shape == (3, 16) and float(value) == pytest.approx(float(want[0]), rel=1e-13)
    got = (np.asarray(w)[..., None] * C).reshape(3, -1)
    np.testing.assert_allclose(got, np.asarray(want[1]), rtol=1e-12, atol=1e-15)
    assert np.all(np.asarray(w)[1, 4:9] == 0.0) and np.asarray(w)[1].max() > 0
    # no gradient flows through the value (the optimizer adds w C itself)
    assert float(jnp.max(jnp.abs(jax.grad(lambda c: group_sparsity_gradient(c, dist, d, mask)[0])(Cf)))) == 0.0


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("rows", [True, False])
def test_native_adam_is_optax_adam(dtype, rows):
    """native.adam_update (in place, one pass) gives optax.adam's new parameters and moments over several steps
    of a decaying rate, for a gradient given as two parts plus the row term w C (rows of 9), or as one array."""
    import optax

    from jaxdeform.nn import native

    if not native.available():
        pytest.skip("native kernels unavailable here (no C++ compiler or not on CPU)")
    shape = (3, 2, 9 * 13)
    keys = jax.random.split(jax.random.PRNGKey(4), 8)
    p0 = jax.random.normal(keys[0], shape, dtype)
    rate = optax.exponential_decay(1e-2, 3, 0.5)
    opt = optax.adam(rate)
    ref_p, ref_state = p0, opt.init(p0)
    p, mu, nu = jnp.copy(p0), jnp.zeros(shape, dtype), jnp.zeros(shape, dtype)

    @jax.jit
    def fused(p, mu, nu, parts, w, t):
        scalars = jnp.stack([0.9, 0.999, 1 - 0.9 ** t, 1 - 0.999 ** t, 1e-8, -rate(t - 1)]).astype(dtype)
        return native.adam_update(p, mu, nu, parts, scalars, w)

    for t in range(1, 6):
        parts = (jax.random.normal(keys[t], shape, dtype), jax.random.normal(keys[t + 1], shape, dtype))
        w = jnp.abs(jax.random.normal(keys[7 - t], shape[:-1] + (13,), dtype)) if rows else None
        grad = parts[0] + parts[1] if rows else parts[0]
        if rows:
            grad = grad + (w[..., None] * ref_p.reshape(shape[:-1] + (13, 9))).reshape(shape)
        updates, ref_state = opt.update(grad, ref_state, ref_p)
        ref_p = optax.apply_updates(ref_p, updates)
        p, mu, nu = fused(p, mu, nu, parts if rows else parts[:1], w, jnp.int32(t))  # int32: optax's count
    tol = 5e-5 if dtype == jnp.float32 else 1e-14  # float32: the parts are added in another order than XLA
    for got, want in ((p, ref_p), (mu, ref_state[0].mu), (nu, ref_state[0].nu)):
        assert got.dtype == dtype
        assert float(jnp.max(jnp.abs(got - want))) <= tol * float(jnp.max(jnp.abs(want)))
    with pytest.raises(Exception, match="not shaped like the parameter"):
        native.adam_update(p, mu, nu, (p[..., :9],), jnp.ones(6, dtype))
    with pytest.raises(Exception, match="rows of at most 64"):
        native.adam_update(p, mu, nu, (p,), jnp.ones(6, dtype), jnp.ones((1,), dtype))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_masked_blocks_match_the_blocks_on_their_inputs(dtype):
    """masked_blocks_error (on CPU: the native kernels on x and the masks, never the children's inputs) gives the
    values and gradients of the vmapped blocks (ae_forward_error) run on the formed inputs am[j, m] x[j], with
    their own decoder C: 2 parents x 3 children, 4 shapes, 361 vertices (a partial last group of vertices)."""
    from jaxdeform.nn.graph_conv import masked_blocks_error

    n = 19
    rings = rings_from_topology(build_topology(grid_faces(n), n * n))
    keys = jax.random.split(jax.random.PRNGKey(0), 6).reshape(2, 3, -1)
    p = jax.vmap(jax.vmap(lambda k: init_ae_block(k, n * n, 5, dtype)))(keys)
    c_dec = p["C"] * 1.0
    x = jax.random.uniform(jax.random.PRNGKey(1), (2, 4, n * n, 9), dtype, -0.9, 0.9)
    am = jax.random.uniform(jax.random.PRNGKey(2), (2, 3, n * n), dtype)

    def formed(p, c_dec, x):
        inputs = am[..., None, :, None] * x[:, None]
        return jax.vmap(jax.vmap(lambda q, c, xin: ae_forward_error(q, xin, rings, "linear", c)))(p, c_dec, inputs)

    def make(blocks):
        def loss(p, c_dec, x):
            z, xh, err = blocks(p, c_dec, x)
            return jnp.sum(err * jnp.arange(1, 5)) + 0.3 * jnp.sum(jnp.sin(xh)) + jnp.sum(jnp.cos(z))
        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))

    (v1, g1) = make(lambda p, c, x: masked_blocks_error(p, x, am, rings, c))(p, c_dec, x)
    (v2, g2) = make(formed)(p, c_dec, x)
    tol = 2e-6 if dtype == jnp.float32 else 1e-13
    assert abs(float(v1 - v2)) <= tol * abs(float(v2))
    for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g2)):
        assert float(jnp.max(jnp.abs(a - b))) <= tol * float(jnp.max(jnp.abs(b)))


def test_masked_blocks_jacobian_under_vmap():
    """jax.jacrev of masked_blocks_error (its adjoint mapped over the cotangents: the native calls then run once per
    element) equals that of the blocks on the formed inputs, for x and a block's C."""
    from jaxdeform.nn.graph_conv import masked_blocks_error

    n = 5
    rings = rings_from_topology(build_topology(grid_faces(n), n * n))
    p = jax.vmap(jax.vmap(lambda k: init_ae_block(k, n * n, 3, jnp.float64)))(
        jax.random.split(jax.random.PRNGKey(3), 4).reshape(1, 4, -1))
    x = jax.random.uniform(jax.random.PRNGKey(4), (1, 2, n * n, 9), jnp.float64, -0.9, 0.9)
    am = jax.random.uniform(jax.random.PRNGKey(5), (1, 4, n * n), jnp.float64)

    def masked(x, c):
        z, xh, err = masked_blocks_error(dict(p, C=c), x, am, rings)
        return jnp.concatenate([err.ravel(), xh[..., :3, :].ravel()])

    def formed(x, c):
        inputs = am[..., None, :, None] * x[:, None]
        z, xh, err = jax.vmap(jax.vmap(lambda q, xin: ae_forward_error(q, xin, rings)))(dict(p, C=c), inputs)
        return jnp.concatenate([err.ravel(), xh[..., :3, :].ravel()])

    got = jax.jit(jax.jacrev(masked, argnums=(0, 1)))(x, p["C"])
    want = jax.jit(jax.jacrev(formed, argnums=(0, 1)))(x, p["C"])
    for a, b in zip(got, want):
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-12 * float(jnp.max(jnp.abs(b)))
