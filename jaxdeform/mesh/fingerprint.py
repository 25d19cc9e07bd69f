"""Fingerprints of the data a run was fitted on.

A fingerprint is a small JSON object that run folders and feature fields store beside their arrays: the vertex,
face and shape counts, a SHA-256 of the triangles and of the reference shape's positions (as float32), and the
reference's bounding box. :func:`difference` tells, in a phrase, how other data differs from it, so that commands
taking a run plus data can refuse data that is not the run's and say why.
"""

from __future__ import annotations

import hashlib

import numpy as np

from jaxdeform.mesh.io import connectivity_hash

#: relative tolerance (of the reference's bounding-box diagonal) within which positions count as the same: the
#: same shapes read back from another file format (e.g. OBJ text of 6 significant digits) pass
RTOL = 1e-5


def positions_hash(vertices) -> str:
    """A SHA-256 hex digest of positions ``(V, 3)`` as little-endian float32 (equal for bit-equal float32 data)."""
    return hashlib.sha256(np.ascontiguousarray(np.asarray(vertices, dtype="<f4")).tobytes()).hexdigest()


def fingerprint(vertices, faces) -> dict:
    """The fingerprint of a mesh or a set of shapes sharing one connectivity.

    **Arguments:**

    - ``vertices``: one shape ``(V, 3)``, or shapes ``(N, V, 3)`` whose shape 0 is the reference.
    - ``faces``: the triangles ``(F, 3)``.

    **Returns:**

    ``{"n_shapes", "n_vertices", "n_faces", "connectivity_sha256", "reference_sha256", "reference_bbox"}`` (JSON
    values; ``reference_bbox`` is ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``).
    """
    v = np.asarray(vertices, np.float64)
    shapes = v if v.ndim == 3 else v[None]
    reference = shapes[0]
    return {
        "n_shapes": int(shapes.shape[0]),
        "n_vertices": int(reference.shape[0]),
        "n_faces": int(np.asarray(faces).shape[0]),
        "connectivity_sha256": connectivity_hash(faces),
        "reference_sha256": positions_hash(reference),
        "reference_bbox": [reference.min(axis=0).tolist(), reference.max(axis=0).tolist()],
    }


def difference(kept: dict, vertices, faces, *, rtol: float = RTOL, whose: str = "the run's data") -> str | None:
    """How a mesh or a set of shapes differs from fingerprinted data, in a phrase, or None when it matches.

    Checked in order: vertex and face counts, the triangles, the shape count (for a set ``(N, V, 3)``), and the
    reference shape (shape 0): equal positions hashes, or bounding boxes within ``rtol`` of the fingerprint's
    diagonal. Entries missing from ``kept`` (older records) are not checked.

    **Arguments:**

    - ``kept``: a :func:`fingerprint`.
    - ``vertices``, ``faces``: the data, as :func:`fingerprint` takes them.
    - ``rtol``: the positions' tolerance.
    - ``whose``: names the fingerprinted data in the phrase.

    **Returns:**

    ``None``, or a phrase such as ``"it has 500 vertices where the run's data had 502"``.
    """
    v = np.asarray(vertices, np.float64)
    shapes = v if v.ndim == 3 else v[None]
    reference = shapes[0]
    counts = (("n_vertices", reference.shape[0], "vertices"), ("n_faces", np.asarray(faces).shape[0], "faces"))
    for key, got, what in counts:
        if key in kept and kept[key] != got:
            return f"it has {got} {what} where {whose} had {kept[key]}"
    if "connectivity_sha256" in kept and kept["connectivity_sha256"] != connectivity_hash(faces):
        return f"its triangles differ from those of {whose} (same counts, other connectivity)"
    if v.ndim == 3 and "n_shapes" in kept and kept["n_shapes"] != shapes.shape[0]:
        return f"it holds {shapes.shape[0]} shapes where {whose} held {kept['n_shapes']}"
    if kept.get("reference_sha256") == positions_hash(reference) or "reference_bbox" not in kept:
        return None
    lo, hi = (np.asarray(b, np.float64) for b in kept["reference_bbox"])
    size = float(np.linalg.norm(hi - lo)) or 1.0
    off = max(np.abs(reference.min(axis=0) - lo).max(), np.abs(reference.max(axis=0) - hi).max())
    if off <= rtol * size:
        return None
    return (
        f"its reference shape's bounding box lies up to {off:.3g} from that of {whose} ({off / size:.3g} of its size)"
    )


def malformed(kept) -> str | None:
    """What is wrong with a stored fingerprint, in a phrase (``"must be an object"``), or None when its entries have
    the types :func:`fingerprint` writes (entries may be absent)."""
    if not isinstance(kept, dict):
        return "must be an object"
    for key in ("n_shapes", "n_vertices", "n_faces"):
        if key in kept and not (isinstance(kept[key], int) and not isinstance(kept[key], bool) and kept[key] >= 1):
            return f"{key} must be a positive whole number, got {kept[key]!r}"
    for key in ("connectivity_sha256", "reference_sha256"):
        if key in kept and not (isinstance(kept[key], str) and len(kept[key]) == 64):
            return f"{key} must be a SHA-256 hex digest"
    if "reference_bbox" in kept:
        box = kept["reference_bbox"]
        try:
            ok = np.asarray(box, np.float64).shape == (2, 3) and bool(np.all(np.isfinite(np.asarray(box, float))))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            return "reference_bbox must be two finite points [[x, y, z], [x, y, z]]"
    return None
