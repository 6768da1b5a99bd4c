"""Errors a user can cause: each names the file, field or message at fault."""

from __future__ import annotations


class QuekaroError(Exception):
    """Base of every error the farm reports to a user rather than crashing on."""


class SceneError(QuekaroError):
    """A scene file that cannot be read, parsed, bundled or rendered."""


class RenderError(QuekaroError):
    """A unit render that failed (child process crashed, timed out or raised)."""


class TileError(QuekaroError):
    """A tile file that is malformed, of the wrong size, or fails its hash."""


class MessageError(QuekaroError):
    """A protocol message that is malformed, oversized, of the wrong version or forged."""

    def __init__(self, reason: str, field: str | None = None) -> None:
        self.reason = reason
        self.field = field
        super().__init__(f"{reason}" + (f" (field {field!r})" if field else ""))
