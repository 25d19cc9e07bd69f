"""Checkpoints with orbax (jaxdeform.nn.archive): round trips, atomic replacement, and one sentence for every path
that is not a readable checkpoint of the expected kind (missing, a file, an empty or foreign folder, damaged)."""

import shutil
import threading

import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from jaxdeform.errors import JaxDeformError, MeshFormatError
from jaxdeform.nn import archive

FMT, VERSION = "jaxdeform-test", 3


def _arrays() -> dict:
    return {
        "param:['layers'][0]['kernel'].value": np.arange(6, dtype=np.float32).reshape(2, 3),
        "rings:coarse:neighbors": np.arange(5, dtype=np.int32),
        "flags": np.asarray([True, False]),
        "scale": np.asarray(2.5),
        "count": np.asarray(7, np.int64),
        "nothing": np.zeros((0, 3), np.int64),
    }


def _record(**more) -> dict:
    return {"format": FMT, "version": VERSION, "config": {"a": [1, 2]}, **more}


@pytest.fixture()
def good(tmp_path):
    return archive.save_tree(tmp_path / "good", _arrays(), _record())


def _one_sentence(err, path) -> str:
    msg = str(err.value)
    assert msg.startswith(str(path)) and msg.endswith(".") and msg.count(". ") == 0 and "\n" not in msg, msg
    return msg


def test_round_trip_keeps_names_dtypes_shapes_and_record(good, tmp_path):
    record, back = archive.read_tree(good, "test", FMT, VERSION)
    assert record == _record()
    assert set(back) == set(_arrays())
    for name, a in _arrays().items():
        assert back[name].dtype == a.dtype and back[name].shape == a.shape, name
        np.testing.assert_array_equal(back[name], a)
    assert good.is_dir() and archive.is_checkpoint(good) and not archive.is_checkpoint(good, key="meta")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good"]  # no temporary left
    assert threading.active_count() == 1 or all(t.daemon for t in threading.enumerate()[1:])


def test_replacing_a_checkpoint_and_a_failed_write_leave_a_whole_one(good, tmp_path, monkeypatch):
    archive.save_tree(good, {"x": np.ones(4)}, _record(round=2))
    record, back = archive.read_tree(good, "test", FMT, VERSION)
    assert record["round"] == 2 and set(back) == {"x"}
    with pytest.raises(ValueError, match="JSON"):
        archive.save_tree(good, {"x": np.ones(4)}, _record(bad=object()))
    import orbax.checkpoint as ocp

    def interrupted(self, directory, *args, **kwargs):
        (directory / "arrays").mkdir(parents=True)  # half a checkpoint, then the interruption
        raise KeyboardInterrupt

    monkeypatch.setattr(ocp.Checkpointer, "save", interrupted)
    for target in (good, tmp_path / "new"):
        with pytest.raises(KeyboardInterrupt):
            archive.save_tree(target, {"x": np.zeros(4)}, _record(round=3))
    monkeypatch.undo()
    assert archive.read_tree(good, "test", FMT, VERSION)[0]["round"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good"]


def _truncate(path):
    path.write_bytes(path.read_bytes()[: max(1, path.stat().st_size // 3)])


DAMAGES = {
    "arrays metadata deleted": lambda c: (c / "arrays" / "_METADATA").unlink(),
    "arrays metadata truncated": lambda c: _truncate(c / "arrays" / "_METADATA"),
    "manifest truncated": lambda c: _truncate(c / "arrays" / "manifest.ocdbt"),
    "data deleted": lambda c: [p.unlink() for p in (c / "arrays" / "d").iterdir()],
    "data truncated": lambda c: [_truncate(p) for p in (c / "arrays" / "d").iterdir()],
    "record truncated": lambda c: _truncate(c / "record" / "metadata"),
    "record deleted": lambda c: (c / "record" / "metadata").unlink(),
    "orbax metadata deleted": lambda c: (c / "_CHECKPOINT_METADATA").unlink(),
    "record item deleted": lambda c: shutil.rmtree(c / "record"),
}


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_damaged_checkpoint_gets_one_sentence_and_no_log_lines(good, tmp_path, capfd, damage):
    bad = tmp_path / "bad"
    shutil.copytree(good, bad)
    DAMAGES[damage](bad)
    capfd.readouterr()
    for error in (JaxDeformError, MeshFormatError):
        with pytest.raises(error) as err:
            archive.read_tree(bad, "test", FMT, VERSION, error=error)
        _one_sentence(err, bad)
    out, errs = capfd.readouterr()
    assert out == "" and errs == "", (out, errs)


def test_paths_that_are_not_checkpoints_of_the_kind(good, tmp_path):
    (tmp_path / "file").write_text("hello")
    (tmp_path / "empty").mkdir()
    np.savez(tmp_path / "old.npz", x=np.zeros(3))
    cases = {"absent": "no such test", "file": "a file", "empty": "no orbax", "old.npz": "a file"}
    for name, what in cases.items():
        with pytest.raises(JaxDeformError, match=what) as err:
            archive.read_tree(tmp_path / name, "test", FMT, VERSION)
        _one_sentence(err, tmp_path / name)
    with pytest.raises(JaxDeformError, match="its format is") as err:
        archive.read_tree(good, "test", "other", VERSION)
    with pytest.raises(JaxDeformError, match="version 3 is not supported"):
        archive.read_tree(good, "test", FMT, VERSION + 1)
    with pytest.raises(JaxDeformError, match="no orbax"):
        archive.read_tree(good, "test", FMT, VERSION, key="meta")
    with pytest.raises(ValueError, match="arrays"):
        archive.save_tree(tmp_path / "x", {}, _record(), key="arrays")


class _Tiny(nnx.Module):
    def __init__(self):
        self.lin = nnx.Linear(3, 2, rngs=nnx.Rngs(0))
        self.count = nnx.Variable(jnp.zeros((), jnp.int32))


def test_save_module_read_archive_load_state(tmp_path):
    module = _Tiny()
    module.lin.kernel[...] = module.lin.kernel[...] + 1.0
    path = archive.save_module(tmp_path / "m", module, _record(), nnx.Param, extra={"x": np.ones(2)}, key="meta")
    record, arrays = archive.read_archive(path, "tiny", FMT, VERSION, key="meta")
    assert record == _record() and "x" in arrays and not any("count" in k for k in arrays)
    fresh = _Tiny()
    archive.load_state(path, fresh, arrays, nnx.Param)
    np.testing.assert_array_equal(np.asarray(fresh.lin.kernel[...]), np.asarray(module.lin.kernel[...]))
    kernel = next(k for k in arrays if "kernel" in k)
    for broken in ({**arrays, kernel: arrays[kernel][:1]}, {**arrays, kernel: np.full_like(arrays[kernel], np.nan)}):
        archive.save_module(path, module, _record(), nnx.Param, key="meta")
        archive.save_tree(path, broken, _record(), key="meta")
        _, back = archive.read_archive(path, "tiny", FMT, VERSION, key="meta")
        with pytest.raises(JaxDeformError, match="missing, misshapen or not finite") as err:
            archive.load_state(path, _Tiny(), back, nnx.Param)
        _one_sentence(err, path)


def test_cli_refuses_to_replace_what_is_not_a_checkpoint_of_the_kind(good, tmp_path):
    from jaxdeform.cli import common

    mesh = tmp_path / "data" / "a.obj"
    mesh.parent.mkdir()
    mesh.write_text("v 0 0 0\n")
    common.check_out_checkpoint(good, [mesh], "test checkpoint")  # replacing a checkpoint of the kind
    common.check_out_checkpoint(tmp_path / "new", [mesh], "test checkpoint")
    with pytest.raises(FileExistsError, match="not a feature-field"):
        common.check_out_checkpoint(good, [mesh], "feature-field checkpoint", key="meta")
    with pytest.raises(ValueError, match="would replace the input"):
        common.check_out_checkpoint(tmp_path / "data", [mesh], "test checkpoint")
    with pytest.raises(NotADirectoryError):
        common.check_out_checkpoint(mesh / "field", [], "test checkpoint")
