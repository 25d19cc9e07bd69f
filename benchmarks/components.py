"""Benchmark of the seed-000 training step (jaxdeform.components.train) on a mesh sequence.

    python -m benchmarks.components --data ../shared/data/horse-gallop --json out/bench/components.json

For each configuration (multiscale default Kz = [10, 5]; multiscale one level; Tan et al. 50 components) on
the training split of ``--data`` (every 10th shape): the first call of the jitted step (``compile_s``:
compilation plus one step) and ``--repeats`` further steps, each blocked; ms per step (= per epoch: the horse
split of 5 shapes fits one batch) as median and min, and the projected time of the configuration's full
training (``epochs`` x median); with ``--loop N``, N more steps dispatched back to back without blocking, as the training
loop runs them (wall and process CPU ms per step); with ``--breakdown``, the parts of each multiscale step timed alone
(:func:`breakdown`). The JSON is written atomically. Not a test: tests/test_benchmarks_smoke.py
only runs it once on a tiny sequence so it cannot rot.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import shlex
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from benchmarks.acap import cpu_info
from jaxdeform import acap
from jaxdeform.components import model, train
from jaxdeform.components import run as crun
from jaxdeform.mesh import load_sequence
from jaxdeform.mesh.io import atomic_path
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn import xla
from jaxdeform.nn.graph_conv import rings_from_topology

CASES = (("multiscale", "default"), ("multiscale", "levels1"), ("tan", "default"))


def _timed(call, args, repeats: int) -> tuple[float, list[float], tuple]:
    """Compile ``call`` on ``args`` (the first call), then time ``repeats`` more calls. Returns (compile seconds,
    per-call ms, the last result)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(call(*args))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(call(*args))
        times.append(1e3 * (time.perf_counter() - t0))
    return compile_s, times, out


def time_step(x, rings, dist, cfg: model.Config, tc: train.TrainConfig, repeats: int, loop: int = 0) -> dict:
    m = model.Model(x.shape[1], cfg, key=jax.random.PRNGKey(0), dtype=x.dtype)
    states = train.level_states(m)
    opt_state = train.optimizer(tc).init(states)
    step = train.make_step(m, tc, rings, dist)
    state = [states, opt_state, jax.random.PRNGKey(1)]

    def threaded(*_):  # every call continues the training from the previous call's parameters
        out = step(*state, x)
        state[:] = out[:3]
        return out

    compile_s, times, (_, _, _, loss, _) = _timed(threaded, (), repeats)
    med = statistics.median(times)
    rec = {
        "compile_s": round(compile_s, 3),
        "step_ms_median": round(med, 2),
        "step_ms_min": round(min(times), 2),
        "epochs": tc.epochs,
        "projected_training_min": round(tc.epochs * med / 6e4, 2),
        "loss_finite": bool(np.isfinite(float(loss))),
    }
    if loop > 0:  # steps dispatched back to back, as the training loop runs them: wall and process CPU time
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(loop):
            threaded()
        jax.block_until_ready(state)
        rec["loop_steps"] = loop
        rec["loop_ms_per_step"] = round(1e3 * (time.perf_counter() - t0) / loop, 2)
        rec["loop_cpu_ms_per_step"] = round(1e3 * (time.process_time() - c0) / loop, 2)
    return rec


def _median_ms(fn, args, repeats: int) -> float:
    return round(statistics.median(_timed(fn, args, repeats)[1]), 2)


def breakdown(x, rings, dist, cfg: model.Config, tc: train.TrainConfig, repeats: int) -> dict:
    """Median ms of the parts of the step, each compiled alone with the step's compiler options: the loss
    (forward), loss and gradient, Adam's update, the group-sparsity terms with their gradient, and level 0 alone."""
    m = model.Model(x.shape[1], cfg, key=jax.random.PRNGKey(0), dtype=x.dtype)
    params = tuple(m.levels)  # nnx Modules are pytrees: jax.grad and optax take the levels as they are
    opt = train.optimizer(tc)
    opt_state = opt.init(params)
    jit = lambda f: jax.jit(f, compiler_options=xla.compiler_options())  # noqa: E731
    loss = lambda p, c=cfg: model.forward_levels(p, x, rings, dist, c).loss  # noqa: E731
    grads = jit(jax.grad(loss))(params)

    def adam(g, state, p):
        updates, state = opt.update(g, state, p)
        return optax.apply_updates(p, updates), state

    def sparsity(p):
        return sum(jnp.sum(model.level_sparsity(q, dist, cfg, level)) for level, q in enumerate(p))

    level0 = dataclasses.replace(cfg, kz=cfg.kz[:1], d=cfg.d[:1])
    return {
        "forward_ms": _median_ms(jit(loss), (params,), repeats),
        "loss_and_gradient_ms": _median_ms(jit(jax.value_and_grad(loss)), (params,), repeats),
        "adam_ms": _median_ms(jit(adam), (grads, opt_state, params), repeats),
        "sparsity_and_gradient_ms": _median_ms(jit(jax.value_and_grad(sparsity)), (params,), repeats),
        "level0_loss_and_gradient_ms": _median_ms(
            jit(jax.value_and_grad(lambda p: loss(p, level0))), (params[:1],), repeats
        ),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--json", required=True)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--cases", nargs="+", default=[f"{m}:{c}" for m, c in CASES], metavar="METHOD:CONFIG")
    parser.add_argument(
        "--loop",
        type=int,
        default=0,
        metavar="N",
        help="also time N steps dispatched back to back, unblocked, as the training loop runs them",
    )
    parser.add_argument(
        "--breakdown",
        action="store_true",
        help="also time the parts of each multiscale step (forward, gradient, Adam, sparsity, level 0)",
    )
    args = parser.parse_args(argv)
    vertices, faces = load_sequence(args.data)
    train_idx, _ = crun.split_indices(vertices.shape[0])
    rest = vertices[0]
    feats = np.asarray(acap.encode(rest, faces, vertices[train_idx]), np.float32)
    x = jnp.asarray(np.asarray(acap.Scaler.fit(feats).transform(feats), np.float32))
    t0 = time.perf_counter()
    dist = jnp.asarray(crun.normalized_geodesics(rest, faces))
    geodesics_s = time.perf_counter() - t0
    rings = rings_from_topology(build_topology(faces, rest.shape[0]))
    records = []
    for case in args.cases:
        method, name = case.split(":")
        cfg, tc = crun.resolve_config(method, name)
        rec = {
            "method": method,
            "config": name,
            "vertices": int(rest.shape[0]),
            "shapes": int(x.shape[0]),
            "blocks": [cfg.blocks(level) for level in range(cfg.levels)],
            "dtype": "float32",
            "device": jax.devices()[0].platform,
            "cpu": cpu_info(),
        }
        rec.update(time_step(x, rings, dist, cfg, tc, args.repeats, args.loop))
        if args.breakdown and method == "multiscale":
            rec["breakdown"] = breakdown(x, rings, dist, cfg, tc, args.repeats)
        print(json.dumps(rec), flush=True)
        records.append(rec)
    payload = {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": " ".join(
            shlex.quote(a) for a in [sys.executable, "-m", "benchmarks.components"] + list(argv or sys.argv[1:])
        ),
        "geodesics_s": round(geodesics_s, 2),
        "records": records,
    }
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        Path(tmp).write_text(json.dumps(payload, indent=2))
    return payload


if __name__ == "__main__":
    main()
