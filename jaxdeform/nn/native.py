"""The mesh convolution, and the two halves of seed 000's autoencoder block, as native XLA FFI custom calls on
CPU (``mesh_conv_kernel.cc``).

Why: on CPU, XLA fuses the producer of a gather's operand into the gather. In a mesh network that operand
is an elementwise chain (tanh, its derivative) or another one-ring sum, so the chain is recomputed once per
ring slot, and in the backward pass the forward sums are recomputed once per backward slot. XLA also runs
the 9x9 channel mixes as batched products with N = 9, well below memory speed. On the horse training split
(8431 vertices, 10 blocks x 5 shapes) the pure-JAX training step took about 300 ms, most of it in those two
places; optimization barriers are removed before fusion on CPU and do not help. A custom call is opaque to
fusion, and the kernel reads each 9-channel row once per use.

The kernels are compiled on first use with the system C++ compiler against jaxlib's own FFI headers
(``jax.ffi.include_dir()``) and cached under ``$XDG_CACHE_HOME/jaxdeform`` (default ``~/.cache/jaxdeform``),
keyed by a hash of the source, the jaxlib version, the CPU and ``JAXDEFORM_NATIVE_CFLAGS`` (extra compiler
flags, appended after ``-O3 -march=native``: ``-mno-avx512f`` builds the 8-lane AVX2 code on an AVX-512 CPU,
which the tests use to check both). Where no compiler is found, the build fails,
the default backend is not the CPU, or ``JAXDEFORM_NATIVE=0`` is set, :func:`available` is False and
:mod:`jaxdeform.nn.graph_conv` uses its pure-JAX definition (same results, slower on CPU).

Threads: a call cuts its vertices (or planes) into at most 16 chunks, a cut fixed by the sizes alone, and keeps
one partial sum per chunk, added in chunk order, so results do not depend on the thread count. The calling thread
and helpers on XLA's own intra-op thread pool (handed to the call through the FFI context) claim chunks one at a
time: as many threads in all as the pool has, and at most ``JAXDEFORM_NATIVE_THREADS`` (default: the hardware's,
at most 16). A kernel's exception (memory) comes back as an error of the call. Before, each call split its range
in equal parts over threads of its own: where XLA ran another operation of the step at the same time, or its
pool's idle workers held the cores, a part waited for a core. On the horse training step (2-core VM, 10-step
blocks, the two code trees alternated) that took 68-71 ms per step against 59-60 ms this way.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shlex
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp

_SOURCE = Path(__file__).with_name("mesh_conv_kernel.cc")
FORWARD = "jaxdeform_mesh_conv_fwd"
BACKWARD = "jaxdeform_mesh_conv_bwd"
#: the fused halves of seed 000's autoencoder block: (FFI target, symbol in the library)
_AE_TARGETS = {
    "encoder_fwd": ("jaxdeform_ae_encoder_fwd", "JaxdeformAeEncoderFwd"),
    "encoder_bwd": ("jaxdeform_ae_encoder_bwd", "JaxdeformAeEncoderBwd"),
    "decoder_fwd": ("jaxdeform_ae_decoder_fwd", "JaxdeformAeDecoderFwd"),
    "decoder_fwd_err": ("jaxdeform_ae_decoder_fwd_err", "JaxdeformAeDecoderFwdErr"),
    "decoder_bwd": ("jaxdeform_ae_decoder_bwd", "JaxdeformAeDecoderBwd"),
    "adam": ("jaxdeform_adam", "JaxdeformAdam"),
    "encoder_fwd_masked": ("jaxdeform_ae_encoder_fwd_masked", "JaxdeformAeEncoderFwdMasked"),
    "encoder_bwd_masked": ("jaxdeform_ae_encoder_bwd_masked", "JaxdeformAeEncoderBwdMasked"),
    "decoder_fwd_err_masked": ("jaxdeform_ae_decoder_fwd_err_masked", "JaxdeformAeDecoderFwdErrMasked"),
}
MAX_CHANNELS = 16  # kLanes in the kernel source
_lock = threading.Lock()
_state: dict = {}


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "jaxdeform"


def _cpu_tag() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def build() -> Path:
    """Compile the kernels (once per source, jaxlib, CPU and extra flags; cached) and return the shared library's
    path."""
    import jaxlib

    extra = shlex.split(os.environ.get("JAXDEFORM_NATIVE_CFLAGS", ""))
    key = _SOURCE.read_bytes() + jaxlib.__version__.encode() + _cpu_tag().encode() + " ".join(extra).encode()
    tag = hashlib.sha256(key).hexdigest()[:16]
    out = _cache_dir() / f"mesh_conv-{tag}.so"
    if out.is_file():
        return out
    cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")
    if cxx is None:
        raise RuntimeError("no C++ compiler found (g++, c++ or clang++)")
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    cmd = [cxx, "-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-pthread",
           *extra, f"-I{jax.ffi.include_dir()}", str(_SOURCE), "-o", tmp]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"compiling {_SOURCE.name} failed: {proc.stderr.strip()[-400:]}")
        os.replace(tmp, out)  # atomic: concurrent builders each write their own temporary
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def available() -> bool:
    """Whether the native kernels serve the default backend (builds and registers them on the first call)."""
    if jax.default_backend() != "cpu" or os.environ.get("JAXDEFORM_NATIVE", "1") == "0":
        return False
    with _lock:
        if "ok" not in _state:
            try:
                lib = ctypes.cdll.LoadLibrary(str(build()))
                jax.ffi.register_ffi_target(FORWARD, jax.ffi.pycapsule(lib.JaxdeformMeshConvFwd), platform="cpu")
                jax.ffi.register_ffi_target(BACKWARD, jax.ffi.pycapsule(lib.JaxdeformMeshConvBwd), platform="cpu")
                for target, symbol in _AE_TARGETS.values():
                    jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, symbol)), platform="cpu")
                _state["lib"] = lib  # keeps the library loaded
                _state["ok"] = True
            except Exception as exc:  # noqa: BLE001 (any build or load failure falls back to pure JAX)
                warnings.warn(f"jaxdeform: native mesh convolution unavailable ({exc}); using the pure-JAX "
                              "definition (slower on CPU).", RuntimeWarning, stacklevel=2)
                _state["ok"] = False
        return _state["ok"]


#: glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -3, -4, -8

#: XLA temporary buffer of one program (bytes) above which :func:`fit_host_allocator` hands large blocks back
#: to ``mmap``: far above the seed-000 default step on horse (117 MB), below the three-level step on all 48
#: horse shapes (5.0 GB).
LARGE_PROGRAM_BYTES = 1 << 30


def tune_host_allocator() -> bool:
    """Keep freed host memory in the process for reuse (glibc only; for long CPU runs: training, experiments).

    XLA on CPU allocates every step's large buffers afresh. glibc serves allocations above 32 MB, and those
    of its per-thread arenas, by ``mmap`` and unmaps them on free, so the next step touches new pages: about
    22,000 page faults and 70 ms of kernel time per seed-000 training step on horse-gallop, on a 2-core VM.
    With one arena, no ``mmap`` and no trimming, the same step faults about once and runs 5-15 % faster
    (alternated runs). The memory then stays with the process until it exits.

    Takes full effect when called before JAX starts its CPU client (the first computation); later it only
    affects threads that have not allocated yet. The command-line entry points call it first thing.
    ``JAXDEFORM_HOST_ALLOCATOR=0`` turns it off. Returns whether the settings were applied.
    """
    if os.environ.get("JAXDEFORM_HOST_ALLOCATOR", "1") == "0" or platform.libc_ver()[0] != "glibc":
        return False
    settings = ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2**31 - 1))
    applied = _mallopt(settings)
    _state["allocator"] = "tuned" if applied else _state.get("allocator")
    return applied


def _mallopt(settings) -> bool:
    try:
        libc = ctypes.CDLL(None)
        return all(libc.mallopt(param, value) == 1 for param, value in settings)
    except (OSError, AttributeError):
        return False


def fit_host_allocator(temp_bytes: int | None) -> bool:
    """After :func:`tune_host_allocator`, before running a program whose XLA temporary buffers take
    ``temp_bytes`` (``compiled.memory_analysis().temp_size_in_bytes``): above :data:`LARGE_PROGRAM_BYTES`,
    blocks above 32 MiB go to ``mmap`` again (freed blocks return to the system) for the rest of the process.

    Why: with one arena and no ``mmap``, the heap of a program with gigabytes of temporaries grows far beyond
    them. The three-level seed-000 step on all 48 horse shapes (5.0 GB of temporaries) peaked at 17.3 GB resident within
    60 steps and was killed by the OOM killer at 24.4 GB after ~800; with large blocks on ``mmap`` it stays at
    7.6 GB (glibc's defaults: 7.5 GB), and its steps take 4.1-4.8 s against 4.0-4.3 s (2-core VM). Such steps
    fault on their large buffers either way (1.3-1.6 M page faults per step). Smaller programs keep the tuned
    heap, as does a program whose size is unknown (``temp_bytes`` None). Returns whether the setting changed now.
    """
    if _state.get("allocator") != "tuned" or temp_bytes is None or temp_bytes <= LARGE_PROGRAM_BYTES:
        return False
    if _mallopt(((_M_MMAP_MAX, 65536), (_M_MMAP_THRESHOLD, 32 << 20))):
        _state["allocator"] = "large blocks by mmap"
        return True
    return False


def host_allocator() -> str | None:
    """The process's host allocator setting: None (glibc's defaults or not glibc), "tuned" or "large blocks by
    mmap" (see :func:`tune_host_allocator` and :func:`fit_host_allocator`)."""
    return _state.get("allocator")


def compiler_options() -> dict:
    """XLA options for the jitted programs of the mesh networks (training steps, encoders).

    On CPU, XLA hands reductions and small-matrix products to YNNPACK "fusions"; in the seed-000 training step
    these ran reductions over the short (..., V, 9) channel axis at a fraction of memory speed (60 ms of a
    200 ms step for one sum over the attention children). With them off, XLA's own loop emitters run the
    same reductions in 2-5 ms. Empty on other backends.
    """
    if jax.default_backend() != "cpu":
        return {}
    return {"xla_cpu_experimental_ynn_fusion_type": ""}


def _require() -> None:
    if not available():
        raise RuntimeError("the native mesh convolution is not available here (see jaxdeform.nn.native).")


def conv_forward(x, neighbors, counts, inv_deg, w_point, w_neighbor, b):
    """y = x W_point + ring_mean(x) W_neighbor + b for x (..., V, Ci); no activation, no autodiff rule."""
    _require()
    shape = x.shape[:-1] + (w_point.shape[-1],)
    call = jax.ffi.ffi_call(FORWARD, jax.ShapeDtypeStruct(shape, x.dtype), vmap_method="broadcast_all")
    return call(x, neighbors, counts, inv_deg, w_point, w_neighbor, b)


def conv_backward(x, gy, neighbors, counts, inv_deg, w_point, w_neighbor):
    """(gx, gW_point, gW_neighbor, gb) of :func:`conv_forward` for the cotangent ``gy``."""
    _require()
    dt = x.dtype
    out = (jax.ShapeDtypeStruct(x.shape, dt), jax.ShapeDtypeStruct(w_point.shape, dt),
           jax.ShapeDtypeStruct(w_neighbor.shape, dt), jax.ShapeDtypeStruct(w_point.shape[:-2] + w_point.shape[-1:], dt))
    call = jax.ffi.ffi_call(BACKWARD, out, vmap_method="broadcast_all")
    return call(x, gy, neighbors, counts, inv_deg, w_point, w_neighbor)


def _like(*arrays):
    return tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in arrays)


# The fused block halves take vmap's batch dimension as a leading group axis of every argument; an argument
# without it (a shared table or weight, the primals of a vmapped adjoint) comes in with a leading 1
# ("expand_dims") and the kernel broadcasts it, so nothing is copied per group.


def ae_encoder_forward(x, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(z, h): h = tanh(conv(x)) and z = flatten(h) C^T for x (..., P, V, 9), C (..., Kz, 9V); z (..., P, Kz).

    No autodiff rule; h is what the adjoint needs."""
    _require()
    out = (jax.ShapeDtypeStruct(x.shape[:-2] + (c.shape[-2],), x.dtype), jax.ShapeDtypeStruct(x.shape, x.dtype))
    call = jax.ffi.ffi_call(_AE_TARGETS["encoder_fwd"][0], out, vmap_method="expand_dims")
    return call(x, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def _block_adjoint(which, primal, saved, cotangent, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(d primal, gW_point, gW_neighbor, gb, dC) of one block half, from its primal input, the outputs of its
    forward call (a tuple) and the cotangent of its output."""
    _require()
    call = jax.ffi.ffi_call(_AE_TARGETS[which][0], _like(primal, w_point, w_neighbor, b, c), vmap_method="expand_dims")
    return call(primal, *saved, cotangent, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def ae_encoder_backward(x, h, dz, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(dx, gW_point, gW_neighbor, gb, dC) of :func:`ae_encoder_forward`'s z for the cotangent ``dz``."""
    return _block_adjoint("encoder_bwd", x, (h,), dz, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def ae_decoder_forward(z, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(x_hat, S): S = tanh(reshape(z C)) and x_hat = tanh(conv(S)) for z (..., P, Kz), C (..., Kz, 9V); both
    (..., P, V, 9). No autodiff rule; S is what the adjoint needs."""
    _require()
    out = (jax.ShapeDtypeStruct(z.shape[:-1] + (c.shape[-1] // 9, 9), z.dtype),) * 2
    call = jax.ffi.ffi_call(_AE_TARGETS["decoder_fwd"][0], out, vmap_method="expand_dims")
    return call(z, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def ae_decoder_forward_error(z, target, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(x_hat, S, err): :func:`ae_decoder_forward` and err = sum over (V, 9) of (x_hat - target)^2 per plane,
    (..., P), for ``target`` shaped like x_hat. No autodiff rule."""
    _require()
    planes = z.shape[:-1]
    out = (jax.ShapeDtypeStruct(planes + (c.shape[-1] // 9, 9), z.dtype),) * 2 + (jax.ShapeDtypeStruct(planes, z.dtype),)
    call = jax.ffi.ffi_call(_AE_TARGETS["decoder_fwd_err"][0], out, vmap_method="expand_dims")
    return call(z, neighbors, counts, inv_deg, w_point, w_neighbor, b, c, target)


def ae_decoder_backward(z, x_hat, hidden, dx_hat, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(dz, gW_point, gW_neighbor, gb, dC) of :func:`ae_decoder_forward`, given its outputs ``x_hat`` and S.

    The cotangent through the final tanh, dx_hat (1 - x_hat^2), is formed here, in XLA, which fuses it into the
    operation that makes dx_hat (the loss's adjoint in training); the kernel takes it in place of dx_hat."""
    shape = jnp.broadcast_shapes(x_hat.shape, dx_hat.shape)
    flat = shape[:-2] + (-1,)  # elementwise over rows of 9V: see graph_conv._tanh
    d, t = jnp.broadcast_to(dx_hat, shape).reshape(flat), jnp.broadcast_to(x_hat, shape).reshape(flat)
    dpre = (d - d * t * t).reshape(shape)
    return decoder_adjoint(z, hidden, dpre, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


# Masked inputs: blocks g (the leading dimensions of ``am`` (..., V) and of their parameters) read am[g, i] x[i],
# x (..., P, V, 9) broadcast against them (a leading 1 per block dimension), never a materialized array of them:
# seed 000's children, diag(AM_k) X_res. Under jax.vmap these calls run once per element ("sequential"): the
# adjoint's x cotangent sums over the blocks reading each x, which the broadcasting of a vmapped call would not
# line up with.


def ae_encoder_forward_masked(x, am, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(z, h) of :func:`ae_encoder_forward` for the masked inputs am[g] x; z (blocks..., P, Kz), h (blocks...,
    P, V, 9)."""
    _require()
    planes = am.shape[:-1] + x.shape[-3:-2]
    out = (jax.ShapeDtypeStruct(planes + (c.shape[-2],), x.dtype),
           jax.ShapeDtypeStruct(planes + x.shape[-2:], x.dtype))
    call = jax.ffi.ffi_call(_AE_TARGETS["encoder_fwd_masked"][0], out, vmap_method="sequential")
    return call(x, am, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def ae_encoder_backward_masked(x, am, h, dz, x_hat, derr, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(dx, gW_point, gW_neighbor, gb, dC) of :func:`ae_encoder_forward_masked` where each block's decoder had
    its masked input as target too (err[g, p] = ||x_hat[g, p] - am[g] x_p||^2, cotangent ``derr``): dx is
    shaped like x, the sum over the blocks reading it of am[g] (their input cotangent - 2 derr (x_hat - am[g] x))."""
    _require()
    call = jax.ffi.ffi_call(_AE_TARGETS["encoder_bwd_masked"][0], _like(x, w_point, w_neighbor, b, c),
                            vmap_method="sequential")
    return call(x, am, h, dz, x_hat, derr, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def ae_decoder_forward_error_masked(z, x, am, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """(x_hat, S, err) of :func:`ae_decoder_forward_error` with the masked inputs am[g] x as targets."""
    _require()
    planes = z.shape[:-1]
    out = (jax.ShapeDtypeStruct(planes + (c.shape[-1] // 9, 9), z.dtype),) * 2 + (jax.ShapeDtypeStruct(planes, z.dtype),)
    call = jax.ffi.ffi_call(_AE_TARGETS["decoder_fwd_err_masked"][0], out, vmap_method="sequential")
    return call(z, neighbors, counts, inv_deg, w_point, w_neighbor, b, c, x, am)


def decoder_adjoint(z, hidden, dpre, neighbors, counts, inv_deg, w_point, w_neighbor, b, c):
    """:func:`ae_decoder_backward` given the pre-activation cotangent dpre = dx_hat (1 - x_hat^2) itself."""
    return _block_adjoint("decoder_bwd", z, (hidden,), dpre, neighbors, counts, inv_deg, w_point, w_neighbor, b, c)


def adam_update(p, mu, nu, parts, scalars, coef=None):
    """(p', mu', nu'): one Adam step in one pass, in place (the results alias ``p``, ``mu``, ``nu``; donate them
    in a jitted caller). The gradient is ``sum(parts) + coef[row] * p`` with rows of ``p.size // coef.size``
    entries (``coef`` None: no such term); ``scalars`` = (b1, b2, bias corrections 1 - b1^t and 1 - b2^t, eps,
    step = -learning rate), in p's dtype. The arithmetic of optax.adam (no eps_root) and apply_updates."""
    _require()
    coef = jnp.zeros((0,), p.dtype) if coef is None else coef
    call = jax.ffi.ffi_call(_AE_TARGETS["adam"][0], _like(p, mu, nu), input_output_aliases={0: 0, 1: 1, 2: 2})
    return call(p, mu, nu, jnp.asarray(scalars, p.dtype), coef, *parts)


def ring_tables(neighbors, degree, dtype):
    """(neighbors int32, counts int32, 1 / max(degree, 1)) as the kernels take them."""
    inv = 1.0 / jnp.maximum(degree, 1).astype(dtype)
    return jnp.asarray(neighbors, jnp.int32), jnp.asarray(degree, jnp.int32), inv
