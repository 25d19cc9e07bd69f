"""What every command shares: the error contract, output checks and atomic outputs, and the shared options.

Error contract: an expected failure (a :class:`~jaxdeform.errors.JaxDeformError`, a ``ValueError`` from bad
arguments, a missing file or another ``OSError``) prints exactly one line ``jaxdeform: error: <sentence>`` to
stderr and the command returns 2, leaving no output behind. Ctrl-C (SIGINT) and SIGTERM end the command with one
line ``jaxdeform: interrupted; ...`` and status 130 or 143, after the outputs being staged are removed (a training
run's checkpoints are kept where the command says so). Unexpected exceptions propagate with their traceback.

This module imports only the standard library and :mod:`jaxdeform.errors`; the libraries a command needs are
imported when it runs.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from jaxdeform.errors import JaxDeformError

PROG = "jaxdeform"
MARKER = ".jaxdeform"  # the file every staged output folder holds (jaxdeform.mesh.io.OUTPUT_MARKER)
MESH_OUT = (".obj", ".ply", ".off")  # the formats save_mesh writes one mesh in


# --------------------------------------------------------------------------------------- error contract


def message(exc: BaseException) -> str:
    """``exc`` as one sentence on one line (a system error as ``path: reason.``)."""
    if isinstance(exc, OSError) and exc.strerror:  # a system error: "[Errno 2] ..." -> "path: reason."
        where = f"{exc.filename}: " if exc.filename else ""
        text = f"{where}{exc.strerror}."
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())


def setup_process() -> None:
    """The command's process settings: it computes in float64 where its inputs are float64 (a program's own
    setting, not the library's)."""
    import jax

    jax.config.update("jax_enable_x64", True)


class Terminated(BaseException):
    """Raised in the command's main thread on SIGTERM, so that staged outputs are cleaned up as on Ctrl-C."""


class Interrupted(BaseException):
    """A command interrupted after it kept something on purpose; ``str(exc)`` says what and where."""


def _on_sigterm(signum, frame) -> None:
    raise Terminated()


def run_command(func: Callable[[argparse.Namespace], int | None], args: argparse.Namespace) -> int:
    """Run a parsed command; an expected failure becomes one ``jaxdeform: error:`` line and exit status 2,
    Ctrl-C one ``jaxdeform: interrupted;`` line and status 130 (143 for SIGTERM)."""
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return int(func(args) or 0)
    except (JaxDeformError, ValueError, OSError) as exc:  # FileNotFoundError is an OSError
        print(f"{PROG}: error: {message(exc)}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, Terminated, Interrupted) as exc:
        status = 143 if isinstance(exc, Terminated) or isinstance(exc.__context__, Terminated) else 130
        what = str(exc) if isinstance(exc, Interrupted) else "nothing was written"
        print(f"{PROG}: interrupted; {what}.", file=sys.stderr)
        return status
    finally:
        signal.signal(signal.SIGTERM, previous)


# ---------------------------------------------------------------------------------------- shared options


def add_out(p: argparse.ArgumentParser, metavar: str, help: str | None, required: bool = True) -> None:
    p.add_argument("--out", "-o", required=required, metavar=metavar, help=help)


def add_json(p: argparse.ArgumentParser, help: str | None = None, required: bool = False) -> None:
    p.add_argument("--json", required=required, metavar="OUT.json", help=help)


def add_data(p: argparse.ArgumentParser, help: str, required: bool = False) -> None:
    """``--data DATA...``: the mesh files or folders a run was trained on."""
    p.add_argument("--data", nargs="+", required=required, metavar="DATA", help=help)


def add_seed(p: argparse.ArgumentParser, help: str | None = None, default: int | None = None) -> None:
    p.add_argument("--seed", type=int, default=default, metavar="S", help=help)


def add_steps(p: argparse.ArgumentParser, help: str, default: int | None = None) -> None:
    p.add_argument("--steps", type=int, default=default, metavar="N", help=help)


def add_quiet(p: argparse.ArgumentParser, help: str = "no progress bars") -> None:
    """``--quiet``: the command's progress bars off."""
    p.add_argument("--quiet", action="store_true", help=help)


def status(args: argparse.Namespace, text: str) -> None:
    """One status line ``jaxdeform: <text>`` on stderr before a wait of more than a few seconds, when stderr is a
    terminal (a captured stderr keeps the one-line error contract) and ``--quiet`` is not given."""
    if not getattr(args, "quiet", False) and sys.stderr.isatty():
        print(f"{PROG}: {text}", file=sys.stderr, flush=True)


def add_force(p: argparse.ArgumentParser, help: str) -> None:
    p.add_argument("--force", action="store_true", help=help)


def steps_seed(cfg, args: argparse.Namespace):
    """``cfg`` (a frozen dataclass with ``steps`` and ``seed``) with the --steps / --seed given, checked."""
    from dataclasses import replace

    if args.steps is not None:
        if args.steps < 1:
            raise ValueError(f"--steps must be positive, got {args.steps}.")
        cfg = replace(cfg, steps=args.steps)
    return cfg if args.seed is None else replace(cfg, seed=args.seed)


# ------------------------------------------------------------------------------------ inputs and outputs


def data_arg(paths: Sequence[str]):
    """A ``DATA...`` argument as the library takes it: one path as itself, several as a list."""
    return list(paths) if len(paths) > 1 else paths[0]


def check_exists(paths: Sequence[str]) -> None:
    for p in paths:
        if not Path(p).exists():
            raise FileNotFoundError(f"{p}: no such file or folder.")


@contextlib.contextmanager
def writing(path: Path):
    """Re-raise a system error met while writing ``path`` as one sentence naming ``path``, not a temporary."""
    try:
        yield
    except OSError as exc:
        if exc.strerror is None:
            raise
        raise OSError(f"cannot write {path}: {exc.strerror}.") from None


def check_out_folder(out: Path, force: bool, inputs: Sequence[str | os.PathLike] = ()) -> None:
    """--out must be a folder, empty unless --force, and neither one of ``inputs`` nor a folder holding one
    (replacing it would delete what the command reads)."""
    target = out.resolve()
    for p in inputs:
        src = Path(p).resolve()
        if src == target or target in src.parents:
            raise ValueError(f"--out {out} would replace the input {p}; write the output elsewhere.")
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out} exists and is not a folder.")
    blocking = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise NotADirectoryError(f"--out {out} cannot be created: {blocking} is a file, not a folder.")
    if out.is_dir() and any(out.iterdir()):
        if not force:
            raise FileExistsError(f"--out {out} exists and is not empty; use --force to replace it.")
        if not is_jaxdeform_output(out):
            raise FileExistsError(
                f"--out {out} holds files jaxdeform did not write (no {MARKER} marker); --force replaces only "
                "jaxdeform's own output folders: give a new path or remove the folder yourself."
            )


def is_jaxdeform_output(folder: Path) -> bool:
    """Whether ``folder`` is an output folder jaxdeform wrote (it holds the marker file that
    :func:`jaxdeform.mesh.io.staged_folder` puts in every folder it stages)."""
    return (Path(folder) / MARKER).is_file()


def check_out_checkpoint(out: Path, inputs: Sequence[str | os.PathLike], what: str, key: str = "record") -> None:
    """An output checkpoint (a folder, :mod:`jaxdeform.nn.archive`) must be new or a checkpoint of the same kind
    (replaced whole), and neither one of ``inputs`` nor a folder holding one."""
    from jaxdeform.nn.archive import is_checkpoint

    target = out.resolve()
    for p in inputs:
        src = Path(p).resolve()
        if src == target or target in src.parents:
            raise ValueError(f"--out {out} would replace the input {p}; write the output elsewhere.")
    blocking = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise NotADirectoryError(f"--out {out} cannot be created: {blocking} is a file, not a folder.")
    if (out.exists() or out.is_symlink()) and not is_checkpoint(out, key):
        raise FileExistsError(f"--out {out} exists and is not a {what} to replace; give a new path.")


def check_out_file(
    out: Path,
    suffixes: Sequence[str],
    inputs: Sequence[str | os.PathLike],
    what: str,
    option: str = "--out",
    protect: Sequence[str | os.PathLike] = (),
) -> None:
    """An output file must not be a folder, must end in one of ``suffixes`` (the format written), and must be
    neither one of ``inputs``, nor a file already in an input folder, nor a mesh file added to an input folder
    (which the command reads whole); nor one of the files in ``protect`` (a run folder's own files: other files,
    such as earlier metrics, may be replaced there)."""
    from jaxdeform.mesh.io import SEQUENCE_SUFFIXES

    if out.is_dir():
        raise IsADirectoryError(f"{option} {out} is a folder; give the path of the {what} to write.")
    if suffixes and out.suffix.lower() not in suffixes:
        raise ValueError(f"{option} {out} must end in {' or '.join(suffixes)} (the {what} written).")
    target = out.resolve()
    for p in inputs:
        src = Path(p).resolve()
        if src == target:
            raise ValueError(f"{option} {out} would replace the input {p}; write the output elsewhere.")
        if src.is_dir() and target.parent == src and target.suffix.lower() in SEQUENCE_SUFFIXES:
            raise ValueError(f"{option} {out} would add a mesh file to the input folder {p}; write it elsewhere.")
        if src.is_dir() and src in target.parents and target.exists():
            raise ValueError(f"{option} {out} would replace a file of the input {p}; write the output elsewhere.")
    for p in protect:
        if Path(p).resolve() == target:
            raise ValueError(f"{option} {out} would replace {p}, which the command reads; write the output elsewhere.")


#: how far outside its reference mesh a result may lie (bounding-box diagonals) before it is refused as absurd
EXTENT_LIMIT = 1e3


def _diagonal(points) -> float:
    import numpy as np

    return float(np.linalg.norm(points.max(axis=-2) - points.min(axis=-2)))


def check_result(positions, reference, what: str) -> None:
    """Refuse a result before it is written: non-finite coordinates, or a mesh (of each frame of ``positions``,
    ``(V, 3)`` or ``(N, V, 3)``) whose bounding box or centre lies more than :data:`EXTENT_LIMIT` reference
    bounding-box diagonals from ``reference``'s. ``what`` names the result ("decoded frame", "edited mesh").

    **Raises:** ``JaxDeformError`` (one sentence, saying nothing was written).
    """
    import numpy as np

    from jaxdeform.errors import JaxDeformError

    p = np.asarray(positions, np.float64)
    frames = p.reshape(-1, *p.shape[-2:])
    ref = np.asarray(reference, np.float64)
    size = max(_diagonal(ref), np.finfo(np.float64).tiny)
    centre = 0.5 * (ref.max(axis=0) + ref.min(axis=0))
    for k, frame in enumerate(frames):
        name = what if len(frames) == 1 else f"{what} {k}"
        if not np.all(np.isfinite(frame)):
            bad = int(np.count_nonzero(~np.isfinite(frame).all(axis=-1)))
            raise JaxDeformError(f"the {name} has {bad} vertices with non-finite coordinates; nothing was written.")
        far = max(_diagonal(frame), float(np.linalg.norm(0.5 * (frame.max(axis=0) + frame.min(axis=0)) - centre)))
        if far > EXTENT_LIMIT * size:
            raise JaxDeformError(
                f"the {name} lies {far / size:.3g} reference sizes away (the limit is {EXTENT_LIMIT:g}): its "
                "input is far outside what the reference mesh can produce; nothing was written."
            )


def check_magnitude(values, reference, option: str, offset: bool = False) -> None:
    """Refuse input positions (control targets), or an ``offset`` (``--translate``), that are not finite or lie
    more than :data:`EXTENT_LIMIT` bounding-box diagonals of ``reference`` from its centre (from zero for an
    offset): one sentence naming ``option``."""
    import numpy as np

    v = np.asarray(values, np.float64)
    ref = np.asarray(reference, np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{option} must be finite numbers.")
    size = max(_diagonal(ref), np.finfo(np.float64).tiny)
    centre = 0.5 * (ref.max(axis=0) + ref.min(axis=0))
    far = float(np.abs(v - (0.0 if offset else centre)).max(initial=0.0))
    if far > EXTENT_LIMIT * size:
        raise ValueError(
            f"{option}: {far:.3g} is more than {EXTENT_LIMIT:g} times the mesh's size ({size:.3g}); "
            "give values on the mesh's scale."
        )


@contextlib.contextmanager
def staged_folder(out: Path):
    """:func:`jaxdeform.mesh.io.staged_folder` with a system error while writing named by ``out`` (one sentence)."""
    from jaxdeform.mesh.io import staged_folder as staged

    with writing(out), staged(out) as tmp:
        yield tmp


@contextlib.contextmanager
def atomic_file(out: Path):
    """Yield a temporary path beside ``out`` that replaces it on success (a write error names ``out``)."""
    from jaxdeform.mesh.io import atomic_path

    with writing(out), atomic_path(out) as tmp:
        yield tmp
