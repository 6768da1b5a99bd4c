"""How the farm's processes log: a sentence a line for people, or one JSON object a line for tools.

`configure(level, fmt, role)` sets the root logger once per process. A log call passes its structured
form as `extra=fields(...)`: the text format prints only the sentence, the JSON format adds the fields.
`farm_logs(home)` finds a local farm's log files, which `quekaro logs` and the page read.
"""

from __future__ import annotations

import json
import logging
import re
import sys
from pathlib import Path
from typing import IO, Any

FORMATS = ("text", "json")
MITSUBA_LOGGER = "mitsuba"  # the logger whose own level Mitsuba's log follows in a render process
LOG_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # a process's name, as a log file's stem
_FIELDS = "quekaro_fields"


def fields(**values: Any) -> dict[str, Any]:
    """The `extra=` of a log call: what the JSON format prints beside the sentence."""
    return {_FIELDS: values}


class JsonFormatter(logging.Formatter):
    """One JSON object a line: time, level, process role, logger, the sentence, and the call's fields."""

    def __init__(self, role: str) -> None:
        super().__init__()
        self.role = role

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {"time": round(record.created, 3), "level": record.levelname.lower(),
                               "role": self.role, "logger": record.name, "message": record.getMessage()}
        out.update(getattr(record, _FIELDS, {}))
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure(level: str, fmt: str = "text", role: str = "", stream: IO[str] | None = None,
              prefix: str = "") -> None:
    """Log at `level` (a name: INFO, debug, ...) to `stream` (stderr) as `fmt` ('text' or 'json'). `role`
    names the process (master, agent-0); `prefix` starts every text line (an emulated agent's mark)."""
    if fmt not in FORMATS:
        raise ValueError(f"--log-format {fmt!r}: expected one of {', '.join(FORMATS)}")
    handler = logging.StreamHandler(stream or sys.stderr)
    if fmt == "json":
        handler.setFormatter(JsonFormatter(role))
    else:
        who = f" {role}" if role else ""
        handler.setFormatter(logging.Formatter(f"{prefix}%(asctime)s{who} %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(getattr(logging, str(level).upper(), logging.INFO))


def verbosity(count: int) -> str:
    """The log level of `-v` given `count` times, as Mitsuba's -v: warnings alone without, INFO, then DEBUG."""
    return ("WARNING", "INFO", "DEBUG")[min(max(count, 0), 2)]


def verbose(count: int) -> None:
    """A command's `-v` given `count` times: its log at `verbosity(count)`, and Mitsuba's own in its render
    process too (core.render.process reads the MITSUBA_LOGGER's level; processes that never set it, such
    as agents at INFO, keep Mitsuba at warnings)."""
    level = verbosity(count)
    configure(level)
    logging.getLogger(MITSUBA_LOGGER).setLevel(level)


def farm_logs(home: Path) -> dict[str, Path]:
    """A local farm's logs by process name: HOME/logs/NAME.log, and the XMPP server's as `xmpp`."""
    logs = {p.stem: p for p in sorted((home / "logs").glob("*.log")) if LOG_NAME.fullmatch(p.stem)}
    server = home / "xmpp" / "prosody.log"  # core.transport.xmpp_server.ProsodyServer's log file
    return logs | ({"xmpp": server} if server.is_file() else {})
