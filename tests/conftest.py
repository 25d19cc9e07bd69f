"""Shared fixtures: paths into ../shared/data (tests that need it skip with a clear reason)."""

from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


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
