"""The synthetic scene: a height map with its albedo and shininess, lighting and textures."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = ["Lighting", "Scene", "band_limited_texture", "shade"]


@dataclass(frozen=True, eq=False)
class Scene:
    """A 3D scene seen from above: what the synthetic camera photographs.

    Arrays are copied to C-contiguous float32 and made read-only (a scene caches its
    rendering layers, see :func:`smdinspect.synth.render_optical`); scenes compare and
    hash by identity.

    Attributes
    ----------
    height_mm : (H, W) float32
        True height of every pixel above the board (base) plane, in the world frame of
        :class:`smdinspect.sff.Surface` (row 0 at the top of the image, ``x = col·p``,
        ``y = (H − 1 − row)·p``).
    albedo : (H, W) or (H, W, 3) float32 in [0, 1]
        Diffuse reflectance, grey or RGB. Grey scenes render grey frames.
    pixel_size_mm : float
        Size of one pixel in the world (object space), mm.
    specular : (H, W) float32 in [0, 1] or None
        Shininess: 0 is matte (solder mask, ceramic), 1 a metal mirror (solder, tin).
    name : str
    meta : dict
        Free-form facts about the scene (generator parameters), written to truth/scene.json.
    """

    height_mm: np.ndarray
    albedo: np.ndarray
    pixel_size_mm: float
    specular: np.ndarray | None = None
    name: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        h = _frozen_f32(self.height_mm, "height_mm")
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise InputError(f"height_mm must be a 2D (H, W) array; got shape {h.shape}")
        if not np.all(np.isfinite(h)):
            raise InputError("height_mm must be finite everywhere (no NaN or inf)")
        a = _frozen_f32(self.albedo, "albedo")
        if a.shape[:2] != h.shape or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
            raise InputError(
                f"albedo must have shape {h.shape} or {h.shape + (3,)}; got {a.shape}"
            )
        _unit_range(a, "albedo")
        s = None
        if self.specular is not None:
            s = _frozen_f32(self.specular, "specular")
            if s.shape != h.shape:
                raise InputError(f"specular must have shape {h.shape}; got {s.shape}")
            _unit_range(s, "specular")
        p = self.pixel_size_mm
        if isinstance(p, bool) or not isinstance(p, (int, float, np.number)) or not (
            math.isfinite(float(p)) and float(p) > 0
        ):
            raise InputError(f"pixel_size_mm must be > 0; got {p!r}")
        if not isinstance(self.name, str):
            raise InputError(f"name must be a string; got {self.name!r}")
        object.__setattr__(self, "height_mm", h)
        object.__setattr__(self, "albedo", a)
        object.__setattr__(self, "specular", s)
        object.__setattr__(self, "pixel_size_mm", float(p))
        object.__setattr__(self, "meta", dict(self.meta))

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.height_mm.shape  # type: ignore[return-value]

    @property
    def is_color(self) -> bool:
        """True when the albedo (and so every frame) is RGB."""
        return self.albedo.ndim == 3

    def height_range_mm(self) -> tuple[float, float]:
        """Lowest and highest height in the scene."""
        return float(self.height_mm.min()), float(self.height_mm.max())


@dataclass(frozen=True)
class Lighting:
    """Fixed lights over the scene (directional, deterministic).

    Diffuse surfaces follow Lambert's law; specular ones (``Scene.specular``) add
    Blinn-Phong glints seen by a camera looking straight down, so a solder fillet shows
    bright bands where its normal bisects a light and the camera, and dark slopes elsewhere.

    Parameters
    ----------
    lights : tuple of (azimuth_deg, elevation_deg, intensity)
        Azimuth from +x towards +y (world frame), elevation above the board.
        The default is an 8-LED ring light at 45° plus a weak light from above.
    ambient : float
        Light reaching every point regardless of its normal.
    shininess : float
        Blinn-Phong exponent of specular surfaces (larger: smaller, sharper glints).
    specular_gain : float
        Peak brightness of a glint of the brightest light relative to a white matte
        surface facing the camera (above 1 saturates the sensor, as real glints do).
    environment : float
        Dim reflection of the surroundings on specular surfaces.
    """

    lights: tuple[tuple[float, float, float], ...] = tuple(
        (45.0 * i + 22.5, 45.0, 1.0) for i in range(8)
    ) + ((0.0, 88.0, 0.4),)
    ambient: float = 0.2
    shininess: float = 30.0
    specular_gain: float = 2.0
    environment: float = 0.12

    def __post_init__(self) -> None:
        try:
            lights = tuple((float(a), float(e), float(i)) for a, e, i in self.lights)
        except (TypeError, ValueError):
            raise InputError(
                "lights must be a sequence of (azimuth_deg, elevation_deg, intensity)"
            ) from None
        if not lights:
            raise InputError("lights must not be empty")
        for a, e, i in lights:
            if not (0.0 < e <= 90.0) or i < 0 or not math.isfinite(a):
                raise InputError(
                    f"each light needs 0 < elevation_deg <= 90 and intensity >= 0; got {(a, e, i)}"
                )
        object.__setattr__(self, "lights", lights)
        for name in ("ambient", "shininess", "specular_gain", "environment"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a number >= 0; got {v!r}")


def shade(scene: Scene, *, lighting: Lighting | None = None) -> np.ndarray:
    """In-focus radiance of every pixel: what a perfectly sharp camera would record.

    Parameters
    ----------
    scene : Scene
    lighting : Lighting, optional

    Returns
    -------
    (H, W) or (H, W, 3) float32
        Relative radiance; 1.0 is a white matte surface facing the camera. Glints may
        exceed 1 (the sensor clips them).
    """
    if not isinstance(scene, Scene):
        raise InputError(f"scene must be a Scene; got {type(scene).__name__}")
    light = Lighting() if lighting is None else lighting
    p = scene.pixel_size_mm
    h = scene.height_mm.astype(np.float64)
    d_row, d_col = np.gradient(h, p)
    gx, gy = d_col, -d_row  # y grows up the image
    norm = np.sqrt(gx * gx + gy * gy + 1.0)
    nx, ny, nz = -gx / norm, -gy / norm, 1.0 / norm
    diffuse = np.full(h.shape, light.ambient)
    flat = light.ambient
    glint = np.zeros(h.shape)
    for az, el, inten in light.lights:
        a, e = math.radians(az), math.radians(el)
        lx, ly, lz = math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)
        diffuse += inten * np.maximum(nx * lx + ny * ly + nz * lz, 0.0)
        flat += inten * lz
        hx, hy, hz = lx, ly, lz + 1.0  # half vector with the view (0, 0, 1)
        hn = math.sqrt(hx * hx + hy * hy + hz * hz)
        cos_h = np.maximum((nx * hx + ny * hy + nz * hz) / hn, 0.0)
        glint += inten * cos_h**light.shininess
    diffuse /= flat  # a flat matte surface gets exactly 1
    brightest = max(i for _, _, i in light.lights)
    glint *= light.specular_gain / max(brightest, 1e-12)  # a full glint of the brightest light
    if scene.specular is None:
        mix_d = diffuse
        mix_s = None
    else:
        s = scene.specular.astype(np.float64)
        mix_d = (1.0 - s) * diffuse
        mix_s = s * (light.environment + glint)
    out = mix_d if mix_s is None else mix_d + mix_s
    if scene.is_color:
        return (scene.albedo * out[:, :, None]).astype(np.float32)
    return (scene.albedo * out).astype(np.float32)


def band_limited_texture(
    shape: tuple[int, int],
    *,
    seed: int,
    mean: float = 0.5,
    contrast: float = 0.2,
    low_cyc_px: float = 0.01,
    high_cyc_px: float = 0.3,
    slope: float = 1.0,
) -> np.ndarray:
    """Random texture with a ``1/f**slope`` spectrum between two frequencies.

    Natural surfaces (paper, ceramic, solder mask) have more power at coarse scales; the
    spectrum is rolled off smoothly below ``low_cyc_px`` and above ``high_cyc_px`` so the
    texture is band-limited (no aliasing, no pixel-level white noise).

    Parameters
    ----------
    shape : (H, W)
    seed : int
        Fixed seed: the same seed gives the same texture.
    mean : float
        Mean value.
    contrast : float
        Standard deviation (RMS contrast in absolute units, e.g. 0.2 for a clearly
        textured surface, 0.01–0.03 for weakly textured solder mask).
    low_cyc_px, high_cyc_px : float
        Band edges in cycles per pixel (0 < low < high <= 0.5).
    slope : float
        Spectral slope of the amplitude (0: white within the band, 1: pink).

    Returns
    -------
    (H, W) float32
        Clipped to [0, 1].
    """
    try:
        hh, ww = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape must be (H, W); got {shape!r}") from None
    if hh < 2 or ww < 2:
        raise InputError(f"shape must be at least (2, 2); got {shape!r}")
    if not (0 < low_cyc_px < high_cyc_px <= 0.5):
        raise InputError(
            f"need 0 < low_cyc_px < high_cyc_px <= 0.5; got {low_cyc_px}, {high_cyc_px}"
        )
    if contrast < 0:
        raise InputError(f"contrast must be >= 0; got {contrast}")
    rng = np.random.default_rng(_seed_int(seed))
    white = rng.standard_normal((hh, ww))
    fy = np.fft.fftfreq(hh)[:, None]
    fx = np.fft.rfftfreq(ww)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f**-slope
    amp *= 1.0 - np.exp(-((f / low_cyc_px) ** 4))  # smooth high-pass at low_cyc_px
    amp *= np.exp(-((f / high_cyc_px) ** 4))  # smooth low-pass at high_cyc_px
    amp[0, 0] = 0.0
    tex = np.fft.irfft2(np.fft.rfft2(white) * amp, s=(hh, ww))
    sd = tex.std()
    if sd > 0:
        tex /= sd
    return np.clip(mean + contrast * tex, 0.0, 1.0).astype(np.float32)


def _seed_int(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be an integer >= 0; got {seed!r}")
    return int(seed)


def _frozen_f32(a: Any, name: str) -> np.ndarray:
    try:
        arr = np.array(a, dtype=np.float32, order="C", copy=True)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array") from None
    arr.flags.writeable = False
    return arr


def _unit_range(a: np.ndarray, name: str) -> None:
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} must be finite everywhere")
    lo, hi = float(a.min()), float(a.max())
    if lo < 0.0 or hi > 1.0:
        raise InputError(f"{name} must lie in [0, 1]; got values in [{lo:.3g}, {hi:.3g}]")
