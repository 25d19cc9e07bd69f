"""Property-based robustness of the readers: mesh files of every format, ACAP feature files, cloth sequences and
components run folders, truncated or with bytes flipped at random, either load as valid data or raise one
jaxdeform error (a ``JaxDeformError``, or an ``OSError`` for a file that cannot be read); never anything else."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxdeform.errors import JaxDeformError
from jaxdeform.mesh import io

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

TRI_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.5]])
TRI_F = np.array([[0, 1, 2], [1, 3, 2]])


@st.composite
def damage(draw):
    """("truncate", fraction) or ("flip", [(relative position, xor byte), ...])."""
    if draw(st.booleans()):
        return "truncate", draw(st.floats(0.0, 1.0))
    flips = draw(
        st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=8)
    )
    return "flip", flips


def apply(path: Path, how) -> None:
    data = bytearray(path.read_bytes())
    kind, arg = how
    if kind == "truncate":
        data = data[: int(len(data) * arg)]
    else:
        for pos, x in arg:
            data[int(pos * len(data))] ^= x
    path.write_bytes(bytes(data))


def damaged_copy(src: Path, tmp_path_factory, how) -> Path:
    """A copy of ``src`` (same name, in a fresh folder) damaged by ``how``."""
    path = tmp_path_factory.mktemp("damaged") / src.name
    shutil.copy(src, path)
    apply(path, how)
    return path


def valid_mesh(v, f) -> None:
    assert v.ndim == 2 and v.shape[1] == 3 and v.shape[0] > 0 and np.all(np.isfinite(v))
    assert f.ndim == 2 and f.shape[1] == 3 and f.shape[0] > 0 and f.min() >= 0 and f.max() < v.shape[0]


def one_error_or(check, load):
    try:
        result = load()
    except (JaxDeformError, OSError) as exc:
        text = str(exc)
        assert text and "\n" not in text.strip(), text
        return
    check(result)


@pytest.mark.parametrize("suffix", [".obj", ".off", ".ply", ".npz"])
@SETTINGS
@given(how=damage())
def test_mesh_readers(tmp_path_factory, suffix, how):
    path = tmp_path_factory.mktemp("m") / f"mesh{suffix}"
    io.save_mesh(path, TRI_V, TRI_F)
    apply(path, how)
    one_error_or(lambda r: valid_mesh(*r), lambda: io.load_mesh(path))


@pytest.fixture(scope="module")
def features_file(tmp_path_factory):
    from jaxdeform.acap.files import encode_arrays, save_features
    from jaxdeform.data.synthetic import bending_tube_sequence

    v, f = bending_tube_sequence(n_frames=3, n_around=6, n_along=8)
    path = tmp_path_factory.mktemp("feat") / "f.npz"
    save_features(path, encode_arrays(v, v[0], f, "spatial", "official"))
    return path


@SETTINGS
@given(how=damage())
def test_feature_file_reader(features_file, tmp_path_factory, how):
    from jaxdeform.acap.files import read_features

    path = damaged_copy(features_file, tmp_path_factory, how)

    def check(result):
        features, reference, faces, weighting = result
        valid_mesh(reference, faces)
        assert features.shape[-2:] == (reference.shape[0], 9) and np.all(np.isfinite(features))

    one_error_or(check, lambda: read_features(path))


@pytest.fixture(scope="module")
def components_run(tmp_path_factory):
    from jaxdeform.components import run as crun
    from jaxdeform.data.synthetic import bending_tube_sequence

    v, f = bending_tube_sequence(n_frames=12, n_around=6, n_along=8)
    data = tmp_path_factory.mktemp("data")
    for k in range(len(v)):
        io.save_mesh(data / f"f{k:02d}.obj", v[k], f)
    out = tmp_path_factory.mktemp("runs") / "run"
    crun.fit(data, "test", out, method="pca", progress=False, log=lambda s: None)
    return out


@pytest.mark.parametrize("name", ["run.json", "mesh.npz", "codes.npz"])
@SETTINGS
@given(how=damage())
def test_components_run_loader(components_run, tmp_path_factory, name, how):
    from jaxdeform.components import run as crun

    folder = tmp_path_factory.mktemp("r") / "run"
    shutil.copytree(components_run, folder)
    apply(folder / name, how)

    def check(run):
        valid_mesh(run.rest, run.faces)
        assert json.loads((folder / "run.json").read_text())["method"] == run.method

    one_error_or(check, lambda: crun.load(folder))


@pytest.fixture(scope="module")
def cloth_sequence(tmp_path_factory):
    from test_cloth_cli import pair

    from jaxdeform.cloth import data as cdata

    path = tmp_path_factory.mktemp("cloth") / "seq_000.npz"
    cdata.write_sequence(path, pair(0, frames=3, n=3))
    return path


@SETTINGS
@given(how=damage())
def test_cloth_sequence_reader(cloth_sequence, tmp_path_factory, how):
    from jaxdeform.cloth import data as cdata

    path = damaged_copy(cloth_sequence, tmp_path_factory, how)

    def check(result):
        seq, shared = result
        for res in ("coarse", "fine"):
            valid_mesh(shared[f"{res}_rest"], shared[f"{res}_faces"])

    one_error_or(check, lambda: cdata.read_sequence(path))


def test_npz_mesh_every_byte_flipped(tmp_path):
    """Each byte of an .npz mesh flipped in turn (zip headers that claim unsupported compression or encryption
    included): one jaxdeform error or a valid mesh."""
    path = tmp_path / "mesh.npz"
    io.save_mesh(path, TRI_V, TRI_F)
    original = path.read_bytes()
    for pos in range(len(original)):
        for x in (1, 32, 128):
            data = bytearray(original)
            data[pos] ^= x
            path.write_bytes(bytes(data))
            one_error_or(lambda r: valid_mesh(*r), lambda: io.load_mesh(path))
