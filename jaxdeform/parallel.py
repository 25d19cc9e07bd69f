"""Data-parallel training over a device mesh: the batch split along one mesh axis, everything else replicated.

    mesh = parallel.batch_mesh()                         # every device along the axis "batch"
    params, hist = components.train.train(..., mesh=mesh)

The training steps built with a ``mesh`` are ``jax.jit`` programs whose parameters, optimizer state and keys are
replicated (``PartitionSpec()``) and whose batch is constrained to ``PartitionSpec(axis)``; GSPMD partitions
the forward and backward passes along the batch and inserts the all-reduce of the gradients. The loss is the
one of the whole global batch (its means run over every device's shapes), so a step gives the single-device
step's numbers to float round-off. The batch must split evenly: its size must be a multiple of the mesh axis's
size (:func:`check_divisible` raises ValueError otherwise).
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

BATCH = "batch"


def batch_mesh(devices=None, axis: str = BATCH) -> Mesh:
    """A one-axis device mesh.

    **Arguments:**

    - ``devices``: the devices (default None: every device of every process).
    - ``axis``: the axis name (default ``"batch"``).

    **Returns:**

    A ``Mesh`` with the single axis ``axis`` over ``devices``.
    """
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), (axis,))


def replicated(mesh: Mesh) -> NamedSharding:
    """The sharding that holds a whole copy on every device of ``mesh``.

    **Arguments:**

    - ``mesh``: the device mesh.

    **Returns:**

    A ``NamedSharding`` with an empty partition spec.
    """
    return NamedSharding(mesh, P())


def batch_sharding(mesh: Mesh, axis: str = BATCH) -> NamedSharding:
    """The sharding that splits the leading (batch) axis over ``mesh``'s ``axis``.

    **Arguments:**

    - ``mesh``: the device mesh.
    - ``axis``: the mesh axis to split over.

    **Returns:**

    A ``NamedSharding``.
    """
    return NamedSharding(mesh, P(axis))


def axis_size(mesh: Mesh, axis: str = BATCH) -> int:
    """The number of devices along ``axis`` of ``mesh``.

    **Arguments:**

    - ``mesh``: the device mesh.
    - ``axis``: the axis name.

    **Returns:**

    The axis size as an int.

    **Raises:**

    ``KeyError``, naming the mesh's axes, if ``mesh`` has no axis ``axis``.
    """
    if axis not in mesh.shape:
        raise KeyError(f"mesh has no axis {axis!r}; its axes are {tuple(mesh.shape)}.")
    return int(mesh.shape[axis])


def check_divisible(batch: int, mesh: Mesh, axis: str = BATCH, what: str = "batch") -> None:
    """Check that ``batch`` (the global batch of one step) splits evenly over ``mesh``'s ``axis``.

    **Arguments:**

    - ``batch``: the global batch size.
    - ``mesh``: the device mesh.
    - ``axis``: the axis name.
    - ``what``: how the error message names the batch.

    **Returns:**

    Nothing.

    **Raises:**

    ``ValueError`` unless ``batch`` is a multiple of the axis size; ``KeyError`` if ``mesh`` has no axis ``axis``.
    """
    k = axis_size(mesh, axis)
    if batch % k:
        raise ValueError(
            f"the {what} of {batch} does not split evenly over the {k} devices of mesh axis "
            f"{axis!r}: choose a {what} that is a multiple of {k}, or a mesh whose axis size divides it."
        )


def replicate(tree, mesh: Mesh):
    """``tree``'s arrays placed whole on every device of ``mesh``.

    **Arguments:**

    - ``tree``: a pytree of arrays.
    - ``mesh``: the device mesh.

    **Returns:**

    New arrays, replicated; the inputs stay valid.
    """
    return jax.device_put(tree, replicated(mesh))


def constrain_batch(x, mesh: Mesh | None, axis: str = BATCH):
    """Inside a jitted function: ``x`` split along ``axis``.

    **Arguments:**

    - ``x``: a pytree of arrays with a leading batch axis.
    - ``mesh``: the device mesh, or None.
    - ``axis``: the axis to split the batch over.

    **Returns:**

    ``x`` with a sharding constraint on its leading axis; ``x`` unchanged when ``mesh`` is None.
    """
    if mesh is None:
        return x
    return jax.lax.with_sharding_constraint(x, batch_sharding(mesh, axis))
