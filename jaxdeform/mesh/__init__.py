"""The ground floor: mesh I/O, topology, geometry, geodesics and rendering of one connectivity.

``render`` and ``geodesic`` are imported on use (``jaxdeform.mesh.render``) to keep start-up light.
"""

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
