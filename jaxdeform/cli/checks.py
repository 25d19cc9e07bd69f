"""Checks of a command's outputs before they are written: results far outside their reference mesh, inputs far
outside the mesh they act on, and output paths that would replace an input (re-exported by ``common``)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

#: how far outside its reference mesh a result may lie (bounding-box diagonals) before it is refused as absurd
EXTENT_LIMIT = 1e3


def _diagonal(points) -> float:
    import numpy as np

    return float(np.linalg.norm(points.max(axis=-2) - points.min(axis=-2)))


def _size_and_centre(reference):
    """``(diagonal, centre)`` of a mesh's bounding box ``(V, 3)``; the diagonal at least the smallest float64."""
    import numpy as np

    ref = np.asarray(reference, np.float64)
    return max(_diagonal(ref), np.finfo(np.float64).tiny), 0.5 * (ref.max(axis=0) + ref.min(axis=0))


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
    size, centre = _size_and_centre(reference)
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
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{option} must be finite numbers.")
    size, centre = _size_and_centre(reference)
    far = float(np.abs(v - (0.0 if offset else centre)).max(initial=0.0))
    if far > EXTENT_LIMIT * size:
        raise ValueError(
            f"{option}: {far:.3g} is more than {EXTENT_LIMIT:g} times the mesh's size ({size:.3g}); "
            "give values on the mesh's scale."
        )


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
