"""Benchmark of the seed-000 fine-tuning step (jaxdeform.components.finetune) with each reconstruction solver.

    python -m benchmarks.finetune RUN --json out/bench/finetune.json [--solvers host,dense,cg]

RUN is a multiscale or tan run folder (``jaxdeform components train``). For each solver, in the order host,
dense, cg: the solver's setup (``acap.prepare`` and the factor, ``setup_s``), the plain reconstruction of a batch
that gives the position targets (``targets``: its first call and the median of ``--repeats`` more), and the
fine-tuning step as ``finetune.fit`` runs it (``finetune.make_step``: the first call, ``compile_s``, then
``--repeats`` more, each blocked; ms per step as median and min, and the projected seconds of ``--project``
steps). Each step starts from the previous step's parameters, on batches of ``--batch`` shapes drawn from the
run's training shapes and ``--mixes`` regional mixes of them, the same draws for every solver; the first and last
position terms are recorded so the solvers can be compared on the same work. The JSON is written atomically. Not
a test: tests/test_benchmarks_smoke.py runs it once on a tiny run so it cannot rot.
"""

from __future__ import annotations

import argparse
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
from flax import nnx

from benchmarks.acap import cpu_info, device_info, parse_solvers
from jaxdeform import acap
from jaxdeform.components import finetune
from jaxdeform.components import run as crun
from jaxdeform.mesh.io import atomic_path
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import rings_from_topology


def _ms_since(t0: float) -> float:
    return 1e3 * (time.perf_counter() - t0)


def time_solver(
    run: crun.Run, pool: np.ndarray, rings, dist, solver: str, *, batch: int, repeats: int, rigid: bool, seed: int
) -> dict:
    """One solver's record (module docstring): setup, targets and steps, with ``pool`` the scaled features the
    batches are drawn from."""
    t0 = time.perf_counter()
    acap.prepare(run.rest, run.faces, solver=solver).reconstructor(None)  # uncached: the cost of a first run
    setup_s = time.perf_counter() - t0
    _, positions, _ = finetune.position_loss_fn(run, rings, dist, 1e5, rigid, solver)
    positions = jax.jit(positions)
    rng = np.random.default_rng(seed)
    draws = [rng.choice(len(pool), min(batch, len(pool)), replace=False) for _ in range(repeats + 1)]
    t0 = time.perf_counter()
    g0 = jax.block_until_ready(positions(jnp.asarray(pool[draws[0]])))
    targets_first_s = time.perf_counter() - t0
    target_ms = []
    targets = [g0]
    for idx in draws[1:]:
        t0 = time.perf_counter()
        targets.append(jax.block_until_ready(positions(jnp.asarray(pool[idx]))))
        target_ms.append(_ms_since(t0))
    opt = optax.adam(2e-4)
    step = finetune.make_step(run, rings, dist, 1e5, opt, rigid, solver)
    params = jax.tree_util.tree_map(jnp.copy, nnx.state(run.model))
    state = opt.init(params)
    terms, step_ms = [], []
    compile_s = 0.0
    for k, idx in enumerate(draws):
        t0 = time.perf_counter()
        params, state, t = jax.block_until_ready(step(params, state, jnp.asarray(pool[idx]), targets[k]))
        if k == 0:
            compile_s = time.perf_counter() - t0
        else:
            step_ms.append(_ms_since(t0))
        terms.append(np.asarray(t, np.float64).tolist())
    return {
        "solver": solver,
        "setup_s": round(setup_s, 4),
        "targets": {
            "first_s": round(targets_first_s, 3),
            "ms_median": round(statistics.median(target_ms), 2),
            "ms_min": round(min(target_ms), 2),
        },
        "compile_s": round(compile_s, 3),
        "step_ms_median": round(statistics.median(step_ms), 2),
        "step_ms_min": round(min(step_ms), 2),
        "first_terms": terms[0],
        "last_terms": terms[-1],
    }


def format_table(records: list[dict], project: int) -> str:
    head = "| solver | setup s | compile s | step ms (median) | step ms (min) | targets ms | " + f"{project} steps s |"
    rows = [head, "|---|---|---|---|---|---|---|"]
    for r in records:
        rows.append(
            f"| {r['solver']} | {r['setup_s']:.2f} | {r['compile_s']:.2f} | {r['step_ms_median']:.1f} | "
            f"{r['step_ms_min']:.1f} | {r['targets']['ms_median']:.1f} | {r['projected_s']:.0f} |"
        )
    return "\n".join(rows)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.finetune", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", metavar="RUN", help="a multiscale or tan run folder")
    parser.add_argument("--json", required=True, metavar="OUT.json")
    parser.add_argument("--data", help="the data the run was trained on (default: its folder)")
    parser.add_argument("--solvers", default="host,dense,cg", help="comma-separated solvers (default all three)")
    parser.add_argument("--repeats", type=int, default=10, help="timed steps after the first (default 10)")
    parser.add_argument("--batch", type=int, default=8, help="shapes per step (default 8, as finetune)")
    parser.add_argument("--mixes", type=int, default=64, help="regional mixes in the pool (default 64)")
    parser.add_argument("--project", type=int, default=3000, help="steps of the projected time (default 3000)")
    parser.add_argument("--rigid", action="store_true", help="the rigid position term (finetune --rigid)")
    args = parser.parse_args(argv)
    solvers = parse_solvers(args.solvers)
    if args.repeats < 1 or args.batch < 1 or args.mixes < 0:
        raise ValueError("--repeats and --batch must be positive and --mixes non-negative.")

    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)  # as the CLI runs it: the reconstruction in float64
    try:
        run = crun.load(args.run)
        finetune.check_run(run)
        vertices, _ = crun.run_data(run, args.data)
        x_train = np.asarray(crun.scaled_features(run, vertices[run.train_idx]))
        dtype = np.dtype(run.record.get("dtype", "float32"))
        dist = crun.normalized_geodesics(run.rest, run.faces, dtype)
        rng = np.random.default_rng(0)
        mixes = finetune.regional_mixes(x_train.astype(dtype), dist, args.mixes, rng) if args.mixes else None
        pool = x_train.astype(dtype) if mixes is None else np.concatenate([x_train.astype(dtype), mixes])
        rings = rings_from_topology(build_topology(run.faces, run.rest.shape[0]))
        records = []
        for solver in solvers:
            rec = time_solver(
                run,
                pool,
                rings,
                jnp.asarray(dist),
                solver,
                batch=args.batch,
                repeats=args.repeats,
                rigid=args.rigid,
                seed=1,
            )
            rec["projected_s"] = round(rec["compile_s"] + args.project * rec["step_ms_median"] / 1e3, 1)
            records.append(rec)
            print(f"{solver}: {rec['step_ms_median']:.1f} ms/step (compile {rec['compile_s']:.1f} s)", file=sys.stderr)
    finally:
        jax.config.update("jax_enable_x64", previous)
    payload = {
        "date": _dt.datetime.now().isoformat(timespec="seconds"),
        "command": "python -m benchmarks.finetune " + shlex.join(sys.argv[1:] if argv is None else list(argv)),
        "run": str(args.run),
        "method": run.method,
        "vertices": int(run.rest.shape[0]),
        "batch": args.batch,
        "rigid": args.rigid,
        "cpu": cpu_info(),
        "device": device_info(),
        "records": records,
        "table": format_table(records, args.project),
    }
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        Path(tmp).write_text(json.dumps(payload, indent=2))
    print(payload["table"])
    return payload


if __name__ == "__main__":
    main()
