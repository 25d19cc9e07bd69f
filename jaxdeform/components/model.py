"""The multiscale model of seed 000: stacked autoencoder blocks linked by attention masks (Sec. 4.1-4.2).

Level 0 is one autoencoder block AE0 (Kz_0 components, sparsity cut-off d_0) on the scaled ACAP features X.
Every block of level l hands its residual X_res = X_in - X^ to Kz_l blocks of level l + 1, block k receiving
diag(AM_k) X_res with the attention masks of its parent's fully connected parameter C (eqs. 4-6):

    am_k,i = sum_j C_k,(i,j)^2  (row k of C reshaped to (V, 9)),    AM_k,i = am_k,i / sum_k' am_k',i,

so the children's inputs add up to the parent's residual. Without attention (the Table 4 ablation) every
child receives the whole residual. The model's reconstruction is the sum of every block's output; the loss is
the sum over blocks of lambda1 L_recon + lambda2 Omega(C) + V(Z) (eq. 2), each block against its own input.

The model is a flax nnx Module, :class:`Model`: its :class:`Config` and one
:class:`~jaxdeform.nn.graph_conv.AEBlock` per level, whose arrays are stacked along a leading axis of size
n_l = Kz_0 ... Kz_(l-1); the blocks of a level run under ``jax.vmap`` (nnx Modules are pytrees): no Python loop
over blocks. :func:`forward_levels` runs a sequence of levels (training merges its split state into them).

Three options of :class:`Config` give the block of Tan et al.'s public TF1 code (convMesh, which seed 000 builds
on) where it differs from this one (:mod:`experiments.components.reference_variants` trains them); their
defaults are this project's block:

- ``init="normal"``: every weight (both convolutions' W_point and W_neighbor, and C) drawn from
  N(0, ``init_std``^2), as convMesh's ``tf.random_normal_initializer(stddev=0.02)``; default Glorot-uniform.
- ``tie_conv=True``: the decoder's convolution uses the encoder's W_point and W_neighbor (its bias its own), as
  convMesh does and as the paper's Fig. 1 caption reads ("the encoder and decoder share the same trainable
  parameters"); the blocks then hold no decoder weights of their own (``conv_dec`` has only ``b``).
- ``decoder_tanh=False``: no tanh on z C, x_hat = tanh(conv_dec(reshape(z C))), as convMesh has it; default
  tanh(conv_dec(tanh(reshape(z C)))), the paper's "all the layers use the tanh".

Every decoding reads the model's own configuration (:meth:`Model.decode_latents`, :func:`decoder_blocks`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Float

from jaxdeform.nn import graph_conv
from jaxdeform.nn.graph_conv import (
    MU,
    AEBlock,
    MeshConv,
    Rings,
    ae_decode_pre,
    ae_encode,
    ae_forward,
    ae_forward_error,
    init_ae_block,
    masked_blocks_error,
)
from jaxdeform.nn.losses import group_sparsity, latent_bound


@dataclasses.dataclass(frozen=True)
class Config:
    """Hyper-parameters (defaults: the paper's, Sec. 4.4). ``kz[l]`` and ``d[l]`` per level."""

    kz: tuple[int, ...] = (10, 5)
    d: tuple[float, ...] = (0.4, 0.2)
    lambda_recon: float = 10.0
    lambda_sparse: float = 1.0
    lambda_latent: float = 1.0  # weight of V(Z): 1 in eq. (2); Tan et al.'s public code uses 0.5
    theta: float = 5.0
    attention: bool = True
    # Whether the loss gradient flows through the attention masks into the parent's C. The paper derives AM
    # from C (eqs. 4-6) without saying; with the gradient on, joint training on horse-gallop is unstable (the
    # loss climbs back up late in training) and the test Erms is several times higher; with the masks held
    # constant in the gradient (they still follow C as C trains), the loss is stable.
    attention_gradient: bool = False
    mask: str = "step"  # "step": seed 000's eq. (3) with cut-off d[l]; "linear": Tan et al.'s clipped ramp
    mask_range: tuple[float, float] = (0.2, 0.4)  # (d_min, d_max) of the "linear" mask
    # Activation of the latent code z = act(flatten(tanh(conv_enc(x))) C^T). "linear" (default): Tan et al.'s
    # public code (z unbounded, V(Z) keeps it near theta). "tanh": the paper's "all the layers use the tanh
    # activation function" read literally (V(Z) is then zero); on horse-gallop AE0's codes then saturate at
    # |z| ~ 40-70 before the tanh, AE0 outputs a near-constant shape and the second level carries the
    # deformation (named configuration "latent-tanh" in components/run.py).
    latent: str = "linear"
    # The block of Tan et al.'s public code, detail by detail (module docstring); the defaults are this project's.
    init: str = "glorot"  # "glorot": Glorot-uniform weights; "normal": N(0, init_std^2); biases zero either way
    init_std: float = 0.02  # standard deviation of init="normal" (convMesh's)
    tie_conv: bool = False  # the decoder's convolution uses the encoder's W_point and W_neighbor
    decoder_tanh: bool = True  # tanh on the decoder's z C before its convolution
    # L_recon of a block: "sum": the mean over shapes of the squared errors summed over the 9 V entries (this
    # project's reading of Sec. 4.1's 1/N sum_i ||X_i - X^_i||^2); "mean": also averaged over the 9 V entries
    # (the section's "MSE" read literally), which weighs the sparsity and latent terms 9 V times more.
    recon: str = "sum"

    def __post_init__(self):
        if len(self.kz) != len(self.d) or not self.kz:
            raise ValueError(f"kz {self.kz} and d {self.d} must give one entry per level (at least one).")
        if min(self.kz) < 1 or not all(0 < x <= 1 for x in self.d):
            raise ValueError("every kz must be >= 1 and every d in (0, 1].")
        if self.mask not in ("step", "linear"):
            raise ValueError(f"mask must be 'step' or 'linear', got {self.mask!r}.")
        if self.latent not in ("linear", "tanh"):
            raise ValueError(f"latent must be 'linear' or 'tanh', got {self.latent!r}.")
        if self.init not in ("glorot", "normal"):
            raise ValueError(f"init must be 'glorot' or 'normal', got {self.init!r}.")
        if not self.init_std > 0:
            raise ValueError(f"init_std must be positive, got {self.init_std}.")
        if self.recon not in ("sum", "mean"):
            raise ValueError(f"recon must be 'sum' or 'mean', got {self.recon!r}.")

    def sparsity_cutoff(self, level: int):
        """The ``d`` argument of :func:`group_sparsity` for ``level``."""
        return self.d[level] if self.mask == "step" else tuple(self.mask_range)

    @property
    def levels(self) -> int:
        return len(self.kz)

    def blocks(self, level: int) -> int:
        """Number of autoencoder blocks at ``level``."""
        return math.prod(self.kz[:level])


class Output(NamedTuple):
    reconstruction: Array  # (B, V, 9): sum of every block's output
    loss: Array  # scalar: sum of the blocks' losses
    terms: dict  # per level: recon, sparsity, latent (summed over the level's blocks)
    latents: tuple  # per level: (n_l, B, Kz_l)


class Model(nnx.Module):
    """The multiscale model: its :class:`Config` and one :class:`~jaxdeform.nn.graph_conv.AEBlock` per level
    (``levels[l]``, arrays stacked along a leading axis of the level's ``config.blocks(l)`` blocks).

    Drawn from ``key``: level l's blocks from ``jax.random.split(sub_l, n_l)`` (:func:`init_ae_block` under
    ``jax.vmap``), ``key, sub_l = jax.random.split(key)`` level by level. ``config.init="normal"``: every weight
    (W_point, W_neighbor, C) then redrawn from N(0, init_std^2) with one key of ``jax.random.split(key, 7 L)``
    per array, level by level in the order of :data:`DRAW_ORDER` (biases keep theirs, zero).
    ``config.tie_conv``: the decoders' W_point and W_neighbor dropped (drawn, then dropped: every other array is
    that of the untied model); the decoders read their encoders'.

    **Arguments:**

    - ``n_vertices``: V.
    - ``config``: the model's hyper-parameters (kept as ``self.config``).
    - ``key``: the PRNG key.
    - ``dtype``: the parameters' dtype.
    """

    def __init__(self, n_vertices: int, config: Config, *, key: Array, dtype=jnp.float32):
        self.config = config
        self.n_vertices = int(n_vertices)
        first = key
        levels = []
        for level, kz in enumerate(config.kz):
            key, sub = jax.random.split(key)
            keys = jax.random.split(sub, config.blocks(level))
            levels.append(jax.vmap(lambda k, kz=kz: init_ae_block(k, n_vertices, kz, dtype))(keys))
        if config.init == "normal":
            _normal_weights(levels, first, config.init_std)
        if config.tie_conv:
            for block in levels:
                block.conv_dec = MeshConv(None, None, block.conv_dec.b[...])
        self.levels = nnx.List(levels)

    def __call__(self, x: Float[Array, "b v 9"], rings: Rings, dist: Float[Array, "v v"]) -> Output:
        """:func:`forward_levels` over every level.

        **Arguments:**

        - ``x``: scaled features ``(B, V, 9)``.
        - ``rings``: the mesh's one-rings.
        - ``dist``: normalized geodesic distances ``(V, V)``.

        **Returns:**

        An :class:`Output`.
        """
        return forward_levels(tuple(self.levels), x, rings, dist, self.config)

    def encode(self, x: Float[Array, "b v 9"], rings: Rings) -> tuple:
        """Latent codes of a batch of scaled features.

        **Arguments:**

        - ``x``: scaled features ``(B, V, 9)``.
        - ``rings``: the mesh's one-rings.

        **Returns:**

        Per level ``(n_l, B, Kz_l)``, as in :attr:`Output.latents`.
        """
        return tuple(z for _, z, _, _ in _levels(tuple(self.levels), x, rings, self.config))

    def reconstruction(self, x: Float[Array, "b v 9"], rings: Rings) -> Float[Array, "b v 9"]:
        """The model's reconstruction of a batch of scaled features (the sum of every block's output).

        **Arguments:**

        - ``x``: scaled features ``(B, V, 9)``.
        - ``rings``: the mesh's one-rings.

        **Returns:**

        The reconstruction ``(B, V, 9)``.
        """
        return sum(jnp.sum(x_hat, axis=0) for _, _, x_hat, _ in _levels(tuple(self.levels), x, rings, self.config))

    def first_levels(self, n: int) -> Model:
        """The model of levels 0..n-1 alone (e.g. to measure what level 0 reconstructs by itself).

        **Arguments:**

        - ``n``: the number of levels kept, 1 to ``config.levels``.

        **Returns:**

        A new :class:`Model` on the same arrays whose configuration keeps the first ``n`` entries of ``kz`` and
        ``d``.

        **Raises:**

        ``ValueError`` if ``n`` is out of range.
        """
        if not 1 <= n <= self.config.levels:
            raise ValueError(f"n must lie in 1..{self.config.levels}, got {n}.")
        out = nnx.merge(*nnx.split(self))
        out.config = dataclasses.replace(self.config, kz=self.config.kz[:n], d=self.config.d[:n])
        out.levels = nnx.List(list(out.levels)[:n])
        return out

    def decode_latents(self, latents: tuple, rings: Rings) -> Float[Array, "b v 9"]:
        """Scaled features from latent codes: the sum over every block of its decoder output.

        A block's output depends on its own code only, so components are decoder outputs of one-hot codes and
        editing optimizes these codes.

        **Arguments:**

        - ``latents``: ``latents[l]`` has shape ``(n_l, B, Kz_l)``, as in :attr:`Output.latents`.
        - ``rings``: the mesh's one-rings.

        **Returns:**

        Scaled features ``(B, V, 9)``.
        """
        out = None
        for block, z in zip(decoder_blocks(tuple(self.levels), self.config), latents):
            x_hat = jnp.sum(jax.vmap(lambda q, zz: decode_block(q, zz, rings, self.config))(block, z), axis=0)
            out = x_hat if out is None else out + x_hat
        return out


#: The arrays of one level in the order of ``config.init="normal"``'s keys (:class:`Model`).
DRAW_ORDER = (
    ("C",),
    ("conv_dec", "W_neighbor"),
    ("conv_dec", "W_point"),
    ("conv_dec", "b"),
    ("conv_enc", "W_neighbor"),
    ("conv_enc", "W_point"),
    ("conv_enc", "b"),
)


def _normal_weights(levels: list[AEBlock], key: Array, std: float) -> None:
    """Redraw every weight (W_point, W_neighbor, C) of ``levels`` in place from N(0, std^2); biases kept."""
    keys = jax.random.split(key, len(DRAW_ORDER) * len(levels))
    for i, block in enumerate(levels):
        for j, path in enumerate(DRAW_ORDER):
            if path[-1] == "b":
                continue
            owner = block if len(path) == 1 else getattr(block, path[0])
            var = getattr(owner, path[-1])
            k = keys[i * len(DRAW_ORDER) + j]
            var.set_value((std * jax.random.normal(k, var.shape)).astype(var.dtype))


def decoder_blocks(levels: tuple[AEBlock, ...], config: Config) -> tuple[AEBlock, ...]:
    """The blocks as the decoders read them: with ``config.tie_conv`` every block's ``conv_dec`` takes its
    encoder's W_point and W_neighbor (its bias its own); otherwise ``levels`` itself.

    **Arguments:**

    - ``levels``: one :class:`AEBlock` per level (or a prefix).
    - ``config``: the model's hyper-parameters.

    **Returns:**

    One :class:`AEBlock` per level whose decoders hold weights (new Modules on the same arrays when tied).
    """
    if not config.tie_conv:
        return tuple(levels)
    return tuple(
        AEBlock(b.conv_enc, MeshConv(b.conv_enc.W_point[...], b.conv_enc.W_neighbor[...], b.conv_dec.b[...]), b.C[...])
        for b in levels
    )


def _flat_tanh(x: Array) -> Array:
    # as graph_conv's block: tanh over rows of 9V (XLA on CPU vectorizes along the minor axis)
    return jnp.tanh(x.reshape(x.shape[:-2] + (-1,))).reshape(x.shape)


def decode_block(
    block: AEBlock, z: Float[Array, "b kz"], rings: Rings, config: Config | None = None
) -> Float[Array, "b v 9"]:
    """One block's decoder output from its codes.

    :func:`jaxdeform.nn.graph_conv.ae_decode`, or, with ``config.decoder_tanh`` False, the same without the tanh
    on z C.

    **Arguments:**

    - ``block``: one :class:`AEBlock` whose decoder holds weights (:func:`decoder_blocks` for tied models).
    - ``z``: codes ``(B, Kz)``.
    - ``rings``: the mesh's one-rings.
    - ``config``: the model's hyper-parameters (default None: the default decoder).

    **Returns:**

    Scaled features ``(B, V, 9)``.
    """
    if config is None or config.decoder_tanh:
        return graph_conv.ae_decode(block, z, rings)
    return _flat_tanh(block.conv_dec(ae_decode_pre(block, z), rings))


def _masked_blocks(p: AEBlock, x, am, rings: Rings, config: Config) -> tuple:
    """(z, x_hat, err) of blocks (n, k) on their masked inputs, as :func:`masked_blocks_error` (which it is for
    the default decoder), the block's decoder that of ``config``; the masks take no gradient."""
    if config.decoder_tanh:
        return masked_blocks_error(p, x, am, rings)
    am = jax.lax.stop_gradient(am)
    inputs = am[..., None, :, None] * x[:, None]
    return jax.vmap(jax.vmap(lambda q, xin: _block(q, xin, rings, config, True)))(p, inputs)


def _block(p: AEBlock, x: Float[Array, "b v 9"], rings: Rings, config: Config, with_error: bool) -> tuple:
    """(z, x_hat, err or None) of one block on its input ``x``; err: the summed squared error per shape."""
    if config.decoder_tanh:  # graph_conv's block
        if with_error:
            return ae_forward_error(p, x, rings, config.latent)
        return ae_forward(p, x, rings, config.latent) + (None,)
    z = ae_encode(p, x, rings)
    if config.latent == "tanh":
        z = jnp.tanh(z)
    x_hat = decode_block(p, z, rings, config)
    if not with_error:
        return z, x_hat, None
    flat = x_hat.shape[:-2] + (-1,)
    return z, x_hat, jnp.sum(jnp.square(x_hat.reshape(flat) - x.reshape(flat)), axis=-1)


def attention_masks(c: Float[Array, "kz nine_v"]) -> Float[Array, "kz v"]:
    """Normalized attention masks AM of one block's C (eqs. 4-6).

    **Arguments:**

    - ``c``: the block's C ``(Kz, 9 V)``.

    **Returns:**

    The masks ``(Kz, V)``; columns sum to one (zero columns stay zero).
    """
    am = jnp.sum(c.reshape(c.shape[0], -1, MU) ** 2, axis=-1)
    total = jnp.sum(am, axis=0, keepdims=True)
    return am / jnp.where(total > 0, total, 1.0)


def _levels(
    levels: tuple[AEBlock, ...], x: Float[Array, "b v 9"], rings: Rings, config: Config, with_error: bool = False
) -> list:
    """Per level: (inputs (n_l, B, V, 9), latents (n_l, B, Kz_l), outputs (n_l, B, V, 9), errors (n_l, B) or
    None): ``with_error`` gives each block's summed squared error against its input, per shape.

    With ``with_error``, the last level's blocks run on their masked inputs (:func:`masked_blocks_error`: the
    parents' residuals and attention masks, the inputs not formed) where the masks take no gradient and the
    latent is linear; that level's inputs are then None. ``config.tie_conv``: the
    decoders read their encoders' convolution weights."""
    blocks = decoder_blocks(levels, config)
    inputs = x[None]  # (n_0 = 1, B, V, 9)
    parent = None  # (residuals (n_l, B, V, 9), masks (n_l, Kz_l, V)) of the level before, where attention applies
    levels = []
    for level, p in enumerate(blocks):
        if (
            with_error
            and parent is not None
            and level + 1 == len(blocks)
            and not config.attention_gradient
            and config.latent == "linear"
        ):
            res, am = parent
            split = lambda a: a.reshape(am.shape[:2] + a.shape[1:])  # noqa: E731  (n_l, ...) -> (parents, Kz, ...)
            outs = _masked_blocks(jax.tree_util.tree_map(split, p), res, am, rings, config)
            z, x_hat, err = (a.reshape((-1,) + a.shape[2:]) for a in outs)
            levels.append((None, z, x_hat, err))
            break
        z, x_hat, err = jax.vmap(lambda q, xin: _block(q, xin, rings, config, with_error))(p, inputs)
        levels.append((inputs, z, x_hat, err))
        if level + 1 < len(blocks):
            res = inputs - x_hat  # (n_l, B, V, 9)
            kz = config.kz[level]
            if config.attention:
                am = jax.vmap(attention_masks)(p.C[...])  # (n_l, Kz_l, V)
                if not config.attention_gradient:
                    am = jax.lax.stop_gradient(am)
                parent = (res, am)
                # over flat (V * 9) rows: XLA on CPU runs this product and its adjoint (a sum over the Kz
                # children) along the minor axis, which is 9 long in the (..., V, 9) layout (10x slower)
                n_l, b = res.shape[:2]
                am_rows = jnp.broadcast_to(am[..., None], am.shape + (MU,)).reshape(n_l, kz, 1, -1)
                children = am_rows * res.reshape(n_l, 1, b, -1)
            else:
                children = jnp.broadcast_to(res[:, None], (res.shape[0], kz) + res.shape[1:])
            inputs = children.reshape((-1,) + res.shape[1:])  # block j of level l+1: parent j // kz, mask j % kz
    return levels


def level_sparsity(block: AEBlock, dist: Float[Array, "v v"], config: Config, level: int) -> Float[Array, " k"]:
    """Omega(C) (eq. 3) of every block of one level.

    **Arguments:**

    - ``block``: that level's :class:`AEBlock` (C stacked over its blocks).
    - ``dist``: normalized geodesic distances ``(V, V)``.
    - ``config``: the model's hyper-parameters.
    - ``level``: the level's index (its sparsity cut-off).

    **Returns:**

    One value per block ``(n_l,)``.
    """
    return jax.vmap(lambda c: group_sparsity(c, dist, config.sparsity_cutoff(level), config.mask))(block.C[...])


def forward_levels(
    levels: tuple[AEBlock, ...], x: Float[Array, "b v 9"], rings: Rings, dist: Float[Array, "v v"], config: Config
) -> Output:
    """Run every level on a batch of scaled features and return the reconstruction and the total loss.

    :meth:`Model.__call__` on all of a model's levels; training runs it on (the merged state of) a prefix.

    **Arguments:**

    - ``levels``: one :class:`AEBlock` per level; may hold fewer levels than ``config`` (a prefix: used by
        separate, level-by-level training).
    - ``x``: scaled features ``(B, V, 9)``.
    - ``rings``: the mesh's one-rings.
    - ``dist``: normalized geodesic distances ``(V, V)``.
    - ``config``: the model's hyper-parameters.

    **Returns:**

    An :class:`Output`: reconstruction ``(B, V, 9)``, total loss, the loss terms per level and the latent codes.
    """
    total = jnp.zeros((), x.dtype)
    recon = jnp.zeros_like(x)
    terms, latents = [], []
    outs = _levels(tuple(levels), x, rings, config, True)
    for level, (p, (_, z, x_hat, err)) in enumerate(zip(levels, outs)):
        rec_l = jnp.mean(err, axis=-1)  # L_recon of each block: the mean over shapes of the summed squares
        if config.recon == "mean":
            rec_l = rec_l / (x.shape[-2] * x.shape[-1])
        sparse_l = level_sparsity(p, dist, config, level)
        latent_l = jax.vmap(lambda zz: latent_bound(zz, config.theta))(z)
        total = total + jnp.sum(
            config.lambda_recon * rec_l + config.lambda_sparse * sparse_l + config.lambda_latent * latent_l
        )
        recon = recon + jnp.sum(x_hat, axis=0)
        terms.append({"recon": jnp.sum(rec_l), "sparsity": jnp.sum(sparse_l), "latent": jnp.sum(latent_l)})
        latents.append(z)
    return Output(recon, total, terms, tuple(latents))
