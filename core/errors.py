"""Errors a user can cause: each names the file, field or message at fault."""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable


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


def did_you_mean(word: str, known: Iterable[str]) -> str:
    """" (did you mean X?)" for the known name closest to a mistyped `word`, else ""."""
    close = difflib.get_close_matches(word, list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


_CPP_LOCATION = re.compile(r"\s*\[[\w./-]+\.(?:cpp|cc|h|hpp|inl):\d+\]")


def without_locations(text: str) -> str:
    """Mitsuba's message without its C++ source locations (`[parser.cpp:111]`), which no user acts on."""
    return _CPP_LOCATION.sub("", text).strip()
