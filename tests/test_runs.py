"""The run-folder API (jaxdeform.runs): every method fits, loads, evaluates and shows through the same calls."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from jaxdeform import runs
from jaxdeform.mesh.io import save_mesh

#: the four methods and their run modules: a new method must be added here and to jaxdeform.runs.KINDS
METHODS = ("components", "cloth", "parts", "handles")


def _finite_numbers(tree) -> list[float]:
    if isinstance(tree, dict):
        return [x for v in tree.values() for x in _finite_numbers(v)]
    if isinstance(tree, (list, tuple)):
        return [x for v in tree for x in _finite_numbers(v)]
    if isinstance(tree, (int, float)) and not isinstance(tree, bool):
        return [float(tree)]
    return []


def _parts_data(tmp_path):
    from test_parts import _two_rigid_parts, _write_shapes

    shapes, faces, _ = _two_rigid_parts(m=4)
    return _write_shapes(tmp_path / "parts-data", shapes, faces), {}


def _handles_data(tmp_path):
    from test_handles_pipeline import PoolBackbone

    from jaxdeform.data.synthetic import twisted_bar

    v, f = twisted_bar(n_along=12, n_width=4, n_depth=2)
    path = tmp_path / "bar.obj"
    save_mesh(path, v, f)
    return path, {"backbone": PoolBackbone(False), "progress": False}


def _components_data(tmp_path):
    from jaxdeform.data.synthetic import bending_tube_sequence

    vertices, faces = bending_tube_sequence(n_frames=12, n_around=8, n_along=16)
    d = tmp_path / "tube"
    for k in range(vertices.shape[0]):
        save_mesh(d / f"f{k:02d}.obj", vertices[k], faces)
    return d, {"progress": False}


def _cloth_data(tmp_path):
    from test_cloth_cli import pair, write

    d = tmp_path / "cloth-data"
    write(d, [pair(k) for k in range(3)])
    return d, {"progress": False}


DATA = {"components": _components_data, "cloth": _cloth_data, "parts": _parts_data, "handles": _handles_data}


def test_the_api_lists_the_four_methods():
    assert tuple(runs.KINDS) == METHODS
    for kind in METHODS:
        mod = runs.module(kind)
        assert mod.KIND == kind
        assert {"default", "test"} <= set(mod.CONFIGS)
        for name in ("fit", "evaluate", "show"):
            assert callable(getattr(mod, name)), (kind, name)
        assert callable(mod.Run.load)


@pytest.mark.parametrize("kind", METHODS)
def test_fit_load_evaluate_show_through_one_api(kind, tmp_path):
    data, options = DATA[kind](tmp_path)
    out = tmp_path / "run"
    fitted = runs.fit(kind, data, "test", out, **options)
    assert fitted.path == out and out.is_dir()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".run")]  # the staging folder is gone
    assert runs.kind_of(out) == kind
    assert json.loads((out / runs.RECORD).read_text())["kind"] == kind
    run = runs.load(out)
    assert isinstance(run, runs.module(kind).Run) and run.path == out and run.record["kind"] == kind
    metrics = runs.evaluate(run)
    numbers = _finite_numbers(metrics)
    assert numbers and all(math.isfinite(x) for x in numbers)
    again = runs.evaluate(runs.load(out), data)  # the data given explicitly: the same figures
    for key in ("rmse", "parts", "handle_weight_min", "faces"):
        if key in metrics:
            assert again[key] == pytest.approx(metrics[key], rel=1e-6)
    shown = runs.show(run, tmp_path / "figures")
    assert shown["files"] and all((tmp_path / "figures" / f).stat().st_size > 0 for f in shown["files"])


def test_a_run_of_another_kind_is_refused_with_one_sentence(tmp_path):
    data, options = _parts_data(tmp_path)
    out = tmp_path / "run"
    runs.fit("parts", data, "test", out)
    with pytest.raises(runs.RunFolderError, match="is a parts run, not a handles run"):
        runs.module("handles").Run.load(out)


@pytest.mark.parametrize("case", ["missing", "no record", "not json", "unknown kind"])
def test_a_folder_that_is_not_a_run_is_one_sentence(tmp_path, case):
    path = tmp_path / "x"
    if case != "missing":
        path.mkdir()
    if case == "not json":
        (path / "run.json").write_text("{trunc")
    elif case == "unknown kind":
        (path / "run.json").write_text(json.dumps({"kind": "splines"}))
    with pytest.raises(runs.RunFolderError) as info:
        runs.load(path)
    text = str(info.value)
    assert text.endswith(".") and "\n" not in text


def test_unknown_names_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown kind"):
        runs.module("splines")
    with pytest.raises(ValueError, match="has no configuration 'huge'"):
        runs.config("parts", "huge")


def test_parts_evaluate_refuses_another_population(tmp_path):
    from test_parts import _two_rigid_parts, _write_shapes

    data, _ = _parts_data(tmp_path)
    run = runs.fit("parts", data, "test", None)
    shapes, faces, _ = _two_rigid_parts(m=3, seed=1)
    other = _write_shapes(tmp_path / "other", shapes, faces)
    with pytest.raises(Exception, match="holds 3 shapes but the run was fitted to 4"):
        runs.evaluate(run, other)
    assert np.isfinite(runs.evaluate(run)["rmse"])


def test_handles_commands_read_a_run_folder_as_the_field(tmp_path):
    from jaxdeform.cli import main

    mesh, options = _handles_data(tmp_path)
    out = tmp_path / "run"
    runs.fit("handles", mesh, "test", out, **options)
    png = tmp_path / "w.png"
    assert main(["handles", "show", str(mesh), "--field", str(out), "--handle", "3", "--out", str(png)]) == 0
    assert png.stat().st_size > 0


def test_parts_cli_writes_a_run_the_api_loads(tmp_path):
    from jaxdeform.cli import main

    data, _ = _parts_data(tmp_path)
    out = tmp_path / "run"
    assert main(["parts", "fit", str(data), "--out", str(out), "--initial-parts", "2"]) == 0
    run = runs.load(out)
    assert run.fit.n_parts >= 2 and runs.evaluate(run)["rmse_over_diagonal"] < 1e-4
