"""Benchmark of DFD rebinding and posing (seed 004, jaxdeform.handles.weights).

    python -m benchmarks.handles --mesh ../shared/data/test-meshes/armadillo.obj --json out/bench/handles.json

Rebind (paper Tab. 3: 4 / 12 / 34 ms for 1 / 10 / 100 handles on an A40): ``dfd_weights(Z, handles)`` on the
mesh's vertices with ``--channels`` random unit features (float32; the time does not depend on the feature
values) or a real field (``--features`` .npy of shape (V, C)); for each handle count, the first call
(``compile_s``: compilation + one call), then ``--repeats`` rounds over all counts (interleaved), each call with
new random handles and blocked; ``ms_host_median``: the same followed by the copy to a NumPy array.

Pose, on an icosphere subdivided until it has >= ``--pose-faces`` faces (default 1M: 1.31M faces, 655k
vertices), float32, ``--pose-handles`` handles, every frame with new (3, 4) transforms from the host; variants
interleaved frame by frame (so they share the machine load): ``affine`` (``blend``), ``translation`` (``blend``
with identity linear parts), ``pou`` (``blend(pou=True)``), ``symmetric`` (``symmetric_blend``, x plane),
``deformer``, ``deformer_pou``, ``deformer_symmetric`` (``Deformer.deform``, cached weights, output copied to
NumPy; its symmetry plane is detected from an x-symmetric 16-channel field). ``fps_median`` = 1000 / median.
The JSON is written atomically. Not a test: tests/test_benchmarks_smoke.py runs it once on a tiny mesh so it
cannot rot.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import shlex
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

import jaxdeform  # noqa: F401  (x64 on; everything here is float32 explicitly)
from benchmarks.acap import cpu_info, device_info
from jaxdeform.handles import weights as hw
from jaxdeform.mesh import load_mesh
from jaxdeform.mesh.io import atomic_path


def _load() -> float:
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return float("nan")


def _timing(times_s: list[float], compile_s: float) -> dict:
    ms = [1e3 * t for t in times_s]
    med = statistics.median(ms)
    return {
        "compile_s": round(compile_s, 4),
        "ms_median": round(med, 3),
        "ms_min": round(min(ms), 3),
        "repeats": len(ms),
    }


def unit_features(n: int, c: int, seed: int) -> np.ndarray:
    z = np.random.default_rng(seed).normal(size=(n, c)).astype(np.float32)
    return z / np.linalg.norm(z, axis=1, keepdims=True)


def bench_rebind(Z: np.ndarray, counts: list[int], repeats: int, seed: int) -> list[dict]:
    """Per handle count: the first call (compile_s), then ``repeats`` rounds over all counts (interleaved, so
    that every count sees the same machine load), each call with new random handles."""
    rng = np.random.default_rng(seed)
    Zj = jax.block_until_ready(jnp.asarray(Z))
    n = Z.shape[0]
    compile_s, dev, host = {}, {k: [] for k in counts}, {k: [] for k in counts}
    for k in counts:
        t0 = time.perf_counter()
        jax.block_until_ready(hw.dfd_weights(Zj, rng.integers(0, n, k)))
        compile_s[k] = time.perf_counter() - t0
    for _ in range(repeats):
        for k in counts:
            h = rng.integers(0, n, k)
            t0 = time.perf_counter()
            jax.block_until_ready(hw.dfd_weights(Zj, h))
            dev[k].append(time.perf_counter() - t0)
            h = rng.integers(0, n, k)
            t0 = time.perf_counter()
            np.asarray(hw.dfd_weights(Zj, h))
            host[k].append(time.perf_counter() - t0)
    records = []
    for k in counts:
        rec = {
            "handles": k,
            "bucket": hw.bucket(k),
            **_timing(dev[k], compile_s[k]),
            "ms_host_median": round(1e3 * statistics.median(host[k]), 3),
        }
        print(json.dumps({"rebind": rec}), flush=True)
        records.append(rec)
    return records


def pose_mesh(min_faces: int) -> tuple[np.ndarray, np.ndarray, int]:
    level = 0
    while 20 * 4**level < min_faces:
        level += 1
    m = trimesh.creation.icosphere(subdivisions=level)
    return np.asarray(m.vertices), np.asarray(m.faces, dtype=np.int64), level


def _frames(rng, v: np.ndarray, handles: np.ndarray, n: int, rotate: bool) -> list[np.ndarray]:
    out = []
    for _ in range(n):
        T = [
            hw.make_transform(
                v[h],
                rng.normal(scale=0.05, size=3),
                rng.normal(size=3) if rotate else None,
                float(rng.uniform(-30, 30)) if rotate else 0.0,
            )
            for h in handles
        ]
        out.append(np.asarray(T, dtype=np.float32))
    return out


def _time_interleaved(variants: dict, frames: int) -> list[dict]:
    """First call of each variant (compile_s), then the variants round-robin, one frame each per round.

    Interleaving makes the variants share the same machine load (other processes on this shared 2-core VM).
    """
    compile_s, times = {}, {name: [] for name in variants}
    for name, (fn, fr) in variants.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn(fr[0]))
        compile_s[name] = time.perf_counter() - t0
    for i in range(1, frames + 1):
        for name, (fn, fr) in variants.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(fr[i]))
            times[name].append(time.perf_counter() - t0)
    records = []
    for name in variants:
        rec = {"variant": name, **_timing(times[name], compile_s[name])}
        rec["fps_median"] = round(1e3 / rec["ms_median"], 1)
        records.append(rec)
    return records


def bench_pose(min_faces: int, k: int, frames: int, seed: int) -> tuple[dict, list[dict]]:
    t0 = time.perf_counter()
    v, f, level = pose_mesh(min_faces)
    mesh_s = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    handles = rng.choice(v.shape[0], size=k, replace=False)
    # a smooth 16-channel field of (|x|, y, z): realistic weight supports (the time does not depend on them) and a
    # mirror symmetry in x for the Deformer to detect
    a, b = rng.normal(size=(16, 3)) * 1.5, rng.normal(size=16)

    def field(p):
        q = np.c_[np.abs(p[:, 0]), p[:, 1], p[:, 2]]
        z = np.tanh(q @ a.T + b)
        return (z / np.linalg.norm(z, axis=1, keepdims=True)).astype(np.float32)

    z = field(v)
    vj = jax.block_until_ready(jnp.asarray(v.astype(np.float32)))
    W = jax.block_until_ready(hw.dfd_weights(jnp.asarray(z), handles))
    plane = hw.Plane(np.array([1.0, 0.0, 0.0]), float(v[:, 0].mean()))
    hpos = v[handles].astype(np.float32)
    affine = _frames(rng, v, handles, frames + 1, rotate=True)
    translate = _frames(rng, v, handles, frames + 1, rotate=False)
    t0 = time.perf_counter()
    dfm = hw.Deformer(v, f, z, field_fn=field)
    detected = dfm.symmetry_plane()
    detect_s = time.perf_counter() - t0
    if detected is None:
        raise RuntimeError("the x-symmetric benchmark field should have a detected symmetry plane.")
    variants = {
        "affine": (lambda T: hw.blend(vj, W, T), affine),
        "translation": (lambda T: hw.blend(vj, W, T), translate),
        "pou": (lambda T: hw.blend(vj, W, T, pou=True), affine),
        "symmetric": (lambda T: hw.symmetric_blend(vj, W, T, hpos, plane), affine),
        "deformer": (lambda T: dfm.deform(handles, T), affine),
        "deformer_pou": (lambda T: dfm.deform(handles, T, pou=True), affine),
        "deformer_symmetric": (lambda T: dfm.deform(handles, T, symmetric=True), affine),
    }
    info = {
        "vertices": int(v.shape[0]),
        "faces": int(f.shape[0]),
        "icosphere_level": level,
        "handles": k,
        "dtype": "float32",
        "mesh_s": round(mesh_s, 2),
        "mean_weight_support": float(np.mean(np.asarray(W) > 0)),
        "deformer_setup_and_symmetry_s": round(detect_s, 3),
        "symmetry_plane": detected.source,
    }
    records = _time_interleaved(variants, frames)
    for rec in records:
        print(json.dumps({"pose": rec}), flush=True)
    return info, records


def format_table(payload: dict) -> str:
    lines = [f"rebind on {payload['vertices']} vertices x {payload['channels']} channels (ms, median / min)"]
    for r in payload["rebind"]:
        lines.append(
            f"  K = {r['handles']:4d} (bucket {r['bucket']:4d}): {r['ms_median']:8.2f} / {r['ms_min']:8.2f}"
            f"   compile {r['compile_s']:.3f} s"
        )
    if payload.get("pose"):
        p = payload["pose_mesh"]
        lines.append(f"pose on {p['vertices']} vertices / {p['faces']} faces, {p['handles']} handles (ms, fps)")
        for r in payload["pose"]:
            lines.append(f"  {r['variant']:15s} {r['ms_median']:8.2f} ms  {r['fps_median']:8.1f} fps")
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mesh", required=True, help="mesh for the rebind timing (armadillo: 25k vertices)")
    parser.add_argument("--json", required=True)
    parser.add_argument(
        "--features", default=None, help=".npy (V, C) features of the mesh's vertices (default: random)"
    )
    parser.add_argument("--channels", type=int, default=384)
    parser.add_argument("--handles", type=int, nargs="+", default=[1, 10, 100])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--pose-faces", type=int, default=1_000_000)
    parser.add_argument("--pose-handles", type=int, default=10)
    parser.add_argument("--pose-frames", type=int, default=60)
    parser.add_argument("--skip-pose", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    verts, faces = load_mesh(args.mesh)
    if args.features:
        Z = np.load(args.features).astype(np.float32)
        if Z.shape[0] != verts.shape[0]:
            raise SystemExit(f"--features has {Z.shape[0]} rows but the mesh has {verts.shape[0]} vertices.")
        Z = Z / np.maximum(np.linalg.norm(Z, axis=1, keepdims=True), 1e-12)
    else:
        Z = unit_features(verts.shape[0], args.channels, args.seed)
    load_before = _load()
    payload = {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": " ".join(
            shlex.quote(a)
            for a in [sys.executable, "-m", "benchmarks.handles"] + list(argv if argv is not None else sys.argv[1:])
        ),
        "mesh": str(args.mesh),
        "vertices": int(verts.shape[0]),
        "faces": int(faces.shape[0]),
        "channels": int(Z.shape[1]),
        "features": args.features or "random unit (seeded)",
        "dtype": "float32",
        "jax_version": jax.__version__,
        "python": sys.version.split()[0],
        "device": device_info(),
        "cpu": cpu_info(),
    }
    payload["rebind"] = bench_rebind(Z, args.handles, args.repeats, args.seed)
    payload["rebind_ms"] = {str(r["handles"]): r["ms_median"] for r in payload["rebind"]}
    if not args.skip_pose:
        payload["pose_mesh"], payload["pose"] = bench_pose(
            args.pose_faces, args.pose_handles, args.pose_frames, args.seed
        )
        payload["pose_fps"] = {r["variant"]: r["fps_median"] for r in payload["pose"]}
    payload["load_avg_1m"] = [load_before, _load()]
    print(format_table(payload), flush=True)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        Path(tmp).write_text(json.dumps(payload, indent=2))
    return payload


if __name__ == "__main__":
    main()
