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

from jaxdeform.cli.checks import check_out_checkpoint, check_out_file  # noqa: F401 (the commands' API)
from jaxdeform.cli.feedback import PROG, waiting  # noqa: F401 (the commands' API)
from jaxdeform.errors import JaxDeformError

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


def add_resume(p: argparse.ArgumentParser) -> None:
    """``--resume``: continue an interrupted training (:func:`jaxdeform.runs.resumable`)."""
    p.add_argument("--resume", action="store_true", help="continue an interrupted training of the same command")


@contextlib.contextmanager
def keeping_checkpoints(out: Path):
    """Turn an interrupt of a training into :class:`Interrupted` naming the partial run folder it kept, if any."""
    from jaxdeform.runs import partial_folder

    try:
        yield
    except (KeyboardInterrupt, Terminated) as exc:
        if partial_folder(out).exists():
            raise Interrupted(f"checkpoint kept in {partial_folder(out)}; run the same command with --resume") from exc
        raise


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
