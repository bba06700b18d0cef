"""Errors that teach: every Lasagna error is one line naming what was wrong, where, and what was expected.

The CLI prints ``str(error)`` and exits with status 2; no traceback reaches the user.
"""
from __future__ import annotations


class LasagnaError(ValueError):
    """Base class. ``where`` is a file, a JSON path (``layers[2].blend``) or a tensor name."""

    def __init__(self, message: str, where: str | None = None):
        self.where = where
        super().__init__(f"{where}: {message}" if where else message)


class DocumentError(LasagnaError):
    """A stack document (``stack.json``) breaks a rule of the format."""


class ImageError(LasagnaError):
    """A PNG (or other raster) is missing, corrupt, too large or of an unsupported kind."""


class PathError(LasagnaError):
    """A path escapes the folder it must stay in, or is not a safe relative path."""


class ExportError(LasagnaError):
    """A document cannot be written in the requested interchange format."""


class ConditionError(LasagnaError):
    """A condition names a label outside a prior's vocabulary, or has the wrong shape."""
