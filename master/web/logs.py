"""The farm's process logs as the page shows them: which there are, a log's last lines, and one unit's lines.

A local farm writes each process's log as HOME/logs/NAME.log and the XMPP server's as HOME/xmpp/prosody.log
(the files `quekaro logs` reads); a farm of separate hosts has none on the master. Only the end of a file
is read (`TAIL_BYTES`, `UNIT_BYTES`): a log of weeks is never read whole for a page.
"""

from __future__ import annotations

import re
from pathlib import Path

from core.logs import farm_logs

TAIL_BYTES = 256 * 1024  # the end of a log the page shows
UNIT_BYTES = 4 * 1024 * 1024  # the end of the master's log searched for a unit's lines
LINES_MAX = 2000


def _end_lines(path: Path, size: int) -> list[str]:
    """The whole lines of the last `size` bytes of the file (a line cut at the start is left out)."""
    with path.open("rb") as log:
        log.seek(0, 2)
        start = max(0, log.tell() - size)
        log.seek(start)
        lines = log.read().decode(errors="replace").splitlines()
    return lines[1:] if start > 0 else lines


def tail(path: Path, lines: int) -> list[str]:
    """The last `lines` lines of a log (at most LINES_MAX, within its last TAIL_BYTES)."""
    return _end_lines(path, TAIL_BYTES)[-max(0, min(lines, LINES_MAX)):] if lines > 0 else []


def unit_lines(home: Path, job_id: str, index: int, limit: int = 200) -> list[str]:
    """What the master's log says of one unit: its lines naming "unit N of job J", or a progressive job's
    "unit N, pass P of job J" (the auction's records: awards, failures with the agent's reason, requeues,
    done), the last `limit` of them."""
    path = farm_logs(home).get("master")
    if path is None:
        return []
    mark = re.compile(rf"unit {index}(, pass \d+)? of job {re.escape(job_id)}:")
    found = [line for line in _end_lines(path, UNIT_BYTES) if mark.search(line)]
    return found[-limit:]
