"""A real small filesystem for tests of a full disk: a tmpfs of a given size (needs root, which CI has)."""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def small_tmpfs(mount: Path, size: str, free: int | None = None) -> Iterator[Path]:
    """A tmpfs of `size` (mount's option, e.g. "256k") at `mount`; with `free`, filled by a file `filler`
    until about `free` bytes are left."""
    mount.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)],
                                           capture_output=True).returncode != 0:
        pytest.skip("needs root to mount a small tmpfs (CI runs as root)")
    try:
        if free is not None:
            fill(mount, free)
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(mount: Path, free: int) -> None:
    """Add to the file `filler` on `mount` until about `free` bytes are left."""
    stat = os.statvfs(mount)
    with (mount / "filler").open("ab") as fh, contextlib.suppress(OSError):
        fh.write(b"\0" * max(0, stat.f_bavail * stat.f_frsize - free))
