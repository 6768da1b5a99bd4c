"""The farm's logs: a sentence a line, or one JSON object a line with the record's fields (core.logs), and
the master's records as the sentences its log prints."""

from __future__ import annotations

import io
import json
import logging

import pytest

from core.logs import configure, fields
from master import auction as au


@pytest.fixture
def root_restored():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for h in list(root.handlers):
        root.removeHandler(h)
    for h in handlers:
        root.addHandler(h)
    root.setLevel(level)


def _log(record: au.Record, fmt: str) -> str:
    stream = io.StringIO()
    configure("info", fmt, role="master", stream=stream)
    logging.getLogger("master.service").log(record.level, "%s", record.sentence(), extra=fields(**record.fields()))
    return stream.getvalue()


DONE = au.UnitDone("ab12", 4, "agent-1@localhost", "f" * 32, seconds=2.34, estimate=2.0, tile_path="/t.exr",
                   tile_hash="cd" * 32, report={"depth": 6, "spp": 64, "band": 2, "nonfinite": 0}, credits=3,
                   on_time=False, stimulus_id="tile-ab12-4-cdcdcdcd")


def test_a_record_logs_as_a_sentence_in_text(root_restored) -> None:
    line = _log(DONE, "text")
    assert "master INFO master.service: unit 4 of job ab12: done by agent-1@localhost in 2.34 s (estimate " \
           "2.00 s; spp 64, depth 6, band 2)" in line
    assert "f" * 32 not in line and line.count("\n") == 1


def test_a_record_logs_as_one_json_object_with_its_fields_and_no_token(root_restored) -> None:
    out = json.loads(_log(DONE, "json"))
    assert out["message"].startswith("unit 4 of job ab12: done by agent-1@localhost")
    assert (out["record"], out["job_id"], out["index"], out["stimulus_id"], out["role"], out["level"]) == \
        ("UnitDone", "ab12", 4, "tile-ab12-4-cdcdcdcd", "master", "info")
    assert "token" not in out and "f" * 32 not in json.dumps(out)


@pytest.mark.parametrize("record", [
    au.UnitAwarded("j", 1, "a", "t" * 32, 1.5, 2, 40.0), au.UnitFailed("j", 1, "a", "t", "failed on a: boom", -1),
    au.UnitRequeued("j", 1, "a", "t", "agent a lost"), au.JobDone("j"), au.JobFailed("j", "why"),
    au.JobCancelled("j", "cancelled by the user"), au.AgentJoined("a", 2.0), au.AgentLost("a", "no heartbeat"),
    au.AgentBack("a"), au.AgentSilent("a", 4.0), au.AgentForgotten("a"), au.AgentBlocklisted("j", "a", "3 failed"),
    au.BidRefused("j", "a", "busy"), au.MessageIgnored("a", "wrong token", "j", 1), au.MessageIgnored(None, "x"),
    au.JobsPaused("disk full on the master", 10), au.JobsResumed("space on the master again", 1 << 30)])
def test_every_record_reads_as_a_sentence_without_its_token(record: au.Record) -> None:
    sentence = record.sentence()
    assert sentence and "\n" not in sentence and "t" * 32 not in sentence and "Record(" not in sentence
    assert "token" not in record.fields()


def test_an_unknown_format_is_refused_naming_the_option() -> None:
    with pytest.raises(ValueError, match="--log-format 'xml'"):
        configure("info", "xml")
