"""The one exception hierarchy of rsucal; messages name the field and the value."""

from __future__ import annotations


class RsucalError(Exception):
    """Root of every error rsucal raises on purpose."""


class ShapeError(RsucalError, ValueError):
    """An array argument has the wrong shape or dtype."""


class DegenerateGeometry(RsucalError):
    """The data cannot determine the quantity asked for (collinear points, too few correspondences...)."""


class InputError(RsucalError):
    """Bad input file or message; `source` names the file (or key) and the message names the field."""

    def __init__(self, source: str, message: str) -> None:
        super().__init__(f"{source}: {message}")
        self.source = source
        self.detail = message


class RecordingError(RsucalError):
    """An MCAP recording is unreadable, truncated or not in the rsucal layout."""
