"""The ground floor: mesh I/O, topology, geometry, geodesics and rendering of one connectivity.

The names below are imported on first use (``from jaxdeform.mesh import build_topology``), so that reading a
mesh file does not import JAX; ``render`` and ``geodesic`` are modules of their own (``jaxdeform.mesh.render``).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

_WHERE = {
    "Topology": "topology",
    "build_topology": "topology",
    "cot_laplacian": "geometry",
    "cotangent_weights": "geometry",
    "face_areas": "geometry",
    "face_normals": "geometry",
    "laplacian_coo": "geometry",
    "vertex_normals": "geometry",
    "load_mesh": "io",
    "load_sequence": "io",
    "save_mesh": "io",
    "save_sequence": "io",
}

__all__ = [
    "Topology",
    "build_topology",
    "cot_laplacian",
    "cotangent_weights",
    "face_areas",
    "face_normals",
    "laplacian_coo",
    "load_mesh",
    "load_sequence",
    "save_mesh",
    "save_sequence",
    "vertex_normals",
]

if TYPE_CHECKING:
    from jaxdeform.mesh.geometry import (
        cot_laplacian,
        cotangent_weights,
        face_areas,
        face_normals,
        laplacian_coo,
        vertex_normals,
    )
    from jaxdeform.mesh.io import load_mesh, load_sequence, save_mesh, save_sequence
    from jaxdeform.mesh.topology import Topology, build_topology


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module 'jaxdeform.mesh' has no attribute '{name}'")
    value = getattr(importlib.import_module(f"jaxdeform.mesh.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
