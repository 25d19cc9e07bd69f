"""Whose error is the test error: the encoder's, or the decoders' (the components')? Fit the codes of each unseen
shape through a trained autoencoder run's decoders.

    python -m experiments.components.projection RUN [--data DATA] [--space features|positions] [--steps 300]
                                                    [--lr 0.02] [--json OUT.json]

The generalization protocol reconstructs an unseen shape as decode(encode(x)). Here the codes of every level
start at encode(x) and are then fitted, the decoders' parameters fixed, in one of two spaces:

- ``features`` (default): Adam (``--steps``, ``--lr``) on the squared error of decode(codes) against x in the
  scaled ACAP features, the decoders' own training objective;
- ``positions``: L-BFGS (scipy, ``--steps`` iterations) on the mean squared distance of the mesh the ACAP
  reconstruction makes of decode(codes) (differentiable, one prefactored solve) to the unseen shape's vertices,
  with the translation free (the fit solves without the refinement step, the scores use the protocol's
  reconstruction). This is how PCA and SPLOCS in coordinates treat an unseen shape (a least-squares
  fit of their weights to it) and what editing does with a few vertices.

If the fitted codes reach a much lower error, the encoder generalizes worse than the components could; if not,
the unseen shapes lie outside what the decoders can produce. Both are scored by the protocol's own metrics
(``components.run.set_metrics``: Erms, STED, relative squared error). Prints progress and writes the JSON
atomically.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from experiments.components.common import write_text
from jaxdeform.components import run as crun
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import Rings, rings_from_topology
from jaxdeform.nn.host import host_scalars


def fit_codes(m, rings: Rings, x, codes0, *, steps: int = 300, lr: float = 0.02, log=None) -> tuple[tuple, np.ndarray]:
    """Codes (one array per level) fitted by Adam from ``codes0`` so that the decoders of model ``m`` reproduce ``x``
    (N, V, 9);
    returns them and the loss (sum of squared feature errors) before each step."""

    def loss(codes):
        return jnp.sum((m.decode_latents(codes, rings) - x) ** 2)

    opt = optax.adam(lr)

    @jax.jit
    def step(codes, state):
        value, grad = jax.value_and_grad(loss)(codes)
        updates, state = opt.update(grad, state, codes)
        return optax.apply_updates(codes, updates), state, value

    codes = tuple(codes0)
    state = opt.init(codes)
    losses = []
    for i in range(steps):
        codes, state, value = step(codes, state)
        losses.append(value)
        if log is not None and i % 25 == 0:
            log(i, float(value))
    return codes, host_scalars(losses)


def fit_positions(m, rings: Rings, run, ref, codes0, *, iterations: int = 150, log=None) -> tuple[tuple, np.ndarray]:
    """Codes fitted by L-BFGS from ``codes0`` so that the ACAP reconstruction of model ``m``'s decoders matches the
    vertices ``ref`` (N, V, 3) up to a translation per shape; returns them and the loss (mean squared vertex
    distance) at the start and after each iteration."""
    import scipy.optimize

    from jaxdeform import acap

    machinery = acap.cached(run.rest, run.faces)
    machinery.reconstructor(None)  # factorized on the host now, not inside the trace below
    w0, unflatten = ravel_pytree(tuple(codes0))  # unflatten casts back to the codes' dtype
    target = jnp.asarray(ref, jnp.float64)
    scale = 1.0 / float(np.mean(np.sum((ref - ref.mean(axis=1, keepdims=True)) ** 2, -1)))  # loss ~ 1 at the start

    def loss(w):
        features = run.scaler.inverse(m.decode_latents(unflatten(w), rings)).astype(jnp.float64)
        d = machinery.decode(features, refine=0) - target
        d = d - jnp.mean(d, axis=1, keepdims=True)
        return jnp.mean(jnp.sum(d * d, -1)) * scale

    value_and_grad = jax.jit(jax.value_and_grad(loss))
    last = {}  # the latest evaluation: the callback reads the accepted point's loss from it instead of recomputing

    def fun(w):
        value, grad = value_and_grad(jnp.asarray(w))
        last.update(w=np.array(w), value=float(value))
        return last["value"], np.asarray(grad, np.float64)

    losses = []

    def callback(w):
        losses.append((last["value"] if np.array_equal(w, last["w"]) else fun(w)[0]) / scale)
        if log is not None and len(losses) % 25 == 0:
            log(len(losses) - 1, losses[-1])

    w0 = np.asarray(w0, np.float64)
    losses.append(fun(w0)[0] / scale)  # the start, then one entry per iteration
    res = scipy.optimize.minimize(
        fun, w0, jac=True, method="L-BFGS-B", callback=callback, options=dict(maxiter=iterations, ftol=0.0, gtol=0.0)
    )
    return unflatten(jnp.asarray(res.x)), np.asarray(losses)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a trained multiscale or tan run (jaxdeform components train)")
    parser.add_argument("--data", help="the run's data set (default: the folder it was trained on)")
    parser.add_argument(
        "--space",
        choices=("features", "positions"),
        default="features",
        help="fit the codes to the scaled features (Adam) or to the vertices through the ACAP reconstruction (L-BFGS)",
    )
    parser.add_argument("--steps", type=int, default=300, help="Adam steps (features) or L-BFGS iterations")
    parser.add_argument("--lr", type=float, default=0.02)
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args(argv)
    run = crun.load(Path(args.run))
    if run.method not in crun.AUTOENCODERS:
        raise SystemExit(f"{args.run}: a {run.method} run has no decoders to fit codes through.")
    vertices, faces = crun.run_data(run, args.data)
    ref = vertices[run.test_idx]
    x = crun.scaled_features(run, ref)
    rings = rings_from_topology(build_topology(faces, run.rest.shape[0]))
    codes0 = tuple(run.model.encode(x, rings))
    t0 = time.perf_counter()
    if args.space == "features":
        codes, losses = fit_codes(
            run.model,
            rings,
            x,
            codes0,
            steps=args.steps,
            lr=args.lr,
            log=lambda i, v: print(f"step {i}: feature loss {v:.6g}", flush=True),
        )
    else:
        codes, losses = fit_positions(
            run.model,
            rings,
            run,
            ref,
            codes0,
            iterations=args.steps,
            log=lambda i, v: print(f"iteration {i}: mean squared distance {v:.6g}", flush=True),
        )
    fit_s = time.perf_counter() - t0
    result = {
        "run": str(args.run),
        "test_shapes": int(ref.shape[0]),
        "space": args.space,
        "steps": args.steps,
        "lr": args.lr if args.space == "features" else None,
        "fit_s": round(fit_s, 1),
    }
    for name, c in (("encoder", codes0), ("fitted", codes)):
        xh = run.model.decode_latents(c, rings)
        rec = {"positions": crun.positions_from_scaled(run, xh), "scaled": np.asarray(x), "scaled_hat": np.asarray(xh)}
        met = crun.set_metrics(ref, rec, faces)
        met["feature_loss"] = float(jnp.sum((xh - x) ** 2))
        result[name] = met
        print(
            f"{name} codes: test Erms {met['erms']:.3f}, STED {met['sted']:.4f}, max relative squared error "
            f"{met['max_relative_squared_error']:.5f}, feature loss {met['feature_loss']:.6g}",
            flush=True,
        )
    result["loss_history"] = losses[:: max(1, len(losses) // 100)].tolist()
    if args.json:
        write_text(Path(args.json), json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
