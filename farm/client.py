"""The user's side of the master's job API: submit, status, result, cancel, requeue (plain HTTP, stdlib only)."""

from __future__ import annotations

import json
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from core.errors import QuekaroError, without_locations
from core.files import staged_together
from core.home import ADMIN_TOKEN, FARM_FILE, default_home
from core.image.imageio import read_image, write_png
from core.model.job import RAW_SUFFIX, JobSpec, RenderOptions
from core.transport.tls import client_context

CONNECT_TIMEOUT_S = 15.0
_REACHED: set[str] = set()  # masters that took a connection in this process


def _reach(url: str) -> None:
    """Fail within CONNECT_TIMEOUT_S where nothing answers a connection (a firewall dropping packets):
    urllib's one timeout, long enough for a submit's planning, also bounds its connection, which the
    system gives up only after about 2 minutes. Checked once per master and process, and not through a
    proxy (HTTPS_PROXY and the like), which urllib uses."""
    parts = urlsplit(url)
    if url in _REACHED or not parts.hostname:
        return
    if urllib.request.getproxies() and not urllib.request.proxy_bypass(parts.hostname):
        return  # urllib goes through the proxy: the master itself may be out of this host's reach
    port = parts.port or (443 if parts.scheme == "https" else 80)
    try:
        socket.create_connection((parts.hostname, port), timeout=CONNECT_TIMEOUT_S).close()
    except TimeoutError:
        raise QuekaroError(f"cannot reach the master at {url}: no answer to a connection within "
                           f"{CONNECT_TIMEOUT_S:.0f} s (a firewall dropping it?)") from None
    except OSError:
        return  # refused, no route: urllib says so at once, in its words
    _REACHED.add(url)


class FarmRefusal(QuekaroError):
    """What the master answered a request it refused: its reason (the message) and the HTTP `status`."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status


@dataclass(frozen=True)
class FarmClient:
    """A master's URL and the admin token that its job API demands."""

    url: str
    token: str
    timeout: float = 600.0
    ca_file: Path | None = None  # the farm's CA, to verify an https master (None: the system's CAs)
    home: Path | None = None  # the home whose farm.json named the URL (a refused connection: a stale file)

    @classmethod
    def from_home(cls, home: Path | None = None, url: str | None = None,
                  token_file: Path | None = None, ca_file: Path | None = None) -> FarmClient:
        """From the farm.json the master writes in its home, overridden by explicit url/token/CA file."""
        home = Path(home or default_home()).absolute()
        info: dict[str, Any] = {}
        farm_file = home / FARM_FILE
        if farm_file.exists():
            info = json.loads(farm_file.read_text())
        token_path = Path(token_file or info.get("token_file") or home / ADMIN_TOKEN)
        if not (url or info.get("url")):
            raise QuekaroError(f"no farm is running in {home} (no {FARM_FILE}): start one with quekaro up, "
                               "or give --url and --token-file")
        if not str(url or info["url"]).startswith(("http://", "https://")):
            raise QuekaroError(f"--url {url!r}: the master's URL starts with http:// or https://")
        url = str(url or info["url"])
        if not token_path.is_file():
            raise QuekaroError(f"admin token file {token_path} " + ("is not a file" if token_path.exists()
                                                                    else "not found"))
        if ca_file is not None and not url.startswith("https://"):
            raise QuekaroError(f"--ca-file {ca_file}: the master at {url} speaks plain HTTP, so no certificate "
                               "is verified")
        ca = ca_file or info.get("ca_file")
        return cls(url.rstrip("/"), token_path.read_text().strip(), ca_file=Path(ca) if ca else None,
                   home=home if url == info.get("url") else None)

    def _request(self, method: str, path: str, body: bytes | None = None,
                 headers: dict[str, str] | None = None) -> bytes:
        return self._exchange(method, path, body, headers)[0]

    def _exchange(self, method: str, path: str, body: bytes | None = None,
                  headers: dict[str, str] | None = None) -> tuple[bytes, Any]:
        """The response's body and headers."""
        _reach(self.url)
        req = urllib.request.Request(self.url + path, data=body, method=method, headers={
            "Authorization": f"Bearer {self.token}", **(headers or {})})
        try:
            context = client_context(self.ca_file) if self.url.startswith("https:") else None
            with urllib.request.urlopen(req, timeout=self.timeout, context=context) as resp:
                return resp.read(), resp.headers
        except urllib.error.HTTPError as exc:
            raise FarmRefusal(exc.code, _reason(exc)) from None
        except urllib.error.URLError as exc:
            if self.home is not None and isinstance(exc.reason, ConnectionRefusedError):
                raise QuekaroError(f"no farm is running in {self.home} ({FARM_FILE} is stale): start one with "
                                   "quekaro up") from None
            why = getattr(exc.reason, "strerror", None) or exc.reason
            raise QuekaroError(f"cannot reach the master at {self.url} ({why})") from None

    def _json(self, method: str, path: str, **kw: Any) -> Any:
        return json.loads(self._request(method, path, **kw))

    def farm(self) -> dict[str, Any]:
        """The farm as the master describes it: its data plane, whether jobs are paused."""
        return dict(self._json("GET", "/api/farm"))

    def submit(self, bundle: bytes, defines: dict[str, str], options: dict[str, Any]) -> str:
        return str(self.submit_spec(bundle, JobSpec(defines, RenderOptions.from_dict(options)))["job_id"])

    def submit_spec(self, bundle: bytes, spec: JobSpec) -> dict[str, Any]:
        """The master's answer to a job: {"job_id"}, and for a frame range {"sequence", "jobs": [{frame,
        job_id}]} (the range's jobs, one a frame)."""
        return dict(self._json("POST", "/api/jobs", body=bundle,
                               headers={"X-Quekaro-Job": spec.header(), "Content-Type": "application/x-tar"}))

    def jobs(self, sequence: str | None = None) -> list[dict[str, Any]]:
        """Every job's summary, or one sequence's (frame order)."""
        query = f"?sequence={urllib.parse.quote(sequence)}" if sequence else ""
        return list(self._json("GET", f"/api/jobs{query}")["jobs"])

    def status(self, job_id: str) -> dict[str, Any]:
        return dict(self._json("GET", f"/api/jobs/{job_id}"))

    def wait(self, job_id: str, timeout: float, poll: float = 0.05,
             while_waiting: Callable[[], None] | None = None) -> dict[str, Any]:
        """The job's status once it no longer runs (done, failed or cancelled), polling every `poll` s and
        calling `while_waiting` in between (e.g. a check that the farm's processes live); a QuekaroError
        after `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            status = self.status(job_id)
            if status["status"] != "running":
                return status
            if while_waiting is not None:
                while_waiting()
            time.sleep(poll)
        raise QuekaroError(f"job {job_id} still running after {timeout:.0f} s")

    def unit(self, job_id: str, index: int) -> dict[str, Any]:
        """One unit: status, agent, attempts and story (master.job_api.unit_summary)."""
        return self._json("GET", f"/api/jobs/{job_id}/units/{index}")

    def agents(self) -> list[dict[str, Any]]:
        return list(self._json("GET", "/api/agents")["agents"])

    def result(self, job_id: str, out: Path, partial: bool = False) -> Path:
        """Download the composed image and its report (which names the image as written here), and write
        the tonemapped PNG beside them; return the image's path: `out` with the suffix of the film's file
        format (.exr, .pfm, .rgbe), as Mitsuba names its output. `partial`: the tiles so far of a job
        running, failed or cancelled (the master's 409 otherwise), and the report of that image."""
        out = Path(out)
        query = "?partial=1" if partial else ""
        body, headers = self._exchange("GET", f"/api/jobs/{job_id}/result{query}")
        name = headers.get_filename() or ""
        out = out.with_suffix(Path(name).suffix or out.suffix or ".exr")
        report = json.loads(self._request("GET", f"/api/jobs/{job_id}/report{query}"))
        if isinstance(report.get("image"), dict):  # the files written here, not the master's own
            report["image"]["file"] = str(out.resolve())
            report["image"]["png"] = str(out.with_suffix(".png").resolve())
        raw = self._request("GET", f"/api/jobs/{job_id}/raw") if isinstance(report.get("denoise"), dict) else None
        if raw is not None:
            report["denoise"]["raw"] = str(out.with_suffix(RAW_SUFFIX).resolve())
        paths = [out, out.with_suffix(".png"), *([out.with_suffix(RAW_SUFFIX)] if raw is not None else []),
                 out.with_suffix(".json")]
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            with staged_together(paths) as (image, png, *raw_file, text):
                image.write_bytes(body)
                if raw is not None:
                    raw_file[0].write_bytes(raw)
                text.write_text(json.dumps(report, indent=2))
                write_png(png, read_image(image))
        except (OSError, QuekaroError) as exc:  # a full disk: what was there before stays as it was
            raise QuekaroError(f"job {job_id}: result not written to {out}: {exc}") from exc
        return out

    def cancel(self, job_id: str) -> bool:
        return bool(self._json("POST", f"/api/jobs/{job_id}/cancel")["cancelled"])

    def requeue(self, job_id: str) -> dict[str, Any]:
        """Run a failed or cancelled job again (a sequence: its failed or cancelled frames): {"requeued": [job
        ids], and for a sequence "refused": {job id: why}}. FarmRefusal (409) says why nothing runs again."""
        return dict(self._json("POST", f"/api/jobs/{job_id}/requeue"))


def _reason(exc: urllib.error.HTTPError) -> str:
    try:
        return without_locations(str(json.loads(exc.read()).get("error", exc.reason)))
    except (ValueError, AttributeError):
        return str(exc.reason)
