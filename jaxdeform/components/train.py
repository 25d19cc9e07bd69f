"""Training of the multiscale model: one jitted Adam step on batches sampled from the training shapes.

Adam (optax) with learning rate 1e-3 and exponential decay, batches of up to 256 shapes sampled with an explicit
PRNG key, all in one jitted step (parameters, optimizer state and key in, the same out).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxdeform.components import model
from jaxdeform.nn.graph_conv import Rings


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    epochs: int = 10_000
    batch: int = 256
    learning_rate: float = 1e-3
    decay_rate: float = 0.96  # exponential decay: lr * decay_rate ** (step / decay_steps)
    decay_steps: int = 1000
    seed: int = 0


def optimizer(tc: TrainConfig) -> optax.GradientTransformation:
    schedule = optax.exponential_decay(tc.learning_rate, tc.decay_steps, tc.decay_rate)
    return optax.adam(schedule)


def make_step(config: model.Config, tc: TrainConfig, rings: Rings, dist) -> Callable:
    """The jitted step (params, opt_state, key, data) -> (params, opt_state, key, loss, terms)."""
    opt = optimizer(tc)

    def loss_fn(params, x):
        out = model.forward(params, x, rings, dist, config)
        return out.loss, out.terms

    @jax.jit
    def step(params, opt_state, key, data):
        key, sub = jax.random.split(key)
        n = data.shape[0]
        idx = jax.random.choice(sub, n, (min(tc.batch, n),), replace=n < tc.batch)
        (loss, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, data[idx])
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, key, loss, terms

    return step


def train(data, rings: Rings, dist, config: model.Config, tc: TrainConfig, *, params=None,
          log: Callable[[int, float, dict], None] | None = None, log_every: int = 100):
    """Train from scratch (or from ``params``) for ``tc.epochs`` steps; returns (params, loss history (epochs,))."""
    data = jnp.asarray(data)
    key = jax.random.PRNGKey(tc.seed)
    key, init_key = jax.random.split(key)
    if params is None:
        params = model.init(init_key, data.shape[1], config, data.dtype)
    opt_state = optimizer(tc).init(params)
    step = make_step(config, tc, rings, jnp.asarray(dist, data.dtype))
    losses = []
    for epoch in range(tc.epochs):
        params, opt_state, key, loss, terms = step(params, opt_state, key, data)
        losses.append(loss)  # kept on the device: no sync per step
        if log is not None and epoch % log_every == 0:
            log(epoch, float(loss), jax.tree_util.tree_map(float, terms))
    return params, np.asarray(jnp.stack(losses))


@functools.partial(jax.jit, static_argnames=("config",))
def reconstruct(params, data, rings: Rings, dist, config: model.Config):
    """The model's reconstruction (N, V, 9) of scaled features (N, V, 9)."""
    return model.forward(params, data, rings, dist, config).reconstruction
