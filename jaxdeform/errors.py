"""Exceptions of jaxdeform. Each carries one clear sentence; the CLI prints it and exits 2.

This module imports nothing of jaxdeform, so every layer (mesh at the bottom included) may raise these.
"""


class JaxDeformError(Exception):
    """Base class of every error jaxdeform raises on purpose."""


class MeshFormatError(JaxDeformError):
    """A mesh file is empty, truncated, of an unknown format or holds invalid numbers."""


class ConnectivityError(JaxDeformError):
    """Meshes that must share one connectivity do not, or faces index vertices that do not exist."""


class DegenerateMeshError(JaxDeformError):
    """A mesh is degenerate in a way the requested computation cannot handle."""
