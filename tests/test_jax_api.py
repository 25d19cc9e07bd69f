"""The library's promise, checked as a user would: every public ACAP stage under jax.jit, jax.vmap, jax.grad,
jax.jvp and jax.jacfwd, each in a fresh Python process with no eager warm-up call, and no global JAX setting
changed by importing jaxdeform. This file: imports, dtypes, a small mesh.

Each test runs a small script in a subprocess (``fresh_process.run_script``); the script asserts and prints ``OK``.
"""

from __future__ import annotations

from fresh_process import run_script


def test_import_changes_no_jax_setting_and_float32_decodes_to_float32():
    run_script(
        """
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
            p = a.decode(feats, refine=refine)  # results left unread: solves may still run at exit
            assert p.dtype == np.float32, (refine, p.dtype)
        print("OK")
    """.replace("import jax\n", "import os, jax\n", 1),
        x64=False,
    )


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
            jf = jax.jacfwd(fn)(x)
            assert jf.shape == feats.shape + x.shape and bool(jnp.all(jnp.isfinite(jf)))
            if mode == "spatial":  # forward and reverse mode agree (the other modes share the stages)
                assert jnp.allclose(jf, jax.jacrev(fn)(x), atol=1e-9)
            if mode != "temporal":
                assert jnp.allclose(jax.vmap(fn)(x), feats, atol=1e-10)
        host = acap.prepare(v[0], f, solver="host", anchors=[0, 5])
        for solver in ("host", "dense", "cg"):
            a = acap.prepare(v[0], f, solver=solver, anchors=[0, 5])
            loc = jax.jit(a.local)(x)
            assert loc[0].shape == (4, x.shape[1], 3)
            feats = a.encode(x)
            dec = lambda g: a.decode(g, refine=1)
            if solver == "host":  # the derivative rules are the solver's interface, shared by the three
                assert jnp.allclose(jax.jacfwd(dec)(feats[1]), jax.jacrev(dec)(feats[1]), atol=1e-9)
            else:
                _, tangent = jax.jvp(dec, (feats,), (jnp.ones_like(feats),))
                _, host_tangent = jax.jvp(lambda g: host.decode(g), (feats,), (jnp.ones_like(feats),))
                assert jnp.allclose(tangent, host_tangent, atol=1e-6), solver
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
