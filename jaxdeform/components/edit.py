"""Latent-space shape editing by control points (seed 000, Sec. 5.1 Fig. 6 and Sec. 5.4 Fig. 18).

Seed 000 edits shapes "under the constraints of the control points and subspace spanned by extracted
deformation components" with the data-driven deformation of its ref. [19] (Gao et al., sparse data-driven
mesh deformation): find latent weights ``w`` of a deformation model whose reconstructed mesh meets target
positions at a few control vertices. Fig. 6 measures how well each method's components generalise this way:
control points by furthest point sampling, targets taken from an unseen shape, error of the whole edited mesh.

This module is method-agnostic. A model is any pure differentiable JAX function of one latent vector:

- ``decode_features(w) -> (V, 9)`` ACAP features (multiscale model: a wrapper around
  ``Model.decode_latents`` with the latent tuple flattened; PCA on features: ``mean + w @ components``),
  optionally scaled (a :class:`~jaxdeform.acap.Scaler` maps them back). Positions come from the
  differentiable ACAP reconstruction :meth:`jaxdeform.acap.Acap.decode` (implicit adjoint of a prefactored
  least-squares solve, so gradients cost one more sparse solve);
- ``decode_positions(w) -> (V, 3)`` vertex positions (PCA on coordinates, SPLOCS): :func:`edit_positions`.

Objective, over the latent ``w`` (K,) and a translation ``t`` (3,)::

    E(w, t) = sum_c |p_c(w) + t - target_c|^2 + regularization |w - w0|^2.

Translation. ACAP features carry no translation (the reconstruction pins one ``anchor`` vertex at its rest
position). ``t`` enters E linearly and unregularised, so its minimiser is closed form,
t*(w) = mean_c(target_c - p_c(w)) (the control points' centroids aligned), and minimising E(w, t*(w)) over w
alone (variable projection) has exactly the minimisers of the joint problem. The same free translation is
used for coordinate models so that every method is compared under the same protocol
(``free_translation=False`` keeps positions as decoded).

Optimiser (one jitted call per stage, at most ``steps`` iterations each, stopping early once the step and
the objective change fall below ``tolerance``). The latents are first rescaled, z = c (w - w0) with c the
column norms of the control Jacobian at w0, so that damping, line searches and tolerances do not depend on
the latents' units. The Jacobian of the 3M control rows is taken by forward mode (K batched JVPs through
the decoder, one primal pass) when K <= 3M, else, or when the decoder has a custom VJP and no forward mode
(the multiscale model's mesh convolution), by reverse mode.

- ``method="bfgs"`` (default): ``optimistix.BFGS`` on E. On horse-gallop (PCA, 4 latents, 20-50 controls)
  it reaches the optimum in 17-21 iterations, where Gauss-Newton-type methods
  need 22-50: the target lies outside the subspace, the residual at the optimum is large, and the
  Gauss-Newton model misses its curvature.
- ``method="lm"``: Levenberg-Marquardt (``optimistix.least_squares``) on the residuals
  (p_C + t* - targets, sqrt(regularization) (w - w0)); 7-11 iterations when the target lies in the
  subspace. optimistix's forward-mode Jacobian option evaluates its zero-filled initial linearisation,
  which the reconstruction's implicit-adjoint solve rejects as non-finite, so the forward-mode Jacobian
  is supplied through a custom VJP instead.
- ``method="adam"``: exactly ``steps`` optax Adam steps on w (``learning_rate`` in latent units) under
  ``lax.scan``; needs hundreds of steps.

Objective "deformation" (``objective="deformation"``, feature-space models): the data-driven deformation of
seed 000's ref. [19] (Gao et al.) solves for the positions and the blending weights together, the positions
meeting the controls and fitting the deformation gradients that the weights blend. Here the mesh of a latent w
is the ACAP least-squares reconstruction of its features with the control vertices held at their targets (the
reconstruction's anchors, their weight 1e3 times the mean edge weight), and w minimises that mesh's deformation energy
(:meth:`Acap.deformation_energy`: how far its edges are from the features' gradients), relative to the rest
code's, plus the regularization. The controls are then met by construction, and the latents choose the
deformation that explains them with least distortion. BFGS (or Adam) in raw latent units; the mesh is the
plain reconstruction (``refine`` = 0), the minimiser of that energy. On horse-gallop at 20 controls (8 unseen
shapes, converged edits) it lowered the mean vertex error of Tan et al. from 0.0071 to 0.0059 and of the
multiscale model from 0.0074 to 0.0058 of the bounding-box diagonal (README, Fig. 6).

Start. The paper defers the deformation itself to [19], whose optimisation starts at the reference shape;
:func:`edit_error` therefore starts at ``latent0`` = the code of the rest shape (for a linear model centred
on the rest shape, zeros; for PCA about the mean, the projection of the rest features).

Stages (coarse to fine). ``stages=(k_1, ..., K)`` runs one edit per stage: stage s optimises the first
``k_s`` latents, starting from the result of stage s - 1, with the others held; every stage minimises the same
E, regularised toward ``latent0``. For the multiscale model (latents ordered level by level, one stage per
level) this is the paper's editing order, "users usually start with editing of the overall shape, and then
focus on adjusting the details" (Sec. 5.4): level 0's codes, then levels 0-1, ..., then every code. The
default (``None``) is one stage over all latents. The held latents enter through a traced 0/1 mask, so all
stages call one compiled function.

Everything after argument checks is one jitted function (called once per stage); the decoder, the ACAP
object and the scaler are static (compared by identity, the scaler by value), so a second call with the same
objects and shapes does not retrace.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from jaxdeform.acap import Acap, Scaler, cached
from jaxdeform.acap.features import DEFAULT_REFINE
from jaxdeform.errors import JaxDeformError

Method = Literal["lm", "bfgs", "adam"]
METHODS = ("lm", "bfgs", "adam")
Objective = Literal["controls", "deformation"]
OBJECTIVES = ("controls", "deformation")

# A cap, not a count: BFGS and LM stop on the tolerance. On horse-gallop at 20 controls BFGS needs 74-112
# iterations for Tan et al.'s 50 codes and up to about 180 in the multiscale model's second stage (60 codes);
# a cap of 50 would cut both short (EditResult.converged).
DEFAULT_STEPS = 500
DEFAULT_LEARNING_RATE = 1e-2
DEFAULT_REGULARIZATION = 1e-6


class EditInputError(JaxDeformError, ValueError):
    """Arguments of an edit are inconsistent (indices out of range, non-finite targets, mismatched shapes)."""


class EditResult(NamedTuple):
    """Outcome of :func:`edit` / :func:`edit_positions`."""

    latent: Float[Array, " k"]  # optimised latent weights w
    positions: Float[Array, "v 3"]  # edited mesh, translation included
    translation: Float[Array, " 3"]  # t*(w) added to the decoded positions (zeros without free translation)
    control_error: Float[Array, ""]  # mean distance between edited control vertices and their targets
    # "controls": E(w, t*) = sum of squared control residuals + regularization |w - w0|^2; "deformation":
    # E(w) / E(latent0) (deformation energies, controls held) + regularization |w - w0|^2
    objective: Float[Array, ""]
    steps: Int[Array, ""]  # optimiser iterations taken (summed over the stages)
    # every stage met the tolerance within the ``steps`` cap (optimistix's result; always False for "adam",
    # which runs a fixed number of steps)
    converged: Bool[Array, ""]


class EditErrorReport(NamedTuple):
    """Outcome of :func:`edit_error` (the protocol of seed 000's Fig. 6)."""

    mean_error: float  # mean over all vertices of |edited - ground truth|, over the rest bounding-box diagonal
    rms_error: float  # sqrt(mean |edited - ground truth|^2), same unit
    control_error: float  # mean control-point residual, same unit
    diagonal: float  # bounding-box diagonal of the rest shape (the unit above)
    controls: np.ndarray  # (n,) control vertex indices (FPS on the rest shape)
    result: EditResult


# --------------------------------------------------------------------------------------------------
# Furthest point sampling
# --------------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("n",))
def _fps(vertices: Float[Array, "v 3"], start: Int[Array, ""], n: int) -> Int[Array, " n"]:
    """Greedy furthest point sampling: a loop over the n samples, each step vectorised over vertices."""

    def sq_dist(i):
        return jnp.sum((vertices - vertices[i]) ** 2, axis=-1)

    chosen = jnp.zeros((n,), jnp.int32).at[0].set(start)
    # chosen vertices get distance -1 so that duplicates (unwelded meshes) still give distinct indices
    d = sq_dist(start).at[start].set(-1.0)

    def body(k, carry):
        chosen, d = carry
        nxt = jnp.argmax(d).astype(jnp.int32)  # first index among ties: deterministic
        d = jnp.minimum(d, sq_dist(nxt)).at[nxt].set(-1.0)  # chosen ones keep -1
        return chosen.at[k].set(nxt), d

    chosen, _ = jax.lax.fori_loop(1, n, body, (chosen, d))
    return chosen


def furthest_point_sampling(vertices: Float[Array, "v 3"], n: int, start: int = 0) -> Int[Array, " n"]:
    """``n`` distinct vertex indices by greedy furthest point sampling (Euclidean), beginning at ``start``.

    Each next index maximises the distance to the nearest already chosen vertex; ties go to the lowest index.

    **Arguments:**

    - ``vertices``: ``(V, 3)``, non-empty and finite.
    - ``n``: the number of samples, in [1, V].
    - ``start``: the first sample, in [0, V).

    **Returns:**

    The indices ``(n,)``, distinct, ``start`` first.

    **Raises:**

    ``EditInputError`` for invalid ``vertices``, ``n`` or ``start``.
    """
    v = np.asarray(vertices)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise EditInputError(f"vertices must be a non-empty (V, 3) array, got shape {v.shape}.")
    if not np.all(np.isfinite(v)):
        raise EditInputError("a vertex coordinate is NaN or infinite.")
    if int(n) != n or not 1 <= n <= v.shape[0]:
        raise EditInputError(f"the number of samples must be an integer in [1, {v.shape[0]}], got {n}.")
    if int(start) != start or not 0 <= start < v.shape[0]:
        raise EditInputError(f"the start index must lie in [0, {v.shape[0]}), got {start}.")
    return _fps(jnp.asarray(vertices), jnp.asarray(int(start), jnp.int32), int(n))


# --------------------------------------------------------------------------------------------------
# The latent -> positions map (static part of the jitted editor)
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class _Model:
    """How latents become positions. Equal (same compiled editor) iff the decoder and ACAP objects are the
    same objects and the scaler and settings are equal."""

    decode: Callable
    acap: Acap | None  # None: ``decode`` returns positions
    scaler: Scaler | None
    anchor: int
    refine: int
    latent_dtype: str  # the decoder is called in the dtype of latent0 (the optimiser works in float64)
    objective: str = "controls"
    # objective "deformation": the control vertices, held at their targets by the reconstruction (static: the
    # reconstruction's factorization depends on them)
    controls: tuple[int, ...] | None = None

    def _key(self):
        return (
            id(self.decode),
            id(self.acap),
            self.scaler,
            self.anchor,
            self.refine,
            self.latent_dtype,
            self.objective,
            self.controls,
        )

    def __eq__(self, other):
        return (
            isinstance(other, _Model)
            and self.decode is other.decode
            and self.acap is other.acap
            and self._key()[2:] == other._key()[2:]
        )

    def __hash__(self):
        return hash(self._key())

    def features(self, w: Float[Array, " k"]) -> Float[Array, "v 9"]:
        out = self.decode(w.astype(self.latent_dtype))
        features = out if self.scaler is None else self.scaler.inverse(out)
        return features.astype(self.acap.rest.dtype)

    def positions(self, w: Float[Array, " k"]) -> Float[Array, "v 3"]:
        if self.acap is None:
            return self.decode(w.astype(self.latent_dtype))
        return self.acap.decode(self.features(w), anchors=self.anchors, refine=self.refine)

    def deformation(self, w: Float[Array, " k"], targets: Float[Array, "m 3"]) -> tuple[Array, Array]:
        """(deformation energy, positions) of the mesh reconstructed from w's features with the control
        vertices held at ``targets`` (objective "deformation"; the plain least-squares reconstruction, which
        minimises that energy under those constraints)."""
        features = self.features(w)
        p = self.acap.decode(features, anchors=list(self.controls), targets=targets.astype(features.dtype), refine=0)
        return self.acap.deformation_energy(features, p), p

    @property
    def anchors(self) -> list[int] | None:
        """Anchors for :meth:`Acap.decode` (None = its default, vertex 0, shared with other callers)."""
        return None if self.anchor == 0 else [self.anchor]


def _control_residuals(model: _Model, free_translation: bool, w, controls, targets):
    """(p_C + t* - targets (M, 3), t* (3,), positions (V, 3)) with t* the optimal translation."""
    p = model.positions(w)
    pc = p[controls]
    t = jnp.mean(targets - pc, axis=0) if free_translation else jnp.zeros((3,), p.dtype)
    return pc + t - targets, t, p


def _forward_jacobian(fn: Callable):
    """``fn`` (K,) -> pytree of residual arrays, with a custom JVP that materialises the Jacobian by forward mode
    (K batched JVPs, one primal pass) and returns its product with the tangent: reverse mode (optimistix's
    Jacobian, R cotangent rows) then transposes that product, R cheap matrix products instead of R backward
    passes through the decoder; forward mode and higher orders stay available."""

    @jax.custom_jvp
    def wrapped(w):
        return fn(w)

    @wrapped.defjvp
    def wrapped_jvp(primals, tangents):
        (w,), (t,) = primals, tangents
        r, lin = jax.linearize(fn, w)
        jac = jax.vmap(lin, out_axes=-1)(jnp.eye(w.shape[0], dtype=w.dtype))  # leaves (..., K)
        return r, jax.tree_util.tree_map(lambda j: j @ t, jac)

    return wrapped


class _Scaled(NamedTuple):
    """The problem in scaled coordinates z = c (w - w0) of this stage's free latents (see :func:`_scaled`)."""

    latent: Callable  # z -> w = w0 + free * z / c (held latents stay at w0 whatever z holds)
    rows: Callable  # z -> control residual rows (M, 3)
    reg_rows: Callable  # z -> sqrt(regularization) (w - w_ref)
    atol: Array  # absolute tolerance (a length)


def _scaled(model, free_translation, tolerance, w0, w_ref, controls, targets, regularization, free) -> _Scaled:
    """Damping (LM) and the first BFGS step are not invariant to the latents' units: optimise
    z = c (w - w0), with c the column norms of the Jacobian at the start, so that every column starts at
    unit norm; z and the residuals are then lengths, and the absolute tolerance is relative to the
    targets' spread."""

    def control_rows(w):
        return _control_residuals(model, free_translation, w, controls, targets)[0].astype(w0.dtype)

    # the Jacobian of the control rows (3M, K) by forward mode when K <= 3M (few latents, the usual case)
    if w0.shape[0] <= 3 * controls.shape[0]:
        control_rows = _forward_jacobian(control_rows)
    jac0 = jax.jacrev(control_rows)(w0)
    jac0 = jac0.reshape(-1, w0.shape[0])
    c = jnp.sqrt(jnp.sum(jac0**2, axis=0) + regularization)
    c = jnp.where((c > 0) & (free > 0), c, 1.0)
    sqrt_reg = jnp.sqrt(regularization).astype(w0.dtype)
    spread = jnp.sqrt(jnp.mean(jnp.sum((targets - jnp.mean(targets, axis=0)) ** 2, axis=-1)))

    # latents outside this stage (free == 0) are masked out of w: their z gets zero gradient, so BFGS (from an
    # identity inverse Hessian) and LM's damped solve leave it at 0, and w ignores it anyway
    def latent(z):
        return w0 + free * z / c

    # the regularization pulls toward w_ref (latent0) in every stage; a stage starts at w0
    return _Scaled(
        latent=latent,
        rows=lambda z: control_rows(latent(z)),
        reg_rows=lambda z: sqrt_reg * (latent(z) - w_ref),
        atol=tolerance * jnp.where(spread > 0, spread, 1.0),
    )


def _lm(problem: _Scaled, steps, tolerance, z0):
    # jac="bwd": optimistix's forward-mode path evaluates its zero-filled initial linearisation, which the
    # ACAP reconstruction's implicit-adjoint solve rejects as non-finite input (the forward-mode Jacobian
    # comes from _forward_jacobian instead).
    solver = optx.LevenbergMarquardt(rtol=tolerance, atol=problem.atol)
    sol = optx.least_squares(
        lambda z, _: (problem.rows(z), problem.reg_rows(z)),
        solver,
        z0,
        max_steps=steps,
        throw=False,
        options={"jac": "bwd"},
    )
    return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful


def _bfgs(problem: _Scaled, steps, tolerance, z0):
    def objective(z, _):
        return jnp.sum(problem.rows(z) ** 2) + jnp.sum(problem.reg_rows(z) ** 2)

    solver = optx.BFGS(rtol=tolerance, atol=problem.atol)
    sol = optx.minimise(objective, solver, z0, max_steps=steps, throw=False)
    return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful


def _adam_scan(objective: Callable[[Array], Array], x0: Array, steps: int, learning_rate) -> Array:
    """``steps`` optax Adam steps on ``objective`` from ``x0`` under ``lax.scan``."""
    opt = optax.adam(learning_rate)

    def step(carry, _):
        x, state = carry
        updates, state = opt.update(jax.grad(objective)(x), state, x)
        return (optax.apply_updates(x, updates), state), None

    (x, _), _ = jax.lax.scan(step, (x0, opt.init(x0)), None, length=steps)
    return x


def _adam(model, free_translation, steps, w0, w_ref, controls, targets, regularization, learning_rate, free):
    """``steps`` Adam steps on w itself (``learning_rate`` in latent units)."""

    def objective(w):
        w = w0 + free * (w - w0)
        r, _, _ = _control_residuals(model, free_translation, w, controls, targets)
        return jnp.sum(r.astype(w.dtype) ** 2) + regularization * jnp.sum((w - w_ref) ** 2)

    w = _adam_scan(objective, w0, steps, learning_rate)
    return w0 + free * (w - w0), jnp.asarray(steps)


def _deformation_solve(
    model: _Model, method, steps, tolerance, w0, w_ref, targets, regularization, learning_rate, free
):
    """Objective "deformation": minimise E(w) / E(latent0) + regularization |w - latent0|^2 over this stage's free
    latents (raw latent units), E the deformation energy of the mesh whose control vertices are held at the
    targets. Returns (w, iterations, converged, objective at w, mesh of w)."""
    e_ref = jax.lax.stop_gradient(model.deformation(w_ref, targets)[0])
    e_ref = jnp.where(e_ref > 0, e_ref, 1.0)

    def latent(z):
        return w0 + free * z

    def objective_and_mesh(w):
        energy, mesh = model.deformation(w, targets)
        return energy.astype(w0.dtype) / e_ref + regularization * jnp.sum((w - w_ref) ** 2), mesh

    def objective(z, _=None):
        return objective_and_mesh(latent(z))[0]

    z0 = jnp.zeros_like(w0)
    if method == "adam":
        z = _adam_scan(objective, z0, steps, learning_rate)
        taken, converged = jnp.asarray(steps), jnp.asarray(False)
    else:
        # the objective starts near 1 (it is relative to the rest code's energy): tolerances are relative ones
        sol = optx.minimise(
            objective, optx.BFGS(rtol=tolerance, atol=1e-3 * tolerance), z0, max_steps=steps, throw=False
        )
        z, taken, converged = sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful
    w = latent(z)
    value, mesh = objective_and_mesh(w)
    return w, taken, converged, value, mesh


@functools.partial(jax.jit, static_argnames=("model", "method", "steps", "tolerance", "free_translation"))
def _edit_jit(
    model: _Model,
    w0,
    w_ref,
    controls,
    targets,
    regularization,
    learning_rate,
    free,
    *,
    method: str,
    steps: int,
    tolerance: float,
    free_translation: bool,
) -> EditResult:
    # the optimiser works in the default float type (float64: jaxdeform enables x64) whatever the decoder's
    # dtype: optimistix keeps its own scalars in that type, and the K latents cost nothing
    latent_dtype, w0 = w0.dtype, w0.astype(jnp.result_type(float))
    w_ref = w_ref.astype(w0.dtype)  # the regularization's reference (latent0); w0 is this stage's start
    free = free.astype(w0.dtype)  # (K,) 1 = optimised in this stage, 0 = held at w0 (traced: stages share one compile)
    if model.objective == "deformation":
        w, taken, converged, objective, p = _deformation_solve(
            model, method, steps, tolerance, w0, w_ref, targets, regularization, learning_rate, free
        )
        r = p[controls] - targets
        return EditResult(
            w.astype(latent_dtype),
            p,
            jnp.zeros((3,), p.dtype),
            jnp.mean(jnp.linalg.norm(r, axis=-1)),
            objective,
            taken,
            converged,
        )
    if method == "adam":
        w, taken = _adam(
            model, free_translation, steps, w0, w_ref, controls, targets, regularization, learning_rate, free
        )
        converged = jnp.asarray(False)  # a fixed number of steps: no stopping test
    else:
        problem = _scaled(model, free_translation, tolerance, w0, w_ref, controls, targets, regularization, free)
        solve = _lm if method == "lm" else _bfgs
        z, taken, converged = solve(problem, steps, tolerance, jnp.zeros_like(w0))
        w = problem.latent(z)
    r, t, p = _control_residuals(model, free_translation, w, controls, targets)
    objective = jnp.sum(r.astype(w0.dtype) ** 2) + regularization * jnp.sum((w - w_ref) ** 2)
    return EditResult(
        w.astype(latent_dtype), p + t, t, jnp.mean(jnp.linalg.norm(r, axis=-1)), objective, taken, converged
    )


# --------------------------------------------------------------------------------------------------
# Argument checks (host side, before tracing)
# --------------------------------------------------------------------------------------------------


def _resolve_acap(acap_or_rest_faces) -> Acap:
    if isinstance(acap_or_rest_faces, Acap):
        return acap_or_rest_faces
    if isinstance(acap_or_rest_faces, (tuple, list)) and len(acap_or_rest_faces) == 2:
        rest, faces = acap_or_rest_faces
        return cached(np.asarray(rest), np.asarray(faces))
    raise EditInputError("the ACAP reference must be an Acap (jaxdeform.acap.prepare) or a (rest, faces) pair.")


def _rest_of(acap_or_rest_faces) -> np.ndarray:
    """Rest vertices (V, 3) from an Acap, a (rest, faces) pair or a bare (V, 3) array."""
    if isinstance(acap_or_rest_faces, Acap):
        return np.asarray(acap_or_rest_faces.rest)
    if isinstance(acap_or_rest_faces, (tuple, list)) and len(acap_or_rest_faces) == 2:
        return np.asarray(acap_or_rest_faces[0])
    rest = np.asarray(acap_or_rest_faces) if acap_or_rest_faces is not None else np.zeros((0,))
    if rest.ndim != 2 or rest.shape[-1] != 3:
        raise EditInputError("the rest shape must be an Acap, a (rest, faces) pair or a (V, 3) array.")
    return rest


def _check_inputs(
    decode,
    latent0,
    controls,
    targets,
    n_vertices: int,
    out_width: int,
    *,
    steps,
    learning_rate,
    regularization,
    method,
    what: str,
):
    if not callable(decode):
        raise EditInputError(f"{what} must be a callable mapping a latent vector to an array.")
    w0 = jnp.asarray(latent0)
    if w0.ndim != 1 or w0.shape[0] == 0 or not jnp.issubdtype(w0.dtype, jnp.floating):
        raise EditInputError(f"latent0 must be a non-empty 1-D float vector, got shape {w0.shape} ({w0.dtype}).")
    if not bool(jnp.all(jnp.isfinite(w0))):
        raise EditInputError("latent0 holds NaN or infinite values.")
    c = np.asarray(controls)
    if c.ndim != 1 or c.size == 0 or not np.issubdtype(c.dtype, np.integer):
        raise EditInputError(f"controls must be a non-empty 1-D integer array, got shape {c.shape} ({c.dtype}).")
    if c.min() < 0 or c.max() >= n_vertices:
        raise EditInputError(f"control indices must lie in [0, {n_vertices}), got min {c.min()} and max {c.max()}.")
    t = np.asarray(targets)
    if t.ndim != 2 or t.shape[1] != 3:
        raise EditInputError(f"targets must be an (M, 3) array, got shape {t.shape}.")
    if t.shape[0] != c.shape[0]:
        raise EditInputError(f"got {c.shape[0]} control indices but {t.shape[0]} targets.")
    if not np.all(np.isfinite(t)):
        raise EditInputError("targets hold NaN or infinite values.")
    if method not in METHODS:
        raise EditInputError(f"unknown method '{method}'; expected one of {', '.join(METHODS)}.")
    if int(steps) != steps or steps < 1:
        raise EditInputError(f"steps must be a positive integer, got {steps}.")
    if not (np.isfinite(regularization) and regularization >= 0):
        raise EditInputError(f"regularization must be finite and non-negative, got {regularization}.")
    if not (np.isfinite(learning_rate) and learning_rate > 0):
        raise EditInputError(f"learning_rate must be finite and positive, got {learning_rate}.")
    try:
        out = jax.eval_shape(decode, w0)
    except Exception as exc:  # the decoder's own error, re-raised as one sentence
        raise EditInputError(f"{what} failed on latent0 of shape {w0.shape}: {exc}") from exc
    if getattr(out, "shape", None) != (n_vertices, out_width):
        raise EditInputError(f"{what} must return ({n_vertices}, {out_width}), got {getattr(out, 'shape', out)}.")
    return w0, jnp.asarray(c, jnp.int32), t


def _default_tolerance(dtype) -> float:
    return 1e-6 if jnp.dtype(dtype) == jnp.float64 else 1e-5


def _check_stages(stages, k: int) -> tuple[int, ...]:
    """``stages`` as increasing latent-prefix sizes ending at K (None: one stage over every latent)."""
    if stages is None:
        return (k,)
    try:
        if isinstance(stages, (str, bytes)) or any(int(x) != x for x in stages):
            raise TypeError
        st = tuple(int(x) for x in stages)
    except (TypeError, ValueError):
        raise EditInputError(f"stages must be a sequence of integer latent counts, got {stages!r}.") from None
    if not st or any(b <= a for a, b in zip(st, st[1:])) or st[0] < 1 or st[-1] != k:
        raise EditInputError(f"stages must be increasing latent counts from 1 up to the latent size {k}, got {st}.")
    return st


def _run(
    model: _Model,
    w0,
    controls,
    targets,
    dtype,
    *,
    steps,
    learning_rate,
    regularization,
    method,
    tolerance,
    free_translation,
    stages=None,
) -> EditResult:
    """One edit per stage (coarse to fine): stage s optimises the first ``stages[s]`` latents from the result
    of stage s - 1, the others held; every stage calls the same compiled function (the mask is traced)."""
    k = int(w0.shape[0])
    stages = _check_stages(stages, k)
    tol = _default_tolerance(dtype) if tolerance is None else float(tolerance)
    fdtype = jnp.result_type(float)
    targets = jnp.asarray(targets, dtype)
    index = np.arange(k)
    result, taken, converged, w_ref = None, 0, True, w0
    for prefix in stages:
        free = jnp.asarray(index < prefix)
        result = _edit_jit(
            model,
            w0,
            w_ref,
            controls,
            targets,
            jnp.asarray(regularization, fdtype),
            jnp.asarray(learning_rate, fdtype),
            free,
            method=method,
            steps=int(steps),
            tolerance=tol,
            free_translation=bool(free_translation),
        )
        w0 = result.latent
        taken = taken + result.steps
        converged = converged & result.converged
    return result._replace(steps=taken, converged=converged)


def _held_controls(objective, method, controls) -> tuple[int, ...] | None:
    """Check ``objective`` (and its compatibility with ``method``) for :func:`edit`.

    Takes the objective name, the method and the checked control indices. Returns the control indices
    as a tuple of ints for the "deformation" objective (they are held at the targets), ``None`` for
    "controls". Raises :class:`EditInputError` (unknown objective, "lm" with "deformation", or repeated
    control indices under "deformation").
    """
    if objective not in OBJECTIVES:
        raise EditInputError(f"unknown objective '{objective}'; expected one of {', '.join(OBJECTIVES)}.")
    held = None
    if objective == "deformation":
        if method == "lm":
            raise EditInputError(
                "the deformation objective is not a least-squares problem in the latents; use method 'bfgs' or 'adam'."
            )
        held = tuple(int(i) for i in np.asarray(controls))
        if len(set(held)) != len(held):
            raise EditInputError(
                "the deformation objective holds each control vertex at its target: the control "
                "indices must be distinct."
            )
    return held


# --------------------------------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------------------------------


def edit(
    decode_features: Callable[[Array], Array],
    latent0: Float[Array, " k"],
    acap_or_rest_faces: Any,
    scaler: Scaler | None,
    controls: Int[Array, " m"],
    targets: Float[Array, "m 3"],
    *,
    steps: int = DEFAULT_STEPS,
    learning_rate: float = DEFAULT_LEARNING_RATE,
    regularization: float = DEFAULT_REGULARIZATION,
    method: Method = "bfgs",
    anchor: int = 0,
    refine: int = DEFAULT_REFINE,
    free_translation: bool = True,
    tolerance: float | None = None,
    stages: tuple[int, ...] | None = None,
    objective: Objective = "controls",
) -> EditResult:
    """Latent weights whose ACAP-reconstructed mesh meets ``targets`` (M, 3) at the ``controls`` (M,) vertices.

    **Arguments:** ``decode_features(w (K,)) -> (V, 9)`` ACAP features (scaled when ``scaler`` is given;
    ``scaler.inverse`` is applied before reconstruction); ``latent0`` (K,): the start. ``acap_or_rest_faces``: an
    :class:`~jaxdeform.acap.Acap` or a ``(rest, faces)`` pair. ``anchor``: vertex pinned at its rest position by the
    reconstruction (translation is then optimised in closed form unless ``free_translation=False``). ``refine``:
    defect-correction steps of :meth:`Acap.decode`. ``method``: "bfgs", "lm" or "adam" (module docstring).
    ``steps``: at most that many BFGS/LM iterations (exactly that many Adam steps, with ``learning_rate``).
    ``regularization`` weighs |w - latent0|^2 against squared control distances (length^2 per squared latent unit).
    ``tolerance``: relative (and, times the targets' spread, absolute) stopping tolerance; default 1e-6 for float64
    positions, 1e-5 for float32. ``stages``: increasing latent-prefix counts ending at K for a coarse-to-fine edit
    (module docstring); ``steps`` then applies per stage. ``objective``: "controls" (the decoded mesh's distance to
    the targets) or "deformation" (the data-driven deformation of seed 000's ref. [19]: the control vertices are
    held at the targets and the latents minimise the deformation energy; "bfgs" or "adam" only; ``anchor``,
    ``refine`` and ``free_translation`` do not apply). Pass the same ``decode_features`` object again to reuse the
    compiled editor.

    **Returns:** an :class:`EditResult`. **Raises:** :class:`EditInputError` for inconsistent arguments.
    """
    acap = _resolve_acap(acap_or_rest_faces)
    n = acap.topo.n_vertices
    if int(anchor) != anchor or not 0 <= anchor < n:
        raise EditInputError(f"the anchor vertex must lie in [0, {n}), got {anchor}.")
    if int(refine) != refine or refine < 0:
        raise EditInputError(f"refine must be a non-negative integer, got {refine}.")
    w0, c, t = _check_inputs(
        decode_features,
        latent0,
        controls,
        targets,
        n,
        9,
        steps=steps,
        learning_rate=learning_rate,
        regularization=regularization,
        method=method,
        what="decode_features",
    )
    held = _held_controls(objective, method, c)
    model = _Model(decode_features, acap, scaler, int(anchor), int(refine), str(w0.dtype), objective, held)
    # host factorisations now: they cannot happen while tracing
    acap.reconstructor(model.anchors)
    if held is not None:
        acap.reconstructor(list(held))
        acap.reconstructor(None)
    return _run(
        model,
        w0,
        c,
        t,
        acap.rest.dtype,
        steps=steps,
        learning_rate=learning_rate,
        regularization=regularization,
        method=method,
        tolerance=tolerance,
        free_translation=free_translation,
        stages=stages,
    )


def edit_positions(
    decode_positions: Callable[[Array], Array],
    latent0: Float[Array, " k"],
    controls: Int[Array, " m"],
    targets: Float[Array, "m 3"],
    *,
    steps: int = DEFAULT_STEPS,
    learning_rate: float = DEFAULT_LEARNING_RATE,
    regularization: float = DEFAULT_REGULARIZATION,
    method: Method = "bfgs",
    free_translation: bool = True,
    tolerance: float | None = None,
    stages: tuple[int, ...] | None = None,
) -> EditResult:
    """:func:`edit` for coordinate-space models: ``decode_positions(w (K,)) -> (V, 3)`` positions directly.

    Same objective, optimiser and free translation as :func:`edit`, so methods compare under one protocol.

    **Arguments:**

    - ``decode_positions``: maps latent weights ``(K,)`` to positions ``(V, 3)``.
    - ``latent0``: the starting weights ``(K,)`` (the regularization's reference).
    - ``controls``, ``targets``: the control vertices ``(M,)`` and their targets ``(M, 3)``.
    - ``steps``, ``learning_rate``, ``regularization``, ``method``, ``free_translation``, ``tolerance``, ``stages``: as
        :func:`edit`'s.

    **Returns:**

    An :class:`EditResult`.

    **Raises:**

    ``EditInputError`` if ``decode_positions`` is not a callable that gives ``(V, 3)`` from ``latent0``, or for
    inconsistent controls, targets or options.
    """
    w0 = jnp.asarray(latent0)
    if not callable(decode_positions):
        raise EditInputError("decode_positions must be a callable mapping a latent vector to an array.")
    try:
        out = jax.eval_shape(decode_positions, w0)
    except Exception as exc:
        raise EditInputError(f"decode_positions failed on latent0 of shape {w0.shape}: {exc}") from exc
    shape = getattr(out, "shape", ())
    if len(shape) != 2 or shape[1] != 3:
        raise EditInputError(f"decode_positions must return a (V, 3) array, got shape {shape}.")
    w0, c, t = _check_inputs(
        decode_positions,
        w0,
        controls,
        targets,
        shape[0],
        3,
        steps=steps,
        learning_rate=learning_rate,
        regularization=regularization,
        method=method,
        what="decode_positions",
    )
    model = _Model(decode_positions, None, None, 0, 0, str(w0.dtype))
    return _run(
        model,
        w0,
        c,
        t,
        out.dtype,
        steps=steps,
        learning_rate=learning_rate,
        regularization=regularization,
        method=method,
        tolerance=tolerance,
        free_translation=free_translation,
        stages=stages,
    )


def bounding_box_diagonal(vertices: Float[Array, "v 3"]) -> float:
    """Length of the axis-aligned bounding-box diagonal.

    **Arguments:**

    - ``vertices``: ``(V, 3)``.

    **Returns:**

    The length as a float.
    """
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))


def edit_error(
    decode: Callable[[Array], Array],
    latent0: Float[Array, " k"],
    acap_or_rest_faces: Any,
    scaler: Scaler | None,
    ground_truth: Float[Array, "v 3"],
    n_controls: int,
    *,
    space: Literal["features", "positions"] = "features",
    start: int = 0,
    **edit_kwargs,
) -> EditErrorReport:
    """The protocol of seed 000's Fig. 6 on one unseen shape.

    ``n_controls`` control vertices by furthest point sampling on the rest shape (from ``start``), targets =
    ``ground_truth`` at those vertices, one edit from ``latent0`` (the code of the rest shape), then the error
    of the whole edited mesh against ``ground_truth``.

    **Arguments:**

    - ``decode``: latent weights ``(K,)`` -> ACAP features ``(V, 9)`` (``space="features"``, :func:`edit`) or positions
        ``(V, 3)`` (``space="positions"``, :func:`edit_positions`).
    - ``latent0``: the code of the rest shape ``(K,)``.
    - ``acap_or_rest_faces``: an :class:`~jaxdeform.acap.Acap` or a ``(rest, faces)`` pair; with ``"positions"`` also a
        bare ``(V, 3)`` rest array.
    - ``scaler``: the features' scaler (ignored with ``"positions"``).
    - ``ground_truth``: the unseen shape ``(V, 3)``, finite.
    - ``n_controls``: the number of control vertices.
    - ``space``: ``"features"`` or ``"positions"``.
    - ``start``: the first furthest-point sample.
    - ``edit_kwargs``: go to the editor (steps, regularization, method, ...).

    **Returns:**

    An :class:`EditErrorReport`: mean (and RMS) vertex distance over all vertices, in units of the rest shape's
    bounding-box diagonal, and the mean control residual in the same unit, with the controls and the edit.

    **Raises:**

    ``EditInputError`` for an unknown ``space``, a ground truth of another shape or with non-finite values, and the
    editor's input errors.
    """
    if space not in ("features", "positions"):
        raise EditInputError(f"unknown space '{space}'; expected 'features' or 'positions'.")
    rest = _rest_of(acap_or_rest_faces)
    gt = np.asarray(ground_truth)
    if gt.shape != rest.shape:
        raise EditInputError(f"the ground truth must have the rest shape's shape {rest.shape}, got {gt.shape}.")
    if not np.all(np.isfinite(gt)):
        raise EditInputError("the ground truth holds NaN or infinite values.")
    controls = np.asarray(furthest_point_sampling(rest, n_controls, start))
    targets = gt[controls]
    if space == "features":
        result = edit(decode, latent0, acap_or_rest_faces, scaler, controls, targets, **edit_kwargs)
    else:
        result = edit_positions(decode, latent0, controls, targets, **edit_kwargs)
    diag = bounding_box_diagonal(rest)
    dist = np.linalg.norm(np.asarray(result.positions, np.float64) - gt, axis=-1)
    return EditErrorReport(
        mean_error=float(dist.mean() / diag),
        rms_error=float(np.sqrt(np.mean(dist**2)) / diag),
        control_error=float(result.control_error) / diag,
        diagonal=diag,
        controls=controls,
        result=result,
    )
