"""Running a script in a fresh Python process, as the tests of the JAX API do (tests/test_jax_api*.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

from conftest import JAXTYPING_ENV

ROOT = Path(__file__).resolve().parents[1]


def run_script(
    code: str, *, x64: bool = True, timeout: int = 900, env_extra: dict | None = None, devices: int = 1
) -> str:
    """Run ``code`` in a fresh interpreter (x64 as asked, ``devices`` forced host devices, nothing else of the
    tests' settings changed but the annotation checks of conftest.py's ``JAXTYPING_ENV``); the script must exit 0
    and print ``OK`` last; returns its stdout."""
    env = dict(os.environ)
    env.pop("JAX_ENABLE_X64", None)
    if x64:
        env["JAX_ENABLE_X64"] = "1"
    if devices > 1:
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    env.update(env_extra or {})
    code = textwrap.dedent(code)
    hook = os.environ.get(JAXTYPING_ENV)
    if hook:  # the script's imports are checked as the tests' own (jaxtyping's import hook, beartype)
        *packages, checker = hook.split(",")
        code = f"import jaxtyping\njaxtyping.install_import_hook({packages!r}, {checker!r})\n" + code
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    assert proc.stdout.strip().endswith("OK"), proc.stdout[-3000:]
    return proc.stdout
