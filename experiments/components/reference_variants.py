"""Diagnostic: three details in which Tan et al.'s public TF1 code (convMesh, the code seed 000 builds on) differs
from this project's seed-000 block, each trained in memory by :mod:`experiments.components.sweep`.

    python -m experiments.components.reference_variants --variant init|tie|init-tie|linear-fc [sweep options]

- ``init``: every weight (both convolutions' W_point and W_neighbor, and C) drawn from N(0, 0.02^2), the biases
  zero, as that code initialises them (here: Glorot-uniform, the C of horse-gallop about 0.005 standard deviation,
  the 9x9 convolutions about 0.33).
- ``tie``: the decoder's convolution uses the encoder's W_point and W_neighbor (its bias its own), as that code
  does and as the paper's Fig. 1 caption reads ("the encoder and decoder share the same trainable parameters");
  here the two convolutions have their own weights and only C is shared.
- ``init-tie``: both.
- ``linear-fc``: the decoder without a tanh on z C, x_hat = tanh(conv_dec(reshape(z C))), as that code has it
  (here: tanh(conv_dec(tanh(reshape(z C)))), the paper's "all the layers use the tanh").

The variants are swapped in for this process only (the model's level function and the decoder), so
that the library keeps one block definition; every other option is the sweep's, and the result line is the
sweep's with ``"variant"`` added to its configuration.
"""

from __future__ import annotations

import argparse
import contextlib
import sys

VARIANTS = ("init", "tie", "init-tie", "linear-fc")
TAN_STD = 0.02  # convMesh: tf.random_normal_initializer(stddev=0.02) for every weight
WEIGHTS = ("W_point", "W_neighbor", "C")


def normal_weights(params: tuple, key, std: float) -> tuple:
    """``params`` with every weight matrix (W_point, W_neighbor, C) redrawn from N(0, std^2); biases kept."""
    import jax

    leaves, tree = jax.tree_util.tree_flatten_with_path(params)
    keys = jax.random.split(key, len(leaves))
    out = []
    for (path, leaf), k in zip(leaves, keys):
        name = getattr(path[-1], "key", None)
        if name not in WEIGHTS + ("b",):
            raise ValueError(f"unexpected parameter {jax.tree_util.keystr(path)}: only {WEIGHTS} and biases are known.")
        out.append((std * jax.random.normal(k, leaf.shape)).astype(leaf.dtype) if name != "b" else leaf)
    return jax.tree_util.tree_unflatten(tree, out)


def tie_decoders(params: tuple) -> tuple:
    """Every block's decoder convolution with its encoder convolution's W_point and W_neighbor (bias its own)."""
    return tuple({**p, "conv_dec": {**p["conv_dec"], "W_point": p["conv_enc"]["W_point"],
                                    "W_neighbor": p["conv_enc"]["W_neighbor"]}} for p in params)


@contextlib.contextmanager
def swapped(variant: str):
    """Within the block, the model trains and reconstructs as ``variant`` (see the module docstring). JAX's
    caches of traced and compiled programs are cleared on entry and on exit, so that no program traced with the
    block as it was serves inside, nor one traced inside serves after; the swapped functions are restored on exit,
    also where the block raises.

    ``tie``: the parameters :func:`jaxdeform.components.train.train` returns hold the trained encoder weights in
    the decoders too, so that code reading the parameters without the model's level function (components,
    editing, :func:`jaxdeform.components.model.decode_latents`) decodes with them."""
    import jax

    from jaxdeform.components import model, train
    from jaxdeform.nn import graph_conv

    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}.")
    saved = (model._levels, graph_conv.ae_decode, train.train)
    levels, _, fit = saved

    def tied(params, *args, **kwargs):
        return levels(tie_decoders(params), *args, **kwargs)

    def decode_linear_fc(params, z, rings):
        g = graph_conv.ae_decode_pre(params, z)
        return graph_conv._tanh(graph_conv.mesh_conv(params["conv_dec"], g, rings.neighbors, rings.mask,
                                                     rings.degree))

    def train_variant(data, rings, dist, config, tc, **kwargs):
        if "init" in variant:
            if kwargs.get("params") is not None:
                raise ValueError("the init variant draws the initial parameters itself; params cannot be given.")
            init_key = train.seed_keys(tc.seed)[1]  # train()'s own: the batches follow the same seed
            params = model.init(init_key, data.shape[1], config, data.dtype)
            kwargs["params"] = normal_weights(params, init_key, TAN_STD)
        params, history = fit(data, rings, dist, config, tc, **kwargs)
        return (tie_decoders(params) if "tie" in variant else params), history

    def clear():
        jax.clear_caches()
        train._reconstruct_jit.cache_clear()

    clear()
    try:
        if "tie" in variant:
            model._levels = tied
        train.train = train_variant
        if variant == "linear-fc":
            graph_conv.ae_decode = decode_linear_fc
        yield
    finally:
        model._levels, graph_conv.ae_decode, train.train = saved
        clear()


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", choices=VARIANTS, required=True)
    a, rest = ap.parse_known_args(argv)
    from experiments.components import sweep

    with swapped(a.variant):
        return sweep.main(rest, extra_config={"variant": a.variant})


if __name__ == "__main__":
    main(sys.argv[1:])
