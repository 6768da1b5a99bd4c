"""Frame sequences: a range of frames (`-D frame=1:240:2`) and the names of the images they make.

A job submitted with a `FrameRange` becomes one job per frame on the master, each with the range's parameter set
to its frame number; the jobs share a sequence id and are scheduled across the agents like any jobs. A frame's
image is named `SCENE_0001.exr` (the number padded to four digits, as Blender, Flamenco and Deadline name them).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from core.errors import QuekaroError

FRAMES_MAX = 10_000  # frames in one sequence
FRAME_MAX = 999_999  # the largest frame number
_RANGE = re.compile(r"(\d+):(\d+)(?::(\d+))?")
SEQUENCE_ID = re.compile(r"seq-[0-9a-f]{8,32}")


@dataclass(frozen=True)
class FrameRange:
    """Frames `first`, `first + step`, ... up to `last` inclusive, given to the scene as parameter `define`."""

    define: str
    first: int
    last: int
    step: int = 1

    def __post_init__(self) -> None:
        _check(f"-D {self.define}={self.first}:{self.last}:{self.step}", self.first, self.last, self.step)

    def __len__(self) -> int:
        return (self.last - self.first) // self.step + 1

    def frames(self) -> list[int]:
        return list(range(self.first, self.last + 1, self.step))

    @classmethod
    def parse(cls, define: str, text: str) -> FrameRange | None:
        """`-D NAME=FIRST:LAST[:STEP]` as a range, None where the value is not of that form (a plain value)."""
        match = _RANGE.fullmatch(text.strip())
        if match is None:
            return None
        first, last, step = (int(match[1]), int(match[2]), int(match[3] or 1))
        _check(f"-D {define}={text.strip()}", first, last, step)  # the error names the value as given
        return cls(define, first, last, step)

    def to_dict(self) -> dict[str, Any]:
        return {"define": self.define, "first": self.first, "last": self.last, "step": self.step}

    @classmethod
    def from_dict(cls, data: Any) -> FrameRange:
        if not isinstance(data, dict) or set(data) != {"define", "first", "last", "step"}:
            raise QuekaroError("job field frames: expected an object of define, first, last, step")
        if not isinstance(data["define"], str) or not data["define"]:
            raise QuekaroError("job field frames: define must name a scene parameter")
        return cls(data["define"], data["first"], data["last"], data["step"])


def _check(where: str, first: Any, last: Any, step: Any) -> None:
    """A range's numbers as `FrameRange` takes them; a QuekaroError naming `where` otherwise."""
    for name, value in (("first", first), ("last", last), ("step", step)):
        if type(value) is not int or not 0 <= value <= FRAME_MAX:
            raise QuekaroError(f"{where}: {name} {value!r} is not a whole number in 0..{FRAME_MAX}")
    if step < 1 or last < first:
        raise QuekaroError(f"{where}: a frame range FIRST:LAST[:STEP] needs FIRST <= LAST and STEP >= 1")
    frames = (last - first) // step + 1
    if frames > FRAMES_MAX:
        raise QuekaroError(f"{where}: {frames} frames, over the {FRAMES_MAX} one sequence may hold")


def frame_name(stem: str, frame: int) -> str:
    """A frame's image name without suffix: `cbox_0001`."""
    return f"{stem}_{frame:04d}"
