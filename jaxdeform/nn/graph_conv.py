"""Mesh convolution (seed 000, eq. (1)) and the autoencoder block of Sec. 4.1.

Convolution, per vertex i (weights shared by all vertices)::

    y_i = x_i W_point + (1/D_i) sum_{j=1..D_i} x_{n_ij} W_neighbor + b

The one-ring mean is a masked sum over the static K slots of the padded rings of
:class:`jaxdeform.mesh.topology.Topology` divided by the degree; there is no loop over vertices. On CPU the
whole convolution (one-ring mean, both 9x9 channel mixes, bias) and its adjoint run as native XLA custom calls
(:mod:`jaxdeform.nn.native`): XLA's own gathers recompute their fused producers once per ring slot and its
9x9 products run far below memory speed (horse training step 322 -> 135 ms, with the changes in train.py). :func:`mesh_conv_reference` is
the pure-JAX definition, used on other backends and checked against the kernels in the tests.

The block's two halves go one step further on CPU: :func:`ae_encode` (conv, tanh, product with ``C^T``) and
:func:`ae_decode` (product with ``C``, tanh, conv, tanh) are one native call each, with one hand-written
adjoint each, so the (B, V, 9) hidden layers and their cotangents are not separate XLA passes over memory
(horse multiscale training step, same process, alternating: 123-141 ms against 149-182 ms layer by layer).
:func:`ae_encode_reference` and :func:`ae_decode_reference` compose the layers; the tests check that both give
the same values and gradients, and the fused gradients against finite differences.

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
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxdeform.nn import native

MU = 9  # ACAP feature size per vertex


class Rings(NamedTuple):
    """Padded one-rings of a connectivity (a pytree of arrays; padding index = the vertex itself)."""

    neighbors: Int[Array, "v k"]
    mask: Bool[Array, "v k"]
    degree: Int[Array, " v"]


def rings_from_topology(topo) -> Rings:
    """The :class:`Rings` of a :class:`~jaxdeform.mesh.topology.Topology`."""
    return Rings(jnp.asarray(topo.neighbors), jnp.asarray(topo.mask), jnp.asarray(topo.degree))


def _glorot(key: Array, shape: tuple[int, int], dtype) -> Array:
    fan_in, fan_out = shape
    limit = jnp.sqrt(6.0 / (fan_in + fan_out)).astype(dtype)
    return jax.random.uniform(key, shape, dtype, -limit, limit)


@partial(jax.jit, static_argnames=("cin", "cout", "dtype"))
def init_mesh_conv(key: Array, cin: int, cout: int, dtype=jnp.float32) -> dict[str, Array]:
    """Parameters of one mesh conv layer: ``W_point`` (cin, cout), ``W_neighbor`` (cin, cout), ``b`` (cout,).

    Weights are Glorot-uniform, the bias is zero. Jitted (an entry point); sizes and dtype are static.
    """
    kp, kn = jax.random.split(key)
    return {
        "W_point": _glorot(kp, (cin, cout), dtype),
        "W_neighbor": _glorot(kn, (cin, cout), dtype),
        "b": jnp.zeros((cout,), dtype),
    }


def _slot_sum(vm: Float[Array, "v f"], neighbors: Int[Array, "v k"], mask: Bool[Array, "v k"]) -> Float[Array, "v f"]:
    """sum_j vm[n_ij] over the K static ring slots: gathers of whole rows, summed element-wise (XLA on CPU
    runs this ~25x faster than a gather to (B, V, K, C) followed by a reduction over K)."""
    acc = jnp.zeros_like(vm)
    for k in range(neighbors.shape[1]):
        acc = acc + jnp.where(mask[:, k, None], vm[neighbors[:, k]], 0.0)
    return acc


@jax.custom_vjp
def _ring_mean_vm(vm, neighbors, mask, inv_deg):
    return _slot_sum(vm, neighbors, mask) * inv_deg[:, None]


def _ring_mean_fwd(vm, neighbors, mask, inv_deg):
    return _ring_mean_vm(vm, neighbors, mask, inv_deg), (neighbors, mask, inv_deg)


def _ring_mean_bwd(res, g):
    # The one-ring relation is symmetric, so the adjoint of "mean over my neighbours" is "sum over my
    # neighbours of their cotangent / their degree": again row gathers, not the scatter JAX would derive.
    neighbors, mask, inv_deg = res
    return _slot_sum(g * inv_deg[:, None], neighbors, mask), None, None, None


_ring_mean_vm.defvjp(_ring_mean_fwd, _ring_mean_bwd)


def ring_mean(
    x: Float[Array, "b v c"], neighbors: Int[Array, "v k"], mask: Bool[Array, "v k"], degree: Int[Array, " v"]
) -> Float[Array, "b v c"]:
    """(1/D_i) sum_j x_{n_ij} over the one-rings (rings must be symmetric, as mesh one-rings are)."""
    b, v, c = x.shape
    vm = jnp.transpose(x, (1, 0, 2)).reshape(v, b * c)
    inv_deg = 1.0 / jnp.maximum(degree, 1).astype(x.dtype)
    out = _ring_mean_vm(vm, neighbors, mask, inv_deg)
    return jnp.transpose(out.reshape(v, b, c), (1, 0, 2))


def mesh_conv_reference(
    params: dict[str, Array],
    x: Float[Array, "b v cin"],
    neighbors: Int[Array, "v k"],
    mask: Bool[Array, "v k"],
    degree: Int[Array, " v"],
) -> Float[Array, "b v cout"]:
    """Pure-JAX mesh convolution of eq. (1) without activation: ``x W_point + ring_mean(x) W_neighbor + b``."""
    nbr = ring_mean(x, neighbors, mask, degree)
    return x @ params["W_point"] + nbr @ params["W_neighbor"] + params["b"]


@jax.custom_vjp
def _conv_native(x, neighbors, counts, inv_deg, w_point, w_neighbor, b):
    return native.conv_forward(x, neighbors, counts, inv_deg, w_point, w_neighbor, b)


def _conv_native_fwd(x, neighbors, counts, inv_deg, w_point, w_neighbor, b):
    y = native.conv_forward(x, neighbors, counts, inv_deg, w_point, w_neighbor, b)
    return y, (x, neighbors, counts, inv_deg, w_point, w_neighbor)


def _conv_native_bwd(res, gy):
    x, neighbors, counts, inv_deg, w_point, w_neighbor = res
    gx, gwp, gwn, gb = native.conv_backward(x, gy, neighbors, counts, inv_deg, w_point, w_neighbor)
    return gx, None, None, None, gwp, gwn, gb


_conv_native.defvjp(_conv_native_fwd, _conv_native_bwd)


def mesh_conv(
    params: dict[str, Array],
    x: Float[Array, "b v cin"],
    neighbors: Int[Array, "v k"],
    mask: Bool[Array, "v k"],
    degree: Int[Array, " v"],
) -> Float[Array, "b v cout"]:
    """Mesh convolution of eq. (1) without activation: ``x W_point + ring_mean(x) W_neighbor + b``.

    On CPU this runs the native kernels of :mod:`jaxdeform.nn.native` (forward and a hand-written adjoint; the
    valid ring slots must come first in each row, as :class:`~jaxdeform.mesh.topology.Topology` lays them
    out); elsewhere, or without a C++ compiler, :func:`mesh_conv_reference`. Both give the same values and
    gradients (tests/test_nn.py).
    """
    wp, wn, b = params["W_point"], params["W_neighbor"], params["b"]
    dtype = jnp.result_type(x, wp, wn, b)
    if (not native.available() or max(x.shape[-1], wp.shape[-1]) > native.MAX_CHANNELS
            or dtype not in (jnp.float32, jnp.float64)):
        return mesh_conv_reference(params, x, neighbors, mask, degree)
    nbr, counts, inv = native.ring_tables(neighbors, degree, dtype)
    cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    return _conv_native(cast(x), nbr, counts, inv, cast(wp), cast(wn), cast(b))


def _tanh(x: Array) -> Array:
    """tanh over a flat view: XLA on CPU vectorizes elementwise loops along the minor axis, which is only 9
    channels long in the (B, V, 9) layout (3-5x slower than over the flattened rows)."""
    return jnp.tanh(x.reshape(x.shape[:-2] + (-1,))).reshape(x.shape)


@partial(jax.jit, static_argnames=("n_vertices", "kz", "dtype"))
def init_ae_block(key: Array, n_vertices: int, kz: int, dtype=jnp.float32) -> dict:
    """Parameters of one autoencoder block: ``conv_enc``, ``conv_dec`` (9 -> 9 each) and ``C`` (Kz, 9V).

    ``C`` is Glorot-uniform over its (Kz, 9V) shape; row k reshaped to (V, 9) is component k.
    """
    ke, kd, kc = jax.random.split(key, 3)
    return {
        "conv_enc": init_mesh_conv(ke, MU, MU, dtype),
        "conv_dec": init_mesh_conv(kd, MU, MU, dtype),
        "C": _glorot(kc, (kz, MU * n_vertices), dtype),
    }


@jax.custom_vjp
def _encode_native(x, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    return native.ae_encoder_forward(x, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)[0]


def _encode_native_fwd(x, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    z, h = native.ae_encoder_forward(x, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)
    return z, (x, h, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def _encode_native_bwd(res, dz):
    x, h, neighbors, counts, inv_deg, w_point, w_neighbor, b, c = res
    dx, gwp, gwn, gb, dc = native.ae_encoder_backward(x, h, dz, neighbors, counts, inv_deg, w_point, w_neighbor,
                                                      b, c)
    return dx, None, None, None, gwp, gwn, gb, dc


_encode_native.defvjp(_encode_native_fwd, _encode_native_bwd)


@jax.custom_vjp
def _decode_native(z, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    return native.ae_decoder_forward(z, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)[0]


def _decode_native_fwd(z, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    x_hat, hidden = native.ae_decoder_forward(z, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)
    return x_hat, (z, x_hat, hidden, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def _decode_native_bwd(res, dx_hat):
    z, x_hat, hidden, neighbors, counts, inv_deg, w_point, w_neighbor, b, c = res
    dz, gwp, gwn, gb, dc = native.ae_decoder_backward(z, x_hat, hidden, dx_hat, neighbors, counts, inv_deg,
                                                      w_point, w_neighbor, b, c)
    return dz, None, None, None, gwp, gwn, gb, dc


_decode_native.defvjp(_decode_native_fwd, _decode_native_bwd)


@jax.custom_vjp
def _decode_error_native(z, target, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    x_hat, _, err = native.ae_decoder_forward_error(z, target, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)
    return x_hat, err


def _decode_error_native_fwd(z, target, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    x_hat, hidden, err = native.ae_decoder_forward_error(z, target, neighbors, counts, inv_deg, w_point,
                                                         w_neighbor, b, c)
    return (x_hat, err), (z, target, x_hat, hidden, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def _decode_error_native_bwd(res, cotangents):
    z, target, x_hat, hidden, neighbors, counts, inv_deg, w_point, w_neighbor, b, c = res
    dx_hat, derr = cotangents
    flat = x_hat.shape[:-2] + (-1,)  # elementwise over rows of 9V: see _tanh
    r2 = 2 * derr[..., None] * (x_hat - target).reshape(flat)  # d err / d x_hat, per entry
    dx_total = (dx_hat.reshape(flat) + r2).reshape(x_hat.shape)
    dz, gwp, gwn, gb, dc = native.ae_decoder_backward(z, x_hat, hidden, dx_total, neighbors, counts, inv_deg,
                                                      w_point, w_neighbor, b, c)
    return dz, (-r2).reshape(target.shape), None, None, None, gwp, gwn, gb, dc


_decode_error_native.defvjp(_decode_error_native_fwd, _decode_error_native_bwd)


def _fused_args(conv: dict, a: Array, c: Array, rings: Rings):
    """The native fused block's arguments (cast to one float dtype), or None where it does not apply."""
    wp, wn, b = conv["W_point"], conv["W_neighbor"], conv["b"]
    dtype = jnp.result_type(a, wp, wn, b, c)
    if (not native.available() or dtype not in (jnp.float32, jnp.float64) or wp.shape[-2:] != (MU, MU)
            or wn.shape[-2:] != (MU, MU) or c.shape[-1] != MU * rings.neighbors.shape[0]):
        return None
    nbr, counts, inv = native.ring_tables(rings.neighbors, rings.degree, dtype)
    cast = lambda t: jnp.asarray(t, dtype)  # noqa: E731
    return cast(a), nbr, counts, inv, cast(wp), cast(wn), cast(b), cast(c)


def ae_encode(params: dict, x: Float[Array, "b v 9"], rings: Rings) -> Float[Array, "b kz"]:
    """z = flatten(tanh(conv_enc(x))) @ C^T; linear, no tanh on z (see the module docstring).

    On CPU the whole encoder is one native call (and one for its adjoint), see :func:`ae_encode_reference`.
    """
    args = _fused_args(params["conv_enc"], x, params["C"], rings)
    if args is None:
        return ae_encode_reference(params, x, rings)
    return _encode_native(*args)


def ae_encode_reference(params: dict, x: Float[Array, "b v 9"], rings: Rings) -> Float[Array, "b kz"]:
    """:func:`ae_encode` from its layers (the mesh convolution, XLA's tanh and product)."""
    h = _tanh(mesh_conv(params["conv_enc"], x, rings.neighbors, rings.mask, rings.degree))
    return h.reshape(h.shape[0], -1) @ params["C"].T


def ae_decode_pre(params: dict, z: Float[Array, "b kz"]) -> Float[Array, "b v 9"]:
    """Decoder fully connected pre-activation: (z @ C) reshaped to (B, V, 9)."""
    out = z @ params["C"]
    return out.reshape(z.shape[0], -1, MU)


def ae_decode(params: dict, z: Float[Array, "b kz"], rings: Rings) -> Float[Array, "b v 9"]:
    """x_hat = tanh(conv_dec(tanh(reshape(z @ C)))); on CPU one native call (see :func:`ae_encode`)."""
    args = _fused_args(params["conv_dec"], z, params["C"], rings)
    if args is None:
        return ae_decode_reference(params, z, rings)
    return _decode_native(*args)


def ae_decode_reference(params: dict, z: Float[Array, "b kz"], rings: Rings) -> Float[Array, "b v 9"]:
    """:func:`ae_decode` from its layers."""
    g = _tanh(ae_decode_pre(params, z))
    return _tanh(mesh_conv(params["conv_dec"], g, rings.neighbors, rings.mask, rings.degree))


def ae_decode_error(params: dict, z: Float[Array, "b kz"], target: Float[Array, "b v 9"],
                    rings: Rings) -> tuple[Float[Array, "b v 9"], Float[Array, " b"]]:
    """(x_hat, err): :func:`ae_decode` and err_m = sum over (V, 9) of (x_hat_m - target_m)^2, the block's
    reconstruction error per shape. On CPU the native decoder sums it while x_hat is in registers (XLA on CPU
    writes the squared differences of a (blocks, B, V, 9) array out in full before reducing them); its adjoint
    adds 2 derr (x_hat - target) to the cotangent of x_hat and returns the opposite for ``target``."""
    args = _fused_args(params["conv_dec"], z, params["C"], rings)
    if args is None or jnp.result_type(target) != args[0].dtype or target.shape != z.shape[:-1] + (
            params["C"].shape[-1] // MU, MU):
        x_hat = ae_decode(params, z, rings)
        return x_hat, jnp.sum(jnp.square(x_hat - target), axis=(-2, -1))
    zz, nbr, counts, inv, wp, wn, b, c = args
    return _decode_error_native(zz, target, nbr, counts, inv, wp, wn, b, c)


def _latent_code(params: dict, x: Float[Array, "b v 9"], rings: Rings, latent: str) -> Float[Array, "b kz"]:
    z = ae_encode(params, x, rings)
    return jnp.tanh(z) if latent == "tanh" else z


def ae_forward(params: dict, x: Float[Array, "b v 9"], rings: Rings,
               latent: str = "linear") -> tuple[Float[Array, "b kz"], Float[Array, "b v 9"]]:
    """(z, x_hat) of one autoencoder block; ``latent="tanh"`` puts a tanh on z (see the module docstring)."""
    z = _latent_code(params, x, rings, latent)
    return z, ae_decode(params, z, rings)


def ae_forward_error(params: dict, x: Float[Array, "b v 9"], rings: Rings, latent: str = "linear",
                     decoder_c: Array | None = None) -> tuple:
    """(z, x_hat, err) of one block: :func:`ae_forward` and the squared error of x_hat against the block's own
    input x per shape (:func:`ae_decode_error`). ``decoder_c``: the decoder's C passed apart (the values of
    ``params["C"]``), so that the gradient comes back in two parts, the encoder's and the decoder's (an optimizer
    that adds them in its own pass, see ``components.train``)."""
    z = _latent_code(params, x, rings, latent)
    dec = params if decoder_c is None else {**params, "C": decoder_c}
    x_hat, err = ae_decode_error(dec, z, x, rings)
    return z, x_hat, err


@jax.custom_vjp
def _masked_blocks_native(x, am, nbr, counts, inv, ewp, ewn, eb, dwp, dwn, db, c, c_dec):
    return _masked_blocks_native_fwd(x, am, nbr, counts, inv, ewp, ewn, eb, dwp, dwn, db, c, c_dec)[0]


def _masked_blocks_native_fwd(x, am, nbr, counts, inv, ewp, ewn, eb, dwp, dwn, db, c, c_dec):
    xb = jnp.expand_dims(x, -4)  # (..., 1, P, V, 9): broadcast over the blocks of each x
    z, h = native.ae_encoder_forward_masked(xb, am, nbr, counts, inv, ewp, ewn, eb, c)
    x_hat, S, err = native.ae_decoder_forward_error_masked(z, xb, am, nbr, counts, inv, dwp, dwn, db, c_dec)
    return (z, x_hat, err), (x, am, nbr, counts, inv, ewp, ewn, eb, dwp, dwn, db, c, c_dec, z, h, x_hat, S)


def _masked_blocks_native_bwd(res, cotangents):
    x, am, nbr, counts, inv, ewp, ewn, eb, dwp, dwn, db, c, c_dec, z, h, x_hat, S = res
    dz, dx_hat, derr = cotangents
    # the decoders' pre-activation cotangent, over rows of 9V (see _tanh): (dx_hat + 2 derr (x_hat - am x))
    # (1 - x_hat^2)
    flat = x_hat.shape[:-2] + (-1,)
    rows = jnp.broadcast_to(am[..., None], am.shape + (MU,)).reshape(am.shape[:-1] + (1, -1))
    xh = x_hat.reshape(flat)
    d = dx_hat.reshape(flat) + 2 * derr[..., None] * (xh - rows * jnp.expand_dims(x, -4).reshape(x.shape[:-3] + (1,) + flat[-2:]))
    dpre = (d - d * xh * xh).reshape(x_hat.shape)
    dz_dec, gdwp, gdwn, gdb, dc_dec = native.decoder_adjoint(z, S, dpre, nbr, counts, inv, dwp, dwn, db, c_dec)
    dxb, gewp, gewn, geb, dc = native.ae_encoder_backward_masked(
        jnp.expand_dims(x, -4), am, h, dz + dz_dec, x_hat, derr, nbr, counts, inv, ewp, ewn, eb, c)
    return (dxb.reshape(x.shape), jnp.zeros_like(am), None, None, None, gewp, gewn, geb, gdwp, gdwn, gdb, dc, dc_dec)


_masked_blocks_native.defvjp(_masked_blocks_native_fwd, _masked_blocks_native_bwd)


def masked_blocks_error(params: dict, x: Float[Array, "n b v 9"], am: Float[Array, "n k v"], rings: Rings,
                        decoder_c: Array | None = None) -> tuple:
    """(z, x_hat, err) of blocks (n, k) on their masked inputs: block (j, m) (parameters stacked (n, k, ...))
    runs :func:`ae_forward_error` (linear latent) on am[j, m, :, None] x[j], its error against that same input.
    Seed 000's children of a level's last blocks: n parents, k children each, am the parents' attention masks.

    The same values as the vmapped blocks on the materialized inputs; the masks get no gradient. On CPU the native
    kernels read x and am instead of the (n, k, B, V, 9) inputs, and the adjoint returns x's cotangent summed over
    the children (the encoder's adjoint adds the target term of each decoder's error); only the decoders'
    pre-activation cotangent is formed in XLA, in one fusion with am x.
    ``decoder_c``: the decoders' C apart (see :func:`ae_forward_error`)."""
    c_dec = params["C"] if decoder_c is None else decoder_c
    args = _fused_args(params["conv_enc"], x, params["C"], rings)
    dec = _fused_args(params["conv_dec"], x, c_dec, rings)
    if args is None or dec is None or jnp.result_type(am) != args[0].dtype:
        am = jax.lax.stop_gradient(am)
        inputs = am[..., None, :, None] * x[:, None]
        blocks = lambda q, cd, xin: ae_forward_error(q, xin, rings, "linear", cd)  # noqa: E731
        return jax.vmap(jax.vmap(blocks))(params, c_dec, inputs)
    xx, nbr, counts, inv, ewp, ewn, eb, c = args
    _, _, _, _, dwp, dwn, db, cd = dec
    return _masked_blocks_native(xx, jax.lax.stop_gradient(am), nbr, counts, inv, ewp, ewn, eb, dwp, dwn, db, c, cd)
