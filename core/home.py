"""A farm's home folder: where it is, and the files in it that the master, the CLI and the local
supervisor all read or write (each names them through this module, never by a string of its own)."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

from core.errors import QuekaroError

ADMIN_TOKEN = "admin.token"  # the job API's secret, written by the master (mode 0600)
FARM_FILE = "farm.json"  # the master's URL, JID and token file, written by the master when it is up
AGENTS_ALLOW = "agents.allow"  # bare JIDs allowed to bid (a supervised local farm writes it)
PROCESSES_FILE = "processes.json"  # a local farm's children, written by its supervisor
MIN_FREE_BYTES = 64 << 20  # below this free in its home the master pauses every job (MasterConfig's default)


def default_home() -> Path:
    """Where a farm keeps its state: $QUEKARO_HOME, else ~/.quekaro/farm."""
    return Path(os.environ.get("QUEKARO_HOME", Path.home() / ".quekaro" / "farm"))


PRIVATE = 0o077  # the permission bits of group and others: none in a farm's folders


def make_private(folder: Path, what: str = "--home") -> int:
    """Make `folder` (made if missing) readable by this user alone, with everything in it, and every file
    this process and its children make from now on (umask 077). A folder of another user is refused.
    Returns how many entries had group or other permissions and lost them (0 for a private folder)."""
    os.umask(PRIVATE)
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        mode = folder.stat()
    except OSError as exc:
        raise QuekaroError(f"{what} {folder}: cannot make the farm's folder there ({exc.strerror})") from None
    if mode.st_uid != os.getuid():
        raise QuekaroError(f"{what} {folder}: the folder belongs to user id {mode.st_uid}, not to this user "
                           f"({os.getuid()}); a farm keeps its tokens and tiles in a folder of its own user")
    if not mode.st_mode & PRIVATE:
        return 0
    return sum(_closed(path) for path in [folder, *folder.rglob("*")])


def _closed(path: Path) -> bool:
    """Take group and other permissions off `path` (not through a link); whether it had any."""
    mode = path.lstat().st_mode
    if stat.S_ISLNK(mode) or not mode & PRIVATE:
        return False
    path.chmod(stat.S_IMODE(mode) & ~PRIVATE)
    return True


def read_processes(home: Path) -> list[dict]:
    """A local farm's processes as its supervisor last wrote them (none for a farm of separate hosts). One
    listed as running whose process is gone reads "dead": the supervisor has not written since (its
    next round restarts it; a full disk may stop the writing, never the restart)."""
    try:
        processes = [dict(p) for p in json.loads((Path(home) / PROCESSES_FILE).read_text())["processes"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    for process in processes:
        if process.get("state") == "running" and not _alive(process.get("pid")):
            process["state"] = "dead"
    return processes


def _alive(pid: object) -> bool:
    """Whether `pid` is a live process (not a zombie its parent has yet to reap)."""
    if type(pid) is not int or pid <= 0:
        return False
    try:
        stat_line = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat_line.rsplit(")", 1)[-1].split()[0] not in ("Z", "X")
