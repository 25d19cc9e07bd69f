"""DeformTransformer of seed 002 (Sec. 3.3 and 4, Fig. 5) and its two ablations, in flax nnx.

The model maps windows of SCALED coarse features to scaled fine features (feature extraction, scaling to
[-0.95, 0.95] and reconstruction are the caller's, :mod:`jaxdeform.acap.features`). ``in_channels`` is 9
for (TS-)ACAP features and 3 for the coordinates ablation.

Mesh encoder, one per resolution (paper Sec. 4: "two convolutional layers with tanh ... In the last
convolutional layer we abandon the activation function ... A fully connected layer is used to map the
output of the convolutional layers into a 16-dimensional latent space")::

    h = tanh(conv_1(x));  h = conv_2(h);  z = flatten(h) W_fc + b_fc          x (V, Cin) -> z (latent,)

conv is the mesh convolution of eq. (5), :func:`jaxdeform.nn.graph_conv.mesh_conv`; conv_1: Cin -> C,
conv_2: C -> C with C = ``conv_channels`` (default 9, as the input). z is linear (no activation).

Fine decoder (the paper does not describe it; our choice mirrors the encoder)::

    g = tanh(reshape(z W_dec + b_dec));  g = tanh(conv_3(g));  y = tanh(conv_4(g))     z -> y (Vf, Cin)

with conv_3: C -> C, conv_4: C -> Cin; the final tanh keeps outputs inside (-1, 1) like the scaled features.
With ``skip`` (off by default) conv_3 also reads the coarse frame's own scaled features interpolated to the
fine vertices, U x_c (U the Loop subdivision weights, (Vf, Vc)): g = tanh([g, U x_c] conv_3). The global
16-d latent then carries what changes over the whole cloth and the convolutions add what follows the local
coarse deformation, which a per-frame code learnt from a few thousand frames cannot place vertex by vertex.

Temporal module over a window of W frames (paper: W = 3), from coarse latents c_1..c_W and the fine latents
p_1..p_W of the fine frames *before* each target frame (p_k = enc_fine(fine frame k - 1), the encoding of an
all-zero feature frame before the sequence start):

- ``kind="transformer"`` (DeformTransformer): u_k = c_k W_c (16 -> d_model), v_k = p_k W_p, then
  :class:`jaxdeform.nn.transformer.Transformer` (``blocks`` encoder + ``blocks`` decoder blocks, ``heads``
  heads, sinusoidal positions, causal decoder) over u (encoder) and v (decoder), then d_model -> 16.
  The latent is 16 (paper) but 8 heads need d_model divisible by 8 and wider than 8 x 2: we project to
  ``d_model`` = 64 (8 channels per head) and back; FFN width ``ffn`` = 256 (4 d_model, Vaswani et al.).
- ``kind="lstm"`` (ablation "RNN/LSTM"): an LSTM (hidden ``d_model``) over x_k = [c_k, p_k] (``lstm_fine_input``
  True, default) or x_k = c_k, state reset at the window start, then hidden -> 16. Gates::

      [i, f, g, o] = x_k W_x + h_{k-1} W_h + b,  c = sig(f) c + sig(i) tanh(g),  h = sig(o) tanh(c)

  (forget-gate bias initialised to 1).
- ``kind="none"`` (ablation "without Transformer"): frame-wise z_k = W_2 tanh(W_1 c_k + b_1) + b_2 (width
  ``d_model``); the fine input is ignored (and no fine encoder exists).

Output position k depends on the coarse window and on p_1..p_k only (causality), so teacher forcing
(training, :mod:`jaxdeform.cloth.train`) and autoregressive synthesis read the same function.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float

from jaxdeform.nn.archive import RecordConfig
from jaxdeform.nn.graph_conv import Rings, mesh_conv
from jaxdeform.nn.transformer import Transformer

KINDS = ("transformer", "lstm", "none")


@dataclasses.dataclass(frozen=True)
class ModelConfig(RecordConfig):
    """Architecture of :class:`DetailModel` (defaults: paper Sec. 4 where it says, else the module docstring)."""

    kind: str = "transformer"  # "transformer" | "lstm" | "none"
    in_channels: int = 9  # 9 for (TS-)ACAP features, 3 for the coordinates ablation
    latent: int = 16  # paper: 16-d latent per frame and resolution
    conv_channels: int = 9  # channels inside the mesh conv layers (paper: as the input)
    d_model: int = 64  # transformer width (latent 16 projected to it) / LSTM hidden / no-temporal MLP width
    heads: int = 8  # paper: 8-head attention
    blocks: int = 2  # paper: N = 2 encoder and 2 decoder blocks
    ffn: int = 256  # transformer feed-forward width (4 d_model)
    window: int = 3  # paper: 3 input frames
    dropout: float = 0.0  # transformer dropout (off: deterministic)
    lstm_fine_input: bool = True  # LSTM also reads the previous fine latent
    skip: bool = False  # the fine decoder also reads the coarse features interpolated to the fine mesh
    seed: int = 0  # parameter initialisation

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"model kind must be one of {', '.join(KINDS)}, got {self.kind!r}.")
        for name in ("in_channels", "latent", "conv_channels", "d_model", "heads", "blocks", "ffn", "window"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"model {name} must be a positive integer, got {getattr(self, name)!r}.")
        if self.kind == "transformer" and self.d_model % self.heads:
            raise ValueError(f"d_model {self.d_model} must be divisible by the number of heads {self.heads}.")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must lie in [0, 1), got {self.dropout}.")


class RingBuffer(nnx.Variable):
    """Connectivity arrays (padded one-rings) held by the model: saved with it, never optimised."""


def _glorot(key: Array, shape: tuple[int, int]) -> Array:
    limit = jnp.sqrt(6.0 / (shape[0] + shape[1]))
    return jax.random.uniform(key, shape, jnp.float32, -limit, limit)


class MeshConv(nnx.Module):
    """One mesh convolution of eq. (5), no activation: ``x W_point + mean_ring(x) W_neighbor + b``."""

    def __init__(self, cin: int, cout: int, *, rngs: nnx.Rngs):
        self.w_point = nnx.Param(_glorot(rngs.params(), (cin, cout)))
        self.w_neighbor = nnx.Param(_glorot(rngs.params(), (cin, cout)))
        self.b = nnx.Param(jnp.zeros((cout,), jnp.float32))

    def __call__(self, x: Float[Array, "b v cin"], rings: Rings) -> Float[Array, "b v cout"]:
        params = {"W_point": self.w_point[...], "W_neighbor": self.w_neighbor[...], "b": self.b[...]}
        return mesh_conv(params, x, rings.neighbors, rings.mask, rings.degree)


class MeshRings(nnx.Module):
    """The padded one-rings of one resolution as non-trainable state."""

    def __init__(self, rings):
        self.neighbors = RingBuffer(jnp.asarray(rings.neighbors, jnp.int32))
        self.mask = RingBuffer(jnp.asarray(rings.mask, bool))
        self.degree = RingBuffer(jnp.asarray(rings.degree, jnp.int32))

    @property
    def n_vertices(self) -> int:
        return int(self.degree.shape[0])

    def get(self) -> Rings:
        return Rings(self.neighbors[...], self.mask[...], self.degree[...])


def _tanh(x: Array) -> Array:
    """tanh over a flat view (XLA on CPU vectorises elementwise loops along the short channel axis badly)."""
    return jnp.tanh(x.reshape(x.shape[:-2] + (-1,))).reshape(x.shape)


class MeshEncoder(nnx.Module):
    """(N, V, Cin) features -> (N, latent): tanh(conv) -> conv -> flatten -> FC."""

    def __init__(self, rings, cin: int, channels: int, latent: int, *, rngs: nnx.Rngs):
        self.rings = MeshRings(rings)
        self.conv1 = MeshConv(cin, channels, rngs=rngs)
        self.conv2 = MeshConv(channels, channels, rngs=rngs)
        self.fc = nnx.Linear(self.rings.n_vertices * channels, latent, rngs=rngs)

    def __call__(self, x: Float[Array, "n v cin"]) -> Float[Array, "n latent"]:
        rings = self.rings.get()
        h = _tanh(self.conv1(x, rings))
        h = self.conv2(h, rings)
        return self.fc(h.reshape(h.shape[0], -1))


class MeshDecoder(nnx.Module):
    """(N, latent) -> (N, V, Cin): FC -> tanh -> [concat the per-vertex ``extra`` channels] -> tanh(conv) ->
    tanh(conv)."""

    def __init__(self, rings, cout: int, channels: int, latent: int, *, extra: int = 0, rngs: nnx.Rngs):
        self.rings = MeshRings(rings)
        self.channels = channels
        self.fc = nnx.Linear(latent, self.rings.n_vertices * channels, rngs=rngs)
        self.conv1 = MeshConv(channels + extra, channels, rngs=rngs)
        self.conv2 = MeshConv(channels, cout, rngs=rngs)

    def __call__(
        self, z: Float[Array, "n latent"], extra: Float[Array, "n v e"] | None = None
    ) -> Float[Array, "n v cout"]:
        rings = self.rings.get()
        g = _tanh(self.fc(z).reshape(z.shape[0], self.rings.n_vertices, self.channels))
        if extra is not None:
            g = jnp.concatenate([g, extra.astype(g.dtype)], axis=-1)
        g = _tanh(self.conv1(g, rings))
        return _tanh(self.conv2(g, rings))


class LSTM(nnx.Module):
    """Single-layer LSTM over the window axis (-2), state reset at position 0 (gates in the module docstring)."""

    def __init__(self, d_in: int, hidden: int, *, rngs: nnx.Rngs):
        self.hidden = hidden
        self.wx = nnx.Linear(d_in, 4 * hidden, rngs=rngs)
        self.wh = nnx.Linear(hidden, 4 * hidden, use_bias=False, rngs=rngs)
        bias = jnp.zeros((4 * hidden,), jnp.float32).at[hidden : 2 * hidden].set(1.0)
        self.wx.bias[...] = bias

    def __call__(self, x: Float[Array, "b w d"]) -> Float[Array, "b w h"]:
        gx = jnp.swapaxes(self.wx(x), 0, 1)  # (W, B, 4H): input part of every gate, all positions at once
        wh = self.wh.kernel[...]
        hid = self.hidden

        def cell(carry, g):
            h, c = carry
            g = g + h @ wh
            i, f, u, o = (g[:, k * hid : (k + 1) * hid] for k in range(4))
            c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * jnp.tanh(u)
            h = jax.nn.sigmoid(o) * jnp.tanh(c)
            return (h, c), h

        zeros = jnp.zeros((x.shape[0], hid), x.dtype)
        _, hs = jax.lax.scan(cell, (zeros, zeros), gx)
        return jnp.swapaxes(hs, 0, 1)


class DetailModel(nnx.Module):
    """Coarse -> fine feature windows (module docstring); ``coarse`` and ``fine`` are Topology or Rings."""

    def __init__(
        self, coarse, fine, config: ModelConfig = ModelConfig(), *, rngs: nnx.Rngs | None = None, upsample=None
    ):
        rngs = nnx.Rngs(config.seed) if rngs is None else rngs
        cfg = config
        self.config = cfg
        self.n_coarse = int(jnp.shape(coarse.degree)[0])
        self.n_fine = int(jnp.shape(fine.degree)[0])
        if cfg.skip:
            if upsample is None or tuple(np.shape(upsample)) != (self.n_fine, self.n_coarse):
                raise ValueError(
                    f"a skip model needs the ({self.n_fine}, {self.n_coarse}) coarse-to-fine interpolation matrix."
                )
            self.upsample = RingBuffer(jnp.asarray(upsample, jnp.float32))
        self.coarse_encoder = MeshEncoder(coarse, cfg.in_channels, cfg.conv_channels, cfg.latent, rngs=rngs)
        self.fine_decoder = MeshDecoder(
            fine, cfg.in_channels, cfg.conv_channels, cfg.latent, extra=cfg.in_channels if cfg.skip else 0, rngs=rngs
        )
        if cfg.kind != "none":
            self.fine_encoder = MeshEncoder(fine, cfg.in_channels, cfg.conv_channels, cfg.latent, rngs=rngs)
        if cfg.kind == "transformer":
            self.proj_coarse = nnx.Linear(cfg.latent, cfg.d_model, rngs=rngs)
            self.proj_fine = nnx.Linear(cfg.latent, cfg.d_model, rngs=rngs)
            self.transformer = Transformer(cfg.d_model, cfg.heads, cfg.blocks, cfg.ffn, cfg.dropout, rngs=rngs)
        elif cfg.kind == "lstm":
            d_in = cfg.latent * (2 if cfg.lstm_fine_input else 1)
            self.lstm = LSTM(d_in, cfg.d_model, rngs=rngs)
        else:
            self.mlp_in = nnx.Linear(cfg.latent, cfg.d_model, rngs=rngs)
        self.head = nnx.Linear(cfg.d_model, cfg.latent, rngs=rngs)

    # ----------------------------------------------------------------------------- per-frame pieces
    def encode_coarse(self, x: Float[Array, "n vc c"]) -> Float[Array, "n l"]:
        """Coarse latents of coarse frames.

        **Arguments:**

        - ``x``: scaled coarse features ``(N, Vc, C)``.

        **Returns:**

        The latents ``(N, L)``.
        """
        return self.coarse_encoder(x)

    def encode_fine(self, x: Float[Array, "n vf c"]) -> Float[Array, "n l"]:
        """Fine latents of fine frames (the temporal models' feedback).

        **Arguments:**

        - ``x``: scaled fine features ``(N, Vf, C)``.

        **Returns:**

        The latents ``(N, L)``.

        **Raises:**

        ``ValueError`` for the no-temporal model (``config.kind == "none"``), which has no fine encoder.
        """
        if self.config.kind == "none":
            raise ValueError("the no-temporal model has no fine encoder.")
        return self.fine_encoder(x)

    def decode_fine(
        self, z: Float[Array, "n l"], coarse: Float[Array, "n vc c"] | None = None
    ) -> Float[Array, "n vf c"]:
        """Fine features from fine latents.

        **Arguments:**

        - ``z``: fine latents ``(N, L)``.
        - ``coarse``: the same frames' scaled coarse features ``(N, Vc, C)``; a ``skip`` model needs them.

        **Returns:**

        Scaled fine features ``(N, Vf, C)``.

        **Raises:**

        ``ValueError`` if a ``skip`` model gets no ``coarse``.
        """
        if not self.config.skip:
            return self.fine_decoder(z)
        if coarse is None:
            raise ValueError("a skip model decodes from the latents and the coarse frames' features.")
        return self.fine_decoder(z, jnp.einsum("fc,nck->nfk", self.upsample[...], coarse))

    def temporal(self, zc: Float[Array, "b w l"], zp: Float[Array, "b w l"] | None) -> Float[Array, "b w l"]:
        """Fine latents of the W target frames from coarse latents and previous-fine latents.

        **Arguments:**

        - ``zc``: coarse latents ``(B, W, L)``.
        - ``zp``: the previous fine frames' latents ``(B, W, L)``; unused (may be None) by the no-temporal model and
            an LSTM without fine input.

        **Returns:**

        The fine latents ``(B, W, L)``.
        """
        kind = self.config.kind
        if kind == "transformer":
            return self.head(self.transformer(self.proj_coarse(zc), self.proj_fine(zp)))
        if kind == "lstm":
            x = jnp.concatenate([zc, zp], axis=-1) if self.config.lstm_fine_input else zc
            return self.head(self.lstm(x))
        return self.head(jnp.tanh(self.mlp_in(zc)))

    # ---------------------------------------------------------------------------------- teacher forcing
    def __call__(
        self, coarse_win: Float[Array, "b w vc c"], fine_prev_win: Float[Array, "b w vf c"] | None = None
    ) -> Float[Array, "b w vf c"]:
        """Fine features of the W target frames (teacher forcing).

        **Arguments:**

        - ``coarse_win``: scaled coarse windows ``(B, W, Vc, C)``.
        - ``fine_prev_win``: ``fine_prev_win[:, k]`` is the fine frame before target k, ``(B, W, Vf, C)``; None only
            for the no-temporal model.

        **Returns:**

        Scaled fine features ``(B, W, Vf, C)``.

        **Raises:**

        ``ValueError`` if a temporal model gets no ``fine_prev_win``.
        """
        b, w = coarse_win.shape[:2]
        zc = self.encode_coarse(coarse_win.reshape((b * w,) + coarse_win.shape[2:])).reshape(b, w, -1)
        zp = None
        if self.config.kind != "none":
            if fine_prev_win is None:
                raise ValueError(f"a {self.config.kind} model needs the previous fine frames.")
            zp = self.encode_fine(fine_prev_win.reshape((b * w,) + fine_prev_win.shape[2:])).reshape(b, w, -1)
        zf = self.temporal(zc, zp)
        xc = coarse_win.reshape((b * w,) + coarse_win.shape[2:])
        return self.decode_fine(zf.reshape(b * w, -1), xc).reshape(b, w, self.n_fine, self.config.in_channels)


def new_model(coarse, fine, config: ModelConfig = ModelConfig(), upsample=None) -> DetailModel:
    """A freshly initialised :class:`DetailModel` (parameters from ``config.seed``).

    **Arguments:**

    - ``coarse``, ``fine``: Topology or Rings of the two meshes.
    - ``config``: the model's configuration.
    - ``upsample``: the ``(Vf, Vc)`` interpolation matrix a ``skip`` model needs.

    **Returns:**

    The model.

    **Raises:**

    ``ValueError`` if a ``skip`` model gets no ``(Vf, Vc)`` matrix.
    """
    return DetailModel(coarse, fine, config, rngs=nnx.Rngs(config.seed), upsample=upsample)


def parameter_count(model: Any) -> int:
    """Number of trainable scalars.

    **Arguments:**

    - ``model``: an nnx module.

    **Returns:**

    The count of scalars in its ``nnx.Param`` leaves.
    """
    return int(sum(x.size for x in jax.tree_util.tree_leaves(nnx.state(model, nnx.Param))))
