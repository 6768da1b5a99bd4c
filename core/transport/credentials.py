"""XMPP passwords for the master and agent processes: from an option, a file, or the environment."""

from __future__ import annotations

import os
from pathlib import Path

from core.errors import QuekaroError

PASSWORD_ENV = "QUEKARO_XMPP_PASSWORD"


def xmpp_password(password: str | None, password_file: str | Path | None) -> str:
    """--password, else --password-file, else $QUEKARO_XMPP_PASSWORD: a missing password is an error.

    A file or the environment keeps the password out of `ps` and shell history."""
    if password:
        return str(password)
    if password_file:
        path = Path(password_file)
        try:
            value = path.read_text().strip()
        except OSError as exc:
            raise QuekaroError(f"--password-file {path}: {exc.strerror or exc}") from None
        if not value:
            raise QuekaroError(f"--password-file {path} is empty")
        return value
    if os.environ.get(PASSWORD_ENV):
        return os.environ[PASSWORD_ENV]
    raise QuekaroError(f"no XMPP password: give --password, --password-file or ${PASSWORD_ENV}")
