"""DeformTransformer (seed 002): transformer pieces, model kinds, training windows, training, synthesis, files."""

import dataclasses
import shutil

import igl
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import grid_mesh
from flax import nnx

from jaxdeform.cloth.model import ModelConfig, new_model
from jaxdeform.cloth.train import (
    TRACE_COUNT,
    TrainConfig,
    gather_windows,
    load_model,
    predict_windows,
    save_model,
    self_fed_inputs,
    self_feed_probability,
    synthesize,
    train,
    windows,
)
from jaxdeform.errors import JaxDeformError
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.transformer import MultiHeadAttention, Transformer, sinusoidal_encoding

# small widths keep compilation short; the structure (8 heads, 2 + 2 blocks, W = 3) is the paper's
SMALL = dict(d_model=32, ffn=64)
KINDS = ("transformer", "lstm", "none")


@pytest.fixture(scope="module")
def meshes():
    vc, fc = grid_mesh(4)
    vf, ff = igl.loop(vc, fc.astype(np.int64))
    return build_topology(fc, len(vc)), build_topology(np.asarray(ff), len(vf))


def _random_windows(key, b, w, vc, vf, c):
    k1, k2 = jax.random.split(key)
    return (
        jax.random.uniform(k1, (b, w, vc, c), minval=-0.9, maxval=0.9),
        jax.random.uniform(k2, (b, w, vf, c), minval=-0.9, maxval=0.9),
    )


# ------------------------------------------------------------------------------------------ transformer


def test_sinusoidal_encoding_formula():
    length, d = 7, 10
    pe = np.asarray(sinusoidal_encoding(length, d))
    for p in range(length):
        for i in range(d // 2):
            w = 1.0 / 10000.0 ** (2 * i / d)
            assert pe[p, 2 * i] == pytest.approx(np.sin(p * w), abs=1e-6)
            assert pe[p, 2 * i + 1] == pytest.approx(np.cos(p * w), abs=1e-6)
    # position 0 is (0, 1, 0, 1, ...) and every (sin, cos) pair has unit norm
    np.testing.assert_allclose(pe[0], np.tile([0.0, 1.0], d // 2), atol=1e-7)
    np.testing.assert_allclose(pe[:, 0::2] ** 2 + pe[:, 1::2] ** 2, 1.0, atol=1e-6)


def test_attention_matches_single_head_formula():
    """With one head, MHA = softmax(QK^T/sqrt(d)) V W_o + b_o, written out by hand."""
    att = MultiHeadAttention(8, heads=1, rngs=nnx.Rngs(0))
    xq, xkv = jax.random.normal(jax.random.PRNGKey(1), (2, 5, 8)), jax.random.normal(jax.random.PRNGKey(2), (2, 4, 8))
    q, k, v = att.q(xq), att.k(xkv), att.v(xkv)
    a = jax.nn.softmax(jnp.einsum("bqd,bkd->bqk", q, k) / np.sqrt(8), axis=-1)
    np.testing.assert_allclose(nnx.jit(lambda m, x, y: m(x, y))(att, xq, xkv), att.o(a @ v), atol=1e-5)


def test_transformer_decoder_is_causal_and_reads_all_source_frames():
    tr = Transformer(16, heads=8, blocks=2, ffn=32, rngs=nnx.Rngs(0))
    src = jax.random.normal(jax.random.PRNGKey(0), (2, 3, 16))
    tgt = jax.random.normal(jax.random.PRNGKey(1), (2, 4, 16))
    run = nnx.jit(lambda m, s, t: m(s, t))
    out = run(tr, src, tgt)
    changed = run(tr, src, tgt.at[:, 2].add(1.0))
    np.testing.assert_allclose(out[:, :2], changed[:, :2], atol=1e-6)
    assert float(jnp.max(jnp.abs(out[:, 2:] - changed[:, 2:]))) > 1e-3
    # every decoder position reads the whole source
    changed_src = run(tr, src.at[:, 2].add(1.0), tgt)
    assert float(jnp.min(jnp.max(jnp.abs(out - changed_src), axis=-1))) > 1e-4


# --------------------------------------------------------------------------------------------- model


@pytest.mark.parametrize("kind,channels", [("transformer", 9), ("lstm", 9), ("none", 9), ("none", 3)])
def test_shapes_and_causality(meshes, kind, channels):
    """Shapes of every kind; changing the fine input at window position k leaves the outputs before k
    unchanged and changes position k (the no-temporal model ignores it and is frame-wise)."""
    tc, tf = meshes
    model = new_model(tc, tf, ModelConfig(kind=kind, in_channels=channels, **SMALL))
    cw, fw = _random_windows(jax.random.PRNGKey(1), 1, 3, tc.n_vertices, tf.n_vertices, channels)
    out = predict_windows(model, cw, fw)
    assert out.shape == (1, 3, tf.n_vertices, channels)
    assert bool(jnp.all(jnp.abs(out) < 1.0))  # tanh output, like features scaled to [-0.95, 0.95]
    for k in (1, 2):
        changed = predict_windows(model, cw, fw.at[:, k].set(-fw[:, k]))
        np.testing.assert_allclose(out[:, :k], changed[:, :k], atol=1e-6)
        if kind == "none":
            np.testing.assert_allclose(out, changed, atol=1e-6)
        else:
            assert float(jnp.max(jnp.abs(out[:, k] - changed[:, k]))) > 1e-5
    if kind == "none":  # frame-wise: a frame's output does not depend on the other coarse frames
        changed = predict_windows(model, cw.at[:, 0].set(-cw[:, 0]), fw)
        np.testing.assert_allclose(out[:, 1:], changed[:, 1:], atol=1e-6)
        with pytest.raises(ValueError, match="previous fine"):
            predict_windows(new_model(tc, tf, ModelConfig(**SMALL)), cw)


def test_config_validation():
    with pytest.raises(ValueError, match="kind"):
        ModelConfig(kind="gru")
    with pytest.raises(ValueError, match="divisible"):
        ModelConfig(d_model=20)
    with pytest.raises(ValueError, match="steps"):
        TrainConfig(steps=0)


# ------------------------------------------------------------------------------------------- windows


def test_windows_stay_inside_sequences_and_shift_fine_by_one():
    """Frame values encode (sequence, frame): every window is consecutive frames of one sequence, the fine
    input is the target shifted by one with zeros before frame 0."""
    lengths = [5, 2, 4]  # the 2-frame sequence is too short for W = 3

    def seq(i, t, v):
        vals = 100.0 * (i + 1) + np.arange(t, dtype=np.float32)
        return np.broadcast_to(vals[:, None, None], (t, v, 2)).copy()

    cs = [seq(i, t, 3) for i, t in enumerate(lengths)]
    fs = [-seq(i, t, 5) for i, t in enumerate(lengths)]
    win = windows(cs, fs, 3)
    assert win.count == (5 - 2) + 0 + (4 - 2)
    cw, fp, ft = (np.asarray(a)[:, :, 0, 0] for a in gather_windows(win.coarse, win.fine, win.starts, 3))
    got = set()
    for c, p, f in zip(cw, fp, ft):
        seq_id, first = int(c[0] // 100) - 1, c[0] % 100
        np.testing.assert_array_equal(c, 100.0 * (seq_id + 1) + first + np.arange(3))
        np.testing.assert_array_equal(f, -c)
        expect_prev = np.concatenate([[0.0] if first == 0 else [f[0] + 1.0], f[:-1]])
        np.testing.assert_array_equal(p, expect_prev)
        got.add((seq_id, int(first)))
    assert got == {(0, 0), (0, 1), (0, 2), (2, 0), (2, 1)}
    with pytest.raises(ValueError, match="frames"):
        windows([cs[1]], [fs[1]], 3)
    with pytest.raises(ValueError, match="fine frames"):
        windows([cs[0]], [fs[2]], 3)


# ------------------------------------------------------------------------------- synthesis consistency


def _check_teacher_forcing(model, coarse):
    """Frame t of synthesis = teacher-forced output at its window position, fed the synthesized frames."""
    w = model.config.window
    fine = np.asarray(synthesize(model, coarse))
    assert fine.shape == (coarse.shape[0], model.n_fine, model.config.in_channels) and np.all(np.isfinite(fine))
    prev = np.concatenate([np.zeros_like(fine[:1]), fine[:-1]])  # prev[t] = fine frame t - 1
    for t in range(coarse.shape[0]):
        s = max(t - w + 1, 0)
        out = predict_windows(model, coarse[None, s : s + w], prev[None, s : s + w])
        np.testing.assert_allclose(out[0, t - s], fine[t], atol=2e-5)


@pytest.mark.parametrize("kind", ["lstm", "none"])
def test_teacher_forcing_matches_autoregressive_synthesis(meshes, kind):
    """(The transformer is checked on the trained model, test_synthesis_matches_teacher_forcing_trained.)"""
    tc, tf = meshes
    model = new_model(tc, tf, ModelConfig(kind=kind, **SMALL))
    _check_teacher_forcing(
        model, jax.random.uniform(jax.random.PRNGKey(3), (7, tc.n_vertices, 9), minval=-0.9, maxval=0.9)
    )


@pytest.mark.parametrize("kind", ["transformer", "none"])
def test_skip_model_synthesis_and_file_round_trip(meshes, kind, tmp_path):
    """The decoder's skip input (coarse features interpolated to the fine mesh) keeps teacher forcing and
    autoregressive synthesis identical, and travels with the saved model."""
    from jaxdeform.cloth.evaluate import Upsampler

    tc, tf = meshes
    vc, fc = grid_mesh(4)
    up = Upsampler(fc, len(vc), levels=1).matrix.toarray()
    cfg = ModelConfig(kind=kind, skip=True, **SMALL)
    with pytest.raises(ValueError, match="interpolation matrix"):
        new_model(tc, tf, cfg)
    model = new_model(tc, tf, cfg, up)
    coarse = jax.random.uniform(jax.random.PRNGKey(5), (5, tc.n_vertices, 9), minval=-0.9, maxval=0.9)
    _check_teacher_forcing(model, coarse)
    loaded, _ = load_model(save_model(tmp_path / "m", model))
    assert loaded.config.skip
    np.testing.assert_array_equal(np.asarray(synthesize(loaded, coarse)), np.asarray(synthesize(model, coarse)))


def test_bad_synthesis_input(meshes):
    tc, tf = meshes
    model = new_model(tc, tf, ModelConfig(kind="lstm", **SMALL))
    with pytest.raises(ValueError, match="coarse sequence"):
        synthesize(model, np.zeros((4, 5, 9), np.float32))


@pytest.mark.slow
def test_sequence_shorter_than_window(meshes):
    tc, tf = meshes
    model = new_model(tc, tf, ModelConfig(kind="lstm", **SMALL))
    coarse = jax.random.uniform(jax.random.PRNGKey(4), (2, tc.n_vertices, 9), minval=-0.9, maxval=0.9)
    _check_teacher_forcing(model, coarse)


# ------------------------------------------------------------------------------------------ self-feeding


@pytest.mark.parametrize("kind", ["transformer", "lstm"])
def test_self_fed_inputs_are_the_sequential_unroll(meshes, kind):
    """W - 1 parallel passes of a causal model give each window position the input a frame-by-frame unroll from
    the window's first input would give it (what synthesis feeds), and leave position 0 alone."""
    tc, tf = meshes
    model = new_model(tc, tf, ModelConfig(kind=kind, window=4, **SMALL))
    cw, fp = _random_windows(jax.random.PRNGKey(7), 2, 4, tc.n_vertices, tf.n_vertices, 9)
    fed = np.asarray(self_fed_inputs(model, cw, fp))
    seq = np.asarray(fp).copy()  # seq[:, k] = input of position k, filled one frame at a time
    for k in range(1, 4):
        seq[:, k] = np.asarray(model(cw, jnp.asarray(seq)))[:, k - 1]
    np.testing.assert_array_equal(fed[:, 0], np.asarray(fp)[:, 0])
    np.testing.assert_allclose(fed, seq, atol=2e-5)
    assert not np.allclose(fed[:, 1:], np.asarray(fp)[:, 1:], atol=1e-2)  # the inputs did change
    # no gradient reaches the parameters through the fed inputs
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    g = jax.grad(lambda p: jnp.sum(self_fed_inputs(nnx.merge(graphdef, p, rest), cw, fp)))(params)
    assert all(float(jnp.max(jnp.abs(x))) == 0.0 for x in jax.tree_util.tree_leaves(g))


def test_self_feed_probability_ramp():
    p = [float(self_feed_probability(0.5, jnp.int32(t), 100)) for t in (0, 25, 50, 99)]
    assert p == pytest.approx([0.0, 0.25, 0.5, 0.5])
    with pytest.raises(ValueError, match="probability"):
        TrainConfig(self_feed=1.5)


def test_self_feeding_changes_training_only_where_the_model_reads_fine_frames(meshes):
    tc, tf = meshes
    cs, fs = _paired_data(tc, tf, n_seq=2, t_len=12)
    out = {}
    for kind in ("transformer", "none"):
        for feed in (0.0, 1.0):
            _, h = train(
                ModelConfig(kind=kind, **SMALL),
                TrainConfig(steps=6, batch_size=4, self_feed=feed),
                tc,
                tf,
                cs,
                fs,
                progress=False,
            )
            out[kind, feed] = h.loss
    assert out["transformer", 0.0][0] == out["transformer", 1.0][0]  # p_0 = 0: the first step is teacher-forced
    assert not np.allclose(out["transformer", 0.0][2:], out["transformer", 1.0][2:])
    np.testing.assert_array_equal(out["none", 0.0], out["none", 1.0])  # the per-frame model reads no fine input


# ------------------------------------------------------------------------------------------ training


def _paired_data(tc, tf, n_seq=3, t_len=30, seed=0):
    """Coarse features from 3 latent sinusoids; fine = a fixed linear map of coarse (then tanh)."""
    rng = np.random.default_rng(seed)
    mix_c = rng.normal(size=(3, tc.n_vertices * 9)) / np.sqrt(3)
    lin = rng.normal(size=(tc.n_vertices * 9, tf.n_vertices * 9)) / np.sqrt(tc.n_vertices * 9)
    cs, fs = [], []
    for _ in range(n_seq):
        t = np.arange(t_len)[:, None]
        s = np.sin(rng.uniform(0.1, 0.3, (1, 3)) * t + rng.uniform(0, 2 * np.pi, (1, 3)))
        c = 0.8 * np.tanh(s @ mix_c)
        f = 0.9 * np.tanh(c @ lin)
        cs.append(c.reshape(t_len, tc.n_vertices, 9).astype(np.float32))
        fs.append(f.reshape(t_len, tf.n_vertices, 9).astype(np.float32))
    return cs, fs


@pytest.fixture(scope="module")
def trained(meshes):
    tc, tf = meshes
    cs, fs = _paired_data(tc, tf)
    cfg = ModelConfig(kind="transformer", **SMALL)
    tcfg = TrainConfig(steps=300, batch_size=8, learning_rate=3e-3)
    before = TRACE_COUNT["train_step"]
    model, hist = train(cfg, tcfg, tc, tf, cs, fs, progress=False)
    return dict(model=model, hist=hist, cfg=cfg, tcfg=tcfg, data=(cs, fs), traces=TRACE_COUNT["train_step"] - before)


def test_training_reduces_loss(trained):
    loss = trained["hist"].loss
    assert loss.shape == (300,) and np.all(np.isfinite(loss))
    first, last = loss[:10].mean(), loss[-20:].mean()
    assert last < first / 10, (first, last)
    assert trained["traces"] == 1  # one compilation for the whole run


def test_training_is_deterministic_and_not_retraced(meshes, trained):
    """Same seed -> same losses; a second run of the same structure reuses the compiled step."""
    tc, tf = meshes
    cs, fs = trained["data"]
    before = TRACE_COUNT["train_step"]
    short = dataclasses.replace(trained["tcfg"], steps=5)
    _, h1 = train(trained["cfg"], short, tc, tf, cs, fs, progress=False)
    _, h2 = train(trained["cfg"], short, tc, tf, cs, fs, progress=False)
    assert TRACE_COUNT["train_step"] == before  # same graph and optimiser as the fixture's run: no new trace
    np.testing.assert_array_equal(h1.loss, h2.loss)
    np.testing.assert_allclose(h1.loss, trained["hist"].loss[:5], rtol=1e-5)


def test_synthesis_no_retrace_and_tracks_data(trained):
    model = trained["model"]
    cs, fs = trained["data"]
    before = TRACE_COUNT["synthesize"]
    outs = [np.asarray(synthesize(model, c)) for c in cs]  # equal lengths: one compilation
    assert TRACE_COUNT["synthesize"] - before <= 1
    synthesize(model, cs[0])
    assert TRACE_COUNT["synthesize"] - before <= 1
    # autoregressive output is far closer to the paired fine data than an untrained guess (zero features)
    err = np.mean([(o - f) ** 2 for o, f in zip(outs, fs)])
    base = np.mean([f**2 for f in fs])
    assert err < 0.25 * base, (err, base)


def test_synthesis_matches_teacher_forcing_trained(trained):
    _check_teacher_forcing(trained["model"], jnp.asarray(trained["data"][0][0]))


def test_save_load_round_trip(tmp_path, trained):
    model = trained["model"]
    cs, _ = trained["data"]
    path = save_model(tmp_path / "run" / "model", model, {"dataset": "synthetic", "frames": 30})
    loaded, meta = load_model(path)
    assert meta == {"dataset": "synthetic", "frames": 30}
    assert loaded.config == model.config
    np.testing.assert_array_equal(np.asarray(synthesize(loaded, cs[0])), np.asarray(synthesize(model, cs[0])))
    assert not list(path.parent.glob(".*"))  # no temporary left behind
    assert path.is_dir() and [p.name for p in path.parent.iterdir()] == ["model"]
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(JaxDeformError):
        load_model(bad)
    with pytest.raises(JaxDeformError, match="no such"):
        load_model(tmp_path / "missing")
    damaged = tmp_path / "damaged"
    shutil.copytree(path, damaged)
    for data in (damaged / "arrays" / "d").iterdir():
        data.write_bytes(data.read_bytes()[:10])
    with pytest.raises(JaxDeformError, match="damaged cloth model checkpoint"):
        load_model(damaged)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["lstm", "none"])
def test_ablations_train(meshes, kind):
    tc, tf = meshes
    cs, fs = _paired_data(tc, tf)
    _, hist = train(
        ModelConfig(kind=kind, **SMALL),
        TrainConfig(steps=300, batch_size=8, learning_rate=2e-3),
        tc,
        tf,
        cs,
        fs,
        progress=False,
    )
    assert hist.loss[-20:].mean() < hist.loss[:10].mean() / 5
