"""Spectral data in a scene's XML, and whether rgb would render it differently (then: a spectral variant).

An rgb render multiplies colours channel by channel; a spectral one multiplies spectra wavelength by
wavelength. They agree for one reflection, and differ once light meets spectra twice, unless the spectra
are flat or close to it. `spectral_need` says why a scene needs a spectral variant (or None);
`colour_error` is its test and `read_spectrum` reads a spectrum given per wavelength or by file.
"""

from __future__ import annotations

import functools
import itertools
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import SceneError
from core.scene.resolver import RESOLVED_ATTR, SRC_ATTR

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.mitsuba_env), and processes that never render must not pay for it.

RGB_TOLERANCE = 0.02  # of the brightest channel, after up to three bounces (a flat 400-700 nm spectrum: 0.9 %)
IOR_TOLERANCE = 1e-4  # relative spread of an index of refraction over wavelength
_GRID = np.arange(360.0, 831.0, 5.0)  # Mitsuba's CIE range, 5 nm steps
_IOR_NAMES = {"eta", "k", "int_ior", "ext_ior"}
CONDUCTORS = ("conductor", "roughconductor")
# Linear sRGB from CIE XYZ (IEC 61966-2-1).
_XYZ_TO_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314],
                         [-0.9692660, 1.8760108, 0.0415560],
                         [0.0556434, -0.2040259, 1.0572252]])


@functools.lru_cache(maxsize=1)
def _cmf() -> np.ndarray:
    import mitsuba as mi

    # The scalar variant's function: usable whatever variant this process has set.
    return np.array([list(mi.scalar_rgb.cie1931_xyz(float(w))) for w in _GRID])


def _rgb(values: np.ndarray) -> np.ndarray:
    """Linear sRGB of a spectrum on _GRID, normalised so that a flat spectrum of 1 is (1, 1, 1)."""
    cmf = _cmf()
    white = _XYZ_TO_SRGB @ cmf.sum(axis=0)
    return (_XYZ_TO_SRGB @ (values[:, None] * cmf).sum(axis=0)) / white


def colour_error(spectra: list[np.ndarray]) -> float:
    """Largest disagreement between channel-wise and per-wavelength products, relative to the brightest
    channel of the per-wavelength result, in linear sRGB: light that bounces two and three times off the
    same spectrum, and once off each of any two of them."""
    worst = 0.0
    scaled = [s / max(float(np.abs(s).mean()), 1e-12) for s in spectra]
    products = [(s, s, None) for s in scaled] + [(s, t, None) for s, t in itertools.combinations(scaled, 2)]
    products += [(s, s, s) for s in scaled]
    for a, b, c in products:
        exact = a * b * (c if c is not None else 1.0)
        channel = _rgb(a) * _rgb(b) * (_rgb(c) if c is not None else 1.0)
        truth = _rgb(exact)
        worst = max(worst, float(np.max(np.abs(truth - channel)) / max(float(np.max(np.abs(truth))), 1e-12)))
    return worst


def _on_grid(wavelengths: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation inside the given range and zero outside it, as Mitsuba's irregular spectrum."""
    order = np.argsort(wavelengths)
    w, v = wavelengths[order], values[order]
    out = np.interp(_GRID, w, v)
    out[(w[0] > _GRID) | (w[-1] < _GRID)] = 0.0
    return out


def read_spectrum(elem: Any, src: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(wavelengths, values) of a `<spectrum>` of the expanded XML given per wavelength or by file (the
    file core.scene.resolver found for it); None for a plain value."""
    where = f"{elem.get(SRC_ATTR, src)}: <spectrum name={elem.get('name')!r}>"
    if elem.get("filename"):
        return _from_file(Path(elem.get(RESOLVED_ATTR, elem.get("filename"))), where)
    value = elem.get("value", "")
    if ":" not in value:
        return None
    try:
        pairs = [item.split(":") for item in value.replace(",", " ").split()]
        data = np.array([[float(w), float(v)] for w, v in pairs])
    except ValueError as exc:
        raise SceneError(f"{where}: value {value[:60]!r} is not 'wavelength:value, ...' ({exc})") from exc
    return data[:, 0], data[:, 1]


def _from_file(path: Path, where: str) -> tuple[np.ndarray, np.ndarray]:
    import mitsuba as mi

    try:  # the scalar variant's reader, usable whatever variant this process has set, or none yet
        wavelengths, values = mi.scalar_rgb.spectrum_from_file(str(path))
    except RuntimeError as exc:
        raise SceneError(f"{where}: cannot read spectrum file {path} ({exc})") from exc
    return np.asarray(wavelengths, dtype=np.float64), np.asarray(values, dtype=np.float64)


def spectral_need(root: Any, scene_path: Path) -> str | None:
    """Why the scene needs a spectral variant, or None when rgb renders its spectral data the same.

    Its colours after bounces must agree within RGB_TOLERANCE (`colour_error`): a flat spectrum passes
    exactly; narrow emission lines and spectra with structure fail. Always spectral: an index of refraction
    that varies with wavelength (dispersion), a conductor of one of Mitsuba's measured metals (`material`),
    and blackbody spectra, which exist only in spectral variants."""
    named = _named_conductor(root, scene_path)
    if named:
        return named
    colours: list[tuple[str, np.ndarray]] = []
    for elem in root.iter("spectrum"):
        src = Path(elem.get(SRC_ATTR, scene_path))
        name = elem.get("name")
        if elem.get("type") == "blackbody":
            return f"{src}: <spectrum type='blackbody'> exists only in spectral variants"
        data = _typed(elem) if elem.get("type") in ("regular", "irregular") else read_spectrum(elem, src)
        if data is None:
            continue
        wavelengths, values = data
        if name in _IOR_NAMES:
            spread = float(np.ptp(values) / max(float(np.abs(values).mean()), 1e-12))
            if spread > IOR_TOLERANCE:
                return f"{src}: <spectrum name={name!r}> varies with wavelength (dispersion, spread {spread:.2%})"
            continue
        colours.append((f"{src}: <spectrum name={name!r}>", _on_grid(wavelengths, values)))
    if not colours:
        return None
    error = colour_error([c for _, c in colours])
    if error > RGB_TOLERANCE:
        names = "; ".join(n for n, _ in colours[:3])
        return (f"per-wavelength data that rgb would render differently (colour after bounces off it off by "
                f"{error:.1%} > {RGB_TOLERANCE:.0%}): {names}")
    return None


def _named_conductor(root: Any, scene_path: Path) -> str | None:
    """A conductor whose `material` names one of Mitsuba's measured metals: its eta and k are spectra that
    Mitsuba reads from its own data, not the XML, and they vary with wavelength (gold's colour off by
    about 5 % per channel in rgb, chromium's 8 %: tests/test_effects.py)."""
    for elem in root.iter("bsdf"):
        if elem.get("type") not in CONDUCTORS:
            continue
        for child in elem.iterfind("string[@name='material']"):
            if child.get("value", "none") != "none":
                where = child.get(SRC_ATTR, elem.get(SRC_ATTR, str(scene_path)))
                return (f"{where}: <bsdf type={elem.get('type')!r}> material {child.get('value')!r} is measured "
                        "per wavelength (its complex index of refraction, hence its colour, varies)")
    return None


def _typed(elem: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """A `<spectrum type="regular|irregular">` with its properties as children."""
    props = {c.get("name"): c.get("value", "") for c in elem if isinstance(c.tag, str)}
    try:
        values = np.array([float(v) for v in props["values"].replace(",", " ").split()])
        if elem.get("type") == "regular":
            lo, hi = float(props["wavelength_min"]), float(props["wavelength_max"])
            return np.linspace(lo, hi, len(values)), values
        return np.array([float(v) for v in props["wavelengths"].replace(",", " ").split()]), values
    except (KeyError, ValueError) as exc:
        raise SceneError(f"{elem.get(SRC_ATTR)}: <spectrum type={elem.get('type')!r}> "
                         f"lacks or mangles {exc}") from exc
