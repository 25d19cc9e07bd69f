"""The ``jaxdeform`` command: ``jaxdeform METHOD ACTION ...`` for the methods acap, parts, components, handles,
cloth and render, one module each in this package (``components edit``, ``components finetune`` and ``handles serve``
in modules of their own; :mod:`jaxdeform.cli.common` holds what they share).

:func:`main` parses ``argv`` and runs the command; it returns 0, or 2 after one line ``jaxdeform: error:
<sentence>`` on stderr for every expected failure, with no output left behind (files are written through a
temporary sibling and renamed into place; output folders are built beside the target and renamed at the end).
Argument errors are argparse's (usage on stderr, exit 2). Parsing and ``--help`` import neither JAX nor NumPy:
a command imports what it needs when it runs.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from jaxdeform.cli import (
    acap,
    cloth,
    common,
    components,
    components_edit,
    components_finetune,
    feedback,
    handles,
    handles_serve,
    parts,
    render,
)

__all__ = ["build_parser", "main"]

DESCRIPTION = (
    "Mesh deformation in JAX. Methods: acap (ACAP/TS-ACAP features: encode, decode), parts (rigid parts by "
    "mixtures of factor analyzers), components (multiscale deformation components and baselines), handles "
    "(Deep Feature Deformation weights), cloth (coarse-to-fine cloth detail synthesis), render (a mesh to PNG)."
)


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command; each parsed command's ``func`` runs it."""
    from jaxdeform import __version__

    parser = argparse.ArgumentParser(prog=common.PROG, description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    actions = {method: method.register(sub) for method in (acap, parts, components, handles, cloth, render)}
    components_finetune.register(actions[components])  # modules of their own, added last
    components_edit.register(actions[components])
    handles_serve.register(actions[handles])
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI on ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    label = " ".join(a for a in argv[:2] if not a.startswith("-"))
    with feedback.session(args, f"{label}..."):
        try:
            common.setup_process()  # after parsing, so that --help imports no JAX
        except KeyboardInterrupt:
            print(f"{common.PROG}: interrupted; nothing was written.", file=sys.stderr)
            return 130
        return common.run_command(args.func, args)
