"""Seed-000 training step (horse-gallop, default configuration) under formulations of the mesh convolution's
one-ring mean, timed in one process.

    python -m benchmarks.mesh_conv_xla --data ../shared/data/horse-gallop --json out/bench/mesh_conv_xla.json

Cases: ``library`` (the ring mean of :mod:`jaxdeform.nn.graph_conv` as it is) and the alternatives below (each
installed in place of ``graph_conv.ring_mean`` for its own step). Each case is compiled and run once (``compile_s``: compilation plus one step),
then the cases take turns for ``--rounds`` rounds of ``--repeats`` blocked steps, so that load from other
processes spreads over all of them; ms per step is the median (and min) over all their steps.

Formulations of mean_j x[n_ij] over the padded rings (V, K) on x (B, V, C):

- ``gather_autodiff``: one masked row gather per ring slot in the vertex-major layout (V, B C); the adjoint is
  JAX's (one scatter-add per slot);
- ``gather_bvc_custom_jvp``: the slot gathers on the V axis of (B, V, C), tangent as scatter-adds (adjoint:
  gathers);
- ``segment_sum``: the V K (vertex, slot) pairs gathered at once and summed with ``jax.ops.segment_sum``;
- ``bcoo``: a ``jax.experimental.sparse.BCOO`` (V, V) matrix with the V K pairs times the vertex-major x.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import sparse as jsparse

from jaxdeform.components import model, train
from jaxdeform.nn import graph_conv


def _vertex_major(x):
    b, v, c = x.shape
    return jnp.transpose(x, (1, 0, 2)).reshape(v, b * c)


def _from_vertex_major(y, b, c):
    return jnp.transpose(y.reshape(y.shape[0], b, c), (1, 0, 2))


def _inverse_degree(degree, dtype):
    return 1.0 / jnp.maximum(degree, 1).astype(dtype)


def gather_autodiff(x, neighbors, mask, degree):
    b, _, c = x.shape
    a = _vertex_major(x)
    acc = jnp.zeros_like(a)
    for k in range(neighbors.shape[1]):
        acc = acc + jnp.where(mask[:, k, None], a[neighbors[:, k]], 0.0)
    return _from_vertex_major(acc * _inverse_degree(degree, x.dtype)[:, None], b, c)


def _bvc_gathers(a, neighbors, mask):
    return sum(jnp.where(mask[None, :, k, None], a[:, neighbors[:, k]], 0.0) for k in range(neighbors.shape[1]))


def _bvc_scatters(t, neighbors, mask):
    acc = jnp.zeros_like(t)
    for k in range(neighbors.shape[1]):
        acc = acc.at[:, neighbors[:, k]].add(jnp.where(mask[None, :, k, None], t, 0.0))
    return acc


@jax.custom_jvp
def _bvc_mean(x, neighbors, mask, inv):
    return _bvc_gathers(x, neighbors, mask) * inv[:, None]


@_bvc_mean.defjvp
def _bvc_mean_jvp(primals, tangents):
    x, neighbors, mask, inv = primals
    return _bvc_mean(x, neighbors, mask, inv), _bvc_scatters(tangents[0], neighbors, mask) * inv[:, None]


def gather_bvc_custom_jvp(x, neighbors, mask, degree):
    return _bvc_mean(x, neighbors, mask, _inverse_degree(degree, x.dtype))


def _pairs(neighbors, mask, degree, dtype):
    v, k = neighbors.shape
    rows = jnp.broadcast_to(jnp.arange(v)[:, None], (v, k)).reshape(-1)
    weights = (mask * _inverse_degree(degree, dtype)[:, None]).reshape(-1)
    return rows, neighbors.reshape(-1), weights


def segment_sum(x, neighbors, mask, degree):
    b, v, c = x.shape
    rows, cols, w = _pairs(neighbors, mask, degree, x.dtype)
    out = jax.ops.segment_sum(_vertex_major(x)[cols] * w[:, None], rows, v, indices_are_sorted=True)
    return _from_vertex_major(out, b, c)


def bcoo(x, neighbors, mask, degree):
    b, v, c = x.shape
    rows, cols, w = _pairs(neighbors, mask, degree, x.dtype)
    matrix = jsparse.BCOO((w, jnp.stack([rows, cols], -1)), shape=(v, v), indices_sorted=True)
    return _from_vertex_major(matrix @ _vertex_major(x), b, c)


FORMULATIONS = {
    "gather_autodiff": gather_autodiff,
    "gather_bvc_custom_jvp": gather_bvc_custom_jvp,
    "segment_sum": segment_sum,
    "bcoo": bcoo,
}


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} x {os.cpu_count()}"
    except OSError:
        pass
    return platform.processor() or platform.machine()


def load(data: str):
    """(x (5, V, 9) float32 scaled features of the training split, rings, normalized geodesics)."""
    from jaxdeform import acap
    from jaxdeform.components import run as crun
    from jaxdeform.mesh import load_sequence
    from jaxdeform.mesh.topology import build_topology

    vertices, faces = load_sequence(data)
    train_idx, _ = crun.split_indices(vertices.shape[0])
    rest = vertices[0]
    feats = np.asarray(acap.encode(rest, faces, vertices[train_idx]), np.float32)
    x = jnp.asarray(np.asarray(acap.Scaler.fit(feats).transform(feats), np.float32))
    dist = jnp.asarray(crun.normalized_geodesics(rest, faces), jnp.float32)
    return x, graph_conv.rings_from_topology(build_topology(faces, rest.shape[0])), dist


class _Case:
    """One formulation's step, its state carried from call to call (each call continues the training)."""

    def __init__(self, name, x, rings, dist):
        self.name, self.x = name, x
        cfg, tc = model.Config(), train.TrainConfig()
        with self._installed():
            m = model.Model(x.shape[1], cfg, key=jax.random.PRNGKey(0), dtype=x.dtype)
            self.step = train.make_step(m, tc, rings, dist)
            states = train.level_states(m)
            self.state = [states, train.optimizer(tc).init(states), jax.random.PRNGKey(1)]
            t0 = time.perf_counter()
            self.loss = self()
            self.compile_s = time.perf_counter() - t0
        self.times: list[float] = []

    def _installed(self):
        name = self.name

        class Ctx:
            def __enter__(self):
                self.saved = graph_conv.ring_mean
                if name in FORMULATIONS:
                    graph_conv.ring_mean = FORMULATIONS[name]

            def __exit__(self, *exc):
                graph_conv.ring_mean = self.saved

        return Ctx()

    def __call__(self) -> float:
        out = jax.block_until_ready(self.step(*self.state, self.x))
        self.state[:] = out[:3]
        return float(out[3])

    def run(self, repeats: int) -> None:
        with self._installed():
            for _ in range(repeats):
                t0 = time.perf_counter()
                self()
                self.times.append(1e3 * (time.perf_counter() - t0))

    def record(self) -> dict:
        return {
            "case": self.name,
            "compile_s": round(self.compile_s, 2),
            "step_ms_median": round(statistics.median(self.times), 1),
            "step_ms_min": round(min(self.times), 1),
            "steps_timed": len(self.times),
            "first_loss": self.loss,
        }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--json", required=True)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument(
        "--cases", nargs="+", default=None, help="cases to time (default: library and every formulation)"
    )
    args = parser.parse_args(argv)
    cases = args.cases or ["library", *FORMULATIONS]
    x, rings, dist = load(args.data)
    runs = [_Case(name, x, rings, dist) for name in cases]
    for _ in range(args.rounds):
        for case in runs:
            case.run(args.repeats)
    records = [case.record() for case in runs]
    for rec in records:
        print(json.dumps(rec), flush=True)
    payload = {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": " ".join([sys.executable, "-m", "benchmarks.mesh_conv_xla", *(argv or sys.argv[1:])]),
        "cpu": cpu_model(),
        "jax": jax.__version__,
        "vertices": int(x.shape[1]),
        "shapes": int(x.shape[0]),
        "ring_slots": int(rings.neighbors.shape[1]),
        "dtype": "float32",
        "records": records,
    }
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(payload, indent=2))
    tmp.replace(out)
    return payload


if __name__ == "__main__":
    main()
