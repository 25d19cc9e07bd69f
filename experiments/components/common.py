"""What the seed-000 experiment scripts share: each data set's split, the hardware line of a table, atomic text
files. A leaf module (it imports no other experiment), so that any of them can import it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxdeform.mesh.io import atomic_path, load_mesh, load_sequence, save_mesh
from jaxdeform.metrics import proper_rotation

#: data set -> split mode (Sec. 5.1: sequences every 10th, pose sets a random half)
SPLITS = {"horse-gallop": "every10", "horse-49": "every10", "samba": "every10", "cactus": "half", "tube": "every10"}


def similarity_onto(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``src`` (V, 3) moved onto ``dst`` (V, 3), same vertex order: centroids matched, scaled to dst's RMS radius
    about its centroid, then turned by the proper rotation that best maps it onto ``dst`` (Kabsch). The scale is
    the size ratio, not the least-squares one, so that a pose difference does not shrink the shape."""
    a = src - src.mean(axis=0)
    b = dst - dst.mean(axis=0)
    a = a * np.sqrt((b**2).sum() / (a**2).sum())
    rot = proper_rotation(b.T @ a)  # rot @ a_i ~ b_i
    return a @ rot.T + dst.mean(axis=0)


def horse49(data: Path, out: Path) -> Path:
    """Table 1's Horse (49 shapes): Sumner's reference horse (``horse-poses/horse_ref.obj``, same connectivity,
    original scale) moved onto the first gallop frame by :func:`similarity_onto`, then the 48 frames of
    ``horse-gallop``; written once as OBJ files to ``out/data/horse-49`` (every 10th from the reference trains:
    5 shapes, 44 test). Returns that folder."""
    folder = Path(out) / "data" / "horse-49"
    gallop = Path(data) / "horse-gallop"
    reference = Path(data) / "horse-poses" / "horse_ref.obj"
    if not gallop.is_dir() or not reference.is_file():
        raise SystemExit(f"horse-49 needs {gallop} and {reference} (../shared/data beside the repository).")
    if (folder / "0048.obj").is_file():
        return folder
    frames, faces = load_sequence(gallop)
    ref, ref_faces = load_mesh(reference)
    if ref.shape != frames.shape[1:] or not np.array_equal(ref_faces, faces):
        raise SystemExit(f"{reference} does not share horse-gallop's connectivity.")
    shapes = np.concatenate([similarity_onto(ref, frames[0])[None], frames])
    for k, v in enumerate(shapes):
        save_mesh(folder / f"{k:04d}.obj", v, faces)
    return folder


BUILDERS = {"horse-49": horse49}


def hardware() -> str:
    """The CPU, and the accelerator that trained when JAX's default backend is not the CPU."""
    import jax

    from benchmarks.acap import cpu_info

    dev = jax.devices()[0]
    if dev.platform == "cpu":
        return f"{cpu_info()} cores, CPU only"
    return f"{getattr(dev, 'device_kind', dev.platform)} ({dev.platform}), host {cpu_info()} cores"


def write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (its folder made)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)
