"""XLA compiler options for the jitted programs of the mesh networks (training steps, encoders)."""

from __future__ import annotations

import jax


def compiler_options() -> dict:
    """Options for ``jax.jit(..., compiler_options=...)`` of the mesh networks' programs.

    On CPU: XLA's YNNPACK fusions off (``xla_cpu_experimental_ynn_fusion_type`` empty), so that reductions and
    products over the short (..., V, 9) channel axis run in XLA's own loop emitters. Empty on other backends.
    Reads the default backend: call it when building a program, not at import.
    """
    if jax.default_backend() != "cpu":
        return {}
    return {"xla_cpu_experimental_ynn_fusion_type": ""}
