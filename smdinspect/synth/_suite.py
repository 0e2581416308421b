"""A second, independent renderer and randomised scenes, so SFF is not tuned to one model.

**The gather renderer** (:func:`render_gather`) differs in model from
:func:`~smdinspect.synth.render_stack` (which scatters soft height layers and composites
them front to back, with occlusion). Here every output pixel *gathers*: it takes the
radiance blurred with the PSF of its *own* defocus ``b·|z − h(pixel)|``, whatever its
neighbours' depths. A bank of blurred copies of the whole radiance is made once, at a
geometric ladder of defocus values (ratio 2^¼, plus zero), and each pixel interpolates
between the two levels around its defocus. The PSF is a Gaussian of
``σ = sqrt(sigma0² + (b·|z − h|)²)`` or a pillbox (disc) of radius ``2·b·|z − h|`` (the
disc with the same σ) convolved with the in-focus Gaussian ``sigma0``. A non-telecentric
lens is mimicked by scaling frame ``n`` about the image centre by
``1 + magnification_per_mm·(z_n − z_ref)``. The sensor (:class:`GatherNoise`) adds Poisson
shot noise, Gaussian read noise, vignetting, exposure flicker, clipping and quantisation.

**Scenes** (:func:`cone`, :func:`slanted_plane`, :func:`steps`, :func:`sphere_cap`,
:func:`bore`, :func:`half_textured`) return ``(radiance, height_mm)`` with heights from
``low_mm`` to ``high_mm``; **textures** (:func:`texture`) are band-limited noise around a
chosen frequency, a weave, grain, or sparse marks; :func:`add_highlight` adds a smooth
specular blob that ignores the texture.

:func:`random_case` draws everything at random from a seed (ranges in its docstring);
:func:`case_stack` writes a case as a stack directory for ``smdinspect reconstruct``.
Tune on :data:`TUNING_SEEDS`; tests and benchmarks use :data:`TEST_SEEDS` only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import InputError
from ._scene import _seed_int as _seed
from ._scenes import _size

__all__ = [
    "Case",
    "GatherNoise",
    "PSF_KINDS",
    "SCENE_KINDS",
    "TEST_SEEDS",
    "TEXTURE_KINDS",
    "TUNING_SEEDS",
    "add_highlight",
    "bore",
    "case_stack",
    "cone",
    "gather_board_stack",
    "half_textured",
    "random_case",
    "render_gather",
    "shade_dome",
    "slanted_plane",
    "sphere_cap",
    "steps",
    "texture",
]

TUNING_SEEDS = range(0, 1000)  #: seeds free for tuning parameters against
TEST_SEEDS = range(10_000, 11_000)  #: seeds for tests and benchmarks, never for tuning
PSF_KINDS = ("gauss", "disc")
SCENE_KINDS = ("cone", "slanted_plane", "steps", "sphere_cap", "bore", "half_textured")
TEXTURE_KINDS = ("band", "weave", "grain", "marks")

_LADDER_LO = 0.25  # first non-zero defocus level (px of σ)
_LADDER_RATIO = 2.0**0.25
_DOF_SIGMA_PX = 1.0 / (2.0 * math.sqrt(2.0))  # σ of a 1 px blur circle (σ = C/(2√2))


# --------------------------------------------------------------------------------------
# The renderer


@dataclass(frozen=True)
class GatherNoise:
    """Sensor of :func:`render_gather`. The defaults are a clean-ish 8-bit camera.

    Parameters
    ----------
    photons_full_scale : float
        Photo-electrons at full scale; shot noise is Poisson in them (0: none).
    read_noise : float
        Gaussian read noise, RMS as a fraction of full scale (0.02 = 2 %).
    exposure : float
        Fraction of full scale reached by radiance 1.0 (brighter parts clip).
    vignetting : float
        Relative light loss in the image corners (quadratic in the radius).
    flicker : float
        Per-frame exposure change, uniform in ``±flicker``.
    bit_depth : {8, 16}
    """

    photons_full_scale: float = 20_000.0
    read_noise: float = 0.002
    exposure: float = 0.85
    vignetting: float = 0.0
    flicker: float = 0.0
    bit_depth: int = 8

    def __post_init__(self) -> None:
        _num(self.photons_full_scale, "photons_full_scale", lo=0.0)
        _num(self.read_noise, "read_noise", lo=0.0, hi=1.0)
        _num(self.exposure, "exposure", lo=0.0, lo_open=True)
        _num(self.vignetting, "vignetting", lo=0.0, hi=0.95)
        _num(self.flicker, "flicker", lo=0.0, hi=0.5)
        if isinstance(self.bit_depth, bool) or self.bit_depth not in (8, 16):
            raise InputError(f"bit_depth must be 8 or 16; got {self.bit_depth!r}")

    @classmethod
    def off(cls, **overrides: Any) -> "GatherNoise":
        """An ideal sensor: no shot or read noise, no vignetting or flicker."""
        return cls(**{"photons_full_scale": 0.0, "read_noise": 0.0, **overrides})


def render_gather(
    radiance: np.ndarray,
    height_mm: np.ndarray,
    z_mm: Sequence[float],
    *,
    blur_px_per_mm: float,
    sigma0_px: float = 0.5,
    psf: str = "gauss",
    magnification_per_mm: float = 0.0,
    z_ref_mm: float | None = None,
    noise: GatherNoise | None = None,
    seed: int = 0,
) -> list[np.ndarray]:
    """Render one frame per ``z_mm``; every pixel blurred by the PSF of its own depth.

    Parameters
    ----------
    radiance : (H, W) or (H, W, 3) float
        In-focus radiance, >= 0 (1.0 reaches ``noise.exposure`` of full scale).
    height_mm : (H, W) float
        Surface height of every pixel.
    z_mm : sequence of float
        Focused-plane height of each frame (any order; frames come back in this order).
    blur_px_per_mm : float
        Growth of the defocus σ (px) per mm of ``|z − h|``; for ``psf="disc"`` the disc
        radius is ``2·σ``. 0 renders every frame in focus.
    sigma0_px : float
        In-focus Gaussian blur, added in quadrature.
    psf : {"gauss", "disc"}
    magnification_per_mm : float
        Frame ``n`` is scaled about the image centre by ``1 + m·(z_n − z_ref_mm)``.
    z_ref_mm : float, optional
        Height at which the scale is 1 (and the truth is registered); default the middle
        of the sweep.
    noise : GatherNoise, optional
        Default ``GatherNoise()``; ``GatherNoise.off()`` for an ideal sensor.
    seed : int
        Frame ``n`` draws from ``SeedSequence([seed, n])``: same seed, same frames.

    Returns
    -------
    list of (H, W) or (H, W, 3) uint8 / uint16
    """
    rad = _image(radiance, "radiance")
    h = _image(height_mm, "height_mm", color=False, nonneg=False)
    if h.shape != rad.shape[:2]:
        raise InputError(f"height_mm must have shape {rad.shape[:2]}; got {h.shape}")
    try:
        z = np.asarray(z_mm, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        z = np.zeros(0)
    if z.size == 0 or not np.all(np.isfinite(z)):
        raise InputError(f"z_mm must be a non-empty sequence of finite numbers; got {z_mm!r}")
    b = _num(blur_px_per_mm, "blur_px_per_mm", lo=0.0)
    s0 = _num(sigma0_px, "sigma0_px", lo=0.0)
    if psf not in PSF_KINDS:
        raise InputError(f"psf must be one of {', '.join(PSF_KINDS)}; got {psf!r}")
    m = _num(magnification_per_mm, "magnification_per_mm")
    zr = 0.5 * (z.min() + z.max()) if z_ref_mm is None else _num(z_ref_mm, "z_ref_mm")
    scale = 1.0 + m * (z - zr)
    if np.any(scale < 0.1):
        raise InputError(f"magnification_per_mm={m} scales a frame by {scale.min():.3g}; "
                         "every frame's scale 1 + m·(z − z_ref_mm) must be >= 0.1")
    cfg = GatherNoise() if noise is None else noise
    if not isinstance(cfg, GatherNoise):
        raise InputError(f"noise must be a GatherNoise; got {type(noise).__name__}")
    seed = _seed(seed)
    bank = _defocus_bank(rad, h, z, b, s0, psf)
    vig = _vignette(h.shape, cfg.vignetting)
    frames = []
    for n, zn in enumerate(z):
        img = _gather(bank, b * np.abs(np.float32(zn) - h))
        if scale[n] != 1.0:
            img = _scale_about_centre(img, float(scale[n]))
        rng = np.random.default_rng(np.random.SeedSequence([seed, n, 0x6A7E]))
        frames.append(_sensor(img, cfg, vig, rng))
    return frames


def gather_board_stack(scene, z_mm: Sequence[float], out: str | Path, *, optics,
                       noise: GatherNoise, seed: int, psf: str = "gauss"):
    """Photograph a board :class:`~smdinspect.synth.Scene` with the gather model instead
    of :func:`~smdinspect.synth.render_stack`, write it as a stack directory at ``out``
    and return it opened (a :class:`~smdinspect.stack.FocalStack`).

    Everything but the geometry and the albedo differs from our own renderer: the light
    (:func:`shade_dome`, not Blinn-Phong under a ring), a second texture laid over the
    albedo, the defocus (each pixel gathers the blur of its own depth, no occlusion, a
    Gaussian or a disc PSF) and the sensor (:class:`GatherNoise`, with vignetting). The
    blur grows at ``optics.blur_rate_px_per_mm()`` from ``optics.sigma0_px``. Through an
    ordinary lens (``optics.telecentric`` False) a point at height h in the frame focused
    at z lands ``optics.scale_at(h, z)`` times as far from the image centre as in the
    scene, as a moving camera sees it (two fixed-point steps of the inverse map).
    """
    import cv2

    from ..stack import FocalStack, StackWriter

    rng = np.random.default_rng(np.random.SeedSequence([_seed(seed), 0x5EED]))
    z = np.asarray(z_mm, np.float64).reshape(-1)
    h = np.asarray(scene.height_mm, np.float32)
    rad, light = shade_dome(scene, rng)
    b = float(optics.blur_rate_px_per_mm())
    s0 = float(optics.sigma0_px)
    hh, ww = h.shape
    bank = _defocus_bank(rad, h, z, b, s0, psf)
    vig = _vignette(h.shape, noise.vignetting)
    rows, cols = np.indices(h.shape, dtype=np.float32)
    cy, cx = (hh - 1) / 2.0, (ww - 1) / 2.0
    diffs = np.diff(z)
    rig = {"step_mm": float(-diffs[0])} if z.size > 1 and np.allclose(diffs, diffs[0]) else {}
    writer = StackWriter(Path(out), pixel_size_mm=scene.pixel_size_mm, rig=rig,
                         meta={"generator": "smdinspect.synth.gather_board_stack",
                               "scene": scene.name, "seed": int(seed), "psf": psf,
                               "shading": light,
                               "noise": {k: getattr(noise, k)
                                         for k in GatherNoise.__dataclass_fields__}})
    for n, zn in enumerate(z):
        img = _gather(bank, b * np.abs(np.float32(zn) - h))
        if not optics.telecentric:
            # output pixel y shows the scene point x with y - c = s(h(x), z)·(x - c)
            mx, my = cols, rows
            for _ in range(2):
                hx = cv2.remap(h, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                s = optics.scale_at(hx, float(zn)).astype(np.float32)
                mx, my = cx + (cols - cx) / s, cy + (rows - cy) / s
            img = cv2.remap(img, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        frame_rng = np.random.default_rng(np.random.SeedSequence([_seed(seed), n, 0x6A7E]))
        writer.add_frame(_sensor(np.maximum(img, 0.0), noise, vig, frame_rng), float(zn))
    return FocalStack.open(out)


def shade_dome(scene, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """In-focus radiance of ``scene`` under a light model unlike
    :func:`~smdinspect.synth.shade`'s, drawn from ``rng``; returns (radiance, params).

    Diffuse: a dome (irradiance ``(1 + n_z)/2``) mixed with one key light at a random
    azimuth and elevation, 1 for a flat surface. Specular (``scene.specular``): a coaxial
    lobe ``exp(−tan²θ / m²)`` (flat metal mirrors the light back: glints clip) plus a ring
    lobe around the tilt ``(90° − elevation)/2`` that mirrors a ring light into the lens,
    tinted by the metal's colour, over a dim reflection of the surroundings. A second
    texture (band-limited noise or grain at a random frequency and contrast) modulates
    the albedo, so the scene's texture statistics are not only our own.
    """
    h = np.asarray(scene.height_mm, np.float64)
    p = float(scene.pixel_size_mm)
    gy, gx = np.gradient(h, p)
    gy = -gy  # rows run down, y up
    norm = np.sqrt(1.0 + gx * gx + gy * gy)
    nx, ny, nz = -gx / norm, -gy / norm, 1.0 / norm
    tan2 = gx * gx + gy * gy
    theta = np.arctan(np.sqrt(tan2))
    az, el = math.radians(rng.uniform(0, 360)), math.radians(rng.uniform(30, 70))
    lx, ly, lz = math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)
    key = float(rng.uniform(0.2, 0.6))
    diffuse = (1 - key) * (1 + nz) / 2 + key * np.maximum(nx * lx + ny * ly + nz * lz, 0) / lz
    m = float(rng.uniform(0.05, 0.25))
    ring_el = float(rng.uniform(20, 60))
    ring_w = math.radians(float(rng.uniform(4, 12)))
    g_coax, g_ring = float(rng.uniform(0.4, 3.0)), float(rng.uniform(0.3, 1.5))
    env = float(rng.uniform(0.05, 0.2))
    lobes = (g_coax * np.exp(-tan2 / (m * m))
             + g_ring * np.exp(-0.5 * ((theta - math.radians((90 - ring_el) / 2)) / ring_w) ** 2))
    kind = "band" if rng.random() < 0.5 else "grain"
    freq = float(np.exp(rng.uniform(math.log(0.05), math.log(0.3))))
    contrast = float(rng.uniform(0.0, 0.3))
    size = max(h.shape)
    tex = texture(kind, size, seed=int(rng.integers(1 << 30)), freq_cyc_px=freq,
                  contrast=1.0)[: h.shape[0], : h.shape[1]]
    alb = np.asarray(scene.albedo, np.float64)
    mod = 1.0 + contrast * 2.0 * (tex - float(tex.mean()))
    alb = np.clip(alb * (mod if alb.ndim == 2 else mod[:, :, None]), 0.0, 1.0)
    spec = np.zeros(h.shape) if scene.specular is None else np.asarray(scene.specular, np.float64)
    if alb.ndim == 3:
        diffuse, lobes, spec = diffuse[:, :, None], lobes[:, :, None], spec[:, :, None]
    tint = 0.5 + 0.5 * alb
    rad = (1 - spec) * alb * diffuse + spec * (env * alb + lobes * tint)
    params = {"key_light": [math.degrees(az), math.degrees(el), key], "roughness": m,
              "ring_elevation_deg": ring_el, "coaxial_gain": g_coax, "ring_gain": g_ring,
              "environment": env, "texture": [kind, freq, contrast]}
    return np.ascontiguousarray(rad, np.float32), params


def _defocus_bank(rad: np.ndarray, h: np.ndarray, z: np.ndarray, b: float, s0: float,
                  psf: str) -> np.ndarray:
    """The radiance blurred at every level of the defocus ladder (0, then
    :data:`_LADDER_LO` × :data:`_LADDER_RATIO`ⁿ px) up to the largest defocus
    ``b·|z − h|`` of the sweep (at most twice the image's side)."""
    top = min(b * float(np.max(np.abs(z[:, None] - np.array([h.min(), h.max()])))),
              2.0 * max(h.shape))
    levels = [0.0, _LADDER_LO]
    while levels[-1] < top:
        levels.append(levels[-1] * _LADDER_RATIO)
    return np.stack([_blur(rad, s0, d, psf) for d in levels])


def _blur(rad: np.ndarray, s0: float, defocus: float, psf: str) -> np.ndarray:
    import cv2

    border = cv2.BORDER_REFLECT
    if psf == "gauss":
        s = math.hypot(s0, defocus)
        return cv2.GaussianBlur(rad, (0, 0), s, borderType=border) if s > 0.05 else rad.copy()
    out = rad
    if defocus > 0:
        out = cv2.filter2D(rad, -1, _disc_kernel(2.0 * defocus), borderType=border)
    if s0 > 0.05:
        out = cv2.GaussianBlur(out, (0, 0), s0, borderType=border)
    return out.copy() if out is rad else out


def _disc_kernel(radius_px: float) -> np.ndarray:
    """Pillbox of ``radius_px`` with an anti-aliased edge (1 px ramp), sum 1."""
    n = int(math.ceil(radius_px + 0.5))
    yy, xx = np.mgrid[-n : n + 1, -n : n + 1]
    k = np.clip(radius_px + 0.5 - np.hypot(yy, xx), 0.0, 1.0).astype(np.float32)
    return k / k.sum()


def _gather(bank: np.ndarray, defocus: np.ndarray) -> np.ndarray:
    """Per pixel, interpolate the bank between the two levels around its defocus."""
    top = bank.shape[0] - 1
    d = np.maximum(defocus, _LADDER_LO)
    k = np.where(defocus < _LADDER_LO, defocus / _LADDER_LO,
                 1.0 + np.log(d / _LADDER_LO) / math.log(_LADDER_RATIO))
    k = np.clip(k, 0.0, top).astype(np.float32)
    i = np.minimum(k.astype(np.intp), top - 1)
    w = k - i.astype(np.float32)
    rows, cols = np.indices(defocus.shape, sparse=True)
    if bank.ndim == 4:
        w = w[:, :, None]
    return (1.0 - w) * bank[i, rows, cols] + w * bank[i + 1, rows, cols]


def _scale_about_centre(img: np.ndarray, s: float) -> np.ndarray:
    import cv2

    hh, ww = img.shape[:2]
    if s < 1.0:  # anti-alias before shrinking
        img = cv2.GaussianBlur(img, (0, 0), 0.5 * math.sqrt(1.0 / (s * s) - 1.0) + 1e-3)
    cx, cy = (ww - 1) / 2.0, (hh - 1) / 2.0
    mat = np.array([[s, 0.0, (1.0 - s) * cx], [0.0, s, (1.0 - s) * cy]], np.float64)
    return cv2.warpAffine(img, mat, (ww, hh), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def _vignette(shape: tuple[int, int], amount: float) -> np.ndarray:
    hh, ww = shape
    rows, cols = np.indices(shape, dtype=np.float32)
    r2 = ((rows - (hh - 1) / 2) ** 2 + (cols - (ww - 1) / 2) ** 2) / (
        ((hh - 1) / 2) ** 2 + ((ww - 1) / 2) ** 2)
    return (1.0 - amount * r2).astype(np.float32)


def _sensor(img: np.ndarray, cfg: GatherNoise, vig: np.ndarray,
            rng: np.random.Generator) -> np.ndarray:
    gain = cfg.exposure * (1.0 + cfg.flicker * rng.uniform(-1.0, 1.0))
    v = img * np.float32(gain) * (vig if img.ndim == 2 else vig[:, :, None])
    if cfg.photons_full_scale > 0:
        p = cfg.photons_full_scale
        v = (rng.poisson(np.clip(v, 0.0, 4.0).astype(np.float64) * p) / p).astype(np.float32)
    if cfg.read_noise > 0:
        v = v + np.float32(cfg.read_noise) * rng.standard_normal(v.shape, dtype=np.float32)
    top = (1 << cfg.bit_depth) - 1
    dtype = np.uint8 if cfg.bit_depth == 8 else np.uint16
    return np.rint(np.clip(v, 0.0, 1.0) * top).astype(dtype)


# --------------------------------------------------------------------------------------
# Textures


def texture(kind: str, size_px: int, *, seed: int, freq_cyc_px: float = 0.1,
            contrast: float = 0.1, mean: float = 0.5) -> np.ndarray:
    """A random ``(size_px, size_px)`` float32 texture in [0, 1].

    Parameters
    ----------
    kind : {"band", "weave", "grain", "marks"}
        ``band``: noise whose spectrum is a log-Gaussian ring at ``freq_cyc_px`` (half an
        octave wide). ``weave``: over/under threads of period ``1/freq_cyc_px`` px at a
        random angle, each thread of its own shade. ``grain``: sparse speckles (about 3 %
        of pixels) of size ``~0.25/freq_cyc_px``. ``marks``: a flat background with a few
        dots and scratches (sparse: most of the image has no texture).
    freq_cyc_px : float
        Dominant spatial frequency, cycles per pixel, in (0, 0.5].
    contrast : float
        RMS contrast as a fraction of ``mean`` (for ``marks``: the marks' depth).
    mean : float
        Mean level (background level for ``marks``).
    """
    import cv2

    if kind not in TEXTURE_KINDS:
        raise InputError(f"kind must be one of {', '.join(TEXTURE_KINDS)}; got {kind!r}")
    n = _size(size_px)
    f0 = _num(freq_cyc_px, "freq_cyc_px", lo=0.0, hi=0.5, lo_open=True)
    c = _num(contrast, "contrast", lo=0.0, hi=1.0)
    mu = _num(mean, "mean", lo=0.0, hi=1.0, lo_open=True)
    rng = np.random.default_rng(np.random.SeedSequence([_seed(seed), 0x7E47]))
    rows, cols = np.indices((n, n), dtype=np.float64)
    if kind == "band":
        f = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.rfftfreq(n)[None, :])
        f[0, 0] = 1e-9
        ring = np.exp(-0.5 * (np.log2(f / f0) / 0.5) ** 2)
        t = np.fft.irfft2(np.fft.rfft2(rng.standard_normal((n, n))) * ring, s=(n, n))
    elif kind == "weave":
        a = rng.uniform(0.0, math.pi)
        u = (cols * math.cos(a) + rows * math.sin(a)) * f0 + rng.uniform(0, 1)
        v = (-cols * math.sin(a) + rows * math.cos(a)) * f0 + rng.uniform(0, 1)
        iu, iv = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        shade_u = rng.uniform(0.7, 1.3, 4096)[iu % 4096]
        shade_v = rng.uniform(0.7, 1.3, 4096)[iv % 4096]
        warp_on_top = (iu + iv) % 2 == 0
        t = np.where(warp_on_top, shade_u * np.sin(math.pi * (u - iu)),
                     shade_v * np.sin(math.pi * (v - iv)))
        t = cv2.GaussianBlur(t.astype(np.float32), (0, 0), 0.6).astype(np.float64)
    elif kind == "grain":
        t = (rng.random((n, n)) < 0.03) * rng.choice([-1.0, 1.0], (n, n))
        t = cv2.GaussianBlur(t.astype(np.float32), (0, 0), max(0.4, 0.25 / f0))
        t = t.astype(np.float64)
    else:  # marks: flat, with a few dots and scratches of depth ±contrast·mean
        img = np.zeros((n, n), np.float32)
        for _ in range(int(rng.integers(3, 12))):
            cen = tuple(int(v) for v in rng.integers(0, n, 2))
            cv2.circle(img, cen, int(rng.integers(1, 4)), float(rng.choice([-1, 1])), -1,
                       cv2.LINE_AA)
        for _ in range(int(rng.integers(1, 5))):
            p0, p1 = (tuple(int(v) for v in rng.integers(0, n, 2)) for _ in range(2))
            cv2.line(img, p0, p1, float(rng.choice([-1, 1])), 1, cv2.LINE_AA)
        img = cv2.GaussianBlur(img, (0, 0), max(0.4, 0.1 / f0))
        peak = float(np.abs(img).max())
        return np.clip(mu * (1.0 + c * img / max(peak, 1e-9)), 0, 1).astype(np.float32)
    t = t - t.mean()
    sd = t.std()
    return np.clip(mu * (1.0 + c * t / max(sd, 1e-12)), 0.0, 1.0).astype(np.float32)


def add_highlight(radiance: np.ndarray, *, seed: int, strength: float = 0.6,
                  radius_frac: float = 0.08) -> np.ndarray:
    """``radiance`` plus a smooth bright Gaussian blob at a random place, clipped to [0, 1].

    The blob ignores the texture (a glint on a shiny part): a focus measure sees no
    detail in it, only its smooth edge.
    """
    rad = _image(radiance, "radiance")
    st = _num(strength, "strength", lo=0.0)
    rf = _num(radius_frac, "radius_frac", lo=0.0, hi=0.5, lo_open=True)
    hh, ww = rad.shape[:2]
    rng = np.random.default_rng(np.random.SeedSequence([_seed(seed), 0x5BEC]))
    cy, cx = rng.uniform(0.2, 0.8) * hh, rng.uniform(0.2, 0.8) * ww
    rows, cols = np.indices((hh, ww), dtype=np.float32)
    blob = st * np.exp(-((rows - cy) ** 2 + (cols - cx) ** 2) / (2 * (rf * max(hh, ww)) ** 2))
    blob = blob if rad.ndim == 2 else blob[:, :, None]
    return np.clip(rad + blob, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------------------
# Scenes: (radiance, height_mm); the shape u in [0, 1] maps to low_mm .. high_mm


def cone(*, size_px: int = 128, low_mm: float = 0.0, high_mm: float = 1.0,
         radius_frac: float = 0.45, texture: np.ndarray | None = None, seed: int = 0):
    """A cone (apex ``high_mm`` at the centre, radius ``radius_frac·size``) on a plane."""
    n, r = _size(size_px), _radius(size_px)
    rf = _num(radius_frac, "radius_frac", lo=0.0, hi=0.5, lo_open=True)
    return _finish(np.maximum(0.0, 1.0 - r / (rf * n)), low_mm, high_mm, texture, seed)


def slanted_plane(*, size_px: int = 128, low_mm: float = 0.0, high_mm: float = 1.0,
                  azimuth_deg: float = 0.0, texture: np.ndarray | None = None, seed: int = 0):
    """A plane rising from ``low_mm`` to ``high_mm`` towards ``azimuth_deg`` (0: +col, 90: up)."""
    return _finish(_ramp(_size(size_px), azimuth_deg), low_mm, high_mm, texture, seed)


def steps(*, size_px: int = 128, low_mm: float = 0.0, high_mm: float = 1.0, n_steps: int = 4,
          riser_px: float = 0.0, azimuth_deg: float = 0.0,
          texture: np.ndarray | None = None, seed: int = 0):
    """``n_steps`` equal terraces rising towards ``azimuth_deg``; risers ``riser_px`` wide
    (0: vertical, an occlusion edge)."""
    n = _size(size_px)
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or not (
            2 <= n_steps <= n // 8):
        raise InputError(f"n_steps must be an integer in [2, {n // 8}]; got {n_steps!r}")
    rp = _num(riser_px, "riser_px", lo=0.0, hi=n / (2 * n_steps))
    t = _ramp(n, azimuth_deg) * n_steps
    k = np.minimum(np.floor(t), n_steps - 1)
    f = rp * n_steps / n  # riser width as a fraction of a terrace
    up = np.clip((t - k - (1.0 - f)) / f, 0.0, 1.0) if f > 0 else 0.0
    u = np.minimum(k + up, n_steps - 1) / (n_steps - 1)
    return _finish(u, low_mm, high_mm, texture, seed)


def sphere_cap(*, size_px: int = 128, low_mm: float = 0.0, high_mm: float = 1.0,
               radius_frac: float = 0.4, cap_deg: float = 60.0,
               texture: np.ndarray | None = None, seed: int = 0):
    """A spherical cap of base radius ``radius_frac·size`` and half-angle ``cap_deg``
    (90: a hemisphere-like dome, steep at its rim) on a plane."""
    n, r = _size(size_px), _radius(size_px)
    a = _num(radius_frac, "radius_frac", lo=0.0, hi=0.5, lo_open=True) * n
    cap = math.radians(_num(cap_deg, "cap_deg", lo=1.0, hi=90.0))
    rs = a / math.sin(cap)
    base = math.sqrt(max(rs * rs - a * a, 0.0))
    u = (np.sqrt(np.maximum(rs * rs - r * r, 0.0)) - base) / (rs - base)
    return _finish(np.where(r < a, u, 0.0), low_mm, high_mm, texture, seed)


def bore(*, size_px: int = 128, low_mm: float = 0.0, high_mm: float = 1.0,
         radius_frac: float = 0.35, fillet_frac: float = 0.5,
         texture: np.ndarray | None = None, seed: int = 0):
    """A round hole: top surface at ``high_mm``, flat floor at ``low_mm`` (centre), joined
    by a quarter-circle fillet ``fillet_frac`` of the radius wide (1: a bowl)."""
    n, r = _size(size_px), _radius(size_px)
    a = _num(radius_frac, "radius_frac", lo=0.0, hi=0.5, lo_open=True) * n
    rf = _num(fillet_frac, "fillet_frac", lo=0.0, hi=1.0, lo_open=True) * a
    s = np.clip((r - (a - rf)) / rf, 0.0, 1.0)
    u = np.where(r < a, 1.0 - np.sqrt(1.0 - s * s), 1.0)
    return _finish(u, low_mm, high_mm, texture, seed)


def half_textured(*, size_px: int = 128, low_mm: float = 0.0, high_mm: float = 1.0,
                  azimuth_deg: float = 90.0, texture: np.ndarray | None = None, seed: int = 0):
    """A slanted plane textured only where ``col < size_px // 2``; the right half is flat at
    the texture's mean. Returns ``(radiance, height_mm, textured)``, ``textured`` a bool mask."""
    rad, h = slanted_plane(size_px=size_px, low_mm=low_mm, high_mm=high_mm,
                           azimuth_deg=azimuth_deg, texture=texture, seed=seed)
    mask = np.zeros(h.shape, bool)
    mask[:, : h.shape[1] // 2] = True
    rad = rad.copy()
    rad[~mask] = rad[mask].mean(axis=0)
    return rad, h, mask


def _finish(u, low_mm, high_mm, tex, seed) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = _num(low_mm, "low_mm"), _num(high_mm, "high_mm")
    if hi < lo:
        raise InputError(f"high_mm must be >= low_mm ({lo}); got {hi}")
    n = u.shape[0]
    if tex is None:
        rad = texture("band", n, seed=seed, freq_cyc_px=0.12, contrast=0.2)
    else:
        rad = _image(tex, "texture")
        if rad.shape[:2] != u.shape:
            raise InputError(f"texture must have shape {u.shape} (+ (3,)); got {rad.shape}")
        if rad.min() < 0 or rad.max() > 1:
            raise InputError("texture must lie in [0, 1]")
    return rad, (lo + (hi - lo) * u).astype(np.float32)


def _ramp(n: int, azimuth_deg: float) -> np.ndarray:
    a = math.radians(_num(azimuth_deg, "azimuth_deg"))
    rows, cols = np.indices((n, n), dtype=np.float64)
    p = cols * math.cos(a) + ((n - 1) - rows) * math.sin(a)
    return (p - p.min()) / max(float(p.max() - p.min()), 1e-12)


def _radius(size_px: int) -> np.ndarray:
    n = _size(size_px)
    rows, cols = np.indices((n, n), dtype=np.float64)
    return np.hypot(rows - (n - 1) / 2, cols - (n - 1) / 2)


# --------------------------------------------------------------------------------------
# Random cases


@dataclass(frozen=True, eq=False)
class Case:
    """One randomised test case: frames, where they were focused, and the truth.

    ``height_mm`` is registered to the frame whose scale is 1 (``params["z_ref_mm"]``).
    ``textured`` marks the pixels with texture (``half_textured`` scenes only, else None).
    """

    name: str
    frames: list
    z_mm: np.ndarray
    height_mm: np.ndarray
    step_mm: float
    pixel_size_mm: float
    textured: np.ndarray | None
    params: dict


def random_case(seed: int, *, size_px: int = 128, kind: str | None = None) -> Case:
    """A case drawn at random from ``seed`` (same seed, same case). ``U``: uniform,
    ``logU``: log-uniform, ``p``: probability.

    - scene ``kind`` from :data:`SCENE_KINDS` (unless given); relief
      ``high − low`` logU 0.1–2 mm above ``low`` U 0–0.5 mm; azimuth U 0–360°, cone/cap/bore
      radius U 0.3–0.48 of the side, cap half-angle U 20–90°, fillet U 0.2–1, 2–6 steps with
      risers 0 (p 0.5) or U 0–3 px;
    - texture kind from :data:`TEXTURE_KINDS`, frequency logU 0.03–0.35 cyc/px, RMS contrast
      logU 0.005–0.3 of the mean, mean U 0.3–0.7; RGB tint p 0.25; highlight p 0.3
      (strength U 0.3–1, radius U 0.04–0.15 of the side);
    - 6–40 frames (uniform integer), sweep span U 1.1–1.5 × relief centred on it;
    - blur rate so that one step is logU 0.3–3 depths of field (DOF: the defocus over which
      the blur circle stays under 1 px, σ ≤ 1/(2√2) px); ``sigma0_px`` U 0.3–1.0; PSF
      gauss or disc (p 0.5 each);
    - magnification: none (p 0.5), else a total change logU 1.005–2× over the sweep,
      growing or shrinking with z, scale 1 at the middle;
    - pixel size logU 0.005–0.03 mm; photons at full scale logU 300–30 000, read noise
      U 0–3 %, exposure U 0.4–0.95, vignetting 0 (p 0.5) or U 0.05–0.4, flicker 0 (p 0.5)
      or U 0.2–3 %, 8 bit (p 0.7) or 16 bit.
    """
    seed = _seed(seed)
    n_px = _size(size_px)
    if kind is not None and kind not in SCENE_KINDS:
        raise InputError(f"kind must be one of {', '.join(SCENE_KINDS)}; got {kind!r}")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xCA5E]))

    def logu(a: float, b: float) -> float:
        return float(math.exp(rng.uniform(math.log(a), math.log(b))))

    def chance(p: float) -> bool:
        return bool(rng.random() < p)

    kind = kind or str(SCENE_KINDS[int(rng.integers(len(SCENE_KINDS)))])
    tex_kind = str(TEXTURE_KINDS[int(rng.integers(len(TEXTURE_KINDS)))])
    p: dict[str, Any] = {"seed": seed, "size_px": n_px, "scene": kind, "texture": tex_kind}
    p.update(freq_cyc_px=logu(0.03, 0.35), contrast=logu(0.005, 0.3),
             mean=float(rng.uniform(0.3, 0.7)))
    rad = texture(tex_kind, n_px, seed=seed, freq_cyc_px=p["freq_cyc_px"],
                  contrast=p["contrast"], mean=p["mean"])
    p["tint"] = [float(v) for v in rng.uniform(0.6, 1.0, 3)] if chance(0.25) else None
    if p["tint"] is not None:
        rad = np.ascontiguousarray(rad[:, :, None] * np.array(p["tint"], np.float32))
    p["highlight"] = None
    if chance(0.3):
        p["highlight"] = {"strength": float(rng.uniform(0.3, 1.0)),
                          "radius_frac": float(rng.uniform(0.04, 0.15))}
    if p["highlight"] is not None:
        rad = add_highlight(rad, seed=seed, **p["highlight"])
    p["pixel_size_mm"] = logu(0.005, 0.03)
    p["low_mm"] = float(rng.uniform(0.0, 0.5))
    p["high_mm"] = p["low_mm"] + logu(0.1, 2.0)
    geo: dict[str, Any] = {"azimuth_deg": float(rng.uniform(0, 360))}
    if kind in ("cone", "sphere_cap", "bore"):
        geo = {"radius_frac": float(rng.uniform(0.3, 0.48))}
        if kind == "sphere_cap":
            geo["cap_deg"] = float(rng.uniform(20, 90))
        if kind == "bore":
            geo["fillet_frac"] = float(rng.uniform(0.2, 1.0))
    if kind == "steps":
        geo["n_steps"] = int(rng.integers(2, min(6, n_px // 8) + 1))
        geo["riser_px"] = 0.0 if chance(0.5) else float(rng.uniform(0, 3))
    p["geometry"] = geo
    fn = {"cone": cone, "slanted_plane": slanted_plane, "steps": steps,
          "sphere_cap": sphere_cap, "bore": bore, "half_textured": half_textured}[kind]
    out = fn(size_px=n_px, low_mm=p["low_mm"], high_mm=p["high_mm"], texture=rad,
             seed=seed, **geo)
    rad, h = out[0], out[1]
    mask = out[2] if len(out) == 3 else None

    relief = p["high_mm"] - p["low_mm"]
    n_frames = int(rng.integers(6, 41))
    span = relief * float(rng.uniform(1.1, 1.5))
    step = span / (n_frames - 1)
    z = p["low_mm"] - 0.5 * (span - relief) + step * np.arange(n_frames, dtype=np.float64)
    p.update(n_frames=n_frames, step_mm=step, step_per_dof=logu(0.3, 3.0),
             sigma0_px=float(rng.uniform(0.3, 1.0)), psf=str(PSF_KINDS[int(rng.integers(2))]))
    p["blur_px_per_mm"] = p["step_per_dof"] * 2.0 * _DOF_SIGMA_PX / step
    p["z_ref_mm"] = float(0.5 * (z[0] + z[-1]))
    if chance(0.5):
        p["magnification_change"] = 1.0
        p["magnification_per_mm"] = 0.0
    else:
        g = logu(1.005, 2.0)
        p["magnification_change"] = g
        p["magnification_per_mm"] = (1 if chance(0.5) else -1) * 2 * (g - 1) / ((g + 1) * span)
    noise = GatherNoise(
        photons_full_scale=logu(300, 30_000), read_noise=float(rng.uniform(0, 0.03)),
        exposure=float(rng.uniform(0.4, 0.95)),
        vignetting=0.0 if chance(0.5) else float(rng.uniform(0.05, 0.4)),
        flicker=0.0 if chance(0.5) else float(rng.uniform(0.002, 0.03)),
        bit_depth=8 if chance(0.7) else 16)
    p["noise"] = {k: getattr(noise, k) for k in GatherNoise.__dataclass_fields__}
    frames = render_gather(rad, h, z, blur_px_per_mm=p["blur_px_per_mm"],
                           sigma0_px=p["sigma0_px"], psf=p["psf"],
                           magnification_per_mm=p["magnification_per_mm"],
                           z_ref_mm=p["z_ref_mm"], noise=noise, seed=seed)
    name = f"suite-{seed:05d}-{kind}-{tex_kind}"
    return Case(name, frames, z, h, float(step), p["pixel_size_mm"], mask, p)


def case_stack(case: Case, root: str | Path) -> Path:
    """Write ``case`` as a stack directory (``stack.json`` + PNG frames) with ``truth/``
    (``height_mm.tiff``, ``case.json``, and ``textured.png`` when the case has a mask).

    Returns the stack directory, ready for ``smdinspect reconstruct``.
    """
    from .. import _atomic
    from ..stack import StackWriter

    if not isinstance(case, Case):
        raise InputError(f"case must be a Case; got {type(case).__name__}")
    root = Path(root)
    writer = StackWriter(root, pixel_size_mm=case.pixel_size_mm, rig={"step_mm": case.step_mm},
                         meta={"generator": "smdinspect.synth.random_case", "case": case.name,
                               "params": case.params})
    for frame, z in zip(case.frames, case.z_mm):
        writer.add_frame(frame, float(z))
    truth = root / "truth"
    _atomic.write_tiff(truth / "height_mm.tiff", np.asarray(case.height_mm, np.float32))
    _atomic.write_json(truth / "case.json", {"name": case.name, "z_mm": case.z_mm.tolist(),
                                             "params": case.params})
    if case.textured is not None:
        _atomic.write_image(truth / "textured.png", case.textured.astype(np.uint8) * 255)
    return root


# --------------------------------------------------------------------------------------
# Validation


def _num(value: Any, name: str, *, lo: float | None = None, hi: float | None = None,
         lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not \
            math.isfinite(float(value)):
        raise InputError(f"{name} must be a finite number; got {value!r}")
    v = float(value)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise InputError(f"{name} must be {'>' if lo_open else '>='} {lo}; got {v}")
    if hi is not None and v > hi:
        raise InputError(f"{name} must be <= {hi}; got {v}")
    return v


def _image(a: Any, name: str, *, color: bool = True, nonneg: bool = True) -> np.ndarray:
    try:
        arr = np.ascontiguousarray(a, dtype=np.float32)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array") from None
    ok = arr.ndim == 2 or (color and arr.ndim == 3 and arr.shape[2] == 3)
    if not ok or min(arr.shape[:2]) < 2:
        want = "(H, W) or (H, W, 3)" if color else "(H, W)"
        raise InputError(f"{name} must be a {want} array; got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite everywhere (no NaN or inf)")
    if nonneg and arr.min() < 0:
        raise InputError(f"{name} must be >= 0; got a minimum of {float(arr.min()):.3g}")
    return arr
