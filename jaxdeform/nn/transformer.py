"""A small sequence-to-sequence Transformer (Vaswani et al. 2017) in flax nnx, with no mesh knowledge.

Used by the DeformTransformer of seed 002 (Sec. 3.3, Fig. 5: 2 encoder + 2 decoder blocks, 8 heads,
sinusoidal positions, causal mask in the decoder). Inputs are already embedded to ``d_model`` channels;
sequences are short (a window of a few frames), so attention is computed densely.

Scaled dot-product attention with H heads of width d_k = d_model / H::

    head_h = softmax(Q_h K_h^T / sqrt(d_k) + mask) V_h,   MHA(x_q, x_kv) = concat_h(head_h) W_o
    Q = x_q W_q + b_q,  K = x_kv W_k + b_k,  V = x_kv W_v + b_v

Masked entries (``mask == False``) get -1e9 before the softmax (not -inf, so a fully masked row stays finite).

Post-LN blocks as in the original paper (residual, then LayerNorm, eps 1e-6)::

    encoder: x <- LN(x + Drop(MHA(x, x)));          x <- LN(x + Drop(FFN(x)))
    decoder: y <- LN(y + Drop(MHA(y, y, causal)));   y <- LN(y + Drop(MHA(y, enc)));   y <- LN(y + Drop(FFN(y)))
    FFN(x) = ReLU(x W_1 + b_1) W_2 + b_2   (frame-wise, width ``ffn``)

Sinusoidal positional encoding (Vaswani et al. Sec. 3.5), position p = 0, 1, ..., channel pairs i::

    PE[p, 2i] = sin(p / 10000^(2i / d)),   PE[p, 2i + 1] = cos(p / 10000^(2i / d))

added to the encoder and decoder inputs (no sqrt(d_model) scaling of the inputs: they are linear
projections, not embedding tables). Dropout (Vaswani: 0.1) is off by default (rate 0.0), so the modules are
deterministic; with a rate > 0 it needs ``rngs`` and follows ``module.train()`` / ``module.eval()``.
Defaults: 8 heads, 2 blocks (seed 002); d_model and ffn are the caller's.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, ArrayLike, Bool, Float

NEG_INF = -1e9  # additive mask value


def sinusoidal_encoding(length: int, d_model: int, dtype=jnp.float32) -> Float[Array, "t d"]:
    """The sinusoidal positional encoding PE of the module docstring.

    **Arguments:**

    - `length`: the number of positions.
    - `d_model`: the channels; an odd d_model drops the last cosine channel.
    - `dtype`: the result's dtype.

    **Returns:**

    PE `(length, d_model)`.
    """
    pos = np.arange(length, dtype=np.float64)[:, None]
    i2 = np.arange(0, d_model, 2, dtype=np.float64)[None, :]
    angle = pos / np.power(10000.0, i2 / d_model)
    pe = np.zeros((length, d_model), np.float64)
    pe[:, 0::2] = np.sin(angle)
    pe[:, 1::2] = np.cos(angle)[:, : d_model // 2]
    return jnp.asarray(pe, dtype)


def causal_mask(length: int) -> Bool[Array, "t t"]:
    """The causal attention mask.

    **Arguments:**

    - `length`: the sequence length.

    **Returns:**

    A bool mask `(length, length)` with mask[q, k] = k <= q: position q attends to itself and earlier
    positions only.
    """
    return jnp.tril(jnp.ones((length, length), bool))


class MultiHeadAttention(nnx.Module):
    """MHA(x_q, x_kv, mask) of the module docstring.

    **Arguments:**

    - `d_model`: the channels, divisible by `heads`.
    - `heads`: the number of heads H.
    - `rngs`: the parameter initialisers' random streams.

    Calling it takes `x_q` `(..., T_q, d)`, `x_kv` `(..., T_k, d)` and an optional bool `mask` that broadcasts
    to `(..., T_q, T_k)` (True = attend), and returns `(..., T_q, d)`.

    **Raises:**

    `ValueError` when `d_model` is not divisible by `heads`.
    """

    def __init__(self, d_model: int, heads: int = 8, *, rngs: nnx.Rngs):
        if d_model % heads:
            raise ValueError(f"d_model {d_model} is not divisible by the number of heads {heads}.")
        self.heads = heads
        self.d_k = d_model // heads
        self.q = nnx.Linear(d_model, d_model, rngs=rngs)
        self.k = nnx.Linear(d_model, d_model, rngs=rngs)
        self.v = nnx.Linear(d_model, d_model, rngs=rngs)
        self.o = nnx.Linear(d_model, d_model, rngs=rngs)

    def _split(self, x: Float[Array, "... t d"]) -> Float[Array, "... h t dk"]:
        x = x.reshape(x.shape[:-1] + (self.heads, self.d_k))
        return jnp.swapaxes(x, -2, -3)

    def __call__(
        self,
        x_q: Float[ArrayLike, "... tq d"],
        x_kv: Float[ArrayLike, "... tk d"],
        mask: Bool[ArrayLike, ...] | None = None,
    ) -> Float[Array, "... tq d"]:
        q, k, v = self._split(self.q(x_q)), self._split(self.k(x_kv)), self._split(self.v(x_kv))
        logits = (q @ jnp.swapaxes(k, -1, -2)) / math.sqrt(self.d_k)  # (..., h, tq, tk)
        if mask is not None:
            logits = jnp.where(mask[..., None, :, :] if mask.ndim >= 3 else mask, logits, NEG_INF)
        attn = jax.nn.softmax(logits, axis=-1)
        out = jnp.swapaxes(attn @ v, -2, -3)  # (..., tq, h, dk)
        return self.o(out.reshape(out.shape[:-2] + (self.heads * self.d_k,)))


class FeedForward(nnx.Module):
    """Frame-wise FFN(x) = ReLU(x W_1 + b_1) W_2 + b_2.

    **Arguments:**

    - `d_model`: the input and output channels.
    - `ffn`: the hidden width.
    - `rngs`: the parameter initialisers' random streams.

    Calling it maps `(..., d)` to `(..., d)`.
    """

    def __init__(self, d_model: int, ffn: int, *, rngs: nnx.Rngs):
        self.w1 = nnx.Linear(d_model, ffn, rngs=rngs)
        self.w2 = nnx.Linear(ffn, d_model, rngs=rngs)

    def __call__(self, x: Float[ArrayLike, "... d"]) -> Float[Array, "... d"]:
        return self.w2(jax.nn.relu(self.w1(x)))


def _dropout(rate: float, rngs: nnx.Rngs | None):
    if rate <= 0.0:
        return None
    if rngs is None:
        raise ValueError("dropout with a rate above 0 needs rngs.")
    return nnx.Dropout(rate, rngs=rngs)


def _drop(layer, x):
    return x if layer is None else layer(x)


class EncoderBlock(nnx.Module):
    """Post-LN encoder block: self-attention and FFN, each with residual + LayerNorm.

    **Arguments:**

    - `d_model`, `heads`, `ffn`: as :class:`MultiHeadAttention` and :class:`FeedForward`.
    - `dropout`: the dropout rate (0: none; above 0 it needs `rngs`).
    - `rngs`: the random streams.

    Calling it maps `x` `(..., T, d)` with an optional attention `mask` to `(..., T, d)`.

    **Raises:**

    `ValueError` for dropout above 0 without `rngs`.
    """

    def __init__(self, d_model: int, heads: int, ffn: int, dropout: float = 0.0, *, rngs: nnx.Rngs):
        self.attn = MultiHeadAttention(d_model, heads, rngs=rngs)
        self.ffn = FeedForward(d_model, ffn, rngs=rngs)
        self.ln1 = nnx.LayerNorm(d_model, rngs=rngs)
        self.ln2 = nnx.LayerNorm(d_model, rngs=rngs)
        self.drop = _dropout(dropout, rngs)

    def __call__(
        self, x: Float[ArrayLike, "... t d"], mask: Bool[ArrayLike, ...] | None = None
    ) -> Float[Array, "... t d"]:
        x = self.ln1(x + _drop(self.drop, self.attn(x, x, mask)))
        return self.ln2(x + _drop(self.drop, self.ffn(x)))


class DecoderBlock(nnx.Module):
    """Post-LN decoder block: causal self-attention, cross-attention over the encoder output, FFN.

    **Arguments:**

    - `d_model`, `heads`, `ffn`, `dropout`, `rngs`: as :class:`EncoderBlock`.

    Calling it maps `y` `(..., T_t, d)` and the encoder output `memory` `(..., T_s, d)`, with optional
    `self_mask` and `memory_mask`, to `(..., T_t, d)`.
    """

    def __init__(self, d_model: int, heads: int, ffn: int, dropout: float = 0.0, *, rngs: nnx.Rngs):
        self.self_attn = MultiHeadAttention(d_model, heads, rngs=rngs)
        self.cross_attn = MultiHeadAttention(d_model, heads, rngs=rngs)
        self.ffn = FeedForward(d_model, ffn, rngs=rngs)
        self.ln1 = nnx.LayerNorm(d_model, rngs=rngs)
        self.ln2 = nnx.LayerNorm(d_model, rngs=rngs)
        self.ln3 = nnx.LayerNorm(d_model, rngs=rngs)
        self.drop = _dropout(dropout, rngs)

    def __call__(
        self,
        y: Float[ArrayLike, "... tt d"],
        memory: Float[ArrayLike, "... ts d"],
        self_mask: Bool[ArrayLike, ...] | None = None,
        memory_mask: Bool[ArrayLike, ...] | None = None,
    ) -> Float[Array, "... tt d"]:
        y = self.ln1(y + _drop(self.drop, self.self_attn(y, y, self_mask)))
        y = self.ln2(y + _drop(self.drop, self.cross_attn(y, memory, memory_mask)))
        return self.ln3(y + _drop(self.drop, self.ffn(y)))


class Transformer(nnx.Module):
    """`blocks` encoder and `blocks` decoder blocks; positions added to both inputs; causal decoder.

    `__call__(src (..., Ts, d), tgt (..., Tt, d)) -> (..., Tt, d)`: output position k depends on all of
    `src` and on `tgt[..., :k + 1, :]` only.

    **Arguments:**

    - `d_model`: the channels, divisible by `heads`.
    - `heads`: the number of attention heads.
    - `blocks`: the number of encoder (and of decoder) blocks, at least 1.
    - `ffn`: the feed-forward width; None: 4 d_model.
    - `dropout`: the dropout rate (0: none, deterministic).
    - `rngs`: the random streams.

    **Raises:**

    `ValueError` for fewer than one block, `d_model` not divisible by `heads`, or dropout without `rngs`.
    """

    def __init__(
        self,
        d_model: int,
        heads: int = 8,
        blocks: int = 2,
        ffn: int | None = None,
        dropout: float = 0.0,
        *,
        rngs: nnx.Rngs,
    ):
        if blocks < 1:
            raise ValueError(f"a Transformer needs at least one block, got {blocks}.")
        ffn = 4 * d_model if ffn is None else int(ffn)
        self.d_model = d_model
        self.encoder = nnx.List([EncoderBlock(d_model, heads, ffn, dropout, rngs=rngs) for _ in range(blocks)])
        self.decoder = nnx.List([DecoderBlock(d_model, heads, ffn, dropout, rngs=rngs) for _ in range(blocks)])

    def encode(self, src: Float[ArrayLike, "... ts d"]) -> Float[Array, "... ts d"]:
        """The encoder stack (positions added).

        **Arguments:**

        - `src`: source sequence `(..., Ts, d)`.

        **Returns:**

        The memory `(..., Ts, d)`.
        """
        x = src + sinusoidal_encoding(src.shape[-2], self.d_model, src.dtype)
        for block in self.encoder:
            x = block(x)
        return x

    def decode(
        self, tgt: Float[ArrayLike, "... tt d"], memory: Float[ArrayLike, "... ts d"]
    ) -> Float[Array, "... tt d"]:
        """The causal decoder stack (positions added).

        **Arguments:**

        - `tgt`: target sequence `(..., Tt, d)`.
        - `memory`: the encoder output `(..., Ts, d)`.

        **Returns:**

        `(..., Tt, d)`; position k depends on `tgt[..., :k + 1, :]` only.
        """
        y = tgt + sinusoidal_encoding(tgt.shape[-2], self.d_model, tgt.dtype)
        mask = causal_mask(tgt.shape[-2])
        for block in self.decoder:
            y = block(y, memory, mask)
        return y

    def __call__(
        self, src: Float[ArrayLike, "... ts d"], tgt: Float[ArrayLike, "... tt d"]
    ) -> Float[Array, "... tt d"]:
        return self.decode(tgt, self.encode(src))
