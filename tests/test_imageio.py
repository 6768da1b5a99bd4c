"""Whole-image files: exact EXR round trip, a job's image in the film's file and component format (as
Mitsuba's own Bitmap writes them), sRGB tonemapping, no silent NaN."""

import errno

import numpy as np
import pytest
from disk_support import small_tmpfs
from render_check import file_kind

from core.files import WriteError
from core.image.imageio import (
    FLOAT16_MAX,
    ImageError,
    linear_to_srgb,
    read_image,
    read_image_channels,
    read_png,
    write_exr,
    write_image,
    write_png,
)
from core.model.job import ImageFile


def test_exr_round_trip(tmp_path):
    image = np.random.default_rng(0).random((5, 7, 3), dtype=np.float32) * 100
    assert np.array_equal(read_image(write_exr(tmp_path / "a.exr", image)), image)


def test_nan_is_never_silent(tmp_path):
    image = np.zeros((2, 2, 3), np.float32)
    image[1, 1, 0] = np.nan
    with pytest.raises(ImageError, match="1 non-finite"):
        write_exr(tmp_path / "a.exr", image)
    with pytest.raises(ImageError, match="non-finite"):
        write_png(tmp_path / "a.png", image)
    write_exr(tmp_path / "b.exr", image, allow_nonfinite=True)
    assert np.isnan(read_image(tmp_path / "b.exr")[1, 1, 0])


def test_png_is_clamped_srgb(tmp_path):
    image = np.array([[[0.0, 0.5, 2.0], [0.0031308, 0.2, -1.0]]], np.float32)
    png = read_png(write_png(tmp_path / "a.png", image))
    expected = np.array([[[0, 0.7354, 1], [0.04, 0.4845, 0]]], np.float32)
    assert np.allclose(png, expected, atol=1 / 255)
    assert np.allclose(linear_to_srgb(np.float32([1.0])), 1.0)


def test_bad_inputs(tmp_path):
    (tmp_path / "x.exr").write_text("hello")
    with pytest.raises(ImageError, match="not an EXR"):
        read_image(tmp_path / "x.exr")
    with pytest.raises(ImageError, match="shape"):
        write_exr(tmp_path / "y.exr", np.zeros((2, 2, 2)))


def test_an_xyz_films_preview_is_converted_as_mitsuba_converts_xyz_to_srgb():
    """core.image.film.display_rgb: an X, Y, Z film's colour planes become linear sRGB by the matrix of
    Mitsuba's own mi.xyz_to_srgb; other films' first three planes pass as they are."""
    import mitsuba as mi

    from core import mitsuba_env
    from core.image.film import display_rgb

    mitsuba_env.init("llvm_ad_rgb", 1)
    planar = np.random.default_rng(4).uniform(0.0, 2.0, size=(4, 3, 5)).astype(np.float32)
    ours = display_rgb(planar, ("X", "Y", "Z"))
    xyz = planar[:3].reshape(3, -1)
    theirs = np.array(mi.xyz_to_srgb(mi.Color3f(xyz[0], xyz[1], xyz[2]))).reshape(3, 3, 5)
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-5)
    assert display_rgb(planar, ("R", "G", "B")) is not None and np.array_equal(display_rgb(planar, ("Y",)), planar[:3])


def _mitsuba_file(path, pixels, names, image_file):
    """The same pixels written by Mitsuba's Bitmap in the film's pixel format, component format and file
    format, read back by Mitsuba: (values, component format)."""
    import mitsuba as mi

    bitmap = mi.Bitmap(np.ascontiguousarray(pixels), getattr(mi.Bitmap.PixelFormat, "".join(names)))
    component = {"float16": mi.Struct.Type.Float16, "float32": mi.Struct.Type.Float32,
                 "uint32": mi.Struct.Type.UInt32}[image_file.component]
    fmt = {"openexr": mi.Bitmap.FileFormat.OpenEXR, "pfm": mi.Bitmap.FileFormat.PFM,
           "rgbe": mi.Bitmap.FileFormat.RGBE}[image_file.format]
    bitmap.convert(component_format=component, srgb_gamma=False).write(str(path), fmt)
    return read_image_channels(path), mi.Bitmap(str(path)).component_format()


@pytest.mark.parametrize("image_file,names", [
    (ImageFile("openexr", "float16"), ("R", "G", "B", "A")), (ImageFile("openexr", "float32"), ("X", "Y", "Z")),
    (ImageFile("openexr", "uint32"), ("R", "G", "B", "A")), (ImageFile("openexr", "uint32"), ("Y",)),
    (ImageFile("pfm"), ("R", "G", "B")), (ImageFile("pfm"), ("Y",)), (ImageFile("rgbe"), ("R", "G", "B")),
])
def test_a_film_file_holds_what_mitsubas_own_file_holds(tmp_path, image_file, names):
    """write_image against Mitsuba's Bitmap writing the same pixels in the same formats: the same values
    once read back (uint32 scaled back to [0, 1] by read_image_channels), the suffix Mitsuba gives."""

    from core import mitsuba_env

    mitsuba_env.init("llvm_ad_rgb", 2)  # Mitsuba's EXR writer hangs at a Dr.Jit thread count of 1 (3.9.1)
    rng = np.random.default_rng(3)
    pixels = rng.uniform(-0.5, 3.0, size=(6, 5, len(names))).astype(np.float32)
    pixels[0, 0, 0] = 1e5  # above float16's range
    path, lossy = write_image(tmp_path / "job.exr", np.moveaxis(pixels, -1, 0), names, image_file)
    assert path == tmp_path / f"job{image_file.suffix}" and path.exists()
    ours, our_names = read_image_channels(path)
    (theirs, their_names), component = _mitsuba_file(tmp_path / f"mitsuba{image_file.suffix}", pixels, names,
                                                     image_file)
    assert our_names == their_names
    np.testing.assert_array_equal(ours, theirs)
    if image_file.component == "float32" and image_file.format != "rgbe":  # lossless: the pixels themselves
        np.testing.assert_array_equal(ours[..., [our_names.index(c) for c in names]], pixels)
    assert file_kind(path)[1] == component.name
    assert bool(lossy) == (image_file.component in ("float16", "uint32") or image_file.format == "rgbe")


def test_a_uint32_file_keeps_every_channel_of_a_film(tmp_path):
    """AOV channels (named beyond any pixel format) in a uint32 EXR: clamped and scaled like the colour."""
    planar = np.array([[[0.25, 2.0]], [[0.5, -1.0]], [[1.0, 0.75]], [[1.0, 1.0]], [[7.0, 0.125]]], np.float32)
    path, _ = write_image(tmp_path / "aov.exr", planar, ("R", "G", "B", "A", "dd.y"), ImageFile("openexr", "uint32"))
    image, names = read_image_channels(path)
    assert names == ("R", "G", "B", "A", "dd.y")
    np.testing.assert_allclose(np.moveaxis(image, -1, 0), np.clip(planar, 0.0, 1.0), atol=1e-6)


def test_what_a_film_file_cannot_hold_is_said():
    planar = np.array([[[FLOAT16_MAX, FLOAT16_MAX * 1.01, -2.0, 0.5]]], np.float32)
    from core.image.imageio import lossy_values

    assert lossy_values(planar, ImageFile("openexr", "float16"))[0].startswith("1 pixel channel values above")
    assert lossy_values(planar, ImageFile("openexr", "uint32"))[0].startswith("3 pixel channel values outside [0, 1]")
    assert lossy_values(planar, ImageFile("rgbe"))[0].startswith("1 pixel channel values negative")
    assert lossy_values(planar, ImageFile("openexr", "float32")) == lossy_values(planar, ImageFile("pfm")) == []


def test_a_film_file_is_refused_where_its_format_cannot_hold_the_channels(tmp_path):
    planar = np.zeros((4, 2, 2), np.float32)
    with pytest.raises(ImageError, match=r"pfm holds R, G, B or Y only, not channels \['R', 'G', 'B', 'A'\]"):
        write_image(tmp_path / "a.exr", planar, ("R", "G", "B", "A"), ImageFile("pfm"))
    assert not list(tmp_path.iterdir())  # nothing half-written
    nan = np.full((3, 2, 2), np.nan, np.float32)
    with pytest.raises(ImageError, match="non-finite"):
        write_image(tmp_path / "a.exr", nan, ("R", "G", "B"), ImageFile("rgbe"))


@pytest.mark.parametrize("image_file", [ImageFile("openexr", "float32"), ImageFile("pfm", "float32"),
                                        ImageFile("rgbe", "float32")], ids=lambda f: f.format)
def test_a_film_file_that_meets_a_full_disk_says_enospc_and_leaves_nothing(tmp_path, image_file):
    """OpenEXR and Mitsuba's Bitmap say a full disk only in words: the error is an ENOSPC all the same,
    which the master answers with 507, not 500."""
    pixels = np.random.default_rng(1).random((3, 256, 256), dtype=np.float32)  # incompressible: over 64 KiB
    with small_tmpfs(tmp_path / "small", "64k") as disk:
        with pytest.raises(WriteError, match="cannot write") as caught:
            write_image(disk / "x", pixels, ("R", "G", "B"), image_file)
        left = list(disk.iterdir())
    assert isinstance(caught.value.__cause__, OSError) and caught.value.__cause__.errno == errno.ENOSPC
    assert left == []
