"""`quekaro bench farm`: what the farm costs over one process, and what a second agent buys.

`run` measures one job (scene, spp, level, units fixed) in two comparisons, each side by side (`alternate`):
`quekaro render` against a local farm of one agent (ratio target OVERHEAD_TARGET), and a farm of one
1-thread agent against one of two (speedup target SPEEDUP_TARGET), where the two agents also render the job
in passes (`--progressive`: what passes cost over whole units, no target). Farm start-up is not counted.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from bench.provenance import rules_for
from bench.report import DEFAULT_OUT, command_of, write_report
from core.scene.bundle import make_bundle
from farm.local import LocalFarm

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = REPO / "scenes" / "cbox.xml"
# farm / render on a render of about 30 s; T(1 agent) / T(2 agents) on this 2-core machine
OVERHEAD_TARGET, SPEEDUP_TARGET = 1.05, 1.8
JOB_TIMEOUT_S = 3600.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for farm.md")
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--res", type=int, default=384)
    parser.add_argument("--spp", type=int, default=320, help="chosen so that the render takes ~30 s on 2 threads")
    parser.add_argument("--level", default="off")
    parser.add_argument("--units", type=int, default=16)
    parser.add_argument("--threads", type=int, default=2, help="threads of `quekaro render` and of the 1-agent farm")
    parser.add_argument("--repeats", type=int, default=2, help="measured runs of each side (after a warm-up)")


class _Job:
    """The benchmark job, as `quekaro render` arguments and as a farm submission."""

    def __init__(self, args: argparse.Namespace, workdir: Path) -> None:
        self.args = args
        self.workdir = workdir
        self.defines = {"res": str(args.res), "spp": str(args.spp)}
        self.options = {"level": args.level, "units": args.units, "spp": args.spp}
        self.bundle = make_bundle(args.scene, self.defines, workdir / "bundle.tar").path.read_bytes()

    def render_seconds(self) -> float:
        """A fresh `quekaro render` process of the job, with --threads T, as a user runs it."""
        a = self.args
        cmd = [sys.executable, "-m", "quekaro", "render", str(a.scene), "--opt", a.level, "--units",
               str(a.units), "--threads", str(a.threads), "-o", str(self.workdir / "render.exr")]
        cmd += [x for k, v in self.defines.items() for x in ("-D", f"{k}={v}")]
        start = time.perf_counter()
        subprocess.run(cmd, check=True, cwd=REPO, capture_output=True)
        return time.perf_counter() - start

    def farm_seconds(self, farm: Any, passes: bool = False) -> float:
        """The job on a running farm, from submit to the downloaded image; `passes`: in passes."""
        client = farm.client()
        start = time.perf_counter()
        job_id = client.submit(self.bundle, self.defines, self.options | ({"progressive": True} if passes else {}))
        status = client.wait(job_id, JOB_TIMEOUT_S, while_waiting=farm.check_alive)
        if status["status"] != "done":
            raise RuntimeError(f"benchmark job {job_id} {status['status']}: {status.get('error')}")
        client.result(job_id, self.workdir / f"farm-{job_id}.exr")
        return time.perf_counter() - start


def alternate(sides: dict[str, Callable[[], float]], repeats: int) -> dict[str, list[float]]:
    """Run every side once unmeasured (Dr.Jit's kernel cache warm, the agents' bundle cached), then
    `repeats` rounds of each side in turn (A B A B ..., so that a slow spell of a shared machine hits both):
    seconds per side."""
    for measure in sides.values():
        measure()
    times: dict[str, list[float]] = {name: [] for name in sides}
    for _ in range(repeats):
        for name, measure in sides.items():
            times[name].append(measure())
    return times


def _up(stack: ExitStack, home: Path, agents: int, threads: int) -> Any:
    """A local farm that `stack` stops, with all its agents registered. Its start-up (XMPP server, master,
    the agents' speed benchmark) is not timed: a farm is started once and serves many jobs."""
    farm = stack.enter_context(LocalFarm(home, agents=agents, threads=threads))
    farm.wait_for_agents()
    return farm


def rules_file(args: argparse.Namespace) -> Path | None:
    """The rule file the job's level planned with (bench.commands records its hash)."""
    return rules_for(args, [args.level])


def run(args: argparse.Namespace) -> dict:
    """1. `quekaro render` with T threads against a farm of 1 agent of T threads: ratio farm / render.
    2. A farm of 1 agent of 1 thread against one of 2 such agents, both up at once (an idle farm costs a
    few heartbeats a second): speedup T(1 agent) / T(2 agents); and the 2 agents' job in passes: ratio
    T(passes) / T(whole units)."""
    if args.repeats < 1:
        raise ValueError(f"--repeats {args.repeats}: must be at least 1")
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        job = _Job(args, tmp)
        with ExitStack() as stack:
            farm = _up(stack, tmp / "farm-a", 1, args.threads)
            first = alternate({"render": job.render_seconds, "farm": lambda: job.farm_seconds(farm)},
                              args.repeats)
        with ExitStack() as stack:
            one, two = _up(stack, tmp / "farm-b", 1, 1), _up(stack, tmp / "farm-c", 2, 1)
            second = alternate({"one": lambda: job.farm_seconds(one), "two": lambda: job.farm_seconds(two),
                                "passes": lambda: job.farm_seconds(two, passes=True)}, args.repeats)
    result = _result(args, first, second)
    text = format_report(result)
    result["report"] = str(write_report(args.out, "farm", "Farm overhead and 2-agent speedup", text,
                                        command_of(args, "quekaro bench farm")))
    if not args.json:
        print(text)
    return result


def _result(args: argparse.Namespace, first: dict[str, list[float]], second: dict[str, list[float]]) -> dict:
    """The headline ratios from each side's fastest run (noise only ever adds time), medians beside, and
    every run."""
    render_s, farm1_s = min(first["render"]), min(first["farm"])
    one_s, two_s, passes_s = min(second["one"]), min(second["two"]), min(second["passes"])
    return {
        "scene": str(args.scene), "res": args.res, "spp": args.spp, "level": args.level, "units": args.units,
        "threads": args.threads, "repeats": args.repeats,
        "render_seconds": render_s, "farm_1_agent_seconds": farm1_s, "overhead_ratio": farm1_s / render_s,
        "overhead_ratio_median": statistics.median(first["farm"]) / statistics.median(first["render"]),
        "farm_1x1_thread_seconds": one_s, "farm_2x1_thread_seconds": two_s, "speedup_2_agents": one_s / two_s,
        "speedup_2_agents_median": statistics.median(second["one"]) / statistics.median(second["two"]),
        "farm_2x1_thread_passes_seconds": passes_s, "passes_ratio": passes_s / two_s,
        "passes_ratio_median": statistics.median(second["passes"]) / statistics.median(second["two"]),
        "runs": {"render": first["render"], "farm_1_agent": first["farm"], "farm_1x1_thread": second["one"],
                 "farm_2x1_thread": second["two"], "farm_2x1_thread_passes": second["passes"]},
        "targets": {"overhead_ratio": OVERHEAD_TARGET, "speedup_2_agents": SPEEDUP_TARGET},
    }


def format_report(r: dict) -> str:
    def runs(name: str) -> str:
        return ", ".join(f"{s:.2f}" for s in r["runs"][name])

    def verdict(ok: bool) -> str:
        return "PASS" if ok else "MISS"

    return "\n".join([
        f"job: {Path(r['scene']).name} {r['res']}x{r['res']}, {r['spp']} spp, level {r['level']}, "
        f"{r['units']} units; fastest of {r['repeats']} alternating runs per side (all runs in brackets)",
        f"quekaro render ({r['threads']} threads)   {r['render_seconds']:7.2f} s   [{runs('render')}]",
        f"farm, 1 agent ({r['threads']} threads)    {r['farm_1_agent_seconds']:7.2f} s   [{runs('farm_1_agent')}]",
        f"  overhead ratio {r['overhead_ratio']:.3f} (medians {r['overhead_ratio_median']:.3f}; target <= "
        f"{OVERHEAD_TARGET}) {verdict(r['overhead_ratio'] <= OVERHEAD_TARGET)}",
        f"farm, 1 agent x 1 thread      {r['farm_1x1_thread_seconds']:7.2f} s   [{runs('farm_1x1_thread')}]",
        f"farm, 2 agents x 1 thread     {r['farm_2x1_thread_seconds']:7.2f} s   [{runs('farm_2x1_thread')}]",
        f"  speedup {r['speedup_2_agents']:.2f} (medians {r['speedup_2_agents_median']:.2f}; target >= "
        f"{SPEEDUP_TARGET}) {verdict(r['speedup_2_agents'] >= SPEEDUP_TARGET)}",
        f"farm, 2 agents, in passes     {r['farm_2x1_thread_passes_seconds']:7.2f} s   "
        f"[{runs('farm_2x1_thread_passes')}]",
        f"  passes / whole units {r['passes_ratio']:.3f} (medians {r['passes_ratio_median']:.3f})",
    ])
