"""The run-folder API shared by the four methods.

Every method package has a ``run`` module with the same entry points, and every run folder it writes holds a
``run.json`` whose ``"kind"`` names the method:

==============  ================================  =================================================================
kind            module                            ``data``
==============  ================================  =================================================================
``components``  :mod:`jaxdeform.components.run`   a folder (or a list) of shapes sharing one mesh
``cloth``       :mod:`jaxdeform.cloth.run`        a paired coarse/fine cloth dataset folder
``parts``       :mod:`jaxdeform.parts.run`        a folder (or a list) of at least two shapes sharing one mesh
``handles``     :mod:`jaxdeform.handles.run`      one mesh file
==============  ================================  =================================================================

Each module provides

- ``KIND`` (the name above) and ``CONFIGS``: named frozen-dataclass configurations, at least ``"default"``
  (the paper's settings) and ``"test"`` (runs in seconds on a CPU);
- ``fit(data, config, out, *, progress=True, **options) -> Run``: fits the method to ``data`` with ``config``
  (a name of ``CONFIGS`` or a configuration object) and writes the run folder ``out``; the folder is built
  beside ``out`` and renamed at the end, so a failed fit leaves no half-written run;
- ``Run.load(path) -> Run``: reads a run folder (one-sentence :class:`~jaxdeform.errors.JaxDeformError` for
  a folder that is not one of the method's runs); every ``Run`` has ``path`` and ``record`` (run.json);
- ``evaluate(run, data=None) -> dict``: the method's metrics of the run on ``data`` (None: the data it was
  fitted to, as run.json records it);
- ``show(run, out) -> dict``: figures of the run written into the folder ``out``, and their summary.

The functions below read the kind of a folder and dispatch to its module; method modules are imported only when
a run of theirs is met. :func:`resumable` is how the trained methods (components, cloth) build a run folder that
an interrupted training can continue (``fit(..., resume=True)``).
"""

from __future__ import annotations

import contextlib
import importlib
import json
import math
import os
import shutil
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol

from jaxdeform.errors import JaxDeformError

#: the run module of every kind
KINDS: dict[str, str] = {
    "components": "jaxdeform.components.run",
    "cloth": "jaxdeform.cloth.run",
    "parts": "jaxdeform.parts.run",
    "handles": "jaxdeform.handles.run",
}
#: the record every run folder holds
RECORD = "run.json"


class RunFolderError(JaxDeformError):
    """A folder is not a run folder of any method, or names an unknown one."""


class Run(Protocol):
    """What every method's run offers (:mod:`jaxdeform.runs`)."""

    path: Path | None
    record: dict

    @classmethod
    def load(cls, path: str | os.PathLike) -> Run: ...


def read_record(path: str | os.PathLike, kind: str | None = None) -> dict:
    """The run.json of a run folder, checked to name a known kind (``kind`` where given).

    **Arguments:**

    - ``path``: the run folder.
    - ``kind``: the kind the run must be (None: any known kind).

    **Returns:**

    The record (a dict with a ``"kind"`` of :data:`KINDS`).

    **Raises:**

    :class:`RunFolderError` (one sentence) if ``path`` is not a folder, has no run.json, or its run.json is not a
    JSON object naming a known kind, or names another kind than ``kind``.
    """
    path = Path(path)
    if not path.is_dir():
        raise RunFolderError(f"{path}: no such run folder.")
    file = path / RECORD
    if not file.is_file():
        raise RunFolderError(f"{path} is not a run folder ({RECORD} is missing).")
    try:
        record = json.loads(file.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RunFolderError(f"{file} is not a readable run record ({type(exc).__name__}).") from None
    if not isinstance(record, dict) or record.get("kind") not in KINDS:
        named = record.get("kind") if isinstance(record, dict) else None
        raise RunFolderError(f"{file} names no known kind of run ({named!r}; expected one of {', '.join(KINDS)}).")
    if kind is not None and record["kind"] != kind:
        raise RunFolderError(f"{path} is a {record['kind']} run, not a {kind} run.")
    return record


#: what each JSON type name of :func:`check_fields` accepts (a bool is not a number)
_JSON_TYPES = {
    "object": lambda x: isinstance(x, dict),
    "list": lambda x: isinstance(x, list),
    "string": lambda x: isinstance(x, str),
    "number": lambda x: isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x),
    "integer": lambda x: isinstance(x, int) and not isinstance(x, bool),
    "boolean": lambda x: isinstance(x, bool),
    "null": lambda x: x is None,
}


def check_fields(where: str | os.PathLike, record: dict, fields: dict[str, tuple[str, ...]], optional=()) -> None:
    """Check the types of a run record's fields.

    **Arguments:**

    - ``where``: names the record (its run.json) in the message.
    - ``record``: the record.
    - ``fields``: for each field, the JSON types it may take (``"object"``, ``"list"``, ``"string"``,
      ``"number"`` (finite), ``"integer"``, ``"boolean"``, ``"null"``).
    - ``optional``: fields that may be absent (records written before they existed).

    **Raises:**

    :class:`RunFolderError`, one sentence naming the first field that is missing or of another type.
    """
    for name, types in fields.items():
        if name not in record:
            if name in optional:
                continue
            raise RunFolderError(f"{where}: its {name!r} field is missing.")
        if not any(_JSON_TYPES[t](record[name]) for t in types):
            got = "null" if record[name] is None else type(record[name]).__name__
            raise RunFolderError(f"{where}: its {name!r} field must be {' or '.join(types)}, got {got}.")


def check_fingerprint(where: str | os.PathLike, record: dict, vertices, faces, what: str) -> None:
    """Check that arrays a run folder holds are the data its record's ``"fingerprint"`` names (records without
    one pass).

    **Arguments:**

    - ``where``: names the record in the message.
    - ``record``: the run record.
    - ``vertices``, ``faces``: the arrays (as :func:`jaxdeform.mesh.fingerprint.fingerprint` takes them).
    - ``what``: names the arrays' file in the message.

    **Raises:**

    :class:`RunFolderError`, one sentence, for a malformed fingerprint or arrays that differ from it.
    """
    from jaxdeform.mesh.fingerprint import difference, malformed

    if "fingerprint" not in record:
        return
    problem = malformed(record["fingerprint"])
    if problem is not None:
        raise RunFolderError(f"{where}: its fingerprint {problem}.")
    differs = difference(record["fingerprint"], vertices, faces, rtol=0.0, whose="the recorded data")
    if differs is not None:
        raise RunFolderError(f"{where}: {what} is not the data the record fingerprints ({differs}).")


def module(kind: str) -> ModuleType:
    """The run module of a kind.

    **Arguments:**

    - ``kind``: one of :data:`KINDS`.

    **Returns:**

    The imported module (``fit``, ``Run``, ``evaluate``, ``show``, ``CONFIGS``).

    **Raises:**

    ``ValueError`` for an unknown kind.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown kind of run {kind!r}; expected one of {', '.join(KINDS)}.")
    return importlib.import_module(KINDS[kind])


def kind_of(path: str | os.PathLike) -> str:
    """The kind of the run folder ``path`` (its run.json's ``"kind"``; errors as :func:`read_record`)."""
    return read_record(path)["kind"]


def load(path: str | os.PathLike) -> Run:
    """Load any method's run folder.

    **Arguments:**

    - ``path``: a run folder written by one of the methods' ``fit``.

    **Returns:**

    The method's ``Run``.

    **Raises:**

    :class:`RunFolderError` if ``path`` is not a run folder; the method's own one-sentence error for a damaged one.
    """
    return module(kind_of(path)).Run.load(path)


def fit(kind: str, data: Any, config: Any, out: str | os.PathLike, **options) -> Run:
    """Fit a method and write its run folder.

    **Arguments:**

    - ``kind``: one of :data:`KINDS`.
    - ``data``: the method's data (the module docstring's table).
    - ``config``: a name of the method's ``CONFIGS`` or one of its configuration objects.
    - ``out``: the run folder to write.
    - ``options``: the method's own keyword options (e.g. ``progress``).

    **Returns:**

    The method's ``Run``, loaded from ``out``.
    """
    return module(kind).fit(data, config, out, **options)


def _kind_of_run(run: Run) -> str:
    kind = run.record.get("kind") if isinstance(getattr(run, "record", None), dict) else None
    if kind not in KINDS:
        raise ValueError(f"{type(run).__name__} is not a run of a known kind (its record names {kind!r}).")
    return kind


def evaluate(run: Run, data: Any = None) -> dict:
    """The metrics of any method's run (the method's ``evaluate``).

    **Arguments:**

    - ``run``: a run of one of the methods.
    - ``data``: the data to evaluate on (None: the data the run was fitted to).

    **Returns:**

    The method's metrics dict.
    """
    return module(_kind_of_run(run)).evaluate(run, data)


def show(run: Run, out: str | os.PathLike) -> dict:
    """The figures of any method's run (the method's ``show``).

    **Arguments:**

    - ``run``: a run of one of the methods.
    - ``out``: the folder to write the figures into.

    **Returns:**

    The summary of what was written.
    """
    return module(_kind_of_run(run)).show(run, Path(out))


def config(kind: str, value: Any, cls: type | None = None):
    """A method's configuration from a name of its ``CONFIGS`` or a configuration object.

    **Arguments:**

    - ``kind``: one of :data:`KINDS`.
    - ``value``: a name (str) or a configuration object (returned as is).
    - ``cls``: the method's configuration class (None: not checked).

    **Returns:**

    The configuration.

    **Raises:**

    ``ValueError`` for an unknown name; ``TypeError`` for an object that is not a ``cls``.
    """
    if isinstance(value, str):
        configs = module(kind).CONFIGS
        if value not in configs:
            raise ValueError(f"{kind} has no configuration {value!r}; expected one of {', '.join(configs)}.")
        value = configs[value]
    if cls is not None and not isinstance(value, cls):
        raise TypeError(f"a {kind} configuration must be a name or a {cls.__name__}, got {type(value).__name__}.")
    return value


#: the settings of a fit, kept in its partial folder (what ``resume`` compares)
RESUME_FILE = "fit-settings.json"


def partial_folder(out: str | os.PathLike) -> Path:
    """The folder a resumable fit of the run folder ``out`` is built in: the hidden sibling ``.NAME.partial``."""
    out = Path(out)
    return out.parent / f".{out.name}.partial"


@contextlib.contextmanager
def resumable(out: Path, settings: dict, resume: bool, log=print):
    """Build the run folder ``out`` in :func:`partial_folder` and rename it onto ``out`` when the block succeeds.

    **Arguments:**

    - ``out``: the run folder.
    - ``settings``: JSON values that identify the fit (method, configuration, data, seeds); kept in the partial
      folder.
    - ``resume``: reuse a partial folder kept by an interrupted fit of equal ``settings``; without it a kept
      partial folder is discarded.
    - ``log``: receives one line when a fit resumes or finds nothing to resume.

    **Yields:**

    ``(folder, resuming)``: the folder to fill (its ``checkpoints`` or ``params`` subfolders are what a training
    resumes from) and whether it holds a kept partial fit.

    **Raises:**

    ``JaxDeformError`` for ``resume`` with a partial fit of other settings. An exception that is not an
    ``Exception`` (Ctrl-C, a termination signal) keeps the partial folder when it holds a checkpoint (a step
    folder of orbax); any other removes it.
    """
    from jaxdeform.mesh.io import staged_folder

    staging = partial_folder(out)
    resuming = False
    if staging.exists():
        try:
            kept = json.loads((staging / RESUME_FILE).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            kept = None
        if resume and kept == settings:
            resuming = True
            log(f"resuming the interrupted fit kept in {staging}")
        elif resume:
            differ = sorted(k for k in settings if not isinstance(kept, dict) or kept.get(k) != settings[k])
            raise JaxDeformError(
                f"the interrupted fit kept in {staging} was started with other settings ({', '.join(differ)}); "
                "run without --resume to start afresh."
            )
        else:
            shutil.rmtree(staging)
    elif resume:
        log(f"no interrupted fit in {staging}; starting from the first step")

    def keep(folder: Path) -> bool:
        return any(p.name.isdigit() for sub in ("params", "checkpoints") for p in (folder / sub).glob("*"))

    with staged_folder(out, staging=staging, keep=keep) as tmp:
        (tmp / RESUME_FILE).write_text(json.dumps(settings))
        yield tmp, resuming
        (tmp / RESUME_FILE).unlink()
