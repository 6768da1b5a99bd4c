"""Whole-image files: linear float32 EXR in and out (RGB, or every channel of a film: alpha, AOVs,
moments), and a tonemapped sRGB PNG of the R, G, B channels for people.

No NaN passes silently: writing an image with non-finite values is an error unless the caller says
`allow_nonfinite=True` (EXR only; a PNG cannot show them).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import OpenEXR
from PIL import Image

from core.errors import QuekaroError

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.render.mitsuba_env), and processes that never render must not pay for it.


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
              channels: Sequence[str] | None = None, planar: bool = False) -> Path:
    """Write a linear float32 EXR (ZIP compressed): RGB, or every channel named in `channels`; `planar`
    images are (channels, H, W) and are written without a copy.

    Written to a temporary name beside `path` and renamed, so a failed write leaves no partial file."""
    path = Path(path)
    if planar:
        names = tuple(channels or ("R", "G", "B"))
        if image.ndim != 3 or image.shape[0] != len(names):
            raise ImageError(f"{path}: planar image shaped {image.shape} does not match {len(names)} channels")
        planes = {c: image[i] for i, c in enumerate(names)}
    elif channels is None:
        planes = {"RGB": as_rgb(image, str(path))}
    else:
        planes = _planes(np.asarray(image, dtype=np.float32), tuple(channels), path)
    if not allow_nonfinite:
        for plane in planes.values():
            _check_finite(plane if plane.ndim == 3 else plane[..., None], path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp: Path) -> None:
        with OpenEXR.File(header, planes) as exr:
            exr.write(str(tmp))

    return _written_atomically(path, write, "EXR")


def _written_atomically(path: Path, write: Callable[[Path], None], what: str) -> Path:
    """`write(tmp)` to a temporary name beside `path`, then rename: a failure leaves no partial file."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        write(tmp)
        os.replace(tmp, path)
    except (OSError, RuntimeError, ValueError) as exc:
        raise ImageError(f"{path}: cannot write {what} ({exc})") from exc
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _planes(image: np.ndarray, channels: tuple[str, ...], path: Path) -> dict[str, np.ndarray]:
    if image.ndim != 3 or image.shape[-1] != len(channels) or len(set(channels)) != len(channels):
        raise ImageError(f"{path}: image shaped {image.shape} does not match its {len(channels)} "
                         f"distinct channel names")
    return {c: np.ascontiguousarray(image[..., i]) for i, c in enumerate(channels)}


def read_exr_channels(path: str | Path) -> tuple[np.ndarray, tuple[str, ...]]:
    """Every channel of an EXR as float32 (H, W, C) and their names: R, G, B first, the rest sorted."""
    channels = _read_planes(Path(path))
    names = [c for c in "RGB" if c in channels] + sorted(c for c in channels if c not in ("R", "G", "B"))
    return np.stack([channels[c] for c in names], axis=-1), tuple(names)


def _read_planes(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise ImageError(f"{path}: no such file")
    if not OpenEXR.isOpenExrFile(str(path)):
        raise ImageError(f"{path}: not an EXR file")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            return {k: np.array(v.pixels, dtype=np.float32) for k, v in exr.channels().items()}
    except Exception as exc:  # OpenEXR reports corrupt files as RuntimeError or ValueError
        raise ImageError(f"{path}: unreadable EXR ({exc})") from exc


def read_exr(path: str | Path) -> np.ndarray:
    """Read an EXR's colour as float32 (H, W, 3), whatever its stored precision: R, G, B; or X, Y, Z as
    they are (an X, Y, Z film's image compared with another's); or Y repeated."""
    path = Path(path)
    channels = _read_planes(path)
    for triple in ("RGB", "XYZ"):
        if all(c in channels for c in triple):
            return np.stack([channels[c] for c in triple], axis=-1)
    if "Y" in channels:
        return np.repeat(channels["Y"][..., None], 3, axis=-1)
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
    try:
        bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True).write(str(path))
    except RuntimeError as exc:
        raise ImageError(f"{path}: cannot write PNG ({exc})") from exc
    return path


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
    return _written_atomically(path, lambda tmp: Image.fromarray(out, "RGB").save(tmp, format="PNG", compress_level=1),
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
