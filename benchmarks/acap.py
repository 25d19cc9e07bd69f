"""Benchmark of the ACAP encoder/decoder (jaxdeform.acap) and its three reconstruction solvers, on a mesh
sequence and on a subdivided large mesh.

    python -m benchmarks.acap --data ../shared/data/horse-gallop --json out/bench/acap.json

Cases, all in one run, each in float32 and float64 (``--no-float64``: float32 only):

1. ``dataset``: every frame of ``--data`` (reference = first file);
2. ``big``: the first ``--big-frames`` frames, Loop-subdivided (``igl.loop``, the same topology operation
   on every frame) until the mesh has at least ``--big-vertices`` vertices (``--skip-big`` leaves it out).

Each case is reconstructed by every solver of ``--solvers`` (``acap.prepare(..., solver=...)``: "host",
"dense", "cg"), one record per (case, dtype, solver), beside the bare cholespy solve of the same system
measured in the same run. The dense solver is skipped (a record with ``skipped`` and the reason) above
``reconstruct.DENSE_MAX_VERTICES`` vertices; conjugate gradients on the big case decode only the first
``--big-cg-frames`` frames with at most ``--big-cg-repeats`` timed calls.

Timings: one first call (``compile_s``: compilation plus any one-off warm-up), then ``--repeats`` timed
calls, each fully blocked (``jax.block_until_ready``) and batched over all frames; per-frame = call time /
frames. The JSON (``{"date", "command", ..., "records": [...]}``) is written atomically; the fields are
described in benchmarks/README.md. Benchmarks are not tests: pytest never runs this file (only a tiny smoke
run in tests/test_benchmarks_smoke.py keeps it working).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import resource
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxdeform import acap
from jaxdeform.acap import reconstruct
from jaxdeform.mesh import load_sequence

# Auto chunking: at most this many vertex-frames per encode/decode call (the temporal encode is never
# chunked: its consistency runs along the whole sequence).
CHUNK_VERTEX_FRAMES = 2_000_000
SOLVE_MIN_REPEATS = 10


# --------------------------------------------------------------------------------------------------
# machine and data
# --------------------------------------------------------------------------------------------------


def cpu_info() -> str:
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{model} x {os.cpu_count()}"


def device_info() -> dict:
    d = jax.devices()[0]
    return {"platform": d.platform, "name": str(d)}


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def subdivide(frames: np.ndarray, faces: np.ndarray, min_vertices: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Loop-subdivide every frame (same connectivity) until it has >= ``min_vertices`` vertices.

    ``igl.loop`` subdivides one mesh's positions; the new faces depend only on the connectivity, so they
    are the same for every frame (checked). Returns (frames (N, V', 3) float64, faces int32, levels).
    """
    import igl

    verts = np.asarray(frames, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    levels = 0
    while verts.shape[1] < min_vertices:
        outs = [igl.loop(np.ascontiguousarray(v), f) for v in verts]
        f_new = np.asarray(outs[0][1], dtype=np.int64)
        for k, (_, fk) in enumerate(outs[1:], start=1):
            if not np.array_equal(fk, f_new):
                raise RuntimeError(f"igl.loop gave different faces for frame {k}: cannot build a sequence.")
        verts = np.stack([np.asarray(v) for v, _ in outs])
        f = np.ascontiguousarray(f_new)
        levels += 1
    return verts, f.astype(np.int32), levels


def skip_reason(solver: str, n_vertices: int) -> str | None:
    """Why ``solver`` is not benchmarked on a mesh of ``n_vertices`` vertices (None: it is)."""
    if solver == "dense" and n_vertices > reconstruct.DENSE_MAX_VERTICES:
        return (
            f"dense solver needs a {n_vertices} x {n_vertices} matrix; benchmarked only up to "
            f"reconstruct.DENSE_MAX_VERTICES = {reconstruct.DENSE_MAX_VERTICES} vertices"
        )
    return None


def parse_solvers(text: str) -> list[str]:
    """Comma-separated solver names -> list in the order of ``reconstruct.SOLVERS`` (ValueError if unknown)."""
    names = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in names if s not in reconstruct.SOLVERS]
    if unknown or not names:
        raise ValueError(
            f"--solvers: expected a comma-separated subset of {','.join(reconstruct.SOLVERS)}, got '{text}'"
        )
    return [s for s in reconstruct.SOLVERS if s in names]


# --------------------------------------------------------------------------------------------------
# timing
# --------------------------------------------------------------------------------------------------


def timed(fn, repeats: int):
    """(output of the first call, first-call seconds, [seconds of each timed call]), every call blocked."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return out, first, times


def timed_paired(fn, bare, repeats: int):
    """Like :func:`timed`, with ``bare()`` timed right after each timed call of ``fn`` (same machine load).

    Returns (first output, first-call seconds, [seconds of each fn call], [seconds of each bare call]).
    """
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    calls, bares = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        calls.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        bare()
        bares.append(time.perf_counter() - t0)
    return out, first, calls, bares


def summary(first: float, times: list[float], frames: int, **extra) -> dict:
    per = [1e3 * t / frames for t in times]
    return {
        "compile_s": round(first, 4),
        "per_frame_ms_median": round(statistics.median(per), 4),
        "per_frame_ms_min": round(min(per), 4),
        "call_s_median": round(statistics.median(times), 4),
        "call_ms_median": round(1e3 * statistics.median(times), 4),
        **extra,
    }


def method_timer():
    """Wrap ``Reconstructor.with_method`` (the solver set-up that ``acap.prepare`` ends with: the cholespy
    factor for "host", the XLA Cholesky factor, compilation included, for "dense", nothing for "cg").

    Returns (restore(), seconds list): one entry per call made while wrapped.
    """
    cls = reconstruct.Reconstructor
    original = cls.__dict__["with_method"]
    seconds: list[float] = []

    def wrapped(self, *args, **kwargs):
        t0 = time.perf_counter()
        rec = jax.block_until_ready(original(self, *args, **kwargs))
        seconds.append(time.perf_counter() - t0)
        return rec

    cls.with_method = wrapped

    def restore():
        cls.with_method = original

    return restore, seconds


def bbox_diagonal(rest: np.ndarray) -> float:
    rest = np.asarray(rest, np.float64)
    return float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))


def roundtrip_error(frames: np.ndarray, decoded: np.ndarray, rest: np.ndarray) -> dict:
    """Vertex error after removing each frame's mean translation, relative to the reference bbox diagonal."""
    x = np.asarray(frames, np.float64)
    y = np.asarray(decoded, np.float64)
    x = x - x.mean(axis=1, keepdims=True)
    y = y - y.mean(axis=1, keepdims=True)
    err = np.linalg.norm(y - x, axis=-1) / bbox_diagonal(rest)
    return {"mean_rel": float(err.mean()), "max_rel": float(err.max()), "finite": bool(np.all(np.isfinite(y)))}


def first_frames(chunks: list, k: int) -> list:
    """The chunks cut down to their first ``k`` frames in total."""
    out, left = [], k
    for c in chunks:
        if left <= 0:
            break
        out.append(c[:left])
        left -= c.shape[0]
    return out


def merged_info(infos) -> dict:
    """``SolveInfo`` of several decode calls -> {"converged": all, "steps": max}."""
    return {"converged": bool(all(bool(i.converged) for i in infos)), "steps": int(max(int(i.steps) for i in infos))}


# --------------------------------------------------------------------------------------------------
# one case: shared encodes, then one record per solver
# --------------------------------------------------------------------------------------------------


def bench_case(
    case: str,
    frames: np.ndarray,
    faces: np.ndarray,
    dtype,
    repeats: int,
    chunk_frames: int = 0,
    solvers=reconstruct.SOLVERS,
    cg_frames: int | None = None,
    cg_repeats: int | None = None,
    log=print,
) -> list[dict]:
    """Benchmark one sequence: encodes once, then prepare / decode / bare solve for each of ``solvers``.

    Returns one record per solver (a ``skipped`` record for a solver not run on this size).
    ``cg_frames`` / ``cg_repeats``: the conjugate gradients' decode uses only the first ``cg_frames``
    frames and at most ``cg_repeats`` timed calls (None: all frames, ``repeats``).
    """
    load_before = os.getloadavg()[0]
    dtype = np.dtype(dtype)
    frames = np.ascontiguousarray(frames, dtype=dtype)
    n, v = frames.shape[:2]
    rest = frames[0]
    diag = bbox_diagonal(rest)
    if chunk_frames <= 0:
        chunk_frames = max(1, CHUNK_VERTEX_FRAMES // v)
    chunks = np.array_split(frames, math.ceil(n / chunk_frames))
    chunk_frames = max(c.shape[0] for c in chunks)
    log(
        f"[{case} {dtype.name}] {v} vertices, {faces.shape[0]} faces, {n} frames "
        f"({len(chunks)} chunk(s) of <= {chunk_frames} frames); solvers {', '.join(solvers)}"
    )

    # Cold set-up, solver-free ("cg" builds no factor): pays JAX's compilation of the reference-frame
    # program for this shape and dtype, so each solver's prepare below is the set-up work alone.
    t0 = time.perf_counter()
    a0 = acap.prepare(rest, faces, solver="cg")
    jax.block_until_ready(a0)
    prepare_cold_s = time.perf_counter() - t0
    log(f"  prepare (cold, solver-free) {prepare_cold_s:.3f} s")

    # encodes: independent of the solver, measured once and reported in every solver's record
    dev_chunks = [jnp.asarray(c) for c in chunks]
    _, first, times = timed(lambda: [a0.local(c) for c in dev_chunks], repeats)
    enc_local = summary(first, times, n, consistency="none")
    log(f"  encode_local  {enc_local['per_frame_ms_median']:.3f} ms/frame")
    _, first, times = timed(lambda: [a0.encode(c, "spatial") for c in chunks], repeats)
    enc = summary(first, times, n, consistency="spatial")
    log(f"  encode        {enc['per_frame_ms_median']:.3f} ms/frame")
    # the features decoded below (and used for the round trip) come from one more, untimed, call
    feats = [a0.encode(c, "spatial") for c in chunks]
    _, first, times = timed(lambda: a0.encode(frames, "temporal"), repeats)
    enc_t = summary(first, times, n, consistency="temporal", chunked=False)
    log(f"  encode_temp.  {enc_t['per_frame_ms_median']:.3f} ms/frame")

    # The bare cholespy solve of the same system: its own factor of the host solver's matrix.
    t0 = time.perf_counter()
    bare = reconstruct.HostCholesky.build(a0.rec.matrix())
    bare_factor_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    b3 = rng.standard_normal((v, 3))
    reconstruct.solve_factor(bare.key, b3)  # warm-up
    solve_times = []
    for _ in range(max(repeats, SOLVE_MIN_REPEATS)):
        t0 = time.perf_counter()
        reconstruct.solve_factor(bare.key, b3)
        solve_times.append(time.perf_counter() - t0)
    solve3_ms = 1e3 * statistics.median(solve_times)
    log(f"  bare cholespy: factor {bare_factor_s:.3f} s, solve (V, 3) {solve3_ms:.3f} ms")

    shared = {
        "vertices": int(v),
        "faces": int(faces.shape[0]),
        "dtype": dtype.name,
        "device": device_info(),
        "cpu": cpu_info(),
        "chunk_frames": int(chunk_frames),
    }
    # The host solver's positions, that the other solvers are compared with: its own decode where "host" is
    # benchmarked (it runs first), else an untimed decode with the bare factor.
    host_positions = None
    if "host" not in solvers:
        ref_acap = eqx.tree_at(lambda a: a.rec.method, a0, bare)
        host_positions = np.concatenate([np.asarray(ref_acap.decode(f)) for f in feats], axis=0)
    records = []
    for solver in sorted(solvers, key=reconstruct.SOLVERS.index):
        reason = skip_reason(solver, v)
        if reason is not None:
            log(f"  [{solver}] skipped: {reason}")
            records.append({"case": case, "solver": solver, **shared, "frames": int(n), "skipped": reason})
            continue
        record, decoded = _bench_solver(
            case,
            solver,
            shared,
            rest,
            faces,
            frames,
            feats,
            host_positions,
            diag,
            bare.key,
            solve3_ms,
            bare_factor_s,
            prepare_cold_s,
            enc,
            enc_local,
            enc_t,
            repeats,
            cg_frames,
            cg_repeats,
            load_before,
            log,
        )
        if solver == "host":
            host_positions = decoded
        records.append(record)
    return records


def _bench_solver(
    case,
    solver,
    shared,
    rest,
    faces,
    frames,
    feats,
    host_positions,
    diag,
    bare_key,
    solve3_ms,
    bare_factor_s,
    prepare_cold_s,
    enc,
    enc_local,
    enc_t,
    repeats,
    cg_frames,
    cg_repeats,
    load_before,
    log,
) -> tuple[dict, np.ndarray]:
    """One solver's record, and its decoded positions (host_positions None: this solver is the reference)."""
    n_all = frames.shape[0]
    restore, method_s = method_timer()
    try:
        t0 = time.perf_counter()
        a = acap.prepare(rest, faces, solver=solver)
        jax.block_until_ready(a)
        prepare_s = time.perf_counter() - t0
    finally:
        restore()
    if a.rec.solver != solver:
        raise RuntimeError(f"acap.prepare(solver='{solver}') gave a '{a.rec.solver}' reconstructor")
    factor_s = method_s[-1] if method_s else None

    n, reps = n_all, repeats
    if solver == "cg":
        n = n_all if cg_frames is None else max(1, min(cg_frames, n_all))
        reps = repeats if cg_repeats is None else max(1, min(cg_repeats, repeats))
    f_used = first_frames(feats, n)
    rhs = [np.random.default_rng(1).standard_normal((f.shape[-2], 3 * f.shape[0])) for f in f_used]

    def bare_all():
        for b in rhs:
            reconstruct.solve_factor(bare_key, b)

    bare_all()  # warm-up
    log(
        f"  [{solver}] prepare {prepare_s:.3f} s (solver set-up {factor_s:.3f} s); decoding {n} frame(s), "
        f"{reps} timed call(s)"
    )

    outs, first, calls, bares = timed_paired(lambda: [a.decode_info(f) for f in f_used], bare_all, reps)
    solve_all_ms = 1e3 * statistics.median(bares)
    dec = summary(first, calls, n, solves=merged_info([i for _, i in outs]))
    dec_ratio = dec["call_ms_median"] / solve_all_ms if solve_all_ms > 0 else None
    dec_paired = statistics.median(c / b for c, b in zip(calls, bares))
    log(
        f"  [{solver}] decode        {dec['call_ms_median']:.3f} ms/call, {dec['per_frame_ms_median']:.3f} ms/frame, "
        f"steps {dec['solves']['steps']}, converged {dec['solves']['converged']}; bare solve {solve_all_ms:.3f} ms, "
        f"ratio {dec_ratio:.2f} (paired {dec_paired:.2f})"
    )

    outs0, first, calls0, bares0 = timed_paired(lambda: [a.decode_info(f, refine=0) for f in f_used], bare_all, reps)
    dec0 = summary(first, calls0, n, solves=merged_info([i for _, i in outs0]))
    solve_all0_ms = 1e3 * statistics.median(bares0)
    dec0_ratio = dec0["call_ms_median"] / solve_all0_ms if solve_all0_ms > 0 else None
    dec0_paired = statistics.median(c / b for c, b in zip(calls0, bares0))
    log(
        f"  [{solver}] decode plain  {dec0['call_ms_median']:.3f} ms/call, {dec0['per_frame_ms_median']:.3f} ms/frame "
        f"(refine=0), steps {dec0['solves']['steps']}; ratio {dec0_ratio:.2f} (paired {dec0_paired:.2f})"
    )

    decoded = np.concatenate([np.asarray(p) for p, _ in outs], axis=0)
    rt = roundtrip_error(frames[:n], decoded, rest)
    deviation = None
    if host_positions is not None:
        dev = np.linalg.norm(decoded.astype(np.float64) - host_positions[:n].astype(np.float64), axis=-1)
        deviation = float(np.max(dev)) / diag
    if decoded.dtype != frames.dtype:
        log(f"  note: decode returned {decoded.dtype} for {frames.dtype.name} input")
    log(
        f"  [{solver}] round trip max {rt['max_rel']:.2e}, max deviation from host {_opt('.2e', deviation)} "
        "(bbox diagonal)"
    )
    record = {
        "case": case,
        "solver": solver,
        **shared,
        "frames": int(n),
        "frames_in_case": int(n_all),
        "repeats": int(reps),
        "prepare_s": round(prepare_s, 4),
        "prepare_cold_s": round(prepare_cold_s, 4),
        "solver_setup_s": None if factor_s is None else round(factor_s, 4),
        "cholespy_factor_s": round(bare_factor_s, 4),
        "encode": enc,
        "encode_local": enc_local,
        "encode_temporal": enc_t,
        "decode": dec,
        "decode_plain": dec0,
        "cholespy_solve_3rhs_ms": round(solve3_ms, 4),
        "cholespy_solve_all_ms": round(solve_all_ms, 4),
        "decode_over_solve": None if dec_ratio is None else round(dec_ratio, 3),
        "decode_over_solve_paired": round(dec_paired, 3),
        "decode_plain_over_solve": None if dec0_ratio is None else round(dec0_ratio, 3),
        "decode_plain_over_solve_paired": round(dec0_paired, 3),
        "cg_steps": dec["solves"]["steps"] if solver == "cg" else None,
        "cg_converged": dec["solves"]["converged"] if solver == "cg" else None,
        "roundtrip": rt,
        "max_dev_from_host": deviation,
        "output_dtype": {"features": str(feats[0].dtype), "decoded": str(decoded.dtype)},
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "load_avg_1m": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }
    a = None  # noqa: F841  (releases the Acap and its host factor before the next solver)
    return record, decoded


# --------------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------------


def _opt(fmt: str, value) -> str:
    return "-" if value is None else format(value, fmt)


_COLUMNS = [
    ("case", 7, lambda r: r["case"]),
    ("solver", 6, lambda r: r["solver"]),
    ("dtype", 7, lambda r: r["dtype"]),
    ("V", 7, lambda r: f"{r['vertices']}"),
    ("N", 3, lambda r: f"{r['frames']}"),
    ("prep s", 7, lambda r: f"{r['prepare_s']:.3f}"),
    ("setup s", 7, lambda r: _opt(".3f", r["solver_setup_s"])),
    ("enc", 7, lambda r: f"{r['encode']['per_frame_ms_median']:.3f}"),
    ("dec call", 9, lambda r: f"{r['decode']['call_ms_median']:.2f}"),
    ("dec", 7, lambda r: f"{r['decode']['per_frame_ms_median']:.3f}"),
    ("plain", 7, lambda r: f"{r['decode_plain']['per_frame_ms_median']:.3f}"),
    ("solve", 8, lambda r: f"{r['cholespy_solve_all_ms']:.2f}"),
    ("dec/sol", 7, lambda r: _opt(".2f", r["decode_over_solve"])),
    ("paired", 6, lambda r: f"{r['decode_over_solve_paired']:.2f}"),
    ("steps", 5, lambda r: f"{r['decode']['solves']['steps']}"),
    ("conv", 4, lambda r: "yes" if r["decode"]["solves"]["converged"] else "NO"),
    ("rt max", 8, lambda r: f"{r['roundtrip']['max_rel']:.1e}"),
    ("dev host", 8, lambda r: _opt(".1e", r["max_dev_from_host"])),
    ("RSS MB", 6, lambda r: f"{r['peak_rss_mb']:.0f}"),
]


def format_table(records: list[dict]) -> str:
    head = "  ".join(name.rjust(w) for name, w, _ in _COLUMNS)
    lines = [head, "-" * len(head)]
    for r in records:
        if "skipped" in r:
            lead = "  ".join(fn(r).rjust(w) for _, w, fn in _COLUMNS[:5])
            lines.append(f"{lead}  skipped: {r['skipped']}")
        else:
            lines.append("  ".join(fn(r).rjust(w) for _, w, fn in _COLUMNS))
    comp = ["", "first-call (compile) seconds: local / encode / temporal / decode / plain"]
    for r in records:
        if "skipped" not in r:
            comp.append(
                f"  {r['case']:>7} {r['solver']:>6} {r['dtype']:>7}: {r['encode_local']['compile_s']:.2f} / "
                f"{r['encode']['compile_s']:.2f} / {r['encode_temporal']['compile_s']:.2f} / "
                f"{r['decode']['compile_s']:.2f} / {r['decode_plain']['compile_s']:.2f}"
            )
    notes = [
        "",
        "prep s: acap.prepare(solver=...) after a solver-free cold prepare; setup s: its solver set-up (factor);",
        "enc/dec/plain: ms per frame (medians); dec call: ms per decode of all N frames (refine=1);",
        "plain: refine=0; solve: bare cholespy solve of all N frames' right-hand sides (3 per frame), ms;",
        "dec/sol: dec call / solve; paired: median of the ratios timed back to back; steps/conv: decode_info;",
        "rt max: round-trip vertex error / bbox diagonal; dev host: max |p - p_host| / bbox diagonal",
    ]
    return "\n".join(lines + comp + notes)


def write_json_atomic(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(payload, fh, indent=2)
            fh.write("\n")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# --------------------------------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m benchmarks.acap", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--data", required=True, help="folder (or .npz) of meshes sharing one connectivity; reference = first"
    )
    p.add_argument("--json", required=True, help="output JSON path (parent folders are created)")
    p.add_argument("--repeats", type=int, default=5, help="timed calls per measurement (after one first call)")
    p.add_argument(
        "--solvers",
        default=",".join(reconstruct.SOLVERS),
        help=f"comma-separated reconstruction solvers to benchmark (default: {','.join(reconstruct.SOLVERS)})",
    )
    p.add_argument(
        "--big-vertices", type=int, default=100_000, help="subdivide the big case to at least this many vertices"
    )
    p.add_argument("--big-frames", type=int, default=8, help="frames of the big case (the first ones)")
    p.add_argument(
        "--big-cg-frames",
        type=int,
        default=2,
        help="frames decoded by conjugate gradients in the big case (the first ones)",
    )
    p.add_argument(
        "--big-cg-repeats",
        type=int,
        default=1,
        help="at most this many timed calls for conjugate gradients in the big case",
    )
    p.add_argument("--skip-big", action="store_true", help="leave out the subdivided big case")
    p.add_argument("--skip-dataset", action="store_true", help="leave out the data set itself (the big case only)")
    p.add_argument("--no-float64", action="store_true", help="float32 only (leave out the float64 runs)")
    p.add_argument(
        "--chunk-frames",
        type=int,
        default=0,
        help=f"frames per encode/decode call (0: auto, <= {CHUNK_VERTEX_FRAMES} vertex-frames per call)",
    )
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error("--repeats must be at least 1")
    if args.skip_big and args.skip_dataset:
        p.error("--skip-big and --skip-dataset leave nothing to measure")
    if args.big_frames < 1 or args.big_cg_frames < 1 or args.big_cg_repeats < 1:
        p.error("--big-frames, --big-cg-frames and --big-cg-repeats must be at least 1")
    try:
        args.solvers = parse_solvers(args.solvers)
    except ValueError as e:
        p.error(str(e))
    return args


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    # float64 cases need x64; it is on for every case so that float32 timings do not depend on the options.
    # The previous setting is restored on return (the smoke test calls main() inside pytest).
    x64_before = bool(jax.config.jax_enable_x64)
    jax.config.update("jax_enable_x64", True)
    try:
        return _run(args, argv)
    finally:
        jax.config.update("jax_enable_x64", x64_before)


def _run(args: argparse.Namespace, argv: list[str]) -> dict:
    frames, faces = load_sequence(args.data)
    print(f"data: {args.data}: {frames.shape[0]} frames, {frames.shape[1]} vertices, {faces.shape[0]} faces")
    print(
        f"device: {device_info()['name']}  cpu: {cpu_info()}  jax {jax.__version__}  solvers: {','.join(args.solvers)}"
    )
    dtypes = [np.float32] if args.no_float64 else [np.float32, np.float64]

    records = []
    for dtype in [] if args.skip_dataset else dtypes:
        records += bench_case("dataset", frames, faces, dtype, args.repeats, args.chunk_frames, args.solvers)
    if not args.skip_big:
        t0 = time.perf_counter()
        big, big_faces, levels = subdivide(frames[: args.big_frames], faces, args.big_vertices)
        sub_s = time.perf_counter() - t0
        print(f"big: {levels} Loop level(s) in {sub_s:.1f} s -> {big.shape[1]} vertices, {big_faces.shape[0]} faces")
        for dtype in dtypes:
            recs = bench_case(
                "big",
                big,
                big_faces,
                dtype,
                args.repeats,
                args.chunk_frames,
                args.solvers,
                cg_frames=args.big_cg_frames,
                cg_repeats=args.big_cg_repeats,
            )
            for rec in recs:
                rec["subdivision"] = {
                    "levels": levels,
                    "seconds": round(sub_s, 3),
                    "base_vertices": int(frames.shape[1]),
                }
            records += recs

    payload = {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": "python -m benchmarks.acap " + shlex.join(argv),
        "data": str(args.data),
        "repeats": args.repeats,
        "solvers": list(args.solvers),
        "dense_max_vertices": reconstruct.DENSE_MAX_VERTICES,
        "jax_enable_x64": bool(jax.config.jax_enable_x64),
        "jax_version": jax.__version__,
        "python": platform.python_version(),
        "records": records,
    }
    write_json_atomic(Path(args.json), payload)
    print()
    print(format_table(records))
    print(f"\nwritten: {args.json}")
    return payload


if __name__ == "__main__":
    main()
