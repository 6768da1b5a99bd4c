"""The farm end to end: real embedded XMPP server, master and agents in separate processes, real HTTP.

Faults are real too: SIGKILL of an agent mid-job, the master killed and restarted, the XMPP server
restarted, a forged message and a forged upload.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from disk_support import small_tmpfs
from farm_support import log_time
from web_support import wait_until

from bench.hosts import wait_for_idle
from core.errors import QuekaroError
from core.image.imageio import read_image
from core.image.tiles import read_tile
from core.model import messages as m
from core.scene.bundle import make_bundle
from core.transport.rates import SenderRates
from farm.client import FarmRefusal
from farm.local import LocalFarm
from master.store import JobStore

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "cbox.xml"
DEFINES = {"res": "64", "spp": "16"}
JOB_TIMEOUT_S = 240.0


def bundle_of(scene: Path, defines: dict[str, str]) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        return make_bundle(scene, defines, Path(tmp) / "b.tar").path.read_bytes()


def wait_job(farm: LocalFarm, job_id: str, timeout: float = JOB_TIMEOUT_S, until=None) -> dict:
    client = farm.client()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.status(job_id)
        if until is not None and until(job):
            return job
        if job["status"] != "running":
            return job
        time.sleep(0.3)
    raise AssertionError(f"job {job_id} still running after {timeout} s: {client.status(job_id)}")


def block_means(image: np.ndarray, block: int = 8) -> np.ndarray:
    h, w = image.shape[0] // block * block, image.shape[1] // block * block
    return image[:h, :w].reshape(h // block, block, w // block, block, 3).mean(axis=(1, 3))


def local_render(tmp: Path, defines: dict[str, str], level: str) -> np.ndarray:
    out = tmp / "local.exr"
    cmd = [sys.executable, "-m", "quekaro", "render", str(SCENE), "-o", str(out), "--opt", level, "--threads", "1"]
    for k, v in defines.items():
        cmd += ["-D", f"{k}={v}"]
    subprocess.run(cmd, check=True, cwd=REPO, capture_output=True, timeout=300)
    return read_image(out)


@pytest.fixture
def farm3(tmp_path):
    with LocalFarm(tmp_path / "farm", agents=3, threads=1) as farm:
        farm.wait_for_agents()
        yield farm


def test_job_on_three_agents_matches_local_render(farm3, tmp_path):
    client = farm3.client()
    sent = time.time()
    job_id = client.submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "off", "units": 6})
    accepted = time.time()
    job = wait_job(farm3, job_id)
    assert job["status"] == "done", job
    # Created when it arrived, not once planned: its time includes the planning the user waited for.
    assert job["created"] - sent < 0.5 * (accepted - sent), (sent, job["created"], accepted)
    out = client.result(job_id, tmp_path / "farm.exr")
    image = read_image(out)
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["image"]["file"] == str(out.resolve())  # not the master's own file, meaningless here
    assert report["image"]["png"] == str(out.with_suffix(".png").resolve())  # the PNG written beside it
    # As submitted: the submitter's path and -a folders (it was the name in the bundle, without the folders).
    assert report["scene"] == {"path": str(SCENE), "defines": DEFINES, "search_paths": []}
    # The whole job, as `quekaro render` counts it (it was the assembly's 0.01 s).
    assert report["totals"]["seconds"] >= report["finished"] - report["created"] > 0.1
    agents = {u["agent"] for u in report["units"]}
    assert len(report["units"]) == job["units_total"]
    assert np.isfinite(image).all() and image.shape == (64, 64, 3)
    reference = local_render(tmp_path, DEFINES, "off")
    # Same job, other seeds and units: equal up to noise. 8x8 block means at 16 spp of a Cornell box
    # carry a few % of noise; a missing tile, a shifted tile or a wrong exposure is off by far more.
    a, b = block_means(image), block_means(reference)
    rel = np.abs(a - b).mean() / b.mean()
    assert rel < 0.08, rel
    # The image mean of one such render has a relative std of 0.9 % (30 seeds measured), so two renders
    # differ by 1.3 % (1 sigma): 6 % is ~5 sigma, while one missing tile of six is off by ~17 %.
    assert abs(image.mean() - reference.mean()) / reference.mean() < 0.06
    assert len(agents) >= 2, agents  # the work was spread over several agents
    with small_tmpfs(tmp_path / "small", "64k", free=16 << 10) as disk:  # under the image's 20 KiB
        (disk / "r.exr").write_bytes(b"an earlier result")
        with pytest.raises(QuekaroError, match=f"job {job_id}: result not written to {disk / 'r.exr'}"):
            client.result(job_id, disk / "r.exr")
        assert sorted(p.name for p in disk.iterdir()) == ["filler", "r.exr"]  # a truncated r.exr was left
        assert (disk / "r.exr").read_bytes() == b"an earlier result"


def _agent_pids(farm: LocalFarm) -> list[int]:
    return [p.pid for name, p in farm.procs if name.startswith("agent-")]


def test_agent_killed_mid_job_the_job_completes(farm3, tmp_path):
    client = farm3.client()
    defines = {"res": "96", "spp": "64"}
    job_id = client.submit(bundle_of(SCENE, defines), defines, {"level": "off", "units": 9})
    wait_job(farm3, job_id, until=lambda j: j["units_done"] >= 1)
    victim = farm3.children[1].proc  # the first agent (children[0] is the master); not supervised here
    os.kill(victim.pid, signal.SIGKILL)
    victim.wait()
    job = wait_job(farm3, job_id)
    assert job["status"] == "done", job
    image = read_image(client.result(job_id, tmp_path / "r.exr"))
    assert np.isfinite(image).all() and (image.mean(axis=2) > 0).mean() > 0.9


@pytest.mark.parametrize("options", [{"level": "off", "units": 9}, {"level": "S", "units": 9, "adaptive": True},
                                     {"level": "VS", "units": 9, "progressive": True},
                                     {"level": "off", "units": 9, "noise": 0.05}],
                         ids=["off", "adaptive", "passes", "noise"])
def test_master_restarted_mid_job_resumes_without_rerendering(farm3, tmp_path, options):
    """An adaptive job's units keep their shares and its agents their first pass through the restart
    (the store's rows and plan): the units rendered after it render the same plan. A progressive job goes
    on from its passes so far (merged again from their tiles): no pass is rendered twice, and each unit
    ends with its own samples (a budget) or its verdict (a noise goal)."""
    client = farm3.client()
    defines = {"res": "96", "spp": "64"}
    job_id = client.submit(bundle_of(SCENE, defines), defines, options)
    deadline = time.monotonic() + 120
    while len(_done_tokens(farm3.home, job_id)) < 4 and time.monotonic() < deadline:  # passes or units
        time.sleep(0.05)
    master = farm3.children[0]
    master.proc.kill()
    master.proc.wait()
    done_before = _done_tokens(farm3.home, job_id)
    farm3._spawn(master)  # the same command again, a child of the farm (it dies with it)
    _wait_http(farm3)
    job = wait_job(farm3, job_id)
    assert job["status"] == "done", job
    attempts = _attempts(farm3.home, job_id)
    for index in done_before:
        assert sum(1 for a in attempts if a[0] == index and a[1] == "done") == 1, (index, attempts)
    out = client.result(job_id, tmp_path / "r.exr")
    image = read_image(out)
    assert np.isfinite(image).all() and (image.mean(axis=2) > 0).mean() > 0.9
    if options.get("adaptive"):
        report = json.loads(out.with_suffix(".json").read_text())
        first, shares = report["adaptive"]["first_spp"], report["adaptive"]["unit_spp"]
        assert [(u["spp"], u["first_spp"]) for u in report["units"]] == [(spp, first) for spp in shares]
    if "progressive" in options or "noise" in options:
        report = json.loads(out.with_suffix(".json").read_text())
        assert len(report["units"]) == 9 and len(done_before) < len(_done_tokens(farm3.home, job_id))
        verdicts = {u["verdict"] for u in report["units"]}
        assert verdicts <= ({"budget"} if "progressive" in options else {"met", "cap"}), report["units"]
        if "progressive" in options:  # each unit its rules' own samples, through the restart
            with JobStore(farm3.home / "jobs.sqlite", readonly=True) as store:
                budgets = [u.spp for u in store.plan(job_id, tmp_path / "scene.xml").units]
            assert [u["spp"] >= b for u, b in zip(report["units"], budgets, strict=True)] == [True] * 9


def test_xmpp_server_restart_mid_job(farm3, tmp_path):
    client = farm3.client()
    defines = {"res": "96", "spp": "64"}
    job_id = client.submit(bundle_of(SCENE, defines), defines, {"level": "off", "units": 9})
    wait_job(farm3, job_id, until=lambda j: j["units_done"] >= 1)
    farm3.server.restart(downtime=1.0)
    job = wait_job(farm3, job_id)
    assert job["status"] == "done", job


def test_forged_upload_and_unknown_sender_are_refused(farm3, tmp_path):
    client = farm3.client()
    job_id = client.submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "off", "units": 4})
    body = b"not an exr"
    req = urllib.request.Request(f"{farm3.url}/jobs/{job_id}/units/0/tile", data=body, method="PUT",
                                 headers={"X-Quekaro-Token": "ab" * 16, "X-Content-SHA256": "00" * 32})
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(req, timeout=10)
    assert err.value.code in (400, 403, 404, 409, 422)
    # A JID the farm did not make: the farm's XMPP server refuses its registration, so it never reaches the
    # master (tests/test_trust.py covers the master's own allowlist).
    peer = subprocess.run(
        [sys.executable, "tests/xmpp_peer.py", "--jid", "intruder@localhost", "--password", "pw",
         "--register", "--server", "127.0.0.1", "--port", str(farm3.server.port), "--to", "master@localhost",
         "--ontology", "quekaro-render", "--body", json.dumps({"v": m.PROTOCOL_VERSION, "conversation": "x"}), "send"],
        cwd=REPO, capture_output=True, text=True, timeout=60)
    job = wait_job(farm3, job_id)
    assert job["status"] == "done", (job, peer.stderr[-2000:])
    events = [json.loads(line) for line in peer.stdout.splitlines() if line.startswith("{")]
    assert events and events[0]["event"] == "error" and "refused" in events[0]["reason"], peer.stdout


def _wait_http(farm: LocalFarm, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            farm.client().jobs()
            return
        except Exception:
            time.sleep(0.3)
    raise AssertionError("master did not come back")


def _attempts(home: Path, job_id: str) -> list[tuple[int, str]]:
    import sqlite3

    with sqlite3.connect(home / "jobs.sqlite") as db:
        return [(r[0], r[1]) for r in db.execute("SELECT idx, outcome FROM attempts WHERE job_id = ?", (job_id,))]


def _done_tokens(home: Path, job_id: str) -> set[int]:
    import sqlite3

    with sqlite3.connect(home / "jobs.sqlite") as db:
        return {r[0] for r in db.execute("SELECT idx FROM units WHERE job_id = ? AND status = 'done'", (job_id,))}


def _children(pid: int) -> set[int]:
    """Every descendant of `pid` (from /proc)."""
    kids: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(entry.name))
    out, todo = set(), [pid]
    while todo:
        for kid in kids.get(todo.pop(), []):
            out.add(kid)
            todo.append(kid)
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def assert_all_gone(pids: set[int], timeout: float, what: str) -> None:
    """Every process in `pids` ends within `timeout` seconds, or the assertion names `what` outlived."""
    deadline = time.monotonic() + timeout
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [p for p in pids if _alive(p)], f"processes of the farm outlived {what}"


def test_sigterm_to_quekaro_up_stops_the_whole_farm(tmp_path):
    home = tmp_path / "farm"
    up = subprocess.Popen([sys.executable, "-m", "quekaro", "up", "--agents", "1", "--threads", "1",
                           "--home", str(home)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while not (home / "farm.json").exists() and time.monotonic() < deadline:
            assert up.poll() is None, up.stdout.read().decode()[-2000:]
            time.sleep(0.3)
        time.sleep(2.0)  # the agent process has been spawned by now
        farm = _children(up.pid)
        assert len(farm) >= 3, farm  # XMPP server, master, agent (and their helpers)
        up.send_signal(signal.SIGTERM)
        assert up.wait(timeout=60) == 0
        assert_all_gone(farm, 20, "quekaro up")
    finally:
        if up.poll() is None:
            up.kill()


def test_a_farm_starts_again_on_the_same_home(tmp_path):
    """`quekaro demo` twice: the second start must not trip over the first one's XMPP accounts."""
    home = tmp_path / "farm"
    for _ in range(2):
        with LocalFarm(home, agents=1, threads=1) as farm:
            farm.wait_for_agents(timeout=120)
            assert farm.client().agents()


def _a_job_under_way(farm: LocalFarm, defines: dict[str, str]) -> tuple:
    """The farm's client and a 4-unit level-off job of `defines`, once an agent holds one of its units."""
    farm.wait_for_agents()
    client = farm.client()
    job_id = client.submit(bundle_of(SCENE, defines), defines, {"level": "off", "units": 4})
    wait_job(farm, job_id, until=lambda j: j["agents_busy"] > 0)
    return client, job_id


def test_a_cancelled_render_ends_and_the_next_job_on_its_agent_is_not_held_behind_it(tmp_path):
    """A cancelled unit's render ran to its end (here ~30 s) while its agent, holding no unit, bid and
    took the next job's unit: that unit missed its deadline, and with one agent its whole job failed."""
    with LocalFarm(tmp_path / "farm", agents=1, threads=1) as farm:
        client, job_id = _a_job_under_way(farm, {"res": "64", "spp": "65536"})
        time.sleep(3.0)  # its bundle fetched, into the render (a unit renders for ~30 s)
        assert client.cancel(job_id)
        small = client.submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "off", "units": 4})
        job = wait_job(farm, small, timeout=120)
        assert job["status"] == "done", job
        assert b"ending the render" in (farm.home / "logs" / "agent-0.log").read_bytes()


def test_a_render_killed_once_on_a_one_agent_farm_is_retried_and_its_job_completes(tmp_path):
    """The unit went to no other agent, so the job failed at its first failure ('render process killed by
    SIGKILL'), though an agent is blocklisted only after 3 and a unit fails its job only after 5."""
    with LocalFarm(tmp_path / "farm", agents=1, threads=1) as farm:
        _, job_id = _a_job_under_way(farm, {"res": "64", "spp": "4096"})
        agent = next(p.pid for name, p in farm.procs if name.startswith("agent-"))
        deadline, child = time.monotonic() + 60, None
        while child is None and time.monotonic() < deadline:
            time.sleep(0.2)
            child = _render_child(agent)
        assert child is not None, "the agent's render process"
        time.sleep(1.0)  # into its render
        os.kill(child, signal.SIGKILL)
        job = wait_job(farm, job_id)
        assert job["status"] == "done", job
        assert job["attempts_retried"] >= 1 and "SIGKILL" in job["last_retry"], job  # as `quekaro status` says


def test_a_result_the_master_cannot_compose_for_a_full_disk_is_a_507_and_composed_once_there_is_space(tmp_path):
    """Composing (write_outputs) names the file it could not write, caused by ENOSPC: that was a 500."""
    with small_tmpfs(tmp_path / "small", "160m") as disk, LocalFarm(disk / "home", agents=1, threads=1) as farm:
        farm.wait_for_agents()
        client = farm.client()
        job_id = client.submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "off", "units": 4})
        assert wait_job(farm, job_id)["status"] == "done"
        client.result(job_id, tmp_path / "first.exr")  # composed once, as every job is when it ends
        for made in (farm.home / "jobs" / job_id).glob("result.*"):
            made.unlink()  # as if never composed: the next request composes it
        filler = disk / "filler"
        with filler.open("wb") as fh, contextlib.suppress(OSError):
            fh.write(b"\0" * (200 << 20))
        with pytest.raises(QuekaroError, match=r"^disk full on the master: the job's image is composed") as full:
            client.result(job_id, tmp_path / "full.exr")
        assert full.value.status == 507
        filler.unlink()
        out = client.result(job_id, tmp_path / "later.exr")
        assert np.array_equal(read_image(out), read_image(tmp_path / "first.exr"))


def _planner_child(master_pid: int) -> int | None:
    """The master's planning process (a render process, core.render.process), if it runs."""
    return _render_child(master_pid)


def _render_child(parent: int) -> int | None:
    """A render process (core.render.process) under `parent`, if one runs."""
    for pid in _children(parent):
        try:
            if b"_child_entry" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return pid
        except OSError:
            continue
    return None


def test_a_planning_that_crashes_fails_its_own_job_and_the_next_job_plans(farm3):
    """A scene whose planning kills its process (here the planner child, SIGKILLed mid pre-pass, as an LLVM
    abort would) is refused with the reason; the master stays up and plans the next job in a new child."""
    client = farm3.client()
    master = farm3.children[0].proc
    big = {"res": "2048", "spp": "4096"}  # its pre-pass at full resolution: several seconds
    outcome: dict[str, object] = {}

    def submit_big() -> None:
        try:
            outcome["job"] = client.submit(bundle_of(SCENE, big), big, {"level": "S"})
        except Exception as exc:  # the refusal, checked below
            outcome["error"] = exc

    thread = threading.Thread(target=submit_big)
    thread.start()
    deadline = time.monotonic() + 60
    while (planner := _planner_child(master.pid)) is None:
        assert time.monotonic() < deadline and thread.is_alive(), outcome
        time.sleep(0.05)
    time.sleep(1.5)  # past Mitsuba's import, into the analysis and the pre-pass
    os.kill(planner, signal.SIGKILL)
    thread.join(120)
    assert "job" not in outcome and "killed by SIGKILL" in str(outcome.get("error")), outcome
    assert "cbox.xml" in str(outcome["error"]) and client.jobs() == []
    job_id = client.submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "S", "units": 4})
    assert wait_job(farm3, job_id)["status"] == "done"
    assert master.poll() is None and _planner_child(master.pid) not in (None, planner)


def test_a_scene_mitsuba_refuses_is_named_as_the_user_submitted_it(farm3, tmp_path):
    """The refusal names the scene file and line as in the user's bundle, not the master's job folder."""
    broken = tmp_path / "broken.xml"
    broken.write_text('<scene version="3.0.0">\n  <shape type="no_such_plugin_here"/>\n</scene>\n')
    client = farm3.client()
    with pytest.raises(FarmRefusal) as refused:
        client.submit(bundle_of(broken, {}), {}, {"level": "S"})
    said = str(refused.value)
    assert refused.value.status == 422 and "HTTP" not in said and ".cpp:" not in said, said
    assert "broken.xml" in said and "no_such_plugin_here" in said and "line 2" in said, said
    assert str(farm3.home) not in said and "/jobs/" not in said, said
    # A scene without a sensor: Mitsuba loads it and has nothing to render (planning raised an IndexError, a 500).
    (tmp_path / "nosensor.xml").write_text('<scene version="3.0.0">\n  <integrator type="path"/>\n'
                                           '  <shape type="sphere"/>\n</scene>\n')
    with pytest.raises(FarmRefusal) as refused:
        client.submit(bundle_of(tmp_path / "nosensor.xml", {}), {}, {"level": "S"})
    assert refused.value.status == 422
    said = str(refused.value)
    assert "nosensor.xml: the scene has no sensor" in said and str(farm3.home) not in said, said
    assert client.jobs() == []


def test_a_job_no_message_can_carry_is_refused_at_submit_with_a_reason(farm3):
    """An image over the protocol's 65536 pixels was accepted (201) and then failed as its first message
    left; a -D value holding a NUL, and an X-Quekaro-Job nested past Python's recursion limit, were 500s."""
    client = farm3.client()
    huge = {"res": "70000", "spp": "1"}
    with pytest.raises(QuekaroError, match=r"70000 outside 1\.\.65536"):
        client.submit(bundle_of(SCENE, huge), huge, {"level": "off"})
    many = {"res": "32", "spp": "2000000"}  # Mitsuba renders it; the farm's messages carry up to 2^20
    with pytest.raises(QuekaroError, match=r"^cbox.xml: sample_count 2000000 \(the scene's, or its -D\) "
                                           r"is above 1048576, .* give --spp"):
        client.submit(bundle_of(SCENE, many), many, {"level": "off"})
    with pytest.raises(QuekaroError, match=r"-D res: its value '32\\x00' holds"):
        client.submit(bundle_of(SCENE, DEFINES), {**DEFINES, "res": "32\x00"}, {"level": "off"})
    deep = urllib.request.Request(client.url + "/api/jobs", data=bundle_of(SCENE, DEFINES), method="POST", headers={
        "authorization": f"bearer {client.token}", "X-Quekaro-Job": "[" * 3000 + "]" * 3000})  # any case (RFC 9110)
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(deep, timeout=60)
    assert refused.value.code == 400 and b"X-Quekaro-Job" in refused.value.read()
    wrong = urllib.request.Request(client.url + "/api/jobs", headers={"Authorization": "Bearer wrong"})
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(wrong, timeout=60)
    assert refused.value.code == 401  # the reason, not aiohttp's bare "Unauthorized"
    assert json.loads(refused.value.read()) == {"error": "missing or wrong admin token", "status": 401}
    assert client.jobs() == []


def test_submitting_several_scenes_one_refused_still_submits_the_others(farm3, tmp_path):
    broken = tmp_path / "broken.xml"
    broken.write_text('<scene version="3.0.0"><shape type="no_such_plugin_here"/></scene>\n')
    done = subprocess.run([sys.executable, "-m", "quekaro", "submit", str(broken), str(SCENE), "--opt", "off",
                           "--home", str(farm3.home)], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert done.returncode == 2, done.stderr
    assert f"1 of 2 scenes refused: {broken}" in done.stderr and "no_such_plugin_here" in done.stderr
    (line,) = done.stdout.splitlines()  # the one submitted: its id and its scene
    job_id, scene = line.split()
    assert scene == SCENE.name
    assert [j["job_id"] for j in farm3.client().jobs()] == [job_id]
    assert wait_job(farm3, job_id)["status"] == "done"


@pytest.mark.slow
@pytest.mark.alone  # its premise, agents sending faster than the old allowance, needs their CPUs
def test_agents_rendering_tiny_units_are_not_refused_as_a_flood(tmp_path):
    """Units that render in milliseconds make each agent send a proposal (or a refusal) and an inform per
    unit, dozens a second for the whole job. The master's per-sender allowance must hold that: a proposal
    refused unread leaves its auction waiting out the CFP timeout and the agent left out after it (the
    farm's benchmark read 2-4 s stalls on 3-7 s jobs when the allowance was 20 a second)."""
    with LocalFarm(tmp_path / "farm", agents=2, threads=1) as farm:
        farm.wait_for_agents()
        wait_for_idle()  # what ran before (in CI, a whole suite's farms) is over: the agents get the CPUs
        client = farm.client()
        defines = {"res": "512", "spp": "16"}
        for _ in range(2):
            job_id = client.submit(bundle_of(SCENE, defines), defines, {"level": "S", "spp": 2, "units": 256})
            assert wait_job(farm, job_id)["status"] == "done"
        master_log = (farm.home / "logs" / "master.log").read_text()
        agent_logs = [log.read_text() for log in (farm.home / "logs").glob("agent-*.log")]
    # The agents did send more than the old allowance (a burst of 100, then 20 a second) let through.
    assert max(_refused_by(SenderRates(20.0, 100.0), log) for log in agent_logs) > 0
    # The refusals themselves, not the silences they cause: a loaded machine may let a call time out anyway.
    refused = [line for line in master_log.splitlines() if "messages a second" in line]
    assert not refused, refused[:5]


def _refused_by(rates: SenderRates, agent_log: str) -> int:
    """How many of the proposals and informs an agent's log shows (refusals are not logged) `rates` would
    have refused, replayed at the times they were logged."""
    sent = sorted(log_time(line) for line in agent_log.splitlines() if "proposing for" in line or ": done in " in line)
    return sum(not rates.allow("agent", t) for t in sent)


def test_a_farm_job_renders_no_unit_below_its_depth_floor(farm3, tmp_path):
    """The master measures each unit's depth floor (planning.depthcut) and the agents' rules hold to it:
    on the suite's interior at level VB the rules alone cut most units to depth 4 or 6, which darkens them
    (tests/test_depth_floors.py); here every unit renders at or above its floor, most of those at the
    user's 8."""
    client = farm3.client()
    scene = REPO / "bench" / "scenes" / "interior-window.xml"
    defines = {"res": "96"}
    job_id = client.submit(bundle_of(scene, defines), defines, {"level": "VB", "spp": 32})
    job = wait_job(farm3, job_id)
    assert job["status"] == "done", job
    report = json.loads(client.result(job_id, tmp_path / "vb.exr").with_suffix(".json").read_text())
    units = report["units"]
    assert all(u["depth"] >= u["depth_floor"] for u in units), [(u["depth"], u["depth_floor"]) for u in units]
    wanted = [u for u in units if u["outputs"]["Rl"] < 0.9]  # units the rules alone would cut
    assert len(wanted) >= len(units) // 2, [u["outputs"] for u in units]
    assert sum(u["depth"] == 8 for u in wanted) >= len(wanted) // 2, [u["depth"] for u in units]
    assert report["prepass"]["depth_floor_depths"] == [8, 6, 4]


@pytest.mark.slow
def test_a_second_agent_logged_in_with_the_same_jid_is_named_in_the_log_and_by_quekaro_agents(tmp_path):
    """Two processes with one JID both receive the master's messages and render every unit awarded to
    it (the second upload of each is refused): the master says so instead of leaving it to be guessed."""
    from test_cli import quekaro

    with LocalFarm(tmp_path / "home", agents=1, threads=1) as farm:
        farm.wait_for_agents()
        (agent,) = [c for c in farm.children if c.name == "agent-0"]
        args = list(agent.proc.args)
        args[args.index("--workdir") + 1] = str(tmp_path / "twin")
        with (tmp_path / "twin.log").open("wb") as log:
            twin = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, cwd=REPO,
                                    env=dict(os.environ, **agent.env, PYTHONPATH=str(REPO)))
        try:
            jid = args[args.index("--jid") + 1]
            wait_until(lambda: "connected to" in (tmp_path / "twin.log").read_text(errors="replace"), 60,
                       "the twin agent's connection")
            job_id = farm.client().submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "off", "units": 4})
            assert wait_job(farm, job_id)["status"] == "done"
            (row,) = farm.client().agents()
            listed = quekaro("agents", "--home", str(farm.home))
        finally:
            twin.terminate()
            twin.wait(30)
        master_log = (farm.home / "logs" / "master.log").read_text()
    assert row["jid"] == jid and row["shared"] and f"2 clients log in as {jid}" in row["shared"], row
    assert f"2 clients log in as {jid}" in master_log
    assert f"warning: 2 clients log in as {jid}" in listed.stdout, listed.stdout



def _level_s_job(farm: LocalFarm, defines: dict[str, str], out: Path) -> tuple[Path, str]:
    """A level-S job of SCENE on the farm once its agents are up, done; its image at `out`, and its id."""
    farm.wait_for_agents()
    client = farm.client()
    job_id = client.submit(bundle_of(SCENE, defines), defines, {"level": "S"})
    job = wait_job(farm, job_id)
    assert job["status"] == "done", job
    return client.result(job_id, out), job_id


def test_a_rule_level_job_renders_each_agents_units_in_batches_and_matches_a_local_render(tmp_path):
    """Units of one job and depth an agent holds render in one call (core.render.batch via
    agents.state's batches): every tile says so, several share a call (its seed), and the image agrees
    with `quekaro render` of the same level up to noise."""
    defines = {"res": "96", "spp": "16"}
    with LocalFarm(tmp_path / "farm", agents=2, threads=1) as farm:
        out, job_id = _level_s_job(farm, defines, tmp_path / "farm.exr")
        tiles = sorted((farm.home / "jobs" / job_id / "tiles").glob("*.exr"))
        seeds = Counter(read_tile(t).meta["seed"] for t in tiles)
    report = json.loads(out.with_suffix(".json").read_text())
    assert len(report["units"]) >= 8 and all(u["method"].startswith("together") for u in report["units"])
    assert len(tiles) == len(report["units"]) and max(seeds.values()) >= 2, seeds  # units shared a call
    # Its agents plan with the master's rules, which cut no depth at level S: no depth floors measured
    # (MasterService._floors), every unit held at the user's depth for an agent with other rules.
    assert "depth_floor_depths" not in report["prepass"], report["prepass"]
    assert {(u["depth"], u["depth_floor"]) for u in report["units"]} == {(report["units"][0]["depth"],) * 2}
    # The pre-pass ran on the master's --threads, the agents' two together (`quekaro master --threads`).
    assert report["options"]["threads"] == 2
    image, reference = read_image(out), local_render(tmp_path, defines, "S")
    a, b = block_means(image), block_means(reference)
    assert np.abs(a - b).mean() / b.mean() < 0.08  # as test_job_on_three_agents_matches_local_render
    # Seeded from the scene file on both sides (core.model.seeds.plan_seed): the job reads the pre-pass
    # it reads in one process, so a level spends alike on a farm and in `quekaro render`.
    local = json.loads((tmp_path / "local.json").read_text())
    assert report["prepass"] == local["prepass"], (report["prepass"], local["prepass"])


def test_a_scene_the_bundle_rewrites_reads_the_pre_pass_it_reads_in_one_process(tmp_path):
    """A scene that reads a file outside its folder is rewritten in the bundle (its copy names the packed
    file); the job's pre-pass is still seeded from the file as submitted, as `quekaro render` seeds it."""
    (tmp_path / "common").mkdir()
    (tmp_path / "common" / "light.xml").write_text(
        "<scene version='3.0.0'><emitter type='constant'><rgb name='radiance' value='0.05'/></emitter></scene>")
    scene = tmp_path / "scene" / "cbox.xml"
    scene.parent.mkdir()
    scene.write_text(SCENE.read_text().replace("</scene>", "<include filename='../common/light.xml'/></scene>"))
    defines = {"res": "48", "spp": "8"}
    with LocalFarm(tmp_path / "farm", agents=1, threads=1) as farm:
        farm.wait_for_agents()
        client = farm.client()
        job_id = client.submit(bundle_of(scene, defines), defines, {"level": "S"})
        assert wait_job(farm, job_id)["status"] == "done"
        out = client.result(job_id, tmp_path / "farm.exr")
        unpacked = next((farm.home / "jobs" / job_id / "scene").glob("*.xml"))
        assert unpacked.read_bytes() != scene.read_bytes()  # the bundle's copy names the packed file
    local = tmp_path / "local.exr"
    cmd = [sys.executable, "-m", "quekaro", "render", str(scene), "-o", str(local), "--opt", "S", "--threads", "1",
           "--no-progress", *(f"-D{k}={v}" for k, v in defines.items())]
    subprocess.run(cmd, check=True, cwd=REPO, capture_output=True, timeout=300)
    farm_prepass = json.loads(out.with_suffix(".json").read_text())["prepass"]
    assert farm_prepass == json.loads(local.with_suffix(".json").read_text())["prepass"], farm_prepass


VERTEX = '<fset label="VB" a="3" b="3.5" c="4" d="4"/>'  # the Ibs output's VB set in the shipped rules


@pytest.mark.parametrize("edit, floors", [
    (lambda text: text + "\n<!-- an agent's own copy -->\n", False),
    (lambda text: text.replace(VERTEX, VERTEX.replace('b="3.5"', 'b="3.6"')), True),
], ids=["a-comment-plans-alike", "a-moved-vertex-plans-otherwise"])
def test_a_farm_measures_depth_floors_at_every_rule_level_only_for_an_agent_whose_rules_compute_otherwise(
        tmp_path, edit, floors):
    """One agent plans with a rule file of its own. Where it computes what the master's rules compute (a
    comment: another file, the same RuleBase.digest), the master knows what its rules cut, and a level-S
    job measures no depth floors; where it computes otherwise (a moved vertex), the master cannot see what
    they cut, and it measures every unit's depth floor, which its own rules alone would not
    (test_a_rule_level_job_renders_each_agents_units_in_batches...)."""
    from core.data import default_rules_path

    text = default_rules_path().read_text()
    other = tmp_path / "other-rules.xml"
    other.write_text(edit(text))
    assert other.read_text() != text
    defines = {"res": "64", "spp": "8"}
    with LocalFarm(tmp_path / "farm", agents=2, threads=1, rules=[default_rules_path(), other]) as farm:
        out, _ = _level_s_job(farm, defines, tmp_path / "s.exr")
    report = json.loads(out.with_suffix(".json").read_text())
    assert bool(report["prepass"].get("depth_floor_depths")) == floors, report["prepass"]
    assert all(u["depth"] >= u["depth_floor"] for u in report["units"])
