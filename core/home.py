"""A farm's home folder: where it is, and the files in it that the master, the CLI and the local
supervisor all read or write (each names them through this module, never by a string of its own)."""

from __future__ import annotations

import os
from pathlib import Path

ADMIN_TOKEN = "admin.token"  # the job API's secret, written by the master (mode 0600)
FARM_FILE = "farm.json"  # the master's URL, JID and token file, written by the master when it is up
AGENTS_ALLOW = "agents.allow"  # bare JIDs allowed to bid (a supervised local farm writes it)
PROCESSES_FILE = "processes.json"  # a local farm's children, written by its supervisor
MIN_FREE_BYTES = 64 << 20  # below this free in its home the master pauses every job (MasterConfig's default)


def default_home() -> Path:
    """Where a farm keeps its state: $QUEKARO_HOME, else ~/.quekaro/farm."""
    return Path(os.environ.get("QUEKARO_HOME", Path.home() / ".quekaro" / "farm"))
