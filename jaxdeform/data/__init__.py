"""Data sources of jaxdeform: deterministic synthetic sequences (``synthetic``) needing no download."""

from jaxdeform.data import synthetic

__all__ = ["synthetic"]
