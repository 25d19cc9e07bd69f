"""Paired coarse/fine cloth datasets on disk (seed 002, Sec. 4 "Datasets").

A dataset is a folder::

    DIR/dataset.json      {"format": "jaxdeform-cloth-dataset", "version": 1, "scenario": "sheet",
                           "sequences": ["seq_000.npz", ...], "split": {"train": [...], "test": [...]},
                           "penetration": {...}, "timing": {...}}
    DIR/seq_000.npz       coarse (T, Vc, 3), fine (T, Vf, 3) float32 frames; coarse_rest (Vc, 3), fine_rest
                          (Vf, 3) the rest meshes (the ACAP reference); coarse_faces, fine_faces (int32);
                          obs_<name> the obstacle track (leading axis T); meta (a JSON string: the scenario);
                          optionally coarse_pins / fine_pins (indices) and *_pin_positions: where the
                          scenario holds them, (P, 3) fixed or (T, P, 3) per frame (a garment's waistband)

Every file is written through an atomic rename, and ``dataset.json`` last, so an interrupted run leaves no
dataset that looks complete. :func:`load_dataset` checks what training needs and says in one sentence what is
wrong: all sequences share one coarse and one fine connectivity, coarse and fine have equal frame counts, the
frames are finite.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from jaxdeform.errors import ConnectivityError, DegenerateMeshError, MeshFormatError
from jaxdeform.mesh.geometry import zero_area_faces
from jaxdeform.mesh.io import atomic_path, natural_key, read_npz_arrays

FORMAT = "jaxdeform-cloth-dataset"
VERSION = 1
REQUIRED = ("coarse", "fine", "coarse_rest", "fine_rest", "coarse_faces", "fine_faces", "meta")
PINS = ("coarse_pins", "coarse_pin_positions", "fine_pins", "fine_pin_positions")  # optional


@dataclass
class Sequence:
    """One paired sequence: coarse and fine frames of the same scenario, simulated separately."""

    name: str
    coarse: np.ndarray  # (T, Vc, 3) float32
    fine: np.ndarray  # (T, Vf, 3) float32
    obstacles: dict  # name -> (T, ...) arrays of the obstacle track
    meta: dict
    pins: dict = field(default_factory=dict)  # coarse_pins, coarse_pin_positions, fine_pins, fine_pin_positions


@dataclass
class ClothDataset:
    """The sequences of a dataset folder, their shared rest meshes and connectivities, and the split."""

    root: Path
    scenario: str
    coarse_rest: np.ndarray
    coarse_faces: np.ndarray
    fine_rest: np.ndarray
    fine_faces: np.ndarray
    sequences: list[Sequence]
    split: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def subset(self, part: str) -> list[Sequence]:
        """The sequences of the split ``part`` ("train" or "test"); all of them if there is no split at all.

        A split that names ``part`` with no sequence is refused (falling back to every sequence would train on
        the test set or score the training set as test)."""
        if not self.split:
            return list(self.sequences)
        names = self.split.get(part)
        if not names:
            raise MeshFormatError(f"{self.root}: its split has no {part} sequences.")
        by_name = {s.name: s for s in self.sequences}
        check_split({part: names}, self.root, by_name)
        return [by_name[n] for n in names]


def default_split(names: list[str], every: int = 5, offset: int = 2) -> dict:
    """The default train/test split of a dataset's sequences.

    Every ``every``-th sequence from index ``offset`` on is a test sequence (the last one if that picks none; never
    all). Interleaved rather than the last ones: the scenarios spread their parameters over the sequence index
    (the DISK's mean wind speed grows with it), so an interleaved test set lies inside the range the training
    sequences cover instead of beyond it.

    **Arguments:**

    - ``names``: the sequences' names in index order.
    - ``every``, ``offset``: the test sequences are those with index % ``every`` == ``offset``.

    **Returns:**

    ``{"train": [...], "test": [...]}``, lists of names.
    """
    n = len(names)
    test = [i for i in range(n) if i % every == offset] or ([n - 1] if n > 1 else [])
    if len(test) >= n:
        test = test[: n - 1]
    return {"train": [x for i, x in enumerate(names) if i not in test], "test": [names[i] for i in test]}


def write_sequence(path: Path, pair: dict) -> None:
    """Write one sequence file, atomically.

    **Arguments:**

    - ``path``: the file to write.
    - ``pair``: a :func:`jaxdeform.cloth.scenarios.simulate_pair`-like dict.

    **Returns:**

    Nothing.
    """
    arrays = {
        "coarse": np.asarray(pair["coarse"], np.float32),
        "fine": np.asarray(pair["fine"], np.float32),
        "coarse_rest": np.asarray(pair["coarse_rest"], np.float32),
        "fine_rest": np.asarray(pair["fine_rest"], np.float32),
        "coarse_faces": np.asarray(pair["coarse_faces"], np.int32),
        "fine_faces": np.asarray(pair["fine_faces"], np.int32),
        "meta": np.asarray(json.dumps(pair.get("meta", {}), default=_jsonable)),
    }
    for name, arr in (pair.get("obstacles") or {}).items():
        arrays[f"obs_{name}"] = np.asarray(arr)
    for name in PINS:
        if name in pair:
            arrays[name] = np.asarray(pair[name])
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def write_index(root: Path, scenario: str, names: list[str], split: dict | None = None, **info) -> Path:
    """Write ``dataset.json`` (written last, atomically).

    **Arguments:**

    - ``root``: the dataset folder.
    - ``scenario``: the scenario kind.
    - ``names``: the sequence files, in index order.
    - ``split``: the split (default None: :func:`default_split`).
    - ``info``: more entries of the record.

    **Returns:**

    The path of dataset.json.
    """
    record = {
        "format": FORMAT,
        "version": VERSION,
        "scenario": scenario,
        "sequences": list(names),
        "split": split or default_split(list(names)),
        **info,
    }
    path = Path(root) / "dataset.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record, indent=1, default=_jsonable) + "\n")
    return path


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def read_sequence(path: Path) -> tuple[Sequence, dict]:
    """One sequence file and its rest meshes / faces, checked for presence, shapes and finiteness.

    **Arguments:**

    - ``path``: the sequence file.

    **Returns:**

    ``(sequence, shared)``: the :class:`Sequence` and a dict of the rest meshes and faces.

    **Raises:**

    ``MeshFormatError`` for a missing array, wrong shapes, non-finite values, a damaged meta record or pins that
    do not match the mesh; ``ConnectivityError`` for frames whose vertex count differs from the rest mesh's.
    """
    path = Path(path)
    arrays = read_npz_arrays(path)
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise MeshFormatError(f"{path}: not a cloth sequence (missing {', '.join(missing)}).")
    coarse, fine = arrays["coarse"], arrays["fine"]
    for what, a in (("coarse", coarse), ("fine", fine)):
        if a.ndim != 3 or a.shape[-1] != 3 or a.shape[0] == 0 or a.dtype.kind not in "iuf":
            raise MeshFormatError(
                f"{path}: {what} frames must be a non-empty numeric (T, V, 3) array, got {a.dtype} {a.shape}."
            )
        if not np.all(np.isfinite(a)):
            raise MeshFormatError(f"{path}: {what} frames hold NaN or infinite coordinates.")
        rest = arrays[f"{what}_rest"]
        if rest.ndim != 2 or rest.shape[1] != 3 or rest.dtype.kind not in "iuf" or not np.all(np.isfinite(rest)):
            raise MeshFormatError(f"{path}: its {what} rest mesh must be a finite (V, 3) array of numbers.")
        if a.shape[1] != rest.shape[0]:
            raise ConnectivityError(
                f"{path}: its {what} frames have {a.shape[1]} vertices but its {what} rest mesh has {rest.shape[0]}."
            )
    try:
        meta = json.loads(str(arrays["meta"]))
    except json.JSONDecodeError:
        raise MeshFormatError(f"{path}: its meta record is not valid JSON.") from None
    if not isinstance(meta, dict):
        raise MeshFormatError(f"{path}: its meta record is not a JSON object.")
    obstacles = _obstacle_track(path, arrays, coarse.shape[0])
    pins = {k: arrays[k] for k in PINS if k in arrays}
    for res in ("coarse", "fine"):
        if f"{res}_pins" in pins:
            idx, pos = pins[f"{res}_pins"], pins.get(f"{res}_pin_positions")
            n = (coarse if res == "coarse" else fine).shape[1]
            if (
                pos is None
                or pos.shape not in ((idx.size, 3), (coarse.shape[0], idx.size, 3))
                or idx.dtype.kind not in "iu"
                or (idx.size and (idx.min() < 0 or idx.max() >= n))
            ):
                raise MeshFormatError(f"{path}: its {res} pins do not match its {res} mesh.")
            if pos.dtype.kind not in "iuf" or not np.all(np.isfinite(pos)):
                raise MeshFormatError(f"{path}: its {res} pin positions hold NaN, infinite or non-numeric values.")
    shared = {k: arrays[k] for k in ("coarse_rest", "fine_rest", "coarse_faces", "fine_faces")}
    return Sequence(path.name, coarse.astype(np.float32), fine.astype(np.float32), obstacles, meta, pins), shared


def _obstacle_track(path: Path, arrays: dict, frames: int) -> dict:
    """The obstacle track (name -> (T, ...) array) of a sequence file: none, or every field of
    :class:`jaxdeform.cloth.obstacles.Obstacles`, numeric and finite, one entry per frame."""
    from jaxdeform.cloth.obstacles import Obstacles, check_rims, complete

    track = {k[4:]: v for k, v in arrays.items() if k.startswith("obs_")}
    if not track:
        return track
    track = complete(track)  # tracks written before the rounded rims: sharp ones
    missing = [f"obs_{k}" for k in Obstacles._fields if k not in track]
    if missing:
        raise MeshFormatError(f"{path}: its obstacle track lacks {', '.join(missing)}.")
    for name in Obstacles._fields:
        a = track[name]
        if a.ndim < 1 or a.shape[0] != frames or a.dtype.kind not in "iuf":
            raise MeshFormatError(
                f"{path}: obs_{name} must hold numbers for each of the {frames} frames, got {a.dtype} {a.shape}."
            )
        if not np.all(np.isfinite(a)):
            raise MeshFormatError(f"{path}: obs_{name} holds NaN or infinite values.")
    check_rims(track["cylinder_r"], track["cylinder_h"], track["cylinder_rounding"], MeshFormatError, f"{path}: ")
    return track


def check_split(split, where, names=None) -> None:
    """Check a dataset's split.

    **Arguments:**

    - ``split``: must map each part to a list of sequence names.
    - ``where``: the start of the error sentence (the file).
    - ``names``: the dataset's sequences; with them, the split may name only those.

    **Returns:**

    Nothing.

    **Raises:**

    ``MeshFormatError`` (one sentence starting with ``where``) otherwise.
    """
    if not (
        isinstance(split, dict)
        and all(isinstance(v, list) and all(isinstance(n, str) for n in v) for v in split.values())
    ):
        raise MeshFormatError(f"{where}: 'split' must map each part to a list of sequence names.")
    unknown = [] if names is None else [n for part in split.values() for n in part if n not in names]
    if unknown:
        raise MeshFormatError(f"{where}: the split names sequences that are not there ({', '.join(unknown[:3])}).")


def _sequence_files(root: Path) -> tuple[list[Path], dict]:
    index = root / "dataset.json"
    if index.is_file():
        try:
            record = json.loads(index.read_text())
        except json.JSONDecodeError:
            raise MeshFormatError(f"{index}: not valid JSON.") from None
        if not isinstance(record, dict) or record.get("format") != FORMAT:
            raise MeshFormatError(f"{index}: not a jaxdeform cloth dataset index.")
        names, split = record.get("sequences", []), record.get("split") or {}
        if not (isinstance(names, list) and all(isinstance(n, str) and n for n in names)):
            raise MeshFormatError(f"{index}: 'sequences' must be a list of file names.")
        check_split(split, index)
        return [root / n for n in names], record
    files = sorted(root.glob("seq_*.npz"), key=lambda p: natural_key(p.name))
    return files, {}


def load_dataset(root: str | Path) -> ClothDataset:
    """Every sequence of a dataset folder, checked (one connectivity per resolution, equal lengths).

    **Arguments:**

    - ``root``: the dataset folder (dataset.json and seq_*.npz).

    **Returns:**

    The :class:`ClothDataset`: its sequences, both rest meshes, the scenario and the split.

    **Raises:**

    ``FileNotFoundError`` if the folder does not exist; ``MeshFormatError`` if it holds no sequence or a damaged one;
    ``ConnectivityError`` if the sequences do not share one connectivity per resolution.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such dataset folder.")
    files, record = _sequence_files(root)
    if not files:
        raise MeshFormatError(f"{root}: holds no cloth sequences (expected dataset.json or seq_*.npz).")
    seqs: list[Sequence] = []
    ref = None
    for path in files:
        seq, shared = read_sequence(path)
        if ref is None:
            ref = (path.name, shared)
            _check_faces(path, shared)
        else:
            for res in ("coarse", "fine"):
                a, b = ref[1][f"{res}_faces"], shared[f"{res}_faces"]
                ra, rb = ref[1][f"{res}_rest"], shared[f"{res}_rest"]
                if a.shape != b.shape or ra.shape != rb.shape or not np.array_equal(a, b):
                    raise ConnectivityError(
                        f"{path.name} has a {res} mesh of {rb.shape[0]} vertices / {b.shape[0]} faces that differs "
                        f"from {ref[0]}'s ({ra.shape[0]} / {a.shape[0]}); all sequences must share one connectivity."
                    )
        if seq.coarse.shape[0] != seq.fine.shape[0]:
            raise ConnectivityError(
                f"{path.name} has {seq.coarse.shape[0]} coarse frames but {seq.fine.shape[0]} fine "
                "frames; coarse and fine sequences must have equal lengths."
            )
        for res in ("coarse", "fine"):
            v = getattr(seq, res).shape[1]
            if v != ref[1][f"{res}_rest"].shape[0]:
                raise ConnectivityError(
                    f"{path.name}: its {res} frames have {v} vertices but its {res} rest mesh has "
                    f"{ref[1][f'{res}_rest'].shape[0]}."
                )
        seqs.append(seq)
    shared = ref[1]
    names = [s.name for s in seqs]
    split = record.get("split") or default_split(names)
    check_split(split, root, names)
    info = {k: v for k, v in record.items() if k not in ("format", "version", "scenario", "sequences", "split")}
    return ClothDataset(
        root,
        record.get("scenario", seqs[0].meta.get("kind", "unknown")),
        shared["coarse_rest"].astype(np.float64),
        shared["coarse_faces"].astype(np.int64),
        shared["fine_rest"].astype(np.float64),
        shared["fine_faces"].astype(np.int64),
        seqs,
        split,
        info,
    )


def _check_faces(path: Path, shared: dict) -> None:
    for res in ("coarse", "fine"):
        f, v = shared[f"{res}_faces"], shared[f"{res}_rest"]
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise MeshFormatError(f"{path.name}: the {res} mesh has no triangle faces.")
        if f.dtype.kind not in "iu" or f.min() < 0 or f.max() >= v.shape[0]:
            raise ConnectivityError(f"{path.name}: the {res} faces index vertices the rest mesh does not have.")
        bad = zero_area_faces(v, f)
        if bad.size:
            raise DegenerateMeshError(
                f"{path.name}: the {res} rest mesh has {bad.size} zero-area face(s), the first "
                f"face {bad[0]}; its ACAP features need a rest mesh without them."
            )
