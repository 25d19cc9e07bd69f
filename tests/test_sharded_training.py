"""Data-parallel training steps (``mesh=``) equal the single-device steps.

Each test runs a script in a fresh interpreter with four forced host devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=4``); the script asserts and prints ``OK``.
"""

from __future__ import annotations

from fresh_process import run_script as run_fresh


def run_script(code: str, *, x64: bool = True) -> str:
    """Run ``code`` in a fresh interpreter with four host devices and x64 as asked; its stdout."""
    return run_fresh(code, x64=x64, timeout=300, devices=4)


COMPONENTS = """
    import dataclasses
    import numpy as np, jax, jax.numpy as jnp
    from jaxdeform import acap, parallel
    from jaxdeform.components import model, train
    from jaxdeform.data.synthetic import bending_tube_sequence
    from jaxdeform.mesh.topology import build_topology
    from jaxdeform.nn.graph_conv import rings_from_topology

    assert len(jax.devices()) == 4
    dtype = {dtype}
    rtol = {rtol}
    verts, faces = bending_tube_sequence(n_frames=8, n_around=8, n_along=10)
    feats = np.asarray(acap.encode(verts[0], faces, verts))
    data = jnp.asarray(acap.Scaler.fit(feats).transform(feats), dtype)
    rings = rings_from_topology(build_topology(faces, verts.shape[1]))
    rest = verts[0]
    dist = np.linalg.norm(rest[:, None] - rest[None], axis=-1)  # stands in for the geodesics
    dist = jnp.asarray(dist / dist.max(), dtype)
    config = model.Config(kz=(3, 2), d=(0.4, 0.2))
    mesh = parallel.batch_mesh()
    rel = lambda a, b: float(jnp.max(jnp.abs(a - b)) / jnp.maximum(jnp.max(jnp.abs(b)), 1e-300))

    def one_step(tc, stage, m, mesh_):
        states = train.level_states(m)
        sub = states if stage is None else states[: stage + 1]
        opt_state = train._opt_init(tc, sub, stage)
        copy = lambda t: jax.tree_util.tree_map(jnp.copy, t)  # the step donates params and optimizer state
        step = train.make_step(m, tc, rings, dist, stage, mesh=mesh_)
        return step(copy(sub), copy(opt_state), jax.random.PRNGKey(7), data)

    params = model.Model(data.shape[1], config, key=jax.random.PRNGKey(0), dtype=dtype)
    worst = 0.0
    # batch 8 = the whole set every step; batch 4 = 4 of the 8 drawn by the key; stage 1 = separate training
    for batch, stage in ((8, None), (4, None), (8, 1)):
        tc = train.TrainConfig(epochs=1, batch=batch, seed=0, joint=stage is None)
        p1, o1, k1, l1, t1 = one_step(tc, stage, params, None)
        p4, o4, k4, l4, t4 = one_step(tc, stage, params, mesh)
        assert l4.sharding.is_fully_replicated and len(l4.sharding.device_set) == 4
        for leaf in jax.tree_util.tree_leaves(p4):
            assert leaf.sharding.is_fully_replicated and len(leaf.sharding.device_set) == 4
        d_loss = rel(l4, l1)
        d_params = max(rel(a, b) for a, b in zip(jax.tree_util.tree_leaves(p4), jax.tree_util.tree_leaves(p1)))
        d_opt = max(rel(a, b) for a, b in zip(jax.tree_util.tree_leaves(o4), jax.tree_util.tree_leaves(o1)))
        assert np.array_equal(np.asarray(k4), np.asarray(k1))
        assert d_loss < rtol and d_params < rtol and d_opt < rtol, (batch, stage, d_loss, d_params, d_opt)
        worst = max(worst, d_loss, d_params, d_opt)
        print(f"batch {{batch}} stage {{stage}}: loss {{d_loss:.3g}} params {{d_params:.3g}} opt {{d_opt:.3g}}")

    # train() with a mesh: same history and parameters as on one device
    tc = train.TrainConfig(epochs=3, batch=4, seed=1)
    pa, ha = train.train(data, rings, dist, config, tc, model=params)
    pb, hb = train.train(data, rings, dist, config, tc, model=params, mesh=mesh)
    np.testing.assert_allclose(hb, ha, rtol=max(rtol, 1e-6))  # the history is float32
    d_train = max(rel(a, b) for a, b in zip(jax.tree_util.tree_leaves(pb), jax.tree_util.tree_leaves(pa)))
    assert d_train < 10 * rtol, d_train
    print(f"train 3 epochs: params {{d_train:.3g}}")

    # a batch that does not split over the 4 devices is refused
    for bad in (dataclasses.replace(tc, batch=6), dataclasses.replace(tc, batch=10, epochs=1)):
        try:
            train.train(data[:6] if bad.batch == 10 else data, rings, dist, config, bad, model=params, mesh=mesh)
        except ValueError as e:
            assert "split evenly" in str(e), e
        else:
            raise AssertionError("no ValueError for an uneven batch")
    print(f"worst {{worst:.3g}}")
    print("OK")
"""


def test_components_step_on_four_devices_equals_one_device_float64():
    print(run_script(COMPONENTS.format(dtype="jnp.float64", rtol=1e-10)))


def test_components_step_on_four_devices_equals_one_device_float32():
    print(run_script(COMPONENTS.format(dtype="jnp.float32", rtol=1e-5), x64=False))


CLOTH = """
    import dataclasses
    import igl
    import numpy as np, jax, jax.numpy as jnp
    from flax import nnx
    from jaxdeform import parallel
    from jaxdeform.cloth.model import ModelConfig
    from jaxdeform.cloth.train import TrainConfig, train
    from jaxdeform.mesh.topology import build_topology

    assert len(jax.devices()) == 4
    n = 4  # a flat n x n grid (coarse) and its Loop subdivision (fine)
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    vc = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    fc = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    vf, ff = igl.loop(vc, fc.astype(np.int64))
    tc, tf = build_topology(fc, len(vc)), build_topology(np.asarray(ff), len(vf))
    rng = np.random.default_rng(0)
    cs = [rng.uniform(-0.9, 0.9, (10, len(vc), 9)).astype(np.float32) for _ in range(2)]
    fs = [rng.uniform(-0.9, 0.9, (10, len(vf), 9)).astype(np.float32) for _ in range(2)]
    mesh = parallel.batch_mesh()
    rel = lambda a, b: float(jnp.max(jnp.abs(a - b)) / jnp.maximum(jnp.max(jnp.abs(b)), 1e-30))
    cfg = ModelConfig(kind="transformer", d_model=32, ffn=64)
    # float32 Adam: the attention key biases have a structurally zero gradient (softmax is shift invariant), so
    # theirs is round-off, which Adam's g / (|g| + eps) scales towards the learning rate; hence the bound
    # |p4 - p1| <= 1e-5 |p| + 0.05 lr per step besides the relative one of the loss
    worst, worst_abs = 0.0, 0.0
    for steps in (1, 3):
        tcfg = TrainConfig(steps=steps, batch_size=8, seed=2)
        m1, h1 = train(cfg, tcfg, tc, tf, cs, fs, progress=False)
        m4, h4 = train(cfg, tcfg, tc, tf, cs, fs, progress=False, mesh=mesh)
        p1, p4 = (jax.tree_util.tree_leaves(nnx.state(m, nnx.Param)) for m in (m1, m4))
        assert all(x.sharding.is_fully_replicated and len(x.sharding.device_set) == 4 for x in p4)
        d_loss = float(np.max(np.abs(h4.loss - h1.loss) / np.abs(h1.loss)))
        d_abs = max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(p4, p1))
        bad = [float(jnp.max(jnp.abs(x - y))) for x, y in zip(p4, p1)
               if float(jnp.max(jnp.abs(x - y))) > 1e-5 * float(jnp.max(jnp.abs(y))) + 0.05 * tcfg.learning_rate * steps]
        print(f"cloth {{steps}} step(s): loss {{d_loss:.3g}} params max abs {{d_abs:.3g}}")
        assert d_loss < 1e-5 and not bad, (steps, d_loss, bad)
        worst, worst_abs = max(worst, d_loss), max(worst_abs, d_abs)
    try:
        train(cfg, TrainConfig(steps=1, batch_size=6), tc, tf, cs, fs, progress=False, mesh=mesh)
    except ValueError as e:
        assert "split evenly" in str(e), e
    else:
        raise AssertionError("no ValueError for an uneven batch")
    print(f"worst loss {{worst:.3g}} params abs {{worst_abs:.3g}}")
    print("OK")
"""


def test_cloth_step_on_four_devices_equals_one_device():
    print(run_script(CLOTH.format()))
