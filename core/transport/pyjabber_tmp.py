"""Remove the empty folder pyjabber leaves in /tmp in every process that imports it.

pyjabber (SPADE's embedded XMPP server, imported by `spade` itself) makes a `pyjabber_xep0363_*`
folder with `tempfile.mkdtemp` at import, for its HTTP upload feature, and never removes it: each
agent, master and server process left one behind (thousands after a test run). The farm never uses
that feature, so the folder, private to this process, is removed when the process exits normally.
"""

from __future__ import annotations

import atexit
import shutil
import sys

_MODULE = "pyjabber.plugins.xep_0363.upload_server"
_registered: set[str] = set()


def remove_upload_dir_at_exit() -> None:
    """Once per process, after pyjabber was imported: remove its upload folder at exit."""
    folder = getattr(sys.modules.get(_MODULE), "TEMP_DIR", None)
    if folder is not None and folder not in _registered:
        _registered.add(folder)
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
