"""The master's memory does not grow with what it is sent: a 200 MB job upload is streamed to disk."""

from __future__ import annotations

import urllib.error
import urllib.request
from pathlib import Path

import pytest

from farm.local import LocalFarm

pytestmark = pytest.mark.slow


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


class _Body:
    """200 MB of zeros, produced a MiB at a time (the client holds none of it either)."""

    def __init__(self, size: int) -> None:
        self.size, self.sent = size, 0

    def __iter__(self):
        chunk = b"\0" * (1 << 20)
        while self.sent < self.size:
            self.sent += len(chunk)
            yield chunk


def test_a_200_mb_upload_does_not_grow_the_master(tmp_path):
    with LocalFarm(tmp_path / "farm", agents=1, threads=1) as farm:
        master = farm.children[0].proc.pid
        before = _peak_rss_mb(master)
        size = 200 << 20
        request = urllib.request.Request(
            farm.url + "/api/jobs", data=_Body(size), method="POST",
            headers={"Authorization": f"Bearer {farm.client().token}", "Content-Type": "application/x-tar",
                     "Content-Length": str(size), "X-Quekaro-Job": '{"defines": {}, "options": {}}'})
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(request, timeout=120)
        assert err.value.code == 422  # zeros are no bundle: refused once read, after streaming to disk
        grown = _peak_rss_mb(master) - before
        assert grown < 50, f"the master's peak memory grew by {grown:.0f} MB for a 200 MB upload"
        assert not list((tmp_path / "farm" / "jobs").rglob(".upload-*"))  # nothing left behind
