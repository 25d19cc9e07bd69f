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

Each variant is a set of options of the model's configuration (:class:`jaxdeform.components.model.Config`:
``init``/``init_std``, ``tie_conv``, ``decoder_tanh``; :data:`VARIANTS`), passed to the sweep as its model
options; every other option is the sweep's, and the result line is the sweep's with ``"variant"`` added to its
configuration (which holds the options too).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

TAN_STD = 0.02  # convMesh: tf.random_normal_initializer(stddev=0.02) for every weight
#: variant -> the options of jaxdeform.components.model.Config that give it
VARIANTS = {
    "init": {"init": "normal", "init_std": TAN_STD},
    "tie": {"tie_conv": True},
    "init-tie": {"init": "normal", "init_std": TAN_STD, "tie_conv": True},
    "linear-fc": {"decoder_tanh": False},
}


def variant_config(config, variant: str):
    """``config`` (a :class:`jaxdeform.components.model.Config`) with the options of ``variant``."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {tuple(VARIANTS)}, got {variant!r}.")
    return dataclasses.replace(config, **VARIANTS[variant])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", choices=tuple(VARIANTS), required=True)
    a, rest = ap.parse_known_args(argv)
    from experiments.components import sweep

    return sweep.main(rest, extra_config={"variant": a.variant}, model_options=VARIANTS[a.variant])


if __name__ == "__main__":
    main(sys.argv[1:])
