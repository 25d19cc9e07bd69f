"""How long each README command example leaves the terminal without anything new: every command runs on a
pseudo-terminal of 120 x 40 (stdout and stderr both on it, as a user sees them), and the longest time between two
writes (or from the start to the first, or from the last to the exit) is its longest silence.

    python -m benchmarks.feedback --work /tmp/examples --out benchmarks/results/feedback.json
    python -m benchmarks.feedback --only "acap encode" "acap decode" --limit 100

``--limit S`` ends a command with SIGTERM after S seconds (its first minutes are what is measured). Commands run
in the order of :data:`EXAMPLES` in the folder ``--work``, each on the outputs of those before it, on the data
in ``../shared/data``. Writes one JSON record per command: ``{"command", "rc", "seconds", "longest_silence_s",
"silence_ends_at_s", "writes", "stopped_at_limit"}``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import select
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

#: the README's command examples (label, arguments after ``jaxdeform``); {data} is the shared data folder
EXAMPLES = [
    ("acap encode", "acap encode {data}/horse-gallop --reference {data}/horse-gallop/0001.obj --out horse.npz"),
    ("acap decode", "acap decode horse.npz --out horse_decoded/"),
    ("components train", "components train {data}/horse-gallop --out runs/horse-ms"),
    ("components evaluate", "components evaluate runs/horse-ms --data {data}/horse-gallop --json runs/horse-ms/m.json"),
    ("components finetune", "components finetune runs/horse-ms --out runs/horse-ms-ft"),
    ("components show", "components show runs/horse-ms --out runs/horse-ms/figures"),
    ("components edit", "components edit runs/horse-ms --controls controls.json --out edited.obj"),
    ("cloth simulate", "cloth simulate --scenario sheet --out data/sheet"),
    ("cloth train", "cloth train data/sheet --out runs/sheet"),
    ("cloth synthesize", "cloth synthesize runs/sheet --coarse data/sheet --split test --out fine/"),
    ("cloth evaluate", "cloth evaluate runs/sheet --data data/sheet --json metrics.json"),
    ("parts fit", "parts fit {data}/horse-poses --out runs/horse"),
    ("parts show", "parts show runs/horse --out runs/horse/figures"),
    ("parts interpolate", "parts interpolate runs/horse --source 0 --target 5 --steps 8 --out runs/horse/interp"),
    ("handles distill", "handles distill {data}/test-meshes/armadillo.obj --out armadillo.field"),
    (
        "handles deform",
        "handles deform {data}/test-meshes/armadillo.obj --field armadillo.field --handle 1234 "
        "--translate 0 10 0 --out moved.obj",
    ),
    ("handles show", "handles show {data}/test-meshes/armadillo.obj --field armadillo.field --handle 1234 --out w.png"),
    ("render", "render {data}/horse-gallop/0001.obj --out horse.png"),
]


def _controls(work: Path, data: Path) -> None:
    """controls.json for ``components edit``: four vertices held where shape 0005 has them."""
    from jaxdeform.mesh.io import load_mesh

    v, _ = load_mesh(data / "horse-gallop" / "0005.obj")
    idx = [0, 500, 3000, 6000]
    (work / "controls.json").write_text(json.dumps({"indices": idx, "targets": v[idx].tolist()}))


def silence(argv: list[str], cwd: Path, limit: float = float("inf")) -> dict:
    """Run ``argv`` on a 120 x 40 pseudo-terminal in ``cwd``; SIGTERM after ``limit`` seconds.

    **Returns:** ``{"rc", "seconds", "longest_silence_s", "silence_ends_at_s", "writes", "stopped_at_limit"}``.
    """
    import fcntl
    import pty
    import termios

    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, cwd=cwd, stdout=follower, stderr=follower, stdin=subprocess.DEVNULL)
    os.close(follower)
    last, worst, writes, stopped = t0, (0.0, 0.0), 0, False
    while True:
        if not stopped and time.perf_counter() - t0 > limit:
            proc.send_signal(signal.SIGTERM)
            stopped = True
        ready, _, _ = select.select([leader], [], [], 0.25)
        if not ready:
            continue
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # the terminal closed with the process
            break
        if not chunk:
            break
        now = time.perf_counter()
        worst, last, writes = max(worst, (now - last, now - t0)), now, writes + 1
    rc = proc.wait()
    os.close(leader)
    end = time.perf_counter()
    worst = max(worst, (end - last, end - t0))
    return {
        "rc": rc,
        "seconds": round(end - t0, 1),
        "longest_silence_s": round(worst[0], 1),
        "silence_ends_at_s": round(worst[1], 1),
        "writes": writes,
        "stopped_at_limit": stopped,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", required=True, help="folder the commands run in (created; their outputs stay there)")
    p.add_argument("--out", help="JSON file of the records (default: stdout only)")
    p.add_argument("--only", nargs="+", metavar="LABEL", help="run only these examples (labels of EXAMPLES)")
    p.add_argument("--limit", type=float, default=float("inf"), help="seconds before SIGTERM (default none)")
    p.add_argument("--data", default=str(DATA), help="the shared data folder")
    args = p.parse_args(argv)
    work, data = Path(args.work), Path(args.data)
    work.mkdir(parents=True, exist_ok=True)
    _controls(work, data)
    exe = [sys.executable, "-m", "jaxdeform"]
    records = []
    for label, command in EXAMPLES:
        if args.only and label not in args.only:
            continue
        record = {"command": label} | silence(exe + command.format(data=data).split(), work, args.limit)
        print(json.dumps(record), flush=True)
        records.append(record)
    if args.out:
        host = {"machine": platform.machine(), "cores": os.cpu_count(), "device": "CPU only"}
        Path(args.out).write_text(json.dumps({"host": host, "records": records}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
