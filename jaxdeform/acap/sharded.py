"""Data-parallel ACAP over a device mesh: the frames of a batch split along one mesh axis, the Acap replicated.

    mesh = sharded.frames_mesh()                    # every device along the axis "frames"
    feats = sharded.encode(a, frames, mesh)         # (N, V, 9), sharded along N
    pos = sharded.decode(a, feats, mesh)            # (N, V, 3), sharded along N

Each device runs :meth:`Acap.encode` / :meth:`Acap.decode_info` on its own frames inside ``jax.shard_map`` (the
host solver's callback included: each device's frames reach the host factor on their own). N need not be a
multiple of the device count: the batch is padded with copies of its last frame, which are dropped again.
Results equal the single-device call's to float round-off. Temporal consistency runs along the whole
sequence and is not split over frames: shard several sequences with ``jax.vmap`` inside your own
``shard_map`` instead.

Multi-host: call ``jax.distributed.initialize()`` in every process first (CPU devices also need
``jax.config.update("jax_cpu_collectives_implementation", "gloo")`` before it); ``frames_mesh()`` then spans all
processes' devices, and each process passes a globally shaped array made from its own frames with
``jax.make_array_from_process_local_data`` (runnable: ``examples/multihost_acap.py``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, ArrayLike, Float

from jaxdeform.acap.features import Acap

FRAMES = "frames"


def frames_mesh(devices=None, axis: str = FRAMES) -> Mesh:
    """A one-axis device mesh for the frames.

    **Arguments:**

    - `devices`: the devices; None: every device of every process.
    - `axis`: the axis name.

    **Returns:**

    A :class:`jax.sharding.Mesh` with the one axis `axis`.
    """
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), (axis,))


def _pad(x, size: int):
    """x (N, ...) padded to (size, ...) with copies of its last entry."""
    n = x.shape[0]
    if n == size:
        return x
    return jnp.concatenate([x, jnp.broadcast_to(x[-1:], (size - n, *x.shape[1:]))], axis=0)


def map_frames(fn, x, mesh: Mesh, axis: str = FRAMES):
    """Apply a function to the frames (leading axis) of an array, split over a mesh axis.

    **Arguments:**

    - `fn`: maps `(n, ...)` to a pytree of `(n, ...)` arrays.
    - `x`: frames `(N, ...)`; N need not be a multiple of the device count.
    - `mesh`: the device mesh.
    - `axis`: the mesh axis to split along.

    **Returns:**

    `fn`'s pytree with leading size N, sharded along its leading axis.
    """
    n = x.shape[0]
    k = mesh.shape[axis]
    size = -(-n // k) * k
    spec = P(axis)
    mapped = jax.shard_map(fn, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)
    xs = jax.device_put(_pad(jnp.asarray(x), size), NamedSharding(mesh, spec))
    out = mapped(xs)
    return out if size == n else jax.tree_util.tree_map(lambda y: y[:n], out)


def encode(
    acap: Acap, vertices: Float[ArrayLike, "n v 3"], mesh: Mesh, consistency: str = "spatial", axis: str = FRAMES
) -> Float[Array, "n v 9"]:
    """:meth:`Acap.encode` of frames, data-parallel over a device mesh.

    **Arguments:**

    - `acap`: the prepared :class:`Acap`.
    - `vertices`: frames `(N, V, 3)`.
    - `mesh`: the device mesh.
    - `consistency`: "spatial" or None/"none" ("temporal" cannot be split over frames).
    - `axis`: the mesh axis to split along.

    **Returns:**

    Features `(N, V, 9)`, sharded along N; equal to the single-device call's to float round-off.

    **Raises:**

    `ValueError` for "temporal" or vertices not `(N, V, 3)`; the checks of :meth:`Acap.encode`.
    """
    if consistency == "temporal":
        raise ValueError("temporal consistency runs along the whole sequence and cannot be split over frames.")
    x = acap._vertices(vertices)
    if x.ndim != 3:
        raise ValueError(f"vertices must be frames (N, V, 3), got {x.shape}.")
    return map_frames(functools.partial(_encode, acap, consistency), x, mesh, axis)


def decode(
    acap: Acap, features: Float[ArrayLike, "n v 9"], mesh: Mesh, *, anchors=None, refine: int = 1, axis: str = FRAMES
) -> Float[Array, "n v 3"]:
    """:meth:`Acap.decode` of features, data-parallel over a device mesh (anchors at their reference).

    **Arguments:**

    - `acap`: the prepared :class:`Acap`.
    - `features`: features `(N, V, 9)`.
    - `mesh`: the device mesh.
    - `anchors`: vertex indices; None: the prepared default.
    - `refine`: number of defect-correction steps.
    - `axis`: the mesh axis to split along.

    **Returns:**

    Positions `(N, V, 3)`, sharded along N; equal to the single-device call's to float round-off.

    **Raises:**

    `ValueError` for features not `(N, V, 9)`; the checks of :meth:`Acap.decode`.
    """
    f = acap._features(features)
    if f.ndim != 3:
        raise ValueError(f"features must be (N, V, 9), got {f.shape}.")
    acap.reconstructor(anchors)  # a new anchor set's factor is built on the host now, once, and kept by the Acap
    return map_frames(functools.partial(_decode, acap, anchors, refine), f, mesh, axis)


def _encode(acap: Acap, consistency: str, x):
    return acap.encode(x, consistency)


def _decode(acap: Acap, anchors, refine: int, f):
    return acap.decode(f, anchors=anchors, refine=refine)
