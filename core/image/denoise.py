"""Denoising a composed image with Intel Open Image Denoise (`mitsuba-oidn`, Mitsuba's own binding).

The denoiser reads the colour and two AOVs of one pass of their own over the image (`AOVS`: albedo and
shading normal, `DENOISER_CHANNELS`, at `AOV_SPP`); `denoise_planar` returns the image with its colour
denoised (OIDN's `QUALITY`), every other channel (alpha, the scene's own AOVs) as rendered. `quekaro bench
denoise` measures what each AOV spp and quality costs and gives (docs/benchmarks/denoise).
"""

from __future__ import annotations

import numpy as np

from core.errors import RenderError

AOVS = "denoise_albedo:albedo,denoise_normal:sh_normal"  # the denoiser's pass: names no scene's own AOV takes
AOV_SPP = 16  # samples a pixel of that pass (the AOVs are far less noisy than the colour)
DENOISER_FILTER = "box"  # what a denoised job reconstructs with: each pixel its own samples
ALBEDO = ("denoise_albedo.R", "denoise_albedo.G", "denoise_albedo.B")
NORMAL = ("denoise_normal.X", "denoise_normal.Y", "denoise_normal.Z")
DENOISER_CHANNELS = ALBEDO + NORMAL
QUALITIES = ("high", "balanced", "fast")  # OIDN's filter qualities (mitsuba_oidn.Quality), best first
QUALITY = "high"  # on a CPU, balanced gives high's very image; fast is measurably worse


def denoise_planar(planar: np.ndarray, channels: tuple[str, ...], aux: np.ndarray,
                   quality: str = QUALITY) -> np.ndarray:
    """The planar C x H x W image with R, G, B denoised (at OIDN's `quality`), every other channel as it
    is; `aux` is the denoiser's pass, planar in `DENOISER_CHANNELS` order. RenderError where the image lacks
    R, G, B."""
    if tuple(channels[:3]) != ("R", "G", "B") or aux.shape != (len(DENOISER_CHANNELS), *planar.shape[1:]):
        raise RenderError(f"cannot denoise channels {list(channels)[:8]} of shape {planar.shape[1:]} with an AOV "
                          f"pass of shape {aux.shape}: expected R, G, B first and {len(DENOISER_CHANNELS)} AOV planes")

    def hwc(images: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.moveaxis(images, 0, -1), dtype=np.float32)

    out = planar.copy()
    out[:3] = np.moveaxis(denoise(hwc(planar[:3]), hwc(aux[:3]), hwc(aux[3:]), quality), -1, 0)
    return out


def denoise(colour: np.ndarray, albedo: np.ndarray, normal: np.ndarray, quality: str = QUALITY) -> np.ndarray:
    """The HDR colour (H x W x 3, linear) denoised with its albedo and shading normal at OIDN's `quality`
    (one of QUALITIES), on OIDN's default device (its CPU one on Dr.Jit's thread pool, its CUDA one where a
    driver is present)."""
    if quality not in QUALITIES:
        raise ValueError(f"denoiser quality {quality!r}: expected one of {', '.join(QUALITIES)}")
    import mitsuba_oidn  # Lazy: OIDN's libraries (~40 MB) load only for a job that denoises

    finite = np.nan_to_num(colour, nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)
    images = (np.ascontiguousarray(a, dtype=np.float32) for a in (finite, albedo, normal))
    level = getattr(mitsuba_oidn.Quality, quality.capitalize())
    return np.asarray(mitsuba_oidn.denoise(*images, hdr=True, quality=level), dtype=np.float32)
