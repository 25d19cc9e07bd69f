"""Runs know their data: fingerprints (jaxdeform.mesh.fingerprint), the run records that store them, the checks of
data given to a run, and the validation of run.json fields on load."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from test_fuzz_readers import apply, damage, one_error_or
from test_runs import DATA

from jaxdeform import runs
from jaxdeform.data.synthetic import bending_tube_sequence
from jaxdeform.errors import JaxDeformError
from jaxdeform.mesh.fingerprint import RTOL, difference, fingerprint, malformed
from jaxdeform.mesh.io import load_mesh, save_mesh


@pytest.fixture(scope="module")
def tube():
    return bending_tube_sequence(n_frames=5, n_around=8, n_along=10)


def test_a_fingerprint_matches_its_data_and_a_copy_read_back_from_obj(tube, tmp_path):
    vertices, faces = tube
    kept = fingerprint(vertices, faces)
    assert kept["n_shapes"] == 5 and kept["n_vertices"] == vertices.shape[1] and kept["n_faces"] == faces.shape[0]
    assert json.loads(json.dumps(kept)) == kept and malformed(kept) is None
    assert difference(kept, vertices, faces) is None
    assert difference(kept, vertices.astype(np.float32), faces) is None
    save_mesh(tmp_path / "ref.obj", vertices[0], faces)
    v, f = load_mesh(tmp_path / "ref.obj")
    assert difference(kept, v, f) is None  # one shape: the reference is compared, the shape count is not


@pytest.mark.parametrize(
    ("case", "phrase"),
    [
        ("vertex added", "vertices where the run's data had"),
        ("faces dropped", "faces where the run's data had"),
        ("triangles reordered", "triangles differ"),
        ("shapes dropped", "holds 3 shapes where the run's data held 5"),
        ("scaled by 1e-8", "bounding box lies up to"),
        ("moved by 10 tolerances", "bounding box lies up to"),
    ],
)
def test_difference_names_what_differs(tube, case, phrase):
    vertices, faces = tube
    kept = fingerprint(vertices, faces)
    size = float(np.linalg.norm(np.ptp(vertices[0], axis=0)))
    other = {
        "vertex added": (np.concatenate([vertices, vertices[:, :1]], axis=1), faces),
        "faces dropped": (vertices, faces[:-2]),
        "triangles reordered": (vertices, faces[::-1]),
        "shapes dropped": (vertices[:3], faces),
        "scaled by 1e-8": (vertices * 1e-8, faces),
        "moved by 10 tolerances": (vertices + 10 * RTOL * size, faces),
    }[case]
    assert phrase in difference(kept, *other)
    assert difference(kept, vertices + 0.1 * RTOL * size, faces) is None


@pytest.mark.parametrize(
    ("value", "phrase"),
    [
        ([], "must be an object"),
        ({"n_vertices": "12"}, "n_vertices must be a positive whole number"),
        ({"n_faces": True}, "n_faces must be a positive whole number"),
        ({"reference_sha256": "abc"}, "SHA-256"),
        ({"reference_bbox": [[0, 0, 0]]}, "two finite points"),
        ({"reference_bbox": [[0, 0, 0], [1, "x", 1]]}, "two finite points"),
    ],
)
def test_malformed_fingerprints_are_named(value, phrase):
    assert phrase in malformed(value)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """One run of every method (test configurations) with the data it was fitted on."""
    root = tmp_path_factory.mktemp("fingerprint-runs")
    out = {}
    for kind, make in DATA.items():
        (root / kind).mkdir()
        data, options = make(root / kind)
        out[kind] = (runs.fit(kind, data, "test", root / kind / "run", **options).path, data)
    return out


def _data_arrays(kind, data):
    from jaxdeform.cloth.data import load_dataset
    from jaxdeform.mesh.io import load_sequence

    if kind == "cloth":
        ds = load_dataset(data)
        return {"coarse": (ds.coarse_rest, ds.coarse_faces), "fine": (ds.fine_rest, ds.fine_faces)}
    if kind == "handles":
        return {"": load_mesh(data)}
    return {"": load_sequence(data)}


@pytest.mark.parametrize("kind", list(DATA))
def test_every_run_records_the_fingerprint_of_its_data(fitted, kind):
    path, data = fitted[kind]
    record = json.loads((path / runs.RECORD).read_text())
    for name, (vertices, faces) in _data_arrays(kind, data).items():
        kept = record["fingerprint"][name] if name else record["fingerprint"]
        assert kept == fingerprint(vertices, faces)
    if kind == "handles":  # the field carries it too: handles deform and serve read it
        from jaxdeform.handles.field import load_field

        assert load_field(path / "field")[1]["fingerprint"] == record["fingerprint"]


def _edit_record(src, dst, edit):
    shutil.copytree(src, dst)
    record = json.loads((dst / runs.RECORD).read_text())
    edit(record)
    (dst / runs.RECORD).write_text(json.dumps(record))
    return dst


def _moved(kept):
    kept["reference_sha256"] = "0" * 64
    kept["reference_bbox"] = [[x + 1.0 for x in point] for point in kept["reference_bbox"]]


@pytest.mark.parametrize("kind", list(DATA))
def test_a_run_whose_arrays_differ_from_its_fingerprint_is_refused(fitted, kind, tmp_path):
    path, _ = fitted[kind]
    edited = _edit_record(path, tmp_path / "run", lambda r: _moved(r["fingerprint"].get("fine", r["fingerprint"])))
    with pytest.raises(JaxDeformError, match="is not the data the record fingerprints") as err:
        runs.load(edited)
    assert "\n" not in str(err.value) and "bounding box" in str(err.value)
    broken = _edit_record(path, tmp_path / "run2", lambda r: r.__setitem__("fingerprint", ["x"]))
    with pytest.raises(JaxDeformError, match="fingerprint.* must be (an )?object"):
        runs.load(broken)


RECORD_CASES = [
    ("parts", "config", {"initial_parts": 0}, "not a parts configuration"),
    ("parts", "config", "default", "'config' field must be object"),
    ("parts", "data", 5, "'data' field must be string or list or null"),
    ("handles", "config", {"n_views": "many"}, "n_views must be a whole number"),
    ("handles", "field", 3, "'field' field must be object"),
    ("cloth", "residual", "yes", "'residual' field must be boolean"),
    ("cloth", "representation", "mesh", "representation must be one of"),
    ("cloth", "final_loss", "low", "'final_loss' field must be number or null"),
    ("cloth", "train_seconds", -1, None),  # a negative duration is odd but harmless: loads
    ("components", "fingerprint", {"n_shapes": 0}, "n_shapes must be a positive whole number"),
    ("components", "data", 5, "'data' field must be string"),
    ("components", "shape_sizes", "big", "'shape_sizes' field must be list"),
]


@pytest.mark.parametrize(("kind", "field", "value", "phrase"), RECORD_CASES)
def test_run_record_fields_are_validated_on_load(fitted, kind, field, value, phrase, tmp_path):
    path, _ = fitted[kind]
    edited = _edit_record(path, tmp_path / "run", lambda r: r.__setitem__(field, value))
    if phrase is None:
        assert runs.load(edited).record[field] == value
        return
    with pytest.raises(JaxDeformError, match=phrase) as err:
        runs.load(edited)
    assert "\n" not in str(err.value) and str(edited / runs.RECORD) in str(err.value)


def test_parts_evaluate_refuses_other_shapes_of_the_same_population(fitted, tmp_path):
    from jaxdeform.mesh.io import load_sequence

    path, data = fitted["parts"]
    run = runs.load(path)
    vertices, faces = load_sequence(data)
    for k, scale in ((0, 1e-8), (2, 1.0)):
        moved = vertices.copy()
        moved[k] *= scale
        if scale == 1.0:
            moved[k, 0] += 0.5  # one vertex of shape 2 moved
        with pytest.raises(JaxDeformError, match=f"not the data the run was fitted on: its shape {k} lies"):
            runs.evaluate(run, (moved, faces))
    assert np.isfinite(runs.evaluate(run, (vertices, faces))["rmse"])


def test_cloth_refuses_data_with_other_rest_meshes(fitted, tmp_path, capsys):
    from jaxdeform.cli import main
    from jaxdeform.cloth import data as cdata

    path, data = fitted["cloth"]
    other = tmp_path / "other"
    other.mkdir()
    ds = cdata.load_dataset(data)
    names = []
    for s in ds.sequences:
        seq, shared = cdata.read_sequence(ds.root / s.name)
        arrays = dict(np.load(ds.root / s.name, allow_pickle=False))
        arrays["coarse_rest"] = shared["coarse_rest"] * 1e-3
        np.savez(other / s.name, **arrays)
        names.append(s.name)
    cdata.write_index(other, ds.scenario, names)
    with pytest.raises(JaxDeformError, match="its coarse mesh is not the one the run was trained on"):
        runs.evaluate(runs.load(path), other)
    code = main(["cloth", "synthesize", str(path), "--coarse", str(other), "--out", str(tmp_path / "syn")])
    err = capsys.readouterr().err
    assert code == 2 and "coarse mesh is not the one the run was trained on" in err and err.count("\n") == 1
    assert not (tmp_path / "syn").exists()


def test_a_field_refuses_the_same_mesh_scaled(fitted, tmp_path):
    from jaxdeform.errors import ConnectivityError
    from jaxdeform.handles.pipeline import field_features

    path, data = fitted["handles"]
    v, f = load_mesh(data)
    with pytest.raises(ConnectivityError, match="bounding box lies up to .*pass --remap"):
        field_features(path, "scaled.obj", v * 2.0, f)
    assert field_features(path, "scaled.obj", v * 2.0, f, remap=True)[1].shape[0] == v.shape[0]
    assert field_features(path, data, v, f)[1].shape[0] == v.shape[0]


@pytest.mark.parametrize("kind", list(DATA))
def test_a_record_written_before_fingerprints_still_loads(fitted, kind, tmp_path):
    path, _ = fitted[kind]
    edited = _edit_record(path, tmp_path / "run", lambda r: r.pop("fingerprint"))
    assert "fingerprint" not in runs.load(edited).record


@pytest.mark.parametrize(
    ("kind", "name"),
    [
        ("parts", "run.json"),
        ("parts", "summary.json"),
        ("handles", "run.json"),
        ("handles", "mesh.npz"),
        ("cloth", "run.json"),
        ("cloth", "representation.npz"),
    ],
)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(how=damage())
def test_damaged_run_files_load_or_give_one_error(fitted, tmp_path_factory, kind, name, how):
    """The parts, handles and cloth run loaders on a run.json or array file truncated or with bytes flipped: one
    jaxdeform error or a run whose record names its kind (tests/test_fuzz_readers.py does the components runs)."""
    folder = tmp_path_factory.mktemp("damaged") / "run"
    shutil.copytree(fitted[kind][0], folder)
    apply(folder / name, how)

    def check(run):
        assert run.record.get("kind", kind) == kind

    one_error_or(check, lambda: runs.load(folder))
