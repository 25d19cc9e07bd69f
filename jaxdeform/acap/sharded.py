"""Data-parallel ACAP over a device mesh: the frames of a batch split along one mesh axis, the Acap replicated.

    mesh = sharded.frames_mesh()                    # every device along the axis "frames"
    feats = sharded.encode(a, frames, mesh)         # (N, V, 9), sharded along N
    pos = sharded.decode(a, feats, mesh)            # (N, V, 3), sharded along N

Each device runs :meth:`Acap.encode` / :meth:`Acap.decode` on its own frames: one jitted ``jax.shard_map``
program, except a decode through the host factor. That one runs as one single-device program per device, since
host callbacks inside a multi-device program can deadlock jax's CPU runtime (reproduced on jax 0.10 with 4
forced host devices: every callback waits in the copy of its argument); each device's frames still reach the
host factor on their own. N need not be a multiple of the device count: the batch is padded with copies of its
last frame, which are dropped again.
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
from jaxdeform.acap.reconstruct import HostCholesky

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


def map_frames(fn, x, mesh: Mesh, axis: str = FRAMES, *, replicated=None):
    """Apply a function to the frames (leading axis) of an array, split over a mesh axis.

    The split runs as one jitted program (``jax.jit`` of ``jax.shard_map``), cached per ``fn``, mesh and axis:
    no retrace when ``fn`` is the same object and the inputs keep their shapes. ``fn`` must not hold host
    callbacks (see the module's note; :func:`map_devices` runs those).

    **Arguments:**

    - `fn`: maps `(n, ...)` to a pytree of `(n, ...)` arrays; with `replicated`, `fn(replicated, x)`.
    - `x`: frames `(N, ...)`; N need not be a multiple of the device count.
    - `mesh`: the device mesh.
    - `axis`: the mesh axis to split along.
    - `replicated`: a pytree every device receives whole (e.g. the :class:`Acap`); None: `fn` takes `x` only.

    **Returns:**

    `fn`'s pytree with leading size N, sharded along its leading axis.
    """
    n, xs = _split(x, mesh, axis)
    program = _program(fn, mesh, axis, replicated is not None)
    out = program(replicated, xs) if replicated is not None else program(xs)
    return _trim(out, n)


def map_devices(fn, x, mesh: Mesh, axis: str = FRAMES):
    """Apply a function to the frames (leading axis) of an array, one single-device call per device of the split.

    For functions that call the host (the host factor's solve): each device's block goes through ``fn`` as its
    own program on that device, all dispatched before any is awaited. Works on a global array of several
    processes (each process maps its own blocks).

    **Arguments:**

    - `fn`: maps `(n, ...)` to an `(n, ...)` array, on the device of its input.
    - `x`: frames `(N, ...)`; N need not be a multiple of the device count.
    - `mesh`: the device mesh.
    - `axis`: the mesh axis to split along.

    **Returns:**

    `fn`'s array with leading size N, sharded along its leading axis.
    """
    n, xs = _split(x, mesh, axis)
    outs = [fn(shard.data) for shard in xs.addressable_shards]
    shape = (xs.shape[0], *outs[0].shape[1:])
    out = jax.make_array_from_single_device_arrays(shape, NamedSharding(mesh, P(axis)), outs)
    return _trim(out, n)


def _split(x, mesh: Mesh, axis: str):
    """(N, padded x sharded along ``axis``): x padded to a multiple of the axis' size with its last frame."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:  # a global array: already split, not padded
        return x.shape[0], x
    n = x.shape[0]
    k = mesh.shape[axis]
    size = -(-n // k) * k
    return n, jax.device_put(_pad(jnp.asarray(x), size), NamedSharding(mesh, P(axis)))


def _trim(out, n: int):
    """The first ``n`` frames of every leaf (no copy when nothing was padded)."""
    return jax.tree_util.tree_map(lambda y: y if y.shape[0] == n else y[:n], out)


@functools.lru_cache(maxsize=64)
def _program(fn, mesh: Mesh, axis: str, with_replicated: bool):
    """``jax.jit(jax.shard_map(fn))`` over ``mesh``'s ``axis``; ``with_replicated``: fn's first argument is
    replicated on every device."""
    spec = P(axis)
    in_specs = (P(), spec) if with_replicated else spec
    return jax.jit(jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=spec, check_vma=False))


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
    return map_frames(_encode_fn(consistency), x, mesh, axis, replicated=acap)


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
    rec = acap.reconstructor(anchors)  # a new anchor set's factor is built on the host now, once, and kept
    key = None if anchors is None else tuple(np.atleast_1d(np.asarray(anchors)).tolist())
    body = _decode_fn(key, int(refine))
    if isinstance(rec.method, HostCholesky):
        return map_devices(functools.partial(body, acap), f, mesh, axis)
    return map_frames(body, f, mesh, axis, replicated=acap)


@functools.lru_cache(maxsize=16)
def _encode_fn(consistency):
    """The per-device body of :func:`encode` (one object per option, so the jitted program is reused)."""

    def body(acap: Acap, x):
        return acap.encode(x, consistency)

    return body


@functools.lru_cache(maxsize=64)
def _decode_fn(anchors: tuple | None, refine: int):
    """The per-device body of :func:`decode` (one object per option, so the jitted program is reused)."""

    def body(acap: Acap, f):
        return acap.decode(f, anchors=None if anchors is None else list(anchors), refine=refine)

    return body
