"""Whole-image files: linear EXR in and out (RGB, or every channel of a film: alpha, AOVs, moments), a
job's image as its film asks (OpenEXR at float16, float32 or uint32; PFM; RGBE), and a tonemapped sRGB
PNG of the R, G, B channels for people.

No NaN passes silently: writing an image with non-finite values is an error unless the caller says
`allow_nonfinite=True` (EXR only; a PNG cannot show them).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import OpenEXR
from PIL import Image

from core.errors import QuekaroError
from core.files import written_atomically
from core.model.job import ImageFile

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.mitsuba_env), and processes that never render must not pay for it.


class ImageError(QuekaroError):
    """An image file that cannot be read or written, or an image that is not H x W x 3."""


def as_rgb(image: np.ndarray, name: str = "image") -> np.ndarray:
    """`image` as a contiguous float32 (H, W, 3) array; grey (H, W) and RGBA are converted."""
    array = np.asarray(image, dtype=np.float32)
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=-1)
    if array.ndim != 3 or array.shape[-1] not in (1, 3, 4) or array.shape[0] == 0 or array.shape[1] == 0:
        raise ImageError(f"{name}: expected an H x W x 3 image, got shape {array.shape}")
    if array.shape[-1] == 1:
        array = np.repeat(array, 3, axis=-1)
    return np.ascontiguousarray(array[..., :3])


def _check_finite(image: np.ndarray, path: Path) -> None:
    bad = int((~np.isfinite(image)).any(axis=-1).sum())
    if bad:
        raise ImageError(f"{path}: image has {bad} non-finite pixels (NaN or Inf)")


def write_exr(path: str | Path, image: np.ndarray, allow_nonfinite: bool = False,
              channels: Sequence[str] | None = None, planar: bool = False, component: str = "float32") -> Path:
    """Write a linear EXR (ZIP compressed; float32 components, or float16 / uint32 as a film may ask): RGB,
    or every channel named in `channels`; `planar` float32 images are (channels, H, W) and are written
    without a copy at float32.

    Written to a temporary name beside `path` and renamed, so a failed write leaves no partial file."""
    path = Path(path)
    if planar:
        names = tuple(channels or ("R", "G", "B"))
        if image.ndim != 3 or image.shape[0] != len(names):
            raise ImageError(f"{path}: planar image shaped {image.shape} does not match {len(names)} channels")
        planes = {c: np.ascontiguousarray(image[i]) for i, c in enumerate(names)}  # a copy only of a view
    elif channels is None:
        planes = {"RGB": as_rgb(image, str(path))}
    else:
        planes = _planes(np.asarray(image, dtype=np.float32), tuple(channels), path)
    if not allow_nonfinite:
        for plane in planes.values():
            _check_finite(plane if plane.ndim == 3 else plane[..., None], path)
    if component != "float32":
        convert = _uint32_plane if component == "uint32" else _float16_plane
        planes = {c: convert(plane) for c, plane in planes.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp: Path) -> None:
        with OpenEXR.File(header, planes) as exr:
            exr.write(str(tmp))

    return written_atomically(path, write, "EXR")


# float16's largest finite value, and uint32's scale: Mitsuba stores a uint32 component as the value
# clamped to [0, 1] times 2^32 - 1 (and reads it back unscaled; `read_image` divides).
FLOAT16_MAX = 65504.0
UINT32_SCALE = 4294967295.0


def write_image(path: str | Path, planar: np.ndarray, channels: Sequence[str], image_file: ImageFile,
                allow_nonfinite: bool = False) -> tuple[Path, list[str]]:
    """Write a planar (channels, H, W) float32 image as a film asks (`image_file`) at `path` with the
    format's suffix, as Mitsuba renames it; return the path written and what the format could not hold
    (values turned to Inf or clamped), each said in a line."""
    path = Path(path).with_suffix(image_file.suffix)
    notes = lossy_values(planar, image_file)
    if image_file.format == "openexr":
        write_exr(path, planar, allow_nonfinite, channels, planar=True, component=image_file.component)
    else:
        _write_with_mitsuba(path, planar, tuple(channels), image_file, allow_nonfinite)
    return path, notes


def lossy_values(planar: np.ndarray, image_file: ImageFile) -> list[str]:
    """What writing `planar` as `image_file` changes, beyond rounding: float16's overflow to Inf,
    uint32's clamp to [0, 1], RGBE's negatives (it has no sign; Mitsuba's writer wraps them around)."""
    if image_file.component == "float16":
        lo, hi, what = -FLOAT16_MAX, FLOAT16_MAX, f"above float16's {FLOAT16_MAX:g}: Inf"
    elif image_file.component == "uint32":
        lo, hi, what = 0.0, 1.0, "outside [0, 1]: clamped"
    elif image_file.format == "rgbe":
        lo, hi, what = 0.0, np.inf, "negative, which RGBE cannot store: wrapped around"
    else:
        return []
    # A plane at a time: the assembly of a large image must not hold image-sized temporaries.
    count = sum(int((np.isfinite(plane) & ((plane < lo) | (plane > hi))).sum()) for plane in planar)
    if not count:
        return []
    return [f"{count} pixel channel values {what} in the file, as the film's {image_file.format} "
            f"{image_file.component} stores them (plain Mitsuba writes the same)"]


def _float16_plane(plane: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):  # beyond FLOAT16_MAX becomes Inf, as in Mitsuba's file (lossy_values says so)
        return plane.astype(np.float16)


def _uint32_plane(plane: np.ndarray) -> np.ndarray:
    """One plane as Mitsuba stores a uint32 component, converted by Mitsuba's Bitmap (a grey bitmap: its
    converter takes no named multichannel target from Python)."""
    import mitsuba as mi

    grey = mi.Bitmap(np.ascontiguousarray(plane[..., None], dtype=np.float32), mi.Bitmap.PixelFormat.Y)
    converted = grey.convert(component_format=mi.Struct.Type.UInt32, srgb_gamma=False)
    return np.array(converted, dtype=np.uint32).reshape(plane.shape)


_PIXEL_FORMATS = {("R", "G", "B"): "RGB", ("Y",): "Y"}


def _write_with_mitsuba(path: Path, planar: np.ndarray, channels: tuple[str, ...], image_file: ImageFile,
                        allow_nonfinite: bool) -> None:
    """PFM and RGBE (colour only, float32), written by Mitsuba's own Bitmap: the file plain Mitsuba writes."""
    import mitsuba as mi

    if channels not in _PIXEL_FORMATS:
        raise ImageError(f"{path}: {image_file.format} holds R, G, B or Y only, not channels {list(channels)[:8]}")
    pixels = np.ascontiguousarray(np.moveaxis(planar, 0, -1), dtype=np.float32)
    if not allow_nonfinite:
        _check_finite(pixels, path)
    bitmap = mi.Bitmap(pixels, getattr(mi.Bitmap.PixelFormat, _PIXEL_FORMATS[channels]))
    file_format = {"pfm": mi.Bitmap.FileFormat.PFM, "rgbe": mi.Bitmap.FileFormat.RGBE}[image_file.format]
    written_atomically(path, lambda tmp: bitmap.write(str(tmp), file_format), image_file.format.upper())


def _planes(image: np.ndarray, channels: tuple[str, ...], path: Path) -> dict[str, np.ndarray]:
    if image.ndim != 3 or image.shape[-1] != len(channels) or len(set(channels)) != len(channels):
        raise ImageError(f"{path}: image shaped {image.shape} does not match its {len(channels)} "
                         f"distinct channel names")
    return {c: np.ascontiguousarray(image[..., i]) for i, c in enumerate(channels)}


def read_image_channels(path: str | Path) -> tuple[np.ndarray, tuple[str, ...]]:
    """Every channel of an image file (EXR, PFM, RGBE) as float32 (H, W, C) and their names: R, G, B
    first, the rest sorted."""
    channels = _read_planes(Path(path))
    names = [c for c in "RGB" if c in channels] + sorted(c for c in channels if c not in ("R", "G", "B"))
    return np.stack([channels[c] for c in names], axis=-1), tuple(names)


def _read_planes(path: Path) -> dict[str, np.ndarray]:
    """Every channel of an image file a film writes, as float32: EXR through OpenEXR (a uint32 channel
    scaled back to [0, 1], see UINT32_SCALE), PFM and RGBE through Mitsuba's Bitmap."""
    if not path.is_file():
        raise ImageError(f"{path}: no such file")
    if not OpenEXR.isOpenExrFile(str(path)):
        return _read_with_mitsuba(path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            return {k: _as_float(v.pixels) for k, v in exr.channels().items()}
    except Exception as exc:  # OpenEXR reports corrupt files as RuntimeError or ValueError
        raise ImageError(f"{path}: unreadable EXR ({exc})") from exc


def _as_float(pixels: np.ndarray) -> np.ndarray:
    if pixels.dtype == np.uint32:
        return (pixels / UINT32_SCALE).astype(np.float32)
    return np.array(pixels, dtype=np.float32)


def _read_with_mitsuba(path: Path) -> dict[str, np.ndarray]:
    if path.suffix.lower() == ".exr":
        raise ImageError(f"{path}: not an EXR file")
    if path.suffix.lower() not in (".pfm", ".rgbe", ".hdr"):
        raise ImageError(f"{path}: not an image file quekaro reads (EXR, PFM or RGBE)")
    import mitsuba as mi

    try:
        bitmap = mi.Bitmap(str(path))
    except RuntimeError as exc:
        raise ImageError(f"{path}: unreadable {path.suffix[1:].upper()} ({exc})") from exc
    names = [bitmap.struct_()[i].name for i in range(bitmap.channel_count())]
    pixels = np.array(bitmap, dtype=np.float32).reshape(bitmap.height(), bitmap.width(), len(names))
    return {name: np.ascontiguousarray(pixels[..., i]) for i, name in enumerate(names)}


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file's colour (EXR, PFM, RGBE) as float32 (H, W, 3), whatever its stored precision:
    R, G, B; or X, Y, Z as they are (an X, Y, Z film's image compared with another's); or Y repeated."""
    return read_colour(path)[0]


def read_colour(path: str | Path) -> tuple[np.ndarray, str]:
    """`read_image`'s pixels and which colour they hold: "RGB", "XYZ" or "Y" (luminance, repeated). Two
    images compare channel by channel only where they hold the same."""
    path = Path(path)
    channels = _read_planes(path)
    for triple in ("RGB", "XYZ"):
        if all(c in channels for c in triple):
            return np.stack([channels[c] for c in triple], axis=-1), triple
    if "Y" in channels:
        return np.repeat(channels["Y"][..., None], 3, axis=-1), "Y"
    raise ImageError(f"{path}: no R, G, B; X, Y, Z or Y channels (has {sorted(channels)})")


def linear_to_srgb(image: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values clamped to [0, 1]."""
    x = np.clip(image, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def tonemap(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Display values in [0, 1]: linear x exposure, clamped, sRGB encoded."""
    return linear_to_srgb(as_rgb(image) * np.float32(exposure))


def write_png(path: str | Path, image: np.ndarray, exposure: float = 1.0) -> Path:
    """Write an 8-bit sRGB PNG of a linear image (x exposure, clamped to [0, 1]); NaN/Inf are an error.

    A grey (H, W) image is written as grey RGB. The encoding is done by Mitsuba's Bitmap.
    """
    import mitsuba as mi

    path = Path(path)
    rgb = as_rgb(image, str(path))
    _check_finite(rgb, path)
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")  # Bitmap needs some variant; scalar starts no JIT
    scaled = np.clip(rgb * np.float32(exposure), 0.0, 1.0)
    bitmap = mi.Bitmap(scaled, mi.Bitmap.PixelFormat.RGB)
    encoded = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    return written_atomically(path, lambda tmp: encoded.write(str(tmp), mi.Bitmap.FileFormat.PNG), "PNG")


def write_png_planar(path: str | Path, planar: np.ndarray, rows: int = 128) -> Path:
    """`write_png` of a planar (channels, H, W) image's first three channels, converted a band of rows at a
    time (the 8-bit copy is a quarter of the float image) and encoded by Pillow, which copies it once;
    Mitsuba's Bitmap made two more copies (a 4096^2 image's assembly went over twice its size)."""
    path = Path(path)
    _, height, width = planar.shape
    out = np.empty((height, width, 3), dtype=np.uint8)
    for y0 in range(0, height, rows):
        band = np.moveaxis(planar[:3, y0:y0 + rows], 0, 2)
        _check_finite(band, path)
        out[y0:y0 + rows] = np.rint(tonemap(band) * 255.0).astype(np.uint8)
    # zlib level 1: a 512 px preview is 13 % larger and encodes in 0.02 s instead of 0.09 s (level 6), a
    # share of a short job's wall time that plain Mitsuba, which writes no preview, does not pay.
    return written_atomically(path, lambda tmp: Image.fromarray(out, "RGB").save(tmp, format="PNG", compress_level=1),
                               "PNG")


def read_png(path: str | Path) -> np.ndarray:
    """Read an 8-bit PNG as float32 (H, W, 3) display values in [0, 1] (no sRGB decoding)."""
    import mitsuba as mi

    path = Path(path)
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    try:
        array = np.array(mi.Bitmap(str(path)), dtype=np.float32) / 255.0
    except RuntimeError as exc:
        raise ImageError(f"{path}: unreadable PNG ({exc})") from exc
    return as_rgb(array, str(path))
