"""Training, autoregressive synthesis and persistence of the seed-002 detail model (:mod:`jaxdeform.cloth.model`).

Training windows (paper Sec. 4: 3 input frames). A window of W consecutive frames s..s+W-1 of one sequence
gives the coarse input ``coarse[s..s+W-1]``, the target ``fine[s..s+W-1]`` and the teacher-forced decoder
input ``fine[s-1..s+W-2]`` (the ground truth shifted right by one frame; an all-zero frame stands for
``fine[-1]``). Windows never cross a sequence boundary; every start s = 0..T-W of every sequence is one
window. Each step draws ``batch_size`` windows uniformly with replacement from
``jax.random.fold_in(PRNGKey(seed), step)``, so a run is a deterministic function of the seed.

Loss: mean squared error over all features of the W target frames (paper: "minimizing the mean squared
error between predicted detailed features and the ground-truth"). Optional position term
(``TrainConfig.position_weight`` > 0, with a :class:`PositionTarget`): the last frame of each window is
unscaled, added to its residual base when the target is a residual, turned into positions by the
differentiable ACAP reconstruction (one anchored least-squares solve, :class:`jaxdeform.acap.reconstruct.
Reconstructor`; identity for coordinates) and compared with the fine simulation:
``position_weight * mean_v |p_v - g_v|^2 / ell^2`` with ell the mean fine rest edge length. Feature MSE
weighs every vertex's rotation alike, while the evaluation's RMSE is dominated by how small rotation errors
integrate along the cloth (a hanging sheet's hem moves with every rotation above it); the position term
trains for what is measured. It costs one solve forward and one backward per window.

Self-feeding (``TrainConfig.self_feed`` = p > 0; off in this config, the paper trains with teacher forcing only;
``jaxdeform cloth train`` defaults to p = 0.5).
At test time the decoder reads the model's own earlier frames, whose errors it never saw in training, and one
training draw can drift away on a sequence unlike the training ones while another does not (DISK's gust sequence).
Parallel scheduled sampling (Duckworth et al. 2019, "Parallel scheduled sampling") trains on inputs like the test
time's without a sequential unroll: W - 1 gradient-free passes over the window, each feeding the previous pass's
predictions of target frames s..s+W-2 in as the fine inputs of positions 1..W-1 (position 0, the frame before the
window, stays the simulation's), so that after them position k reads frames that were themselves predicted from
predictions, as in synthesis. Each window of the batch takes these inputs with probability p_t, else the
simulation's; p_t rises linearly from 0 to p over the first half of the training (early predictions are noise),
then stays. The loss and its gradient are those of the last pass only. A step costs W - 1 extra forward passes.

Optimiser: Adam, learning rate 1e-3,
optionally decayed exponentially, lr(t) = lr0 * decay_rate^(t / decay_steps) (off by default: decay_rate 1).
The whole step (batch gather, forward, backward, Adam) is one ``jax.jit`` program, compiled once per run
(its first call is reported apart as compile time).

Data parallel: ``train(..., mesh=...)`` (a :class:`jax.sharding.Mesh`, e.g. :func:`jaxdeform.parallel.batch_mesh`)
splits each step's ``batch_size`` windows along the mesh axis ``axis``; parameters, the rest of the model state,
the optimizer state and the training windows are replicated on every device. The loss is the whole batch's mean
(GSPMD all-reduces the gradients), so a step equals the single-device step to float round-off. ``batch_size``
must be a multiple of the axis's device count (ValueError otherwise).

Autoregressive synthesis (paper Fig. 5: "during testing, these [fine] features are initialized to zeros,
and once a new high-resolution frame is generated, its TS-ACAP feature is added"). For frame t the window
starts at s = max(t - W + 1, 0) and frame t is read at window position t - s:

- t >= W - 1: the window is coarse frames t-W+1..t and the model's own fine frames t-W..t-1 (last position);
- t < W - 1: the first window, coarse frames 0..W-1, fine input (zeros, fine_0, ..., fine_{t-1}), read at
  position t. This is exactly the layout of the training windows that start at frame 0 (no padding frames
  the model never saw); the price is that the first W - 1 frames see up to W - 1 - t coarse frames ahead.

A sequence shorter than W is padded at the end by repeating its last coarse frame (only the first T outputs
are returned). Coarse latents of all frames are computed once; the scan carries the fine *latents* of the
frames produced so far (T + 1, latent), so each frame costs one fine decode, one fine encode and one small
temporal pass. The whole synthesis is one jitted function with ``lax.scan`` over frames; sequences of equal
length reuse one compilation. Kind "none" has no recurrence: frames are decoded in chunks, independently.

:func:`predict_windows` is the jitted teacher-forced forward pass (evaluation of windows, tests).

Persistence: :func:`save_model` writes one orbax checkpoint folder (:mod:`jaxdeform.nn.archive`: parameters, the
padded one-rings of both meshes, the JSON configuration and caller metadata) atomically; :func:`load_model`
rebuilds the model from it alone.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jaxtyping import Array, Float, Int

from jaxdeform import parallel
from jaxdeform.cloth.model import DetailModel, ModelConfig, new_model
from jaxdeform.errors import JaxDeformError
from jaxdeform.nn import xla
from jaxdeform.nn.archive import StepCheckpoints, load_state, read_archive, save_module
from jaxdeform.nn.graph_conv import Rings
from jaxdeform.nn.host import host_scalars, recent_mean

FORMAT = "jaxdeform-cloth-model"
FORMAT_VERSION = 1
TRACE_COUNT: Counter = Counter()  # Python traces of the jitted train step and synthesis (tests check retracing)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation of :func:`train` (paper: Adam; lr 1e-3 as in the brief; the rest are our defaults)."""

    steps: int = 3000
    batch_size: int = 16  # windows per step
    learning_rate: float = 1e-3
    decay_rate: float = 1.0  # lr multiplied by this every decay_steps (1.0: constant)
    decay_steps: int = 1000
    seed: int = 0  # batch sampling (parameters come from ModelConfig.seed)
    log_every: int = 50  # progress-bar refresh interval (steps)
    position_weight: float = 0.0  # weight of the position term (module docstring); 0 = the paper's loss
    self_feed: float = 0.0  # final probability that a window reads the model's own predictions (module docstring)

    def __post_init__(self):
        for name in ("steps", "batch_size", "decay_steps", "log_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"training {name} must be a positive integer, got {getattr(self, name)!r}.")
        if not (self.learning_rate > 0 and np.isfinite(self.learning_rate)):
            raise ValueError(f"the learning rate must be a positive number, got {self.learning_rate}.")
        if not 0 < self.decay_rate <= 1:
            raise ValueError(f"decay_rate must lie in (0, 1], got {self.decay_rate}.")
        if not (self.position_weight >= 0 and np.isfinite(self.position_weight)):
            raise ValueError(f"position_weight must be a non-negative number, got {self.position_weight}.")
        if not 0.0 <= self.self_feed <= 1.0:
            raise ValueError(f"self_feed is a probability and must lie in [0, 1], got {self.self_feed}.")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


class History(NamedTuple):
    """Training record: loss of every step, wall time, compile time (first step) and mean step time."""

    loss: np.ndarray  # (steps,) float32, MSE of the step's batch before its update
    seconds: float  # whole optimisation, compilation included
    compile_seconds: float  # first step: tracing + compilation + one step
    step_seconds: float  # mean time of the later steps


# ------------------------------------------------------------------------------------------- windows


@dataclasses.dataclass(frozen=True)
class Windows:
    """All training windows of a set of paired sequences (see the module docstring).

    ``coarse`` / ``fine`` hold the sequences one after another, each preceded by one all-zero frame;
    ``starts[m]`` is the row of window m's first target frame in them.
    """

    coarse: Float[Array, "n vc c"]
    fine: Float[Array, "n vf c"]
    starts: Int[Array, " m"]
    window: int

    @property
    def count(self) -> int:
        return int(self.starts.shape[0])


def _as_sequences(seqs, what: str) -> list[np.ndarray]:
    if isinstance(seqs, np.ndarray) or isinstance(seqs, jax.Array):
        seqs = [seqs]
    out = []
    for i, s in enumerate(seqs):
        a = np.asarray(s, dtype=np.float32)
        if a.ndim != 3:
            raise ValueError(f"{what} sequence {i} must be a (T, V, C) array, got shape {a.shape}.")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what} sequence {i} holds NaN or infinite values.")
        out.append(a)
    if not out:
        raise ValueError(f"no {what} sequences were given.")
    if len({a.shape[1:] for a in out}) != 1:
        raise ValueError(f"{what} sequences differ in vertex or channel count: {sorted({a.shape[1:] for a in out})}.")
    return out


def windows(coarse_seqs: Sequence, fine_seqs: Sequence, window: int) -> Windows:
    """Every window of ``window`` consecutive frames of every paired (coarse, fine) sequence (module docstring).

    Sequences shorter than the window give no window.

    **Arguments:**

    - ``coarse_seqs``: scaled coarse sequences, each ``(T_i, Vc, C)``.
    - ``fine_seqs``: the frame-aligned fine sequences, each ``(T_i, Vf, C)``.
    - ``window``: W.

    **Returns:**

    The :class:`Windows`.

    **Raises:**

    ``ValueError`` for unpaired or mismatched sequences, or if no sequence gives a window.
    """
    cs, fs = _as_sequences(coarse_seqs, "coarse"), _as_sequences(fine_seqs, "fine")
    if len(cs) != len(fs):
        raise ValueError(f"{len(cs)} coarse sequences but {len(fs)} fine sequences were given.")
    if cs[0].shape[2] != fs[0].shape[2]:
        raise ValueError(f"coarse features have {cs[0].shape[2]} channels but fine ones {fs[0].shape[2]}.")
    for i, (c, f) in enumerate(zip(cs, fs)):
        if c.shape[0] != f.shape[0]:
            raise ValueError(f"sequence {i} has {c.shape[0]} coarse frames but {f.shape[0]} fine frames.")
    w = int(window)
    if w < 1:
        raise ValueError(f"the window must be at least 1 frame, got {window}.")
    starts, row = [], 0
    for c in cs:
        t = c.shape[0]
        starts.append(row + 1 + np.arange(max(t - w + 1, 0)))
        row += t + 1
    starts = np.concatenate(starts).astype(np.int32)
    if starts.size == 0:
        raise ValueError(f"no sequence has the {w} frames one training window needs.")

    return Windows(stack_like_windows(cs), stack_like_windows(fs), jnp.asarray(starts), w)


def gather_windows(
    coarse: Float[Array, "n vc c"], fine: Float[Array, "n vf c"], starts: Int[Array, " b"], window: int
) -> tuple[Float[Array, "b w vc c"], Float[Array, "b w vf c"], Float[Array, "b w vf c"]]:
    """The windows starting at rows ``starts`` of :class:`Windows`' stacked sequences.

    **Arguments:**

    - ``coarse``, ``fine``: the stacked sequences (:class:`Windows`).
    - ``starts``: rows of the windows' first target frames ``(B,)``.
    - ``window``: W.

    **Returns:**

    ``(coarse window, teacher-forced fine input, fine target)``: ``(B, W, Vc, C)``, ``(B, W, Vf, C)`` and
    ``(B, W, Vf, C)``.
    """
    idx = starts[:, None] + jnp.arange(window)[None, :]
    return coarse[idx], fine[idx - 1], fine[idx]


def self_fed_inputs(
    predict, coarse_win: Float[Array, "b w vc c"], fine_prev: Float[Array, "b w vf c"]
) -> Float[Array, "b w vf c"]:
    """The fine inputs of a window as synthesis would feed them (module docstring, "Self-feeding").

    W - 1 passes without gradient, each moving the previous pass's predictions of the target frames 0..W-2 into
    the input positions 1..W-1; position 0 keeps ``fine_prev[:, 0]``.

    **Arguments:**

    - ``predict``: the model, ``predict(coarse_win, fine_prev_win)``.
    - ``coarse_win``: coarse windows ``(B, W, Vc, C)``.
    - ``fine_prev``: the teacher-forced fine inputs ``(B, W, Vf, C)``.

    **Returns:**

    The self-fed inputs ``(B, W, Vf, C)``; with W = 1 the inputs unchanged.
    """
    fed = fine_prev
    for _ in range(fine_prev.shape[1] - 1):  # W - 1 <= a few passes, unrolled once at trace time
        pred = jax.lax.stop_gradient(predict(coarse_win, fed))
        fed = jnp.concatenate([fine_prev[:, :1], pred[:, :-1]], axis=1)
    return fed


def self_feed_probability(p: float, step: Array, steps: int) -> Array:
    """p_t of the module docstring: 0 at step 0, rising linearly to p at half the training, p from then on.

    **Arguments:**

    - ``p``: the final probability.
    - ``step``: the current step.
    - ``steps``: the training's steps.

    **Returns:**

    p_t as a scalar array.
    """
    return p * jnp.minimum(1.0, step.astype(jnp.float32) / max(steps / 2.0, 1.0))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PositionTarget:
    """What the position term of the loss needs (module docstring); arrays stacked like :class:`Windows`."""

    positions: Float[Array, "n vf 3"]  # fine simulation frames
    base: Float[Array, "n vf c"] | None  # unscaled residual base features (None: the target is not a residual)
    lo: Float[Array, " c"]  # the fine scaling (:class:`jaxdeform.cloth.features.Scaling`)
    hi: Float[Array, " c"]
    reconstructor: object  # Reconstructor of the fine mesh anchored on the pins; None for coordinates
    anchor_targets: Float[Array, "a 3"] | None
    edge: float = dataclasses.field(metadata=dict(static=True), default=1.0)  # mean fine rest edge length

    @staticmethod
    def build(
        positions: Sequence, base: Sequence | None, lo, hi, reconstructor, anchor_targets, edge: float
    ) -> PositionTarget:
        """From per-sequence arrays (the same order as the training sequences)."""
        return PositionTarget(
            stack_like_windows(positions),
            None if base is None else stack_like_windows(base),
            jnp.asarray(lo, jnp.float32),
            jnp.asarray(hi, jnp.float32),
            reconstructor,
            None if anchor_targets is None else jnp.asarray(anchor_targets, jnp.float32),
            float(edge),
        )


def stack_like_windows(seqs: Sequence) -> Float[Array, "n v c"]:
    """Sequences one after another, each preceded by a zero frame (the rows of :class:`Windows`).

    **Arguments:**

    - ``seqs``: sequences ``(T_i, V, C)``.

    **Returns:**

    ``(sum_i (T_i + 1), V, C)`` float32.
    """
    seqs = [np.asarray(x, np.float32) for x in seqs]
    zero = np.zeros((1,) + seqs[0].shape[1:], np.float32)
    return jnp.asarray(np.concatenate([x for s in seqs for x in (zero, s)]))


def position_error(pos: PositionTarget, scaled: Float[Array, "b vf c"], rows: Int[Array, " b"]) -> Array:
    """Mean squared vertex distance over ell^2 of scaled fine features decoded to positions.

    **Arguments:**

    - ``pos``: the position target (module docstring).
    - ``scaled``: scaled fine features ``(B, Vf, C)``.
    - ``rows``: the rows of ``pos`` they belong to ``(B,)``.

    **Returns:**

    The error as a scalar array.
    """
    from jaxdeform.acap.features import gradients_from_features
    from jaxdeform.cloth.features import LIMIT

    f = (scaled / LIMIT + 1.0) * 0.5 * (pos.hi - pos.lo) + pos.lo
    if pos.base is not None:
        f = f + pos.base[rows]
    if pos.reconstructor is None:
        p = f
    else:
        p = pos.reconstructor(gradients_from_features(f), pos.anchor_targets)
    return jnp.mean(jnp.sum(jnp.square(p - pos.positions[rows]), -1)) / (pos.edge * pos.edge)


# ------------------------------------------------------------------------------------------ training


def _tx(lr: float, decay_rate: float, decay_steps: int) -> optax.GradientTransformation:
    if decay_rate < 1.0:
        return optax.adam(optax.exponential_decay(lr, decay_steps, decay_rate))
    return optax.adam(lr)


@functools.cache
def _train_step(
    graphdef,
    window: int,
    batch: int,
    lr: float,
    decay_rate: float,
    decay_steps: int,
    position_weight: float = 0.0,
    self_feed: float = 0.0,
    steps: int = 1,
    mesh: jax.sharding.Mesh | None = None,
    axis: str = parallel.BATCH,
):
    """The jitted training step for one model structure and optimiser (cached: no retrace across runs).

    ``mesh``: the windows of a step split along ``mesh``'s ``axis``, every argument and result replicated over
    ``mesh`` (ValueError unless ``batch`` is a multiple of the axis's size).
    """
    tx = _tx(lr, decay_rate, decay_steps)
    if mesh is not None:
        parallel.check_divisible(batch, mesh, axis, "batch_size")

    def step(params, rest, opt_state, coarse, fine, starts, key, t, pos):
        TRACE_COUNT["train_step"] += 1
        sel = jax.random.randint(jax.random.fold_in(key, t), (batch,), 0, starts.shape[0])
        cw, fp, ft = parallel.constrain_batch(gather_windows(coarse, fine, starts[sel], window), mesh, axis)

        def loss_fn(p):
            model = nnx.merge(graphdef, p, rest)
            model.train()
            inputs = fp
            if self_feed > 0 and model.config.kind != "none":  # the per-frame model reads no fine input
                own = jax.random.bernoulli(
                    jax.random.fold_in(jax.random.fold_in(key, t), 1),
                    self_feed_probability(self_feed, t, steps),
                    (batch,),
                )
                inputs = jnp.where(own[:, None, None, None], self_fed_inputs(model, cw, fp), fp)
            pred = model(cw, inputs)
            loss = jnp.mean(jnp.square(pred - ft))
            if pos is not None and position_weight > 0:
                loss = loss + position_weight * position_error(pos, pred[:, -1], starts[sel] + window - 1)
            return loss, nnx.state(model, nnx.Not(nnx.Param))

        (loss, new_rest), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), new_rest, opt_state, loss

    shardings = {}
    if mesh is not None:
        rep = parallel.replicated(mesh)
        shardings = {"in_shardings": rep, "out_shardings": rep}
    return jax.jit(step, donate_argnums=(0, 2), compiler_options=xla.compiler_options(), **shardings)


def _checked_windows(
    model_cfg: ModelConfig, coarse_topo, fine_topo, coarse_seqs: Sequence, fine_seqs: Sequence
) -> Windows:
    """The training :func:`windows` of the paired sequences, checked against the two meshes.

    Guarantees ``win.coarse`` is (rows, Vc, C) and ``win.fine`` (rows, Vf, C) with Vc / Vf the vertex counts of
    ``coarse_topo`` / ``fine_topo`` and C = ``model_cfg.in_channels``; raises ValueError otherwise (coarse first),
    and whatever :func:`windows` raises before that.
    """
    win = windows(coarse_seqs, fine_seqs, model_cfg.window)
    nc, nf = int(np.shape(coarse_topo.degree)[0]), int(np.shape(fine_topo.degree)[0])
    if win.coarse.shape[1:] != (nc, model_cfg.in_channels):
        raise ValueError(
            f"coarse features must be (T, {nc}, {model_cfg.in_channels}), got (T, {win.coarse.shape[1]}, "
            f"{win.coarse.shape[2]})."
        )
    if win.fine.shape[1:] != (nf, model_cfg.in_channels):
        raise ValueError(
            f"fine features must be (T, {nf}, {model_cfg.in_channels}), got (T, {win.fine.shape[1]}, "
            f"{win.fine.shape[2]})."
        )
    return win


def _position_target(tc: TrainConfig, positions: PositionTarget | None, win: Windows) -> PositionTarget | None:
    """The :class:`PositionTarget` the step uses: ``positions`` when ``tc.position_weight`` > 0, else None.

    With a positive weight, raises ValueError if ``positions`` is None or its frames do not line up with the
    rows of ``win.fine``.
    """
    if tc.position_weight > 0:
        if positions is None:
            raise ValueError("position_weight > 0 needs the fine positions (a PositionTarget).")
        if positions.positions.shape[:2] != win.fine.shape[:2]:
            raise ValueError("the PositionTarget's frames do not line up with the training windows.")
        return positions
    return None


def _run_steps(
    step_fn,
    state: tuple,
    win: Windows,
    key,
    positions: PositionTarget | None,
    tc: TrainConfig,
    desc: str,
    progress: bool,
    ckpt: StepCheckpoints | None = None,
    checkpoint_every: int = 0,
    resume: bool = False,
) -> tuple[tuple, np.ndarray, float, float]:
    """Run ``tc.steps`` calls of the jitted ``step_fn`` from ``state`` = (params, rest, opt_state).

    Step t passes ``jnp.int32(t)`` and the same ``key``, windows and ``positions``. A tqdm bar titled ``desc``
    (shown when ``progress``) advances every ``tc.log_every`` steps and at the end, with the mean recent loss.
    With ``ckpt``, the state and the losses so far are saved every ``checkpoint_every`` steps; ``resume``
    continues from the newest one (the steps are deterministic: the same result as an uninterrupted loop).
    Returns ``(final state, losses (steps,) float32, seconds, compile seconds)``: the wall time of the whole loop
    (the losses' transfer to the host included) and of the first step run (tracing, compilation and one step).
    """
    from tqdm.auto import tqdm

    params, rest, opt_state = state
    done = np.zeros(tc.steps, np.float32)
    start = 0
    if ckpt is not None and resume and ckpt.latest() is not None:
        like = {"params": params, "rest": rest, "opt_state": opt_state, "losses": done}
        got = ckpt.restore(ckpt.latest(), jax.tree_util.tree_map(np.asarray, like))
        params, rest, opt_state = (jax.tree_util.tree_map(jnp.asarray, got[k]) for k in ("params", "rest", "opt_state"))
        done, start = np.asarray(got["losses"]).copy(), int(ckpt.latest())
    losses = []
    t0 = time.perf_counter()
    compile_s = 0.0
    with tqdm(total=tc.steps, initial=start, desc=desc, unit="step", disable=not progress) as bar:
        for t in range(start, tc.steps):
            params, rest, opt_state, loss = step_fn(
                params, rest, opt_state, win.coarse, win.fine, win.starts, key, jnp.int32(t), positions
            )
            losses.append(loss)
            if t == start:
                loss.block_until_ready()
                compile_s = time.perf_counter() - t0
            if (t + 1) % tc.log_every == 0 or t + 1 == tc.steps:
                bar.set_postfix(loss=f"{recent_mean(losses, tc.log_every):.5f}")
                bar.update((t + 1) - bar.n)
            if ckpt is not None and checkpoint_every and (t + 1) % checkpoint_every == 0 and t + 1 < tc.steps:
                done[start : t + 1] = host_scalars(losses)
                ckpt.save(t + 1, {"params": params, "rest": rest, "opt_state": opt_state, "losses": done})
    done[start:] = host_scalars(losses)
    seconds = time.perf_counter() - t0
    return (params, rest, opt_state), done, seconds, compile_s


def train(
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    coarse_topo,
    fine_topo,
    coarse_seqs: Sequence,
    fine_seqs: Sequence,
    progress: bool = True,
    *,
    model: DetailModel | None = None,
    positions: PositionTarget | None = None,
    upsample=None,
    mesh: jax.sharding.Mesh | None = None,
    axis: str = parallel.BATCH,
    checkpoint_dir=None, checkpoint_every: int = 0, resume: bool = False,
) -> tuple[DetailModel, History]:  # fmt: skip
    """Fit a :class:`DetailModel` to paired scaled feature sequences with teacher forcing (module docstring).

    **Arguments:**

    - ``model_cfg``: the model's configuration.
    - ``train_cfg``: the training configuration.
    - ``coarse_topo``, ``fine_topo``: Topology (or Rings) of the two meshes.
    - ``coarse_seqs``, ``fine_seqs``: frame-aligned sequences, ``coarse_seqs[i]`` ``(T_i, Vc, C)`` and ``fine_seqs[i]``
        ``(T_i, Vf, C)``.
    - ``progress``: show a progress bar.
    - ``model``: continue training this existing model of the same configuration instead of a fresh one.
    - ``positions``: enables the position term of the loss (``train_cfg.position_weight`` > 0; module docstring).
    - ``upsample``: the ``(Vf, Vc)`` interpolation matrix a ``skip`` model needs.
    - ``mesh``: data parallel over ``mesh``'s ``axis`` (module docstring); None trains on one device.
    - ``checkpoint_dir``, ``checkpoint_every``, ``resume``: checkpoints every that many steps, resumed from.

    **Returns:**

    ``(model, history)``: the trained model and its :class:`History`. With ``mesh`` the model's arrays are replicated
    over ``mesh``.

    **Raises:**

    ``ValueError`` before any step unless ``train_cfg.batch_size`` is a multiple of ``mesh.shape[axis]``, or if
    ``model`` was built with another configuration than ``model_cfg``.
    """
    if mesh is not None:
        parallel.check_divisible(int(train_cfg.batch_size), mesh, axis, "batch_size")
    win = _checked_windows(model_cfg, coarse_topo, fine_topo, coarse_seqs, fine_seqs)
    if model is None:
        model = new_model(coarse_topo, fine_topo, model_cfg, upsample)
    elif model.config != model_cfg:
        raise ValueError("the model to continue was built with another configuration than model_cfg.")
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    tc = train_cfg
    opt_state = _tx(tc.learning_rate, tc.decay_rate, tc.decay_steps).init(params)
    positions = _position_target(tc, positions, win)
    step_fn = _train_step(
        graphdef,
        win.window,
        int(tc.batch_size),
        float(tc.learning_rate),
        float(tc.decay_rate),
        int(tc.decay_steps),
        float(tc.position_weight),
        float(tc.self_feed),
        int(tc.steps) if tc.self_feed > 0 else 1,
        **({} if mesh is None else {"mesh": mesh, "axis": axis}),
    )
    key = jax.random.PRNGKey(tc.seed)
    if mesh is not None:  # state and windows placed on the mesh once (the step would copy them on every call)
        params, rest, opt_state, arrays, key = parallel.replicate(
            (params, rest, opt_state, (win.coarse, win.fine, win.starts), key), mesh
        )
        win = Windows(*arrays, window=win.window)

    (params, rest, opt_state), loss_arr, seconds, compile_s = _run_steps(
        step_fn, (params, rest, opt_state), win, key, positions, tc, f"train {model_cfg.kind}", progress,
        None if checkpoint_dir is None else StepCheckpoints(checkpoint_dir), checkpoint_every, resume,
    )  # fmt: skip
    nnx.update(model, params, rest)
    model.eval()
    step_s = (seconds - compile_s) / max(tc.steps - 1, 1)
    return model, History(loss_arr, seconds, compile_s, step_s)


# ----------------------------------------------------------------------------------------- synthesis


@functools.cache
def _predict_fn(graphdef):
    def run(state, coarse_win, fine_prev_win):
        TRACE_COUNT["predict"] += 1
        model = nnx.merge(graphdef, state)
        model.eval()
        return model(coarse_win, fine_prev_win)

    return jax.jit(run, compiler_options=xla.compiler_options())


def predict_windows(
    model: DetailModel, coarse_win: Float[Array, "b w vc c"], fine_prev_win: Float[Array, "b w vf c"] | None = None
) -> Float[Array, "b w vf c"]:
    """Teacher-forced prediction ``model(coarse_win, fine_prev_win)``, jitted (one compilation per shape).

    **Arguments:**

    - ``model``: the detail model.
    - ``coarse_win``: scaled coarse windows ``(B, W, Vc, C)``.
    - ``fine_prev_win``: the previous fine frames ``(B, W, Vf, C)``; None (zeros) only for a model without temporal
        feedback (``config.kind == "none"``).

    **Returns:**

    Predicted scaled fine windows ``(B, W, Vf, C)``.

    **Raises:**

    ``ValueError`` if ``fine_prev_win`` is None for a model that needs it.
    """
    graphdef, state = nnx.split(model)
    if fine_prev_win is None:
        if model.config.kind != "none":
            raise ValueError(f"a {model.config.kind} model needs the previous fine frames.")
        fine_prev_win = jnp.zeros(coarse_win.shape[:2] + (model.n_fine, model.config.in_channels), jnp.float32)
    return _predict_fn(graphdef)(state, jnp.asarray(coarse_win, jnp.float32), jnp.asarray(fine_prev_win, jnp.float32))


@functools.cache
def _synthesize_fn(graphdef, chunk: int):
    """The jitted synthesis for one model structure (cached; one compilation per sequence length)."""

    def run(state, coarse):
        TRACE_COUNT["synthesize"] += 1
        model = nnx.merge(graphdef, state)
        model.eval()
        cfg = model.config
        w, t_len = cfg.window, coarse.shape[0]
        zc = model.encode_coarse(coarse)  # (T, L): all coarse frames at once (the coarse mesh is small)
        if cfg.kind == "none":
            zf = model.temporal(zc[None], None)[0]
            n = -(-t_len // chunk)
            zf = jnp.pad(zf, ((0, n * chunk - t_len), (0, 0))).reshape(n, chunk, -1)
            xc = jnp.pad(coarse, ((0, n * chunk - t_len), (0, 0), (0, 0))).reshape((n, chunk) + coarse.shape[1:])
            # (n, chunk, Vf, C): chunks in sequence, frames batched
            out = jax.lax.map(lambda a: model.decode_fine(*a), (zf, xc))
            return out.reshape((n * chunk,) + out.shape[2:])[:t_len]
        if t_len < w:  # repeat the last coarse frame (module docstring)
            zc = jnp.concatenate([zc, jnp.repeat(zc[-1:], w - t_len, axis=0)])
        t_pad = zc.shape[0]
        z0 = model.encode_fine(jnp.zeros((1, model.n_fine, cfg.in_channels), coarse.dtype))[0]
        hist = jnp.zeros((t_pad + 1, zc.shape[1]), zc.dtype).at[0].set(z0)  # hist[j]: latent of fine frame j-1

        def frame(hist, t):
            s = jnp.maximum(t - w + 1, 0)
            zc_win = jax.lax.dynamic_slice_in_dim(zc, s, w)
            zp_win = jax.lax.dynamic_slice_in_dim(hist, s, w)  # fine frames s-1 .. s+w-2 (later ones unused)
            z = jax.lax.dynamic_index_in_dim(model.temporal(zc_win[None], zp_win[None])[0], t - s, keepdims=True)
            y = model.decode_fine(z, jax.lax.dynamic_index_in_dim(coarse, t, keepdims=True))  # (1, Vf, C)
            hist = jax.lax.dynamic_update_index_in_dim(hist, model.encode_fine(y)[0], t + 1, 0)
            return hist, y[0]

        _, ys = jax.lax.scan(frame, hist, jnp.arange(t_len))
        return ys

    return jax.jit(run, compiler_options=xla.compiler_options())


def synthesize(model: DetailModel, coarse_seq: Float[Array, "t vc c"], *, chunk: int = 32) -> Float[Array, "t vf c"]:
    """Fine feature sequence from a scaled coarse one, autoregressively (module docstring).

    **Arguments:**

    - ``model``: the detail model.
    - ``coarse_seq``: scaled coarse features ``(T, Vc, C)``, ``T >= 1``.
    - ``chunk``: frames decoded together by the no-temporal model (memory bound only).

    **Returns:**

    Scaled fine features ``(T, Vf, C)``.

    **Raises:**

    ``ValueError`` if ``coarse_seq`` is not ``(T >= 1, Vc, C)`` for the model's meshes.
    """
    x = jnp.asarray(coarse_seq, dtype=jnp.float32)
    cfg = model.config
    if x.ndim != 3 or x.shape[1:] != (model.n_coarse, cfg.in_channels) or x.shape[0] < 1:
        raise ValueError(
            f"the coarse sequence must be (T >= 1, {model.n_coarse}, {cfg.in_channels}), got shape {tuple(x.shape)}."
        )
    graphdef, state = nnx.split(model)
    return _synthesize_fn(graphdef, int(chunk))(state, x)


# --------------------------------------------------------------------------------------- persistence


def _rings_of(model: DetailModel) -> tuple[Rings, Rings]:
    return model.coarse_encoder.rings.get(), model.fine_decoder.rings.get()


def save_model(path: str | os.PathLike, model: DetailModel, meta: dict | None = None) -> Path:
    """Write the model (parameters, both meshes' one-rings, configuration) and JSON ``meta`` atomically.

    **Arguments:**

    - ``path``: the checkpoint folder to write (replaced if it exists).
    - ``model``: the detail model.
    - ``meta``: JSON-serialisable metadata stored with it (default None: empty).

    **Returns:**

    The written path.
    """
    record = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "config": model.config.to_dict(),
        "n_coarse": model.n_coarse,
        "n_fine": model.n_fine,
        "meta": dict(meta or {}),
    }
    rings = {
        f"rings:{name}:{field}": np.asarray(arr)
        for name, r in zip(("coarse", "fine"), _rings_of(model))
        for field, arr in r._asdict().items()
    }
    if model.config.skip:
        rings["upsample"] = np.asarray(model.upsample[...])
    return save_module(path, model, record, nnx.Param, extra=rings)


def load_model(path: str | os.PathLike) -> tuple[DetailModel, dict]:
    """Read a model written by :func:`save_model`.

    **Arguments:**

    - ``path``: the model's checkpoint folder.

    **Returns:**

    ``(model, meta)``: the model (in eval mode) and its metadata dict.

    **Raises:**

    ``JaxDeformError`` for a missing path or anything but a cloth model checkpoint (damaged included).
    """
    record, arrays = read_archive(path, "cloth model", FORMAT, FORMAT_VERSION)
    try:
        config = ModelConfig.from_dict(record["config"])
        rings = [Rings(*(arrays[f"rings:{name}:{f}"] for f in Rings._fields)) for name in ("coarse", "fine")]
        model = new_model(rings[0], rings[1], config, arrays.get("upsample"))
    except (KeyError, ValueError, TypeError) as exc:
        raise JaxDeformError(f"{path}: not a jaxdeform cloth model checkpoint ({type(exc).__name__}: {exc}).") from None
    load_state(path, model, arrays, nnx.Param)
    model.eval()
    return model, dict(record.get("meta", {}))
