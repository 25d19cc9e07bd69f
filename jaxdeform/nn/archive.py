"""One ``.npz`` per trained flax nnx module: its state arrays plus a JSON record, written atomically.

Layout: ``param:<keystr of the state path>`` for every array of the module's state (or of the part selected
by ``what``, e.g. ``nnx.Param``), any extra arrays the caller adds, and ``record`` (or another ``key``: a JSON
string holding at least ``format`` and ``version``). Readers get one-sentence
:class:`~jaxdeform.errors.JaxDeformError` for a missing file, a file that is not an archive, another format or
version, or a parameter that is missing, misshapen or not finite. Used by the feature field of seed 004 and the
cloth models of seed 002.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from jaxdeform.errors import JaxDeformError, MeshFormatError
from jaxdeform.mesh.io import atomic_path, read_npz_arrays

PREFIX = "param:"


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


def save_module(
    path: str | os.PathLike,
    module: nnx.Module,
    record: dict,
    *what,
    extra: dict[str, np.ndarray] | None = None,
    key: str = "record",
) -> Path:
    """Write a module's archive atomically.

    **Arguments:**

    - `path`: the .npz file.
    - `module`: the flax nnx module.
    - `record`: a JSON-serialisable dict (at least `format` and `version`).
    - `what`: nnx state filters (default: all of the state).
    - `extra`: more arrays to store.
    - `key`: the name of the record's entry.

    **Returns:**

    The path written.

    **Raises:**

    `ValueError` when `record` is not JSON-serialisable.
    """
    try:
        text = json.dumps(record)
    except TypeError as exc:
        raise ValueError(f"meta must be JSON-serialisable ({exc}).") from None
    arrays = state_arrays(module, *what)
    arrays.update(extra or {})
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **{key: np.asarray(text)}, **arrays)
    return path


def read_archive(
    path: str | os.PathLike, what: str, fmt: str, version: int, key: str = "record"
) -> tuple[dict, dict[str, np.ndarray]]:
    """Read an archive and check its format and version.

    **Arguments:**

    - `path`: the .npz file.
    - `what`: names the kind of file in the messages.
    - `fmt`: the expected format.
    - `version`: the expected version.
    - `key`: the name of the record's entry.

    **Returns:**

    `(record, arrays)`: the record dict and the remaining arrays by name.

    **Raises:**

    `JaxDeformError` (one sentence) for a missing file, a file that is not an archive, another format or
    version.
    """
    path = Path(path)
    if not path.is_file():
        raise JaxDeformError(f"{path}: no such {what} file.")
    try:
        arrays = read_npz_arrays(path)
    except MeshFormatError as exc:
        why = str(exc).split(": ", 1)[-1].rstrip(".")
        raise JaxDeformError(f"{path}: not a {what} archive ({why}).") from None
    try:
        record = json.loads(str(arrays.pop(key)))
        if not isinstance(record, dict) or record.get("format") != fmt:
            raise ValueError("format")
    except (KeyError, ValueError, TypeError) as exc:
        raise JaxDeformError(f"{path}: not a jaxdeform {what} file ({type(exc).__name__}: {exc}).") from None
    if record.get("version") != version:
        raise JaxDeformError(f"{path}: {what} format version {record.get('version')} is not supported.")
    return record, arrays


def load_state(path: str | os.PathLike, module: nnx.Module, arrays: dict[str, np.ndarray], *what) -> None:
    """Fill the module's state from archive arrays, checking every array.

    **Arguments:**

    - `path`: the archive's path, for the messages.
    - `module`: the flax nnx module, updated in place.
    - `arrays`: the arrays from :func:`read_archive`.
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
    """Mixin for frozen dataclass configurations that archive records carry as plain dicts."""

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
