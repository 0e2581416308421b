"""Test scenes with known heights: cone, staircase, slanted plane, half-textured plane."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import InputError
from ._scene import Scene, _seed_int, band_limited_texture

__all__ = ["cone_scene", "half_textured_scene", "slanted_plane_scene", "staircase_scene"]

_TINT = np.array([0.96, 0.88, 0.74], np.float32)  # warm paper, for colour scenes


def cone_scene(
    *,
    size_px: int = 256,
    pixel_size_mm: float = 0.015,
    height_mm: float = 1.6,
    radius_frac: float = 0.45,
    contrast: float = 0.2,
    seed: int = 0,
    color: bool = False,
) -> Scene:
    """The textured cone of Nayar's *Shape from Focus* on a textured base plane.

    Height ``height_mm·max(0, 1 − r/R)`` with ``R = radius_frac·size`` about the image
    centre; about 40 frames of Δd = 0.05 mm cover the default from below the base to
    above the apex.

    Parameters
    ----------
    size_px : int
        Image side (square).
    pixel_size_mm : float
    height_mm : float
        Apex height above the base plane.
    radius_frac : float
        Cone base radius as a fraction of the image side (0 < r <= 0.5).
    contrast : float
        RMS contrast of the texture (mean 0.5).
    seed : int
        Texture seed.
    color : bool
        RGB albedo (tinted) instead of grey.
    """
    n = _size(size_px)
    p = _positive(pixel_size_mm, "pixel_size_mm")
    hm = _positive(height_mm, "height_mm")
    rf = _positive(radius_frac, "radius_frac")
    if rf > 0.5:
        raise InputError(f"radius_frac must be <= 0.5; got {rf}")
    rows, cols = np.indices((n, n), dtype=np.float64)
    c = (n - 1) / 2.0
    r = np.hypot(rows - c, cols - c)
    height = hm * np.maximum(0.0, 1.0 - r / (rf * n))
    albedo = _albedo((n, n), seed, contrast, color)
    return Scene(height.astype(np.float32), albedo, p, name="cone",
                 meta=_meta(locals(), "cone", ("size_px", "pixel_size_mm", "height_mm",
                                               "radius_frac", "contrast", "seed", "color")))


def staircase_scene(
    *,
    size_px: int = 256,
    pixel_size_mm: float = 0.015,
    n_steps: int = 5,
    step_mm: float = 0.2,
    contrast: float = 0.2,
    seed: int = 0,
    color: bool = False,
) -> Scene:
    """Terraces of known height rising from left to right, with vertical risers.

    Terrace ``k`` (columns ``[k·W/n, (k+1)·W/n)``) is at ``k·step_mm``. The risers are
    occlusion edges: the higher terrace hides the lower one's continuation.
    """
    n = _size(size_px)
    p = _positive(pixel_size_mm, "pixel_size_mm")
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or not (
        2 <= n_steps <= n // 4
    ):
        raise InputError(f"n_steps must be an integer in [2, {n // 4}]; got {n_steps!r}")
    s = _positive(step_mm, "step_mm")
    cols = np.arange(n)
    k = np.minimum(cols * n_steps // n, n_steps - 1)
    height = np.broadcast_to((k * s)[None, :], (n, n)).astype(np.float32)
    albedo = _albedo((n, n), seed, contrast, color)
    return Scene(height, albedo, p, name="staircase",
                 meta=_meta(locals(), "staircase", ("size_px", "pixel_size_mm", "n_steps",
                                                    "step_mm", "contrast", "seed", "color")))


def step_target_scene(
    *,
    size_px: int = 256,
    pixel_size_mm: float = 0.015,
    block_mm: float = 0.4,
    contrast: float = 0.2,
    seed: int = 0,
    color: bool = False,
) -> Scene:
    """A block of known height on a flat base, both textured: a gauge block or shim as
    ``smdinspect calibrate z-scale`` wants it.

    The block covers the centred square of half the image side (a quarter of the field,
    under its centre) at ``block_mm``; the base is at 0. Its edges are occlusion edges.
    """
    n = _size(size_px)
    p = _positive(pixel_size_mm, "pixel_size_mm")
    b = _positive(block_mm, "block_mm")
    rows, cols = np.indices((n, n))
    inside = (np.abs(rows - (n - 1) / 2) < n / 4) & (np.abs(cols - (n - 1) / 2) < n / 4)
    height = np.where(inside, b, 0.0).astype(np.float32)
    albedo = _albedo((n, n), seed, contrast, color)
    return Scene(height, albedo, p, name="step",
                 meta=_meta(locals(), "step", ("size_px", "pixel_size_mm", "block_mm",
                                               "contrast", "seed", "color")))


def slanted_plane_scene(
    *,
    size_px: int = 256,
    pixel_size_mm: float = 0.015,
    rise_mm: float = 1.0,
    base_mm: float = 0.0,
    azimuth_deg: float = 0.0,
    contrast: float = 0.2,
    seed: int = 0,
    color: bool = False,
) -> Scene:
    """A textured plane tilted so its height rises by ``rise_mm`` across the image.

    Height ``base_mm + rise_mm·u``, ``u`` in [0, 1] the position along the world
    direction ``azimuth_deg`` (0: +x, to the right; 90: +y, up the image).
    """
    n = _size(size_px)
    p = _positive(pixel_size_mm, "pixel_size_mm")
    rise = _finite(rise_mm, "rise_mm")
    base = _finite(base_mm, "base_mm")
    az = math.radians(_finite(azimuth_deg, "azimuth_deg"))
    rows, cols = np.indices((n, n), dtype=np.float64)
    x, y = cols, (n - 1) - rows
    proj = x * math.cos(az) + y * math.sin(az)
    u = (proj - proj.min()) / max(proj.max() - proj.min(), 1e-12)
    height = (base + rise * u).astype(np.float32)
    albedo = _albedo((n, n), seed, contrast, color)
    return Scene(height, albedo, p, name="plane",
                 meta=_meta(locals(), "plane", ("size_px", "pixel_size_mm", "rise_mm",
                                                "base_mm", "azimuth_deg", "contrast", "seed",
                                                "color")))


def half_textured_scene(
    *,
    size_px: int = 256,
    pixel_size_mm: float = 0.015,
    base_mm: float = 0.3,
    rise_mm: float = 0.4,
    flat_albedo: float = 0.5,
    contrast: float = 0.2,
    seed: int = 0,
    color: bool = False,
) -> Scene:
    """A plane rising up the image whose left half is textured and right half is not.

    The right half (``col >= W // 2``) has the constant albedo ``flat_albedo``: apart
    from sensor noise it is textureless, so a focus measure cannot find its depth there.
    The textured half is ``col < W // 2`` (``meta["textured_cols"]``, start and stop).
    """
    n = _size(size_px)
    p = _positive(pixel_size_mm, "pixel_size_mm")
    base = _finite(base_mm, "base_mm")
    rise = _finite(rise_mm, "rise_mm")
    fa = _finite(flat_albedo, "flat_albedo")
    if not 0 <= fa <= 1:
        raise InputError(f"flat_albedo must lie in [0, 1]; got {fa}")
    rows = np.arange(n, dtype=np.float64)[:, None]
    height = np.broadcast_to(base + rise * ((n - 1) - rows) / (n - 1), (n, n)).astype(np.float32)
    albedo = _albedo((n, n), seed, contrast, color, mean=fa)
    half = n // 2
    if color:
        albedo[:, half:] = fa * _TINT
    else:
        albedo[:, half:] = fa
    return Scene(height, albedo, p, name="halftex",
                 meta=_meta(locals(), "halftex", ("size_px", "pixel_size_mm", "base_mm",
                                                  "rise_mm", "flat_albedo", "contrast", "seed",
                                                  "color")) | {"textured_cols": [0, half]})


def _albedo(shape, seed, contrast, color, mean=0.5):
    c = _finite(contrast, "contrast")
    if c < 0:
        raise InputError(f"contrast must be >= 0; got {c}")
    tex = band_limited_texture(shape, seed=_seed_int(seed), mean=mean, contrast=c)
    if color:
        return np.ascontiguousarray(tex[:, :, None] * _TINT)
    return tex


def _meta(scope: dict[str, Any], kind: str, names) -> dict[str, Any]:
    return {"scene": kind, **{k: scope[k] for k in names}}


def _size(size_px: Any) -> int:
    if isinstance(size_px, bool) or not isinstance(size_px, (int, np.integer)) or size_px < 16:
        raise InputError(f"size_px must be an integer >= 16; got {size_px!r}")
    return int(size_px)


def _finite(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not \
            math.isfinite(float(value)):
        raise InputError(f"{name} must be a finite number; got {value!r}")
    return float(value)


def _positive(value: Any, name: str) -> float:
    v = _finite(value, name)
    if v <= 0:
        raise InputError(f"{name} must be > 0; got {v}")
    return v
