"""Mesh and mesh-sequence I/O: OBJ, PLY, OFF and .npz sequences.

Every loader returns ``vertices`` as float64 ``(V, 3)`` and ``faces`` as int32 ``(F, 3)`` (polygons are
fan-triangulated). Files are read strictly: an empty, truncated or non-numeric file, a face that indexes a
missing vertex, or a non-finite coordinate raises :class:`~jaxdeform.errors.MeshFormatError` with one
sentence. Sequences (a folder in natural order, a list of files, or one ``.npz``) must share one
connectivity, else :class:`~jaxdeform.errors.ConnectivityError`. Writers go through a temporary file and an
atomic rename, so a failed write never leaves half a file.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Float

from jaxdeform.errors import ConnectivityError, MeshFormatError
from jaxdeform.typing import Int, Real

MESH_SUFFIXES = (".obj", ".ply", ".off")
SEQUENCE_SUFFIXES = MESH_SUFFIXES + (".npz",)


def natural_key(name: str) -> list:
    """Sort key that orders 'frame2' before 'frame10'.

    **Arguments:**

    - `name`: a file name.

    **Returns:**

    A list of text and integer parts (text lower-cased).
    """
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SEQUENCE_SUFFIXES:
        raise MeshFormatError(
            f"{path}: unknown mesh format '{path.suffix or '(none)'}'; expected one of {', '.join(SEQUENCE_SUFFIXES)}."
        )
    return suffix


def _read_text(path: Path) -> str:
    if not path.is_file():
        raise MeshFormatError(f"{path}: no such file.")
    text = path.read_text(errors="replace")
    if not text.strip():
        raise MeshFormatError(f"{path}: the file is empty.")
    return text


def _finish(path: Path, vertices: np.ndarray, faces: np.ndarray, base: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Shared validation of a parsed mesh; messages number vertices as the file does (from ``base``: 1 for OBJ)."""
    if vertices.shape[0] == 0:
        raise MeshFormatError(f"{path}: the file holds no vertices.")
    if faces.shape[0] == 0:
        raise MeshFormatError(f"{path}: the file holds no faces.")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.argwhere(~np.isfinite(vertices))[0, 0])
        raise MeshFormatError(f"{path}: vertex {bad} has a NaN or infinite coordinate.")
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        bad = int(faces.max()) if faces.max() >= vertices.shape[0] else int(faces.min())
        raise MeshFormatError(
            f"{path}: a face refers to vertex {bad + base} but the file has {vertices.shape[0]} vertices "
            f"(numbered {base}..{vertices.shape[0] - 1 + base}; truncated or corrupt file)."
        )
    keys = np.sort(faces, axis=1)
    rep = np.flatnonzero((keys[:, 0] == keys[:, 1]) | (keys[:, 1] == keys[:, 2]))
    if rep.size:
        a, b, c = faces[rep[0]] + base
        raise MeshFormatError(
            f"{path}: a face joins the vertices {a}, {b} and {c}, one of them twice; faces must have 3 distinct "
            "vertices."
        )
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    if counts.max(initial=0) > 1:
        dup = keys[first[np.argmax(counts > 1)]] + base
        raise MeshFormatError(
            f"{path}: two faces join the same vertices {dup[0]}, {dup[1]} and {dup[2]} (a duplicate face); "
            "remove one of them."
        )
    return vertices.astype(np.float64), faces.astype(np.int32)


def _triangulate(polys: list[list[int]], path: Path) -> np.ndarray:
    tris = []
    for poly in polys:
        if len(poly) < 3:
            raise MeshFormatError(f"{path}: a face has fewer than 3 vertices (truncated or corrupt file).")
        for k in range(1, len(poly) - 1):
            tris.append((poly[0], poly[k], poly[k + 1]))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _parse_floats(rows: list[str], width: int, path: Path, what: str) -> np.ndarray:
    try:
        arr = np.array([r.split()[:width] for r in rows], dtype=np.float64)
    except ValueError:
        raise MeshFormatError(f"{path}: a {what} line is truncated or not numeric.") from None
    if arr.ndim != 2 or arr.shape[1] != width:
        raise MeshFormatError(f"{path}: a {what} line has fewer than {width} numbers (truncated file).")
    return arr


def read_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read vertex positions and faces of a Wavefront OBJ (texture/normal indices ignored).

    **Arguments:**

    - `path`: the file.

    **Returns:**

    `(vertices, faces)`: vertices `(V, 3)` float64 and faces `(F, 3)` int32 (polygons fan-triangulated).

    **Raises:**

    `MeshFormatError` (one sentence naming the file) for a missing, empty, truncated, non-numeric or
    corrupt file, a face indexing a missing vertex or a non-finite coordinate.
    """
    path = Path(path)
    text = _read_text(path)
    vrows, frows = [], []
    for line in text.splitlines():
        if line.startswith("v "):
            vrows.append(line[2:])
        elif line.startswith("f "):
            frows.append(line[2:])
    vertices = _parse_floats(vrows, 3, path, "vertex") if vrows else np.zeros((0, 3))
    n = vertices.shape[0]
    polys = []
    try:
        for row in frows:
            idx = [int(tok.split("/")[0]) for tok in row.split()]
            polys.append([i - 1 if i > 0 else n + i for i in idx])
    except ValueError:
        raise MeshFormatError(f"{path}: a face line is truncated or not numeric.") from None
    return _finish(path, vertices, _triangulate(polys, path), base=1)


def read_off(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an ASCII OFF file.

    **Arguments:**

    - `path`: the file.

    **Returns:**

    `(vertices, faces)`: vertices `(V, 3)` float64 and faces `(F, 3)` int32 (polygons fan-triangulated).

    **Raises:**

    `MeshFormatError` (one sentence naming the file) for a missing, empty, truncated, non-numeric or
    corrupt file, a face indexing a missing vertex or a non-finite coordinate.
    """
    path = Path(path)
    lines = [ln.split("#")[0].strip() for ln in _read_text(path).splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise MeshFormatError(f"{path}: the file holds only comments, no mesh.")
    if not lines[0].upper().startswith("OFF"):
        raise MeshFormatError(f"{path}: missing the 'OFF' header.")
    header = lines[0][3:].split() or (lines.pop(1).split() if len(lines) > 1 else [])
    try:
        nv, nf = int(header[0]), int(header[1])
    except (IndexError, ValueError):
        raise MeshFormatError(f"{path}: the OFF counts line is missing or not numeric.") from None
    body = lines[1:]
    if len(body) < nv + nf:
        raise MeshFormatError(f"{path}: expected {nv} vertices and {nf} faces but the file ends early (truncated).")
    vertices = _parse_floats(body[:nv], 3, path, "vertex")
    polys = []
    try:
        for row in body[nv : nv + nf]:
            toks = row.split()
            k = int(toks[0])
            if len(toks) < k + 1:
                raise MeshFormatError(f"{path}: a face line is truncated.")
            polys.append([int(t) for t in toks[1 : k + 1]])
    except ValueError:
        raise MeshFormatError(f"{path}: a face line is not numeric.") from None
    return _finish(path, vertices, _triangulate(polys, path))


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an ASCII or binary PLY file (through trimesh, vertex order kept).

    **Arguments:**

    - `path`: the file.

    **Returns:**

    `(vertices, faces)`: vertices `(V, 3)` float64 and faces `(F, 3)` int32 (polygons fan-triangulated).

    **Raises:**

    `MeshFormatError` (one sentence naming the file) for a missing, empty, truncated, non-numeric or
    corrupt file, a face indexing a missing vertex or a non-finite coordinate. Also when the
    header's counts disagree with the body.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise MeshFormatError(f"{path}: no such file.")
    if path.stat().st_size == 0:
        raise MeshFormatError(f"{path}: the file is empty.")
    try:
        mesh = trimesh.load(str(path), file_type="ply", process=False, force="mesh")
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise MeshFormatError(f"{path}: not a readable PLY mesh ({type(exc).__name__}).") from None
    declared = _ply_counts(path)
    nv, nf = declared.get("vertex"), declared.get("face")
    # trimesh reads a truncated ASCII body without complaint; polygons may split into several triangles
    if (nv is not None and vertices.shape[0] != nv) or (nf is not None and faces.shape[0] < nf):
        raise MeshFormatError(
            f"{path}: the header declares {nv} vertices and {nf} faces but the file holds "
            f"{vertices.shape[0]} and {faces.shape[0]} (truncated file)."
        )
    return _finish(path, vertices, faces)


def _ply_counts(path: Path) -> dict[str, int]:
    """The element counts a PLY header declares ({"vertex": N, "face": M, ...}); empty if none is readable."""
    counts: dict[str, int] = {}
    with open(path, "rb") as fh:
        for _ in range(200):  # a header is a few dozen lines
            line = fh.readline()
            if not line or line.strip() == b"end_header":
                break
            parts = line.split()
            if len(parts) == 3 and parts[0] == b"element":
                try:
                    counts[parts[1].decode("ascii", "replace")] = int(parts[2])
                except ValueError:
                    pass
    return counts


def load_mesh(path: str | os.PathLike) -> tuple[Float[np.ndarray, "v 3"], Int[np.ndarray, "f 3"]]:
    """Load one mesh (OBJ, PLY, OFF, or a one-shape .npz), chosen by suffix.

    **Arguments:**

    - `path`: the file.

    **Returns:**

    `(vertices, faces)`: vertices `(V, 3)` float64 and faces `(F, 3)` int32 (polygons fan-triangulated).

    **Raises:**

    `MeshFormatError` (one sentence naming the file) for a missing, empty, truncated, non-numeric or
    corrupt file, a face indexing a missing vertex or a non-finite coordinate. Also for an unknown
    suffix or a .npz holding more than one shape.
    """
    path = Path(path)
    suffix = _suffix(path)
    if suffix == ".npz":
        vertices, faces = load_sequence(path)
        if vertices.shape[0] != 1:
            raise MeshFormatError(f"{path}: holds {vertices.shape[0]} shapes where one mesh was expected.")
        return vertices[0], faces
    return {".obj": read_obj, ".off": read_off, ".ply": read_ply}[suffix](path)


def _expand(paths: Sequence[str | os.PathLike] | str | os.PathLike) -> list[Path]:
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files = [f for f in p.iterdir() if f.is_file() and f.suffix.lower() in SEQUENCE_SUFFIXES]
            if not files:
                raise MeshFormatError(f"{p}: the folder holds no mesh files ({', '.join(SEQUENCE_SUFFIXES)}).")
            out.extend(sorted(files, key=lambda f: natural_key(f.name)))
        else:
            out.append(p)
    if not out:
        raise MeshFormatError("no input meshes were given.")
    return out


def check_same_connectivity(faces_ref: ArrayLike, faces: ArrayLike, n_ref: int, n: int, where: str) -> None:
    """Check that two meshes share one connectivity.

    **Arguments:**

    - `faces_ref`: the first mesh's faces `(F, 3)`.
    - `faces`: the other mesh's faces.
    - `n_ref`: the first mesh's vertex count.
    - `n`: the other mesh's vertex count.
    - `where`: names the other mesh in the message.

    **Returns:**

    None.

    **Raises:**

    `ConnectivityError` unless the vertex counts are equal and the faces identical.
    """
    if n != n_ref:
        raise ConnectivityError(
            f"{where} has {n} vertices but the first mesh has {n_ref}; meshes must share one connectivity."
        )
    if faces.shape != faces_ref.shape or not np.array_equal(faces, faces_ref):
        raise ConnectivityError(f"{where} has different faces from the first mesh; meshes must share one connectivity.")


def load_sequence(
    paths: Sequence[str | os.PathLike] | str | os.PathLike,
) -> tuple[Float[np.ndarray, "n v 3"], Int[np.ndarray, "f 3"]]:
    """Load meshes that share one connectivity.

    **Arguments:**

    - `paths`: a folder (its mesh files in natural order), one file, or a list of files/folders. A `.npz` holds
      `vertices` `(N, V, 3)` or `(V, 3)` and `faces`.

    **Returns:**

    `(vertices, faces)`: vertices `(N, V, 3)` float64 and faces `(F, 3)` int32.

    **Raises:**

    `MeshFormatError` for an unreadable file or no input; `ConnectivityError` when the meshes do not share
    one connectivity or a face repeats a vertex.
    """
    frames: list[np.ndarray] = []
    faces_ref: np.ndarray | None = None
    for path in _expand(paths):
        if _suffix(path) == ".npz":
            verts, faces = _read_npz(path)
        else:
            v, faces = load_mesh(path)
            verts = v[None]
        if faces_ref is None:
            from jaxdeform.mesh.topology import repeated_vertex_face  # jax-importing module: not at start-up

            bad = repeated_vertex_face(faces)
            if bad >= 0:
                raise ConnectivityError(
                    f"{path}: face {bad} repeats a vertex index; faces must have 3 distinct vertices."
                )
            faces_ref = faces
            n_ref = verts.shape[1]
        else:
            check_same_connectivity(faces_ref, faces, n_ref, verts.shape[1], str(path))
        frames.append(verts)
    assert faces_ref is not None
    return np.concatenate(frames, axis=0), faces_ref


def _read_npz(path: Path) -> tuple[np.ndarray, np.ndarray]:
    if not path.is_file():
        raise MeshFormatError(f"{path}: no such file.")
    data = read_npz_arrays(path)
    if "vertices" not in data or "faces" not in data:
        raise MeshFormatError(f"{path}: a mesh .npz needs arrays 'vertices' and 'faces'.")
    try:
        verts = np.asarray(data["vertices"], dtype=np.float64)
        faces = np.asarray(data["faces"], dtype=np.int64)
    except (TypeError, ValueError) as exc:
        raise MeshFormatError(
            f"{path}: 'vertices' and 'faces' must be numeric arrays ({type(exc).__name__})."
        ) from None
    if verts.ndim == 2:
        verts = verts[None]
    if verts.ndim != 3 or verts.shape[-1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshFormatError(f"{path}: 'vertices' must be (N,V,3) and 'faces' (F,3).")
    if verts.shape[0] == 0:
        raise MeshFormatError(f"{path}: 'vertices' holds no shapes (N = 0).")
    for k in range(verts.shape[0]):
        _finish(Path(f"{path}[{k}]"), verts[k], faces)
    return verts, faces.astype(np.int32)


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


def default_mode(path: str | os.PathLike, directory: bool = False) -> None:
    """Give a temporary file or folder the permissions a normal one would have under the process umask.

    For a file (0600) or folder (0700) from `tempfile`, before it is renamed into place.

    **Arguments:**

    - `path`: the file or folder.
    - `directory`: True for a folder.
    """
    os.chmod(path, (0o777 if directory else 0o666) & ~_UMASK)


def read_npz_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All arrays of a .npz (no pickles).

    **Arguments:**

    - `path`: the file.

    **Returns:**

    A dict of the arrays by name.

    **Raises:**

    `FileNotFoundError` for a missing file; `MeshFormatError` (one sentence) for anything unreadable.
    """
    import zipfile
    import zlib

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file.")
    try:
        data = np.load(path, allow_pickle=False)
        if not hasattr(data, "files"):  # a plain .npy array (np.load returns it, not an archive)
            raise MeshFormatError(f"{path}: is a single .npy array, not a .npz archive.")
        with data:
            return {k: np.asarray(data[k]) for k in data.files}
    except MeshFormatError:
        raise
    except (
        OSError,
        ValueError,
        EOFError,
        zipfile.BadZipFile,
        KeyError,
        NotImplementedError,
        RuntimeError,
        zlib.error,
    ) as exc:
        # a damaged zip header can claim an unsupported compression (NotImplementedError) or encryption (RuntimeError)
        raise MeshFormatError(f"{path}: not a readable .npz archive ({type(exc).__name__}).") from None


def atomic_path(path: Path):
    """Context manager yielding a temporary path beside `path` that is renamed onto it on success.

    **Arguments:**

    - `path`: the final path; its folder is created if missing.

    **Returns:**

    The context manager; on an exception the temporary file is removed and `path` is untouched.
    """
    import contextlib

    @contextlib.contextmanager
    def _cm():
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
        os.close(fd)
        default_mode(tmp)
        try:
            yield Path(tmp)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise

    return _cm()


def connectivity_hash(faces) -> str:
    """A SHA-256 hex digest of a mesh's triangles (as int64, in their order): equal for meshes of one
    connectivity, what run folders and fields store to recognise the mesh they were fitted on."""
    import hashlib

    return hashlib.sha256(np.ascontiguousarray(np.asarray(faces, dtype=np.int64)).tobytes()).hexdigest()


OUTPUT_MARKER = ".jaxdeform"  # the file in every folder staged_folder writes


def staged_folder(out: str | os.PathLike, *, staging: str | os.PathLike | None = None, keep=None):
    """Context manager yielding a temporary sibling folder of ``out`` to fill, which replaces ``out`` on success.

    **Arguments:**

    - `out`: the folder to write; an existing one (empty or not) is replaced only when the block succeeds.
    - `staging`: the folder to fill instead of a fresh temporary one (created if missing, reused as it is if
      present: a resumable job's partial output).
    - `keep`: called with the staging folder when the block is interrupted (an exception that is not an
      ``Exception``: Ctrl-C, a termination signal); if it returns True the staging folder is left in place.

    **Returns:**

    The context manager; on an exception the staging folder is removed (unless `keep` keeps it) and ``out`` is
    left as it was. The folder written holds the marker file :data:`OUTPUT_MARKER` (what the CLI's ``--force``
    checks before it replaces a folder).
    """
    import contextlib
    import shutil

    out = Path(out)

    @contextlib.contextmanager
    def _cm():
        out.parent.mkdir(parents=True, exist_ok=True)
        if staging is None:
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
            default_mode(tmp, directory=True)
        else:
            tmp = Path(staging)
            tmp.mkdir(parents=True, exist_ok=True)
        trash = None
        try:
            (tmp / OUTPUT_MARKER).write_text("written by jaxdeform\n")
            yield tmp
            if out.exists():
                if any(out.iterdir()):  # move aside, swap in, then delete
                    trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
                    os.replace(out, trash / out.name)
                else:
                    out.rmdir()
            os.replace(tmp, out)
        except BaseException as exc:
            if isinstance(exc, Exception) or keep is None or not keep(tmp):
                shutil.rmtree(tmp, ignore_errors=True)
            if trash is not None:
                if not out.exists() and (trash / out.name).exists():
                    os.replace(trash / out.name, out)  # put the old folder back
                shutil.rmtree(trash, ignore_errors=True)
            raise
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True)

    return _cm()


def save_mesh(path: str | os.PathLike, vertices: Real[ArrayLike, "v 3"], faces: Int[ArrayLike, "f 3"]) -> None:
    """Write one mesh as OBJ, OFF, PLY or .npz (chosen by suffix), atomically.

    **Arguments:**

    - `path`: the file to write.
    - `vertices`: positions `(V, 3)` (written as float64).
    - `faces`: triangles `(F, 3)`.

    **Raises:**

    `MeshFormatError` for an unknown suffix.
    """
    path = Path(path)
    suffix = _suffix(path)
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if suffix == ".npz":
        save_sequence(path, vertices[None], faces)
        return
    with atomic_path(path) as tmp:
        if suffix == ".ply":
            import trimesh

            trimesh.Trimesh(vertices, faces, process=False).export(str(tmp), file_type="ply")
            return
        with open(tmp, "w") as fh:
            if suffix == ".off":
                fh.write(f"OFF\n{len(vertices)} {len(faces)} 0\n")
                np.savetxt(fh, vertices, fmt="%.9g")
                np.savetxt(fh, np.c_[np.full(len(faces), 3), faces], fmt="%d")
            else:
                np.savetxt(fh, vertices, fmt="v %.9g %.9g %.9g")
                np.savetxt(fh, faces + 1, fmt="f %d %d %d")


def save_sequence(path: str | os.PathLike, vertices: Real[ArrayLike, "n v 3"], faces: Int[ArrayLike, "f 3"]) -> None:
    """Write a sequence as one `.npz` (arrays `vertices`, `faces`), atomically.

    **Arguments:**

    - `path`: the `.npz` file to write.
    - `vertices`: positions `(N, V, 3)`.
    - `faces`: triangles `(F, 3)` (written as int32).

    **Raises:**

    `MeshFormatError` unless the suffix is `.npz`.
    """
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise MeshFormatError(f"{path}: a sequence is saved as .npz.")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, vertices=np.asarray(vertices), faces=np.asarray(faces, dtype=np.int32))
