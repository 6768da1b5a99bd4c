"""What the master sends for the auction's commands (master.service.outgoing): an agent's awards of a job in
one Awards message per run, every other message as it is, each agent's messages in the auction's order."""

from __future__ import annotations

import dataclasses

from core.model import messages as m
from core.model.geometry import Rect
from core.model.units import WorkUnit
from master import auction as au
from master.service import outgoing


def job(job_id: str) -> m.JobInfo:
    return m.JobInfo(job_id=job_id, scene_url=f"http://127.0.0.1:8765/jobs/{job_id}/scene", scene_hash="ab" * 32,
                     width=64, height=64, spp=8, depth=4, level="S", ranges={})


def award(job_id: str, index: int) -> m.Award:
    unit = WorkUnit(index=index, rect=Rect(16 * index, 0, 16, 16), C=0.5, S=256, Nd=0.1, cost=1.0)
    return m.Award(conversation=f"{job_id}-{index}", job=job(job_id), unit=unit, token=f"{index + 1:032x}",
                   upload_url=f"http://127.0.0.1:8765/jobs/{job_id}/units/{index}/tile", seed=index, estimate_s=1.0)


def unpacked(sent: list[tuple[str, m.Message]], to: str) -> list[m.Message]:
    return [one for agent, msg in sent if agent == to
            for one in (msg.each() if isinstance(msg, m.Awards) else (msg,))]


def test_a_rounds_awards_to_each_agent_go_in_one_message_per_job_in_order() -> None:
    cancel = m.Cancel(conversation="c", job_id="j1", index=9, reason="x")
    sends = [("a", award("j1", 0)), ("b", award("j1", 1)), ("a", award("j1", 2)), ("b", award("j1", 3)),
             ("a", award("j2", 0)), ("a", cancel), ("a", award("j1", 3))]
    commands: list[au.Instruction] = []
    for to, msg in sends:  # the auction's events between its sends, as it emits them
        commands += [au.SendToAgent(to, msg), au.UnitAwarded("j", 0, to, "t", 1.0, 1, 2.0)]
    sent = outgoing(commands)
    kinds = [(to, type(msg).__name__, getattr(msg, "job", None) and msg.job.job_id) for to, msg in sent]
    assert kinds == [("a", "Awards", "j1"), ("a", "Award", "j2"), ("a", "Cancel", None), ("a", "Award", "j1"),
                     ("b", "Awards", "j1")]
    for to in ("a", "b"):  # each agent reads what the auction sent it, in its order
        assert unpacked(sent, to) == [msg for agent, msg in sends if agent == to]


def test_a_lone_award_goes_as_itself() -> None:
    one = award("j1", 0)
    assert outgoing([au.SendToAgent("a", one)]) == [("a", one)]
    other = dataclasses.replace(one, conversation="x")
    two = outgoing([au.SendToAgent("a", one), au.SendToAgent("b", other)])
    assert [type(msg) for _, msg in two] == [m.Award, m.Award]
