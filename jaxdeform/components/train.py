"""Training of the multiscale model: one jitted Adam step, checkpoints with orbax, resume, progress.

Adam (optax's, :func:`optimizer`) with learning rate 1e-3 and exponential decay; batches of up to ``batch``
shapes sampled with an explicit PRNG key (when the training set is not larger than the batch, every step sees the whole set, as the
paper's horse split of 5 shapes does). Everything of a step runs in one jitted call (the model's state,
optimizer state and key in, the same out).

The model is a :class:`jaxdeform.components.model.Model` (a flax nnx Module). The jitted step works on its
split state, one ``nnx.State`` per level (:func:`level_states`), and merges it with the levels' graph
definitions inside the step; :func:`train` takes and returns the Module.

Joint training (default, the paper's) minimizes the sum of every block's loss at once. Separate training
(Table 4) trains level 0 alone, then level 1 on the residuals of the frozen level 0, and so on, each stage
for ``epochs`` epochs with a fresh optimizer.

Checkpoints: with ``checkpoint_dir`` the state (the model's level states, optimizer state, key, loss history,
stage) is saved by orbax every ``checkpoint_every`` epochs and at the end; ``resume=True`` continues from the newest
one. The step is deterministic, so a resumed run ends bit-identical to an uninterrupted one (tested on CPU).

Data parallel: with ``mesh`` (a :class:`jax.sharding.Mesh`, e.g. :func:`jaxdeform.parallel.batch_mesh`) the
shapes of each step's batch are split along the mesh axis ``axis``; parameters, optimizer state, key and the
training set are replicated on every device. The loss is the whole batch's (GSPMD all-reduces the gradients),
so a step equals the single-device step to float round-off. The batch of a step (``min(len(data), tc.batch)``
shapes) must be a multiple of the axis's device count (ValueError otherwise).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from jaxdeform import parallel
from jaxdeform.components import model
from jaxdeform.nn import xla
from jaxdeform.nn.archive import StepCheckpoints
from jaxdeform.nn.graph_conv import Rings
from jaxdeform.nn.host import host_scalars


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    epochs: int = 10_000
    batch: int = 256
    learning_rate: float = 1e-3
    # Exponential decay, lr * decay_rate ** (step / decay_steps): the paper gives no rate. 0.1 ** 0.1 takes the
    # rate to 1e-4 over the 10,000 epochs; a slower decay (0.96 per 1,000 steps) lets Adam's oscillation grow
    # into a loss explosion late in horse-gallop training (docs/seed000-components.md).
    decay_rate: float = 0.1**0.1
    decay_steps: int = 1000
    seed: int = 0
    joint: bool = True  # False: level-by-level ("separate") training, Table 4
    # Largest global norm of a step's gradient before Adam (None: no clipping; the paper mentions none).
    clip_norm: float | None = None

    def __post_init__(self):
        if not 0 < self.decay_rate <= 1:
            raise ValueError(f"decay_rate must lie in (0, 1], got {self.decay_rate}.")
        if self.clip_norm is not None and not self.clip_norm > 0:
            raise ValueError(f"clip_norm must be positive, got {self.clip_norm}.")


def schedule(tc: TrainConfig) -> optax.Schedule:
    """Learning rate per step: ``learning_rate * decay_rate ** (step / decay_steps)``.

    **Arguments:**

    - ``tc``: the training hyper-parameters.

    **Returns:**

    The optax schedule.
    """
    return optax.exponential_decay(tc.learning_rate, tc.decay_steps, tc.decay_rate)


def optimizer(tc: TrainConfig) -> optax.GradientTransformation:
    """Adam on :func:`schedule`, after clipping the gradient's global norm to ``tc.clip_norm`` when it is set.

    **Arguments:**

    - ``tc``: the training hyper-parameters.

    **Returns:**

    The optax gradient transformation.
    """
    if tc.clip_norm is None:
        return optax.adam(schedule(tc))
    return optax.chain(optax.clip_by_global_norm(tc.clip_norm), optax.adam(schedule(tc)))


def _batch(key, data, batch: int):
    n = data.shape[0]
    if n <= batch:
        return data
    return data[jax.random.choice(key, n, (batch,), replace=False)]


def step_batch(n_data: int, tc: TrainConfig) -> int:
    """The number of shapes in each step's batch for a training set of ``n_data`` shapes.

    **Arguments:**

    - ``n_data``: the training set's size.
    - ``tc``: the training hyper-parameters.

    **Returns:**

    ``min(n_data, tc.batch)``.
    """
    return min(int(n_data), tc.batch)


def level_states(m: model.Model) -> tuple[nnx.State, ...]:
    """The model's state split by level, as the step takes it.

    **Arguments:**

    - ``m``: the model.

    **Returns:**

    One ``nnx.State`` per level (``nnx.state(m.levels[l])``; its arrays are the model's, not copies).
    """
    return tuple(nnx.state(level) for level in m.levels)


def with_level_states(m: model.Model, states) -> model.Model:
    """A new model of ``m``'s structure and configuration holding ``states``.

    **Arguments:**

    - ``m``: the model whose structure is used (left unchanged).
    - ``states``: one ``nnx.State`` per level, as :func:`level_states` gives.

    **Returns:**

    The new :class:`~jaxdeform.components.model.Model`.
    """
    graphdef, state = nnx.split(m)
    out = nnx.merge(graphdef, jax.tree_util.tree_map(lambda a: a, state))  # Variables of its own: m stays as it is
    for level, state in zip(out.levels, states):
        nnx.update(level, state)
    return out


def make_step(
    m: model.Model,
    tc: TrainConfig,
    rings: Rings,
    dist,
    stage: int | None = None,
    *,
    mesh: jax.sharding.Mesh | None = None,
    axis: str = parallel.BATCH,
) -> Callable:
    """The jitted step (states, opt_state, key, data) -> (states, opt_state, key, loss, terms) of model ``m``:
    the loss's gradient (every term of eq. (2), the group sparsity's included) through :func:`optimizer` and
    ``optax.apply_updates``.

    ``states`` is :func:`level_states` of a model of ``m``'s structure (``m`` gives the levels' graph definitions
    and the configuration; its arrays are not used). The step donates ``states`` and ``opt_state``: their buffers
    may hold the outputs, so the arrays passed in are invalid after the call; pass each step the previous step's
    outputs.

    ``stage`` = None: joint training of every level. ``stage`` = l: separate training of level l; ``states``
    is then the prefix of levels 0..l, the levels before l are frozen (no gradient, not updated).

    ``mesh``: data parallel over ``mesh``'s ``axis`` (see the module's docstring). The step then takes and
    returns ``states``, ``opt_state``, ``key`` and ``data`` replicated over ``mesh`` (arrays elsewhere are copied
    onto it when called; place them with :func:`jaxdeform.parallel.replicate` to avoid the copy) and splits the
    batch along ``axis``; it raises ValueError when tracing if the step's batch (:func:`step_batch`) is not a
    multiple of ``mesh.shape[axis]``. Loss and terms come back replicated.
    """
    opt = optimizer(tc)
    if mesh is not None:
        parallel.axis_size(mesh, axis)  # KeyError now for a mesh without the axis

    config = m.config
    defs = tuple(nnx.graphdef(level) for level in m.levels)

    def levels(trainable, frozen):
        states = tuple(frozen) + (trainable,) if stage is not None else trainable
        return tuple(nnx.merge(d, s) for d, s in zip(defs, states))

    def loss_fn(trainable, frozen, x):
        out = model.forward_levels(levels(trainable, frozen), x, rings, dist, config)
        return out.loss, out.terms

    def step(params, opt_state, key, data):
        if mesh is not None:
            parallel.check_divisible(step_batch(data.shape[0], tc), mesh, axis, "step's batch")
        key, sub = jax.random.split(key)
        x = parallel.constrain_batch(_batch(sub, data, tc.batch), mesh, axis)
        if stage is None:
            trainable, frozen = params, ()
        else:
            trainable, frozen = params[stage], jax.lax.stop_gradient(params[:stage])
        (loss, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(trainable, frozen, x)
        updates, opt_state = opt.update(grads, opt_state, trainable)
        trainable = optax.apply_updates(trainable, updates)
        params = trainable if stage is None else tuple(params[:stage]) + (trainable,)
        return params, opt_state, key, loss, terms

    shardings = {}
    if mesh is not None:
        rep = parallel.replicated(mesh)
        shardings = {"in_shardings": rep, "out_shardings": rep}
    return jax.jit(step, compiler_options=xla.compiler_options(), donate_argnums=(0, 1), **shardings)


def _temp_bytes(compiled) -> int | None:
    """XLA's temporary-buffer bytes of a compiled program, when the backend reports them."""
    try:
        mem = compiled.memory_analysis()
    except (NotImplementedError, RuntimeError):
        return None
    return None if mem is None else int(mem.temp_size_in_bytes)


def _stages(config: model.Config, tc: TrainConfig) -> list[int | None]:
    return [None] if tc.joint else list(range(config.levels))


def _opt_init(tc: TrainConfig, params, stage):
    return optimizer(tc).init(params if stage is None else params[stage])


_Checkpoints = StepCheckpoints  # training checkpoints: jaxdeform.nn.archive.StepCheckpoints


def _state(params, opt_state, key, history, stage_index, epoch):
    return {
        "params": params,
        "opt_state": opt_state,
        "key": key,
        "history": history,
        "stage": np.int32(stage_index),
        "epoch": np.int32(epoch),
    }


def seed_keys(seed: int) -> tuple:
    """The two keys :func:`train` draws from ``seed``.

    **Arguments:**

    - ``seed``: the training seed.

    **Returns:**

    ``(batch key, initialisation key)``, the second for :class:`jaxdeform.components.model.Model` where no
    model is given.
    """
    key, init_key = jax.random.split(jax.random.PRNGKey(seed))
    return key, init_key


def _resume(ckpt: _Checkpoints, tc: TrainConfig, stages: list[int | None], params: tuple, key, history: np.ndarray):
    """The training state of ``ckpt``'s newest checkpoint, restored in the structure of the fresh state given.

    ``params`` (the level states, :func:`level_states`), ``key`` and ``history`` are the fresh run's (they give the checkpoint's tree structure and
    dtypes). Returns ``(params, opt_state, key, history, start_stage, start_epoch)`` as device arrays (a host
    copy for ``history``): training continues with epoch ``start_epoch`` of stage ``start_stage``.
    """
    latest = ckpt.latest()
    stage_index = min(latest // tc.epochs, len(stages) - 1)  # the stage whose optimizer state was saved
    stage0 = stages[stage_index]
    prefix = params if stage0 is None else params[: stage0 + 1]
    like = _state(params, _opt_init(tc, prefix, stage0), key, history, stage_index, 0)
    state = ckpt.restore(latest, jax.tree_util.tree_map(np.asarray, like))
    params = jax.tree_util.tree_map(jnp.asarray, tuple(state["params"]))  # nnx.State per level
    opt_state = jax.tree_util.tree_map(jnp.asarray, state["opt_state"])
    key = jnp.asarray(state["key"])
    history = np.asarray(state["history"]).copy()
    return params, opt_state, key, history, int(state["stage"]), int(state["epoch"])


def _full_params(sub, params: tuple, stage: int | None) -> tuple:
    """Every level's parameters: the trained ``sub`` (all levels, or levels 0..``stage``) followed by the levels
    of ``params`` after ``stage``."""
    return sub if stage is None else tuple(sub) + tuple(params[stage + 1 :])


class _StageLosses:
    """The step losses of one stage on their way into ``history`` (kept on the device until :meth:`flush`).

    ``history[base + e]`` receives the loss of epoch ``e`` of the stage; losses are appended in epoch order from
    epoch ``first``.
    """

    def __init__(self, history: np.ndarray, base: int, first: int):
        self.history, self.base = history, base
        self.losses, self.on_host = [], first  # the step losses of epochs on_host, on_host + 1, ... on the device

    def append(self, loss) -> None:
        self.losses.append(loss)  # kept on the device: no sync per step

    def flush(self, upto: int) -> None:
        """Write the losses of epochs < ``upto`` into ``history`` with one device_get."""
        self.history[self.base + self.on_host : self.base + upto] = host_scalars(self.losses)
        self.losses, self.on_host = [], upto


@dataclasses.dataclass
class _Run:
    """The fixed inputs and the side channels (log, progress bar, snapshots, checkpoints, timing) of one
    :func:`train` call; :meth:`stage` trains one stage with them. ``history`` is filled in place."""

    data: object
    rings: Rings
    dist: object
    template: model.Model  # the model's structure and configuration
    tc: TrainConfig
    stages: list
    history: np.ndarray
    mesh: object
    axis: str
    log: Callable | None
    log_every: int
    bar: object
    snapshot: Callable | None
    snapshot_every: int
    ckpt: _Checkpoints | None
    checkpoint_every: int
    timing: dict | None

    def stage(self, stage_index: int, first: int, params: tuple, opt_state, key) -> tuple:
        """Train stage ``stage_index`` from epoch ``first`` to ``tc.epochs``; returns ``(params, key)`` after it.

        ``params`` holds every level's state (:func:`level_states`); ``opt_state`` is the optimizer state to continue (used only when ``first``
        > 0; None or a fresh start initializes one). Every epoch's loss lands in ``history``; the compile and
        run times (when ``timing``) accumulate into ``timing``.
        """
        tc, timing, data = self.tc, self.timing, self.data
        stage = self.stages[stage_index]
        sub = params if stage is None else params[: stage + 1]
        step = make_step(self.template, tc, self.rings, self.dist, stage, mesh=self.mesh, axis=self.axis)
        if opt_state is None or first == 0:
            opt_state = _opt_init(tc, sub, stage)
        if self.mesh is not None:  # the compiled step takes its state on the mesh
            sub, opt_state, key = parallel.replicate((sub, opt_state, key), self.mesh)
        losses = _StageLosses(self.history, stage_index * tc.epochs, first)

        t0 = time.perf_counter()
        if first < tc.epochs:  # compiled ahead: its temporary-buffer size goes into the timing record
            step = step.lower(sub, opt_state, key, data).compile()
            temp = _temp_bytes(step)
            if timing is not None and temp is not None:
                timing["step_temp_bytes"] = max(temp, timing.get("step_temp_bytes", 0))
        for epoch in range(first, tc.epochs):
            if epoch == first and timing is not None:  # compiling and the first call: timed apart
                sub, opt_state, key, loss, terms = jax.block_until_ready(step(sub, opt_state, key, data))
                timing["compile_s"] = timing.get("compile_s", 0.0) + time.perf_counter() - t0
                t_run = time.perf_counter()
            else:
                sub, opt_state, key, loss, terms = step(sub, opt_state, key, data)
            losses.append(loss)
            self._after_epoch(stage_index, epoch, loss, terms, sub, opt_state, key, params, losses)
        if timing is not None and tc.epochs > first:
            jax.block_until_ready(sub)
            timing["run_s"] = timing.get("run_s", 0.0) + time.perf_counter() - t_run
            timing["epochs_timed"] = timing.get("epochs_timed", 0) + tc.epochs - first - 1
        losses.flush(tc.epochs)
        return _full_params(sub, params, stage), key

    def _after_epoch(
        self, stage_index: int, epoch: int, loss, terms, sub, opt_state, key, params: tuple, losses: _StageLosses
    ) -> None:
        """Log, progress, snapshot and checkpoint after ``epoch`` of stage ``stage_index``, each when due.

        ``sub``, ``opt_state``, ``key`` are the state after the epoch's step, ``params`` every level's parameters
        at the start of the stage.
        """
        tc, bar = self.tc, self.bar
        stage = self.stages[stage_index]
        done = epoch + 1
        if (self.log is not None or bar is not None) and (epoch % self.log_every == 0 or done == tc.epochs):
            terms_f = jax.tree_util.tree_map(float, terms)
            if self.log is not None:
                self.log(stage_index * tc.epochs + epoch, float(loss), terms_f)
            if bar is not None:
                bar.set_postfix_str(_terms_text(float(loss), terms_f), refresh=False)
        if bar is not None and (done % self.log_every == 0 or done == tc.epochs):
            bar.update(done - bar.n + stage_index * tc.epochs)
        if self.snapshot is not None and done % self.snapshot_every == 0:
            self.snapshot(
                stage_index * tc.epochs + done, with_level_states(self.template, _full_params(sub, params, stage))
            )
        if self.ckpt is not None and (done % self.checkpoint_every == 0 or done == tc.epochs):
            losses.flush(done)
            self._save(stage_index, done, _full_params(sub, params, stage), opt_state, key)

    def _save(self, stage_index: int, done: int, full: tuple, opt_state, key) -> None:
        """Checkpoint after ``done`` epochs of stage ``stage_index`` (``full``: every level's parameters).

        Mid-stage the optimizer state is saved as is; at the end of a stage the checkpoint holds the next
        stage's fresh optimizer state and epoch 0 of it (after the last stage: stage ``len(stages)``).
        """
        tc, stages, history = self.tc, self.stages, self.history
        base = stage_index * tc.epochs
        if done < tc.epochs:
            saved = _state(full, opt_state, key, history, stage_index, done)
        elif stage_index + 1 < len(stages):  # the next stage starts with a fresh optimizer
            nxt = stages[stage_index + 1]
            saved = _state(full, _opt_init(tc, full[: nxt + 1], nxt), key, history, stage_index + 1, 0)
        else:
            saved = _state(full, opt_state, key, history, len(stages), 0)
        self.ckpt.save(base + done, saved)


def _initial_model(m, init_key, n_vertices: int, config: model.Config, dtype) -> tuple:
    """The model :func:`train` starts from and its level states: a fresh ``model.Model`` from ``init_key`` when
    ``m`` is None, else ``m`` with copies of its arrays (the step donates its state: the caller's model stays
    valid). Returns ``(model, level states)``; ValueError if ``m`` was built with another configuration."""
    if m is None:
        m = model.Model(n_vertices, config, key=init_key, dtype=dtype)
    elif m.config != config:
        raise ValueError("the model to continue was built with another configuration than config.")
    return m, jax.tree_util.tree_map(jnp.copy, level_states(m))


def _progress_bar(total: int, initial: int):
    """A tqdm bar of ``total`` epochs starting at ``initial`` (resumed runs), labelled "components train".
    The caller closes it."""
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        initial=initial,
        desc="components train",
        unit="epoch",
        dynamic_ncols=True,
    )


def train(
    data,
    rings: Rings,
    dist,
    config: model.Config,
    tc: TrainConfig,
    *,
    model: model.Model | None = None,
    checkpoint_dir=None,
    checkpoint_every: int = 1000,
    resume: bool = False,
    progress: bool = False,
    log: Callable[[int, float, dict], None] | None = None,
    log_every: int = 100,
    timing: dict | None = None,
    snapshot: Callable[[int, model.Model], None] | None = None,
    snapshot_every: int = 1000,
    mesh: jax.sharding.Mesh | None = None,
    axis: str = parallel.BATCH,
):
    """Train for ``tc.epochs`` epochs (per level when ``tc.joint`` is False).

    **Arguments:** ``data``: scaled ACAP features ``(N, V, 9)``; ``rings``, ``dist`` ``(V, V)``: one-rings and
    normalized geodesics; ``config``, ``tc``: model and training hyper-parameters; ``model``: start from this model
    (built with ``config``) instead of a fresh one; ``checkpoint_dir``, ``checkpoint_every``, ``resume``: checkpoints; ``progress``: a tqdm
    bar with the loss terms and ``log(epoch, loss, terms)``, both every ``log_every`` epochs; ``timing``: receives the
    compile and training times; ``snapshot(epochs_done, model)`` (learning curves): every ``snapshot_every`` epochs of
    a stage; ``mesh``: data parallel over ``mesh``'s ``axis`` (module docstring).

    **Returns:** ``(model, history)``: the trained :class:`~jaxdeform.components.model.Model` (a new Module; its
    arrays replicated over ``mesh`` when given) and the loss history ``(stages * epochs,)``.

    **Raises:** ``ValueError`` before any step if ``min(len(data), tc.batch)`` is not a multiple of
    ``mesh.shape[axis]``, or if ``model`` was built with another configuration than ``config``.
    """
    data = jnp.asarray(data)
    if mesh is not None:
        parallel.check_divisible(step_batch(data.shape[0], tc), mesh, axis, "step's batch")
        data = parallel.replicate(data, mesh)
    dtype = data.dtype
    key, init_key = seed_keys(tc.seed)
    template, params = _initial_model(model, init_key, data.shape[1], config, dtype)
    stages = _stages(config, tc)
    history = np.zeros(len(stages) * tc.epochs, np.float32)
    dist = jnp.asarray(dist, dtype)
    ckpt = _Checkpoints(checkpoint_dir, checkpoint_every) if checkpoint_dir is not None else None

    start_stage, start_epoch = 0, 0
    if ckpt is not None and resume and ckpt.latest() is not None:
        params, opt_state, key, history, start_stage, start_epoch = _resume(ckpt, tc, stages, params, key, history)
    else:
        opt_state = None

    bar = _progress_bar(len(stages) * tc.epochs, start_stage * tc.epochs + start_epoch) if progress else None
    run = _Run(
        data,
        rings,
        dist,
        template,
        tc,
        stages,
        history,
        mesh,
        axis,
        log,
        log_every,
        bar,
        snapshot,
        snapshot_every,
        ckpt,
        checkpoint_every,
        timing,
    )
    for stage_index in range(start_stage, len(stages)):
        first = start_epoch if stage_index == start_stage else 0
        params, key = run.stage(stage_index, first, params, opt_state, key)
        opt_state = None
    if bar is not None:
        bar.close()
    return with_level_states(template, params), history


def _terms_text(loss: float, terms: list) -> str:
    parts = [f"loss {loss:.4g}"]
    for level, t in enumerate(terms):
        parts.append(f"L{level} rec {t['recon']:.3g} sp {t['sparsity']:.3g} lat {t['latent']:.2g}")
    return " | ".join(parts)


@functools.cache
def _reconstruct_jit():
    # built on first use: the compiler options depend on the backend, which importing must not initialize. The
    # model enters as a pytree (nnx Modules are): its configuration is part of the tree's static structure.
    return jax.jit(lambda m, x, rings: m.reconstruction(x, rings), compiler_options=xla.compiler_options())


def reconstruct(m: model.Model, data, rings: Rings):
    """The model's reconstruction of scaled features (jitted; one compilation per configuration and shape).

    **Arguments:**

    - ``m``: the model.
    - ``data``: scaled ACAP features ``(N, V, 9)``.
    - ``rings``: the mesh's one-ring neighbourhoods.

    **Returns:**

    The reconstructed scaled features ``(N, V, 9)``.
    """
    return _reconstruct_jit()(m, data, rings)


def save_params(checkpoint_dir, m: model.Model, step: int) -> None:
    """Write the state of model ``m`` as the checkpoint of ``step`` in ``checkpoint_dir``.

    The model's state only (as training checkpoints hold it, :func:`level_states`): :func:`load_params` reads
    it; a training cannot resume from it.

    **Arguments:**

    - ``checkpoint_dir``: the checkpoint folder.
    - ``m``: the model.
    - ``step``: the step number the checkpoint is saved under.

    **Returns:**

    Nothing.
    """
    _Checkpoints(checkpoint_dir, 1).save(int(step), {"params": level_states(m)})


def load_params(checkpoint_dir, like: model.Model) -> model.Model:
    """The model of the newest checkpoint in ``checkpoint_dir``.

    **Arguments:**

    - ``checkpoint_dir``: the checkpoint folder.
    - ``like``: a model of the checkpoint's configuration (e.g. freshly built); it gives the structure and the
        dtypes and is left unchanged.

    **Returns:**

    A new :class:`~jaxdeform.components.model.Model` of ``like``'s structure holding the checkpoint's state.

    **Raises:**

    ``FileNotFoundError`` if the folder holds no checkpoint; ``ValueError`` if the checkpoint does not hold the
    state of a model of ``like``'s configuration (other structure or shapes).
    """
    ckpt = _Checkpoints(checkpoint_dir, 1)
    latest = ckpt.latest()
    if latest is None:
        raise FileNotFoundError(f"{checkpoint_dir}: no checkpoint in it.")
    restored = ckpt.manager.restore(latest, args=ckpt._ocp.args.StandardRestore())  # nested dicts and lists
    saved = _arrays_by_path(restored["params"])
    like_states = level_states(like)
    paths, treedef = jax.tree_util.tree_flatten_with_path(like_states)
    wanted = {_path_name(path): leaf for path, leaf in paths}
    if saved.keys() != wanted.keys() or any(saved[k].shape != wanted[k].shape for k in wanted):
        raise ValueError(f"{checkpoint_dir}: the checkpoint does not hold parameters of this configuration.")
    states = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(saved[_path_name(path)]) for path, _ in paths])
    return with_level_states(like, states)


def _path_name(path) -> str:
    """A pytree path as "0/conv_enc/W_point": sequence indices and dict keys, a Variable's "value" left out."""
    parts = [str(getattr(k, "key", getattr(k, "idx", getattr(k, "name", k)))) for k in path]
    return "/".join(p for p in parts if p != "value")


def _arrays_by_path(tree) -> dict:
    """The leaves of a restored checkpoint tree by :func:`_path_name`."""
    return {_path_name(path): np.asarray(leaf) for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}
