"""The jaxtyping annotations of ``jaxdeform.mesh``, ``jaxdeform.acap`` and ``jaxdeform.nn`` are checked while the
tests run (jaxtyping's import hook with beartype: ``--jaxtyping-packages`` in pyproject.toml's pytest addopts).

These tests fail when the hook is off: a wrongly shaped argument must raise jaxtyping's type-check error.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import grid_mesh
from jaxtyping import TypeCheckError

from jaxdeform import acap
from jaxdeform.mesh import build_topology, vertex_normals
from jaxdeform.nn.graph_conv import ring_mean, rings_from_topology


def test_a_wrongly_shaped_argument_is_refused():
    v, f = grid_mesh(4)
    topo = build_topology(f)
    assert vertex_normals(v, topo).shape == v.shape  # NumPy vertices (V, 3) are accepted
    with pytest.raises(TypeCheckError, match="vertex_normals"):
        vertex_normals(v[:, :2], topo)  # (V, 2)


def test_dimensions_are_checked_across_arguments():
    v, f = grid_mesh(4)
    rings = rings_from_topology(build_topology(f))
    x = np.zeros((2, len(v), 9))
    assert ring_mean(x, *rings).shape == x.shape
    with pytest.raises(TypeCheckError, match="ring_mean"):
        ring_mean(x[:, :-1], *rings)  # one vertex fewer than the rings have


def test_pytree_dataclass_fields_are_checked_and_survive_the_tree_utilities():
    v, f = grid_mesh(4)
    topo = build_topology(f)
    with pytest.raises(TypeCheckError, match="Topology"):
        dataclasses.replace(topo, faces=topo.faces[:, :2])
    # JAX rebuilds the pytree through its (checked) __init__ with stand-ins for the arrays
    shapes = jax.eval_shape(lambda t: t, topo)
    assert shapes.faces.shape == topo.faces.shape
    assert jax.tree_util.tree_map(lambda x: None, topo).n_vertices == topo.n_vertices
    moved = eqx.tree_at(lambda t: t.faces, topo, topo.faces[::-1])
    assert moved.faces[0, 0] == topo.faces[-1, 0]


def test_acap_traces_under_jit_and_vmap_with_the_checks():
    v, f = grid_mesh(4)
    frames = np.stack([v, v + 0.01 * np.random.default_rng(0).normal(size=v.shape)])
    a = acap.prepare(v, f)
    feats = jax.jit(lambda m, x: m.encode(x))(a, frames)
    np.testing.assert_allclose(jax.vmap(a.encode)(jnp.asarray(frames)), feats, atol=1e-10)
    back = jax.vmap(lambda m, g: m.decode(g), in_axes=(None, 0))(a, feats)
    np.testing.assert_allclose(back, a.decode(feats), atol=1e-8)
