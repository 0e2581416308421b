"""Render focal stacks: layered thin-lens defocus with occlusion, then a noisy sensor.

How a frame is made (:func:`render_optical`, then :func:`render_frame`):

1. **Shading.** :func:`~smdinspect.synth.shade` turns the scene into in-focus radiance
   (Lambert + Blinn-Phong glints on specular parts; fixed lights; computed once per scene).
2. **Layers.** Heights are cut into thin layers of thickness ``t`` (``layer_mm``) centred
   at ``c_j = h_min + j·t``. Layer ``j`` covers everything at or above it with a *soft,
   cumulative* coverage ``A_j = clip((h − c_j)/t + 1, 0, 1)``, so a pixel between two
   layer centres is shared linearly between them: its blur is interpolated and the depth
   at which it is sharpest is continuous in ``h`` (no staircase from the quantisation).
3. **Blur per layer.** Each layer is blurred with its own Gaussian σ from
   :meth:`Optics.blur_sigma_px` for this frame's ``z_mm`` (``cv2.GaussianBlur``; large σ
   at reduced resolution). Far from focus, neighbouring layers whose defocus differs by
   less than 25 % share one blur.
4. **Occlusion.** Layers are composited far to near (lowest first) as premultiplied
   colour with their *blurred coverage* as alpha: ``acc = blur(R·A) + (1 − blur(A))·acc``.
   A defocused raised part thus spreads over the background next to it, while a focused
   top edge stays sharp over a blurred background, as with a real lens. What a layer shows
   where it is hidden by something much higher (more than ``4t`` above it) is unknown;
   it is filled with the layer's own colour interpolated under the occluder
   (pyramid push-pull) plus the occluder's fine texture, so a background seen "around" a
   defocused edge keeps realistic fine detail but not the occluder's colour.
5. **Magnification.** With an ordinary (non-telecentric) lens every layer is scaled about
   the image centre by :meth:`Optics.scale_at` before blurring.

The sensor (:class:`SensorConfig`) then adds per-frame illumination flicker, sub-pixel
jitter, shot and read noise, clipping at full well, and 8/16-bit quantisation.

Not modelled: cast shadows, inter-reflections, diffraction beyond ``Optics.sigma0_px``,
and the change of viewing direction across the field of an ordinary lens (glints are
computed for a camera looking straight down). Shot noise is Gaussian with variance equal
to the electron count (Poisson-like; accurate above a few tens of electrons).

Determinism: every random draw of a frame comes from ``frame_rng(seed, z_mm)``, a
generator seeded by the stack seed and the frame's focus height in nanometres, so one
frame rendered on its own (the simulated camera of :mod:`smdinspect.acquire`) is
byte-identical to the same frame of a stack rendered with the same seed.
"""

from __future__ import annotations

import logging
import math
import shutil
import weakref
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import InputError
from ..optics import Optics
from ._scene import Lighting, Scene, _seed_int, shade

log = logging.getLogger(__name__)

__all__ = [
    "SensorConfig",
    "frame_rng",
    "render_frame",
    "render_optical",
    "render_stack",
]

_JUMP_LAYERS = 4  # heights more than this many layers above a layer occlude it
_GROUP_REL = 0.25  # far layers whose defocus differs by < 25 % share one blur
_NEAR_LAYERS = 4  # layers within this many of z are never grouped
_LOWRES_SIGMA = 4.0  # runs of groups blurred by more than this (px) render at 1/2 .. 1/8


@dataclass(frozen=True)
class SensorConfig:
    """The camera sensor: noise, quantisation, flicker and jitter.

    The default is a typical machine-vision sensor and *is* noisy: 10 000 e⁻ full well,
    8 e⁻ read noise, shot noise, ±1 % flicker.

    Parameters
    ----------
    bit_depth : {8, 16}
        Output ``uint8`` or ``uint16`` (full range).
    full_well_e : float
        Electrons at saturation; shot noise is relative to it.
    read_noise_e : float
        Read noise, electrons RMS.
    shot_noise : bool
        Photon shot noise (Gaussian approximation of Poisson: variance = electrons).
    exposure : float
        Fraction of full well reached by a white matte surface facing the camera
        (glints brighter than ``1/exposure`` saturate).
    flicker : float
        Per-frame illumination change, uniform in ``±flicker`` (0.01 = ±1 %).
    jitter_px : float
        Per-frame lateral stage wobble: a random sub-pixel shift with this RMS per axis
        (Lanczos resampling). 0 disables it.

    Notes
    -----
    Randomness never comes from a global state. :func:`render_frame` takes a generator or
    an integer seed; with a seed it uses :func:`frame_rng` ``(seed, z_mm)``, as
    :func:`render_stack` does for every frame. The draws of one frame are, in order:
    flicker (1 value), jitter (2 values), the noise image.
    """

    bit_depth: int = 8
    full_well_e: float = 10_000.0
    read_noise_e: float = 8.0
    shot_noise: bool = True
    exposure: float = 0.85
    flicker: float = 0.01
    jitter_px: float = 0.0

    def __post_init__(self) -> None:
        if self.bit_depth not in (8, 16) or isinstance(self.bit_depth, bool):
            raise InputError(f"bit_depth must be 8 or 16; got {self.bit_depth!r}")
        _check_number(self.full_well_e, "full_well_e", positive=True)
        _check_number(self.exposure, "exposure", positive=True)
        for name in ("read_noise_e", "flicker", "jitter_px"):
            _check_number(getattr(self, name), name)
        if self.flicker >= 1:
            raise InputError(f"flicker must be < 1 (a fraction); got {self.flicker}")
        if not isinstance(self.shot_noise, (bool, np.bool_)):
            raise InputError(f"shot_noise must be True or False; got {self.shot_noise!r}")

    PRESETS = ("off", "low", "normal", "high")

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> "SensorConfig":
        """A named noise level: ``off`` (ideal sensor), ``low``, ``normal`` (the default),
        ``high`` (small pixels, poor light)."""
        table = {
            "off": dict(read_noise_e=0.0, shot_noise=False, flicker=0.0, jitter_px=0.0),
            "low": dict(full_well_e=30_000.0, read_noise_e=4.0, flicker=0.003),
            "normal": {},
            "high": dict(full_well_e=4_000.0, read_noise_e=12.0, flicker=0.03,
                         exposure=0.6),
        }
        if name not in table:
            raise InputError(f"noise preset must be one of {', '.join(cls.PRESETS)}; got {name!r}")
        return cls(**{**table[name], **overrides})

    @property
    def max_dn(self) -> int:
        """Largest output value (255 or 65535)."""
        return (1 << self.bit_depth) - 1

    @property
    def dtype(self) -> type:
        return np.uint8 if self.bit_depth == 8 else np.uint16


def frame_rng(seed: int, z_mm: float) -> np.random.Generator:
    """The random generator of the frame focused at ``z_mm`` in a stack rendered with ``seed``.

    Seeded by ``(seed, round(z_mm·1e6))`` (the focus height in nanometres), so a frame's
    noise depends only on the seed and where the focus was, not on which other frames were
    rendered before it. Two frames at the same height share their noise.
    """
    s = _seed_int(seed)
    z = float(z_mm)
    if not math.isfinite(z):
        raise InputError(f"z_mm must be finite; got {z_mm!r}")
    z_nm = int(round(z * 1e6))
    zz = 2 * z_nm if z_nm >= 0 else -2 * z_nm - 1  # zig-zag: non-negative entropy
    return np.random.default_rng(np.random.SeedSequence([s, zz, 0x5F3D]))


# --------------------------------------------------------------------------------------
# Prepared layers (per scene, cached)


class _Prepared:
    """Shading, layer geometry and background fills of one scene (frame-independent)."""

    def __init__(self, scene: Scene, lighting: Lighting, layer_mm: float) -> None:
        import cv2

        self.scene = scene
        self.h = scene.height_mm
        rad = shade(scene, lighting=lighting)
        self.L = rad if rad.ndim == 3 else rad[:, :, None]
        self.C = self.L.shape[2]
        self.L_hf = self.L - _as_hwc(cv2.GaussianBlur(self.L, (0, 0), 2.0,
                                                      borderType=cv2.BORDER_REFLECT))
        hmin, hmax = scene.height_range_mm()
        self.t = float(layer_mm)
        n = int(math.ceil((hmax - hmin) / self.t - 1e-9)) + 1
        self.centres = hmin + self.t * np.arange(n, dtype=np.float64)
        self.jump_mm = _JUMP_LAYERS * self.t
        row_max = self.h.max(axis=1)
        col_max = self.h.max(axis=0)
        hh, ww = self.h.shape
        self.bbox: list[tuple[int, int, int, int] | None] = [(0, hh, 0, ww)]
        for j in range(1, n):
            thr = self.centres[j - 1]
            rows = np.flatnonzero(row_max > thr)
            if rows.size == 0:
                self.bbox.append(None)
                continue
            cols = np.flatnonzero(col_max > thr)
            self.bbox.append((int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1))
        # low-resolution grid for the fills of hidden background
        self.f = max(1, min(8, min(hh, ww) // 16))
        self.small = (max(1, math.ceil(ww / self.f)), max(1, math.ceil(hh / self.f)))
        self._fills: dict[int, np.ndarray] = {}
        self._mean = self.L.reshape(-1, self.C).mean(axis=0)
        self._levels: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def level(self, f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(h_pad, h_small, L_small)`` for reduced resolution ``1/f``.

        ``h_pad`` is the height map padded (edge values) to a multiple of ``f``;
        ``h_small`` and ``L_small`` are its and the radiance's block averages.
        """
        import cv2

        got = self._levels.get(f)
        if got is None:
            hh, ww = self.h.shape
            ph, pw = -hh % f, -ww % f
            h_pad = cv2.copyMakeBorder(self.h, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
            l_pad = _as_hwc(cv2.copyMakeBorder(self.L, 0, ph, 0, pw, cv2.BORDER_REPLICATE))
            size = ((ww + pw) // f, (hh + ph) // f)
            got = (h_pad, cv2.resize(h_pad, size, interpolation=cv2.INTER_AREA),
                   _as_hwc(cv2.resize(l_pad, size, interpolation=cv2.INTER_AREA)))
            self._levels[f] = got
        return got

    def fill(self, a: int, box: tuple[int, int, int, int], f: int = 1) -> np.ndarray:
        """Layer ``a``'s colour interpolated under everything, smooth, on a crop.

        ``box = (r0, r1, c0, c1)`` in pixels of the ``1/f`` resolution grid; returns
        ``(r1 - r0, c1 - c0, C)`` float32.
        """
        import cv2

        small = self._fills.get(a)
        if small is None:
            near = (np.abs(self.h - self.centres[a]) <= self.jump_mm).astype(np.float32)
            num = _as_hwc(cv2.resize(self.L * near[:, :, None], self.small,
                                     interpolation=cv2.INTER_AREA))
            den = cv2.resize(near, self.small, interpolation=cv2.INTER_AREA)
            small = _push_pull(num, den, fallback=self._mean)
            self._fills[a] = small
        r0, r1, c0, c1 = box
        hh, ww = self.h.shape
        fx, fy = small.shape[1] / ww, small.shape[0] / hh
        # output pixel x sits at full-res (x + c0 + 0.5)·f − 0.5, i.e. fill-grid
        # coordinate ((x + c0 + 0.5)·f)·fx − 0.5
        m = np.array([[f * fx, 0.0, (c0 + 0.5) * f * fx - 0.5],
                      [0.0, f * fy, (r0 + 0.5) * f * fy - 0.5]])
        return _as_hwc(cv2.warpAffine(small, m, (c1 - c0, r1 - r0),
                                      flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                      borderMode=cv2.BORDER_REPLICATE))


_CACHE: "weakref.WeakKeyDictionary[Scene, dict]" = weakref.WeakKeyDictionary()


def _prepared(scene: Scene, lighting: Lighting, layer_mm: float) -> _Prepared:
    per_scene = _CACHE.setdefault(scene, {})
    key = (lighting, round(layer_mm, 9))
    prep = per_scene.get(key)
    if prep is None:
        if len(per_scene) >= 2:
            per_scene.clear()
        prep = per_scene[key] = _Prepared(scene, lighting, layer_mm)
    return prep


def _push_pull(num: np.ndarray, den: np.ndarray, *, fallback: np.ndarray) -> np.ndarray:
    """Fill where ``den`` (coverage in [0, 1]) is 0 by pyramid interpolation of num/den."""
    import cv2

    levels = [(num, den)]
    while min(levels[-1][1].shape[:2]) > 2:
        n, d = levels[-1]
        levels.append((_as_hwc(cv2.pyrDown(n)), cv2.pyrDown(d)))
    n, d = levels[-1]
    total = float(d.sum())
    if total > 1e-6:
        value = np.broadcast_to(n.reshape(-1, n.shape[2]).sum(axis=0) / total, n.shape)
    else:
        value = np.broadcast_to(np.asarray(fallback, np.float32), n.shape)
    value = np.ascontiguousarray(value, dtype=np.float32)
    for n, d in reversed(levels):
        hh, ww = d.shape[:2]
        up = _as_hwc(cv2.resize(value, (ww, hh), interpolation=cv2.INTER_LINEAR))
        w = np.clip(d * 4.0, 0.0, 1.0)[:, :, None]
        own = n / np.maximum(d, 1e-6)[:, :, None]
        value = (w * own + (1.0 - w) * up).astype(np.float32)
    return value


def _as_hwc(a: np.ndarray) -> np.ndarray:
    return a if a.ndim == 3 else a[:, :, None]


# --------------------------------------------------------------------------------------
# Optical image


def default_layer_mm(scene: Scene, optics: Optics) -> float:
    """Layer thickness over which σ grows by ~0.25 px (at most 600 layers)."""
    g = optics.blur_rate_px_per_mm()
    t = max(0.25 / g, 0.002)
    lo, hi = scene.height_range_mm()
    return max(t, (hi - lo) / 600.0, 1e-6)


def render_optical(
    scene: Scene,
    z_mm: float,
    *,
    optics: Optics,
    lighting: Lighting | None = None,
    layer_mm: float | None = None,
) -> np.ndarray:
    """The image the lens forms on the sensor when focused at ``z_mm`` (no sensor effects).

    Parameters
    ----------
    scene : Scene
    z_mm : float
        Height of the focused plane above the base plane (mm).
    optics : Optics
        Its object pixel (``pixel_pitch_mm / magnification``) must equal the scene's
        ``pixel_size_mm``; see :meth:`Optics.for_pixel_size`.
    lighting : Lighting, optional
    layer_mm : float, optional
        Layer thickness; default: σ grows by ≈ 0.25 px per layer (0.021 mm for the
        default optics).

    Returns
    -------
    (H, W) or (H, W, 3) float32
        Relative irradiance (1 = white matte surface in focus), grey or RGB like the albedo.
    """
    _check_scene_optics(scene, optics)
    z = _check_number(z_mm, "z_mm")
    light = Lighting() if lighting is None else lighting
    if not isinstance(light, Lighting):
        raise InputError(f"lighting must be a Lighting; got {type(light).__name__}")
    t = default_layer_mm(scene, optics) if layer_mm is None else _check_number(
        layer_mm, "layer_mm", positive=True)
    prep = _prepared(scene, light, t)
    hh, ww = scene.shape
    C = prep.C
    centres = prep.centres
    groups = [(a, b) for a, b in _group_layers(centres, z, prep.t) if prep.bbox[a] is not None]
    mids = [float(np.mean(centres[a:b + 1])) for a, b in groups]
    sigmas = [float(s) for s in optics.blur_sigma_px(np.array(mids), z)]
    scales = [1.0] * len(groups) if optics.telecentric else \
        [float(s) for s in optics.scale_at(np.array(mids), z)]
    jobs = list(zip(groups, sigmas, scales))
    # Blurry runs below and above the sharp middle are composited at reduced resolution
    # (over-compositing is associative): the low run into the background, the high run
    # into a foreground buffer laid over the result at the end.
    sharp = [i for i, s in enumerate(sigmas) if s < _LOWRES_SIGMA]
    lo_end = sharp[0] if sharp else len(jobs)
    hi_start = sharp[-1] + 1 if sharp else len(jobs)
    acc = np.zeros((hh, ww, C), np.float32)
    if lo_end:
        run = jobs[:lo_end]
        f = _run_factor(min(s for _, s, _ in run), hh, ww)
        buf = _composite_run(prep, run, z, f, C + 1)
        acc += _upsample(buf, f, hh, ww)[:, :, :C]
    for (a, b), sigma, scale in jobs[lo_end:hi_start]:
        layer, dst = _layer(prep, a, b, sigma, scale, 1)
        _over(acc, layer, dst, C)
    if hi_start < len(jobs):
        run = jobs[hi_start:]
        f = _run_factor(min(s for _, s, _ in run), hh, ww)
        buf = _composite_run(prep, run, z, f, C + 1)
        _over(acc, _upsample(buf, f, hh, ww), (0, hh, 0, ww), C)
    return acc[:, :, 0] if C == 1 else acc


def _run_factor(sigma_min: float, hh: int, ww: int) -> int:
    """Largest power-of-two reduction keeping σ ≥ 2 reduced pixels (at most 8)."""
    f = 1
    while f < 8 and sigma_min / (2 * f) >= 2.0 and min(hh, ww) / (2 * f) >= 16:
        f *= 2
    return f


def _composite_run(prep: "_Prepared", run, z: float, f: int, channels: int) -> np.ndarray:
    """Premultiplied colour + alpha of a run of groups composited far to near at 1/f."""
    h_pad = prep.level(f)[0] if f > 1 else prep.h
    buf = np.zeros((h_pad.shape[0] // f, h_pad.shape[1] // f, channels), np.float32)
    for (a, b), sigma, scale in run:
        layer, dst = _layer(prep, a, b, sigma, scale, f)
        _over(buf, layer, dst, channels - 1)
    return buf


def _upsample(buf: np.ndarray, f: int, hh: int, ww: int) -> np.ndarray:
    import cv2

    if f == 1:
        return buf
    up = _as_hwc(cv2.resize(buf, (buf.shape[1] * f, buf.shape[0] * f),
                            interpolation=cv2.INTER_LINEAR))
    return up[:hh, :ww]


def _over(acc: np.ndarray, layer: np.ndarray, dst, C: int) -> None:
    """``acc = layer OVER acc`` in place on the box ``dst`` (premultiplied colour).

    ``acc`` has C channels (colour) or C + 1 (colour + alpha), ``layer`` C + 1.
    Works on rows flattened to ``w·channels`` (fast contiguous loops).
    """
    d0, d1, e0, e1 = dst
    view = acc[d0:d1, e0:e1]
    h, w, n = view.shape
    flat = view.view()
    flat.shape = (h, w * n)  # never a copy (raises instead): each crop row is contiguous
    inv = 1.0 - layer[:, :, C]
    flat *= np.repeat(inv, n, axis=1) if n > 1 else inv
    flat += np.ascontiguousarray(layer[:, :, :n]).reshape(h, w * n)


def _layer(prep: "_Prepared", a: int, b: int, sigma: float, scale: float, f: int):
    """One group's blurred premultiplied colour + coverage, on the 1/f grid.

    Returns ``(layer, box)``: ``(h, w, C + 1)`` float32 and where it goes
    ``(r0, r1, c0, c1)`` in the 1/f grid.
    """
    import cv2

    C = prep.C
    centres = prep.centres
    t = prep.t
    hh, ww = prep.h.shape
    pad = int(math.ceil(3.0 * sigma / f)) + 2
    r0, r1, c0, c1 = prep.bbox[a]
    if f > 1:
        h_full, h_small, l_small = prep.level(f)
        hs, ws = h_small.shape
        r0, c0 = max(0, r0 // f - pad), max(0, c0 // f - pad)
        r1, c1 = min(hs, -(-r1 // f) + pad), min(ws, -(-c1 // f) + pad)
        cover_full = h_full[r0 * f:r1 * f, c0 * f:c1 * f] - np.float32(centres[a] - t)
        cover_full *= np.float32(1.0 / t)
        np.clip(cover_full, 0.0, 1.0, out=cover_full)
        cover = cv2.resize(cover_full, (c1 - c0, r1 - r0), interpolation=cv2.INTER_AREA)
        hc = h_small[r0:r1, c0:c1]
        rad = l_small[r0:r1, c0:c1]
        shape = (hs, ws)
    else:
        r0, c0 = max(0, r0 - pad), max(0, c0 - pad)
        r1, c1 = min(hh, r1 + pad), min(ww, c1 + pad)
        hc = prep.h[r0:r1, c0:c1]
        cover = hc - np.float32(centres[a] - t)
        cover *= np.float32(1.0 / t)
        np.clip(cover, 0.0, 1.0, out=cover)
        rad = prep.L[r0:r1, c0:c1]
        shape = (hh, ww)
    near = hc < centres[b] + prep.jump_mm
    if not near.all():
        hidden = prep.fill(a, (r0, r1, c0, c1), f)
        if f == 1:  # fine texture of the occluder; blurred away at reduced resolution
            hidden += prep.L_hf[r0:r1, c0:c1]
        rad = np.where(near[:, :, None], rad, hidden)
    if C == 1:
        layer = _as_hwc(cv2.merge([cv2.multiply(rad[:, :, 0], cover), cover]))
    else:
        layer = cv2.merge([cv2.multiply(rad, cv2.merge([cover] * C)), cover])
    box = (r0, r1, c0, c1)
    if scale != 1.0:
        centre = (((hh - 1) / 2.0 + 0.5) / f - 0.5, ((ww - 1) / 2.0 + 0.5) / f - 0.5)
        layer, box = _scale_layer(layer, box, scale, centre, shape, pad)
    if f > 1:
        # block averaging and the final linear upsampling add ~1/4 px² (1/f grid) of variance
        s = math.sqrt(max((sigma / f) ** 2 - 0.25, 0.25))
        layer = _as_hwc(cv2.GaussianBlur(layer, (0, 0), s, borderType=cv2.BORDER_REFLECT))
    else:
        layer = _blur(layer, sigma)
    return layer, box


def _group_layers(centres: np.ndarray, z: float, t: float) -> list[tuple[int, int]]:
    """Split layer indices into runs rendered with one σ (fine near z, coarse far away)."""
    groups = []
    n = len(centres)
    a = 0
    near = _NEAR_LAYERS * t
    while a < n:
        b = a
        da = centres[a] - z
        if abs(da) >= near:
            while b + 1 < n:
                db = centres[b + 1] - z
                if np.sign(db) != np.sign(da) or abs(db) < near:
                    break
                if centres[b + 1] - centres[a] > _GROUP_REL * min(abs(da), abs(db)):
                    break
                b += 1
        groups.append((a, b))
        a = b + 1
    return groups


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of an (h, w, c) float32 image; large σ at reduced resolution."""
    import cv2

    if sigma < 0.2:
        return img
    hh, ww = img.shape[:2]
    f = 1
    while sigma / (2 * f) >= 2.0 and min(hh, ww) / (2 * f) >= 8:
        f *= 2
    if f == 1:
        return _as_hwc(cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT))
    # pad to a multiple of f so down- and up-sampling are exact integer factors (no shift)
    ph, pw = -hh % f, -ww % f
    if ph or pw:
        img = _as_hwc(cv2.copyMakeBorder(img, 0, ph, 0, pw, cv2.BORDER_REFLECT))
    small = cv2.resize(img, ((ww + pw) // f, (hh + ph) // f), interpolation=cv2.INTER_AREA)
    # area averaging and linear upsampling add about 1/4 px² (small pixels) of variance
    s_small = math.sqrt(max((sigma / f) ** 2 - 0.25, 0.25))
    small = cv2.GaussianBlur(small, (0, 0), s_small, borderType=cv2.BORDER_REFLECT)
    up = _as_hwc(cv2.resize(small, (ww + pw, hh + ph), interpolation=cv2.INTER_LINEAR))
    return up[:hh, :ww] if (ph or pw) else up


def _scale_layer(layer, box, scale, centre_rc, shape, pad):
    """Scale a layer crop about the principal point; returns (image, destination box)."""
    import cv2

    r0, r1, c0, c1 = box
    hh, ww = shape
    cr, cc = centre_rc

    def fwd(r, c):
        return cr + scale * (r - cr), cc + scale * (c - cc)

    (a0, b0), (a1, b1) = fwd(r0, c0), fwd(r1, c1)
    d0 = 0 if r0 == 0 else max(0, int(math.floor(a0)) - 1)
    e0 = 0 if c0 == 0 else max(0, int(math.floor(b0)) - 1)
    d1 = hh if r1 == hh else min(hh, int(math.ceil(a1)) + 1)
    e1 = ww if c1 == ww else min(ww, int(math.ceil(b1)) + 1)
    # destination (x', y') in crop coordinates from source crop (x, y):
    # X' = s (X - c) + c, X = x + c0, X' = x' + e0
    tx = scale * (c0 - cc) + cc - e0
    ty = scale * (r0 - cr) + cr - d0
    m = np.array([[scale, 0.0, tx], [0.0, scale, ty]], dtype=np.float64)
    out = cv2.warpAffine(layer, m, (e1 - e0, d1 - d0), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)
    return _as_hwc(out), (d0, d1, e0, e1)


# --------------------------------------------------------------------------------------
# Sensor


def render_frame(
    scene: Scene,
    z_mm: float,
    *,
    optics: Optics,
    sensor: SensorConfig | None = None,
    rng: np.random.Generator | int = 0,
    lighting: Lighting | None = None,
    layer_mm: float | None = None,
) -> np.ndarray:
    """One camera frame focused at ``z_mm``: optics, then flicker, jitter, noise, ADC.

    Parameters
    ----------
    scene : Scene
    z_mm : float
        Height of the focused plane above the base plane (mm).
    optics : Optics
    sensor : SensorConfig, optional
        Default :class:`SensorConfig` (noisy).
    rng : numpy Generator or int
        An integer is a stack seed: the frame then uses ``frame_rng(rng, z_mm)`` and is
        byte-identical to the frame at ``z_mm`` of ``render_stack(..., seed=rng)``.
    lighting, layer_mm
        See :func:`render_optical`.

    Returns
    -------
    (H, W) or (H, W, 3) uint8 or uint16
    """
    sensor = SensorConfig() if sensor is None else sensor
    if not isinstance(sensor, SensorConfig):
        raise InputError(f"sensor must be a SensorConfig; got {type(sensor).__name__}")
    if isinstance(rng, np.random.Generator):
        gen = rng
    else:
        gen = frame_rng(rng, _check_number(z_mm, "z_mm"))
    img = render_optical(scene, z_mm, optics=optics, lighting=lighting, layer_mm=layer_mm)
    return _expose(img, sensor, gen)


def _expose(img: np.ndarray, sensor: SensorConfig, gen: np.random.Generator) -> np.ndarray:
    import cv2

    flick = 1.0 + sensor.flicker * float(gen.uniform(-1.0, 1.0))
    shift = gen.standard_normal(2) * sensor.jitter_px
    if sensor.jitter_px > 0:
        m = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]])
        img = cv2.warpAffine(img, m, (img.shape[1], img.shape[0]),
                             flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REFLECT)
    fw = np.float32(sensor.full_well_e)
    e = np.maximum(img, 0.0).astype(np.float32) * np.float32(sensor.exposure * flick) * fw
    var = e if sensor.shot_noise else np.zeros_like(e)
    if sensor.read_noise_e > 0:
        var = var + np.float32(sensor.read_noise_e) ** 2
    if sensor.shot_noise or sensor.read_noise_e > 0:
        e = e + np.sqrt(var) * gen.standard_normal(e.shape, dtype=np.float32)
    dn = np.clip(e * np.float32(sensor.max_dn / sensor.full_well_e), 0, sensor.max_dn)
    return np.rint(dn).astype(sensor.dtype)


# --------------------------------------------------------------------------------------
# Stacks


def render_stack(
    scene: Scene,
    z_mm: Sequence[float],
    *,
    optics: Optics,
    sensor: SensorConfig | None = None,
    seed: int = 0,
    out: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    lighting: Lighting | None = None,
    layer_mm: float | None = None,
    overwrite: bool = False,
    previews: bool = True,
    truth_extra: dict[str, Any] | None = None,
    stage_scale: float = 1.0,
):
    """Render a focal stack, frame by frame, in the order of ``z_mm``.

    Parameters
    ----------
    scene : Scene
    z_mm : (n_frames,) float
        Focused-plane heights (mm), at least 3, all different. A sweep that starts high
        and steps down by Δd matches the paper's ``h_n = d − (d_f + n·Δd)`` with Δd > 0
        (the rig block then holds a positive ``step_mm``).
    optics : Optics
    sensor : SensorConfig, optional
    seed : int
        Frame ``n`` uses ``frame_rng(seed, z_mm[n])``.
    out : path, optional
        Stack directory to write (frames + ``stack.json`` via
        :class:`~smdinspect.stack.StackWriter`, and ``truth/``: ``height_mm.tiff``
        (float32), ``height_mm.npy``, ``scene.json``, PNG previews). Must be missing or
        empty unless ``overwrite``, which first removes an earlier stack's
        ``stack.json``, ``frame_*`` files and ``truth/``.
    progress : callable(done, total), optional
    lighting, layer_mm
        See :func:`render_optical`.
    previews : bool
        Write the PNG previews in ``truth/`` (needs matplotlib).
    truth_extra : dict, optional
        Extra JSON-able facts stored in ``truth/scene.json`` (e.g. the board labels file).
    stage_scale : float
        A stage that lies about its z: frame ``n`` is rendered at
        ``z_lo + stage_scale·(z_mm[n] − z_lo)`` (``z_lo`` the lowest) but recorded at
        ``z_mm[n]``, as a rig whose real step is ``stage_scale`` times the one it reports
        (for ``smdinspect calibrate z-scale``). ``truth/scene.json`` records it.

    Returns
    -------
    FocalStack
        When ``out`` is given (opened from disk).
    list of ndarray
        Otherwise, the frames in the order of ``z_mm``.
    """
    from ..stack import FocalStack, StackWriter

    sensor = SensorConfig() if sensor is None else sensor
    if not isinstance(sensor, SensorConfig):
        raise InputError(f"sensor must be a SensorConfig; got {type(sensor).__name__}")
    _check_scene_optics(scene, optics)
    seed = _seed_int(seed)
    z = np.asarray(z_mm, dtype=np.float64)
    if z.ndim != 1 or z.size < 3:
        raise InputError(f"z_mm must be a list of at least 3 heights; got shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise InputError("z_mm must be finite")
    if np.unique(np.round(z * 1e6)).size != z.size:
        raise InputError("z_mm holds the same height twice; every frame needs its own z")
    stage_scale = _check_number(stage_scale, "stage_scale", positive=True)
    z_true = z if stage_scale == 1.0 else z.min() + stage_scale * (z - z.min())
    t = default_layer_mm(scene, optics) if layer_mm is None else _check_number(
        layer_mm, "layer_mm", positive=True)
    n = z.size
    writer = None
    root = None
    if out is not None:
        root = Path(out)
        _prepare_out(root, overwrite)
        diffs = np.diff(z)
        rig: dict[str, Any] = {"d_f_mm": optics.working_distance_mm,
                               "d_mm": float(z[0]) + optics.working_distance_mm}
        if np.allclose(diffs, diffs[0], rtol=1e-6, atol=1e-9):
            rig["step_mm"] = float(-diffs[0])
        writer = StackWriter(
            root,
            pixel_size_mm=scene.pixel_size_mm,
            optics=optics.to_dict(),
            rig=rig,
            meta={
                "generator": "smdinspect.synth",
                "scene": scene.name,
                "seed": seed,
                "sensor": asdict(sensor),
                "lighting": asdict(lighting or Lighting()),
                "layer_mm": t,
            },
        )
    keep = set(np.linspace(0, n - 1, 4).round().astype(int).tolist())
    kept: dict[int, np.ndarray] = {}
    frames = []
    for i, (zi, zt) in enumerate(zip(z, z_true)):
        frame = render_frame(scene, float(zt), optics=optics, sensor=sensor, rng=seed,
                             lighting=lighting, layer_mm=t)
        if writer is None:
            frames.append(frame)
        else:
            writer.add_frame(frame, float(zi))
            if i in keep:
                kept[i] = frame
        if progress is not None:
            progress(i + 1, n)
    if writer is None:
        return frames
    from ._truth import write_truth

    write_truth(
        root / "truth",
        scene,
        z_mm=z,
        optics=optics,
        sensor=sensor,
        seed=seed,
        preview_frames={float(z[i]): kept[i] for i in sorted(kept)},
        previews=previews,
        extra=truth_extra if stage_scale == 1.0 else
        {**(truth_extra or {}), "stage_scale": stage_scale},
    )
    log.info("wrote %d frames and truth/ to %s", n, root)
    return FocalStack.open(root)


def _prepare_out(root: Path, overwrite: bool) -> None:
    if root.exists() and not root.is_dir():
        raise InputError(f"out {root} exists and is not a directory")
    if root.is_dir() and any(root.iterdir()):
        if not overwrite:
            raise InputError(f"out directory {root} is not empty; pass --force to overwrite")
        for p in root.iterdir():
            if p.name == "stack.json" or (p.name.startswith("frame_") and p.is_file()):
                p.unlink()
            elif p.name == "truth" and p.is_dir():
                shutil.rmtree(p)
    root.mkdir(parents=True, exist_ok=True)


def _check_scene_optics(scene: Any, optics: Any) -> None:
    if not isinstance(scene, Scene):
        raise InputError(f"scene must be a Scene; got {type(scene).__name__}")
    if not isinstance(optics, Optics):
        raise InputError(f"optics must be an Optics; got {type(optics).__name__}")
    p, q = scene.pixel_size_mm, optics.pixel_size_mm
    if abs(p - q) > 1e-3 * p:
        raise InputError(
            f"the scene's pixel_size_mm {p:g} differs from the optics' object pixel {q:g} "
            f"(pixel_pitch_mm / magnification); use Optics.for_pixel_size({p:g})"
        )


def _check_number(value: Any, name: str, *, positive: bool = False) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise InputError(f"{name} must be a number; got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite; got {v}")
    if positive and v <= 0:
        raise InputError(f"{name} must be > 0; got {v}")
    if not positive and v < 0 and name not in ("z_mm",):
        raise InputError(f"{name} must be >= 0; got {v}")
    return v
