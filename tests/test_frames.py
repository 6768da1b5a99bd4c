"""Frame ranges and the job fields of a sequence (core.model.frames, JobSpec): parsed, refused at the edges,
carried through the job's JSON unchanged."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from core.errors import QuekaroError
from core.model.frames import FRAME_MAX, FRAMES_MAX, FrameRange, frame_name
from core.model.job import JobSpec, RenderOptions


def test_a_range_lists_its_frames_with_its_step():
    assert FrameRange.parse("frame", "1:10:3").frames() == [1, 4, 7, 10]
    assert FrameRange.parse("frame", "5:5").frames() == [5]
    assert len(FrameRange.parse("f", "0:9")) == 10


@pytest.mark.parametrize("text", ["1", "1.5:3", "a:b", "1:2:3:4", "-1:3", ""])
def test_a_plain_value_is_not_a_range(text):
    assert FrameRange.parse("frame", text) is None


@pytest.mark.parametrize("text, fault", [("9:1", "FIRST <= LAST"), ("1:5:0", "STEP >= 1"),
                                         (f"0:{FRAME_MAX + 1}", "0..999999"), (f"0:{FRAMES_MAX}", "frames, over")])
def test_a_bad_range_is_refused_naming_it(text, fault):
    with pytest.raises(QuekaroError, match=fault) as err:
        FrameRange.parse("frame", text)
    assert f"-D frame={text}:" in str(err.value)  # the value as the user gave it, not as a range reads it


def test_frame_names_pad_to_four_digits_and_grow_past_them():
    assert frame_name("cbox", 1) == "cbox_0001"
    assert frame_name("cbox", 12345) == "cbox_12345"


@given(first=st.integers(0, 500), count=st.integers(1, 300), step=st.integers(1, 7))
def test_a_range_survives_the_jobs_json(first, count, step):
    spec = JobSpec({"spp": "4"}, RenderOptions(level="S"), name="shot 1",
                   frames=FrameRange("frame", first, first + (count - 1) * step, step))
    assert JobSpec.from_dict(spec.to_dict()) == spec
    assert spec.frames.frames()[-1] == first + (count - 1) * step


def test_each_frame_of_a_range_sets_its_parameter():
    spec = JobSpec({"spp": "4"}, frames=FrameRange("frame", 1, 3))
    frame = spec.frame_job("seq-0123abcd", 2)
    assert (frame.defines, frame.sequence, frame.frame, frame.frames) == ({"spp": "4", "frame": "2"},
                                                                          "seq-0123abcd", 2, None)
    assert JobSpec.from_dict(frame.to_dict()) == frame


def test_a_plain_job_reads_as_before():
    assert JobSpec().to_dict() == {"defines": {}, "options": RenderOptions().to_dict()}


@pytest.mark.parametrize("data, fault", [
    ({"name": "a\nb"}, "--name"), ({"name": "x" * 81}, "--name"), ({"name": 3}, "--name"),
    ({"sequence": "seq-1234567"}, "sequence"), ({"sequence": "job-01234567", "frame": 1}, "sequence"),
    ({"sequence": "seq-01234567"}, "gives both"), ({"frame": 1}, "gives both"),
    ({"sequence": "seq-01234567", "frame": -1}, "frame -1"),
    ({"sequence": "seq-01234567", "frame": True}, "frame True"),
    ({"frames": {"define": "f", "first": 1, "last": 2}}, "frames"),
    ({"frames": {"define": "f", "first": 1, "last": 2, "step": 1}, "defines": {"f": "3"}}, "both"),
    ({"frames": {"define": "f", "first": 1, "last": 2, "step": 1}, "sequence": "seq-01234567", "frame": 1},
     "frames and sequence"),
    ({"tags": []}, "'tags' is not known"),
])
def test_bad_sequence_fields_are_refused_naming_them(data, fault):
    with pytest.raises(QuekaroError, match=fault):
        JobSpec.from_dict(data)
