"""Seed 000 multiscale model: attention masks, the level structure, and training on a tiny synthetic set."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import grid_mesh

from jaxdeform.components import model, train
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import AEBlock, ae_decode, ae_encode, rings_from_topology


def _grid(n=6):
    pts, faces = grid_mesh(n)
    dist = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    return pts, faces, dist / dist.max()


def _features(pts, n_shapes=24, seed=0):
    """Smooth bumps of random amplitude at two places: features (N, V, 9) within [-0.9, 0.9]."""
    rng = np.random.default_rng(seed)
    bumps = np.stack([np.exp(-20 * np.sum((pts - c) ** 2, axis=1)) for c in ([0.25, 0.25, 0], [0.75, 0.7, 0])])
    amp = rng.uniform(-1, 1, size=(n_shapes, 2))
    pattern = rng.uniform(-1, 1, size=(2, 9))
    return 0.9 * np.tanh(np.einsum("nk,kv,kc->nvc", amp, bumps, pattern))


@pytest.fixture(scope="module")
def setup():
    pts, faces, dist = _grid()
    rings = rings_from_topology(build_topology(faces, len(pts)))
    return pts, rings, jnp.asarray(dist), jnp.asarray(_features(pts))


def test_attention_masks_sum_to_one():
    c = jnp.asarray(np.random.default_rng(1).normal(size=(4, 9 * 7)))
    am = np.asarray(model.attention_masks(c))
    assert am.shape == (4, 7) and np.all(am >= 0)
    np.testing.assert_allclose(am.sum(axis=0), 1.0, rtol=1e-12)
    # a vertex where only component 2 is non-zero belongs to it entirely
    c2 = np.zeros((4, 7, 9))
    c2[2, 3] = 1.0
    c2[:, :3] = 1.0
    assert np.asarray(model.attention_masks(jnp.asarray(c2.reshape(4, -1))))[2, 3] == pytest.approx(1.0)


def _block(p, x, rings, latent):
    """(z, x_hat) of one block by hand: encode, the latent activation, decode."""
    z = ae_encode(p, x, rings)
    z = jnp.tanh(z) if latent == "tanh" else z
    return z, ae_decode(p, z, rings)


@pytest.mark.parametrize(
    "kz, attention, latent",
    [
        ((3, 2), True, "linear"),
        ((3, 2), False, "linear"),
        ((4,), True, "linear"),
        ((2, 2, 2), True, "linear"),
        ((3, 2), True, "tanh"),
        ((3, 2), False, "tanh"),
    ],
)
def test_levels_structure_and_residual_split(setup, kz, attention, latent):
    pts, rings, dist, x = setup
    config = model.Config(kz=kz, d=tuple(0.4 / 2**i for i in range(len(kz))), attention=attention, latent=latent)
    params = model.Model(len(pts), config, key=jax.random.PRNGKey(0), dtype=x.dtype)
    batch = x[:5]
    out = jax.jit(lambda p, b: model.forward_levels(tuple(p.levels), b, rings, dist, config))(params, batch)
    assert [z.shape for z in out.latents] == [(config.blocks(l), 5, k) for l, k in enumerate(kz)]
    # by hand: level 0, then the children's inputs (attention-weighted residuals) and outputs
    p0 = jax.tree_util.tree_map(lambda a: a[0], params.levels[0])
    z0, xh0 = _block(p0, batch, rings, latent)
    np.testing.assert_allclose(np.asarray(out.latents[0][0]), np.asarray(z0), atol=1e-12)
    if latent == "tanh":
        assert all(float(jnp.max(jnp.abs(z))) < 1.0 for z in out.latents)
    expected = xh0
    if len(kz) > 1:
        res = batch - xh0
        am = model.attention_masks(p0.C[...]) if attention else jnp.ones((kz[0], len(pts)))
        inputs = am[:, None, :, None] * res[None]
        if attention:
            np.testing.assert_allclose(np.asarray(inputs.sum(axis=0)), np.asarray(res), atol=1e-12)
        if len(kz) == 2:
            for k in range(kz[0]):
                pk = jax.tree_util.tree_map(lambda a: a[k], params.levels[1])
                expected = expected + _block(pk, inputs[k], rings, latent)[1]
            np.testing.assert_allclose(np.asarray(out.reconstruction), np.asarray(expected), atol=1e-10)
    else:
        np.testing.assert_allclose(np.asarray(out.reconstruction), np.asarray(xh0), atol=1e-12)
    assert np.isfinite(float(out.loss))


def test_config_refuses_an_unknown_latent_activation():
    with pytest.raises(ValueError, match="latent"):
        model.Config(latent="relu")


def test_training_reduces_the_loss_and_is_deterministic(setup):
    pts, rings, dist, x = setup
    config = model.Config(kz=(3, 2), d=(0.5, 0.3))
    tc = train.TrainConfig(epochs=300, batch=16, seed=3)
    p1, h1 = train.train(x, rings, dist, config, tc)
    _, h2 = train.train(x, rings, dist, config, tc)
    np.testing.assert_array_equal(h1, h2)
    assert h1[-20:].mean() < 0.5 * h1[:5].mean()
    rec = np.asarray(train.reconstruct(p1, x, rings))
    before = np.sum(np.asarray(x) ** 2)
    assert np.sum((rec - np.asarray(x)) ** 2) < 0.3 * before


@pytest.mark.parametrize("kz", [(3, 2), (2, 2, 2)])
def test_decode_latents_reproduces_the_forward_reconstruction(setup, kz):
    pts, rings, dist, x = setup
    config = model.Config(kz=kz, d=tuple(0.4 / 2**i for i in range(len(kz))))
    params = model.Model(len(pts), config, key=jax.random.PRNGKey(1), dtype=x.dtype)
    out = model.forward_levels(tuple(params.levels), x[:4], rings, dist, config)
    again = params.decode_latents(out.latents, rings)
    np.testing.assert_allclose(np.asarray(again), np.asarray(out.reconstruction), atol=1e-12)


@pytest.mark.parametrize("joint", [True, False])
def test_resumed_training_is_bit_identical(setup, tmp_path, joint):
    pts, rings, dist, x = setup
    config = model.Config(kz=(3, 2), d=(0.5, 0.3))
    tc = train.TrainConfig(epochs=40, batch=16, seed=5, joint=joint)
    p_full, h_full = train.train(x, rings, dist, config, tc)
    # an interrupted run: the first 20 (joint) or 60 (separate: stage 1 half done) epochs, checkpointed
    cut = 20 if joint else 60
    stop = dataclasses.replace(tc, epochs=tc.epochs)
    ck = tmp_path / "ckpt"
    with pytest.raises(_Interrupt):
        train.train(
            x,
            rings,
            dist,
            config,
            stop,
            checkpoint_dir=ck,
            checkpoint_every=10,
            log=_interrupt_after(cut - 1),
            log_every=1,
        )
    p_res, h_res = train.train(x, rings, dist, config, tc, checkpoint_dir=ck, checkpoint_every=10, resume=True)
    for a, b in zip(jax.tree_util.tree_leaves(p_full), jax.tree_util.tree_leaves(p_res)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(h_full, h_res)


@pytest.mark.parametrize("joint", [True, False])
def test_loss_history_is_every_step_loss_in_order(setup, tmp_path, joint):
    # the history reaches the host in pieces (at each checkpoint, 7 epochs apart here, and at the end of each
    # stage): it must hold each epoch's loss at its epoch, as the per-step log saw it
    pts, rings, dist, x = setup
    config = model.Config(kz=(3, 2), d=(0.5, 0.3))
    tc = train.TrainConfig(epochs=30, batch=16, seed=2, joint=joint)
    logged = {}
    _, h_ck = train.train(
        x,
        rings,
        dist,
        config,
        tc,
        checkpoint_dir=tmp_path / "ck",
        checkpoint_every=7,
        log=lambda e, loss, terms: logged.__setitem__(e, loss),
        log_every=1,
    )
    _, h_plain = train.train(x, rings, dist, config, tc)
    n = tc.epochs * (1 if joint else config.levels)
    assert h_ck.shape == (n,) and sorted(logged) == list(range(n))
    np.testing.assert_array_equal(h_ck, np.array([logged[e] for e in range(n)], np.float32))
    np.testing.assert_array_equal(h_ck, h_plain)


class _Interrupt(Exception):
    pass


def _interrupt_after(epoch):
    def log(e, loss, terms):
        if e >= epoch:
            raise _Interrupt()

    return log


def test_separate_training_freezes_earlier_levels(setup):
    pts, rings, dist, x = setup
    config = model.Config(kz=(3, 2), d=(0.5, 0.3))
    tc = train.TrainConfig(epochs=30, batch=16, seed=2, joint=False)
    params, hist = train.train(x, rings, dist, config, tc)
    assert hist.shape == (60,) and np.all(np.isfinite(hist))
    # level 0 after both stages equals level 0 trained alone (stage 1 does not touch it)
    alone, _ = train.train(x, rings, dist, model.Config(kz=(3,), d=(0.5,)), dataclasses.replace(tc, joint=True))
    for a, b in zip(jax.tree_util.tree_leaves(params.levels[0]), jax.tree_util.tree_leaves(alone.levels[0])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_attention_gradient_switch(setup):
    """With ``attention_gradient`` off, the children's losses reach the parent's C only through the residual;
    on, also through the masks: the gradients of the level-1 loss with respect to C0 are finite and differ."""
    _, rings, dist, x = setup
    grads = []
    for attention_gradient in (False, True):
        cfg = model.Config(kz=(3, 2), d=(0.4, 0.2), attention_gradient=attention_gradient)
        params = model.Model(x.shape[1], cfg, key=jax.random.PRNGKey(7), dtype=x.dtype)

        def level1_loss(c0, params=params, cfg=cfg):
            level0 = AEBlock(params.levels[0].conv_enc, params.levels[0].conv_dec, c0)
            p = (level0,) + tuple(params.levels[1:])
            return sum(model.forward_levels(p, x, rings, dist, cfg).terms[1].values())

        grads.append(np.asarray(jax.grad(level1_loss)(params.levels[0].C[...])))
    assert all(np.all(np.isfinite(g)) for g in grads)
    assert not np.allclose(grads[0], grads[1])


def test_loss_weights_scale_their_terms(setup):
    """The total loss is sum over blocks of lambda_recon L_recon + lambda_sparse Omega + lambda_latent V(Z)."""
    _, rings, dist, x = setup
    base = model.Config(kz=(3, 2), d=(0.4, 0.2), theta=0.01)  # tiny theta: V(Z) is non-zero
    params = model.Model(x.shape[1], base, key=jax.random.PRNGKey(3), dtype=x.dtype)
    out = model.forward_levels(tuple(params.levels), x, rings, dist, base)
    sums = {k: float(sum(t[k] for t in out.terms)) for k in ("recon", "sparsity", "latent")}
    assert sums["latent"] > 0
    weights = dict(lambda_recon=1.0, lambda_sparse=0.5, lambda_latent=0.25)
    got = float(model.forward_levels(tuple(params.levels), x, rings, dist, dataclasses.replace(base, **weights)).loss)
    want = sums["recon"] + 0.5 * sums["sparsity"] + 0.25 * sums["latent"]
    assert got == pytest.approx(want, rel=1e-5)


def test_mean_reconstruction_divides_the_recon_term_by_the_feature_entries(setup):
    """recon="mean": L_recon averaged over the 9 V entries too; the other terms and the outputs unchanged."""
    _, rings, dist, x = setup
    base = model.Config(kz=(3, 2), d=(0.4, 0.2), theta=0.01)
    m = model.Model(x.shape[1], base, key=jax.random.PRNGKey(4), dtype=x.dtype)
    summed = model.forward_levels(tuple(m.levels), x, rings, dist, base)
    mean = model.forward_levels(tuple(m.levels), x, rings, dist, dataclasses.replace(base, recon="mean"))
    entries = x.shape[1] * x.shape[2]
    for a, b in zip(summed.terms, mean.terms):
        assert float(b["recon"]) == pytest.approx(float(a["recon"]) / entries, rel=1e-6)
        assert float(b["sparsity"]) == float(a["sparsity"]) and float(b["latent"]) == float(a["latent"])
    drop = base.lambda_recon * sum(float(t["recon"]) for t in summed.terms) * (1 - 1 / entries)
    assert float(summed.loss) - float(mean.loss) == pytest.approx(drop, rel=1e-5)
    assert np.array_equal(np.asarray(summed.reconstruction), np.asarray(mean.reconstruction))
    with pytest.raises(ValueError, match="recon must be"):
        model.Config(recon="max")


def test_learning_rate_schedule_and_gradient_clipping():
    """The default rate decays exponentially from 1e-3 to 1e-4 over the 10,000 epochs; with ``clip_norm`` every
    step's gradient is scaled to that global norm before Adam sees it (a spike moves Adam's moments no more
    than an ordinary step)."""
    tc = train.TrainConfig()
    rate = train.schedule(tc)
    assert float(rate(0)) == pytest.approx(1e-3)
    assert float(rate(tc.epochs)) == pytest.approx(1e-4, rel=1e-4)
    assert float(rate(tc.epochs // 2)) == pytest.approx(1e-3 * 0.1**0.5, rel=1e-4)  # exponential, not linear

    params = {"w": jnp.arange(1.0, 5.0)}
    grads = [{"w": jnp.array([0.3, -0.1, 0.2, 0.05])}, {"w": jnp.array([400.0, 900.0, -100.0, 50.0])}]
    clipped_tc = dataclasses.replace(tc, clip_norm=0.5)
    opt, plain = train.optimizer(clipped_tc), train.optimizer(tc)
    s_opt, s_plain = opt.init(params), plain.init(params)
    for g in grads:
        u_opt, s_opt = opt.update(g, s_opt, params)
        norm = float(jnp.linalg.norm(g["w"]))
        scaled = {"w": g["w"] * min(1.0, 0.5 / norm)}
        u_ref, s_plain = plain.update(scaled, s_plain, params)
        np.testing.assert_allclose(np.asarray(u_opt["w"]), np.asarray(u_ref["w"]), rtol=1e-6)
    # without clipping the spike's update differs (Adam is not invariant to a change of scale between steps)
    s_p = plain.init(params)
    for g in grads:
        u_unclipped, s_p = plain.update(g, s_p, params)
    assert not np.allclose(np.asarray(u_unclipped["w"]), np.asarray(u_opt["w"]), rtol=1e-3)


@pytest.mark.parametrize("bad", [{"decay_rate": 0.0}, {"decay_rate": 1.5}, {"clip_norm": 0.0}, {"clip_norm": -1.0}])
def test_train_config_refuses_a_bad_rate_or_clip(bad):
    with pytest.raises(ValueError):
        train.TrainConfig(**bad)


def test_model_forward_mode_and_second_order(setup):
    """Through a seed-000 model (two levels, attention): jax.jvp of the reconstruction loss and of the
    reconstruction matches central differences in float64, jax.jacfwd of the latent codes equals jax.jacrev's,
    and grad-of-grad of the loss gives H v as central differences of the gradient. The attention masks take
    their gradient here (``attention_gradient``), so that the derivatives are those of the function itself."""
    _, rings, dist, x = setup
    config = model.Config(kz=(3, 2), d=(0.5, 0.3), attention_gradient=True)
    params = model.Model(x.shape[1], config, key=jax.random.PRNGKey(5), dtype=jnp.float64)
    x = x.astype(jnp.float64)

    def random_like(tree, seed):
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
        return treedef.unflatten([jax.random.normal(k, a.shape, a.dtype) for k, a in zip(keys, leaves)])

    def central(f, a, v, h=1e-5):
        plus = f(jax.tree_util.tree_map(lambda p, t: p + h * t, a, v))
        minus = f(jax.tree_util.tree_map(lambda p, t: p - h * t, a, v))
        return jax.tree_util.tree_map(lambda p, m: (p - m) / (2 * h), plus, minus)

    def close(got, want, rtol):  # relative to the largest entry of want
        want = [np.asarray(b) for b in jax.tree_util.tree_leaves(want)]
        scale = max(float(np.max(np.abs(b))) for b in want)
        for a, b in zip(jax.tree_util.tree_leaves(got), want):
            assert np.all(np.isfinite(np.asarray(a))) and np.max(np.abs(np.asarray(a) - b)) <= rtol * scale

    def outputs(a):  # smooth in the parameters and the input (the sparsity centres are piecewise constant)
        p, xx = a
        out = model.forward_levels(tuple(p.levels), xx, rings, dist, config)
        return sum(out.terms[level]["recon"] for level in range(config.levels)), out.reconstruction

    v = random_like((params, x), 6)
    _, tangent = jax.jit(lambda a, t: jax.jvp(outputs, (a,), (t,)))((params, x), v)
    close(tangent, central(jax.jit(outputs), (params, x), v), 1e-6)

    codes = lambda xx: params.encode(xx, rings)  # noqa: E731
    close(jax.jit(jax.jacfwd(codes))(x[:2]), jax.jit(jax.jacrev(codes))(x[:2]), 1e-10)

    loss = lambda a: outputs(a)[0]  # noqa: E731
    grad = jax.grad(loss)
    hv = jax.jit(
        jax.grad(
            lambda a: sum(
                jnp.vdot(g, t) for g, t in zip(jax.tree_util.tree_leaves(grad(a)), jax.tree_util.tree_leaves(v))
            )
        )
    )((params, x))
    close(hv, central(jax.jit(grad), (params, x), v), 1e-6)
