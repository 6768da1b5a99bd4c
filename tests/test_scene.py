"""Scene specs, -D parsing, XML reading (includes, defaults, referenced files) and loading."""

import shutil
from pathlib import Path

import pytest

from core.errors import SceneError
from core.scene.scene import (
    SceneSpec,
    film_info,
    film_info_from_scene,
    image_size,
    load,
    parse_defines,
    referenced_files,
)

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "tests" / "data" / "scenes"


def test_parse_defines_and_errors():
    assert parse_defines(["spp=16", "res=64", "s=a=b"]) == {"spp": "16", "res": "64", "s": "a=b"}
    for bad, needle in [(["spp"], "NAME=VALUE"), (["=3"], "parameter name"), (["1x=2"], "parameter name"),
                        (["a=1", "a=2"], "twice")]:
        with pytest.raises(SceneError, match=needle):
            parse_defines(bad)


def test_spec_round_trip_and_hash():
    spec = SceneSpec("x.xml", {"spp": 4})
    again = SceneSpec.from_dict(spec.to_dict())
    assert again == spec and hash(again) == hash(spec) and again.defines == {"spp": "4"}
    with pytest.raises(SceneError):
        SceneSpec.from_dict({"defines": {}})


def test_include_defaults_and_overrides(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "film.xml").write_text(
        '<scene version="3.0.0"><default name="w" value="40"/><sensor type="perspective">'
        '<film type="hdrfilm"><integer name="width" value="$w"/><integer name="height" value="$h"/>'
        '<rfilter type="box"/></film></sensor>'
        '<shape type="obj"><string name="filename" value="mesh.obj"/></shape></scene>')
    (tmp_path / "sub" / "mesh.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    main = tmp_path / "main.xml"
    main.write_text('<scene version="3.0.0"><default name="h" value="10"/>'
                    '<include filename="sub/film.xml"/></scene>')
    # Mitsuba 3.9 looks a mesh named in an included file up after parsing, from the main scene's folder,
    # not beside the include (mi.load_file fails the same way: "mesh.obj": file not found).
    with pytest.raises(SceneError, match=r"film.xml:1: file 'mesh.obj' not found; searched: "):
        referenced_files(SceneSpec(main))
    (tmp_path / "mesh.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert image_size(SceneSpec(main)) == (40, 10)
    assert image_size(SceneSpec(main, {"w": "7"})) == (7, 10)
    info = film_info(SceneSpec(main))
    assert (info.filter_type, info.filter_radius) == ("box", 0.5)
    assert referenced_files(SceneSpec(main)) == [tmp_path / "sub" / "film.xml", tmp_path / "mesh.obj"]


def test_missing_reference_and_bad_xml(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene><shape")
    with pytest.raises(SceneError, match=r"bad.xml"):
        image_size(SceneSpec(bad))
    missing = tmp_path / "m.xml"
    missing.write_text('<scene version="3.0.0"><shape type="ply"><string name="filename" value="no.ply"/>'
                       '</shape></scene>')
    with pytest.raises(SceneError, match=r"no.ply"):
        referenced_files(SceneSpec(missing))
    with pytest.raises(SceneError, match="not found"):
        load(SceneSpec(tmp_path / "absent.xml"))


def test_load_errors_name_the_file():
    with pytest.raises(SceneError, match=r"tiny.xml.*unused"):
        load(SceneSpec(DATA / "tiny.xml", {"nonsense": "1"}), "llvm_ad_rgb", threads=1)
    with pytest.raises(SceneError, match=r"tiny.xml"):
        load(SceneSpec(DATA / "tiny.xml", {"width": "abc"}), "llvm_ad_rgb", threads=1)


@pytest.mark.parametrize("name", ["cbox.xml", "glass-corner.xml"])
def test_xml_film_info_matches_mitsuba(name):
    spec = SceneSpec(REPO / "scenes" / name, {"res": "24", "spp": "1"})
    assert film_info(spec) == film_info_from_scene(load(spec, "llvm_ad_rgb", threads=1))
    assert referenced_files(spec) == []  # built-in shapes only


def test_a_cropped_film_renders_its_crop_window(tmp_path):
    """hdrfilm's crop_offset_x/y, crop_width/height: the image is the crop window (Mitsuba's output), read
    from the XML as Mitsuba reads it; a window outside the film is refused naming the fields."""
    scenes = REPO / "tests" / "compat" / "scenes"
    spec = SceneSpec(scenes / "crop.xml")
    info = film_info(spec)
    assert (info.width, info.height, info.offset) == (40, 32, (18, 10))
    assert info == film_info_from_scene(load(spec, "llvm_ad_rgb", threads=1))
    shutil.copy(scenes / "_room.xml", tmp_path)
    moved = tmp_path / "outside.xml"
    moved.write_text(spec.path.read_text().replace('"crop_offset_x" value="18"', '"crop_offset_x" value="30"'))
    with pytest.raises(SceneError, match=r"outside.xml: film crop window 40x32 at \(30, 10\).*crop_offset_x"):
        film_info(SceneSpec(moved))


def test_sizes_of_hard_cases():
    assert image_size(SceneSpec(DATA / "tiny.xml", {"width": "1", "height": "1"})) == (1, 1)
    assert image_size(SceneSpec(DATA / "tiny.xml", {"width": "1", "height": "9"})) == (1, 9)
    assert referenced_files(SceneSpec(DATA / "tiny.xml")) == [DATA / "_sensor.xml"]


def test_a_film_without_colour_channels_is_refused_naming_it(tmp_path):
    """A specfilm writes one channel per sensitivity curve: tiles carry colour as R, G, B, so the scene is
    refused before anything renders, naming the film and its channels."""
    scenes = REPO / "tests" / "compat" / "scenes"
    shutil.copy(scenes / "_room.xml", tmp_path)
    spectral = (scenes / "lanczos.xml").read_text().replace(
        '<film type="hdrfilm">', '<film type="specfilm"><spectrum name="band1" value="400:1, 500:1, 501:0, 700:0"/>')
    (tmp_path / "spec.xml").write_text(spectral)
    import mitsuba as mi

    before = mi.variant()
    load(SceneSpec(tmp_path / "spec.xml"), "llvm_ad_spectral", threads=1)  # the variant its analysis picks
    try:
        with pytest.raises(SceneError, match=r"spec.xml: film specfilm writes channels \['band1'\]"):
            film_info(SceneSpec(tmp_path / "spec.xml"))
    finally:
        if before is not None:
            mi.set_variant(before)


FILM = """<scene version="3.0.0"><integrator type="path"/>
    <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="6"/>
        <string name="pixel_format" value="{pixel}"/><string name="file_format" value="{file}"/>
        <string name="component_format" value="{component}"/></film></sensor>
    <shape type="sphere"/><emitter type="constant"/>
</scene>"""


@pytest.mark.parametrize("file,pixel,component", [
    ("openexr", "rgba", "float16"), ("EXR", "xyz", "uint32"), ("openexr", "luminance", "float32"),
    ("pfm", "luminance", "float16"), ("PFM", "rgba", "uint32"), ("pfm", "xyza", "float32"),
    ("rgbe", "luminance_alpha", "float16"), ("rgbe", "xyz", "float32"),
])
def test_the_films_file_is_read_as_mitsuba_writes_it(tmp_path, file, pixel, component):
    """hdrfilm's file_format and component_format (any case): the suffix and component type of the file
    plain Mitsuba writes, and the colour it keeps where PFM and RGBE override the pixel format."""
    from render_check import mitsuba_file_kind

    scene = tmp_path / "film.xml"
    scene.write_text(FILM.format(pixel=pixel, file=file, component=component))
    info = film_info(SceneSpec(scene))
    assert info.colour == film_info_from_scene(load(SceneSpec(scene), "llvm_ad_rgb", threads=1)).colour
    suffix, kind = mitsuba_file_kind(scene, "llvm_ad_rgb")
    assert (info.image_file.suffix, info.image_file.component) == (suffix, kind.lower())


def test_a_film_file_mitsuba_refuses_is_refused_naming_the_field(tmp_path):
    scene = tmp_path / "film.xml"
    scene.write_text(FILM.format(pixel="rgb", file="png", component="float32"))
    with pytest.raises(SceneError, match=r"film.xml: film hdrfilm \(file_format 'png'.*openexr, pfm, rgbe"):
        film_info(SceneSpec(scene))
    scene.write_text(FILM.format(pixel="rgb", file="openexr", component="half"))
    with pytest.raises(SceneError, match=r"component_format 'half'.*float16, float32, uint32"):
        film_info(SceneSpec(scene))
    png = tmp_path / "png.xml"
    png.write_text(FILM.format(pixel="rgb", file="png", component="float32"))
    with pytest.raises(SceneError, match="file_format"):  # Mitsuba refuses it too
        load(SceneSpec(png), "llvm_ad_rgb", threads=1)


SHAPE_SENSORS = """<scene version="3.0.0"><integrator type="path"/>
    <shape type="rectangle"><sensor type="irradiancemeter"><film type="hdrfilm">
        <integer name="width" value="1"/><integer name="height" value="1"/>{file}</film></sensor></shape>
    <sensor type="perspective"><film type="hdrfilm">
        <integer name="width" value="11"/><integer name="height" value="7"/></film></sensor>
    <shape type="sphere"><sensor type="irradiancemeter"><film type="hdrfilm">
        <integer name="width" value="2"/><integer name="height" value="1"/></film></sensor></shape>
    <sensor type="orthographic"><film type="hdrfilm">
        <integer name="width" value="13"/><integer name="height" value="5"/></film></sensor>
    <emitter type="constant"/>
</scene>"""


def test_sensors_carried_by_shapes_are_numbered_as_mitsuba_numbers_them(tmp_path):
    """Mitsuba numbers a shape's sensor among the top-level ones in an order the XML does not show (here
    perspective, the sphere's meter, orthographic, the rectangle's meter): `-s N` is the loaded scene's N,
    and its film is read from there; films asking for different files cannot be told apart, and are refused."""
    scene = tmp_path / "shapes.xml"
    scene.write_text(SHAPE_SENSORS.format(file=""))
    spec = SceneSpec(scene)
    loaded = load(spec, "llvm_ad_rgb", threads=1)
    sizes = [(info.width, info.height) for info in (film_info(spec, i) for i in range(4))]
    assert sizes == [tuple(int(v) for v in s.film().crop_size()) for s in loaded.sensors()]
    assert sizes == [(11, 7), (2, 1), (13, 5), (1, 1)]  # not the XML's order: the test's premise
    with pytest.raises(SceneError, match=r"shapes.xml: sensor 4 asked for, the scene has 4 \(0..3\)"):
        film_info(spec, 4)
    scene.write_text(SHAPE_SENSORS.format(file='<string name="file_format" value="pfm"/>'))
    with pytest.raises(SceneError, match=r"shapes.xml: a shape carries a sensor.*openexr float16, pfm float32"):
        film_info(SceneSpec(scene), 0)


def test_a_missing_include_names_each_folder_searched_once(tmp_path):
    """The including file's folder and the scene's are one folder here: it was listed twice."""
    scene = tmp_path / "scene.xml"
    scene.write_text("<scene version='3.0.0'><include filename='nope.xml'/></scene>")
    with pytest.raises(SceneError, match=r"nope.xml' not found; searched: ") as err:
        referenced_files(SceneSpec(scene))
    assert str(err.value).count(str(tmp_path)) == 2, err.value  # the file's own name, then the folder once
