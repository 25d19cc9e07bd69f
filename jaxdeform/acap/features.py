"""ACAP features: encode meshes to 9-d per-vertex features, decode features to meshes, and the Scaler.

Feature layout per vertex (official order): (logR_01, logR_02, logR_12, S_00, S_01, S_02, S_11, S_12, S_22)
where logR is the skew matrix of the consistent axis-angle vector v: logR_01 = -v_z, logR_02 = v_y,
logR_12 = -v_x.

:class:`Acap` holds everything computed once per (reference, connectivity, weighting): topology, reference
frame of the local fits, the host graph for consistency, and a jitted local step. ``encode``/``decode`` keep
a small cache of these, keyed by the bytes of the reference and faces, so repeated calls do not refactor
or recompile.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections import OrderedDict

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxdeform.acap import consistency as cons
from jaxdeform.acap.gradients import (
    RestFrame,
    Weighting,
    deformation_gradients_cm,
    rest_frame,
    to_vertex_major,
)
from jaxdeform.acap.reconstruct import Reconstructor
from jaxdeform.acap.rotations import exp_rotation_cm, from_cm, log_rotation_cm, mm_cm, polar_cm, skew, to_cm
from jaxdeform.errors import ConnectivityError, DegenerateMeshError
from jaxdeform.mesh.topology import Topology, build_topology

DEFAULT_REFINE = 1
_S_IDX = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def features_from(v: Float[Array, "... 3"], s: Float[Array, "... 3 3"]) -> Float[Array, "... 9"]:
    """9-d features from axis-angle vectors and symmetric S."""
    rot = jnp.stack([-v[..., 2], v[..., 1], -v[..., 0]], axis=-1)
    return jnp.concatenate([rot, s[..., _S_IDX[0], _S_IDX[1]]], axis=-1)


def split_features_cm(f: Float[Array, "9 ..."]) -> tuple[Array, Array]:
    """Features in the component-major layout (9, *batch) -> (axis-angle (3, *batch), S (3, 3, *batch))."""
    v = jnp.stack([-f[2], f[1], -f[0]])
    s00, s01, s02, s11, s12, s22 = (f[k] for k in range(3, 9))
    return v, jnp.stack([jnp.stack([s00, s01, s02]), jnp.stack([s01, s11, s12]), jnp.stack([s02, s12, s22])])


def split_features(f: Float[Array, "... 9"]) -> tuple[Array, Array]:
    """Inverse of :func:`features_from`: (axis-angle vectors (..., 3), S (..., 3, 3))."""
    v, s = split_features_cm(to_cm(f, 1))
    return from_cm(v, 1), from_cm(s)


def gradients_from_features_cm(f: Float[Array, "9 ..."]) -> Float[Array, "3 3 ..."]:
    """T = exp(log R) S in the component-major layout."""
    v, s = split_features_cm(f)
    return mm_cm(exp_rotation_cm(v), s)


def gradients_from_features(f: Float[Array, "... 9"]) -> Float[Array, "... 3 3"]:
    """T = exp(log R) S."""
    return from_cm(gradients_from_features_cm(to_cm(f, 1)))


# The encoder runs as a few separately jitted stages: compiled as one program, XLA on CPU picked layouts and
# fusions that made the whole 4x slower than the sum of its parts (horse-gallop: 20 ms against 5 ms/frame).


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


def _local_cm(frame: RestFrame, vertices):
    """Raw axis-angle vectors (3, V, N) and S (3, 3, V, N) of frames (N, V, 3) (component-major)."""
    return _polar_stage(_gradients_stage(frame, vertices))


def _local(frame: RestFrame, vertices):
    return _output_stage(*_local_cm(frame, vertices))


def _encode_parts(frame: RestFrame, rings: cons.Rings, vertices, mode: str):
    v, s = _local_cm(frame, vertices)
    if mode != "none":
        v = cons.consistent_cm(v, rings, mode)
    return _output_stage(v, s)


def _check_vertices(vertices: np.ndarray, n: int) -> None:
    if vertices.ndim != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices must be (N, V, 3), got {vertices.shape}.")
    if vertices.shape[1] != n:
        raise ConnectivityError(f"the meshes have {vertices.shape[1]} vertices but the reference has {n}.")
    if not np.all(np.isfinite(vertices)):
        raise DegenerateMeshError("a vertex coordinate is NaN or infinite.")


@dataclasses.dataclass
class Acap:
    """ACAP machinery for one reference mesh and connectivity (build once with :func:`prepare`)."""

    rest: np.ndarray
    faces: np.ndarray
    topo: Topology
    frame: RestFrame
    graph: cons.Graph
    weighting: Weighting
    _reconstructors: dict = dataclasses.field(default_factory=dict)

    def local(self, vertices) -> tuple[Array, Array]:
        """(axis-angle vectors (N,V,3) with angles in [0, pi], S (N,V,3,3)): jitted, no consistency."""
        return _local(self.frame, jnp.asarray(vertices, dtype=self.frame.dtype))

    def encode_parts(self, vertices, consistency: cons.Consistency | None = "spatial") -> tuple[Array, Array]:
        """(consistent axis-angle vectors (N,V,3), S (N,V,3,3))."""
        vertices = np.asarray(vertices)
        if vertices.ndim == 2:
            vertices = vertices[None]
        _check_vertices(vertices, self.topo.n_vertices)
        if consistency not in (None, "none", "spatial", "temporal"):
            raise ValueError(f"unknown consistency '{consistency}'; expected 'spatial', 'temporal' or 'none'.")
        mode = "none" if consistency is None else consistency
        return _encode_parts(self.frame, self.graph.rings, jnp.asarray(vertices, dtype=self.frame.dtype), mode)

    def encode(self, vertices, consistency: cons.Consistency | None = "spatial") -> Float[Array, "n v 9"]:
        v, s = self.encode_parts(vertices, consistency)
        return features_from(v, s)

    def reconstructor(self, anchors=None) -> Reconstructor:
        key = None if anchors is None else tuple(np.atleast_1d(np.asarray(anchors)).tolist())
        if key not in self._reconstructors:
            self._reconstructors[key] = Reconstructor.build(self.rest, self.topo, self.frame.weights, anchors)
        return self._reconstructors[key]

    def deformation_energy(self, features, positions) -> Float[Array, "..."]:
        """The ACAP reconstruction's objective without its anchor term, per shape:
        sum over edges of w_ij |(p_i - p_j) - (T_i + T_j)/2 (q_i - q_j)|^2, with T the deformation gradients of
        ``features`` (..., V, 9) and p = ``positions`` (..., V, 3). Zero when the positions realise the features'
        gradients exactly; :meth:`decode` with ``refine=0`` minimises it under its anchors. Differentiable in both.
        """
        rec = self.reconstructor(None)  # the edge terms are the same for every anchor set
        features = jnp.asarray(features)
        lead, v = features.shape[:-2], features.shape[-2]
        target = rec.edge_targets_vm(_decode_gradients(_features_cm(features)))  # (E, 3, B)
        p = jnp.moveaxis(jnp.asarray(positions, target.dtype).reshape(-1, v, 3), 0, -1)  # (V, 3, B)
        diff = rec.sqrt_w.astype(target.dtype)[:, None, None] * (p[rec.edge_i] - p[rec.edge_j]) - target
        return jnp.sum(diff**2, axis=(0, 1)).reshape(lead)

    def decode(self, features, *, anchors=None, targets=None, refine: int = DEFAULT_REFINE) -> Float[Array, "... v 3"]:
        """Positions (..., V, 3) from features (..., V, 9); differentiable in features and targets.

        ``refine=0`` is the plain ACAP reconstruction (one least-squares solve). Each refinement step
        (defect correction) re-fits the gradients of the current positions with the encoder's own local
        fits and solves the same prefactored least-squares problem for the correction, so that the
        decoded mesh reproduces the given gradients more closely (horse-gallop round trip, mean error
        over the bounding-box diagonal: 1.5e-3 with 0 steps, 5.6e-4 with 1, 3.1e-4 with 2).
        """
        return _decode(self.reconstructor(anchors), self.frame, features, targets, refine)


@jax.jit
def _features_cm(features):
    """Features (..., V, 9) -> (9, V, B) (its own stage: fused with the next, XLA on CPU ran 2x slower)."""
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
    """Edge targets (E, 3, B) of T (its own stage: fused with either neighbour, XLA on CPU ran 2x slower)."""
    return rec.edge_targets_vm(t)


@jax.jit
def _solve_stage(rec: Reconstructor, target, targets):
    return rec.solve_targets_vm(target, targets)


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


def _decode(rec: Reconstructor, frame: RestFrame, features, targets, refine: int):
    # Separately jitted stages (see the encoder's note): one program was 2-4x slower on XLA CPU.
    t = _decode_gradients(_features_cm(features))
    target = _edge_stage(rec, t)
    targets = None if targets is None else _anchor_targets(rec, features, targets)
    p = _solve_stage(rec, target, targets)
    if refine:
        zero = jnp.zeros((rec.anchors.shape[0], 3, target.shape[-1]), target.dtype)  # corrections move no anchor
        for _ in range(refine):
            p = p + _solve_stage(rec, _defect_stage(rec, target, _refit_stage(frame, p)), zero)
    return _decode_output(p, features)


def prepare(rest, faces, weighting: Weighting = "official") -> Acap:
    """Build the :class:`Acap` of a reference mesh (host work: topology, graph, reference fits)."""
    rest = np.asarray(rest)
    if rest.dtype not in (np.float32, np.float64):
        rest = rest.astype(np.float64)
    if rest.ndim != 2 or rest.shape[1] != 3:
        raise ValueError(f"the reference must be (V, 3), got {rest.shape}.")
    if not np.all(np.isfinite(rest)):
        raise DegenerateMeshError("a reference vertex coordinate is NaN or infinite.")
    faces = np.asarray(faces)
    topo = build_topology(faces, rest.shape[0])
    frame = rest_frame(jnp.asarray(rest), topo, weighting)
    graph = cons.build_graph(np.asarray(topo.edges), topo.n_vertices)
    return Acap(rest=rest, faces=faces.astype(np.int32), topo=topo, frame=frame, graph=graph, weighting=weighting)


_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 8


def cached(rest, faces, weighting: Weighting = "official") -> Acap:
    """:func:`prepare` with a small LRU cache keyed by the reference and faces bytes."""
    rest = np.asarray(rest)
    faces = np.asarray(faces)
    key = (hashlib.sha1(rest.tobytes()).hexdigest(), rest.shape, str(rest.dtype),
           hashlib.sha1(faces.astype(np.int64).tobytes()).hexdigest(), weighting)
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    acap = prepare(rest, faces, weighting)
    _CACHE[key] = acap
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return acap


def encode(rest, faces, vertices, *, consistency: cons.Consistency | None = "spatial",
           weighting: Weighting = "official") -> Float[Array, "n v 9"]:
    """ACAP features (N, V, 9) of ``vertices`` (N, V, 3) relative to ``rest`` (V, 3).

    ``consistency``: "spatial" (ACAP), "temporal" (TS-ACAP, frames in order) or None/"none" (angles in
    [0, pi]).
    """
    return cached(rest, faces, weighting).encode(vertices, consistency)


def decode(features, rest, faces, *, anchors=None, targets=None, refine: int = DEFAULT_REFINE,
           weighting: Weighting = "official"):
    """Vertex positions (..., V, 3) from features (..., V, 9); differentiable in ``features``.

    ``anchors``: vertex indices held at ``targets`` (default: their reference positions); without anchors
    vertex 0 is held at its reference position (the features carry no translation). ``refine``: number
    of defect-correction steps (see :meth:`Acap.decode`; 0 = plain ACAP reconstruction).
    """
    return cached(rest, faces, weighting).decode(features, anchors=anchors, targets=targets, refine=refine)


def turn_reference(features: Float[Array, "n v 9"]) -> Float[Array, "v 3"]:
    """Per-vertex reference rotation vectors (V, 3) of a set of shapes' features, for :func:`align_turns`
    (the training shapes of a model: see :func:`jaxdeform.acap.consistency.turn_reference`)."""
    return cons.turn_reference(jnp.asarray(features)[..., :3])


def align_turns(features: Float[Array, "... v 9"], reference: Float[Array, "v 3"]) -> Float[Array, "... v 9"]:
    """The same features with every rotation vector on the 2 pi branch nearest ``reference`` (consistency
    across shapes; the rotations, so the decoded positions, do not change)."""
    f = jnp.asarray(features)
    return jnp.concatenate([cons.align_turns(f[..., :3], jnp.asarray(reference, f.dtype)), f[..., 3:]], axis=-1)


# --------------------------------------------------------------------------------------------------
# Scaler
# --------------------------------------------------------------------------------------------------

SCALE_LIMIT = 0.95
SCALE_PAD = 1e-6


def check_quantile(quantile: float, name: str = "quantile") -> None:
    """ValueError unless ``quantile`` (the :meth:`Scaler.fit` argument, or the option ``name``) lies in [0, 0.5)."""
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
    def fit(features, quantile: float = 0.0) -> "Scaler":
        f = np.asarray(features)
        check_quantile(quantile)
        if quantile == 0.0:
            return Scaler(float(f[..., :3].min()) - SCALE_PAD, float(f[..., :3].max()) + SCALE_PAD,
                          float(f[..., 3:].min()) - SCALE_PAD, float(f[..., 3:].max()) + SCALE_PAD)
        r0, r1 = np.quantile(f[..., :3], [quantile, 1.0 - quantile])
        s0, s1 = np.quantile(f[..., 3:], [quantile, 1.0 - quantile])
        return Scaler(float(r0) - SCALE_PAD, float(r1) + SCALE_PAD, float(s0) - SCALE_PAD, float(s1) + SCALE_PAD,
                      float(quantile))

    def _bounds(self, dtype):
        lo = jnp.asarray([self.rot_min] * 3 + [self.s_min] * 6, dtype)
        hi = jnp.asarray([self.rot_max] * 3 + [self.s_max] * 6, dtype)
        return lo, hi

    def transform(self, features):
        f = jnp.asarray(features)
        lo, hi = self._bounds(f.dtype)
        if self.quantile > 0.0:
            f = jnp.clip(f, lo, hi)
        return (2.0 * (f - lo) / (hi - lo) - 1.0) * SCALE_LIMIT

    def inverse(self, scaled):
        x = jnp.asarray(scaled)
        lo, hi = self._bounds(x.dtype)
        return (x / SCALE_LIMIT + 1.0) * 0.5 * (hi - lo) + lo

    def to_array(self) -> np.ndarray:
        """(rot_min, rot_max, s_min, s_max), plus the quantile where it is not 0 (clipping scalers)."""
        bounds = [self.rot_min, self.rot_max, self.s_min, self.s_max]
        return np.array(bounds + ([self.quantile] if self.quantile > 0.0 else []))

    @staticmethod
    def from_array(a) -> "Scaler":
        """From :meth:`to_array` (four entries, as files written before ``quantile`` hold: no clipping)."""
        a = np.asarray(a, dtype=np.float64).ravel()
        return Scaler(*map(float, a[:5]))


def log_matrices(v: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """Full 3x3 log(R) (skew) from axis-angle vectors."""
    return skew(v)
