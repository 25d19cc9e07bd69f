"""Checkpoints with orbax: one folder per trained module or fitted model, its arrays plus a JSON record.

Layout of a checkpoint folder ``PATH`` (written by an orbax ``Checkpointer`` with a composite handler):

- ``PATH/arrays/``: an orbax PyTree item (OCDBT), a flat dict of NumPy arrays by name: ``param:<keystr of the
  state path>`` for every array of a module's state (or of the part selected by ``what``, e.g. ``nnx.Param``)
  and any extra arrays the caller adds;
- ``PATH/<key>/``: an orbax JSON item, the record (``record`` by default, another ``key`` where the caller
  says): at least ``format`` and ``version``; arrays of zero size (which orbax does not store) are listed there
  under ``__empty__`` and rebuilt on reading;
- ``PATH/_CHECKPOINT_METADATA``: orbax's own.

Writes are synchronous and atomic: the checkpoint is written into a temporary sibling folder and renamed onto
``PATH``, replacing what was there only once it is complete; on an error nothing is left at ``PATH`` but what
was there before. Reading needs no target structure: the raw arrays come back, and :func:`load_state` checks
them against a module. Readers get one-sentence :class:`~jaxdeform.errors.JaxDeformError` (or the subclass the
caller names) for a missing path, a path that is not an orbax checkpoint (a file, an empty or foreign folder, a
damaged checkpoint), another format or version, or a parameter that is missing, misshapen or not finite; orbax's
log lines are held back while it works, and after a damaged read the "Event loop is closed" reports of orbax's
reads still pending are dropped (a filter put once in front of ``sys.unraisablehook``; everything else passes).
orbax is imported inside the functions, so importing this module does not load it. Used by the cloth models of
seed 002, the parts models of seed 003, the feature field of seed 004 and the linear baselines of seed 000.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from jaxdeform.errors import JaxDeformError

PREFIX = "param:"
#: the orbax item holding the arrays
ARRAYS = "arrays"
#: the record's entry listing the zero-size arrays (name -> [shape, dtype])
EMPTY = "__empty__"


def state_arrays(module: nnx.Module, *what) -> dict[str, np.ndarray]:
    """The module's state arrays by archive name.

    **Arguments:**

    - `module`: a flax nnx module.
    - `what`: nnx state filters (default: all of the state).

    **Returns:**

    `{param:<path>: array}` of numpy arrays.
    """
    leaves = jax.tree_util.tree_flatten_with_path(nnx.state(module, *what))[0]
    return {PREFIX + jax.tree_util.keystr(path): np.asarray(leaf) for path, leaf in leaves}


@contextlib.contextmanager
def _quiet():
    """Hold back orbax's (absl) log lines while it works; the logger's level is restored after."""
    logger = logging.getLogger("absl")
    level = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(level)


def _unraisable(hook):
    """An unraisable-exception hook that drops the 'Event loop is closed' of orbax's reads left pending when a
    damaged checkpoint failed (their completion reaches a loop orbax has closed) and passes the rest to ``hook``."""

    def filtered(u):
        exc = u.exc_value
        if isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed" and u.object is None:
            return
        hook(u)

    filtered._jaxdeform_filter = True
    return filtered


def _staged(path: Path, write) -> None:
    """Call ``write(folder)`` on a fresh folder in a temporary sibling of ``path``, then put it at ``path``
    (an existing entry there is moved aside first, put back on an error, removed on success)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    trash = None
    try:
        write((tmp / "checkpoint").absolute())
        if path.exists() or path.is_symlink():
            trash = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            os.replace(path, trash / "old")
        os.replace(tmp / "checkpoint", path)
    except BaseException:
        if trash is not None and (trash / "old").exists() and not (path.exists() or path.is_symlink()):
            os.replace(trash / "old", path)  # put the old checkpoint back
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True)


def save_tree(path: str | os.PathLike, arrays: dict[str, np.ndarray], record: dict, key: str = "record") -> Path:
    """Write arrays and a JSON record as one orbax checkpoint folder, atomically.

    **Arguments:**

    - `path`: the checkpoint folder (replaced if it exists; its parent is created if missing).
    - `arrays`: NumPy arrays by name (names are free text; zero-size arrays are allowed).
    - `record`: a JSON-serialisable dict (at least `format` and `version`).
    - `key`: the name of the record's item.

    **Returns:**

    The path written.

    **Raises:**

    `ValueError` when `record` is not JSON-serialisable or `key` names the arrays' item.
    """
    import orbax.checkpoint as ocp

    if key == ARRAYS:
        raise ValueError(f"the record cannot be stored under {ARRAYS!r}, the arrays' item.")
    arrays = {str(k): np.asarray(v) for k, v in arrays.items()}
    empty = {k: [list(a.shape), a.dtype.str] for k, a in arrays.items() if a.size == 0}
    record = {**record, EMPTY: empty} if empty else dict(record)
    try:
        record = json.loads(json.dumps(record))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"meta must be JSON-serialisable ({exc}).") from None
    tree = {k: a for k, a in arrays.items() if a.size}
    items = {key: ocp.args.JsonSave(record)}
    if tree:
        items[ARRAYS] = ocp.args.PyTreeSave(tree)

    def write(folder):
        with _quiet():
            ocp.Checkpointer(ocp.CompositeCheckpointHandler()).save(folder, args=ocp.args.Composite(**items))

    path = Path(path)
    _staged(path, write)
    return path


def is_checkpoint(path: str | os.PathLike, key: str = "record") -> bool:
    """Whether ``path`` looks like a checkpoint folder of this module (orbax's metadata and a ``key`` item).

    **Arguments:**

    - `path`: the path.
    - `key`: the name of the record's item.

    **Returns:**

    True for a folder holding ``_CHECKPOINT_METADATA`` and ``key/`` (its contents are not read).
    """
    path = Path(path)
    return (path / "_CHECKPOINT_METADATA").is_file() and (path / key).is_dir()


def _restore(path: Path, key: str) -> tuple[object, object]:
    """The raw record and arrays of the checkpoint folder ``path`` (arrays ``{}`` where it stores none)."""
    import orbax.checkpoint as ocp

    items = {key: ocp.args.JsonRestore()}
    if (path / ARRAYS).is_dir():
        items[ARRAYS] = ocp.args.PyTreeRestore()
    with _quiet():
        out = ocp.Checkpointer(ocp.CompositeCheckpointHandler()).restore(
            path.absolute(), args=ocp.args.Composite(**items)
        )
    return out[key], (out[ARRAYS] if ARRAYS in items else {})


def _read(path: Path, what: str, key: str, error: type[JaxDeformError]) -> tuple[object, dict[str, np.ndarray]]:
    """The raw record and the arrays (zero-size ones rebuilt) of a checkpoint, or one-sentence ``error``."""
    if not path.exists():
        raise error(f"{path}: no such {what} checkpoint.")
    if not path.is_dir():
        raise error(f"{path}: not a {what} checkpoint (a file; a checkpoint is an orbax folder).")
    if not is_checkpoint(path, key):
        raise error(f"{path}: not a {what} checkpoint (no orbax checkpoint with a '{key}' item there).")
    try:
        record, arrays = _restore(path, key)
    except Exception as exc:  # orbax, tensorstore and json raise many types for damaged files
        if not getattr(sys.unraisablehook, "_jaxdeform_filter", False):
            sys.unraisablehook = _unraisable(sys.unraisablehook)
        status = re.match(r"[A-Z_]+(?=:)", str(exc))  # tensorstore's status code, e.g. DATA_LOSS
        why = type(exc).__name__ + (f" {status.group()}" if status else "")
        raise error(f"{path}: a damaged {what} checkpoint (orbax could not read it: {why}).") from None
    if not isinstance(arrays, dict) or not all(isinstance(a, np.ndarray) for a in arrays.values()):
        raise error(f"{path}: not a {what} checkpoint (its arrays are not a flat dict of arrays).")
    arrays = dict(arrays)
    if isinstance(record, dict) and EMPTY in record:
        record = dict(record)
        try:
            for name, (shape, dtype) in record.pop(EMPTY).items():
                arrays[name] = np.zeros(shape, np.dtype(dtype))
        except (TypeError, ValueError, AttributeError):
            raise error(f"{path}: not a {what} checkpoint (its list of empty arrays is malformed).") from None
    return record, arrays


def read_tree(
    path: str | os.PathLike,
    what: str,
    fmt: str,
    version: int,
    key: str = "record",
    error: type[JaxDeformError] = JaxDeformError,
) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a checkpoint folder written by :func:`save_tree` (or :func:`save_module`) and check its format and
    version.

    **Arguments:**

    - `path`: the checkpoint folder.
    - `what`: names the kind of checkpoint in the messages.
    - `fmt`: the expected format.
    - `version`: the expected version.
    - `key`: the name of the record's item.
    - `error`: the exception type raised (a :class:`~jaxdeform.errors.JaxDeformError` subclass).

    **Returns:**

    `(record, arrays)`: the record dict and the arrays by name (NumPy, as stored).

    **Raises:**

    `error` (one sentence) for a missing path, a path that is not an orbax checkpoint or a damaged one, another
    format or version.
    """
    path = Path(path)
    record, arrays = _read(path, what, key, error)
    if not isinstance(record, dict) or record.get("format") != fmt:
        got = record.get("format") if isinstance(record, dict) else type(record).__name__
        raise error(f"{path}: not a jaxdeform {what} checkpoint (its format is {got!r}, not {fmt!r}).")
    if record.get("version") != version:
        raise error(f"{path}: {what} format version {record.get('version')} is not supported.")
    return record, arrays


def save_module(
    path: str | os.PathLike,
    module: nnx.Module,
    record: dict,
    *what,
    extra: dict[str, np.ndarray] | None = None,
    key: str = "record",
) -> Path:
    """Write a module's checkpoint atomically (:func:`save_tree` of its state arrays and ``extra``).

    **Arguments:**

    - `path`: the checkpoint folder.
    - `module`: the flax nnx module.
    - `record`: a JSON-serialisable dict (at least `format` and `version`).
    - `what`: nnx state filters (default: all of the state).
    - `extra`: more arrays to store.
    - `key`: the name of the record's item.

    **Returns:**

    The path written.

    **Raises:**

    `ValueError` when `record` is not JSON-serialisable.
    """
    arrays = state_arrays(module, *what)
    arrays.update(extra or {})
    return save_tree(path, arrays, record, key=key)


def read_archive(
    path: str | os.PathLike, what: str, fmt: str, version: int, key: str = "record"
) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a module's checkpoint and check its format and version (:func:`read_tree`).

    **Arguments:**

    - `path`: the checkpoint folder.
    - `what`: names the kind of checkpoint in the messages.
    - `fmt`: the expected format.
    - `version`: the expected version.
    - `key`: the name of the record's item.

    **Returns:**

    `(record, arrays)`: the record dict and the arrays by name.

    **Raises:**

    `JaxDeformError` (one sentence) for a missing path, a path that is not an orbax checkpoint or a damaged one,
    another format or version.
    """
    return read_tree(path, what, fmt, version, key=key)


def load_state(path: str | os.PathLike, module: nnx.Module, arrays: dict[str, np.ndarray], *what) -> None:
    """Fill the module's state from checkpoint arrays, checking every array.

    **Arguments:**

    - `path`: the checkpoint's path, for the messages.
    - `module`: the flax nnx module, updated in place.
    - `arrays`: the arrays from :func:`read_archive` or :func:`read_tree`.
    - `what`: nnx state filters (default: all of the state).

    **Raises:**

    `JaxDeformError` for a parameter that is missing, misshapen or not finite.
    """
    state = nnx.state(module, *what)
    leaves, treedef = jax.tree_util.tree_flatten_with_path(state)
    new = []
    for key_path, leaf in leaves:
        name = PREFIX + jax.tree_util.keystr(key_path)
        arr = arrays.get(name)
        if arr is None or arr.shape != np.shape(leaf) or not np.all(np.isfinite(arr)):
            raise JaxDeformError(f"{path}: the parameter {name[len(PREFIX) :]} is missing, misshapen or not finite.")
        new.append(jnp.asarray(arr, dtype=leaf.dtype))
    nnx.update(module, jax.tree_util.tree_unflatten(treedef, new))


class RecordConfig:
    """Mixin for frozen dataclass configurations that checkpoint records carry as plain dicts."""

    def to_dict(self) -> dict:
        """The configuration as a plain dict."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict):
        """The configuration from a plain dict.

        **Arguments:**

        - `d`: field values by name.

        **Returns:**

        The configuration.

        **Raises:**

        `ValueError` for unknown keys.
        """
        unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown {cls.__name__} keys: {', '.join(sorted(unknown))}.")
        return cls(**d)


class StepCheckpoints:
    """Training checkpoints in ``directory``: one orbax step folder per saved step, the newest two kept; saves
    are synchronous. What the components' and the cloth models' trainings resume from.

    ``latest()`` is the newest saved step (None: none); ``save(step, state)`` writes a pytree of arrays;
    ``restore(step, like)`` reads one back in the structure and dtypes of ``like``.
    """

    def __init__(self, directory, every: int = 1):
        import orbax.checkpoint as ocp

        self._ocp = ocp
        self.every = every
        opts = ocp.CheckpointManagerOptions(max_to_keep=2, enable_async_checkpointing=False)
        self.manager = ocp.CheckpointManager(Path(directory).absolute(), options=opts)

    def latest(self) -> int | None:
        return self.manager.latest_step()

    def save(self, step: int, state) -> None:
        self.manager.save(step, args=self._ocp.args.StandardSave(state))
        self.manager.wait_until_finished()

    def restore(self, step: int, like):
        return self.manager.restore(step, args=self._ocp.args.StandardRestore(like))
