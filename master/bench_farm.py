"""`quekaro bench farm`: what the farm costs over one process, and what a second agent buys.

In one run, on one job (scene, spp, level, units fixed):
  1. `quekaro render` of the job (a fresh process, --threads T) against the same job on a running
     local farm with 1 agent of T threads: time from submit to the downloaded image. Ratio = farm / render.
     Target: <= 1.05 on a render of about 30 s.
  2. A farm with 1 agent of 1 thread against a farm with 2 agents of 1 thread each: speedup = T1 / T2.
     Target: >= 1.8 on this 2-core machine.
Farm start-up (XMPP server, master, agents' speed benchmark) is not counted: a farm is started once
and serves many jobs. Each farm renders the job once unmeasured first, so that every side starts with
Dr.Jit's kernel cache warm.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = REPO / "scenes" / "cbox.xml"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--res", type=int, default=384)
    parser.add_argument("--spp", type=int, default=512, help="chosen so that the render takes ~30 s on 2 threads")
    parser.add_argument("--level", default="off")
    parser.add_argument("--units", type=int, default=16)
    parser.add_argument("--threads", type=int, default=2, help="threads of `quekaro render` and of the 1-agent farm")


def _render_seconds(args: argparse.Namespace, defines: dict[str, str], out: Path) -> float:
    cmd = [sys.executable, "-m", "quekaro", "render", str(args.scene), "--opt", args.level, "--units",
           str(args.units), "--threads", str(args.threads), "-o", str(out)]
    cmd += [a for k, v in defines.items() for a in ("-D", f"{k}={v}")]
    start = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO, capture_output=True)
    return time.perf_counter() - start


def _farm_seconds(home: Path, agents: int, threads: int, bundle: bytes, defines: dict[str, str],
                  options: dict, out: Path) -> float:
    """Time of the job on a farm that is already up (after one unmeasured warm-up job)."""
    from quekaro.local_farm import LocalFarm

    with LocalFarm(home, agents=agents, threads=threads) as farm:
        farm.wait_for_agents()
        client = farm.client()
        times = []
        for _ in range(2):
            start = time.perf_counter()
            job_id = client.submit(bundle, defines, options)
            while (status := client.status(job_id))["status"] == "running":
                time.sleep(0.05)
            if status["status"] != "done":
                raise RuntimeError(f"benchmark job {job_id} {status['status']}: {status.get('error')}")
            client.result(job_id, out)
            times.append(time.perf_counter() - start)
    return times[-1]


def run(args: argparse.Namespace) -> dict:
    from core.bundle import make_bundle

    defines = {"res": str(args.res), "spp": str(args.spp)}
    options = {"level": args.level, "units": args.units, "spp": args.spp}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        bundle = make_bundle(args.scene, defines, tmp / "bundle.tar").path.read_bytes()
        _render_seconds(args, defines, tmp / "warm.exr")
        render_s = _render_seconds(args, defines, tmp / "render.exr")
        farm1_s = _farm_seconds(tmp / "farm-a", 1, args.threads, bundle, defines, options, tmp / "a.exr")
        one_s = _farm_seconds(tmp / "farm-b", 1, 1, bundle, defines, options, tmp / "b.exr")
        two_s = _farm_seconds(tmp / "farm-c", 2, 1, bundle, defines, options, tmp / "c.exr")
    result = {
        "scene": str(args.scene), "res": args.res, "spp": args.spp, "level": args.level, "units": args.units,
        "render_seconds": render_s, "farm_1_agent_seconds": farm1_s, "overhead_ratio": farm1_s / render_s,
        "farm_1x1_thread_seconds": one_s, "farm_2x1_thread_seconds": two_s, "speedup_2_agents": one_s / two_s,
    }
    if not args.json:
        print(f"quekaro render ({args.threads} threads)        {render_s:7.2f} s")
        print(f"farm, 1 agent ({args.threads} threads)         {farm1_s:7.2f} s   overhead ratio "
              f"{result['overhead_ratio']:.3f} (target <= 1.05)")
        print(f"farm, 1 agent x 1 thread           {one_s:7.2f} s")
        print(f"farm, 2 agents x 1 thread          {two_s:7.2f} s   speedup {result['speedup_2_agents']:.2f} "
              "(target >= 1.8)")
    return result
