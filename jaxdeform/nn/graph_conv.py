"""Mesh convolution (seed 000, eq. (1)) and the autoencoder block of Sec. 4.1, as flax nnx Modules.

Convolution, per vertex i (weights shared by all vertices)::

    y_i = x_i W_point + (1/D_i) sum_{j=1..D_i} x_{n_ij} W_neighbor + b

The one-ring mean (:func:`ring_mean`) is a masked sum over the static K slots of the padded rings of
:class:`jaxdeform.mesh.topology.Topology` divided by the degree, in a vertex-major layout (V, B C) so that every
slot is one gather of whole rows; there is no loop over vertices. Its derivative is given as a JVP
(``jax.custom_jvp``): the tangent is the same linear map written as one scatter-add per slot, which the rings'
symmetry (j in ring(i) iff i in ring(j)) makes equal to the gathers. Reverse mode transposes that tangent into
gathers again, forward mode and higher orders differentiate plain JAX.

Autoencoder block (Sec. 4.1): encoder = one conv layer + one fully connected layer; decoder mirrored;
the fully connected layers share one parameter ``C`` (Kz, 9V) without bias (encoder uses ``C^T``,
decoder uses ``C``); the two conv layers have their own weights.

Activations. The paper says "all the layers use the tanh activation function", but also bounds the
latent code with V(Z) = (1/Kz) sum_k max(max_m |Z_mk| - theta, 0) with theta = 5, which would be
identically zero if z were a tanh output (|tanh| < 1). The block here leaves the encoder's fully connected
layer *linear* (no tanh on z, as in the public code of Tan et al. 2018 that the paper follows) and applies
tanh after every other layer; ``latent="tanh"`` in :func:`ae_forward` (``Config.latent`` of
:mod:`jaxdeform.components.model`, the named configuration ``latent-tanh``) adds the tanh on z, the literal
reading::

    encode: h = tanh(conv_enc(x)); z = flatten(h) @ C^T                      (B, Kz), no tanh
    decode: g = tanh(reshape(z @ C)); x_hat = tanh(conv_dec(g))              (B, V, 9)

The final tanh matches the features scaled to [-0.95, 0.95].

Modules: :class:`MeshConv` holds one conv layer's weights (``W_point``, ``W_neighbor``, ``b`` as ``nnx.Param``),
:class:`AEBlock` one block's ``conv_enc``, ``conv_dec`` and ``C``. Their arrays may carry leading axes (blocks
stacked for ``jax.vmap``; flax nnx Modules are pytrees, so ``jax.vmap``, ``jax.jit`` and ``jax.grad`` take them
as arguments). :func:`init_mesh_conv` and :func:`init_ae_block` draw them; the functions below run them.
:func:`mesh_conv` itself takes the weights by name (a mapping of arrays), for layers that keep them elsewhere.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, ArrayLike, Bool, Float

from jaxdeform.typing import Int

MU = 9  # ACAP feature size per vertex


class Rings(NamedTuple):
    """Padded one-rings of a connectivity (a pytree of arrays; padding index = the vertex itself)."""

    neighbors: Int[Array, "v k"]
    mask: Bool[Array, "v k"]
    degree: Int[Array, " v"]


def rings_from_topology(topo) -> Rings:
    """The :class:`Rings` of a topology.

    **Arguments:**

    - `topo`: a :class:`~jaxdeform.mesh.topology.Topology`.

    **Returns:**

    The :class:`Rings` (jnp arrays).
    """
    return Rings(jnp.asarray(topo.neighbors), jnp.asarray(topo.mask), jnp.asarray(topo.degree))


def _glorot(key: Array, shape: tuple[int, int], dtype) -> Array:
    fan_in, fan_out = shape
    limit = jnp.sqrt(6.0 / (fan_in + fan_out)).astype(dtype)
    return jax.random.uniform(key, shape, dtype, -limit, limit)


class MeshConv(nnx.Module):
    """One mesh conv layer of eq. (1), no activation: ``x W_point + ring_mean(x) W_neighbor + b``.

    **Arguments:**

    - ``W_point``, ``W_neighbor``: weights ``(..., cin, cout)``, or None for a layer that takes them from another
        (a tied decoder, :meth:`__call__`'s ``shared``).
    - ``b``: the bias ``(..., cout)``.

    Leading axes (stacked layers) are for ``jax.vmap``; a call takes one layer.
    """

    def __init__(self, W_point: Array | None, W_neighbor: Array | None, b: Array):
        self.W_point = None if W_point is None else nnx.Param(W_point)
        self.W_neighbor = None if W_neighbor is None else nnx.Param(W_neighbor)
        self.b = nnx.Param(b)

    def weights(self, shared: MeshConv | None = None) -> dict[str, Array]:
        """The layer's arrays by name, as :func:`mesh_conv` takes them.

        **Arguments:**

        - ``shared``: take ``W_point`` and ``W_neighbor`` from this layer (None: the layer's own).

        **Returns:**

        ``{"W_point", "W_neighbor", "b"}``.

        **Raises:**

        ``ValueError`` if the layer has no weights of its own and ``shared`` is None.
        """
        src = self if shared is None else shared
        if src.W_point is None or src.W_neighbor is None:
            raise ValueError("the convolution holds no weights of its own (a tied decoder): pass the shared layer.")
        return {"W_point": src.W_point[...], "W_neighbor": src.W_neighbor[...], "b": self.b[...]}

    def __call__(self, x: Float[ArrayLike, "b v cin"], rings: Rings, shared: MeshConv | None = None) -> Array:
        """:func:`mesh_conv` with this layer's weights.

        **Arguments:**

        - ``x``: inputs ``(B, V, cin)``.
        - ``rings``: the :class:`Rings` of the connectivity.
        - ``shared``: as :meth:`weights`.

        **Returns:**

        Outputs ``(B, V, cout)``.
        """
        return mesh_conv(self.weights(shared), x, rings.neighbors, rings.mask, rings.degree)


class AEBlock(nnx.Module):
    """One autoencoder block (Sec. 4.1): ``conv_enc``, ``conv_dec`` (:class:`MeshConv`, 9 -> 9) and ``C``
    ``(Kz, 9V)`` (an ``nnx.Param``; its row k reshaped to ``(V, 9)`` is component k). Arrays may carry leading
    (block) axes, as :class:`MeshConv`'s.

    **Arguments:**

    - ``conv_enc``, ``conv_dec``: the two convolutions.
    - ``C``: the shared fully connected parameter.
    """

    def __init__(self, conv_enc: MeshConv, conv_dec: MeshConv, C: Array):
        self.conv_enc = conv_enc
        self.conv_dec = conv_dec
        self.C = nnx.Param(C)


@partial(jax.jit, static_argnames=("cin", "cout", "dtype"))
def init_mesh_conv(key: Array, cin: int, cout: int, dtype=jnp.float32) -> MeshConv:
    """A fresh mesh conv layer.

    Jitted (an entry point); sizes and dtype are static.

    **Arguments:**

    - `key`: a PRNG key.
    - `cin`, `cout`: input and output channels (static).
    - `dtype`: the parameters' dtype (static).

    **Returns:**

    The :class:`MeshConv`: `W_point` `(cin, cout)` and `W_neighbor` `(cin, cout)` Glorot-uniform (from the two
    halves of ``jax.random.split(key)``), `b` `(cout,)` zero.
    """
    kp, kn = jax.random.split(key)
    return MeshConv(_glorot(kp, (cin, cout), dtype), _glorot(kn, (cin, cout), dtype), jnp.zeros((cout,), dtype))


def _slot_gathers(
    vm: Float[Array, "v f"], neighbors: Int[ArrayLike, "v k"], mask: Bool[ArrayLike, "v k"]
) -> Float[Array, "v f"]:
    """sum_k [mask_ik] vm[n_ik]: one gather of whole rows per ring slot."""
    acc = jnp.zeros_like(vm)
    for k in range(neighbors.shape[1]):
        acc = acc + jnp.where(mask[:, k, None], vm[neighbors[:, k]], 0.0)
    return acc


def _slot_scatters(
    vm: Float[Array, "v f"], neighbors: Int[ArrayLike, "v k"], mask: Bool[ArrayLike, "v k"]
) -> Float[Array, "v f"]:
    """The transpose of :func:`_slot_gathers`: row i added to row n_ik for every valid slot (a scatter-add per
    slot). Equal to :func:`_slot_gathers` on symmetric rings."""
    acc = jnp.zeros_like(vm)
    for k in range(neighbors.shape[1]):
        acc = acc.at[neighbors[:, k]].add(jnp.where(mask[:, k, None], vm, 0.0))
    return acc


@jax.custom_jvp
def _ring_mean_vm(vm, neighbors, mask, inv_deg):
    return _slot_gathers(vm, neighbors, mask) * inv_deg[:, None]


@_ring_mean_vm.defjvp
def _ring_mean_vm_jvp(primals, tangents):
    # linear in vm: the tangent is the same map on the tangent, written with scatter-adds so that its transpose
    # (reverse mode) is gathers; the tables get no tangent
    vm, neighbors, mask, inv_deg = primals
    return _ring_mean_vm(vm, neighbors, mask, inv_deg), _slot_scatters(tangents[0], neighbors, mask) * inv_deg[:, None]


def ring_mean(
    x: Float[ArrayLike, "b v c"],
    neighbors: Int[ArrayLike, "v k"],
    mask: Bool[ArrayLike, "v k"],
    degree: Int[ArrayLike, " v"],
) -> Float[Array, "b v c"]:
    """The one-ring mean (1/D_i) sum_j x_{n_ij}.

    The rings must be symmetric (j in ring(i) iff i in ring(j), as mesh one-rings are): the derivatives rely
    on it.

    **Arguments:**

    - `x`: per-vertex values `(B, V, C)`.
    - `neighbors`: padded one-rings `(V, K)`.
    - `mask`: their valid slots `(V, K)`.
    - `degree`: vertex degrees `(V,)` (0 is treated as 1).

    **Returns:**

    Means `(B, V, C)` in x's dtype; differentiable in x (forward and reverse mode).
    """
    b, v, c = x.shape
    vm = jnp.transpose(x, (1, 0, 2)).reshape(v, b * c)
    inv_deg = 1.0 / jnp.maximum(degree, 1).astype(x.dtype)
    out = _ring_mean_vm(vm, neighbors, mask, inv_deg)
    return jnp.transpose(out.reshape(v, b, c), (1, 0, 2))


def mesh_conv(
    params: Mapping[str, ArrayLike],
    x: Float[ArrayLike, "b v cin"],
    neighbors: Int[ArrayLike, "v k"],
    mask: Bool[ArrayLike, "v k"],
    degree: Int[ArrayLike, " v"],
) -> Float[Array, "b v cout"]:
    """Mesh convolution of eq. (1) without activation: `x W_point + ring_mean(x) W_neighbor + b`.

    **Arguments:**

    - `params`: the weights by name, `W_point`, `W_neighbor` `(cin, cout)` and `b` `(cout,)` (e.g.
        :meth:`MeshConv.weights`).
    - `x`: inputs `(B, V, cin)`.
    - `neighbors`, `mask`, `degree`: as :func:`ring_mean`.

    **Returns:**

    Outputs `(B, V, cout)`.
    """
    nbr = ring_mean(x, neighbors, mask, degree)
    return x @ params["W_point"] + nbr @ params["W_neighbor"] + params["b"]


def _tanh(x: Array) -> Array:
    """tanh over a flat view: XLA on CPU vectorizes elementwise loops along the minor axis, which is only 9
    channels long in the (B, V, 9) layout (much slower than over the flattened rows)."""
    return jnp.tanh(x.reshape(x.shape[:-2] + (-1,))).reshape(x.shape)


@partial(jax.jit, static_argnames=("n_vertices", "kz", "dtype"))
def init_ae_block(key: Array, n_vertices: int, kz: int, dtype=jnp.float32) -> AEBlock:
    """A fresh autoencoder block.

    **Arguments:**

    - `key`: a PRNG key.
    - `n_vertices`: V (static).
    - `kz`: the latent size Kz (static).
    - `dtype`: the parameters' dtype (static).

    **Returns:**

    The :class:`AEBlock`: `conv_enc`, `conv_dec` (9 -> 9 each, :func:`init_mesh_conv`) and `C` `(Kz, 9V)`
    Glorot-uniform over its shape, from the three keys of ``jax.random.split(key, 3)`` in that order.
    """
    ke, kd, kc = jax.random.split(key, 3)
    return AEBlock(
        init_mesh_conv(ke, MU, MU, dtype), init_mesh_conv(kd, MU, MU, dtype), _glorot(kc, (kz, MU * n_vertices), dtype)
    )


def ae_encode(block: AEBlock, x: Float[ArrayLike, "b v 9"], rings: Rings) -> Float[Array, "b kz"]:
    """The block's encoder z = flatten(tanh(conv_enc(x))) @ C^T; linear, no tanh on z (module docstring).

    **Arguments:**

    - `block`: one :class:`AEBlock`.
    - `x`: features `(B, V, 9)`.
    - `rings`: the :class:`Rings` of the connectivity.

    **Returns:**

    Codes z `(B, Kz)`.
    """
    h = _tanh(block.conv_enc(x, rings))
    return h.reshape(h.shape[0], -1) @ block.C[...].T


def ae_decode_pre(block: AEBlock, z: Float[ArrayLike, "b kz"]) -> Float[Array, "b v 9"]:
    """Decoder fully connected pre-activation.

    **Arguments:**

    - `block`: one :class:`AEBlock`.
    - `z`: codes `(B, Kz)`.

    **Returns:**

    (z @ C) reshaped to `(B, V, 9)`.
    """
    out = z @ block.C[...]
    return out.reshape(z.shape[0], -1, MU)


def ae_decode(block: AEBlock, z: Float[ArrayLike, "b kz"], rings: Rings) -> Float[Array, "b v 9"]:
    """The block's decoder x_hat = tanh(conv_dec(tanh(reshape(z @ C)))).

    **Arguments:**

    - `block`: one :class:`AEBlock` (its `conv_dec` with weights of its own).
    - `z`: codes `(B, Kz)`.
    - `rings`: the :class:`Rings` of the connectivity.

    **Returns:**

    x_hat `(B, V, 9)`, in [-1, 1].
    """
    g = _tanh(ae_decode_pre(block, z))
    return _tanh(block.conv_dec(g, rings))


def ae_decode_error(
    block: AEBlock, z: Float[ArrayLike, "b kz"], target: Float[ArrayLike, "b v 9"], rings: Rings
) -> tuple[Float[Array, "b v 9"], Float[Array, " b"]]:
    """Decode and measure the block's reconstruction error per shape.

    **Arguments:**

    - `block`: one :class:`AEBlock`.
    - `z`: codes `(B, Kz)`.
    - `target`: features `(B, V, 9)`.
    - `rings`: the :class:`Rings` of the connectivity.

    **Returns:**

    `(x_hat, err)`: :func:`ae_decode` `(B, V, 9)` and err_m = sum over (V, 9) of (x_hat_m - target_m)^2, `(B,)`.
    """
    x_hat = ae_decode(block, z, rings)
    flat = x_hat.shape[:-2] + (-1,)  # over rows of 9V: see _tanh
    return x_hat, jnp.sum(jnp.square(x_hat.reshape(flat) - target.reshape(flat)), axis=-1)


def _latent_code(block: AEBlock, x: Float[ArrayLike, "b v 9"], rings: Rings, latent: str) -> Float[Array, "b kz"]:
    z = ae_encode(block, x, rings)
    return jnp.tanh(z) if latent == "tanh" else z


def ae_forward(
    block: AEBlock, x: Float[ArrayLike, "b v 9"], rings: Rings, latent: str = "linear"
) -> tuple[Float[Array, "b kz"], Float[Array, "b v 9"]]:
    """One autoencoder block's forward pass.

    **Arguments:**

    - `block`: one :class:`AEBlock`.
    - `x`: features `(B, V, 9)`.
    - `rings`: the :class:`Rings` of the connectivity.
    - `latent`: "linear" (default) or "tanh" (a tanh on z; module docstring).

    **Returns:**

    `(z, x_hat)`: codes `(B, Kz)` and reconstructions `(B, V, 9)`.
    """
    z = _latent_code(block, x, rings, latent)
    return z, ae_decode(block, z, rings)


def ae_forward_error(block: AEBlock, x: Float[ArrayLike, "b v 9"], rings: Rings, latent: str = "linear") -> tuple:
    """One block's forward pass with its reconstruction error.

    **Arguments:**

    - `block`, `x`, `rings`, `latent`: as :func:`ae_forward`.

    **Returns:**

    `(z, x_hat, err)`: :func:`ae_forward` and the squared error of x_hat against the block's own input x per
    shape `(B,)` (:func:`ae_decode_error`).
    """
    z = _latent_code(block, x, rings, latent)
    x_hat, err = ae_decode_error(block, z, x, rings)
    return z, x_hat, err


def masked_blocks_error(
    blocks: AEBlock, x: Float[ArrayLike, "n b v 9"], am: Float[ArrayLike, "n k v"], rings: Rings
) -> tuple:
    """A grid of blocks (n, k) on their masked inputs.

    Seed 000's children of a level's last blocks: n parents, k children each, am the parents' attention masks.

    **Arguments:**

    - `blocks`: :class:`AEBlock` arrays stacked `(n, k, ...)`.
    - `x`: features `(n, B, V, 9)`.
    - `am`: attention masks `(n, k, V)`; they get no gradient.
    - `rings`: the :class:`Rings` of the connectivity.

    **Returns:**

    `(z, x_hat, err)` stacked over `(n, k)`: block (j, m) runs :func:`ae_forward_error` (linear latent) on
    am[j, m, :, None] x[j], its error against that same input.
    """
    am = jax.lax.stop_gradient(am)
    inputs = am[..., None, :, None] * x[:, None]
    run = lambda q, xin: ae_forward_error(q, xin, rings, "linear")  # noqa: E731
    return jax.vmap(jax.vmap(run))(blocks, inputs)
