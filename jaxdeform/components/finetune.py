"""Fine-tuning a trained seed-000 autoencoder run for its vertices (``jaxdeform components finetune``).

The paper trains on the scaled ACAP features' squared error only. On horse-gallop's unseen shapes that error is a
poor guide to the vertices': a small, smooth rotation error that a leg integrates costs little in the features and
much in the positions, so neither a closer fit of the features nor more shapes in feature space lowers Erms (README,
seed 000). Here the run's model (encoders and decoders, every level) trains further on, per step, ``batch`` shapes
drawn from the training shapes and ``mixes`` regional mixes of them (:func:`regional_mixes`), with the loss

    model loss (the sum of the blocks' losses, as in training) + w * mean_v |p_v - g_v|^2 / r^2,

where p is the ACAP reconstruction of the model's output (one prefactored, differentiable solve, no refinement),
g that of the shape's own features, both centred (the translation is free), and r^2 the reference shape's mean
squared distance from its centroid. Adam, its learning rate constant or, with ``lr_final``, falling from ``lr``
to ``lr_final`` over the steps along a half cosine. The mixes matter: the position term on the
training shapes alone changes nothing (their reconstruction is already close), and the mixes alone, with the
feature loss, raise Erms.

The result is a run folder like any other (the generalization protocol is unchanged: encode, decode,
reconstruct); its run.json records the fine-tuning under ``finetune``.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from jaxdeform import acap
from jaxdeform.components import run as crun
from jaxdeform.components import train
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import rings_from_topology


def regional_mixes(
    x: np.ndarray,
    dist: np.ndarray,
    n: int,
    rng: np.random.Generator,
    regions: tuple[int, int] = (3, 12),
    sigma: float = 0.15,
    alpha: float = 0.5,
) -> np.ndarray:
    """Regional mixes of shapes: every vertex a convex combination of the shapes, varying smoothly over the surface.

    A mix picks R ~ U{regions} random centre vertices, gives each a Dirichlet(alpha) combination of the S shapes,
    and blends the centres' combinations over the mesh by the normalized Gaussian weights exp(-(dist / sigma)^2)
    of the geodesic distances.

    **Arguments:**

    - ``x``: the S shapes ``(S, V, C)`` (e.g. scaled features).
    - ``dist``: geodesic distances ``(V, V)``.
    - ``n``: the number of mixes.
    - ``rng``: the random generator.
    - ``regions``: the range of R.
    - ``sigma``: the Gaussian's width, in the units of ``dist``.
    - ``alpha``: the Dirichlet concentration.

    **Returns:**

    The mixes ``(n, V, C)``.
    """
    s, v, _ = x.shape
    out = np.empty((n,) + x.shape[1:], x.dtype)
    for i in range(n):  # data preparation, once per run
        centres = rng.choice(v, rng.integers(regions[0], regions[1] + 1), replace=False)
        w = np.exp(-((np.asarray(dist[centres], np.float64) / sigma) ** 2))  # (R, V)
        w /= np.maximum(w.sum(axis=0, keepdims=True), 1e-300)
        per_vertex = w.T @ rng.dirichlet(np.full(s, alpha), size=len(centres))  # (V, S), rows sum to 1
        out[i] = np.einsum("vs,svc->vc", per_vertex, x)
    return out


def generated_meshes(
    run: crun.Run,
    x: np.ndarray,
    dist: np.ndarray,
    n: int,
    noise: float,
    rng: np.random.Generator,
    rings,
    chunk: int = 16,
) -> np.ndarray:
    """(n, V, 9) scaled ACAP features of meshes the run's model generates beyond the mixes: the codes that its
    encoder gives ``n`` regional mixes of the shapes ``x`` (S, V, 9), each code entry moved by ``noise`` times its
    standard deviation over those codes (Gaussian), decoded, reconstructed to vertices, and those meshes' own
    features extracted again (rotation branches aligned, scaled: what an unseen shape gives the encoder)."""
    base = regional_mixes(x, dist, n, rng)
    enc = jax.jit(lambda m, xb: m.encode(xb, rings))
    dec = jax.jit(lambda m, zb: m.decode_latents(zb, rings))
    codes = [
        np.concatenate(z, axis=1)
        for z in zip(*[enc(run.model, jnp.asarray(base[i : i + chunk])) for i in range(0, n, chunk)])
    ]  # per level (n_l, n, Kz)
    moved = [c + noise * c.std(axis=1, keepdims=True) * rng.standard_normal(c.shape).astype(c.dtype) for c in codes]
    feats = np.concatenate(
        [np.asarray(dec(run.model, tuple(jnp.asarray(c[:, i : i + chunk]) for c in moved))) for i in range(0, n, chunk)]
    )
    return np.asarray(crun.scaled_features(run, crun.positions_from_scaled(run, feats)), x.dtype)


def rigid_residual(p, g):
    """(B, V, 3) residual of positions p against targets g after centring both and rotating each p onto its g by
    the proper rotation that minimizes the squared residual (Kabsch), as Erms aligns a reconstruction. The rotation
    enters without a gradient: at the minimizing rotation the squared residual's derivative in it vanishes
    (envelope theorem), so the gradient in p is that of the full minimum."""
    p = p - jnp.mean(p, axis=1, keepdims=True)
    g = g - jnp.mean(g, axis=1, keepdims=True)
    a = jax.lax.stop_gradient(jnp.einsum("bvx,bvy->bxy", g, p))  # R maximizing tr(R^T a) maps p onto g
    u, _, vt = jnp.linalg.svd(a)
    flip = jnp.where(jnp.linalg.det(u @ vt) < 0, -1.0, 1.0).astype(u.dtype)
    u = u.at[..., :, 2].multiply(flip[..., None])
    r = u @ vt
    return jnp.einsum("bxy,bvy->bvx", r, p) - g


def position_loss_fn(run: crun.Run, rings, dist, weight: float, rigid: bool = False, solver: str | None = None):
    """The fine-tuning loss and its parts, as functions.

    **Arguments:**

    - ``run``: the autoencoder run.
    - ``rings``: the mesh's one-rings.
    - ``dist``: normalized geodesic distances ``(V, V)``.
    - ``weight``: the position term's weight w.
    - ``rigid``: take the term after rotating each reconstruction onto its target (:func:`rigid_residual`), so a
        global rotation, which Erms does not count, costs nothing.
    - ``solver``: the reconstruction's linear solver, "host", "dense" or "cg" (:func:`jaxdeform.acap.prepare`; None:
        :func:`jaxdeform.acap.default_solver`).

    **Returns:**

    ``(loss, positions, term)``: ``loss(params (nnx.state(run.model)), x (B, V, 9) scaled features, g (B, V, 3)
    their positions)`` ->
    ``(total, (model loss, position term))``, the module docstring's loss, one differentiable function;
    ``positions(x)`` the plain ACAP reconstruction of scaled features that the position term compares (the targets
    g come from it too); ``term(x_hat, g)`` the position term of the model's output x_hat.
    """
    machinery = acap.cached(run.rest, run.faces, solver=solver)
    machinery.reconstructor(None)  # factorized now, not inside a trace
    inv_r2 = 1.0 / float(np.mean(np.sum((run.rest - run.rest.mean(axis=0)) ** 2, axis=-1)))

    def positions(x):
        return machinery.decode(run.scaler.inverse(x).astype(jnp.float64), refine=0)

    def term(x_hat, g):
        if rigid:
            d = rigid_residual(positions(x_hat), g)
        else:
            d = positions(x_hat) - g
            d = d - jnp.mean(d, axis=1, keepdims=True)
        return (jnp.mean(jnp.sum(d * d, axis=-1)) * inv_r2).astype(x_hat.dtype)

    graphdef = nnx.graphdef(run.model)

    def loss(params, x, g):
        out = nnx.merge(graphdef, params)(x, rings, dist)
        pos = term(out.reconstruction, g)
        return out.loss + weight * pos, (out.loss, pos)

    return loss, positions, term


def make_step(
    run: crun.Run,
    rings,
    dist,
    weight: float,
    opt: optax.GradientTransformation,
    rigid: bool = False,
    solver: str | None = None,
):
    """step(params, state, x, g) -> (params, state, (model loss, position term)), ``params`` the ``nnx.State`` of a
    model of ``run.model``'s structure (``nnx.state(run.model)``): one Adam step on
    :func:`position_loss_fn`'s loss, as three jitted stages: the model's forward with its VJP, the position term
    with its gradient in the model's output, then the model's pullback and the update. The same gradient as one
    jitted ``value_and_grad`` of the loss; the ACAP decode inside a larger XLA program loses the stage boundaries
    that keep it fast on the CPU (the staged step runs in about half the time of the fused one)."""
    _, _, term = position_loss_fn(run, rings, dist, weight, rigid, solver)
    graphdef = nnx.graphdef(run.model)

    @jax.jit
    def forward(params, x):
        def f(p):
            out = nnx.merge(graphdef, p)(x, rings, dist)
            return out.loss, out.reconstruction

        (model_loss, x_hat), pullback = jax.vjp(f, params)
        return model_loss, x_hat, pullback

    position = jax.jit(jax.value_and_grad(term))

    @jax.jit
    def update(params, state, pullback, model_loss, pos, d_x_hat):
        (grad,) = pullback((jnp.ones_like(model_loss), (weight * d_x_hat).astype(d_x_hat.dtype)))
        updates, state = opt.update(grad, state, params)
        return optax.apply_updates(params, updates), state, jnp.stack([model_loss, pos])

    def step(params, state, x, g):
        model_loss, x_hat, pullback = forward(params, x)
        pos, d_x_hat = position(x_hat, g)
        return update(params, state, pullback, model_loss, pos, d_x_hat)

    return step


def check_run(run: crun.Run) -> None:
    """Check that ``run`` can be fine-tuned.

    **Arguments:**

    - ``run``: a components run.

    **Returns:**

    Nothing.

    **Raises:**

    ``RunError`` (one sentence) for a run without an autoencoder.
    """
    if run.method not in crun.AUTOENCODERS:
        raise crun.RunError(f"{run.path} is a {run.method} run: only multiscale and tan runs can be fine-tuned.")


def check_options(
    steps: int,
    batch: int,
    mixes: int,
    position_weight: float,
    lr: float,
    seed: int = 0,
    lr_final: float | None = None,
    generated: int = 0,
    code_noise: float = 1.0,
    solver: str | None = None,
) -> None:
    """Check the fine-tuning options.

    **Arguments:**

    As :func:`finetune`'s.

    **Returns:**

    Nothing.

    **Raises:**

    ``ValueError`` (one sentence) for an option out of range.
    """
    if solver is not None and solver not in acap.SOLVERS:
        raise ValueError(f"--solver must be one of {', '.join(acap.SOLVERS)}, got '{solver}'.")
    if seed < 0:
        raise ValueError(f"--seed must be a non-negative integer, got {seed}.")
    if steps < 1 or batch < 1:
        raise ValueError(f"--steps and --batch must be positive integers, got {steps} and {batch}.")
    if mixes < 0 or generated < 0:
        raise ValueError(f"--mixes and --generated must be non-negative integers, got {mixes} and {generated}.")
    if not (np.isfinite(code_noise) and code_noise >= 0):
        raise ValueError(f"--code-noise must be a non-negative number, got {code_noise}.")
    if not (np.isfinite(position_weight) and position_weight >= 0):
        raise ValueError(f"--position-weight must be a non-negative number, got {position_weight}.")
    if not (np.isfinite(lr) and lr > 0):
        raise ValueError(f"--lr must be a positive number, got {lr}.")
    if lr_final is not None and not (np.isfinite(lr_final) and 0 < lr_final <= lr):
        raise ValueError(f"--lr-final must be a positive number no larger than --lr ({lr}), got {lr_final}.")


def schedule(lr: float, steps: int, lr_final: float | None = None):
    """The learning rate: ``lr`` throughout, or from ``lr`` at step 0 to ``lr_final`` at the last step along a half
    cosine."""
    if lr_final is None or lr_final == lr:
        return lr
    return optax.cosine_decay_schedule(lr, max(steps - 1, 1), alpha=lr_final / lr)


def finetune(
    run: crun.Run,
    x_train,
    *,
    mixes: int = 400,
    steps: int = 1000,
    batch: int = 8,
    position_weight: float = 1e5,
    lr: float = 2e-4,
    seed: int = 0,
    progress: bool = True,
    lr_final: float | None = None,
    rigid: bool = False,
    generated: int = 0,
    code_noise: float = 1.0,
    solver: str | None = None,
):
    """Fine-tune the run's model on its training shapes and their mixes (module docstring).

    **Arguments:**

    - ``run``: an autoencoder run.
    - ``x_train``: the training shapes' scaled ACAP features ``(N, V, 9)``.
    - ``mixes``: regional mixes of the training shapes added to the pool (:func:`regional_mixes`).
    - ``steps``, ``batch``: Adam steps and shapes per step.
    - ``position_weight``: the weight w of the position term.
    - ``lr``, ``lr_final``: the learning rate, constant or falling to ``lr_final`` (:func:`schedule`).
    - ``seed``, ``progress``: the seed of the mixes and the batches; show a progress bar.
    - ``rigid``: the position term after rotating each reconstruction onto its target (:func:`rigid_residual`).
    - ``generated``, ``code_noise``: shapes the model generates from noisy codes of regional mixes, added to the pool
        (:func:`generated_meshes`).
    - ``solver``: the reconstruction's linear solver (:func:`position_loss_fn`).

    **Returns:**

    ``(model, history)``: the fine-tuned Module (a new one) and ``(steps, 2)``: the model loss and position term of each
    step's batch before its update.

    **Raises:**

    ``ValueError`` for an option out of range (:func:`check_options`); ``RunError`` for a run without an autoencoder.
    """
    check_options(steps, batch, mixes, position_weight, lr, seed, lr_final, generated, code_noise, solver)
    check_run(run)
    faces, rest = run.faces, run.rest
    dtype = np.dtype(run.record.get("dtype", "float32"))
    dist = crun.normalized_geodesics(rest, faces, dtype)
    rng = np.random.default_rng(seed)
    x_train = np.asarray(x_train, dtype)
    pool = np.concatenate([x_train, regional_mixes(x_train, dist, mixes, rng)]) if mixes else x_train
    rings = rings_from_topology(build_topology(faces, rest.shape[0]))
    if generated:
        pool = np.concatenate([pool, generated_meshes(run, x_train, dist, generated, code_noise, rng, rings)])
    _, positions, _ = position_loss_fn(run, rings, jnp.asarray(dist), position_weight, solver=solver)
    positions = jax.jit(positions)
    targets = np.concatenate([np.asarray(positions(jnp.asarray(pool[i : i + 8]))) for i in range(0, len(pool), 8)])
    opt = optax.adam(schedule(lr, steps, lr_final))
    step = make_step(run, rings, jnp.asarray(dist), position_weight, opt, rigid, solver)

    graphdef, params = nnx.split(run.model)
    params = jax.tree_util.tree_map(jnp.copy, params)  # a state of its own: run.model stays as it is
    state = opt.init(params)
    history = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, desc="components finetune", unit="step", dynamic_ncols=True)
    for i in range(steps):
        idx = rng.choice(len(pool), min(batch, len(pool)), replace=False)
        params, state, terms = step(params, state, jnp.asarray(pool[idx]), jnp.asarray(targets[idx]))
        history.append(terms)  # kept on the device: no sync per step
        if bar is not None and (i % 20 == 0 or i + 1 == steps):
            t = np.asarray(terms)
            bar.set_postfix_str(f"model {t[0]:.4g} position {t[1]:.3g}", refresh=False)
            bar.update(i + 1 - bar.n)
    if bar is not None:
        bar.close()
    history = np.asarray(jax.device_get(history), np.float64).reshape(steps, 2)  # one transfer, no XLA op
    return nnx.merge(graphdef, params), history


def fit(
    run: crun.Run,
    out: Path,
    data=None,
    *,
    mixes: int = 400,
    steps: int = 1000,
    batch: int = 8,
    position_weight: float = 1e5,
    lr: float = 2e-4,
    seed: int = 0,
    progress: bool = True,
    lr_final: float | None = None,
    rigid: bool = False,
    generated: int = 0,
    code_noise: float = 1.0,
    solver: str | None = None,
) -> dict:
    """Fine-tune ``run`` and write the result as a new run folder.

    The options and the run are checked by :func:`finetune`; a caller that wants them refused before the features
    are read calls :func:`check_options` and :func:`check_run` first, as the CLI does.

    **Arguments:**

    - ``run``: an autoencoder run.
    - ``out``: the empty folder to write: a copy of the run with the new parameters and training codes, and
        run.json with ``finetune``.
    - ``data``: the data folder to read the training shapes from (default None: the run's data folder).
    - the other options: as :func:`finetune`'s.

    **Returns:**

    The ``finetune`` record: options, seconds, first and last loss terms, source run.
    """
    vertices, _ = crun.run_data(run, data)
    x_train = crun.scaled_features(run, vertices[run.train_idx])
    options = dict(
        mixes=mixes,
        steps=steps,
        batch=batch,
        position_weight=position_weight,
        lr=lr,
        seed=seed,
        lr_final=lr_final,
        rigid=rigid,
        generated=generated,
        code_noise=code_noise,
        solver=solver,
    )
    t0 = time.perf_counter()
    tuned, history = finetune(run, x_train, progress=progress, **options)
    record = {
        **options,
        "lr_final": lr if lr_final is None else lr_final,
        "solver": acap.default_solver(run.rest.shape[0]) if solver is None else solver,
        "seconds": round(time.perf_counter() - t0, 1),
        "first_terms": history[0].tolist(),
        "last_terms": history[-1].tolist(),
        "source": str(run.path),
    }
    out = Path(out)
    for name in ("mesh.npz", "history.npy"):
        if (run.path / name).is_file():
            shutil.copy2(run.path / name, out / name)
    train.save_params(out / "params", tuned, steps)
    rings = rings_from_topology(build_topology(run.faces, run.rest.shape[0]))
    codes = tuned.encode(jnp.asarray(x_train), rings)
    np.savez(out / "codes.npz", **{f"level{i}": np.asarray(z) for i, z in enumerate(codes)})
    (out / "run.json").write_text(json.dumps(dict(run.record, finetune=record), indent=2))
    return record
