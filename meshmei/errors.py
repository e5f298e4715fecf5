"""Exceptions raised by meshmei for bad input."""

__all__ = ["MeshError"]


class MeshError(ValueError):
    """A mesh (vertex or face array) is malformed; the message names the problem and what arrived."""
