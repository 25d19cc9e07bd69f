"""The library's promise, checked as a user would: every public ACAP stage under jax.jit, jax.vmap, jax.grad,
jax.jvp and jax.jacfwd, each in a fresh Python process with no eager warm-up call, and no global JAX setting
changed by importing jaxdeform. This file: horse-gallop transforms with finite differences, the solvers.

Each test runs a small script in a subprocess (``fresh_process.run_script``); the script asserts and prints ``OK``.
"""

from __future__ import annotations

import pytest
from conftest import data_dir
from fresh_process import run_script

HORSE_TRANSFORMS = """
    import numpy as np, jax, jax.numpy as jnp
    from jaxdeform import acap
    from jaxdeform.mesh import load_sequence

    verts, faces = load_sequence({data!r})
    frames = jnp.asarray(verts[[0, 12, 30]])
    a = acap.prepare(verts[0], faces, solver={solver!r})
    rng = np.random.default_rng(0)

    # no eager call anywhere before these: each is the first use of its stage in this process
    enc = jax.jit(a.encode)
    feats = enc(frames)
    assert feats.shape == (3, verts.shape[1], 9) and feats.dtype == jnp.float64
    dec = jax.jit(lambda f: a.decode(f))
    pos = dec(feats)
    assert pos.shape == frames.shape
    err = float(jnp.abs(pos - frames).max()) / float(np.ptp(verts[0]))
    assert err < 0.02, err  # the ACAP round trip reproduces the frames

    # vmap over frames equals the batched call
    fv = jax.vmap(a.encode)(frames)
    assert jnp.allclose(fv, feats, atol=1e-9), float(jnp.abs(fv - feats).max())
    pv = jax.vmap(lambda f: a.decode(f))(feats)
    assert jnp.allclose(pv, pos, atol=1e-8), float(jnp.abs(pv - pos).max())

    def check(name, fn, x, h, fd_fn=None):
        # directional derivative d, cotangent w: <grad, d> and <w, jvp> against central differences
        d = jnp.asarray(rng.normal(size=x.shape))
        y, jv = jax.jvp(fn, (x,), (d,))
        w = jnp.asarray(rng.normal(size=y.shape))
        g = jax.grad(lambda z: jnp.vdot(fn(z), w))(x)
        f2 = fn if fd_fn is None else fd_fn
        fd = (jnp.vdot(f2(x + h * d), w) - jnp.vdot(f2(x - h * d), w)) / (2 * h)
        for got in (jnp.vdot(g, d), jnp.vdot(jv, w)):
            rel = abs(float(got) - float(fd)) / abs(float(fd))
            assert rel < 1e-5, (name, float(got), float(fd), rel)
        print(name, "ok", flush=True)

    check("encode / deformed vertices", jax.jit(lambda x: a.encode(x)), frames, 1e-7)
    check("decode / features", dec, feats, 1e-6)
    anchors = [0, 100, 2000]
    check("decode / anchor targets", jax.jit(lambda t: a.decode(feats, anchors=anchors, targets=t)), frames[:, anchors], 1e-4)
    # the reference: central differences of fresh Acaps (each its own factor) against with_rest's derivative
    check("decode / reference", jax.jit(lambda r: a.with_rest(r).decode(feats)), a.rest, 1e-6,
          fd_fn=lambda r: acap.prepare(np.asarray(r), faces, solver={solver!r}).decode(feats))
    print("OK")
"""


@pytest.mark.slow
def test_horse_stages_trace_and_differentiate_in_a_fresh_process():
    """The CPU default (host factor) on real frames; the other solvers' transforms: the small-mesh test."""
    run_script(HORSE_TRANSFORMS.format(data=str(data_dir("horse-gallop")), solver="host"))


def test_solvers_agree_on_horse():
    """dense against host to 1e-8 relative (float64), conjugate gradients to their tolerance; the status."""
    run_script(f"""
        import numpy as np, jax.numpy as jnp
        from jaxdeform import acap
        from jaxdeform.mesh import load_sequence
        verts, faces = load_sequence({str(data_dir("horse-gallop"))!r})
        frames = verts[::8]
        host = acap.prepare(verts[0], faces, solver="host")
        feats = host.encode(frames)
        ref = np.asarray(host.decode(feats))
        scale = np.abs(ref).max()
        dense = acap.prepare(verts[0], faces, solver="dense")
        d = np.asarray(dense.decode(feats))
        assert np.abs(d - ref).max() / scale < 1e-8, np.abs(d - ref).max() / scale
        cg = acap.prepare(verts[0], faces, solver="cg", cg_rtol=1e-10)
        c, info = cg.decode_info(feats)
        assert bool(info.converged) and int(info.steps) > 1
        assert np.abs(np.asarray(c) - ref).max() / scale < 1e-6, np.abs(np.asarray(c) - ref).max() / scale
        short = acap.prepare(verts[0], faces, solver="cg", cg_max_steps=5)
        _, info = short.decode_info(feats)
        assert not bool(info.converged) and int(info.steps) == 5
        print("OK")
    """)


def test_exit_with_decodes_still_running():
    """A script that ends right after dispatching decodes (results never read) exits cleanly: the host factors are
    released only after the computations that solve with them have finished (this aborted at every exit before)."""
    run_script(
        f"""
        import numpy as np
        from jaxdeform import acap
        from jaxdeform.mesh import load_sequence
        verts, faces = load_sequence({str(data_dir("horse-gallop"))!r})
        a = acap.prepare(verts[0], faces)
        feats = a.encode(verts[:8].astype(np.float32))
        for refine in (0, 1, 2):
            p = a.decode(feats, refine=refine)
        print("OK")
        """
    )
