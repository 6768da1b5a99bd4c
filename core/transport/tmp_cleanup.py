"""Remove the empty folders pyjabber leaves in the temporary folder (/tmp).

pyjabber (SPADE's embedded XMPP server: `spade` imports it, the farm never runs it) makes a `pyjabber_xep0363_*`
folder with `tempfile.mkdtemp` at import, for its HTTP upload feature, and never removes it: each
agent, master and server process left one behind (thousands after a test run). The farm never uses
that feature, so the folder, private to this process, is removed when the process exits normally;
those of processes that were killed are swept by the next process once they are an hour old and
still empty (a process running for longer loses its own too: harmless, as nothing here uploads).
"""

from __future__ import annotations

import atexit
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

_MODULE = "pyjabber.plugins.xep_0363.upload_server"
PREFIX = "pyjabber_xep0363_"
STALE_S = 3600.0
_registered: set[str] = set()


def remove_upload_dir_at_exit() -> None:
    """Once per process, after pyjabber was imported: remove its upload folder at exit, and sweep the
    stale ones of processes that could not."""
    folder = getattr(sys.modules.get(_MODULE), "TEMP_DIR", None)
    if folder is not None and folder not in _registered:
        _registered.add(folder)
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        sweep_stale(Path(tempfile.gettempdir()), time.time())


def sweep_stale(tmp: Path, now: float) -> int:
    """Remove this user's empty pyjabber folders in `tmp` untouched for STALE_S; returns how many.
    Only empty ones: rmdir refuses anything with content, so nothing of anyone's is lost."""
    removed = 0
    for folder in tmp.glob(f"{PREFIX}*"):
        try:
            info = folder.lstat()
            if folder.is_symlink() or info.st_uid != os.getuid() or now - info.st_mtime < STALE_S:
                continue
            folder.rmdir()
            removed += 1
        except OSError:  # not empty, not a folder, gone meanwhile, not ours to remove
            continue
    return removed
