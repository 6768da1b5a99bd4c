"""Files written whole or not at all: through a temporary name beside the target, renamed once complete;
several files that belong together (an image, its preview, its report) renamed only once all are written."""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from core.errors import QuekaroError


class WriteError(QuekaroError):
    """A file could not be written; nothing of it is left. Its cause is ENOSPC on a full disk."""


def written_atomically(path: Path, write: Callable[[Path], None], what: str) -> Path:
    """`write(tmp)` to a temporary name beside `path`, then rename: a failure leaves no partial file."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        write(tmp)
        os.replace(tmp, path)
    except (OSError, RuntimeError, ValueError) as exc:
        cause = exc
        if not isinstance(exc, OSError) and os.strerror(errno.ENOSPC) in str(exc):
            cause = OSError(errno.ENOSPC, str(exc))  # OpenEXR and Mitsuba say a full disk only in words
        raise WriteError(f"{path}: cannot write {what} ({exc})") from cause
    finally:
        tmp.unlink(missing_ok=True)
    return path


@contextmanager
def staged_together(finals: Sequence[Path]) -> Iterator[list[Path]]:
    """Temporary names beside `finals` (keeping each suffix, which writers go by) to write into; renamed
    onto `finals`, in their order, only when the block ends without error, else removed: a failed write (a
    full disk) leaves the files that were there before as they were. The renames are not one atomic step:
    put last the file that says the set is complete (a report)."""
    staged = [final.with_name(f".{final.stem}.{os.getpid()}.part{final.suffix}") for final in finals]
    try:
        yield staged
        for temporary, final in zip(staged, finals, strict=True):
            os.replace(temporary, final)
    finally:
        for temporary in staged:
            temporary.unlink(missing_ok=True)
