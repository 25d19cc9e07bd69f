"""The library's promise, checked as a user would: every public ACAP stage under jax.jit, jax.vmap, jax.grad,
jax.jvp and jax.jacfwd, each in a fresh Python process with no eager warm-up call, and no global JAX setting
changed by importing jaxdeform.

Each test runs a small script in a subprocess (``run_script``); the script asserts and prints ``OK``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from conftest import data_dir

ROOT = Path(__file__).resolve().parents[1]


def run_script(code: str, *, x64: bool = True, timeout: int = 900, env_extra: dict | None = None) -> str:
    """Run ``code`` in a fresh interpreter (x64 as asked, nothing else of the tests' settings changed)."""
    env = dict(os.environ)
    env.pop("JAX_ENABLE_X64", None)
    if x64:
        env["JAX_ENABLE_X64"] = "1"
    env.update(env_extra or {})
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    assert proc.stdout.strip().endswith("OK"), proc.stdout[-3000:]
    return proc.stdout


def test_import_changes_no_jax_setting_and_float32_decodes_to_float32():
    run_script("""
        import jax
        before = (jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision, os.environ.get("XLA_FLAGS"))
        import jaxdeform, jaxdeform.mesh, jaxdeform.acap, jaxdeform.nn.graph_conv, jaxdeform.nn.transformer
        import jaxdeform.components.model, jaxdeform.cloth.model, jaxdeform.parts.mfa, jaxdeform.handles.field
        import jaxdeform.cli
        assert (jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision, os.environ.get("XLA_FLAGS")) == before
        assert jax.numpy.zeros(1).dtype == jax.numpy.float32
        import numpy as np
        from jaxdeform.data.synthetic import bending_tube_sequence
        v, f = bending_tube_sequence(n_frames=3, n_around=8, n_along=10)
        a = jaxdeform.acap.prepare(v[0], f)
        feats = a.encode(v.astype(np.float32))
        assert feats.dtype == np.float32, feats.dtype
        for refine in (0, 1, 2):
            p = a.decode(feats, refine=refine)
            assert p.dtype == np.float32, (refine, p.dtype)
        print("OK")
    """.replace("import jax\n", "import os, jax\n", 1), x64=False)


def test_float32_in_float32_out_with_x64_enabled():
    run_script("""
        import numpy as np, jax.numpy as jnp
        from jaxdeform import acap
        from jaxdeform.data.synthetic import bending_tube_sequence
        v, f = bending_tube_sequence(n_frames=3, n_around=8, n_along=10)
        for solver in ("host", "dense", "cg"):
            a = acap.prepare(v[0], f, solver=solver)  # a float64 reference
            feats = a.encode(v.astype(np.float32))
            assert feats.dtype == np.float32
            p = a.decode(feats)
            assert p.dtype == np.float32, (solver, p.dtype)
            p64 = a.decode(feats.astype(np.float64))
            assert p64.dtype == np.float64
            assert float(jnp.abs(p - p64).max()) < 1e-3 * float(np.ptp(v))
        print("OK")
    """)


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


def test_every_stage_under_every_transform_on_a_small_mesh():
    """jit, vmap, grad, jvp and jacfwd of local, encode (every consistency mode), decode (anchors, refinement,
    each solver) and deformation_energy; jacfwd against jacrev where both apply."""
    run_script("""
        import numpy as np, jax, jax.numpy as jnp
        from jaxdeform import acap
        from jaxdeform.data.synthetic import bending_tube_sequence
        v, f = bending_tube_sequence(n_frames=4, n_around=6, n_along=6)
        x = jnp.asarray(v)
        a = acap.prepare(v[0], f)
        for mode in ("none", "spatial", "temporal"):  # the encoder does not depend on the solver
            fn = lambda y: a.encode(y, mode)
            feats = jax.jit(fn)(x)
            assert jnp.allclose(jax.jacfwd(fn)(x), jax.jacrev(fn)(x), atol=1e-9), mode
            if mode != "temporal":
                assert jnp.allclose(jax.vmap(fn)(x), feats, atol=1e-10)
        for solver in ("host", "dense", "cg"):
            a = acap.prepare(v[0], f, solver=solver, anchors=[0, 5])
            loc = jax.jit(a.local)(x)
            assert loc[0].shape == (4, x.shape[1], 3)
            feats = a.encode(x)
            dec = lambda g: a.decode(g, refine=1)
            jf = jax.jacfwd(dec)(feats[1])
            jr = jax.jacrev(dec)(feats[1])
            assert jnp.allclose(jf, jr, atol=1e-6 if solver == "cg" else 1e-9), solver
            assert jnp.allclose(jax.vmap(dec)(feats), jax.jit(dec)(feats), atol=1e-7)
            # anchors given inside the trace, as concrete indices (traced ones: conjugate gradients only)
            p = jax.jit(lambda g, t: a.decode(g, anchors=[3, 7], targets=t))(feats, x[:, [3, 7]])
            assert jnp.allclose(p[:, [3, 7]], x[:, [3, 7]], atol=1e-3)
            if solver == "cg":
                p2 = jax.jit(lambda g, i, t: a.decode(g, anchors=i, targets=t))(feats, jnp.array([3, 7]), x[:, [3, 7]])
                assert jnp.allclose(p, p2, atol=1e-8)
            e = jax.jit(a.deformation_energy)(feats, x)
            ge = jax.grad(lambda y: a.deformation_energy(feats, y).sum())(x)
            assert e.shape == (4,) and ge.shape == x.shape
            # the Acap itself may be a jit argument
            p3 = jax.jit(lambda acp, g: acp.decode(g))(a, feats)
            assert jnp.allclose(p3, a.decode(feats), atol=1e-8)
        print("OK")
    """)


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


SHARDED_ACAP = """
    import numpy as np, jax, jax.numpy as jnp
    from jaxdeform import acap
    from jaxdeform.acap import sharded
    from jaxdeform.mesh import load_sequence
    assert len(jax.devices()) == 4
    verts, faces = load_sequence({data!r})
    frames = verts[:10]  # not a multiple of 4: padded and trimmed
    mesh = sharded.frames_mesh()
    for solver in ("host", "cg"):
        a = acap.prepare(verts[0], faces, solver=solver)
        one = a.encode(frames)
        many = sharded.encode(a, frames, mesh)
        assert float(jnp.abs(one - many).max()) < 1e-12
        d_one = a.decode(one)
        d_many = sharded.decode(a, one, mesh)
        assert float(jnp.abs(d_one - d_many).max()) < 1e-9 * float(np.ptp(verts[0])), float(jnp.abs(d_one - d_many).max())
    even = sharded.encode(a, verts[:8], mesh)
    assert even.sharding.spec == jax.sharding.PartitionSpec("frames")  # stays split along the frames
    print("OK")
"""


@pytest.mark.slow
def test_sharded_encode_decode_equal_one_device():
    run_script(SHARDED_ACAP.format(data=str(data_dir("horse-gallop"))),
               env_extra={"XLA_FLAGS": "--xla_force_host_platform_device_count=4"})


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    start = text.index("<!-- jax-api-example -->")
    block = text[text.index("```python\n", start) + len("```python\n"):]
    return block[:block.index("```")]


@pytest.mark.slow
def test_readme_jax_example_runs_verbatim():
    """The README's jit / vmap / grad / jvp / sharded example, exactly as printed, in a fresh process (4 devices)."""
    data_dir("horse-gallop")  # skips with its reason when the data is absent
    run_script(_readme_example() + '\nprint("OK")\n', x64=False,
               env_extra={"XLA_FLAGS": "--xla_force_host_platform_device_count=4"})
