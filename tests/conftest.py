"""Shared fixtures: paths into ../shared/data (tests that need it skip with a clear reason).

Compilation is most of the suite's time (XLA on a 2-core CPU), so the suite compiles less and once:

- a persistent compilation cache for the session (a fresh temporary folder, shared by the xdist workers and the
  CLI subprocesses through the environment): after the per-module release of compiled code below, and in every
  subprocess, a program compiled before is read back instead of compiled again;
- XLA's backend optimisations off (``JAX_DISABLE_MOST_OPTIMIZATIONS``): the tests check results, not speed; the
  skipped LLVM passes may move a last bit (fused multiply-adds), which every tolerance here absorbs (the whole
  suite passes both ways); benchmarks/ and the experiments compile as usual.

Concurrent writers of one cache entry (two workers, or two subprocesses) at worst make a reader warn and compile
again. A ``JAX_COMPILATION_CACHE_DIR`` of the caller's is used as it is (and fills with every program of the suite).

Together they took the suite from 2,066 s to 1,233 s on the 2-core CPU (2026-11-29). Both are defaults: a caller's
own settings of these variables win.
"""

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:  # set before jax is imported, inherited by workers and subprocesses
    _cache = tempfile.mkdtemp(prefix="jaxdeform-tests-xla-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)  # the process that made it removes it
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
# the library changes no JAX setting; the tests run with x64 enabled (float64 checks), workers and subprocesses too
os.environ["JAX_ENABLE_X64"] = "1"

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

#: the packages whose annotations the tests check, and the checker (pyproject.toml: --jaxtyping-packages), for the
#: scripts that tests/fresh_process.py runs in fresh interpreters (the hook lives in this process only)
JAXTYPING_ENV = "JAXDEFORM_TEST_JAXTYPING_PACKAGES"


def pytest_configure(config):
    packages = config.getoption("jaxtyping_packages", None)
    if packages:
        os.environ[JAXTYPING_ENV] = packages
    else:
        os.environ.pop(JAXTYPING_ENV, None)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Free compiled XLA executables after each test module.

    Every executable keeps its machine code in its own memory mappings. Over the whole suite they passed
    vm.max_map_count (65,530: 40k mappings after ~170 tests), and XLA then aborted or segfaulted while
    compiling the next function.
    """
    yield
    import gc
    import sys

    import jax

    jax.clear_caches()
    sim = sys.modules.get("jaxdeform.cloth.simulate")
    if sim is not None:
        sim.clear_compiled()
    gc.collect()


def data_dir(name: str) -> Path:
    path = DATA / name
    if not path.is_dir():
        pytest.skip(f"real data '{name}' not found at {path} (../shared/data beside the repository)")
    return path


@pytest.fixture(scope="session")
def acap_bar():
    import numpy as np

    from jaxdeform.mesh import load_sequence

    d = data_dir("acap-bar")
    verts, faces = load_sequence([d / "1.obj", d / "2.obj", d / "3.obj"])

    def gt(name):
        return np.loadtxt(d / name).reshape(3, -1, 3, 3)

    return verts, faces, gt


@pytest.fixture(scope="session")
def horse():
    from jaxdeform.mesh import load_sequence

    return load_sequence(data_dir("horse-gallop"))


def grid_mesh(n: int = 6):
    """A flat n x n grid in the z = 0 plane, 0..1 in x and y: (vertices (n*n, 3), faces (2(n-1)^2, 3))."""
    import numpy as np

    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    pts = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return pts, faces
