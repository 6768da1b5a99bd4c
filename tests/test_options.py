"""Job options are a schema: known keys, integer types, finite ranges, refused with the field named, at
the CLI, at the master's API and when a stored job is resumed."""

from __future__ import annotations

import pytest

from core.errors import QuekaroError
from core.model.job import RenderOptions
from planning.jobplan import scene_spp


@pytest.mark.parametrize(("options", "match"), [
    ({"spp": float("inf")}, r"option spp \(--spp inf\): not an integer"),
    ({"spp": 1e400}, r"option spp \(--spp inf\): not an integer"),
    ({"spp": 0}, r"option spp \(--spp 0\): outside 1\.\.1048576"),
    ({"spp": True}, r"option spp \(--spp True\): not an integer"),
    ({"units": "4"}, r"option units \(--units '4'\): not an integer"),
    ({"depth": 0}, r"option depth \(--depth 0\): outside 1\.\.1024 \(or -1 for unbounded\)"),
    ({"colour": "red"}, "option 'colour' is not known"),
    ({"integrator": "raytracer"}, "not one of Mitsuba's integrators"),
    ({"defuzzifier": "mean"}, "option defuzzifier"),
    ({"variant": "cuda; rm -rf"}, "not a Mitsuba variant name"),
    ({"level": "XL"}, "--opt 'XL'"),
])
def test_bad_options_are_refused_naming_the_field(options, match):
    with pytest.raises(QuekaroError, match=match):
        RenderOptions.from_dict(options)


def test_good_options_round_trip():
    options = RenderOptions.from_dict({"level": "S", "spp": 16, "depth": -1, "units": 6, "sensor": 1})
    assert RenderOptions.from_dict(options.to_dict()) == options


def test_a_zero_sample_count_from_a_define_is_refused(tmp_path):
    from core.model.job import SceneSpec

    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><default name="spp" value="8"/><sensor type="perspective">'
                     '<sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>'
                     '</sensor></scene>')
    assert scene_spp(SceneSpec(scene)) == 8
    with pytest.raises(QuekaroError, match="sample_count 0"):
        scene_spp(SceneSpec(scene, {"spp": "0"}))
