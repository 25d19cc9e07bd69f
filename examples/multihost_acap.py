"""Multi-host ACAP: encode and decode a sequence data-parallel over the devices of several processes.

Every process loads only its own block of frames, builds its part of one global batch with
``jax.make_array_from_process_local_data`` and calls :func:`jaxdeform.acap.sharded.encode` / ``decode`` on it.
The round-trip error of each process's frames (the largest vertex distance over the reference's bounding-box
diagonal, up to a translation) is gathered and printed by process 0 as one JSON line.

On a cluster, start one copy per host with its rank::

    python examples/multihost_acap.py DATA --coordinator HOST0:12355 --num-processes 4 --process-id RANK

On one machine, ``--processes N`` starts the N copies itself (CPU devices talk through gloo collectives)::

    python examples/multihost_acap.py ../shared/data/horse-gallop --processes 2 --frames 8

Arguments: ``DATA`` is a folder of meshes that share one connectivity (the first one is the reference) or a
``.npz`` sequence; ``--frames`` (default: all) must be a multiple of the number of processes.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
from pathlib import Path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def spawn(argv: list[str], processes: int, timeout: float) -> int:
    """Run ``processes`` copies of this script on this machine; the worst exit status."""
    coordinator = f"127.0.0.1:{_free_port()}"
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                __file__,
                *argv,
                "--coordinator",
                coordinator,
                "--num-processes",
                str(processes),
                "--process-id",
                str(i),
            ]
        )
        for i in range(processes)
    ]
    codes = []
    for p in procs:
        try:
            codes.append(p.wait(timeout=timeout))
        except subprocess.TimeoutExpired:
            p.kill()
            codes.append(124)
    return max(codes, key=abs)


def worker(data: str, frames: int | None, coordinator: str, num_processes: int, process_id: int) -> None:
    import jax

    # CPU devices of several processes need a collectives backend (accelerators bring their own)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator, num_processes=num_processes, process_id=process_id)

    import numpy as np
    from jax.experimental import multihost_utils
    from jax.sharding import NamedSharding, PartitionSpec

    from jaxdeform import acap
    from jaxdeform.acap import sharded
    from jaxdeform.mesh import load_sequence
    from jaxdeform.mesh.io import SEQUENCE_SUFFIXES, natural_key

    path = Path(data)
    files = (
        [path]
        if path.is_file()
        else sorted(
            (f for f in path.iterdir() if f.suffix.lower() in SEQUENCE_SUFFIXES), key=lambda f: natural_key(f.name)
        )
    )
    if len(files) == 1:  # one .npz holding the whole sequence: every process reads it, keeps its block
        everything, faces = load_sequence(files)
        n = len(everything) if frames is None else frames
        rest = everything[0]
        take = lambda lo, hi: everything[lo:hi]  # noqa: E731
    else:
        n = len(files) if frames is None else frames
        rest, faces = load_sequence(files[:1])
        rest = rest[0]
        take = lambda lo, hi: load_sequence(files[lo:hi])[0]  # noqa: E731
    if n % num_processes:
        raise SystemExit(f"{n} frames cannot be split evenly over {num_processes} processes; pass --frames.")
    block = n // num_processes
    mine = take(process_id * block, (process_id + 1) * block).astype(np.float32)

    a = acap.prepare(rest.astype(np.float32), faces)  # host work, in every process
    mesh = sharded.frames_mesh()  # every device of every process
    x = jax.make_array_from_process_local_data(NamedSharding(mesh, PartitionSpec(sharded.FRAMES)), mine)
    feats = sharded.encode(a, x, mesh)
    pos = sharded.decode(a, feats, mesh)

    local = np.concatenate([np.asarray(s.data) for s in sorted(pos.addressable_shards, key=lambda s: s.index[0].start)])
    diag = float(np.linalg.norm(np.ptp(rest, axis=0)))
    # the features carry no translation: the decode holds vertex 0 at the reference, so compare up to a shift
    moved = (local - local[:, :1]) - (mine - mine[:, :1])
    err = np.array([np.linalg.norm(moved, axis=-1).max() / diag], np.float32)
    errs = multihost_utils.process_allgather(err)
    if process_id == 0:
        print(
            json.dumps(
                {
                    "processes": num_processes,
                    "devices": jax.device_count(),
                    "frames": n,
                    "vertices": int(rest.shape[0]),
                    "features": list(feats.shape),
                    "round_trip_max_over_diag": [float(e) for e in np.ravel(errs)],
                }
            ),
            flush=True,
        )
    jax.distributed.shutdown()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", help="a folder of meshes with one connectivity, or a .npz sequence")
    p.add_argument("--frames", type=int, default=None, help="use the first FRAMES frames (default: all)")
    p.add_argument("--processes", type=int, default=None, help="start this many processes on this machine")
    p.add_argument("--coordinator", help="HOST:PORT of process 0")
    p.add_argument("--num-processes", type=int)
    p.add_argument("--process-id", type=int)
    p.add_argument("--timeout", type=float, default=600, help="seconds to wait for the local processes")
    args = p.parse_args(argv)
    if args.processes is not None:
        if args.processes < 1:
            p.error("--processes must be at least 1")
        rest = [args.data] + ([] if args.frames is None else ["--frames", str(args.frames)])
        return spawn(rest, args.processes, args.timeout)
    if args.coordinator is None or args.num_processes is None or args.process_id is None:
        p.error("give --processes N, or --coordinator, --num-processes and --process-id")
    if not os.path.exists(args.data):
        p.error(f"{args.data} does not exist")
    worker(args.data, args.frames, args.coordinator, args.num_processes, args.process_id)
    return 0


if __name__ == "__main__":
    sys.exit(main())
