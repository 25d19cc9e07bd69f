"""What the seed-000 experiment scripts share: each data set's split, the hardware line of a table, atomic text
files. A leaf module (it imports no other experiment), so that any of them can import it."""

from __future__ import annotations

from pathlib import Path

from jaxdeform.mesh.io import atomic_path

#: data set -> split mode (Sec. 5.1: sequences every 10th, pose sets a random half)
SPLITS = {"horse-gallop": "every10", "samba": "every10", "cactus": "half", "tube": "every10"}


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
