"""Moving per-step training scalars to the host.

The training loops keep each step's loss on the device (no synchronization per step) and read them back in
batches. ``np.asarray(jnp.stack(losses))`` would do that through one XLA concatenation with one operand per
step, compiled anew for every list length, a cost that grows with the list and is paid again at every checkpoint.
``jax.device_get`` of the list copies the buffers as they are and compiles nothing.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np


def host_scalars(values: Sequence[jax.Array], dtype=np.float32) -> np.ndarray:
    """Device scalars as one host array, with no XLA computation.

    **Arguments:**

    - `values`: device scalars.
    - `dtype`: the result's dtype.

    **Returns:**

    A numpy array `(len(values),)` of `dtype`.
    """
    if len(values) == 0:
        return np.zeros(0, dtype)
    return np.asarray(jax.device_get(list(values)), dtype=dtype).reshape(len(values))


def recent_mean(values: Sequence[jax.Array], n: int) -> float:
    """Mean of the last device scalars (for progress bars).

    **Arguments:**

    - `values`: device scalars.
    - `n`: how many of the last to average.

    **Returns:**

    A Python float; NaN for no values.
    """
    return float(host_scalars(values[-n:], np.float64).mean()) if len(values) else float("nan")
