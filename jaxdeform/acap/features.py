"""ACAP features: encode meshes to 9-d per-vertex features, decode features to meshes, and the Scaler.

Feature layout per vertex (official order): (logR_01, logR_02, logR_12, S_00, S_01, S_02, S_11, S_12, S_22)
where logR is the skew matrix of the consistent axis-angle vector v: logR_01 = -v_z, logR_02 = v_y,
logR_12 = -v_x.

:class:`Acap` (built by :func:`prepare`) is a pytree holding everything computed once per (reference,
connectivity, weighting, solver): topology, the reference constants of the local fits, the consistency graph
and the reconstruction with its factor. Its methods are pure and trace under jit, vmap, grad and jvp. The
module-level :func:`encode`/:func:`decode` are host conveniences that keep a small cache of Acaps, keyed by
the bytes of the reference and faces, so repeated calls do not refactor or recompile.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections import OrderedDict

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxdeform.acap import consistency as cons
from jaxdeform.acap.gradients import (
    RestFrame,
    Weighting,
    _rest_constants,
    deformation_gradients_cm,
    rest_frame,
    to_vertex_major,
)
from jaxdeform.acap.reconstruct import (
    CG_MAX_STEPS,
    DENSE_MAX_VERTICES,
    SOLVERS,
    ConjugateGradient,
    Reconstructor,
    SolveInfo,
    all_finite,
    is_traced,
)
from jaxdeform.acap.rotations import exp_rotation_cm, from_cm, log_rotation_cm, mm_cm, polar_cm, skew, to_cm
from jaxdeform.errors import ConnectivityError, DegenerateMeshError
from jaxdeform.mesh.topology import Topology, build_topology
from jaxdeform.typing import Int

DEFAULT_REFINE = 1
_S_IDX = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def features_from(
    v: Float[jax.typing.ArrayLike, "*batch 3"], s: Float[jax.typing.ArrayLike, "*batch 3 3"]
) -> Float[Array, "*batch 9"]:
    """9-d ACAP features from axis-angle vectors and symmetric stretch matrices.

    **Arguments:**

    - `v`: axis-angle vectors, shape `(..., 3)`.
    - `s`: symmetric stretch matrices S, shape `(..., 3, 3)`; only the upper triangle is read.

    **Returns:**

    Features of shape `(..., 9)` in the official order (module docstring), dtype following the inputs.
    """
    rot = jnp.stack([-v[..., 2], v[..., 1], -v[..., 0]], axis=-1)
    return jnp.concatenate([rot, s[..., _S_IDX[0], _S_IDX[1]]], axis=-1)


def split_features_cm(f: Float[Array, "9 ..."]) -> tuple[Array, Array]:
    """Split features in the component-major layout.

    **Arguments:**

    - `f`: features, shape `(9, ...)` (component axis first).

    **Returns:**

    `(v, s)`: axis-angle vectors `(3, ...)` and symmetric S `(3, 3, ...)`, both component-major.
    """
    v = jnp.stack([-f[2], f[1], -f[0]])
    s00, s01, s02, s11, s12, s22 = (f[k] for k in range(3, 9))
    return v, jnp.stack([jnp.stack([s00, s01, s02]), jnp.stack([s01, s11, s12]), jnp.stack([s02, s12, s22])])


def split_features(
    f: Float[jax.typing.ArrayLike, "*batch 9"],
) -> tuple[Float[Array, "*batch 3"], Float[Array, "*batch 3 3"]]:
    """Inverse of :func:`features_from`.

    **Arguments:**

    - `f`: features, shape `(..., 9)`.

    **Returns:**

    `(v, s)`: axis-angle vectors `(..., 3)` and symmetric S `(..., 3, 3)`.
    """
    v, s = split_features_cm(to_cm(f, 1))
    return from_cm(v, 1), from_cm(s)


def gradients_from_features_cm(f: Float[Array, "9 ..."]) -> Float[Array, "3 3 ..."]:
    """Deformation gradients T = exp(log R) S in the component-major layout.

    **Arguments:**

    - `f`: features, shape `(9, ...)`.

    **Returns:**

    T of shape `(3, 3, ...)`, dtype following `f`; differentiable in `f`.
    """
    v, s = split_features_cm(f)
    return mm_cm(exp_rotation_cm(v), s)


def gradients_from_features(f: Float[jax.typing.ArrayLike, "*batch 9"]) -> Float[Array, "*batch 3 3"]:
    """Deformation gradients T = exp(log R) S of features.

    **Arguments:**

    - `f`: features, shape `(..., 9)`.

    **Returns:**

    T of shape `(..., 3, 3)`, dtype following `f`; differentiable in `f`.
    """
    return from_cm(gradients_from_features_cm(to_cm(f, 1)))


# The encoder runs as a few separately jitted stages: compiled as one program, XLA on CPU picked layouts and
# fusions that made the whole several times slower than the sum of its parts.


@jax.jit
def _gradients_stage(frame: RestFrame, vertices):
    return deformation_gradients_cm(frame, to_vertex_major(vertices))


@jax.jit
def _polar_stage(t):
    r, s = polar_cm(t)
    return log_rotation_cm(r), s


@jax.jit
def _output_stage(v, s):
    """(3, V, N), (3, 3, V, N) -> (N, V, 3), (N, V, 3, 3)."""
    return jnp.moveaxis(v, (0, 1, 2), (2, 1, 0)), jnp.moveaxis(s, (0, 1, 2, 3), (2, 3, 1, 0))


def _frame_as(frame: RestFrame, dtype) -> RestFrame:
    """The reference constants of ``frame`` in ``dtype`` (the frame itself when it already is)."""
    if frame.dtype == dtype:
        return frame
    return dataclasses.replace(
        frame,
        weights=frame.weights.astype(dtype),
        c_ring=frame.c_ring.astype(dtype),
        c_normal=frame.c_normal.astype(dtype),
    )


def _local_cm(frame: RestFrame, vertices):
    """Raw axis-angle vectors (3, V, N) and S (3, 3, V, N) of frames (N, V, 3) (component-major)."""
    return _polar_stage(_gradients_stage(frame, vertices))


def _encode_parts(frame: RestFrame, rings: cons.Rings, vertices, mode: str):
    v, s = _local_cm(frame, vertices)
    if mode != "none":
        v = cons.consistent_cm(v, rings, mode)
    return _output_stage(v, s)


def _check_shape(shape: tuple, n: int) -> None:
    if len(shape) < 2 or shape[-1] != 3:
        raise ValueError(f"vertices must be (..., V, 3), got {tuple(shape)}.")
    if shape[-2] != n:
        raise ConnectivityError(f"the meshes have {shape[-2]} vertices but the reference has {n}.")


def _finite_or_raise(x: Array, error: Exception) -> Array:
    """``x`` after checking that every entry is finite: raises ``error`` when called eagerly; inside a trace
    that closes over a concrete ``x`` the check becomes ``equinox.error_if`` (its result is not concrete)."""
    ok = all_finite(x)
    if is_traced(ok):
        return eqx.error_if(x, ~ok, str(error))
    if not bool(ok):
        raise error
    return x


def _float_array(x, default) -> Array:
    """``x`` as a floating JAX array. JAX arrays and traced values keep their device and their float dtype
    (others become ``default``); anything else goes through NumPy: float32/float64 kept (float64 only where x64
    is enabled), other types ``default``."""
    if isinstance(x, jax.Array) or is_traced(x):  # a JAX array, or e.g. a list of tracers
        x = jnp.asarray(x)
        return x.astype(x.dtype if jnp.issubdtype(x.dtype, jnp.floating) else default)
    host = np.asarray(x)
    return jnp.asarray(
        host, dtype=jax.dtypes.canonicalize_dtype(host.dtype if host.dtype in (np.float32, np.float64) else default)
    )


class _HostCache:
    """Per-:class:`Acap` host cache of reconstructors for concrete anchor sets (compared by identity, so that
    an Acap stays a hashable static-free pytree)."""

    def __init__(self):
        self.items: dict = {}


class Acap(eqx.Module):
    """The ACAP machinery of one reference mesh and connectivity: a pytree, built once by :func:`prepare`.

    Every method traces under ``jax.jit``, ``jax.vmap``, ``jax.grad``, ``jax.jvp`` and ``jax.jacfwd`` (the Acap
    may be closed over or passed as an argument) and follows the dtype of its input: float32 in, float32 out;
    float64 where x64 is enabled. Called eagerly, the methods also check their input on the host and raise
    jaxdeform's errors; inside a trace the value checks are ``equinox.error_if``.
    """

    rest: Float[Array, "v 3"]
    faces: Int[Array, "f 3"]
    topo: Topology
    frame: RestFrame
    rings: cons.Rings
    rec: Reconstructor  # the default anchors'
    weighting: str = eqx.field(static=True, default="official")
    _cache: _HostCache = eqx.field(static=True, default_factory=_HostCache)

    def __hash__(self):
        # by identity, so that bound methods are hashable: ``jax.jit(acap.encode)`` works as users write it
        return id(self)

    @property
    def graph(self) -> cons.Graph:
        """The host graph of the consistency solves (edges and component roots for the exact MILP path)."""
        return cons.Graph(
            n=self.topo.n_vertices,
            edges=np.asarray(self.topo.edges, np.int64),
            roots=np.flatnonzero(np.asarray(self.rings.is_root)),
            rings=self.rings,
        )

    @property
    def solver(self) -> str:
        """The reconstruction solver: "host", "dense" or "cg"."""
        return self.rec.solver

    def _vertices(self, vertices):
        """Vertices as a float array (..., V, 3), checked (host checks when concrete, error_if when traced)."""
        x = _float_array(vertices, self.frame.dtype)
        if not is_traced(vertices):
            _check_shape(x.shape, self.topo.n_vertices)
        elif x.ndim < 2 or x.shape[-1] != 3 or x.shape[-2] != self.topo.n_vertices:
            raise ConnectivityError(f"vertices must be (..., {self.topo.n_vertices}, 3), got {x.shape}.")
        return _finite_or_raise(x, DegenerateMeshError("a vertex coordinate is NaN or infinite."))

    def local(self, vertices) -> tuple[Array, Array]:
        """The raw local fits (no consistency) of meshes.

        **Arguments:**

        - `vertices`: positions, shape `(..., V, 3)`.

        **Returns:**

        `(v, s)`: axis-angle vectors `(..., V, 3)` with angles in [0, pi] and S `(..., V, 3, 3)`.
        """
        return self.encode_parts(vertices, "none")

    def encode_parts(self, vertices, consistency: str | None = "spatial") -> tuple[Array, Array]:
        """Consistent axis-angle vectors and stretch matrices of meshes.

        **Arguments:**

        - `vertices`: positions, shape `(..., V, 3)`; `(N, V, 3)` frames in order for "temporal".
        - `consistency`: "spatial" (default), "temporal" (frames along the first axis) or None/"none".

        **Returns:**

        `(v, s)`: consistent axis-angle vectors `(..., V, 3)` and S `(..., V, 3, 3)`, in the vertices' float
        dtype. Differentiable in the vertices: the integer consistency choices are held fixed in the derivative.

        **Raises:**

        `ValueError` for an unknown `consistency`, a bad shape or non-(N, V, 3) input to "temporal";
        `ConnectivityError` when V differs from the reference; `DegenerateMeshError` for a non-finite coordinate.
        """
        if consistency not in (None, "none", "spatial", "temporal"):
            raise ValueError(f"unknown consistency '{consistency}'; expected 'spatial', 'temporal' or 'none'.")
        mode = "none" if consistency is None else consistency
        x = self._vertices(vertices)
        if mode == "temporal" and x.ndim != 3:
            raise ValueError(f"temporal consistency needs frames (N, V, 3), got {x.shape}.")
        lead, n = x.shape[:-2], self.topo.n_vertices
        v, s = _encode_parts(_frame_as(self.frame, x.dtype), self.rings, x.reshape(-1, n, 3), mode)
        return v.reshape(*lead, n, 3), s.reshape(*lead, n, 3, 3)

    def encode(self, vertices, consistency: str | None = "spatial") -> Float[Array, "... v 9"]:
        """ACAP features of meshes.

        **Arguments:**

        - `vertices`: positions, shape `(..., V, 3)`.
        - `consistency`: as in :meth:`encode_parts`.

        **Returns:**

        Features of shape `(..., V, 9)` (see :meth:`encode_parts` for dtype, derivative and raised errors).
        """
        v, s = self.encode_parts(vertices, consistency)
        return features_from(v, s)

    def reconstructor(self, anchors=None) -> Reconstructor:
        """The reconstruction for an anchor set.

        Concrete anchor sets other than the default are built once and kept (a new factor for the factored
        solvers).

        **Arguments:**

        - `anchors`: vertex indices; None: the prepared default.

        **Returns:**

        The :class:`Reconstructor` holding those anchors.
        """
        if anchors is None:
            return self.rec
        if is_traced(anchors):
            return self.rec.with_anchors(anchors)
        key = tuple(np.atleast_1d(np.asarray(anchors)).tolist())
        if not is_traced(self.rec.anchors) and key == tuple(np.asarray(self.rec.anchors).tolist()):
            return self.rec
        if key in self._cache.items:
            return self._cache.items[key]
        rec = self.rec.with_anchors(anchors)
        if not is_traced(rec):
            self._cache.items[key] = rec
        return rec

    def with_rest(self, rest: Float[jax.typing.ArrayLike, "v 3"]) -> Acap:
        """The same Acap with its reference-side constants recomputed from a new reference.

        The fit constants, edge weights and reconstruction weights are recomputed; the topology stays; a
        factored solver solves only at its own reference (see :meth:`Reconstructor.with_rest`).

        **Arguments:**

        - `rest`: the new reference positions, shape `(V, 3)`.

        **Returns:**

        A new :class:`Acap`; its :meth:`encode` and :meth:`decode` are differentiable with respect to `rest`.
        """
        rest = jnp.asarray(rest)
        frame = self.frame
        w, c_ring, c_normal = _rest_constants(rest, frame.topo, frame.plan, self.weighting)
        frame = dataclasses.replace(frame, weights=w, c_ring=c_ring, c_normal=c_normal)
        return Acap(
            rest=rest,
            faces=self.faces,
            topo=self.topo,
            frame=frame,
            rings=self.rings,
            rec=self.rec.with_rest(rest, w),
            weighting=self.weighting,
        )

    def deformation_energy(self, features, positions) -> Float[Array, ...]:
        """The ACAP reconstruction's objective without its anchor term, per shape.

        The sum over edges of w_ij |(p_i - p_j) - (T_i + T_j)/2 (q_i - q_j)|^2, with T the deformation
        gradients of the features and p the positions. :meth:`decode` with `refine=0` minimises it under its
        anchors.

        **Arguments:**

        - `features`: features, shape `(..., V, 9)`.
        - `positions`: positions p, shape `(..., V, 3)`.

        **Returns:**

        The energy per shape, shape `(...)`: zero when the positions realise the features' gradients exactly.
        Differentiable in both arguments.
        """
        rec = self.rec  # the edge terms are the same for every anchor set
        features = jnp.asarray(features)
        lead, v = features.shape[:-2], features.shape[-2]
        target = rec.edge_targets_vm(_decode_gradients(_features_cm(features)))  # (E, 3, B)
        p = jnp.moveaxis(jnp.asarray(positions, target.dtype).reshape(-1, v, 3), 0, -1)  # (V, 3, B)
        diff = rec.sqrt_w.astype(target.dtype)[:, None, None] * (p[rec.edge_i] - p[rec.edge_j]) - target
        return jnp.sum(diff**2, axis=(0, 1)).reshape(lead)

    def _features(self, features):
        f = _float_array(features, self.frame.dtype)
        if not is_traced(features):
            if f.ndim < 2 or f.shape[-1] != 9:
                raise ValueError(f"features must be (..., V, 9), got {f.shape}.")
            f = _finite_or_raise(f, ValueError("a feature is NaN or infinite."))
        if f.ndim < 2 or f.shape[-1] != 9 or f.shape[-2] != self.topo.n_vertices:
            raise ConnectivityError(f"features must be (..., {self.topo.n_vertices}, 9), got {f.shape}.")
        return f

    def decode_info(
        self, features, *, anchors=None, targets=None, refine: int = DEFAULT_REFINE, initial=None
    ) -> tuple[Float[Array, "... v 3"], SolveInfo]:
        """Positions from features, with the diagnostics of the linear solves.

        `refine=0` is the plain ACAP reconstruction (one least-squares solve). Each refinement step
        (defect correction) re-fits the gradients of the current positions with the encoder's own local
        fits and solves the same least-squares problem for the correction, so that the decoded mesh
        reproduces the given gradients more closely.

        **Arguments:**

        - `features`: features, shape `(..., V, 9)`.
        - `anchors`: vertex indices held at `targets`; None: the prepared default (the lowest vertex of each
          connected component: vertex 0 for a connected mesh).
        - `targets`: anchor positions, shape `(..., A, 3)`; None: the anchors' reference positions.
        - `refine`: number of defect-correction steps (0: plain reconstruction).
        - `initial`: a starting guess of the positions `(..., V, 3)` for conjugate gradients (default: the
          reference; e.g. the positions of the frame before); the factored solvers do not need one.

        **Returns:**

        `(positions, info)`: positions `(..., V, 3)` in the features' dtype and the :class:`SolveInfo` of the
        linear solves.

        **Raises:**

        `ValueError` for a bad feature shape or a non-finite feature; `ConnectivityError` when V differs
        from the reference.
        """
        f = self._features(features)
        return _decode(self.reconstructor(anchors), _frame_as(self.frame, f.dtype), f, targets, refine, initial)

    def decode(
        self, features, *, anchors=None, targets=None, refine: int = DEFAULT_REFINE, initial=None
    ) -> Float[Array, "... v 3"]:
        """Positions from features.

        **Arguments:**

        As :meth:`decode_info`.

        **Returns:**

        Positions `(..., V, 3)` in the features' dtype. Differentiable in the features and the targets (and
        the reference, through :meth:`with_rest`).
        """
        return self.decode_info(features, anchors=anchors, targets=targets, refine=refine, initial=initial)[0]


@jax.jit
def _features_cm(features):
    """Features (..., V, 9) -> (9, V, B) (its own stage: fused with the next, XLA on CPU runs slower)."""
    v = features.shape[-2]
    return jnp.moveaxis(features.reshape(-1, v, 9), (0, 1, 2), (2, 1, 0))


@jax.jit
def _decode_gradients(f_cm):
    """Features (9, V, B) -> T (V, 3, 3, B)."""
    return jnp.moveaxis(gradients_from_features_cm(f_cm), (0, 1), (1, 2))


@jax.jit
def _anchor_targets(rec: Reconstructor, features, targets):
    """Anchor targets (A, 3, B) for features (..., V, 9)."""
    return rec.targets_vm(targets, features.shape[:-2], features.dtype)


@jax.jit
def _edge_stage(rec: Reconstructor, t):
    """Edge targets (E, 3, B) of T (its own stage: fused with either neighbour, XLA on CPU runs slower)."""
    return rec.edge_targets_vm(t)


@jax.jit
def _solve_stage(rec: Reconstructor, target, targets, y0):
    return rec.solve(target, targets, y0)


@jax.jit
def _refit_stage(frame: RestFrame, p):
    """T(p) (V, 3, 3, B): the encoder's local fits of the current positions p (V, 3, B)."""
    return jnp.moveaxis(deformation_gradients_cm(frame, jnp.swapaxes(p, 0, 1)), (0, 1), (1, 2))


@jax.jit
def _defect_stage(rec: Reconstructor, target, t_p):
    """Edge targets of T - T(p), the gradients the current positions still miss (linear: a difference)."""
    return target - rec.edge_targets_vm(t_p)


@jax.jit
def _decode_output(p, features):
    lead, v = features.shape[:-2], features.shape[-2]
    return jnp.moveaxis(p, -1, 0).reshape(*lead, v, 3)


@jax.jit
def _initial_stage(rec: Reconstructor, features, initial):
    """The conjugate gradients' start (V, 3, B): ``initial`` (..., V, 3) broadcast to the batch, or the reference."""
    lead, v = features.shape[:-2], features.shape[-2]
    if initial is None:
        return jnp.broadcast_to(rec.rest.astype(features.dtype)[:, :, None], (v, 3, math.prod(lead)))
    x = jnp.broadcast_to(jnp.asarray(initial, features.dtype), (*lead, v, 3))
    return jnp.moveaxis(x.reshape(-1, v, 3), 0, -1)


def _decode(rec: Reconstructor, frame: RestFrame, features, targets, refine: int, initial=None):
    # Separately jitted stages (see the encoder's note): as one program, XLA on CPU runs slower.
    t = _decode_gradients(_features_cm(features))
    target = _edge_stage(rec, t)
    targets = None if targets is None else _anchor_targets(rec, features, targets)
    y0 = _initial_stage(rec, features, initial) if isinstance(rec.method, ConjugateGradient) else None
    p, info = _solve_stage(rec, target, targets, y0)
    if refine:
        zero = jnp.zeros((rec.anchors.shape[0], 3, target.shape[-1]), target.dtype)  # corrections move no anchor
        for _ in range(refine):
            dp, step_info = _solve_stage(rec, _defect_stage(rec, target, _refit_stage(frame, p)), zero, None)
            p = p + dp
            info = info.merge(step_info)
    return _decode_output(p, features), info


def default_solver(n_vertices: int, backend: str | None = None) -> str:
    """The solver `prepare(solver=None)` picks.

    **Arguments:**

    - `n_vertices`: the mesh's vertex count.
    - `backend`: a JAX backend name; None: `jax.default_backend()`.

    **Returns:**

    "host" (the host factor) on CPU; on an accelerator "dense" up to DENSE_MAX_VERTICES vertices, "cg"
    (conjugate gradients) above.
    """
    backend = jax.default_backend() if backend is None else backend
    if backend == "cpu":
        return "host"
    return "dense" if n_vertices <= DENSE_MAX_VERTICES else "cg"


def prepare(
    rest,
    faces,
    weighting: Weighting = "official",
    *,
    solver: str | None = None,
    anchors=None,
    cg_rtol: float | None = None,
    cg_max_steps: int = CG_MAX_STEPS,
) -> Acap:
    """Build the :class:`Acap` of a reference mesh.

    Does all host work: topology, consistency graph, reference fits, edge weights and the reconstruction's
    factor for the anchors.

    **Arguments:**

    - `rest`: reference positions, shape `(V, 3)`; float32 or float64 (other types become float64).
    - `faces`: triangles, shape `(F, 3)`, integer vertex indices.
    - `weighting`: the edge weighting of the local fits (default "official").
    - `solver`: "host" (sparse Cholesky on the host), "dense" (XLA Cholesky, on the device), "cg" (matrix-free
      conjugate gradients) or None (:func:`default_solver`).
    - `anchors`: the default anchor vertex indices; None: the lowest vertex of each connected
      component (vertex 0 for a connected mesh).
    - `cg_rtol`: relative tolerance of conjugate gradients (None: the solver's default).
    - `cg_max_steps`: at most this many conjugate-gradient steps.

    **Returns:**

    The :class:`Acap`. The reference's dtype is the Acap's own; each call computes in its input's dtype.

    **Raises:**

    `ValueError` for a reference not `(V, 3)` or an unknown solver; `DegenerateMeshError` for a non-finite
    reference coordinate; the topology's errors for bad faces (see :func:`build_topology`).
    """
    rest = np.asarray(rest)
    if rest.dtype not in (np.float32, np.float64):
        rest = rest.astype(np.float64)
    if rest.ndim != 2 or rest.shape[1] != 3:
        raise ValueError(f"the reference must be (V, 3), got {rest.shape}.")
    if not np.all(np.isfinite(rest)):
        raise DegenerateMeshError("a reference vertex coordinate is NaN or infinite.")
    if solver is not None and solver not in SOLVERS:
        raise ValueError(f"unknown solver '{solver}'; expected one of {', '.join(SOLVERS)}.")
    faces = np.asarray(faces)
    topo = build_topology(faces, rest.shape[0])
    rest_j = jnp.asarray(rest)
    frame = rest_frame(rest_j, topo, weighting)
    graph = cons.build_graph(np.asarray(topo.edges), topo.n_vertices)
    solver = default_solver(topo.n_vertices) if solver is None else solver
    rec = Reconstructor.build(
        rest_j, topo, frame.weights, anchors, solver=solver, cg_rtol=cg_rtol, cg_max_steps=cg_max_steps
    )
    return Acap(
        rest=rest_j,
        faces=jnp.asarray(faces, jnp.int32),
        topo=topo,
        frame=frame,
        rings=graph.rings,
        rec=rec,
        weighting=weighting,
    )


_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 8


def cached(rest, faces, weighting: Weighting = "official", *, solver: str | None = None) -> Acap:
    """:func:`prepare` with a small LRU cache keyed by the reference and faces bytes.

    **Arguments:**

    - `rest`, `faces`, `weighting`, `solver`: as :func:`prepare`.

    **Returns:**

    The cached (or newly prepared) :class:`Acap`.
    """
    rest = np.asarray(rest)
    faces = np.asarray(faces)
    key = (
        hashlib.sha1(rest.tobytes()).hexdigest(),
        rest.shape,
        str(rest.dtype),
        hashlib.sha1(faces.astype(np.int64).tobytes()).hexdigest(),
        weighting,
        solver,
    )
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    acap = prepare(rest, faces, weighting, solver=solver)
    _CACHE[key] = acap
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return acap


def encode(
    rest, faces, vertices, *, consistency: str | None = "spatial", weighting: Weighting = "official"
) -> Float[Array, "... v 9"]:
    """ACAP features of meshes relative to a reference (host convenience).

    :func:`prepare` cached by the reference's bytes; use :meth:`Acap.encode` inside jit.

    **Arguments:**

    - `rest`: reference positions, shape `(V, 3)`.
    - `faces`: triangles, shape `(F, 3)`.
    - `vertices`: positions, shape `(..., V, 3)`.
    - `consistency`: "spatial" (ACAP), "temporal" (TS-ACAP, frames in order) or None/"none" (angles in
      [0, pi]).
    - `weighting`: as :func:`prepare`.

    **Returns:**

    Features of shape `(..., V, 9)` (see :meth:`Acap.encode_parts` for raised errors).
    """
    return cached(rest, faces, weighting).encode(vertices, consistency)


def decode(
    features,
    rest,
    faces,
    *,
    anchors=None,
    targets=None,
    refine: int = DEFAULT_REFINE,
    weighting: Weighting = "official",
):
    """Vertex positions from features (host convenience, see :func:`encode`).

    **Arguments:**

    - `features`: features, shape `(..., V, 9)`.
    - `rest`, `faces`, `weighting`: as :func:`encode`.
    - `anchors`: vertex indices held at `targets`; without anchors the lowest vertex of each connected
      component is held at its reference position (the features carry no translation).
    - `targets`: anchor positions; None: their reference positions.
    - `refine`: number of defect-correction steps (see :meth:`Acap.decode_info`; 0 = plain ACAP
      reconstruction).

    **Returns:**

    Positions of shape `(..., V, 3)`.
    """
    return cached(rest, faces, weighting).decode(features, anchors=anchors, targets=targets, refine=refine)


def turn_reference(features: Float[jax.typing.ArrayLike, "n v 9"]) -> Float[Array, "v 3"]:
    """Per-vertex reference rotation vectors of a set of shapes' features, for :func:`align_turns`.

    **Arguments:**

    - `features`: the features of a set of shapes (e.g. a model's training shapes), shape `(N, V, 9)`.

    **Returns:**

    Reference rotation vectors of shape `(V, 3)` (see :func:`jaxdeform.acap.consistency.turn_reference`).
    """
    return cons.turn_reference(jnp.asarray(features)[..., :3])


def align_turns(
    features: Float[jax.typing.ArrayLike, "*batch v 9"], reference: Float[jax.typing.ArrayLike, "v 3"]
) -> Float[Array, "*batch v 9"]:
    """The same features with every rotation vector on the 2 pi branch nearest a reference.

    **Arguments:**

    - `features`: features, shape `(..., V, 9)`.
    - `reference`: reference rotation vectors (from :func:`turn_reference`), shape `(V, 3)`.

    **Returns:**

    Features `(..., V, 9)` in the input's dtype, consistent across shapes; the rotations, so the decoded
    positions, do not change.
    """
    f = jnp.asarray(features)
    return jnp.concatenate([cons.align_turns(f[..., :3], jnp.asarray(reference, f.dtype)), f[..., 3:]], axis=-1)


# --------------------------------------------------------------------------------------------------
# Scaler
# --------------------------------------------------------------------------------------------------

SCALE_LIMIT = 0.95
SCALE_PAD = 1e-6


def check_quantile(quantile: float, name: str = "quantile") -> None:
    """Check a clipping quantile.

    **Arguments:**

    - `quantile`: the :meth:`Scaler.fit` argument.
    - `name`: the option's name in the error message.

    **Raises:**

    `ValueError` unless `quantile` lies in [0, 0.5).
    """
    if not 0.0 <= quantile < 0.5:
        raise ValueError(f"{name} must lie in [0, 0.5), got {quantile}.")


@dataclasses.dataclass(frozen=True)
class Scaler:
    """Maps rotation entries (features 0-2) and S entries (3-8) linearly to [-0.95, 0.95].

    One global min/max over all rotation entries and one over all S entries (all shapes and vertices),
    each padded by 1e-6 (the official convention). With ``quantile`` q > 0 the bounds are the q and 1 - q
    quantiles instead, and :meth:`transform` clips to them: a few badly shaped one-rings can stretch S far
    beyond the rest (horse-gallop: S entries up to 13 where 99.8 % lie in [-0.8, 2.8]), and a global range
    then leaves the ordinary deformation a narrow band of the [-0.95, 0.95] a tanh decoder can produce.
    """

    rot_min: float
    rot_max: float
    s_min: float
    s_max: float
    quantile: float = 0.0

    @staticmethod
    def fit(features, quantile: float = 0.0) -> Scaler:
        """Fit the bounds to a set of features.

        **Arguments:**

        - `features`: features, shape `(..., 9)`.
        - `quantile`: 0: global min/max; q in (0, 0.5): the q and 1 - q quantiles, with clipping.

        **Returns:**

        The :class:`Scaler`.

        **Raises:**

        `ValueError` unless `quantile` lies in [0, 0.5).
        """
        f = np.asarray(features)
        check_quantile(quantile)
        if quantile == 0.0:
            return Scaler(
                float(f[..., :3].min()) - SCALE_PAD,
                float(f[..., :3].max()) + SCALE_PAD,
                float(f[..., 3:].min()) - SCALE_PAD,
                float(f[..., 3:].max()) + SCALE_PAD,
            )
        r0, r1 = np.quantile(f[..., :3], [quantile, 1.0 - quantile])
        s0, s1 = np.quantile(f[..., 3:], [quantile, 1.0 - quantile])
        return Scaler(
            float(r0) - SCALE_PAD, float(r1) + SCALE_PAD, float(s0) - SCALE_PAD, float(s1) + SCALE_PAD, float(quantile)
        )

    def _bounds(self, dtype):
        lo = jnp.asarray([self.rot_min] * 3 + [self.s_min] * 6, dtype)
        hi = jnp.asarray([self.rot_max] * 3 + [self.s_max] * 6, dtype)
        return lo, hi

    def transform(self, features):
        """Scale features to [-0.95, 0.95].

        **Arguments:**

        - `features`: features, shape `(..., 9)`.

        **Returns:**

        Scaled features of the same shape and dtype (clipped to the bounds first when `quantile` > 0).
        """
        f = jnp.asarray(features)
        lo, hi = self._bounds(f.dtype)
        if self.quantile > 0.0:
            f = jnp.clip(f, lo, hi)
        return (2.0 * (f - lo) / (hi - lo) - 1.0) * SCALE_LIMIT

    def inverse(self, scaled):
        """Inverse of :meth:`transform` (up to its clipping).

        **Arguments:**

        - `scaled`: scaled features, shape `(..., 9)`.

        **Returns:**

        Features of the same shape and dtype.
        """
        x = jnp.asarray(scaled)
        lo, hi = self._bounds(x.dtype)
        return (x / SCALE_LIMIT + 1.0) * 0.5 * (hi - lo) + lo

    def to_array(self) -> np.ndarray:
        """The scaler as an array, for saving.

        **Returns:**

        `(rot_min, rot_max, s_min, s_max)`, plus the quantile where it is not 0 (clipping scalers).
        """
        bounds = [self.rot_min, self.rot_max, self.s_min, self.s_max]
        return np.array(bounds + ([self.quantile] if self.quantile > 0.0 else []))

    @staticmethod
    def from_array(a) -> Scaler:
        """The scaler from :meth:`to_array`.

        **Arguments:**

        - `a`: four entries (a scaler without clipping) or five (with its quantile).

        **Returns:**

        The :class:`Scaler`.
        """
        a = np.asarray(a, dtype=np.float64).ravel()
        return Scaler(*map(float, a[:5]))


def log_matrices(v: Float[jax.typing.ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Full 3x3 log(R) (skew) from axis-angle vectors.

    **Arguments:**

    - `v`: axis-angle vectors, shape `(..., 3)`.

    **Returns:**

    Skew matrices of shape `(..., 3, 3)`.
    """
    return skew(v)
