"""The farm's control-message schema: versioned JSON bodies of FIPA-ACL-style messages, validated on receipt.

Every message travels as (metadata, body) over XMPP. The metadata carries the performative, the ontology
(`quekaro-render`), the protocol (`fipa-contract-net`) and the conversation id; the body is a JSON object
with the protocol version `v`, the conversation id again (so the two can be checked against each other)
and the fields of one message kind. `encode` and `parse` are the only ways in and out: both validate
every field (types, ranges, finite numbers, lengths), so a peer never acts on a malformed message.

Unknown fields are refused rather than ignored: the version number is the one place where peers agree
on what a body may hold, and silently dropping fields would hide a version mismatch.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Union

from core.errors import MessageError, TileError
from core.model.fields import constrained
from core.model.geometry import DEFAULT_FILTER_RADIUS, Rect, filter_reach
from core.model.job import RFILTERS, VARIANT_PATTERN
from core.model.levels import LEVELS, OFF
from core.model.units import SPP_MAX, WorkUnit
from fuzzy.engine import DEFUZZIFIERS

# 2: several awards a round, slots in Register; 3: the rules an agent plans with, in Register; 4: a round's
# awards of one job to one agent in one message (Awards), and no inform from agents (the upload answers);
# 5: progressive jobs (JobInfo.passes: a unit is a pass, at its spp, its tile carrying the film's weights);
# 6: a pass of a progressive job at a rule level carries its unit's depth (WorkUnit.depth); 7: a job's
# threads per agent (JobInfo.threads, `submit -t`) and an agent's host (Register.host); 8: a progressive
# job's passes that spill (JobInfo.spill)
PROTOCOL_VERSION = 8
ONTOLOGY = "quekaro-render"
PROTOCOL = "fipa-contract-net"
# Prosody drops a sender whose stanza exceeds 256 KiB (docs/design.md section 4): stay well below it.
MAX_BODY_BYTES = 64 * 1024
# A CFP lists at most this many units; with the field limits below it stays under MAX_BODY_BYTES.
MAX_CFP_UNITS = 64

_ID = re.compile(r"[A-Za-z0-9._:@/+-]{1,128}")
_HEX = re.compile(r"[0-9a-f]{16,128}")
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,31}")
# A relative path inside a scene bundle: no leading '/', no '..' component, no control character or
# backslash; spaces and any script are a user's file names (as the bundle's own member check allows).
_SCENE_NAME = re.compile(r"(?!/)(?!.*(^|/)\.\.(/|$))[^\x00-\x1f\x7f\\]{1,512}")


def check_scene_name(name: str) -> None:
    """MessageError unless `name` can travel as a job's scene_name (checked at submit, not at the auction)."""
    if not _SCENE_NAME.fullmatch(name):
        raise MessageError(f"scene file name {name[:80]!r} cannot travel to the agents: a relative path inside "
                           "the bundle without '..', control characters or backslashes", "job.scene_name")


# --- message parts -------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class JobInfo:
    """What an agent needs to render any unit of a job: where the scene is and what the user asked for."""

    job_id: str = constrained(pattern=_ID)
    scene_url: str = constrained(max_len=2048, pattern=re.compile(r"https?://[\x21-\x7e]+"))
    scene_hash: str = constrained(pattern=_HEX)
    width: int = constrained(lo=1, hi=65536)
    height: int = constrained(lo=1, hi=65536)
    spp: int = constrained(lo=1, hi=SPP_MAX)
    depth: int = constrained(lo=-1, hi=1024)  # Mitsuba's max_depth: -1 means unbounded
    level: str = constrained(choices=LEVELS)
    # Observed (lo, hi) of the dynamic input variables (C, S, Nd) over the whole scene.
    ranges: dict[str, tuple[float, float]] = constrained(max_items=16, key_pattern=_NAME, lo=-1e12, hi=1e12)  # noqa: RUF009
    # How to render, as the master's effect analysis decided: the scene file inside the bundle, its -D
    # parameters, the Mitsuba variant and the integrator. Each agent picks depth/spp/band with its rules.
    scene_name: str = constrained(max_len=512, pattern=_SCENE_NAME, default="scene.xml")
    defines: dict[str, str] = constrained(max_items=64, key_pattern=_NAME, max_len=1024, default_factory=dict)  # noqa: RUF009
    variant: str = constrained(pattern=VARIANT_PATTERN, default="llvm_ad_rgb")
    # None: the scene's own integrator, as written; a plugin type: the user's override.
    integrator: str | None = constrained(pattern=re.compile(r"[a-z][a-z0-9_]{0,31}"), default=None)
    sensor: int = constrained(lo=0, hi=1024, default=0)  # which of the scene's sensors renders
    # The job's own rule file, inside the bundle (its sha256); None: each agent's default rules.
    rules_sha256: str | None = constrained(pattern=_HEX, default=None)
    defuzzifier: str | None = constrained(choices=DEFUZZIFIERS, default=None)  # None: each agent's own
    # No unit's band below this: the film filter's reach, the band pixels the master's composition cuts
    # (core.model.geometry.filter_reach); a master that does not send it composes with Mitsuba's default.
    min_band: int = constrained(lo=0, hi=64, default=filter_reach(DEFAULT_FILTER_RADIUS))
    # Adaptive jobs: the first pass's samples per pixel in every unit, whose own mean spp the plan set
    # (WorkUnit.spp); the agent renders each unit in two passes (core.render.adaptive), not by its rules.
    first_spp: int | None = constrained(lo=1, hi=SPP_MAX, default=None)
    # The reconstruction filter that replaces the scene's (a denoised job's box); None: the scene's own.
    rfilter: str | None = constrained(choices=RFILTERS, default=None)
    # Progressive jobs: each unit is one pass of a unit of the image (master.auction.passes), rendered at
    # its own spp, its unit's depth (at a rule level) or the job's, and min_band, its tile carrying the
    # film's weights (core.image.passes). No agent's rules choose: the master's plan did.
    passes: bool = False
    # A progressive job's passes draw their samples on their unit alone, the band holding the spill
    # (JobPlan.spill, core.render.per_pixel.render_core); each renders in a call of its own.
    spill: bool = False
    # Dr.Jit threads each agent renders the job on (`submit -t`), at most its own --threads; None: its own.
    threads: int | None = constrained(lo=1, hi=4096, default=None)

    def check(self) -> None:
        for name, (lo, hi) in self.ranges.items():
            if lo > hi:
                raise MessageError(f"range lower bound {lo} above upper bound {hi}", f"ranges.{name}")

    def check_unit(self, unit: WorkUnit, field: str) -> None:
        """An adaptive job's units carry their mean spp, at least the first pass's; a progressive job's their
        pass's, and at a rule level their depth; other jobs' neither."""
        if self.passes:
            if unit.spp is None:
                raise MessageError(f"unit {unit.index} of a progressive job has no spp (its pass's)", field)
            if (unit.depth is None) != (self.level == OFF):
                raise MessageError(f"unit {unit.index} of a progressive job at level {self.level} has depth "
                                   f"{unit.depth} (a pass carries its unit's depth at a rule level only)", field)
            return
        if unit.depth is not None:
            raise MessageError(f"unit {unit.index} has depth {unit.depth} in a job that is not in passes", field)
        if self.first_spp is None and unit.spp is not None:
            raise MessageError(f"unit {unit.index} has spp {unit.spp} in a job whose rules choose it", field)
        if self.first_spp is not None and (unit.spp is None or unit.spp < self.first_spp):
            raise MessageError(f"unit {unit.index} of an adaptive job needs spp >= first_spp {self.first_spp}, "
                               f"has {unit.spp}", field)


# --- messages ------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class Message:
    """Base of every message kind: the conversation id and the FIPA performative it travels under."""

    performative: ClassVar[str] = ""
    conversation: str = constrained(pattern=_ID)

    def check(self) -> None:
        """Cross-field checks beyond each field's own constraints."""


@dataclass(frozen=True, kw_only=True)
class CallForProposal(Message):
    """Master -> agent: units of one job up for auction; answer (Propose or Refuse) within reply_within_s."""

    performative: ClassVar[str] = "cfp"
    job: JobInfo
    units: tuple[WorkUnit, ...] = constrained(max_items=MAX_CFP_UNITS, min_items=1)
    # Relative, not absolute: the hosts' clocks need not agree.
    reply_within_s: float = constrained(lo=0.001, hi=3600.0)

    def check(self) -> None:
        self.job.check()
        image = Rect(0, 0, self.job.width, self.job.height)
        seen: set[int] = set()
        for unit in self.units:
            if unit.index in seen:
                raise MessageError(f"unit {unit.index} listed twice", "units")
            seen.add(unit.index)
            if unit.rect.area == 0 or unit.rect.intersect(image) != unit.rect:
                raise MessageError(f"unit {unit.index} rectangle {unit.rect} outside the image", "units.rect")
            self.job.check_unit(unit, "units.spp")


@dataclass(frozen=True, kw_only=True)
class Estimate:
    """An agent's bid on one unit: the seconds it expects to take."""

    index: int = constrained(lo=0, hi=10**7)
    seconds: float = constrained(lo=0.0, hi=1e9)


@dataclass(frozen=True, kw_only=True)
class Propose(Message):
    """Agent -> master: estimates for the announced units it is willing to render (its speed x their cost)."""

    performative: ClassVar[str] = "propose"
    job_id: str = constrained(pattern=_ID)
    estimates: tuple[Estimate, ...] = constrained(max_items=MAX_CFP_UNITS, min_items=1)

    def check(self) -> None:
        if len({e.index for e in self.estimates}) != len(self.estimates):
            raise MessageError("unit estimated twice", "estimates")


@dataclass(frozen=True, kw_only=True)
class Refuse(Message):
    """Agent -> master: declines a call for proposals (busy, cannot fetch the scene, ...)."""

    performative: ClassVar[str] = "refuse"
    job_id: str = constrained(pattern=_ID)
    reason: str = constrained(max_len=1024)


@dataclass(frozen=True, kw_only=True)
class Award(Message):
    """Master -> agent (accept-proposal): render this unit; upload the tile with the token; seed fixed."""

    performative: ClassVar[str] = "accept-proposal"
    job: JobInfo
    unit: WorkUnit
    token: str = constrained(pattern=_HEX)
    upload_url: str = constrained(max_len=2048, pattern=re.compile(r"https?://[\x21-\x7e]+"))
    seed: int = constrained(lo=0, hi=2**31 - 1)
    estimate_s: float = constrained(lo=0.0, hi=1e9)

    def check(self) -> None:
        self.job.check()
        self.job.check_unit(self.unit, "unit.spp")


@dataclass(frozen=True, kw_only=True)
class AwardedUnit:
    """One award of an `Awards`: an `Award`'s fields but its job."""

    conversation: str = constrained(pattern=_ID)
    unit: WorkUnit
    token: str = constrained(pattern=_HEX)
    upload_url: str = constrained(max_len=2048, pattern=re.compile(r"https?://[\x21-\x7e]+"))
    seed: int = constrained(lo=0, hi=2**31 - 1)
    estimate_s: float = constrained(lo=0.0, hi=1e9)


@dataclass(frozen=True, kw_only=True)
class Awards(Message):
    """Master -> agent (accept-proposals): awards of one job sent together, each an `Award` (`each`).

    Why: a round awards an agent several units of a job at once; one message carries the job's
    description once and crosses the XMPP server once. Its conversation is its first award's."""

    performative: ClassVar[str] = "accept-proposals"
    job: JobInfo
    awards: tuple[AwardedUnit, ...] = constrained(max_items=MAX_CFP_UNITS, min_items=2)

    def check(self) -> None:
        self.job.check()
        if self.conversation != self.awards[0].conversation:
            raise MessageError("the message's conversation is not its first award's", "conversation")
        if len({a.unit.index for a in self.awards}) != len(self.awards):
            raise MessageError("a unit awarded twice in one message", "awards")
        for award in self.awards:
            self.job.check_unit(award.unit, "awards.unit.spp")

    def each(self) -> tuple[Award, ...]:
        return tuple(Award(job=self.job, **{f.name: getattr(a, f.name) for f in dataclasses.fields(a)})
                     for a in self.awards)


def packed(awards: Sequence[Award]) -> list[Award | Awards]:
    """Awards of one job to one agent as few messages as the body's limit allows, in their order: runs of
    two or more as `Awards`, a lone one as itself. A run is encoded once to check its size (split in halves
    only where it does not fit), since the sender encodes each message again."""
    out: list[Award | Awards] = []
    for start in range(0, len(awards), MAX_CFP_UNITS):
        out += _fitting(awards[start:start + MAX_CFP_UNITS])
    return out


def _fitting(run: Sequence[Award]) -> list[Award | Awards]:
    pack = _together(run)
    if len(run) == 1 or _fits(pack):
        return [pack]
    half = len(run) // 2
    return _fitting(run[:half]) + _fitting(run[half:])


def _together(run: Sequence[Award]) -> Award | Awards:
    if len(run) == 1:
        return run[0]
    items = tuple(AwardedUnit(conversation=a.conversation, unit=a.unit, token=a.token, upload_url=a.upload_url,
                              seed=a.seed, estimate_s=a.estimate_s) for a in run)
    return Awards(conversation=run[0].conversation, job=run[0].job, awards=items)


def _fits(msg: Message) -> bool:
    try:
        encode(msg)
    except MessageError:
        return False
    return True


@dataclass(frozen=True, kw_only=True)
class Reject(Message):
    """Master -> agent (reject-proposal): the units it bid on went elsewhere."""

    performative: ClassVar[str] = "reject-proposal"
    job_id: str = constrained(pattern=_ID)
    reason: str = constrained(max_len=1024)


@dataclass(frozen=True, kw_only=True)
class Inform(Message):
    """A unit rendered and its tile uploaded, with the parameters it was rendered with. The master makes one
    from each tile it takes (its header holds these); agents send none since protocol 4, and one from the
    wire counts for nothing (a unit is done only by its tile's upload)."""

    performative: ClassVar[str] = "inform"
    job_id: str = constrained(pattern=_ID)
    index: int = constrained(lo=0, hi=10**7)
    token: str = constrained(pattern=_HEX)
    tile_hash: str = constrained(pattern=_HEX)
    depth: int = constrained(lo=-1, hi=1024)
    # As rendered: a sampler rounds the count it is given up (orthogonal to the next prime squared,
    # 1031^2 for SPP_MAX), so a unit at the limit renders a little more.
    spp: int = constrained(lo=1, hi=2 * SPP_MAX)
    band: int = constrained(lo=0, hi=65536)
    seconds: float = constrained(lo=0.0, hi=1e9)
    nonfinite: int = constrained(lo=0, hi=1 << 32)  # pixels that were NaN/inf before clamping


@dataclass(frozen=True, kw_only=True)
class TileFigures:
    """What a tile's header says its unit was rendered with (core.image.tiles writes it, the agent uploads it):
    the master reads it back as the unit's result and holds it to an inform's bounds (`check`)."""

    depth: int = constrained(lo=-1, hi=1024)
    spp: int = constrained(lo=1, hi=2 * SPP_MAX)  # as rendered, like Inform.spp
    band: int = constrained(lo=0, hi=65536)
    seconds: float = constrained(lo=0.0, hi=1e9)
    nonfinite: int = constrained(lo=0, hi=1 << 32)
    first_spp: int | None = constrained(lo=1, hi=SPP_MAX, default=None)  # an adaptive job's first pass

    @classmethod
    def from_header(cls, meta: dict[str, Any]) -> TileFigures:
        """The figures a tile's header states (core.image.tiles writes them); TileError naming the field
        that is missing or not a number. Their bounds are `check`ed by the master's auction."""
        if meta.get("spp") is None:
            raise TileError("tile header lacks its spp")

        def read(name: str, kind: type, default: Any) -> Any:
            value = meta.get(name)
            if value is None:
                return default
            try:
                return kind(value)
            except (TypeError, ValueError):
                what = "sample count" if "spp" in name else "number"
                raise TileError(f"tile header's {name} {value!r} is not a {what}") from None

        return cls(depth=read("depth", int, -1), spp=read("spp", int, None), band=read("band", int, 0),
                   seconds=read("seconds", float, 0.0), nonfinite=read("nonfinite", int, 0),
                   first_spp=read("first_spp", int, None))


@dataclass(frozen=True, kw_only=True)
class Failure(Message):
    """Agent -> master: the awarded unit could not be rendered."""

    performative: ClassVar[str] = "failure"
    job_id: str = constrained(pattern=_ID)
    index: int = constrained(lo=0, hi=10**7)
    token: str = constrained(pattern=_HEX)
    reason: str = constrained(max_len=1024)


@dataclass(frozen=True, kw_only=True)
class Register(Message):
    """Agent -> master: here I am, with my measured speed (reference-cost seconds per second)."""

    performative: ClassVar[str] = "register"
    speed: float = constrained(lo=1e-6, hi=1e6)
    threads: int = constrained(lo=1, hi=4096)
    rules: str = constrained(max_len=256)
    # The machine it runs on (its host name), for the user's eyes: the page's and `quekaro agents`' rows.
    host: str | None = constrained(max_len=253, pattern=re.compile(r"[A-Za-z0-9._-]{1,253}"), default=None)
    # Units it holds at once (its --slots): the master awards it no more. None: not told (the master's own).
    slots: int | None = constrained(lo=1, hi=MAX_CFP_UNITS, default=None)
    # What it plans with: the digest of what its rules compute (fuzzy.rulebase.RuleBase.digest, a sha256;
    # for a job without rules of its own) and its --defuzzifier
    # (for a job that names none; None: the file's dialect decides). The master measures depth floors
    # at every rule level unless every live agent plans as it does (Auction.plan_alike).
    rules_sha256: str | None = constrained(pattern=_HEX, default=None)
    defuzzifier: str | None = constrained(choices=DEFUZZIFIERS, default=None)


@dataclass(frozen=True, kw_only=True)
class Welcome(Message):
    """Master -> agent: its Register (this conversation) arrived. Until one comes on its current connection,
    the agent sends Register again with each heartbeat: the server drops messages to a JID that is offline,
    as the master is while it too reconnects after a server restart."""

    performative: ClassVar[str] = "welcome"


@dataclass(frozen=True, kw_only=True)
class Introduce(Message):
    """Master -> agent: a heartbeat came from an agent this master holds no Register of (the master
    restarted while the agent stayed connected, or the Register was lost): send one, so that the master
    learns its speed. Sent with each such heartbeat until a Register arrives."""

    performative: ClassVar[str] = "introduce"


@dataclass(frozen=True, kw_only=True)
class HeldUnit:
    """A unit an agent holds: awarded to it and not yet answered with Inform or Failure."""

    job_id: str = constrained(pattern=_ID)
    index: int = constrained(lo=0, hi=10**7)


@dataclass(frozen=True, kw_only=True)
class Heartbeat(Message):
    """Agent -> master, periodically: still alive, and the units it holds."""

    performative: ClassVar[str] = "heartbeat"
    busy: tuple[HeldUnit, ...] = constrained(max_items=256)


@dataclass(frozen=True, kw_only=True)
class Cancel(Message):
    """Master -> agent: stop this unit (index given) or every unit of this job (index None)."""

    performative: ClassVar[str] = "cancel"
    job_id: str = constrained(pattern=_ID)
    index: int | None = constrained(lo=0, hi=10**7, default=None)
    reason: str = constrained(max_len=1024)


KINDS: dict[str, type[Message]] = {
    cls.performative: cls
    for cls in (CallForProposal, Propose, Refuse, Award, Awards, Reject, Inform, Failure, Register, Welcome,
                Introduce, Heartbeat, Cancel)
}


# --- encoding ------------------------------------------------------------------------------------------


def encode(msg: Message) -> tuple[str, str]:
    """The (performative, JSON body) of a message, validated and size-checked as the receiver will."""
    if type(msg) not in KINDS.values():
        raise MessageError(f"not a message kind: {type(msg).__name__}")
    wire = _to_json(msg)
    body = json.dumps({"v": PROTOCOL_VERSION, **wire}, separators=(",", ":"), allow_nan=False, ensure_ascii=False)
    _check_size(body)
    _check_value(type(msg), wire, "")  # the sender is held to the same rules as any receiver (`check`)
    return msg.performative, body


def check(msg: Message) -> None:
    """MessageError where a message built here (not parsed) breaks the rules any receiver holds it to."""
    _check_value(type(msg), _to_json(msg), "")


def check_job(job: JobInfo) -> None:
    """MessageError where a job's description breaks the rules every message holds it to (field `job...`)."""
    _check_value(JobInfo, _to_json(job), "job").check()


def metadata(msg: Message) -> dict[str, str]:
    """The XMPP metadata a message travels under."""
    return {
        "performative": msg.performative,
        "ontology": ONTOLOGY,
        "protocol": PROTOCOL,
        "conversation": msg.conversation,
    }


def parse(performative: str, body: str | bytes) -> Message:
    """Validate a received body as the kind its performative names; MessageError if anything is off."""
    cls = KINDS.get(performative) if isinstance(performative, str) else None
    if cls is None:
        raise MessageError(f"unknown performative {str(performative)[:40]!r}", "performative")
    if isinstance(body, bytes):
        _check_size(body)
        try:
            body = body.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise MessageError("body is not UTF-8", "body") from exc
    if not isinstance(body, str):
        raise MessageError("body is not text", "body")
    _check_size(body)
    try:
        data = json.loads(body, parse_constant=_refuse_constant)
    except (ValueError, RecursionError) as exc:
        raise MessageError(f"body is not valid JSON: {str(exc)[:120]}", "body") from exc
    if not isinstance(data, dict):
        raise MessageError("body is not a JSON object", "body")
    version = data.pop("v", None)
    if type(version) is not int:
        raise MessageError("protocol version missing or not an integer", "v")
    if version != PROTOCOL_VERSION:
        raise MessageError(f"protocol version {version} not supported (this side: {PROTOCOL_VERSION})", "v")
    return _check_value(cls, data, "")


def parse_with_metadata(meta: dict[str, str], body: str | bytes) -> Message:
    """Parse a body and check the metadata it came with: ontology, protocol and matching conversation id."""
    if meta.get("ontology") != ONTOLOGY:
        raise MessageError(f"ontology {str(meta.get('ontology'))[:40]!r} is not {ONTOLOGY!r}", "ontology")
    if meta.get("protocol") != PROTOCOL:
        raise MessageError(f"protocol {str(meta.get('protocol'))[:40]!r} is not {PROTOCOL!r}", "protocol")
    msg = parse(meta.get("performative", ""), body)
    if meta.get("conversation") != msg.conversation:
        raise MessageError("conversation id in the metadata differs from the body's", "conversation")
    return msg


def _check_size(body: str | bytes) -> None:
    # len() of a str counts characters, each at least one byte: a cheap bound before encoding it.
    if len(body) > MAX_BODY_BYTES:
        raise MessageError(f"body of {len(body)}+ bytes exceeds the limit of {MAX_BODY_BYTES}", "body")
    if isinstance(body, str):
        try:
            size = len(body.encode("utf-8"))
        except UnicodeEncodeError as exc:
            raise MessageError("body holds characters that are not valid Unicode", "body") from exc
        if size > MAX_BODY_BYTES:
            raise MessageError(f"body of {size} bytes exceeds the limit of {MAX_BODY_BYTES}", "body")
    if len(body) == 0:
        raise MessageError("empty body", "body")


def _refuse_constant(name: str) -> None:
    raise MessageError(f"non-finite number {name} in body", "body")


def _to_json(value: Any) -> Any:
    if isinstance(value, Rect):
        return value.as_list()
    if dataclasses.is_dataclass(value):
        return {f.name: _to_json(getattr(value, f.name)) for f in _wire_fields(value)}
    if isinstance(value, tuple | list):
        return [_to_json(v) for v in value]
    if isinstance(value, dict):
        return {k: _to_json(v) for k, v in value.items()}
    return value


# --- validation: JSON value -> typed value, driven by the dataclasses' type hints --------------------------

_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _check_value(cls: type, data: Any, where: str) -> Any:
    """Build a dataclass instance from a JSON object, checking every field; `where` names the path so far."""
    if not isinstance(data, dict):
        raise MessageError("expected a JSON object", where or "body")
    hints = _hints(cls)
    names = [f.name for f in _wire_fields(cls)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise MessageError(f"unknown field {unknown[0][:40]!r}", _join(where, unknown[0][:40]))
    values = {}
    for f in _wire_fields(cls):
        path = _join(where, f.name)
        if f.name not in data:
            if f.default is dataclasses.MISSING:
                raise MessageError("required field missing", path)
            values[f.name] = f.default
            continue
        values[f.name] = _convert(hints[f.name], data[f.name], dict(f.metadata), path)
    try:
        obj = cls(**values)
    except MessageError as exc:  # a type's own checks (e.g. a unit's S against its rectangle)
        raise MessageError(exc.reason, exc.field or where or "body") from exc
    if hasattr(obj, "check"):
        obj.check()
    return obj


def _wire_fields(cls: Any) -> list[dataclasses.Field]:
    """The fields that travel: a field marked `wire=False` (e.g. a unit's neighbours) stays at home and
    takes its default on the receiving side."""
    return [f for f in dataclasses.fields(cls) if f.metadata.get("wire", True)]


def _join(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def _convert(hint: Any, value: Any, meta: dict[str, Any], path: str) -> Any:
    origin = typing.get_origin(hint)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in typing.get_args(hint):
            return None
        (inner,) = [a for a in typing.get_args(hint) if a is not type(None)]
        return _convert(inner, value, meta, path)
    if hint is Rect:
        return _rect(value, path)
    if dataclasses.is_dataclass(hint):
        return _check_value(hint, value, path)
    if origin is tuple:
        return _tuple(hint, value, meta, path)
    if origin is dict:
        return _mapping(hint, value, meta, path)
    return _scalar(hint, value, meta, path)


def _tuple(hint: Any, value: Any, meta: dict[str, Any], path: str) -> tuple:
    if not isinstance(value, list):
        raise MessageError("expected a JSON array", path)
    args = typing.get_args(hint)
    if len(args) == 2 and args[1] is Ellipsis:
        if len(value) > meta.get("max_items", 1 << 16) or len(value) < meta.get("min_items", 0):
            raise MessageError(f"array of {len(value)} items outside the allowed count", path)
        inner = {k: v for k, v in meta.items() if k not in ("max_items", "min_items")}
        return tuple(_convert(args[0], v, inner, f"{path}[{i}]") for i, v in enumerate(value))
    if len(value) != len(args):
        raise MessageError(f"expected {len(args)} items, got {len(value)}", path)
    pairs = enumerate(zip(args, value, strict=True))
    return tuple(_convert(a, v, meta, f"{path}[{i}]") for i, (a, v) in pairs)


def _mapping(hint: Any, value: Any, meta: dict[str, Any], path: str) -> dict:
    if not isinstance(value, dict):
        raise MessageError("expected a JSON object", path)
    if len(value) > meta.get("max_items", 1 << 16):
        raise MessageError(f"object of {len(value)} entries exceeds the allowed count", path)
    _, inner_hint = typing.get_args(hint)
    inner = {k: v for k, v in meta.items() if k not in ("max_items", "key_pattern")}
    out = {}
    for key, item in value.items():
        if not meta.get("key_pattern", _NAME).fullmatch(key):
            raise MessageError(f"key {key[:40]!r} is not a valid name", path)
        out[key] = _convert(inner_hint, item, inner, f"{path}.{key}")
    return out


def _rect(value: Any, path: str) -> Rect:
    if not isinstance(value, list) or len(value) != 4 or any(type(v) is not int for v in value):
        raise MessageError("expected a rectangle [x, y, w, h] of integers", path)
    if any(v < 0 or v > 65536 for v in value):
        raise MessageError(f"rectangle {value} has a coordinate outside 0..65536", path)
    return Rect.from_list(value)


def _scalar(hint: Any, value: Any, meta: dict[str, Any], path: str) -> Any:
    if hint is bool:
        if type(value) is not bool:
            raise MessageError("expected true or false", path)
        return value
    if hint is int:
        if type(value) is not int:  # bool is an int subclass: refused here on purpose
            raise MessageError("expected an integer", path)
    elif hint is float:
        if type(value) not in (int, float):
            raise MessageError("expected a number", path)
        if isinstance(value, int) and abs(value) > 1 << 53:
            raise MessageError("number out of range", path)
        value = float(value)
        if not math.isfinite(value):
            raise MessageError("expected a finite number", path)
    elif hint is str:
        if type(value) is not str:
            raise MessageError("expected a string", path)
        if len(value) > meta.get("max_len", 128):
            raise MessageError(f"string of {len(value)} characters is too long", path)
        if "pattern" in meta and not meta["pattern"].fullmatch(value):
            raise MessageError(f"malformed value {value[:40]!r}", path)
        if "choices" in meta and value not in meta["choices"]:
            raise MessageError(f"{value[:40]!r} is not one of {', '.join(meta['choices'])}", path)
        return value
    else:  # pragma: no cover - a schema bug, not a peer's
        raise TypeError(f"unsupported field type {hint!r} at {path}")
    if value < meta.get("lo", -math.inf) or value > meta.get("hi", math.inf):
        raise MessageError(f"{value} outside {meta.get('lo')}..{meta.get('hi')}", path)
    return value
