"""`quekaro bench first-tile`: how soon the page's live image shows a job's first tile after the job's first
award (issue 61's target: within TARGET_S).

A local farm of `--agents` agents renders, in each of `--rounds` rounds, a whole-unit job and a progressive
(`--progressive`: the units' own samples in passes, a small first one) job of one scene, one job at a time, each twice:
once with its preview (GET /ui/api/jobs/JOB/preview.png, the page's live image) polled every `--poll` s,
once with the preview fetched as the page's script fetches it, on each event of its stream
(/ui/events?job=JOB) with a new tile count. One job is watched one way only: the master composes a job's
preview at most once a second, for all its clients. For each job, on the wall clock the master's store
keeps: the first award (the store's attempts), the first tile recorded (its results), the first preview
with a lit pixel (no tile covers a black one), and the bound: the render call that delivered the first tile,
its units (passes) and the seconds its agent predicted for them (a tile lands when its call ends; an agent
renders a job's passes in batches). The first round also pays the agents' scene loading and kernel
compilation: the rounds after it are the steady figures.
"""

from __future__ import annotations

import argparse
import http.client
import io
import json
import os
import statistics
import tempfile
import threading
import time
import urllib.parse
from contextlib import suppress
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from bench.args import check_minimums
from bench.report import DEFAULT_OUT, command_of, write_report
from core.errors import QuekaroError
from core.home import ADMIN_TOKEN
from core.scene.bundle import make_bundle
from farm.local import LocalFarm
from master.store import JobStore
from master.web.events import TICK_S
from planning.progressive import budget_passes

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = REPO / "scenes" / "cbox.xml"
TARGET_S = 2.0  # issue 61: the first tile on the page within 2 s of a job's first award
JOB_TIMEOUT_S = 900.0
MODES = {"whole": {}, "passes": {"progressive": True}}  # each job's options beyond level, units and spp


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for first-tile.md")
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--res", type=int, default=256)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--level", default="off")
    parser.add_argument("--units", type=int, default=16)
    parser.add_argument("--agents", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1, help="Dr.Jit threads of each agent")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of the two jobs (the first pays the start-up)")
    parser.add_argument("--poll", type=float, default=0.1, help="seconds between two requests of the preview")


# ---- the page, over HTTP --------------------------------------------------------------------------------


@dataclass(frozen=True)
class PageSession:
    """A logged-in session of the farm's page: what its script's requests carry."""

    host: str
    port: int
    cookie: str

    @classmethod
    def open(cls, url: str, token: str) -> PageSession:
        """Log in through the page's form (POST /ui/login), as a person does."""
        parts = urllib.parse.urlsplit(url)
        conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=30)
        try:
            conn.request("POST", "/ui/login", urllib.parse.urlencode({"token": token}),
                         {"Content-Type": "application/x-www-form-urlencoded"})
            answer = conn.getresponse()
            answer.read()
            cookie = answer.getheader("Set-Cookie", "").split(";", 1)[0]
        finally:
            conn.close()
        if answer.status != 303 or not cookie:
            raise QuekaroError(f"the page's login answered HTTP {answer.status} without a session")
        return cls(str(parts.hostname), int(parts.port or 80), cookie)

    def get(self, path: str) -> bytes:
        conn = http.client.HTTPConnection(self.host, self.port, timeout=60)
        try:
            conn.request("GET", path, headers={"Cookie": self.cookie})
            answer = conn.getresponse()
            body = answer.read()
        finally:
            conn.close()
        if answer.status != 200:
            raise QuekaroError(f"GET {path}: HTTP {answer.status}")
        return body

    def preview_lit(self, job_id: str) -> bool:
        """Whether the job's preview, as the page loads it, shows any tile (a pixel no tile covers is black)."""
        return lit(self.get(f"/ui/api/jobs/{job_id}/preview.png"))


def lit(png: bytes) -> bool:
    return bool(np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).max() > 0)


class EventWatch(threading.Thread):
    """The page's event stream for one job, handled as the page's script does: on each `job` event whose
    tile count differs from the last, the preview is fetched again. `seen_at`: when that preview first
    showed a tile."""

    def __init__(self, page: PageSession, job_id: str) -> None:
        super().__init__(daemon=True, name=f"events {job_id}")
        self.page, self.job_id = page, job_id
        self.seen_at: float | None = None
        self.error: str | None = None
        self._conn = http.client.HTTPConnection(page.host, page.port, timeout=JOB_TIMEOUT_S)

    def run(self) -> None:
        try:
            self._conn.request("GET", f"/ui/events?job={self.job_id}", headers={"Cookie": self.page.cookie})
            self._follow(self._conn.getresponse())
        except (OSError, http.client.HTTPException, ValueError, QuekaroError) as exc:
            if self.seen_at is None:
                self.error = f"{type(exc).__name__}: {exc}"

    def _follow(self, stream: http.client.HTTPResponse) -> None:
        event, shown = "", None
        while self.seen_at is None:
            raw = stream.readline()
            if not raw:
                return  # the stream ended
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                event = line[7:]
            elif event == "job" and line.startswith("data: "):
                tiles = json.loads(line[6:]).get("tiles")
                if tiles != shown:
                    shown = tiles
                    if self.page.preview_lit(self.job_id) and tiles:
                        self.seen_at = time.time()

    def stop(self) -> None:
        with suppress(OSError):
            if self._conn.sock is not None:
                self._conn.sock.shutdown(2)
        self._conn.close()


# ---- one job --------------------------------------------------------------------------------------------

POLL, PAGE = "poll", "page"  # how a job's first tile is watched for: the preview polled, or as the page does


@dataclass(frozen=True)
class Run:
    """One job's times, in seconds from its first award (None: never seen), and its first render call."""

    round: int
    mode: str  # whole or passes
    watch: str  # POLL or PAGE
    job_id: str
    award_s: float  # submission -> first award (planning, pre-pass, the first call for proposals)
    tile_s: float  # first award -> first tile recorded by the master
    shown_s: float | None  # first award -> the preview first lit, fetched as `watch` says
    call_units: int  # units (passes) of the render call that delivered the first tile
    call_estimate_s: float  # the seconds its agent predicted for them
    first_estimate_s: float  # its first unit's (pass's) own prediction
    call_render_s: float  # the render seconds its units report (each a share of the call's)


def submit_and_time(farm: LocalFarm, page: PageSession, bundle: bytes, job: dict[str, Any], watch: str,
                    poll: float) -> tuple[str, float, float | None]:
    """Submit the job, watch for its first tile (polling its preview, or following its event stream as the
    page does: one job is watched one way only, since a preview composed for one client is throttled for
    the others), and wait for its end: (job id, submitted, first tile shown), wall-clock times."""
    client = farm.client()
    submitted = time.time()
    job_id = client.submit(bundle, job["defines"], job["options"])
    shown = poll_preview(farm, page, job_id, poll) if watch == POLL else follow_events(farm, page, job_id)
    status = client.wait(job_id, JOB_TIMEOUT_S, while_waiting=farm.check_alive)
    if status["status"] != "done":
        raise QuekaroError(f"benchmark job {job_id} {status['status']}: {status.get('error')}")
    return job_id, submitted, shown


def poll_preview(farm: LocalFarm, page: PageSession, job_id: str, poll: float) -> float | None:
    """When the job's preview first showed a tile; None if the job ended first."""
    client = farm.client()
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while time.monotonic() < deadline:
        if page.preview_lit(job_id):
            return time.time()
        if client.status(job_id)["status"] != "running":
            return None
        farm.check_alive()
        time.sleep(poll)
    raise QuekaroError(f"job {job_id}: no tile in its preview after {JOB_TIMEOUT_S:.0f} s")


def follow_events(farm: LocalFarm, page: PageSession, job_id: str) -> float | None:
    """When the page, following the job's events, first showed a tile; None if the job ended first."""
    watch = EventWatch(page, job_id)
    watch.start()
    client = farm.client()
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while watch.is_alive() and time.monotonic() < deadline:
        if client.status(job_id)["status"] != "running":
            watch.join(timeout=3.0)  # its last events may still come
            break
        farm.check_alive()
        watch.join(timeout=0.2)
    watch.stop()
    if watch.error:
        raise QuekaroError(f"job {job_id}'s event stream: {watch.error}")
    return watch.seen_at


def store_times(home: Path, job_id: str, alone: bool) -> dict[str, Any]:
    """From the master's store: the first award, the first tile, and the render call that delivered it: the
    attempts its agent was awarded with that tile's, in one auction round, or the tile's alone (`alone`: an
    agent renders a progressive job's first pass alone, agents/state.py)."""
    with JobStore(home / "jobs.sqlite", readonly=True) as store:
        award = store.db.execute("SELECT MIN(started) FROM attempts WHERE job_id = ?", (job_id,)).fetchone()[0]
        idx, tile = store.db.execute("SELECT idx, recorded FROM results WHERE job_id = ? ORDER BY recorded LIMIT 1",
                                     (job_id,)).fetchone()
        attempts = store.attempts(job_id)
    done = next(a for a in attempts if a.index == idx and a.outcome == "done")
    call = [done] if alone else [a for a in attempts if a.agent == done.agent and a.started == done.started]
    return {"award": award, "tile": tile, "call_units": len(call),
            "call_estimate_s": sum(a.estimate or 0.0 for a in call), "first_estimate_s": done.estimate or 0.0,
            "call_render_s": sum(a.seconds or 0.0 for a in call)}  # each unit's share of its call's seconds


def measure(farm: LocalFarm, page: PageSession, bundle: bytes, job: dict[str, Any], run_of: tuple[int, str, str],
            poll: float) -> Run:
    """One job, watched as `run_of` (round, mode, watch) says."""
    job_id, submitted, shown = submit_and_time(farm, page, bundle, job, run_of[2], poll)
    found = store_times(farm.home, job_id, alone=run_of[1] == "passes")
    award = found["award"]
    return Run(*run_of, job_id, round(award - submitted, 3), round(found["tile"] - award, 3),
               None if shown is None else round(shown - award, 3), found["call_units"],
               round(found["call_estimate_s"], 3), round(found["first_estimate_s"], 3),
               round(found["call_render_s"], 3))


# ---- the benchmark --------------------------------------------------------------------------------------


def jobs_of(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    defines = {"res": str(args.res), "spp": str(args.spp)}
    base = {"level": args.level, "units": args.units, "spp": args.spp}
    return {mode: {"defines": defines, "options": {**base, **extra}} for mode, extra in MODES.items()}


def run(args: argparse.Namespace) -> dict[str, Any]:
    check_minimums(args, res=1, spp=1, units=1, agents=1, threads=1, rounds=1)
    jobs = jobs_of(args)
    runs: list[Run] = []
    load = [os.getloadavg()[0]]  # what else the machine ran: its figures are wall-clock times
    with tempfile.TemporaryDirectory(prefix="quekaro-first-tile-") as tmp:
        bundle = make_bundle(args.scene, jobs["whole"]["defines"], Path(tmp) / "bundle.tar").path.read_bytes()
        with LocalFarm(Path(tmp) / "farm", agents=args.agents, threads=args.threads) as farm:
            farm.wait_for_agents()
            page = PageSession.open(farm.url, (farm.home / ADMIN_TOKEN).read_text().strip())
            print(HEADER, flush=True)
            for round_ in range(1, args.rounds + 1):
                for watch in (POLL, PAGE):
                    for mode, job in jobs.items():
                        runs.append(measure(farm, page, bundle, job, (round_, mode, watch), args.poll))
                        print(row_text(runs[-1]), flush=True)
    load.append(os.getloadavg()[0])
    result = {**summary(args, runs), "load": [round(x, 2) for x in load], "cores": os.cpu_count()}
    text = format_report(args, result)
    print(text)
    command = command_of(args, "quekaro bench first-tile")
    result["report"] = str(write_report(args.out, "first-tile", "First tile on the page", text, command))
    return result


FIELDS = ("award_s", "tile_s", "shown_s", "call_units", "call_estimate_s", "first_estimate_s", "call_render_s")


def summary(args: argparse.Namespace, runs: list[Run]) -> dict[str, Any]:
    """Each (mode, watch)'s median over the steady rounds (all rounds where there is one), the page's
    against TARGET_S."""
    steady = [r for r in runs if r.round > 1] or runs
    medians = {}
    for mode in MODES:
        for watch in (POLL, PAGE):
            mine = [r for r in steady if (r.mode, r.watch) == (mode, watch)]
            medians[f"{mode} {watch}"] = {f: _median([getattr(r, f) for r in mine]) for f in FIELDS}
    target = {mode: _within(medians[f"{mode} {PAGE}"]["shown_s"]) for mode in MODES}
    return {"target_s": TARGET_S, "scene": args.scene.name, "res": args.res, "spp": args.spp, "level": args.level,
            "units": args.units, "agents": args.agents, "threads": args.threads, "poll_s": args.poll,
            "runs": [asdict(r) for r in runs], "steady_rounds": sorted({r.round for r in steady}),
            "medians": medians, "meets_target": target}


def _within(seconds: float | None) -> bool:
    return seconds is not None and seconds <= TARGET_S


def _median(values: list[Any]) -> float | None:
    known = [v for v in values if v is not None]
    return round(statistics.median(known), 3) if known else None


# ---- the report -----------------------------------------------------------------------------------------


def _s(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _units(value: float | None) -> str:
    return "-" if value is None else f"{value:g}"


HEADER = ("round  mode    watch  job          submit>  award>  award>   first render call\n"
          "                                   award    tile    shown")


def row_text(r: Run) -> str:
    return (f"{r.round:>5}  {r.mode:<6}  {r.watch:<5}  {r.job_id:<12} {_s(r.award_s):>7} {_s(r.tile_s):>7} "
            f"{_s(r.shown_s):>7}   {r.call_units:>2} x, est. {_s(r.call_estimate_s)} s "
            f"(first {_s(r.first_estimate_s)} s), rendered {_s(r.call_render_s)} s")


def format_report(args: argparse.Namespace, result: dict[str, Any]) -> str:
    """The runs, then each mode's steady medians: the page's against the target, and the bound its first
    render call sets."""
    rounds = ", ".join(map(str, result["steady_rounds"]))
    lines = [f"{result['scene']} {args.res} px wide, {args.spp} spp, level {args.level}, --units {args.units}; "
             f"{args.agents} agents of {args.threads} thread(s). Seconds. watch: poll, the preview requested "
             f"every {args.poll:g} s; page, the preview requested as the page does, on its event stream's "
             f"news of a tile.{_load_text(result)}", "", HEADER, *(row_text(Run(**r)) for r in result["runs"]), "",
             f"Target: the first tile on the page within {TARGET_S:g} s of the job's first award "
             f"(medians of round(s) {rounds}):"]
    for mode in MODES:
        lines += mode_lines(args, mode, result)
    return "\n".join(lines)


def _load_text(result: dict[str, Any]) -> str:
    """The machine's 1-minute load average at the start and the end, where the run measured it."""
    if "load" not in result:
        return ""
    start, end = result["load"]
    return f" Load average {start:.2f} at the start, {end:.2f} at the end, on {result['cores']} cores."


def mode_lines(args: argparse.Namespace, mode: str, result: dict[str, Any]) -> list[str]:
    """A mode's medians against the target, and what bounds them: the first render call, then the page."""
    page, poll = result["medians"][f"{mode} {PAGE}"], result["medians"][f"{mode} {POLL}"]
    verdict = "met" if result["meets_target"][mode] else "missed"
    lag = None if page["shown_s"] is None else page["shown_s"] - page["tile_s"]
    return [f"  {mode:<6} page {_s(page['shown_s'])} s ({verdict}); preview polled {_s(poll['shown_s'])} s; tile "
            f"recorded {_s(page['tile_s'])} s (the page's jobs) / {_s(poll['tile_s'])} s (the polled ones).",
            f"         Bound: the first tile lands when its agent's first render call ends: "
            f"{_units(page['call_units'])} unit(s){_call_spp(args, mode)}, rendered {_s(page['call_render_s'])} s "
            f"(predicted {_s(page['call_estimate_s'])} s; the first alone {_s(page['first_estimate_s'])} s). The "
            f"page shows it {_s(lag)} s later (its event stream's {TICK_S:g} s tick, then the preview's "
            "composition)."]


def _call_spp(args: argparse.Namespace, mode: str) -> str:
    """The samples each unit of a first render call renders, where the job's spp says (level off)."""
    if args.level != "off":
        return ""
    if mode == "passes":
        return f" of {budget_passes(args.spp)[0]} spp (a budget's first pass, its smallest, alone in its call)"
    return f" of {args.spp} spp"
