"""The message schema: round trips, refusals that name the field at fault, size limits, and a fuzz run."""

from __future__ import annotations

import contextlib
import dataclasses
import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.errors import MessageError
from core.model import messages as m
from core.model.geometry import Rect
from core.model.units import SPP_MAX, WorkUnit

HASH = "ab" * 32
TOKEN = "0123456789abcdef" * 2


def job(**changes) -> m.JobInfo:
    base = dict(
        job_id="job-1", scene_url="http://127.0.0.1:8765/jobs/job-1/scene", scene_hash=HASH,
        width=96, height=64, spp=16, depth=8, level="S", ranges={"C": (0.0, 2.5), "Nd": (0.0, 1.0)},
    )  # fmt: skip
    return m.JobInfo(**{**base, **changes})


def unit(index: int = 0, rect: Rect | None = None, cost: float = 1.5) -> WorkUnit:
    rect = rect or Rect(0, 0, 32, 32)
    return WorkUnit(index=index, rect=rect, C=0.7, S=rect.area, Nd=0.1, cost=cost)


ONE_AWARD = m.Award(conversation="c2", job=job(), unit=unit(), token=TOKEN, upload_url="http://127.0.0.1:8765/t/0",
                    seed=0, estimate_s=3.0)

ONE_OF_EACH = [
    m.CallForProposal(
        conversation="c1", job=job(), units=(unit(0), unit(1, Rect(32, 0, 64, 64))), reply_within_s=2
    ),
    m.Propose(conversation="c1", job_id="job-1", estimates=(m.Estimate(index=0, seconds=3.0),)),
    m.Refuse(conversation="c1", job_id="job-1", reason="busy"),
    m.Award(
        conversation="c2",
        job=job(),
        unit=unit(),
        token=TOKEN,
        upload_url="http://127.0.0.1:8765/t/0",
        seed=0,
        estimate_s=3.0,
    ),
    m.packed([ONE_AWARD, dataclasses.replace(ONE_AWARD, conversation="c3", unit=unit(1), token="cd" * 16)])[0],
    m.Reject(conversation="c1", job_id="job-1", reason="awarded elsewhere"),
    m.Inform(
        conversation="c2",
        job_id="job-1",
        index=0,
        token=TOKEN,
        tile_hash=HASH,
        depth=4,
        spp=8,
        band=2,
        seconds=2.9,
        nonfinite=0,
    ),
    m.Failure(conversation="c2", job_id="job-1", index=0, token=TOKEN, reason="child process crashed"),
    m.Register(conversation="r1", speed=1.25, threads=1, rules="rules/quekaro.xml"),
    m.Welcome(conversation="r1"),
    m.Introduce(conversation="i1"),
    m.Heartbeat(conversation="h1", busy=(m.HeldUnit(job_id="job-1", index=0),)),
    m.Cancel(conversation="c2", job_id="job-1", index=None, reason="job cancelled"),
]


@pytest.mark.parametrize("msg", ONE_OF_EACH, ids=lambda msg: msg.performative)
def test_every_kind_round_trips(msg: m.Message) -> None:
    performative, body = m.encode(msg)
    assert performative == msg.performative
    assert json.loads(body)["v"] == m.PROTOCOL_VERSION
    assert m.parse(performative, body) == msg
    assert m.parse_with_metadata(m.metadata(msg), body.encode()) == msg


def test_every_performative_has_a_kind() -> None:
    assert {msg.performative for msg in ONE_OF_EACH} == set(m.KINDS)


def of_kind(kind: type[m.Message]) -> m.Message:
    return next(msg for msg in ONE_OF_EACH if type(msg) is kind)


def body_of(msg: m.Message) -> dict:
    return json.loads(m.encode(msg)[1])


def refused(performative: str, data: dict | str) -> MessageError:
    body = data if isinstance(data, str) else json.dumps(data)
    with pytest.raises(MessageError) as info:
        m.parse(performative, body)
    return info.value


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda d: d.pop("token"), "token"),
        (lambda d: d.update(index=-1), "index"),
        (lambda d: d.update(index=True), "index"),
        (lambda d: d.update(index=1.0), "index"),
        (lambda d: d.update(seconds="3"), "seconds"),
        (lambda d: d.update(seconds=1e300), "seconds"),
        (lambda d: d.update(token="NOT-HEX"), "token"),
        (lambda d: d.update(token=TOKEN + "\n"), "token"),
        (lambda d: d.update(extra=1), "extra"),
        (lambda d: d.update(v=m.PROTOCOL_VERSION + 1), "v"),
        (lambda d: d.pop("v"), "v"),
        (lambda d: d.update(job_id="a b"), "job_id"),
        (lambda d: d.update(conversation=""), "conversation"),
    ],
)
def test_bad_inform_fields_are_refused_by_name(change, field: str) -> None:
    data = body_of(of_kind(m.Inform))
    change(data)
    assert refused("inform", data).field == field


def test_an_inform_carries_the_spp_a_sampler_rounds_a_jobs_most_up_to() -> None:
    """Mitsuba's orthogonal sampler renders 1031^2 samples where it is given 2^20, the most a job asks for:
    the agent reports what it rendered, so the master must read that count."""
    data = body_of(of_kind(m.Inform))
    data["spp"] = 1031**2
    assert m.parse("inform", json.dumps(data)).spp == 1031**2
    data["spp"] = 2 * SPP_MAX + 1
    assert refused("inform", data).field == "spp"


def test_cfp_cross_field_checks() -> None:
    data = body_of(ONE_OF_EACH[0])
    data["units"][1]["rect"] = [80, 0, 32, 32]  # runs past the 96-pixel width
    data["units"][1]["S"] = 32 * 32
    assert refused("cfp", data).field == "units.rect"
    data = body_of(ONE_OF_EACH[0])
    data["units"][1]["index"] = 0
    assert refused("cfp", data).field == "units"
    data = body_of(ONE_OF_EACH[0])
    data["job"]["ranges"]["C"] = [3.0, 1.0]
    assert refused("cfp", data).field == "ranges.C"
    data = body_of(ONE_OF_EACH[0])
    data["job"]["level"] = "XL"
    assert refused("cfp", data).field == "job.level"
    data = body_of(ONE_OF_EACH[0])
    data["units"] = []
    assert refused("cfp", data).field == "units"


def test_non_finite_and_malformed_json_are_refused() -> None:
    body = m.encode(of_kind(m.Inform))[1].replace('"seconds":2.9', '"seconds":NaN')
    assert refused("inform", body).field == "body"
    assert refused("inform", body.replace("NaN", "Infinity")).field == "body"
    assert refused("inform", "{").field == "body"
    assert refused("inform", "[1, 2]").field == "body"
    assert refused("inform", "[" * 50_000 + "]" * 50_000).field == "body"  # recursion, not a crash
    assert refused("inform", '{"v": ' + "9" * 5000 + "}").field == "body"  # int-string limit
    assert refused("inform", "\ud800").field == "body"  # lone surrogate
    with pytest.raises(MessageError, match="UTF-8"):
        m.parse("inform", b"\xff\xfe")
    assert refused("no-such", "{}").field == "performative"


def test_empty_and_oversized_bodies_are_refused_before_parsing() -> None:
    assert refused("inform", "").field == "body"
    # Not JSON at all, so only the size check can be what refuses it.
    with pytest.raises(MessageError, match="exceeds the limit"):
        m.parse("inform", "x" * (m.MAX_BODY_BYTES + 1))
    with pytest.raises(MessageError, match="exceeds the limit"):
        m.parse("inform", "é" * (m.MAX_BODY_BYTES // 2 + 1))  # few characters, too many bytes
    assert m.MAX_BODY_BYTES <= 256 * 1024 // 4  # well under Prosody's stanza limit


def test_largest_cfp_fits_the_size_limit() -> None:
    """MAX_CFP_UNITS units with the longest values each field allows still encode under the limit."""
    long_url = "http://" + "h" * 2000
    big = job(
        job_id="j" * 128,
        scene_url=long_url,
        scene_hash="f" * 128,
        width=65536,
        height=65536,
        ranges={f"v{i:02d}{'x' * 28}": (-1.2345678901234567e11, 1.2345678901234567e11) for i in range(16)},
    )
    units = tuple(
        WorkUnit(index=10**7 - i, rect=Rect(65535, 65535, 1, 1), C=1.2345678901234567e11,
                 S=1, Nd=1.2345678901234567e11, cost=1.2345678901234567e11)
        for i in range(m.MAX_CFP_UNITS)
    )  # fmt: skip
    cfp = m.CallForProposal(conversation="c" * 128, job=big, units=units, reply_within_s=3599.999999)
    performative, body = m.encode(cfp)
    assert len(body.encode()) < m.MAX_BODY_BYTES
    assert m.parse(performative, body) == cfp


def test_encode_refuses_what_parse_would_refuse() -> None:
    with pytest.raises(MessageError) as info:
        m.encode(m.Refuse(conversation="c1", job_id="job-1", reason="x" * 5000))
    assert info.value.field == "reason"
    with pytest.raises(MessageError):
        m.encode(m.Propose(conversation="c1", job_id="job-1", estimates=()))


def test_metadata_must_match_the_body() -> None:
    msg = ONE_OF_EACH[2]
    _, body = m.encode(msg)
    meta = m.metadata(msg)
    with pytest.raises(MessageError) as info:
        m.parse_with_metadata({**meta, "conversation": "forged"}, body)
    assert info.value.field == "conversation"
    with pytest.raises(MessageError) as info:
        m.parse_with_metadata({**meta, "ontology": "other"}, body)
    assert info.value.field == "ontology"
    with pytest.raises(MessageError):
        m.parse_with_metadata({**meta, "performative": "inform"}, body)


# --- fuzzing: nothing but MessageError ever comes out of parse ---------------------------------------------

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=40),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=12), inner, max_size=6),
    max_leaves=30,
)


def mutated(draw_msg: m.Message, path_value: tuple[list[str], object]) -> dict:
    data = body_of(draw_msg)
    keys, value = path_value
    node = data
    for key in keys[:-1]:
        node = node.get(key) if isinstance(node, dict) and isinstance(node.get(key), dict) else node
    if isinstance(node, dict) and keys:
        node[keys[-1]] = value
    return data


field_names = st.sampled_from(
    ["v", "conversation", "job", "units", "index", "rect", "token", "seconds", "estimates", "busy", "ranges",
     "width", "level", "spp", "reason", "unit", "job_id", "C", "x"]
)  # fmt: skip
performatives = st.sampled_from([*m.KINDS, "bogus"])


def _parse_or_refuse(performative: str, body: str | bytes) -> None:
    with contextlib.suppress(MessageError):
        m.parse(performative, body)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(performatives, st.binary(max_size=300) | st.text(max_size=300))
def test_fuzz_random_bytes_and_text(performative: str, body: str | bytes) -> None:
    _parse_or_refuse(performative, body)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(performatives, json_values)
def test_fuzz_random_json(performative: str, value: object) -> None:
    _parse_or_refuse(performative, json.dumps(value))
    if isinstance(value, dict):
        _parse_or_refuse(performative, json.dumps({"v": m.PROTOCOL_VERSION, **value}))


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(ONE_OF_EACH), st.lists(field_names, min_size=1, max_size=3), json_values)
def test_fuzz_valid_messages_with_one_field_mutated(msg: m.Message, keys: list[str], value: object) -> None:
    data = mutated(msg, (keys, value))
    _parse_or_refuse(msg.performative, json.dumps(data))


@pytest.mark.parametrize("name", ["scène d'été.xml", "file names/a b.xml", "日本/シーン.xml", "a+b_c-1.xml"])
def test_a_users_scene_file_name_travels(name: str) -> None:
    """Spaces, apostrophes and any script: names users give their files (a job with 'scène one.xml' had
    been accepted at submit and failed at its auction, its message refused)."""
    m.check_scene_name(name)
    cfp = m.CallForProposal(conversation="c1", job=job(scene_name=name), units=(unit(0),), reply_within_s=2)
    assert m.parse(*m.encode(cfp)).job.scene_name == name


@pytest.mark.parametrize("name", ["../x.xml", "a/../../x.xml", "/abs.xml", "a\\b.xml", "a\nb.xml", "a\x00b.xml", ""])
def test_a_scene_name_leaving_the_bundle_is_refused(name: str) -> None:
    with pytest.raises(MessageError, match="cannot travel to the agents") as info:
        m.check_scene_name(name)
    assert info.value.field == "job.scene_name"
    with pytest.raises(MessageError):
        m.encode(m.CallForProposal(conversation="c1", job=job(scene_name=name), units=(unit(0),), reply_within_s=2))


def test_a_rounds_awards_pack_into_one_message_that_gives_them_back() -> None:
    """Awards of one job travel as one Awards message (the job's description once), which the agent reads
    as the awards themselves, in order; a lone award travels as itself."""
    awards = [dataclasses.replace(ONE_AWARD, conversation=f"a{i}", unit=unit(i, Rect(32 * i, 0, 32, 32)),
                                  token=f"{i:032x}", seed=i, estimate_s=float(i)) for i in range(4)]
    (packed,) = m.packed(awards)
    assert isinstance(packed, m.Awards) and packed.conversation == "a0"
    performative, body = m.encode(packed)
    assert performative == "accept-proposals" and len(body) < 0.6 * sum(len(m.encode(a)[1]) for a in awards)
    assert m.parse(performative, body).each() == tuple(awards)
    assert m.packed(awards[:1]) == awards[:1]


def test_awards_beyond_the_body_limit_pack_into_several_messages() -> None:
    url = "http://127.0.0.1:8765/" + "u" * 2000  # the longest upload URL a message allows
    awards = [dataclasses.replace(ONE_AWARD, conversation=f"a{i}", unit=unit(i), token=f"{i:032x}", upload_url=url)
              for i in range(m.MAX_CFP_UNITS)]
    packed = m.packed(awards)
    assert len(packed) > 1 and all(len(m.encode(p)[1].encode()) <= m.MAX_BODY_BYTES for p in packed)
    assert [a for p in packed for a in (p.each() if isinstance(p, m.Awards) else (p,))] == awards


@pytest.mark.parametrize("change, field", [
    (lambda d: d.update(conversation="other"), "conversation"),
    (lambda d: d["awards"][1].update(unit=d["awards"][0]["unit"]), "awards"),
    (lambda d: d.update(awards=d["awards"][:1]), "awards"),
    (lambda d: d["awards"][0].update(token="xyz"), "awards[0].token"),
])
def test_bad_awards_are_refused_by_name(change, field: str) -> None:
    data = body_of(m.packed([ONE_AWARD, dataclasses.replace(ONE_AWARD, conversation="c3", unit=unit(1))])[0])
    change(data)
    assert refused("accept-proposals", data).field == field
