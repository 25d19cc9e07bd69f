"""The library's promise, checked as a user would: every public ACAP stage under jax.jit, jax.vmap, jax.grad,
jax.jvp and jax.jacfwd, each in a fresh Python process with no eager warm-up call, and no global JAX setting
changed by importing jaxdeform. This file: several devices, and the README's example run verbatim.

Each test runs a small script in a subprocess (``fresh_process.run_script``); the script asserts and prints ``OK``.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from conftest import data_dir
from fresh_process import ROOT, run_script

SHARDED_ACAP = """
    import numpy as np, jax, jax.numpy as jnp
    from jaxdeform import acap
    from jaxdeform.acap import sharded
    from jaxdeform.mesh import load_sequence
    assert len(jax.devices()) == 4
    verts, faces = load_sequence({data!r})
    frames = verts[:10]  # not a multiple of 4: padded and trimmed
    mesh = sharded.frames_mesh()
    for solver in ("host", "cg"):
        a = acap.prepare(verts[0], faces, solver=solver)
        one = a.encode(frames)
        many = sharded.encode(a, frames, mesh)
        assert float(jnp.abs(one - many).max()) < 1e-12
        d_one = a.decode(one)
        d_many = sharded.decode(a, one, mesh)
        assert float(jnp.abs(d_one - d_many).max()) < 1e-9 * float(np.ptp(verts[0])), float(jnp.abs(d_one - d_many).max())
    even = sharded.encode(a, verts[:8], mesh)
    assert even.sharding.spec == jax.sharding.PartitionSpec("frames")  # stays split along the frames
    print("OK")
"""


@pytest.mark.slow
def test_sharded_encode_decode_equal_one_device():
    run_script(
        SHARDED_ACAP.format(data=str(data_dir("horse-gallop"))),
        devices=4,
    )


REPEATED_HOST_DECODE = """
    import numpy as np, jax
    from jaxdeform import acap
    from jaxdeform.acap import sharded
    from jaxdeform.mesh import load_sequence
    assert len(jax.devices()) == 4
    verts, faces = load_sequence({data!r})
    a = acap.prepare(verts[0], faces, solver="host")
    feats = a.encode(verts[:8])  # 2 frames per device
    one = np.asarray(a.decode(feats))
    mesh = sharded.frames_mesh()
    for _ in range(6):  # with the host callbacks inside one multi-device program, 3 of 3 such runs hung
        many = sharded.decode(a, feats, mesh)
        assert many.sharding.spec == jax.sharding.PartitionSpec("frames")
        assert np.abs(np.asarray(many) - one).max() < 1e-9 * np.ptp(verts[0]), np.abs(np.asarray(many) - one).max()
    print("OK")
"""


@pytest.mark.slow
def test_sharded_host_decode_repeated_on_four_devices_finishes():
    """The host factor's decode of 8 horse frames over 4 devices, 6 times in a row: finishes (no deadlock of
    host callbacks) and equals the one-device decode each time."""
    run_script(REPEATED_HOST_DECODE.format(data=str(data_dir("horse-gallop"))), devices=4, timeout=300)


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    start = text.index("<!-- jax-api-example -->")
    block = text[text.index("```python\n", start) + len("```python\n") :]
    return block[: block.index("```")]


@pytest.mark.slow
def test_readme_jax_example_runs_verbatim():
    """The README's jit / vmap / grad / jvp / sharded example, exactly as printed, in a fresh process (4 devices)."""
    data_dir("horse-gallop")  # skips with its reason when the data is absent
    run_script(
        _readme_example() + '\nprint("OK")\n',
        x64=False,
        devices=4,
    )


@pytest.mark.slow
def test_multihost_example_runs_two_processes():
    """examples/multihost_acap.py: two processes on this machine (gloo collectives), each with its own frames."""
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "multihost_acap.py"),
            str(data_dir("cactus")),
            "--processes",
            "2",
            "--frames",
            "4",
            "--timeout",
            "600",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=660,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["processes"] == 2 and report["devices"] == 2 and report["features"][0] == 4
    assert len(report["round_trip_max_over_diag"]) == 2  # one entry per process
    assert max(report["round_trip_max_over_diag"]) < 0.02
